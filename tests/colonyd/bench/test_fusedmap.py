"""Smoke test of the fused map's cost benchmark (colonyd/bench/fusedmap.py)."""

from __future__ import annotations

import numpy as np

from colonyd.bench.fusedmap import OUTPUTS, ROUNDS, labelled, run
from voxel.grid import VoxelGrid


def test_every_round_times_every_output_of_a_turned_pair_of_layers() -> None:
    grid = VoxelGrid(0.1, surface=True)
    x = np.linspace(-1.0, 1.0, 101)
    grid.integrate(np.column_stack([x, np.full(x.size, 2.0), x]), np.zeros(3), time=1.0)
    out = run(grid, yaw=30.0, repeats=1)
    assert out["layer_voxels"] == grid.known_count()
    # the turned copy lands elsewhere: the fused map holds more voxels than one layer
    assert out["fused_voxels"] > out["layer_voxels"]  # type: ignore[operator]
    seconds = out["cpu_seconds"]
    assert isinstance(seconds, dict) and list(seconds) == list(ROUNDS)
    assert all(list(v) == list(OUTPUTS) and min(v.values()) >= 0 for v in seconds.values())


def test_the_labelled_fraction_gives_classes_to_about_that_share_of_voxels() -> None:
    grid = VoxelGrid(0.1, surface=True)
    x = np.linspace(-1.0, 1.0, 101)
    grid.integrate(np.column_stack([x, np.full(x.size, 2.0), x]), np.zeros(3), time=1.0)
    full = grid.delta_since(0)
    assert labelled(full, 0.0) is full
    ids = labelled(full, 0.5).channels["class_ids"]
    share = float(np.mean(ids[:, 0] >= 0))
    assert ids.shape == (len(full), 3) and 0.3 < share < 0.7
    out = run(grid, yaw=30.0, repeats=1, fraction=0.5)
    assert out["labelled"] == 0.5
