"""Planar poses (x, y, yaw): compose, relative increments, to and from 4x4 matrices."""

from __future__ import annotations

import math

import numpy as np


def wrap(angle: float) -> float:
    """Angle wrapped into [-pi, pi)."""
    return (angle + math.pi) % (2 * math.pi) - math.pi


def compose(pose: np.ndarray, increment: np.ndarray) -> np.ndarray:
    """Pose (x, y, yaw) moved by a body-frame increment (dx, dy, dyaw)."""
    x, y, a = pose
    dx, dy, da = increment
    c, s = math.cos(a), math.sin(a)
    return np.array([x + c * dx - s * dy, y + s * dx + c * dy, wrap(a + da)])


def relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Increment (dx, dy, dyaw) in a's body frame that takes pose a to pose b."""
    c, s = math.cos(a[2]), math.sin(a[2])
    ex, ey = b[0] - a[0], b[1] - a[1]
    return np.array([c * ex + s * ey, -s * ex + c * ey, wrap(b[2] - a[2])])


def from_matrix(m: np.ndarray) -> np.ndarray:
    """(x, y, yaw) of a 4x4 pose (its projection onto the ground plane)."""
    return np.array([m[0, 3], m[1, 3], math.atan2(m[1, 0], m[0, 0])])


def to_matrix(pose: np.ndarray, z: float = 0.0) -> np.ndarray:
    """4x4 pose of (x, y, yaw) at height z."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:3, 3] = (pose[0], pose[1], z)
    return m
