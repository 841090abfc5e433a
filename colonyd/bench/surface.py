"""Harness prototype of the grid's per-voxel surface channel: the mean hit position per voxel.

Not the daemon's code (issue 12): the offline harnesses (`paper_offline`, `cctv_offline`,
`--peer-points means`) accumulate, beside a run's `VoxelGrid`, the mean of the hit points it
integrated in each voxel, so that a peer's map can be given as those means instead of the
voxels' centres, before the grid carries that channel on the wire. Hits are as the grid's
(`voxel.scan.sort_beams`): finite points with a return, within the sensor's max range, keyed as
`voxel.keys.points_to_keys`. As the channel fuses it (and colours, normals), each scan is one
sample of weight 1, its points' mean in the voxel: the mean over scans of the scans' means.
"""

from __future__ import annotations

import numpy as np

from plugins.observation import Observation
from voxel import keys as vk
from voxel.sensor import SensorModel


class SurfaceMeans:
    """Per voxel of `resolution`: the sum of the scans' mean hit points in it (world frame)
    and the count of those scans."""

    def __init__(self, resolution: float) -> None:
        if not resolution > 0:
            msg = f"SurfaceMeans: expected a positive resolution, found {resolution!r}"
            raise ValueError(msg)
        self.resolution = resolution
        self._parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._keys = np.zeros(0, np.int64)  # packed, sorted
        self._sums = np.zeros((0, 3))
        self._counts = np.zeros(0, np.int64)

    def add(self, points: np.ndarray, origin: np.ndarray, max_range: float = np.inf) -> int:
        """Add one scan's hit points (N, 3, world frame) seen from `origin`: those finite, at a
        positive distance no more than `max_range` (the others hit nothing in the grid).
        Returns how many were added."""
        pts = np.asarray(points, np.float64).reshape(-1, 3)
        with np.errstate(invalid="ignore"):
            r2 = np.sum((pts - np.asarray(origin, np.float64).reshape(3)) ** 2, axis=1)
            hit = np.isfinite(pts).all(axis=1) & (r2 > 0) & (r2 <= max_range * max_range)
        pts = pts[hit]
        if len(pts) == 0:
            return 0
        keys, inverse = np.unique(
            vk.pack(vk.points_to_keys(pts, self.resolution)), return_inverse=True
        )
        sums = np.stack(
            [np.bincount(inverse, pts[:, a], minlength=len(keys)) for a in range(3)], axis=1
        )
        means = sums / np.bincount(inverse, minlength=len(keys))[:, None]
        self._parts.append((keys, means, np.ones(len(keys), np.int64)))
        return len(pts)

    def add_observation(self, obs: Observation, pose: np.ndarray, sensor: SensorModel) -> int:
        """Add `obs`'s hits as `integrate_observation` gives them to the grid with `pose` (the
        pose the grid saw: the estimate, or the truth for a fixture); beams without a return
        hit nothing."""
        if obs.delta is not None or len(obs) == 0:
            return 0
        pts = obs.points_world(pose)
        if obs.no_return is not None:
            pts = pts[~obs.no_return]
        return self.add(pts, pose[:3, 3], float(sensor.max_range))

    def _merge(self) -> None:
        if not self._parts:
            return
        keys = np.concatenate([self._keys, *(p[0] for p in self._parts)])
        sums = np.concatenate([self._sums, *(p[1] for p in self._parts)])
        counts = np.concatenate([self._counts, *(p[2] for p in self._parts)])
        self._parts = []
        self._keys, inverse = np.unique(keys, return_inverse=True)
        n = len(self._keys)
        self._sums = np.stack([np.bincount(inverse, sums[:, a], minlength=n) for a in range(3)], 1)
        self._counts = np.bincount(inverse, counts, minlength=n).astype(np.int64)

    def points(self, keys: np.ndarray) -> np.ndarray:
        """Per voxel key (N, 3): the mean of its scans' mean hit points, or its centre where it
        has none."""
        self._merge()
        keys = np.asarray(keys, np.int64).reshape(-1, 3)
        out = vk.keys_to_centers(keys, self.resolution)
        if len(self._keys) == 0 or len(keys) == 0:
            return out
        packed = vk.pack(keys)
        i = np.minimum(np.searchsorted(self._keys, packed), len(self._keys) - 1)
        found = self._keys[i] == packed
        out[found] = self._sums[i[found]] / self._counts[i[found], None]
        return out

    def __len__(self) -> int:
        self._merge()
        return len(self._keys)
