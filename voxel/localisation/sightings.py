"""Sightings: the transform between an observer's frame and an agent's own, from where the observer
saw the agent and where the agent believed it was at those moments (a CCTV anchoring a robot)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from voxel.errors import LocalisationError
from voxel.localisation import se2


@dataclass(frozen=True)
class FrameFit:
    """A planar transform taking the observer's frame into the agent's, and how well it fits."""

    transform: np.ndarray  # (4, 4): a rotation about z and a translation in x, y
    rmse: float  # m, of the sighted positions after the fit
    yaw_error: float  # rad, largest heading disagreement after the fit
    spread: float  # m, largest distance between two sighted positions
    ok: bool
    reason: str = ""


def frame_from_sightings(
    seen: np.ndarray,
    believed: np.ndarray,
    *,
    min_sightings: int = 4,
    min_spread: float = 1.0,
    max_rmse: float = 0.15,
    max_yaw: float = math.radians(15.0),
) -> FrameFit:
    """Fit T with believed ≈ T · seen from N planar poses (x, y, yaw) of one agent: `seen` in the
    observer's frame, `believed` in the agent's own (its estimate at the same moments).

    Positions give the fit (2D Kabsch); headings only check it. Not ok with fewer than
    `min_sightings`, positions within `min_spread` of each other (the rotation is undetermined),
    a residual above `max_rmse` or a heading off by more than `max_yaw`.
    """
    a = np.asarray(seen, np.float64)
    b = np.asarray(believed, np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape != b.shape:
        msg = f"sightings: expected two (N, 3) arrays of (x, y, yaw), found {a.shape} and {b.shape}"
        raise LocalisationError(msg)
    n = len(a)
    spread = float(np.max(np.linalg.norm(a[:, None, :2] - a[None, :, :2], axis=2))) if n else 0.0
    if n < min_sightings or spread < min_spread:
        text = (
            f"expected {min_sightings} sightings at least {min_spread} m apart, found {n} "
            f"within {spread:.2f} m"
        )
        return FrameFit(np.eye(4), math.inf, math.inf, spread, False, text)
    ca, cb = a[:, :2].mean(axis=0), b[:, :2].mean(axis=0)
    h = (a[:, :2] - ca).T @ (b[:, :2] - cb)
    angle = math.atan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
    c, s = math.cos(angle), math.sin(angle)
    r = np.array([[c, -s], [s, c]])
    t = cb - r @ ca
    residual = b[:, :2] - (a[:, :2] @ r.T + t)
    rmse = float(np.sqrt(np.mean(np.sum(residual**2, axis=1))))
    yaw = max(abs(se2.wrap(float(d))) for d in b[:, 2] - a[:, 2] - angle)
    m = np.eye(4)
    m[:2, :2], m[:2, 3] = r, t
    if rmse > max_rmse or yaw > max_yaw:
        text = (
            f"expected rmse <= {max_rmse} m and headings within {math.degrees(max_yaw):.0f} deg, "
            f"found {rmse:.3f} m, {math.degrees(yaw):.1f} deg"
        )
        return FrameFit(m, rmse, yaw, spread, False, text)
    return FrameFit(m, rmse, yaw, spread, True)
