"""Smoke tests of the catch-up steps and the start-to-ready timing of `colonyd bench colony`."""

from __future__ import annotations

from colonyd.bench.catchup import catchup_steps, start_to_ready


def test_catchup_steps_install_every_voxel_of_the_layer() -> None:
    out = catchup_steps(300_000, repeats=1)
    assert out["voxels"] == 300_000  # catchup_steps raises unless the install got them all
    assert out["parts"] == 2  # parts of 250 k voxels, as a daemon serves them
    assert 0 < out["bytes"] < 300_000 * 2
    steps = ("serve_cpu_s", "encode_cpu_s", "decode_cpu_s", "admit_cpu_s", "install_cpu_s")
    assert out["total_cpu_s"] >= max(out[k] for k in steps) > 0


def test_a_daemon_is_timed_from_spawn_to_ready(tmp_path) -> None:
    out = start_to_ready(tmp_path, runs=1)
    assert out["start_runs"] == 1
    assert 0 < out["start_to_ready_cpu_s_min"] <= out["start_to_ready_wall_s_min"] + 1.0
    assert out["start_to_ready_wall_s_median"] == out["start_to_ready_wall_s_min"]


def test_newcomers_catch_up_one_after_another_with_their_timelines(tmp_path) -> None:
    from colonyd.bench.colony import _catchup

    out = _catchup(tmp_path, 20_000, runs=2)
    assert [r["catchup_voxels"] for r in out["catchup_runs"]] == [20_000, 20_000]
    assert out["catchup_s"] <= out["catchup_s_median"] <= out["catchup_s_max"]
    each = [r["catchup_s"] for r in out["catchup_runs"]]
    assert out["catchup_s_each"] == each and out["catchup_s_first"] == each[0]
    for run in out["catchup_runs"]:
        line = run["timeline_ms"]
        # the newcomer's steps in order, the holder's serve between its request and first reply
        steps = ["request", "arrived", "query", "locked", "snapshot", "encoded_first", "encoded"]
        steps += ["first", "received", "admitted"]
        assert [line[k] for k in steps] == sorted(line[k] for k in steps), line
        # the holder marks its first reply once `reply` returns: the newcomer may have it sooner
        assert line["encoded"] <= line["first_reply"], line
        assert line["request"] == 0
        assert abs(line["installed"] - run["catchup_s"] * 1000) < 1.0
        assert line["asked"] <= 0 and line["admitted"] <= line["installed"]
        assert 0 < run["decode_ms"] <= line["received"]
        assert run["server_cpu_ms"] > 0 and run["newcomer_cpu_ms"] > 0
        assert run["server_process_cpu_ms"] >= run["server_cpu_ms"] - 1.0  # every thread
