"""The demo's printed summary and its progress lines (no daemons: the dicts the demo builds)."""

from __future__ import annotations

from pathlib import Path

from colonyd.demo import _progress_line, _replay_line, _summary_text


def _robot(carries: str, aligned: bool, after: float | None, ate: float | None) -> dict:
    return {
        "carries": carries,
        "ate_m": ate,
        "ate_alone_m": None if ate is None else 2 * ate,
        "ate_odometry_m": None if ate is None else 0.2,
        "final_pose_error_m": 0.0,
        "aligned": aligned,
        "time_to_align_s": after,
        "bytes_sent_per_s": 2048.0,
        "bytes_received_per_s": 1024.0,
    }


def _summary(lidar_aligned: bool) -> dict:
    return {
        "seconds": 84.1,
        "colony_frame": "cctv-1",
        "robots": {
            "cctv-1": _robot("CCTV", True, None, None),  # the root: aligned with no time
            "lidar-1": _robot("2D LiDAR", lidar_aligned, 12.5 if lidar_aligned else None, 0.01),
        },
        "late_joiner": "lidar-1",
        "late_joiner_catch_up_s": 4.7,
        "map": {"frame": "cctv-1.odom", "voxels": 10, "occupied": 5, "layers_fused": ["cctv-1"]},
        "load_average": [7.9, 5.1, 3.0],
        "cpus": 2,
    }


def test_summary_names_the_root_and_says_why_others_did_not_align():
    text = _summary_text(_summary(lidar_aligned=False), Path("demo-out"))
    rows = {line.split()[0]: line for line in text.splitlines()[1:3]}
    assert "colony frame's root" in rows["cctv-1"] and "not aligned" not in rows["cctv-1"]
    assert "not aligned" in rows["lidar-1"]
    assert "not aligned within the run: lidar-1." in text
    assert "load average was 7.9 on 2 cores" in text
    assert "2D LiDAR robot (lidar-1): ATE 0.020 m alone -> 0.010 m in the colony" in text


def test_summary_of_an_aligned_colony_has_no_excuse():
    text = _summary_text(_summary(lidar_aligned=True), Path("demo-out"))
    assert "aligned after 12.5 s" in text
    assert "not aligned" not in text


def test_progress_line_for_a_log():
    reports = [
        {"agent": "cctv-1", "colony_frame": {"root": "cctv-1", "agents": {"cctv-1": [], "b": []}}},
        {"agent": "b"},
    ]
    line = _progress_line(reports, 12.0)
    assert line == (
        "demo at  12.0 s: 2 members answered; aligned with the colony frame (cctv-1): b, cctv-1"
    )
    assert _progress_line([], 1.0).endswith("(?): none yet")


def test_the_replays_after_the_colony_are_announced():
    """After the colony's last table the demo replayed each robot alone for a minute or more
    with nothing printed: it looked hung."""
    line = _replay_line(149.1, ["depth-1", "lidar-1"])
    assert line.startswith("colony stopped at 149.1 s; replaying depth-1, lidar-1 alone")
    assert "colonyd localize" in line


def test_the_table_in_a_log_is_not_cut_at_80_columns():
    """Without a terminal the demo prints its table once, at the end: at rich's default 80
    columns it read "lidar3…", "replic…" and split every figure over two lines."""
    from colonyd.demo import _table, stdout_console
    from colonyd.tracks import Track

    counts = {"bytes_published": 6_689_000, "bytes_received": 15_096_000}
    reports = [
        {
            "agent": agent,
            "colony_frame": {"root": "cctv-1", "agents": {"cctv-1": []}},
            "pose_error_m": 0.001,
            "layers": {agent: {"seq": 141}, "cctv-1": {"seq": 40}},
            "metrics": {"counts": counts},
        }
        for agent in ("cctv-1", "lidar3d-1")
    ]
    tracks = {"lidar3d-1": Track("3D LiDAR", 0.0), "cctv-1": Track("CCTV", 0.0)}
    console = stdout_console()  # pytest captures stdout: not a terminal
    with console.capture() as captured:
        console.print(_table(reports, tracks, 149.1))
    text = captured.get()
    assert "…" not in text
    assert "lidar3d-1" in text and "replicas" in text and "14742 KiB" in text
    assert len(text.splitlines()) == 7  # title, border, header, rule, 2 one-line rows, border
