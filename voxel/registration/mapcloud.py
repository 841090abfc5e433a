"""A map as registration sees it: occupied voxels' surface points plus, when the file has it, known
space."""

from __future__ import annotations

from dataclasses import dataclass
from os import PathLike
from pathlib import Path

import numpy as np

from voxel import keys as vk
from voxel.errors import AlignmentError, FileFormatError

#: Map file suffixes `load_map` reads.
MAP_SUFFIXES = (".bt", ".npz", ".ply")

UNKNOWN, FREE, OCCUPIED = -1, 0, 1


@dataclass(frozen=True, eq=False)
class MapCloud:
    """Occupied voxels' surface points (N, 3) of one map in its own frame (their mean hit
    positions where the map keeps them, `VoxelGrid.occupied_surface`; else their centres), and
    its known voxels if any.

    known: sorted packed keys of every known voxel (occupied and free) at `resolution`, with
    `known_occupied` telling which are occupied; None for point clouds (PLY) without free space.
    """

    resolution: float
    occupied: np.ndarray
    known: np.ndarray | None = None
    known_occupied: np.ndarray | None = None
    name: str = "map"

    @classmethod
    def from_keys(
        cls,
        resolution: float,
        keys: np.ndarray,
        occupied: np.ndarray,
        name: str = "map",
        surface: np.ndarray | None = None,
    ) -> MapCloud:
        """A map from voxel keys (N, 3) and their occupied mask (N,); the others are free.
        `surface` (N, 3): the voxels' surface points (`VoxelGrid.surface_points`); default
        their centres."""
        keys = np.asarray(keys, dtype=np.int64).reshape(-1, 3)
        occupied = np.asarray(occupied, dtype=bool).reshape(-1)
        packed = vk.pack(keys)
        order = np.argsort(packed, kind="stable")
        if surface is None:
            points = vk.keys_to_centers(keys[occupied], resolution)
        else:
            points = np.asarray(surface, dtype=np.float64).reshape(-1, 3)[occupied]
        return cls(float(resolution), points, packed[order], occupied[order], name)

    @property
    def planar(self) -> bool:
        """True when every occupied voxel lies in one horizontal layer (a 2D scanner's map)."""
        z = self.occupied[:, 2]
        return bool(z.size and float(z.max() - z.min()) < 0.5 * self.resolution)

    @property
    def has_free_space(self) -> bool:
        """True when the map knows its free voxels (grids and OctoMap files; not PLY)."""
        return self.known is not None

    def state_at(self, points: np.ndarray) -> np.ndarray:
        """State (UNKNOWN -1, FREE 0, OCCUPIED 1) of this map's voxel at each point (N, 3)."""
        known, known_occupied = self.known, self.known_occupied
        if known is None or known_occupied is None or known.size == 0:
            return np.full(len(points), UNKNOWN, np.int8)
        keys = vk.points_to_keys(points, self.resolution)
        ok = vk.in_range(keys)
        packed = vk.pack(np.where(ok[:, None], keys, 0))
        idx = np.minimum(np.searchsorted(known, packed), known.size - 1)
        hit = ok & (known[idx] == packed)
        return np.where(hit, np.where(known_occupied[idx], OCCUPIED, FREE), UNKNOWN).astype(np.int8)


def load_map(path: str | PathLike[str]) -> MapCloud:
    """Read a map file: OctoMap .bt, a grid snapshot .npz (`colonyd map`'s grid.npz) or a PLY
    cloud."""
    path = Path(path)
    if not path.is_file():
        msg = f"{path}: expected a map file ({', '.join(MAP_SUFFIXES)}), found nothing there"
        raise FileFormatError(msg)
    suffix = path.suffix.lower()
    if suffix == ".bt":
        from voxel.octomap_io import read_bt

        bt = read_bt(path)
        cloud = MapCloud.from_keys(bt.resolution, bt.keys, bt.occupied, name=str(path))
    elif suffix == ".npz":
        from voxel.grid import VoxelGrid

        grid = VoxelGrid.load(path)
        occ, free = grid.occupied_keys(), grid.free_keys()
        mask = np.zeros(len(occ) + len(free), bool)
        mask[: len(occ)] = True
        keys = np.concatenate([occ, free])
        cloud = MapCloud.from_keys(
            grid.resolution, keys, mask, name=str(path), surface=grid.surface_points(keys)
        )
    elif suffix == ".ply":
        from voxel.ply import read_ply

        points, _ = read_ply(path)
        cloud = MapCloud(_spacing(points), points, name=str(path))
    else:
        msg = (
            f"{path}: expected a map file ending in {', '.join(MAP_SUFFIXES)}, "
            f"found {suffix or 'no suffix'!r}"
        )
        raise FileFormatError(msg)
    if len(cloud.occupied) == 0:
        msg = f"{path}: expected a map with occupied voxels to align, found none"
        raise AlignmentError(msg)
    return cloud


def _spacing(points: np.ndarray) -> float:
    """Voxel size of a PLY cloud of voxel centres: the median nearest-neighbour distance."""
    if len(points) < 2:
        return 0.05
    from scipy.spatial import cKDTree

    sample = points[:: max(1, len(points) // 2000)]
    d, _ = cKDTree(points).query(sample, k=2)
    spacing = float(np.median(d[:, 1]))
    return spacing if spacing > 0 else 0.05
