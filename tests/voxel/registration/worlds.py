"""Constructed maps with known answers: an irregular floor plan, extruded to 3D, cropped and
moved."""

from __future__ import annotations

import numpy as np

from voxel import keys as vk
from voxel.registration import MapCloud
from voxel.registration.transform import apply

RES = 0.1


def floor_plan(
    seed: int = 0, size: tuple[float, float] = (24.0, 12.0)
) -> tuple[np.ndarray, np.ndarray]:
    """Occupied and free cells (N, 2) of a building: outer walls, rooms of random widths along a
    corridor with doors, and random furniture blocks; every cell inside is observed."""
    rng = np.random.default_rng(seed)
    w, h = round(size[0] / RES), round(size[1] / RES)
    occ = np.zeros((w, h), bool)
    occ[[0, -1], :] = True
    occ[:, [0, -1]] = True
    corridor = (h // 2 - 8, h // 2 + 8)
    occ[:, corridor[0]] = occ[:, corridor[1]] = True
    x = 0
    while x < w - 30:
        x += int(rng.integers(25, 60))
        if x >= w - 5:
            break
        occ[x, : corridor[0]] = True
        occ[x + int(rng.integers(-6, 7)), corridor[1] :] = True
    for _ in range(60):  # doors into the corridor
        d = int(rng.integers(5, w - 15))
        occ[d : d + 9, corridor[0] if rng.random() < 0.5 else corridor[1]] = False
    for _ in range(25):  # furniture
        cx, cy = int(rng.integers(5, w - 10)), int(rng.integers(5, h - 10))
        if corridor[0] - 6 < cy < corridor[1] + 6:
            continue
        occ[cx : cx + int(rng.integers(3, 9)), cy : cy + int(rng.integers(3, 9))] = True
    occupied = np.argwhere(occ)
    free = np.argwhere(~occ)
    return occupied, free


def plan_map(
    occupied: np.ndarray, free: np.ndarray, *, height: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Voxel keys (N, 3) and occupied mask of a plan: one layer, or walls `height` voxels tall
    standing on a floor, under a ceiling, with free space between."""
    if height == 0:
        keys = np.concatenate([occupied, free])
        z = np.zeros((len(keys), 1), np.int64)
        mask = np.zeros(len(keys), bool)
        mask[: len(occupied)] = True
        return np.hstack([keys, z]), mask
    layers = np.arange(1, height + 1)
    walls = np.array([[x, y, z] for z in layers for x, y in occupied[::1]], np.int64)
    floors = np.array(
        [[x, y, z] for z in (0, height + 1) for x, y in np.concatenate([occupied, free])], np.int64
    )
    air = np.array([[x, y, z] for z in layers[::3] for x, y in free], np.int64)
    keys = np.concatenate([walls, floors, air])
    mask = np.zeros(len(keys), bool)
    mask[: len(walls) + len(floors)] = True
    return keys, mask


def crop_and_move(
    keys: np.ndarray, mask: np.ndarray, lo_x: float, hi_x: float, move: np.ndarray | None = None
) -> MapCloud:
    """The part of a map with lo_x <= x < hi_x (metres), its voxel centres moved by `move` and
    voxelised again (occupied wins)."""
    x = (keys[:, 0] + 0.5) * RES
    sel = (x >= lo_x) & (x < hi_x)
    keys, mask = keys[sel], mask[sel]
    if move is not None:
        keys = vk.points_to_keys(apply(move, vk.keys_to_centers(keys, RES)), RES)
        packed = vk.pack(keys)
        uniq, inv = np.unique(packed, return_inverse=True)
        mask = np.bincount(inv, weights=mask, minlength=len(uniq)) > 0
        keys = vk.unpack(uniq)
    return MapCloud.from_keys(RES, keys, mask)


def error(found: np.ndarray, truth: np.ndarray, points: np.ndarray) -> tuple[float, float]:
    """RMS distance (metres) of `points` moved by the found and the true transform, and yaw error
    (deg)."""
    rms = float(
        np.sqrt(np.mean(np.sum((apply(found, points) - apply(truth, points)) ** 2, axis=1)))
    )
    rel = found[:3, :3] @ truth[:3, :3].T
    yaw = abs(float(np.degrees(np.arctan2(rel[1, 0], rel[0, 0]))))
    return rms, yaw
