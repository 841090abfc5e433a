"""Rotations as unit quaternions (x, y, z, w), the protocol's order, and 3x3 matrices.

One convention everywhere: scalar last, Hamilton product, active rotation (a matrix maps points
from the rotated frame into the reference frame: a quaternion (0, 0, sin(a/2), cos(a/2)) turns
+x towards +y by a), and w >= 0 for quaternions computed from matrices.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from voxel.errors import InputError


def quaternion_to_matrix(q: np.ndarray | tuple[float, float, float, float]) -> np.ndarray:
    """Rotation matrix (3, 3) float64 of a non-zero quaternion (x, y, z, w), normalised first
    (InputError for a zero or non-finite one)."""
    x, y, z, w = (float(c) for c in np.asarray(q, dtype=np.float64).reshape(4))
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not 0.0 < n < math.inf:
        raise InputError(f"expected a non-zero finite quaternion (x, y, z, w), found {q!r}")
    x, y, z, w = x / n, y / n, z / n, w / n
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    return np.array(
        [
            [1.0 - 2.0 * (yy + zz), 2.0 * (xy - wz), 2.0 * (xz + wy)],
            [2.0 * (xy + wz), 1.0 - 2.0 * (xx + zz), 2.0 * (yz - wx)],
            [2.0 * (xz - wy), 2.0 * (yz + wx), 1.0 - 2.0 * (xx + yy)],
        ]
    )


def matrix_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) float64, w >= 0, of a rotation matrix (3, 3).

    Shepperd's method (as scipy's `Rotation.from_matrix`): the largest of w^2, x^2, y^2, z^2
    (read from the trace and the diagonal) is computed from the diagonal and the others from
    the off-diagonal sums and differences, so no component is divided by a small number. A
    quaternion with w = 0 has its first non-zero component positive."""
    m = np.asarray(rotation, dtype=np.float64).tolist()
    trace = m[0][0] + m[1][1] + m[2][2]
    decision = [m[0][0], m[1][1], m[2][2], trace]
    i = decision.index(max(decision))
    q = [0.0, 0.0, 0.0, 0.0]
    if i == 3:
        q = [m[2][1] - m[1][2], m[0][2] - m[2][0], m[1][0] - m[0][1], 1.0 + trace]
    else:
        j, k = (i + 1) % 3, (i + 2) % 3
        q[i] = 1.0 - trace + 2.0 * m[i][i]
        q[j] = m[j][i] + m[i][j]
        q[k] = m[k][i] + m[i][k]
        q[3] = m[k][j] - m[j][k]
    out = np.array(q) / math.sqrt(sum(c * c for c in q))
    lead = out[3] if out[3] != 0.0 else out[np.flatnonzero(out[:3])[0]]
    return -out if lead < 0 else out


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
