"""Scan-to-map matching: a local map of an agent's recent keyframes and robust point-to-plane (2D:
point-to-line) ICP."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from voxel.errors import LocalisationError
from voxel.localisation import se2

#: A direction of the Gauss-Newton Hessian with less than this share of its largest eigenvalue
#: is degenerate (`patch_covariance`).
DEGENERATE = 0.01
#: At most this many scan points in a restart (a regular subsample of the scan).
PROBE_POINTS = 500
#: A restart's score (mean Cauchy loss) at most this times the best one's: as good a fit.
PROBE_TOLERANCE = 1.05

if TYPE_CHECKING:
    from scipy.spatial import cKDTree


def thin(points: np.ndarray, cell: float) -> np.ndarray:
    """One point per `cell`-sized voxel (the first one met), in input order."""
    if len(points) == 0:
        return points
    out: np.ndarray = points[thin_index(points, cell)]
    return out


def thin_index(points: np.ndarray, cell: float) -> np.ndarray:
    """Indices (ascending) of the points `thin` keeps: the first met in each `cell`-sized voxel."""
    if len(points) == 0:
        return np.zeros(0, np.int64)
    keys = np.floor(points / cell).astype(np.int64)
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    if float(np.prod(span.astype(np.float64))) < 2.0**62:  # one integer per cell: a 1-D unique
        packed = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
        _, first = np.unique(packed, return_index=True)
    else:
        _, first = np.unique(keys, axis=0, return_index=True)
    out: np.ndarray = np.sort(first)
    return out


def surface_normals(
    where: np.ndarray, points: np.ndarray, tree: cKDTree, k: int, planar: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (M, 3) at `where` from the covariance of their k nearest `points` (indexed by
    `tree`), and a flatness in [0, 1] (1: a clean line or plane).

    planar: points of a 2D scanner; normals lie in the x-y plane (normal of the fitted line).
    """
    k = min(k, len(points))
    _, idx = tree.query(where, k=k)
    nb = points[idx]  # (M, k, 3)
    dim = 2 if planar else 3
    centred = nb[:, :, :dim] - nb[:, :, :dim].mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", centred, centred) / k
    values, vectors = np.linalg.eigh(cov)  # ascending
    normals = np.zeros((len(where), 3))
    normals[:, :dim] = vectors[:, :, 0]
    spread = values[:, -1] + 1e-12
    flatness = (
        1.0 - values[:, 0] / spread if planar else 1.0 - values[:, 0] / (values[:, 1] + 1e-12)
    )
    return normals, np.clip(flatness, 0.0, 1.0)


def orient(normals: np.ndarray, points: np.ndarray, viewpoint: np.ndarray) -> np.ndarray:
    """`normals` (M, 3) at `points` (M, 3) flipped to face `viewpoint` (3,): the side of the
    surface the sensor saw. A wall seen from one side then differs from its other face a wall's
    thickness away, which an unsigned normal cannot tell apart."""
    towards = np.asarray(viewpoint, np.float64).reshape(3) - points
    sign = np.where(np.einsum("ij,ij->i", normals, towards) < 0.0, -1.0, 1.0)
    flipped: np.ndarray = normals * sign[:, None]
    return flipped


class MatchTarget(Protocol):
    """What `match` aligns a scan to: points (N, 3) with unit normals (N, 3) and a k-d tree over
    the points (None: nothing to match)."""

    @property
    def points(self) -> np.ndarray: ...
    @property
    def normals(self) -> np.ndarray: ...
    @property
    def tree(self) -> cKDTree | None: ...
    @property
    def oriented(self) -> bool:
        """True when the normals face the side their surface was seen from (`orient`)."""
        ...


class LocalMap:
    """The agent's recent map: points of its last `keyframes` keyframes in the map frame, thinned,
    with normals.

    A new keyframe is taken when the agent has moved `key_distance` metres or turned `key_angle`
    radians since the last one. Normals face the keyframe's viewpoint (`oriented`), so `match`
    does not pair a scan of a wall's far face with the near face in the map. Every keyframe has
    an id (counting from 0), and every point the id of its keyframe (`labels`), so a match can
    say which keyframes it was measured against.
    """

    oriented = True

    def __init__(
        self,
        *,
        planar: bool,
        keyframes: int = 30,
        cell: float = 0.05,
        k: int = 8,
        key_distance: float = 0.25,
        key_angle: float = 0.15,
    ) -> None:
        if keyframes < 1 or cell <= 0 or k < 3:
            msg = (
                "local map: expected keyframes >= 1, cell > 0, k >= 3, "
                f"found {keyframes}, {cell}, {k}"
            )
            raise LocalisationError(msg)
        self.planar, self.cell, self.k = planar, cell, k
        self.key_distance, self.key_angle = key_distance, key_angle
        self.frames: deque[tuple[np.ndarray, np.ndarray, int]] = deque(maxlen=keyframes)
        self.last_key: np.ndarray | None = None
        self.next_id = 0
        self.points = np.zeros((0, 3))
        self.normals = np.zeros((0, 3))
        self.labels = np.zeros(0, np.int64)
        self.tree: cKDTree | None = None

    def __len__(self) -> int:
        return len(self.points)

    def wants(self, pose: np.ndarray) -> bool:
        """Whether a scan taken at `pose` (4x4) should become a keyframe."""
        if self.last_key is None:
            return True
        moved = float(np.linalg.norm(pose[:3, 3] - self.last_key[:3, 3]))
        rel = self.last_key[:3, :3].T @ pose[:3, :3]
        turned = math.acos(max(-1.0, min(1.0, (np.trace(rel) - 1.0) / 2.0)))
        return moved >= self.key_distance or turned >= self.key_angle

    @property
    def ids(self) -> list[int]:
        """The ids of the keyframes held, oldest first."""
        return [f[2] for f in self.frames]

    def add(
        self, points_map: np.ndarray, pose: np.ndarray, viewpoint: np.ndarray | None = None
    ) -> int | None:
        """Add a keyframe's points (already in the map frame): normals from the map around them,
        facing `viewpoint` (the sensor's position in the map frame; default the pose's), then a
        new tree. Its id, or None when it held too few points to keep.

        Older keyframes keep the normals they were given, so a keyframe costs one scan's normals
        and two tree builds, however long the window.
        """
        new = thin(np.asarray(points_map, np.float64), self.cell)
        self.last_key = np.asarray(pose, np.float64).copy()
        both = np.concatenate([self.points, new]) if len(self.points) else new
        if len(both) >= self.k:
            from scipy.spatial import cKDTree  # loads on first use, not at start-up

            normals, flat = surface_normals(new, both, cKDTree(both), self.k, self.planar)
            eye = self.last_key[:3, 3] if viewpoint is None else viewpoint
            normals = orient(normals, new, eye)
            keep = flat > 0.7  # corners and clutter have no reliable normal
            added = self.next_id
            self.next_id += 1
            self.frames.append((new[keep], normals[keep], added))
        else:
            added = None
        self.labels = (
            np.concatenate([np.full(len(f[0]), f[2], np.int64) for f in self.frames])
            if self.frames
            else np.zeros(0, np.int64)
        )
        self.points = (
            np.concatenate([f[0] for f in self.frames]) if self.frames else np.zeros((0, 3))
        )
        self.normals = (
            np.concatenate([f[1] for f in self.frames]) if self.frames else np.zeros((0, 3))
        )
        from scipy.spatial import cKDTree  # loads on first use, not at start-up

        self.tree = cKDTree(self.points) if len(self.points) >= self.k else None
        return added


@dataclass(frozen=True)
class Match:
    """Result of matching a scan to a map: the refined pose and how much to trust it."""

    pose: np.ndarray  # (4, 4) body pose in the map frame
    covariance: (
        np.ndarray
    )  # (dof, dof): x y yaw (dof 3) or x y z rx ry rz (dof 6), rotations about the pose
    matched: int
    rmse: float
    iterations: int
    ok: bool
    reason: str = ""
    #: When the target labels its points (`LocalMap.labels`): the labels the final
    #: correspondences came from (G,) and the information (dof, dof) each label's pairs gave
    #: (their share of the Gauss-Newton Hessian; they sum to it).
    labels: np.ndarray | None = None
    information: np.ndarray | None = None


def _increment(delta: np.ndarray, centre: np.ndarray, dof: int) -> np.ndarray:
    """4x4 of a small motion: rotation about `centre`, then a translation."""
    if dof == 3:
        rot = np.array([0.0, 0.0, delta[2]])
        t = np.array([delta[0], delta[1], 0.0])
    else:
        rot, t = delta[3:], delta[:3]
    angle = float(np.linalg.norm(rot))
    r = np.eye(3)
    if angle > 1e-12:
        a = rot / angle
        kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
        r = np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = centre - r @ centre + t
    return m


@dataclass
class _Solution:
    """Where one Gauss-Newton run ended: the pose and its last linearisation (the matched
    residuals `r`, Jacobian rows `j`, Cauchy weights `w`, matched map points `q`); `ok` False
    when too few correspondences remained."""

    pose: np.ndarray
    ok: bool = False
    matched: int = 0
    iterations: int = 0
    rmse: float = math.inf
    sigma2: float = 1.0
    j: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    w: np.ndarray = field(default_factory=lambda: np.zeros(0))
    r: np.ndarray = field(default_factory=lambda: np.zeros(0))
    q: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    paired: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # map indices


def _solve(
    src: np.ndarray,
    local: MatchTarget,
    init: np.ndarray,
    *,
    dof: int,
    distances: tuple[float, float],
    iterations: int,
    robust_scale: float,
    min_matched: int,
    eye: np.ndarray,
) -> _Solution:
    """Gauss-Newton on point-to-plane distances from `init`: correspondences within
    distances[0], then distances[1] in the second half of the iterations."""
    tree = local.tree
    assert tree is not None, "a target with points"
    t = np.asarray(init, np.float64).copy()
    rot, trans = src @ t[:3, :3].T, t[:3, 3]
    oriented = bool(getattr(local, "oriented", False))
    half = max(1, iterations // 2)
    out = _Solution(t)
    for it in range(1, iterations + 1):
        limit = distances[0] if it <= half else distances[1]
        moved = rot + trans
        d, idx = tree.query(moved, distance_upper_bound=limit)
        ok = np.isfinite(d)
        if oriented:
            view = t[:3, :3] @ eye + t[:3, 3] - moved
            facing = np.einsum("ij,ij->i", local.normals[np.where(ok, idx, 0)], view) >= 0.0
            ok &= facing
        out.matched, out.iterations = int(ok.sum()), it
        if out.matched < min_matched:
            out.pose, out.ok = t, False
            return out
        paired = idx[ok]
        p, q, n = moved[ok], local.points[paired], local.normals[paired]
        r = np.einsum("ij,ij->i", p - q, n)
        w = 1.0 / (1.0 + (r / robust_scale) ** 2)
        lever = p - t[:3, 3]
        if dof == 3:
            j = np.column_stack([n[:, 0], n[:, 1], lever[:, 0] * n[:, 1] - lever[:, 1] * n[:, 0]])
        else:
            j = np.column_stack([n, np.cross(lever, n)])
        h = j.T @ (j * w[:, None])
        g = j.T @ (w * r)
        delta = -np.linalg.solve(h + 1e-6 * np.eye(dof), g)
        t = _increment(delta, t[:3, 3], dof) @ t
        rot, trans = src @ t[:3, :3].T, t[:3, 3]
        out.rmse = float(np.sqrt(np.sum(w * r**2) / np.sum(w)))
        out.sigma2 = float(np.sum(w * r**2) / max(np.sum(w) - dof, 1.0))
        out.j, out.w, out.r, out.q, out.paired = j, w, r, q, paired
        if it > half and float(np.linalg.norm(delta)) < 1e-5:
            break
    out.pose, out.ok = t, True
    return out


def _group(points: np.ndarray, size: float) -> tuple[np.ndarray, int]:
    """Index (M,) of the `size`-sized cell each point lies in, and the number of cells."""
    keys = np.floor(points / size).astype(np.int64)
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    packed = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
    _, inverse = np.unique(packed, return_inverse=True)
    inverse = inverse.ravel()
    return inverse, int(inverse.max()) + 1 if len(inverse) else 0


def patch_covariance(
    j: np.ndarray, w: np.ndarray, r: np.ndarray, q: np.ndarray, patch: float, floor: float
) -> tuple[np.ndarray, dict[str, float]]:
    """Covariance of the weighted least-squares estimate when residuals are correlated within
    surface patches: the sandwich H^-1 (J^T W S W J) H^-1, S = sw^2 I + sc^2 B (B: 1 for two
    residuals on the same `patch`-sized cell of the map, 0 otherwise; a cluster-robust
    variance, Liang & Zeger 1986).

    sw^2 (independent noise) and sc^2 (a patch's shared error: its normal, the sensor's bias
    there) come from the residuals' within- and between-patch spread (one-way ANOVA); sc is at
    least `floor` (the map's own resolution: a patch is not known better than that). A
    direction only few patches constrain keeps the variance of those few patches, however
    many points lie on them: N points on one wall count as one measurement, not N. A patch of
    0.25 m (`match`'s default) is about the span of the k = 8 neighbours a map normal is
    fitted to: the residuals that share a normal's error."""
    dof = j.shape[1]
    h = j.T @ (j * w[:, None]) + 1e-6 * np.eye(dof)
    hinv = np.linalg.inv(h)
    g, count = _group(q, patch)
    sw = np.bincount(g, weights=w, minlength=count)
    mean = np.bincount(g, weights=w * r, minlength=count) / np.maximum(sw, 1e-12)
    within = float(np.sum(w * (r - mean[g]) ** 2) / max(float(np.sum(w)) - count, 1.0))
    within = max(within, 1e-4)  # a residual is not known better than 1 cm (as before)
    grand = float(np.sum(w * r) / np.sum(w))
    size = float(np.sum(w)) / count  # weighted points per patch
    between = float(np.sum(sw * (mean - grand) ** 2) / max(count - 1, 1))
    shared = max((between - within) / max(size, 1.0), floor**2)
    wj = j * w[:, None]
    sums = np.stack([np.bincount(g, weights=wj[:, k], minlength=count) for k in range(dof)], 1)
    # the 1e-6 prior that keeps H invertible, as a measurement of the same noise: a direction
    # nothing constrains keeps a variance of ~1e6 * within, as the plain inverse Hessian gives
    meat = within * (wj.T @ wj + 1e-6 * np.eye(dof)) + shared * (sums.T @ sums)
    cov = hinv @ meat @ hinv
    # Degenerate directions (Zhang, Kaess & Singh 2016): where H holds less than `DEGENERATE`
    # of its strongest direction's information, that little is the normals' noise (a wall's
    # normals tilted by a degree "constrain" its length), not the surface: unconstrained there.
    # Rotations are compared in metres at the scan's effective lever arm (rotation information
    # over translation information, each per axis).
    t, rot = (slice(0, 2), slice(2, 3)) if dof == 3 else (slice(0, 3), slice(3, 6))
    lever2 = float(np.trace(h[rot, rot]) / max(float(np.trace(h[t, t])), 1e-12))
    scale = np.ones(dof)
    scale[rot] = 1.0 / math.sqrt(max(lever2, 1e-6))
    values, vectors = np.linalg.eigh(h * np.outer(scale, scale))
    weak = values < DEGENERATE * values[-1]
    if weak.any():
        v = vectors[:, weak] * scale[:, None]  # back to the pose's units
        cov = cov + 1e6 * within * (v @ v.T)  # as the 1e-6 prior alone would give
    return 0.5 * (cov + cov.T), {"within": within, "shared": shared, "patches": float(count)}


def _score(
    src: np.ndarray, local: MatchTarget, pose: np.ndarray, limit: float, scale: float
) -> float:
    """Mean Cauchy loss of the scan at `pose` (point-to-plane, a point without a map point
    within `limit` costs as much as one at `limit`): how well a pose explains the scan."""
    tree = local.tree
    assert tree is not None, "a target with points"
    moved = src @ pose[:3, :3].T + pose[:3, 3]
    d, idx = tree.query(moved, distance_upper_bound=limit)
    ok = np.isfinite(d)
    r = np.full(len(src), limit)
    i = idx[ok]
    r[ok] = np.einsum("ij,ij->i", moved[ok] - local.points[i], local.normals[i])
    return float(np.mean(np.log1p((r / scale) ** 2)))


def match(
    points_body: np.ndarray,
    local: MatchTarget,
    init: np.ndarray,
    *,
    dof: int = 3,
    max_distance: float = 0.5,
    final_distance: float = 0.15,
    iterations: int = 20,
    robust_scale: float = 0.05,
    min_matched: int = 30,
    inflation: float = 1.0,
    sensor: np.ndarray | None = None,
    patch: float = 0.25,
    probe: bool | None = None,
) -> Match:
    """Refine the body pose `init` (4x4) so the scan `points_body` (N, 3, body frame) lies on the
    local map (or any `MatchTarget`: the colony's map near the agent).

    Gauss-Newton on point-to-plane distances (point-to-line for 2D maps) with Cauchy weights;
    correspondences within `max_distance`, shrinking to `final_distance` in the second half.
    dof 3 moves x, y, yaw (a ground robot); dof 6 moves everything. When the target's normals
    are `oriented`, a correspondence whose map normal faces away from the sensor (at `sensor`,
    body frame; default the body's origin) is dropped: the scan sees the other face of that
    surface. A target with `labels` (one integer per point) gets each label's share of the
    final Hessian back (`Match.labels`, `Match.information`).

    The covariance (times `inflation`) covers the three sources of error Censi (2007, "An
    accurate closed-form estimate of ICP's covariance") lists. Sensor noise, counting
    independent constraints, not points: residuals on one `patch`-sized piece of surface share
    its error (`patch_covariance`), at least the map cell's; a degenerate direction
    (`DEGENERATE`; Zhang, Kaess & Singh 2016) gets the variance of no information. Wrong
    convergence, which the Hessian at one minimum cannot see and which Brossard, Bonnabel &
    Barrau (2020, "A new approach to 3D ICP covariance estimation", RA-L) find dominates real
    ICP errors: `probe` (default: dof 3) restarts
    Gauss-Newton half a final distance, a map cell or two standard deviations either side
    along the least constrained horizontal direction; a restart that ends elsewhere with as good
    a score (`_score`) widens the covariance to cover it (a wall's length, a repeating
    structure). The returned pose is always the first run's.
    """
    if dof not in (3, 6):
        msg = f"dof: expected 3 (x, y, yaw) or 6, found {dof}"
        raise LocalisationError(msg)
    t = np.asarray(init, np.float64).copy()
    if local.tree is None:
        return Match(t, np.eye(dof) * 1e6, 0, math.inf, 0, False, "empty map")
    src = np.asarray(points_body, np.float64)
    eye = np.zeros(3) if sensor is None else np.asarray(sensor, np.float64).reshape(3)
    solve: dict[str, Any] = dict(
        dof=dof, robust_scale=robust_scale, min_matched=min_matched, eye=eye
    )
    best = _solve(
        src, local, t, distances=(max_distance, final_distance), iterations=iterations, **solve
    )
    if not best.ok:
        return Match(
            best.pose,
            np.eye(dof) * 1e6,
            best.matched,
            math.inf,
            best.iterations,
            False,
            f"{best.matched} correspondences, expected at least {min_matched}",
        )
    cell = float(getattr(local, "cell", 0.05))
    cov, _ = patch_covariance(best.j, best.w, best.r, best.q, patch, cell / math.sqrt(12.0))
    if probe if probe is not None else dof == 3:
        cov = cov + _ambiguity(src, local, best, cov, cell, final_distance, iterations, solve)
    cov = inflation * cov
    labels = getattr(local, "labels", None)
    if labels is None or len(best.paired) == 0:
        return Match(best.pose, cov, best.matched, best.rmse, best.iterations, True)
    groups, which = np.unique(np.asarray(labels)[best.paired], return_inverse=True)
    info = np.zeros((len(groups), dof, dof))
    np.add.at(info, which.ravel(), np.einsum("ni,nj->nij", best.j * best.w[:, None], best.j))
    return Match(
        best.pose,
        cov,
        best.matched,
        best.rmse,
        best.iterations,
        True,
        labels=groups,
        information=info,
    )


def _ambiguity(
    src: np.ndarray,
    local: MatchTarget,
    best: _Solution,
    cov: np.ndarray,
    cell: float,
    final_distance: float,
    iterations: int,
    solve: dict[str, Any],
) -> np.ndarray:
    """Covariance (3x3) to add for other minima along the least constrained horizontal direction
    (dof 3): restarts `best` half of `final_distance`, a map cell or two standard deviations
    (the most of them) either side along it (yaw following, as the covariance couples it), on
    at most `PROBE_POINTS` of the scan, each run with a third of the iterations; one that ends
    more than a standard deviation away, scoring at most `PROBE_TOLERANCE` times `best`'s, adds
    its offset's outer product (half each side)."""
    values, vectors = np.linalg.eigh(cov[:2, :2])
    u = vectors[:, -1]
    sd = math.sqrt(max(float(values[-1]), 0.0))
    step = max(cell, 2.0 * sd, 0.5 * final_distance)
    along = np.array([u[0], u[1], 0.0])
    along[2] = float(cov[2, :2] @ np.linalg.solve(cov[:2, :2] + 1e-12 * np.eye(2), u))
    src = src[:: max(1, -(-len(src) // PROBE_POINTS))]  # a subsample: a restart only looks
    base = _score(src, local, best.pose, final_distance, solve["robust_scale"])
    here = se2.from_matrix(best.pose)
    extra = np.zeros((3, 3))
    for sign in (-1.0, 1.0):
        start = _increment(sign * step * along, best.pose[:3, 3], 3) @ best.pose
        other = _solve(
            src,
            local,
            start,
            distances=(final_distance, final_distance),
            iterations=max(2, iterations // 3),
            **solve,
        )
        if not other.ok:
            continue
        delta = se2.from_matrix(other.pose) - here
        delta[2] = math.remainder(float(delta[2]), 2.0 * math.pi)
        far = float(delta[:2] @ np.linalg.solve(cov[:2, :2] + 1e-12 * np.eye(2), delta[:2]))
        if (
            far > 1.0
            and _score(src, local, other.pose, final_distance, solve["robust_scale"])
            <= base * PROBE_TOLERANCE
        ):
            extra += 0.5 * np.outer(delta, delta)
    return extra
