"""Trajectory metrics: Umeyama alignment and absolute trajectory error (ATE) as `evo_ape -a`
computes it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from voxel.errors import LocalisationError


@dataclass(frozen=True)
class Similarity:
    """x -> scale * R x + t."""

    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)
    scale: float = 1.0

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Points (N, 3) moved by this transform."""
        moved: np.ndarray = self.scale * points @ self.rotation.T + self.translation
        return moved

    def matrix(self) -> np.ndarray:
        """4x4 matrix (rotation block scaled)."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m


def _positions(value: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64)
    if a.ndim == 3 and a.shape[1:] == (4, 4):
        a = a[:, :3, 3]
    if a.ndim != 2 or a.shape[1] != 3:
        msg = f"{name}: expected positions (N, 3) or poses (N, 4, 4), found shape {a.shape}"
        raise LocalisationError(msg)
    if not np.all(np.isfinite(a)):
        msg = f"{name}: expected finite positions, found NaN or infinity"
        raise LocalisationError(msg)
    return a


def umeyama(source: np.ndarray, target: np.ndarray, *, with_scale: bool = False) -> Similarity:
    """Least-squares similarity (or rigid, without scale) moving `source` (N, 3) onto `target` (N,
    3).

    Umeyama (1991), as evo's `geometry.umeyama_alignment`: the rotation from the SVD of the
    cross-covariance with the reflection fixed, the scale (when asked) from the source variance.
    """
    x = _positions(source, "source")
    y = _positions(target, "target")
    if x.shape != y.shape:
        msg = f"umeyama: expected two point sets of the same shape, found {x.shape} and {y.shape}"
        raise LocalisationError(msg)
    if len(x) < 3:
        msg = f"umeyama: expected at least 3 corresponding points, found {len(x)}"
        raise LocalisationError(msg)
    mx, my = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mx, y - my
    cov = yc.T @ xc / len(x)
    u, d, vt = np.linalg.svd(cov)
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s[2, 2] = -1.0
    r = u @ s @ vt
    scale = float(np.trace(np.diag(d) @ s) / np.mean(np.sum(xc**2, axis=1))) if with_scale else 1.0
    return Similarity(r, my - scale * r @ mx, scale)


@dataclass(frozen=True)
class TrajectoryError:
    """Absolute trajectory error after alignment: per-pose translation errors and their
    statistics."""

    errors: np.ndarray  # (N,) metres
    alignment: Similarity

    @property
    def rmse(self) -> float:
        """Root mean square of the errors, metres."""
        return float(np.sqrt(np.mean(self.errors**2)))

    @property
    def mean(self) -> float:
        """Mean error, metres."""
        return float(np.mean(self.errors))

    @property
    def max(self) -> float:
        """Largest error, metres."""
        return float(np.max(self.errors))


def absolute_trajectory_error(
    reference: np.ndarray, estimate: np.ndarray, *, align: bool = True, with_scale: bool = False
) -> TrajectoryError:
    """ATE of `estimate` against `reference` (positions (N, 3) or poses (N, 4, 4), pose i with pose
    i).

    `align` (evo's `-a`) first moves the estimate by the rigid Umeyama fit onto the reference;
    `with_scale` (`-as`) also scales it. The error of pose i is the distance between positions.
    """
    ref = _positions(reference, "reference")
    est = _positions(estimate, "estimate")
    if ref.shape != est.shape:
        msg = f"trajectories: expected the same number of poses, found {len(ref)} and {len(est)}"
        raise LocalisationError(msg)
    fit = umeyama(est, ref, with_scale=with_scale) if align else Similarity(np.eye(3), np.zeros(3))
    return TrajectoryError(np.linalg.norm(fit.apply(est) - ref, axis=1), fit)
