"""Information-rich voxel grid: storage, integration, queries, history, deltas and file formats."""

from voxel.delta import Delta
from voxel.errors import VoxelError
from voxel.grid import FREE_STATE, OCCUPIED, UNKNOWN, IntegrationReport, VoxelGrid
from voxel.sensor import SensorModel

__all__ = [
    "FREE_STATE",
    "OCCUPIED",
    "UNKNOWN",
    "Delta",
    "IntegrationReport",
    "SensorModel",
    "VoxelError",
    "VoxelGrid",
]
