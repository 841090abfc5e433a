"""Adapter to `voxel.grid.VoxelGrid`; a minimal stand-in keeps the daemon runnable without it."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from voxel import keys as vk
from voxel.delta import Delta
from voxel.sensor import SensorModel

log = logging.getLogger(__name__)


class FallbackGrid:
    """Endpoint-only log-odds grid with per-voxel versions, used only if voxel.grid is missing."""

    def __init__(self, resolution: float, **_: Any) -> None:
        self.resolution = float(resolution)
        self.version = 0
        self._packed = np.empty(0, np.int64)
        self._lo = np.empty(0, np.float32)
        self._ver = np.empty(0, np.int64)
        self._lt = np.empty(0, np.float64)

    def _upsert(self, packed: np.ndarray, lo: np.ndarray, ver: np.ndarray, lt: np.ndarray) -> None:
        idx = np.searchsorted(self._packed, packed)
        idx_c = np.minimum(idx, max(self._packed.shape[0] - 1, 0))
        found = (self._packed.shape[0] > 0) & (self._packed[idx_c] == packed) if self._packed.size else np.zeros(packed.shape[0], bool)
        upd = idx_c[found]
        newer = ver[found] >= self._ver[upd]
        sel = upd[newer]
        self._lo[sel] = lo[found][newer]
        self._ver[sel] = ver[found][newer]
        self._lt[sel] = lt[found][newer]
        add = ~found
        if add.any():
            p = np.concatenate([self._packed, packed[add]])
            order = np.argsort(p, kind="stable")
            self._packed = p[order]
            self._lo = np.concatenate([self._lo, lo[add]])[order]
            self._ver = np.concatenate([self._ver, ver[add]])[order]
            self._lt = np.concatenate([self._lt, lt[add]])[order]

    def integrate(self, points: np.ndarray, origin: np.ndarray, *, time: float = 0.0,
                  sensor: SensorModel | None = None, **_: Any) -> None:
        sensor = sensor or SensorModel()
        pts = np.asarray(points, np.float64).reshape(-1, 3)
        if not len(pts):
            return
        packed, counts = np.unique(vk.pack(vk.points_to_keys(pts, self.resolution)), return_counts=True)
        cur = np.zeros(packed.shape[0], np.float32)
        if self._packed.size:
            idx = np.minimum(np.searchsorted(self._packed, packed), self._packed.shape[0] - 1)
            hit = self._packed[idx] == packed
            cur[hit] = np.nan_to_num(self._lo[idx[hit]])
        new = np.clip(cur + counts * sensor.log_hit, sensor.log_min, sensor.log_max).astype(np.float32)
        self.version += 1
        n = packed.shape[0]
        self._upsert(packed, new, np.full(n, self.version), np.full(n, time))

    def apply(self, delta: Delta) -> int:
        n = len(delta)
        if n:
            self._upsert(vk.pack(delta.keys), delta.logodds.astype(np.float32),
                         np.full(n, delta.to_version, np.int64), delta.last_time)
        self.version = max(self.version, delta.to_version)
        return n

    def delta_since(self, version: int) -> Delta:
        sel = self._ver > version
        return Delta(self.resolution, version, self.version, vk.unpack(self._packed[sel]),
                     self._lo[sel], self._lt[sel])

    def known_count(self) -> int:
        return int((~np.isnan(self._lo)).sum())

    def occupied_keys(self) -> np.ndarray:
        return vk.unpack(self._packed[self._lo >= 0])

    def save(self, path: str | Path) -> None:
        with open(path, "wb") as fh:
            np.savez(fh, res=self.resolution, version=self.version, packed=self._packed,
                     lo=self._lo, ver=self._ver, lt=self._lt)

    @classmethod
    def load(cls, path: str | Path) -> FallbackGrid:
        with np.load(path) as z:
            g = cls(float(z["res"]))
            g.version = int(z["version"])
            g._packed, g._lo, g._ver, g._lt = z["packed"], z["lo"], z["ver"], z["lt"]
        return g


try:
    from voxel.grid import VoxelGrid  # type: ignore[assignment]
except ImportError:  # the voxel package without its grid yet
    VoxelGrid = FallbackGrid  # type: ignore[misc,assignment]
    log.debug("voxel.grid not available; using the endpoint-only fallback grid")


def new_grid(resolution: float) -> VoxelGrid:
    """An empty grid at `resolution`."""
    return VoxelGrid(resolution)


def load_grid(path: str | Path) -> VoxelGrid:
    """A grid saved with `grid.save(path)`."""
    return VoxelGrid.load(path)
