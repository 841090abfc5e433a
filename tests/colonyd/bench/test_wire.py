"""Smoke test of the wire benchmark (colonyd/bench/wire.py) on a two-frame camera path."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

bench_wire = pytest.importorskip("colonyd.bench.wire")

KEYS = {
    "scenario",
    "changed_voxels",
    "occupied_changed",
    "bytes_full",
    "bytes_per_changed_voxel",
    "raw_scan_zstd_bytes",
    "encode_voxels_per_s",
    "decode_voxels_per_s",
}


def test_wire_bench_reports_every_field(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    tiny = bench_wire.Scenario("camera_2", 0.05, lambda: bench_wire._camera_path(2))
    monkeypatch.setattr(bench_wire, "scenarios", lambda shared_data: [tiny])
    out = tmp_path / "wire.json"
    results = bench_wire.run_wire_bench(out, None, repeats=1)
    assert json.loads(out.read_text()) == results
    (row,) = results
    assert set(row) >= KEYS
    assert row["changed_voxels"] > 10_000 and row["occupied_changed"] > 0
    assert row["replica_exact"] is True  # the replica that applied the decoded frames
    assert row["bytes_per_changed_voxel"] < 1.0
    assert row["bytes_full"] < row["raw_scan_zstd_bytes"]
    # the faster zstd level, timed beside: a little larger (the level is the sender's choice)
    assert row["bytes_full"] < row["bytes_full_zstd3"] < 1.3 * row["bytes_full"]
    assert row["encode_voxels_per_s_zstd3"] > 0
