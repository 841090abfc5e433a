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
    for it in range(1, iterations + 1):
        limit = end_m if it > half else start_m * (end_m / start_m) ** ((it - 1) / half)
        moved = apply(t, source)
        d, idx = tree.query(moved, distance_upper_bound=limit)
        ok = np.isfinite(d)
        matched = int(ok.sum())
        if matched < 6:
            break
        rmse = float(np.sqrt(np.mean(d[ok] ** 2)))
        step = fit_rigid(moved[ok], target[idx[ok]], dof)
        t = step @ t
        shift = float(
            np.max(
                np.linalg.norm(
                    apply(step, moved[ok][:: max(1, matched // 200)])
                    - moved[ok][:: max(1, matched // 200)],
                    axis=1,
                )
            )
        )
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
