"""The daemon's access to `voxel.grid.VoxelGrid`: one place that creates and loads layer grids."""

from __future__ import annotations

from pathlib import Path

from voxel.grid import VoxelGrid

__all__ = ["VoxelGrid", "load_grid", "new_grid"]


def new_grid(resolution: float, block_shape: str = "cube") -> VoxelGrid:
    """An empty grid at `resolution` (a layer; only its origin writes it); "planar" blocks suit
    a layer mapped by 2D scanners only."""
    return VoxelGrid(resolution, block_shape=block_shape)


def load_grid(path: str | Path) -> VoxelGrid:
    """A grid saved with `grid.save(path)`."""
    return VoxelGrid.load(path)
