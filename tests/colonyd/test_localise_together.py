"""Localising together, live: a short-range LiDAR robot aligned with a depth-camera robot fuses
scan matches against the peer's map (counted in its status) and shares its estimate with its
covariance in Pose messages (truth read only to check the error stays small)."""

from __future__ import annotations

import time


def _spec(agent: str, epoch: float, extra: str = "") -> str:
    return (
        f"sim:world=office,agent={agent},frames=900,seed=1,odometry_noise=realistic,"
        f"epoch={epoch}{extra}"
    )


def _localisation(report: dict) -> dict:
    """The counts of the report's one sim source ({} before its first frame)."""
    entries = [v for k, v in report["localisation"].items() if k.startswith("sim:")]
    return entries[0] if entries else {}


def test_a_lidar_robot_matches_its_scans_against_an_aligned_peers_map(make_colony):
    colony = make_colony("together")
    epoch = time.time() + 3.0  # both paths start together, whoever starts first
    env = {"COLONYD_ALIGN_S": "1", "COLONYD_OBJECTS_S": "1", "COLONYD_COLONY_MAP_S": "0.5"}
    for agent, extra in (("depth-1", ""), ("lidar-1", ",lidar_range=4")):
        d = colony.add(agent, [_spec(agent, epoch, extra)], start=False)
        d.env = env
        d.start()
    colony.wait_members(2, timeout=20)

    def fused(reports: list[dict]) -> bool:
        lidar = next(r for r in reports if r["agent"] == "lidar-1")
        depth = next(r for r in reports if r["agent"] == "depth-1")
        seen = [m for m in depth["members"] if m["agent"] == "lidar-1"]
        return (
            _localisation(lidar).get("colony_accepted", 0) >= 5
            and bool(seen)
            and seen[0]["pose_std_m"] is not None
        )

    # (the sims run 90 s from the epoch: on a loaded machine the pair may align only after 45 s,
    # and the paths must still be running then; the wait ends as soon as the matches are in)
    reports = colony.wait_status(fused, 90, agents=("lidar-1", "depth-1"))
    lidar = next(r for r in reports if r["agent"] == "lidar-1")
    counts = _localisation(lidar)
    assert counts["colony_accepted"] >= 5, counts
    assert "depth-1" in counts["colony_map"]["sources"], counts
    assert set(lidar["colony_frame"]["agents"]) >= {"lidar-1", "depth-1"}, lidar["colony_frame"]
    assert lidar["pose_error_m"] is not None and lidar["pose_error_m"] < 0.3, lidar["pose_error_m"]
    assert lidar["pose_covariance"][0][0] > 0, lidar["pose_covariance"]
    depth = next(r for r in reports if r["agent"] == "depth-1")
    seen = next(m for m in depth["members"] if m["agent"] == "lidar-1")
    assert seen["pose_std_m"] is not None and seen["pose_std_m"] > 0, seen  # Pose carries it
