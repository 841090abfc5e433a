"""Rotations as unit quaternions (x, y, z, w), the protocol's order, and 3x3 matrices (scipy's
`Rotation`).

One convention everywhere: scalar last, Hamilton product, active rotation (a matrix maps points
from the rotated frame into the reference frame: a quaternion (0, 0, sin(a/2), cos(a/2)) turns
+x towards +y by a), and w >= 0 for quaternions computed from matrices.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np


def _rotation() -> Any:
    """scipy's Rotation, loaded on first use (not at start-up). scipy.spatial first: a thread
    importing scipy.spatial.transform while another imports scipy.spatial would otherwise take
    the two module locks in opposite orders (Python's import deadlock error, seen with six
    threads' first imports at once)."""
    import scipy.spatial  # noqa: F401 - its lock before .transform's
    from scipy.spatial.transform import Rotation

    return Rotation


def quaternion_to_matrix(q: np.ndarray | tuple[float, float, float, float]) -> np.ndarray:
    """Rotation matrix (3, 3) float64 of a non-zero quaternion (x, y, z, w), normalised first."""
    Rotation = _rotation()
    matrix: np.ndarray = Rotation.from_quat(np.asarray(q, dtype=np.float64)).as_matrix()
    return matrix


def matrix_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) float64, w >= 0, of a rotation matrix (3, 3)."""
    Rotation = _rotation()

    q: np.ndarray = Rotation.from_matrix(np.asarray(rotation, dtype=np.float64)).as_quat(
        canonical=True
    )
    return q


def euler_pose(
    x: float, y: float, z: float, yaw: float, pitch: float = 0.0, roll: float = 0.0
) -> np.ndarray:
    """4x4 transform: rotation Rz(yaw) Ry(pitch) Rx(roll) (ZYX Euler, radians), then (x, y, z)."""
    cy, sy, cp, sp, cr, sr = (
        np.cos(yaw),
        np.sin(yaw),
        np.cos(pitch),
        np.sin(pitch),
        np.cos(roll),
        np.sin(roll),
    )
    pose = np.eye(4)
    pose[:3, :3] = [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ]
    pose[:3, 3] = [x, y, z]
    return pose


def pose_from_degrees(values: Sequence[float]) -> np.ndarray:
    """4x4 transform from `x, y, z, yaw[, pitch, roll]` (metres, degrees; ZYX Euler)."""
    x, y, z, *angles = (float(v) for v in values)
    yaw, pitch, roll = (np.radians(a) for a in (*angles, 0.0, 0.0)[:3])
    return euler_pose(x, y, z, float(yaw), float(pitch), float(roll))
