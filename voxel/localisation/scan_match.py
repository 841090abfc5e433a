"""Scan-to-map matching: a local map of an agent's recent keyframes and robust point-to-plane (2D:
point-to-line) ICP."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

from voxel.errors import LocalisationError

if TYPE_CHECKING:
    from scipy.spatial import cKDTree


def thin(points: np.ndarray, cell: float) -> np.ndarray:
    """One point per `cell`-sized voxel (the first one met), in input order."""
    if len(points) == 0:
        return points
    keys = np.floor(points / cell).astype(np.int64)
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    if float(np.prod(span.astype(np.float64))) < 2.0**62:  # one integer per cell: a 1-D unique
        packed = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
        _, first = np.unique(packed, return_index=True)
    else:
        _, first = np.unique(keys, axis=0, return_index=True)
    return points[np.sort(first)]


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
    inflation: float = 10.0,
    sensor: np.ndarray | None = None,
) -> Match:
    """Refine the body pose `init` (4x4) so the scan `points_body` (N, 3, body frame) lies on the
    local map (or any `MatchTarget`: the colony's map near the agent).

    Gauss-Newton on point-to-plane distances (point-to-line for 2D maps) with Cauchy weights;
    correspondences within `max_distance`, shrinking to `final_distance` in the second half.
    dof 3 moves x, y, yaw (a ground robot); dof 6 moves everything. The covariance is the
    Gauss-Newton inverse Hessian times the residual variance, times `inflation` (neighbouring
    residuals are correlated, so the raw one is overconfident); a direction the map does not
    constrain (a corridor's length) keeps a large variance. When the target's normals are
    `oriented`, a correspondence whose map normal faces away from the sensor (at `sensor`, body
    frame; default the body's origin) is dropped: the scan sees the other face of that surface.
    A target with `labels` (one integer per point) gets each label's share of the final
    Hessian back (`Match.labels`, `Match.information`).
    """
    if dof not in (3, 6):
        msg = f"dof: expected 3 (x, y, yaw) or 6, found {dof}"
        raise LocalisationError(msg)
    t = np.asarray(init, np.float64).copy()
    if local.tree is None:
        return Match(t, np.eye(dof) * 1e6, 0, math.inf, 0, False, "empty map")
    src = np.asarray(points_body, np.float64)
    rot, trans = src @ t[:3, :3].T, t[:3, 3]
    oriented = bool(getattr(local, "oriented", False))
    eye = np.zeros(3) if sensor is None else np.asarray(sensor, np.float64).reshape(3)
    half = max(1, iterations // 2)
    matched, rmse, it = 0, math.inf, 0
    h = np.eye(dof)
    sigma2 = 1.0
    j = np.zeros((0, dof))
    w = np.zeros(0)
    paired = np.zeros(0, np.int64)
    for it in range(1, iterations + 1):
        limit = max_distance if it <= half else final_distance
        moved = rot + trans
        d, idx = local.tree.query(moved, distance_upper_bound=limit)
        ok = np.isfinite(d)
        if oriented:
            view = t[:3, :3] @ eye + t[:3, 3] - moved
            facing = np.einsum("ij,ij->i", local.normals[np.where(ok, idx, 0)], view) >= 0.0
            ok &= facing
        matched = int(ok.sum())
        if matched < min_matched:
            return Match(
                t,
                np.eye(dof) * 1e6,
                matched,
                math.inf,
                it,
                False,
                f"{matched} correspondences, expected at least {min_matched}",
            )
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
        step = _increment(delta, t[:3, 3], dof)
        t = step @ t
        rot, trans = src @ t[:3, :3].T, t[:3, 3]
        rmse = float(np.sqrt(np.sum(w * r**2) / np.sum(w)))
        sigma2 = float(np.sum(w * r**2) / max(np.sum(w) - dof, 1.0))
        if it > half and float(np.linalg.norm(delta)) < 1e-5:
            break
    cov = inflation * max(sigma2, 1e-4) * np.linalg.inv(h + 1e-6 * np.eye(dof))
    labels = getattr(local, "labels", None)
    if labels is None or len(paired) == 0:
        return Match(t, cov, matched, rmse, it, True)
    groups, which = np.unique(np.asarray(labels)[paired], return_inverse=True)
    info = np.zeros((len(groups), dof, dof))
    np.add.at(info, which, np.einsum("ni,nj->nij", j * w[:, None], j))
    return Match(t, cov, matched, rmse, it, True, labels=groups, information=info)
