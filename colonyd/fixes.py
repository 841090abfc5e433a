"""Pose fixes: the error a fixed camera claims for a robot it saw, and the fix in its frame."""

from __future__ import annotations

import math

import numpy as np

from colonyd.alignment import ColonyFrame
from voxel.localisation import frame_error, se2


def fix_covariance(in_camera: np.ndarray) -> np.ndarray:
    """The covariance (6x6, x y z roll pitch yaw) a CCTV sends with a robot's body pose seen at
    `in_camera` (4x4, camera frame): 1 cm per metre of range in x and y (the board's known height
    fixes the range) plus 1 cm, 4 degrees in yaw."""
    sd = 0.01 * float(np.linalg.norm(np.asarray(in_camera, np.float64)[:3, 3])) + 0.01
    return np.diag([sd**2, sd**2, 0.05**2, 0.05**2, 0.05**2, math.radians(4.0) ** 2])


def sightings_covariance(rmse: float, spread: float, positions: np.ndarray) -> np.ndarray:
    """Error of a frame fitted to sightings (6x6, x y z roll pitch yaw, about our origin): the
    fit's residual in x and y, about the sightings' centroid, and a yaw of that residual over
    their spread (a lever of `spread` metres)."""
    planar = np.diag([rmse**2, rmse**2, (rmse / max(spread, 0.1)) ** 2])
    cov = np.zeros((6, 6))
    cov[np.ix_(frame_error.PLANAR, frame_error.PLANAR)] = frame_error.floored(
        frame_error.about(planar, positions[:, :2].mean(axis=0))
    )
    return cov


def fix_in_own_frame(
    frame: ColonyFrame, own: str, origin: str, body: np.ndarray, covariance: np.ndarray
) -> tuple[np.ndarray, np.ndarray] | None:
    """A fix from `origin` (the robot's body pose `body`, 4x4 in origin's frame, with its 6x6
    `covariance`) in `own`'s frame through the colony frame: the body pose (x, y, yaw) and its
    covariance (3x3: the fix's, rotated, plus the alignments' error at the robot's position,
    `frame_error.at`). None when either frame is not aligned."""
    mine, theirs = frame.transforms.get(own), frame.transforms.get(origin)
    if mine is None or theirs is None:
        return None
    to_own = np.linalg.inv(mine) @ theirs
    seen = to_own @ np.asarray(body, np.float64)
    # a peer's covariance is checked to a tolerance of its largest variance: made positive
    cov = frame_error.positive(frame_error.planar(np.asarray(covariance, np.float64)))
    rot = np.eye(3)
    rot[:2, :2] = to_own[:2, :2]
    alignment = frame_error.moved(
        frame.covariance(own) + frame.covariance(origin), np.linalg.inv(mine)
    )
    out = rot @ cov @ rot.T + frame_error.at(alignment, seen[:2, 3])
    return se2.from_matrix(seen), out
