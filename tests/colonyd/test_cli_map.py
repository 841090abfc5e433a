"""The offline mapping command end to end, as a user runs it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from voxel.grid import VoxelGrid


def test_colonyd_map_writes_a_grid_from_a_sim_source(tmp_path: Path) -> None:
    out = tmp_path / "out"
    run = subprocess.run(
        [sys.executable, "-m", "colonyd", "map", "--source", "sim:world=room,agent=lidar-1,frames=5",
         "--resolution", "0.1", "--out", str(out)],
        capture_output=True, text=True, timeout=120,
    )
    assert run.returncode == 0, run.stderr
    for name in ("grid.npz", "map.bt", "map.ply", "trajectory.tum"):
        assert (out / name).stat().st_size > 0
    grid = VoxelGrid.load(out / "grid.npz")
    assert len(grid.occupied_keys()) > 0 and len(grid.free_keys()) > 0


def test_colonyd_map_bad_source_fails_with_a_clear_message(tmp_path: Path) -> None:
    run = subprocess.run(
        [sys.executable, "-m", "colonyd", "map", "--source", "nosuch:thing", "--out", str(tmp_path)],
        capture_output=True, text=True, timeout=60,
    )
    assert run.returncode != 0
    assert "nosuch" in run.stderr
