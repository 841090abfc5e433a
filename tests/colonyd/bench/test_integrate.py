"""The integration benchmark runs end to end and reports what the issue asks for."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from colonyd.bench.integrate import run_integrate_bench

FIELDS = {
    "scenario",
    "resolution",
    "points",
    "ours_ms",
    "octomap_ms",
    "speedup",
    "occupied_agreement",
    "free_agreement",
    "bytes_per_known_voxel",
    "octomap_bytes_per_node",
}


def test_lidar2d_scenario_agrees_with_octomap(tmp_path: Path) -> None:
    pytest.importorskip("pyoctomap")
    out = tmp_path / "bench.json"
    results = run_integrate_bench(out, None, repeats=1, only=["lidar2d_1081_0.05"])
    assert json.loads(out.read_text()) == results
    (row,) = results
    assert set(row) >= FIELDS
    assert row["occupied_agreement"] >= 0.95 and row["free_agreement"] >= 0.9
    assert row["ours_ms"] > 0 and row["octomap_ms"] > 0
    (run,) = row["per_run"]  # one run: its medians are the row's
    assert (run["ours_ms"], run["speedup"]) == (
        pytest.approx(row["ours_ms"], abs=0.01),
        pytest.approx(row["speedup"], abs=0.01),
    )
    # memory is deterministic: a planar scan in planar blocks costs less per voxel than OctoMap
    assert row["block_shape"] == "planar"
    assert row["bytes_per_known_voxel"] <= row["octomap_bytes_per_node"]


def test_unknown_scenario_is_a_config_error(tmp_path: Path) -> None:
    from colonyd.errors import ConfigError

    with pytest.raises(
        ConfigError, match=r"unknown scenario.*'nope'.*expected some of.*lidar3d_64x1024_0\.05"
    ):
        run_integrate_bench(tmp_path / "x.json", None, repeats=1, only=["nope"])


@pytest.mark.parametrize("module", ["integrate", "wire"])
def test_unreadable_depth_png_names_the_file(tmp_path: Path, module: str) -> None:
    """Both benchmarks read the frames through one reader (`redkitchen_depths`)."""
    import importlib

    from plugins.errors import ParseError

    frames = tmp_path / "redkitchen-50" / "frames"
    frames.mkdir(parents=True)
    (frames / "frame-000000.depth.png").write_bytes(b"not a png")
    bench = importlib.import_module(f"colonyd.bench.{module}")
    with pytest.raises(
        ParseError, match=r"frame-000000\.depth\.png: expected a readable 16-bit PNG"
    ):
        next(iter(bench._redkitchen(tmp_path)()))
