"""Smoke tests of the catch-up steps and the start-to-ready timing of `colonyd bench colony`."""

from __future__ import annotations

from colonyd.bench.catchup import catchup_steps, start_to_ready


def test_catchup_steps_install_every_voxel_of_the_layer() -> None:
    out = catchup_steps(300_000, repeats=1)
    assert out["voxels"] == 300_000  # catchup_steps raises unless the install got them all
    assert out["parts"] == 2  # parts of 250 k voxels, as a daemon serves them
    assert 0 < out["bytes"] < 300_000 * 2
    steps = ("serve_cpu_s", "encode_cpu_s", "decode_cpu_s", "install_cpu_s")
    assert out["total_cpu_s"] >= max(out[k] for k in steps) > 0


def test_a_daemon_is_timed_from_spawn_to_ready(tmp_path) -> None:
    out = start_to_ready(tmp_path, runs=1)
    assert out["start_runs"] == 1
    assert 0 < out["start_to_ready_cpu_s_min"] <= out["start_to_ready_wall_s_min"] + 1.0
    assert out["start_to_ready_wall_s_median"] == out["start_to_ready_wall_s_min"]
