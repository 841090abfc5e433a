"""Tests of delta extraction and merging: errors say what was expected and what was found."""

from __future__ import annotations

import numpy as np
import pytest

from voxel.delta import Delta, same_content
from voxel.errors import DeltaError
from voxel.grid import VoxelGrid


def test_merge_rejects_keys_off_the_key_space_and_foreign_channel_shapes() -> None:
    grid = VoxelGrid(0.1)
    far = Delta(0.1, 0, 1, np.array([[2**21, 0, 0]]), np.zeros(1), np.zeros(1))
    with pytest.raises(
        DeltaError,
        match=r"delta keys must lie in \[-1048576, 1048575\] on every axis, found \[0, 2097152\]",
    ):
        grid.apply(far)
    odd = Delta(
        0.1, 0, 1, np.zeros((1, 3)), np.zeros(1), np.zeros(1), {"class_ids": np.zeros((1, 5))}
    )
    with pytest.raises(
        DeltaError, match=r"delta channel 'class_ids' has shape \(5,\) per voxel, grid holds \(3,\)"
    ):
        grid.apply(odd)


def test_same_content_ignores_unknown_voxels_and_order() -> None:
    keys = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]])
    a = Delta(0.1, 0, 1, keys, np.array([0.5, np.nan, -0.5]), np.zeros(3))
    b = Delta(0.1, 0, 2, keys[[2, 0]], np.array([-0.5, 0.5]), np.zeros(2))
    assert same_content(a, b)
    assert not same_content(a, Delta(0.1, 0, 1, keys[[0]], np.array([0.5]), np.zeros(1)))
    assert not same_content(a, Delta(0.1, 0, 1, keys, a.logodds, np.zeros(3), {"hits": np.ones(3)}))
