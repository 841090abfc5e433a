"""Benchmark scenes: depth images and LiDAR scans of `plugins.world.furnished_room`, rendered by its
ray caster."""

from __future__ import annotations

import math

import numpy as np

from plugins.world import furnished_room
from voxel.depth import pixel_rays

ROOM = furnished_room()

#: Kinect v1 intrinsics, 640 x 480.
KINECT = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])


def render(origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Distance along each direction (in units of its length) from `origin` to the room's first
    surface."""
    t: np.ndarray = ROOM.cast(origin, dirs).t
    return t


def camera_pose(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes: x right, y down, z forward) looking at target."""
    z = target - position
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.array([0.0, 0.0, 1.0]))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, y, z], axis=1)
    pose[:3, 3] = position
    return pose


def depth_frame(
    pose: np.ndarray,
    k: np.ndarray = KINECT,
    w: int = 640,
    h: int = 480,
    max_depth: float = 5.0,
    noise: float = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """A synthetic depth image (metres, 0 = no reading beyond max_depth) of the room."""
    world_dirs = pixel_rays(k, w, h) @ pose[:3, :3].T
    norms = np.linalg.norm(world_dirs, axis=1)
    rng = render(pose[:3, 3], world_dirs / norms[:, None])
    z = rng / norms
    if noise:
        z = z + np.random.default_rng(seed).normal(scale=noise, size=z.shape) * z * z
    z[~np.isfinite(z) | (z > max_depth)] = 0.0
    image: np.ndarray = z.reshape(h, w)
    return image


def lidar2d_scan(
    origin: np.ndarray, beams: int = 1081, fov: float = math.radians(270), max_range: float = 30.0
) -> tuple[np.ndarray, np.ndarray]:
    """A planar scan; returns (endpoints, no_return mask); no-return beams point at max range."""
    a = np.linspace(-fov / 2, fov / 2, beams)
    dirs = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)
    r = render(origin, dirs)
    nr = ~np.isfinite(r) | (r > max_range)
    r = np.where(nr, max_range, r)
    return origin + dirs * r[:, None], nr


def lidar3d_scan(
    origin: np.ndarray,
    rings: int = 64,
    cols: int = 1024,
    max_range: float = 30.0,
    fov_up: float = 2.0,
    fov_down: float = -24.8,
) -> tuple[np.ndarray, np.ndarray]:
    """A spinning 3D LiDAR scan in an open courtyard made of the room scaled x6 (points within
    30 m)."""
    el = np.radians(np.linspace(fov_down, fov_up, rings))
    az = np.linspace(-math.pi, math.pi, cols, endpoint=False)
    e, a = np.meshgrid(el, az, indexing="ij")
    dirs = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    scale = np.array([6.0, 6.0, 3.0])
    r = render(origin / scale, dirs / scale)
    # render() works on a unit-direction parameter; rescale distances back to metres.
    r = r * np.linalg.norm(dirs / scale, axis=1) / np.linalg.norm(dirs / scale, axis=1) ** 2
    nr = ~np.isfinite(r) | (r > max_range)
    r = np.where(nr, max_range, r)
    return origin + dirs * r[:, None], nr
