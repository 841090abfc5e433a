"""Rigid transforms as 4x4 matrices: build from x y z roll pitch yaw, read back, apply to points."""

from __future__ import annotations

import math

import numpy as np

from voxel.rotation import euler_pose


def rigid(
    x: float = 0.0,
    y: float = 0.0,
    z: float = 0.0,
    roll: float = 0.0,
    pitch: float = 0.0,
    yaw: float = 0.0,
) -> np.ndarray:
    """4x4 transform with rotation Rz(yaw) Ry(pitch) Rx(roll) (radians) and translation (x, y,
    z)."""
    return euler_pose(x, y, z, yaw, pitch, roll)


def euler(t: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in radians of a transform built as Rz(yaw) Ry(pitch) Rx(roll)."""
    r = np.asarray(t)[:3, :3]
    pitch = math.asin(max(-1.0, min(1.0, -float(r[2, 0]))))
    return (
        math.atan2(float(r[2, 1]), float(r[2, 2])),
        pitch,
        math.atan2(float(r[1, 0]), float(r[0, 0])),
    )


def apply(t: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (N, 3) moved by the 4x4 transform `t`."""
    moved: np.ndarray = points @ t[:3, :3].T + t[:3, 3]
    return moved


def planar(yaw: float, x: float, y: float, z: float = 0.0) -> np.ndarray:
    """4x4 transform of a rotation about z by `yaw` then a translation."""
    return rigid(x, y, z, yaw=yaw)


def wrap_angle(a: float | np.ndarray) -> float | np.ndarray:
    """Angle(s) wrapped into [-pi, pi)."""
    return (np.asarray(a) + math.pi) % (2 * math.pi) - math.pi


def displacement(t1: np.ndarray, t2: np.ndarray, points: np.ndarray) -> float:
    """Largest distance between `points` moved by `t1` and by `t2` (how different two poses are)."""
    return float(np.max(np.linalg.norm(apply(t1, points) - apply(t2, points), axis=1)))
