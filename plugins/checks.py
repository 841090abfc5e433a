"""Array checks for sensor input: shape, dtype and finiteness, with expected/found messages."""

from __future__ import annotations

import numpy as np

from plugins.errors import SensorInputError
from voxel import rotation


def as_array(
    value: object,
    field: str,
    *,
    shape: tuple[int | None, ...],
    dtype: type = np.float64,
    finite: bool = True,
) -> np.ndarray:
    """`value` as an array of `shape` (None = any length); raise SensorInputError naming `field`."""
    try:
        array: np.ndarray = np.asarray(value, dtype=dtype)
    except (TypeError, ValueError):
        msg = f"{field}: expected an array of {np.dtype(dtype).name}, found {type(value).__name__}"
        raise SensorInputError(msg) from None
    if array.ndim != len(shape) or any(
        want is not None and got != want for want, got in zip(shape, array.shape, strict=False)
    ):
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        msg = f"{field}: expected shape {want}, found {array.shape}"
        raise SensorInputError(msg)
    if finite and array.dtype.kind == "f" and not np.all(np.isfinite(array)):
        bad = int(np.count_nonzero(~np.isfinite(array)))
        msg = f"{field}: expected finite values, found {bad} NaN or infinite"
        raise SensorInputError(msg)
    return array


def as_pose(value: object, field: str) -> np.ndarray:
    """A 4x4 rigid transform (float64) with a proper rotation; raise SensorInputError otherwise."""
    pose = as_array(value, field, shape=(4, 4))
    if not np.allclose(pose[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        msg = f"{field}: expected last row [0, 0, 0, 1], found {pose[3].tolist()}"
        raise SensorInputError(msg)
    rotation = pose[:3, :3]
    error = float(np.abs(rotation @ rotation.T - np.eye(3)).max())
    if error > 1e-2 or np.linalg.det(rotation) < 0:
        msg = (
            f"{field}: expected a rotation matrix (orthonormal, det +1), "
            f"found deviation {error:.3g}"
        )
        raise SensorInputError(msg)
    return pose


def parse_mount(text: str, field: str = "mount") -> np.ndarray:
    """A sensor's pose in the robot body from `x/y/z/yaw_deg[/pitch_deg/roll_deg]` (metres and
    degrees, ZYX Euler): the 4x4 transform taking sensor points into the body frame."""
    try:
        values = [float(v) for v in text.split("/")]
    except ValueError:
        values = []
    if len(values) not in (4, 6) or not np.all(np.isfinite(values)):
        msg = (
            f"{field}: expected x/y/z/yaw_deg or x/y/z/yaw_deg/pitch_deg/roll_deg "
            f"(e.g. 0.2/0/0.3/0), found {text!r}"
        )
        raise SensorInputError(msg)
    return rotation.pose_from_degrees(values)


def as_intrinsics(value: object, field: str = "K") -> np.ndarray:
    """A 3x3 pinhole camera matrix with positive focal lengths."""
    K = as_array(value, field, shape=(3, 3))
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0.0, 0.0, 1.0]):
        msg = (
            f"{field}: expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, "
            f"found {K.tolist()}"
        )
        raise SensorInputError(msg)
    return K


def intrinsics_from_fov(width: int, height: int, fov: float) -> np.ndarray:
    """Pinhole K from a horizontal field of view in radians (the paper's Algorithm 1, square
    pixels)."""
    if not 0.0 < fov < np.pi:
        msg = f"fov: expected a horizontal field of view in (0, pi) radians, found {fov!r}"
        raise SensorInputError(msg)
    if width <= 0 or height <= 0:
        msg = f"image size: expected positive width and height, found {width}x{height}"
        raise SensorInputError(msg)
    f = 0.5 * width / np.tan(0.5 * fov)
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def camera_intrinsics(
    K: object, fov: float | None, width: int, height: int, camera: str
) -> np.ndarray:
    """A camera's intrinsics: `K` if given, else a pinhole of horizontal field of view `fov`;
    SensorInputError naming the `camera` when it has neither."""
    if K is not None:
        return as_intrinsics(K)
    if fov is not None:
        return intrinsics_from_fov(width, height, float(fov))
    msg = f"{camera}: expected intrinsics K or a horizontal field of view fov, found neither"
    raise SensorInputError(msg)


def pose_matrix(
    x: float, y: float, z: float, yaw: float, pitch: float = 0.0, roll: float = 0.0
) -> np.ndarray:
    """4x4 transform from a position and ZYX Euler angles (radians)."""
    return rotation.euler_pose(x, y, z, yaw, pitch, roll)


def quaternion_to_matrix(qx: float, qy: float, qz: float, qw: float) -> np.ndarray:
    """Rotation matrix (3, 3) of a quaternion (normalised here); `voxel.rotation` does the math."""
    q = np.array([qx, qy, qz, qw], dtype=np.float64)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-9:
        msg = f"quaternion: expected a non-zero finite quaternion, found {q.tolist()}"
        raise SensorInputError(msg)
    return rotation.quaternion_to_matrix(q / n)
