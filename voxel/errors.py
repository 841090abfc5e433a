"""Errors raised by the voxel package."""

from __future__ import annotations


class VoxelError(Exception):
    """Base class of every error raised by the voxel package."""


class InputError(VoxelError, ValueError):
    """Points, poses or channels given to the grid have the wrong shape, type or value."""


class DeltaError(VoxelError, ValueError):
    """A delta does not fit the grid it is applied to."""


class FileFormatError(VoxelError):
    """A snapshot, PLY or OctoMap file is not what it claims to be."""


class AlignmentError(VoxelError, ValueError):
    """Maps or parameters given to registration cannot be aligned as asked (empty map, bad dof)."""


class LocalisationError(VoxelError, ValueError):
    """Trajectories, odometry or sensor data given to localisation have the wrong shape or value."""
