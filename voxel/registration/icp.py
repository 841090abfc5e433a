"""Local refinement: trimmed point-to-point ICP restricted to 3, 4 or 6 degrees of freedom, and the
point-to-plane covariance of the result."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from voxel.registration.transform import apply, planar

if TYPE_CHECKING:
    from scipy.spatial import cKDTree


#: Relative and absolute slack (metres) of `Nearest`'s reuse tests, far above rounding.
_SLACK = 1e-9


@dataclass(frozen=True)
class IcpResult:
    """Refined transform (B into A), the correspondences it ended with and their RMS distance."""

    transform: np.ndarray
    matched: int
    rmse: float
    iterations: int


def fit_rigid(p: np.ndarray, q: np.ndarray, dof: int) -> np.ndarray:
    """Least-squares transform moving points p (N, 3) onto q (N, 3): dof 3 (x, y, yaw; z kept),
    4 (x, y, z, yaw) or 6 (Kabsch)."""
    cp, cq = p.mean(axis=0), q.mean(axis=0)
    a, b = p - cp, q - cq
    if dof == 6:
        u, _, vt = np.linalg.svd(a.T @ b)
        d = np.sign(np.linalg.det(vt.T @ u.T))
        r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
        t = np.eye(4)
        t[:3, :3] = r
        t[:3, 3] = cq - r @ cp
        return t
    yaw = math.atan2(
        float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])),
        float(np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1])),
    )
    c, s = math.cos(yaw), math.sin(yaw)
    txy = cq[:2] - np.array([c * cp[0] - s * cp[1], s * cp[0] + c * cp[1]])
    return planar(yaw, float(txy[0]), float(txy[1]), float(cq[2] - cp[2]) if dof == 4 else 0.0)


class Nearest:
    """Exactly `tree.query(points, distance_upper_bound=limit)` for the same points moving a little
    between calls (ICP's iterations), with fewer tree look-ups.

    A look-up finds each point's two nearest target points within twice the limit; while a point
    has moved by less than half the gap between them (`_SLACK` spare), the nearest is still the
    same target point (any other is farther by the triangle inequality) and its distance is
    computed directly, as the tree computes it (x, y, z squares summed in order, the square
    root; within the limit when the squared distance is below the squared limit). A point with
    nothing within the look-up's range stays without a neighbour while that range, less its
    move, is beyond the limit. Only the others are looked up again. Ties of the two nearest are
    looked up as the tree alone would (never reused).
    """

    def __init__(self, tree: cKDTree, target: np.ndarray) -> None:
        self.tree, self.target = tree, target
        self.at: np.ndarray | None = None  # where each point was at its last look-up
        self.nn = np.empty(0, np.int64)  # its nearest target point then (len(target): none)
        self.d1 = np.empty(0)  # the distance to it (inf: none within `reach`)
        self.gap = np.empty(0)  # a lower bound on the distance to every other target point
        self.reach = np.empty(0)  # the look-up's range

    def query(self, points: np.ndarray, limit: float) -> tuple[np.ndarray, np.ndarray]:
        """Distances (inf beyond `limit`) and indices (len(target) beyond) of the nearest target
        points, as `tree.query(points, distance_upper_bound=limit)` returns them."""
        n_target = len(self.target)
        if self.at is None or len(self.at) != len(points):
            self.at = points.copy()
            self.nn = np.full(len(points), n_target, np.int64)
            self.d1 = np.full(len(points), np.inf)
            self.gap = np.zeros(len(points))
            self.reach = np.zeros(len(points))
            stale = np.ones(len(points), bool)
        else:
            moved = np.sqrt(np.sum((points - self.at) ** 2, axis=1)) * (1.0 + _SLACK) + _SLACK
            has = self.nn < n_target
            kept = np.where(
                has, self.d1 + 2.0 * moved < self.gap, self.reach - moved > limit * (1.0 + _SLACK)
            )
            stale = ~kept
        if stale.any():
            self._look_up(points, stale, limit)
        has = self.nn < n_target
        diff = points[has] - self.target[self.nn[has]]
        sq = (diff[:, 0] * diff[:, 0] + diff[:, 1] * diff[:, 1]) + diff[:, 2] * diff[:, 2]
        within = sq < limit * limit
        d = np.full(len(points), np.inf)
        idx = np.full(len(points), n_target, np.int64)
        rows = np.flatnonzero(has)[within]
        d[rows] = np.sqrt(sq[within])
        idx[rows] = self.nn[has][within]
        return d, idx

    def _look_up(self, points: np.ndarray, stale: np.ndarray, limit: float) -> None:
        assert self.at is not None
        at = points[stale]
        reach = 1.5 * limit
        dd, ii = self.tree.query(at, k=2, distance_upper_bound=reach)
        if len(self.target) < 2:  # k=2 of a one-point tree: the second is always missing
            dd, ii = np.asarray(dd).reshape(-1, 2), np.asarray(ii).reshape(-1, 2)
        nn, d1 = ii[:, 0].copy(), dd[:, 0].copy()
        gap = np.where(np.isfinite(dd[:, 1]), dd[:, 1], reach)
        tie = np.isfinite(d1) & (dd[:, 1] == d1)
        if tie.any():  # which of equals the tree returns alone: its own query, never reused
            _, i1 = self.tree.query(at[tie], distance_upper_bound=limit)
            nn[tie] = np.where(i1 < len(self.target), i1, nn[tie])
            gap[tie] = 0.0
        self.at[stale], self.nn[stale], self.d1[stale] = at, nn, d1
        self.gap[stale], self.reach[stale] = gap, reach


def icp(
    source: np.ndarray,
    tree: cKDTree,
    target: np.ndarray,
    init: np.ndarray,
    dof: int,
    *,
    start_m: float,
    end_m: float,
    iterations: int = 30,
    tol_m: float = 1e-4,
) -> IcpResult:
    """Refine `init` so `source` (B's points) lands on `target` (A's points, indexed by `tree`).

    Correspondences are nearest neighbours within a distance that shrinks geometrically from
    `start_m` to `end_m` over the first half of the iterations, then stays; stops early when an
    iteration moves the points less than `tol_m`.
    """
    t = init.copy()
    half = max(1, iterations // 2)
    matched, rmse = 0, math.inf
    it = 0
    nearest = Nearest(tree, target)
    for it in range(1, iterations + 1):
        limit = end_m if it > half else start_m * (end_m / start_m) ** ((it - 1) / half)
        moved = apply(t, source)
        d, idx = nearest.query(moved, limit)
        ok = np.isfinite(d)
        matched = int(ok.sum())
        if matched < 6:
            break
        rmse = float(np.sqrt(np.mean(d[ok] ** 2)))
        pairs = moved[ok]
        step = fit_rigid(pairs, target[idx[ok]], dof)
        t = step @ t
        every = pairs[:: max(1, matched // 200)]
        shift = float(np.max(np.linalg.norm(apply(step, every) - every, axis=1)))
        if it > half and shift < tol_m:
            break
    return IcpResult(t, matched, rmse, it)


def normals(
    points: np.ndarray, tree: cKDTree, where: np.ndarray, planar_map: bool, k: int = 10
) -> np.ndarray:
    """Unit surface normals (M, 3) of the map `points` (indexed by `tree`) at points `where` (M, 3),
    from the smallest principal axis of k neighbours; in-plane (xy) normals for a planar map."""
    _, idx = tree.query(where, k=min(k, len(points)))
    nb = points[idx]
    nb = nb - nb.mean(axis=1, keepdims=True)
    if planar_map:
        nb = nb[:, :, :2]
    cov = np.einsum("mki,mkj->mij", nb, nb)
    _, vec = np.linalg.eigh(cov)
    n = vec[:, :, 0]
    if planar_map:
        n = np.column_stack([n, np.zeros(len(n))])
    return n


def covariance(
    moved: np.ndarray, target: np.ndarray, normal: np.ndarray, dof: int
) -> tuple[np.ndarray, list[str]]:
    """Covariance of the transform parameters from point-to-plane residuals of matched pairs
    (moved B points, their A points, A's normals): sigma^2 (J^T J)^-1, with parameter names.

    Parameters: dof 3 x, y, yaw; 4 x, y, z, yaw; 6 x, y, z, roll, pitch, yaw. A direction the
    geometry does not constrain (a corridor's axis) shows as a huge variance (capped at 1e6).
    """
    r = np.einsum("ij,ij->i", moved - target, normal)
    rot = np.cross(moved - moved.mean(axis=0), normal)
    cols = {
        "x": normal[:, 0],
        "y": normal[:, 1],
        "z": normal[:, 2],
        "roll": rot[:, 0],
        "pitch": rot[:, 1],
        "yaw": rot[:, 2],
    }
    names = {
        3: ["x", "y", "yaw"],
        4: ["x", "y", "z", "yaw"],
        6: ["x", "y", "z", "roll", "pitch", "yaw"],
    }[dof]
    jac = np.column_stack([cols[n] for n in names])
    sigma2 = float(np.mean(r * r)) if len(r) > len(names) else 1.0
    info = jac.T @ jac
    w, v = np.linalg.eigh(info)
    inv_w = np.where(
        w > 1e-9 * max(float(w.max()), 1e-12), 1.0 / np.maximum(w, 1e-300), 1e6 / max(sigma2, 1e-12)
    )
    cov = (v * inv_w) @ v.T * sigma2
    return np.minimum(cov, 1e6), names
