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


def test_best_classes_are_the_full_deltas_labelled_known_voxels_in_its_order():
    """`VoxelGrid.best_classes` reads the class channels alone and gives what the full delta's
    rows give (known, with a class: the column of the highest probability), in its order."""
    rng = np.random.default_rng(3)
    grid = VoxelGrid(0.1)
    n = 400
    keys = rng.integers(-40, 40, (n, 3))
    ids = rng.integers(0, 9, (n, 3)).astype(np.int16)
    ids[rng.random(n) < 0.4] = -1  # no class
    probs = np.where(ids >= 0, rng.integers(0, 4, (n, 3)) / 4, 0.0).astype(np.float32)  # ties
    lo = rng.normal(0, 1, n).astype(np.float32)
    lo[rng.random(n) < 0.2] = np.nan  # unknown again
    grid.apply(Delta(0.1, 0, 1, keys, lo, np.ones(n), {"class_ids": ids, "class_probs": probs}))
    full = grid.delta_since(0)
    column = full.channels["class_probs"].argmax(axis=1)[:, None]
    cls = np.take_along_axis(full.channels["class_ids"], column, axis=1)[:, 0]
    prob = np.take_along_axis(full.channels["class_probs"], column, axis=1)[:, 0]
    rows = np.flatnonzero(~np.isnan(full.logodds) & (cls >= 0))
    got = grid.best_classes()
    assert len(rows) > 50 and len(rows) < len(full)
    for x, y in zip(got, (full.keys[rows], cls[rows], prob[rows]), strict=True):
        assert x.dtype == y.dtype and np.array_equal(x, y)
    plain = VoxelGrid(0.1)
    plain.apply(Delta(0.1, 0, 1, keys, lo, np.ones(n)))
    assert [len(x) for x in plain.best_classes()] == [0, 0, 0]
