"""Depth images back-projected to world points, with their colour and labels."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from voxel.errors import InputError


class DepthPoints(NamedTuple):
    """The valid pixels of one depth image as world points seen from `origin`."""

    points: np.ndarray  # (N, 3) float64, world frame
    origin: np.ndarray  # (3,) camera centre
    colours: np.ndarray | None  # (N, 3) from the colour image
    class_ids: np.ndarray | None  # (N,) int16 from the label image
    class_probs: np.ndarray | None  # (N,) float32 ones, with labels


def pixel_rays(intrinsics: np.ndarray, width: int, height: int) -> np.ndarray:
    """Camera-frame rays (H * W, 3) through every pixel, row-major, scaled to z = 1 (a point at
    depth d is d * ray)."""
    k = intrinsics
    v, u = np.mgrid[0:height, 0:width]
    rays = np.stack(
        [(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones((height, width))], axis=-1
    )
    return rays.reshape(-1, 3)


def camera_points(
    depth: np.ndarray, intrinsics: np.ndarray, stride: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (M, 3) float64 of the valid pixels (finite, > 0), row-major, and their
    flat pixel indices.

    Pinhole model, OpenCV axes (x right, y down, z forward); every `stride`-th row and column.
    """
    k = intrinsics
    h, w = depth.shape
    v, u = np.mgrid[0:h:stride, 0:w:stride]
    z = depth[::stride, ::stride]
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(z) & (z > 0)
    index = (v * w + u)[valid]
    z = z[valid].astype(np.float64)
    x = (u[valid] - k[0, 2]) * z / k[0, 0]
    y = (v[valid] - k[1, 2]) * z / k[1, 1]
    return np.column_stack([x, y, z]), index


def back_project(
    depth: np.ndarray,
    intrinsics: np.ndarray,
    pose: np.ndarray,
    *,
    colour: np.ndarray | None = None,
    labels: np.ndarray | None = None,
) -> DepthPoints:
    """Pixels of a depth image (metres, 0/NaN = no reading) in the world, from camera-to-world
    `pose`."""
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2:
        msg = f"depth must be an (H, W) image, found shape {depth.shape}"
        raise InputError(msg)
    k = np.asarray(intrinsics, dtype=np.float64)
    if k.shape != (3, 3):
        msg = f"intrinsics must be a 3x3 matrix, found shape {k.shape}"
        raise InputError(msg)
    t = np.asarray(pose, dtype=np.float64)
    if t.shape != (4, 4) or not np.all(np.isfinite(t)):
        msg = f"pose must be a finite 4x4 camera-to-world matrix, found shape {t.shape}"
        raise InputError(msg)
    h, w = depth.shape
    cam, index = camera_points(depth, k)
    world = cam @ t[:3, :3].T + t[:3, 3]
    colours = class_ids = class_probs = None
    if colour is not None:
        c = np.asarray(colour)
        if c.shape[:2] != (h, w) or c.ndim != 3 or c.shape[2] != 3:
            msg = f"colour must be an (H, W, 3) image matching depth {(h, w)}, found {c.shape}"
            raise InputError(msg)
        colours = c.reshape(-1, 3)[index]
    if labels is not None:
        lab = np.asarray(labels)
        if lab.shape != (h, w):
            msg = f"labels must be an (H, W) image matching depth {(h, w)}, found {lab.shape}"
            raise InputError(msg)
        class_ids = lab.reshape(-1)[index].astype(np.int16)
        class_probs = np.ones(index.shape[0], dtype=np.float32)
    return DepthPoints(world, t[:3, 3], colours, class_ids, class_probs)
