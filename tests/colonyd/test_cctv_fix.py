"""A surveyed CCTV anchors a robot, live: the CCTV sees the robot's boards and sends PoseFix; the
robot, not yet aligned with the CCTV, fits the transform from the sightings, offers it, and
then fuses the fixes (truth read only to check the error stays small)."""

from __future__ import annotations

import time


def _spec(agent: str, epoch: float, extra: str = "") -> str:
    rate = 1 if agent.startswith("cctv") else 10
    return f"sim:world=room,agent={agent},frames={40 * rate},seed=2,epoch={epoch}{extra}" + (
        "" if agent.startswith("cctv") else ",odometry_noise=realistic"
    )


def test_a_cctv_anchors_a_robot_it_sees(make_colony):
    colony = make_colony("anchor")
    epoch = time.time() + 3.0
    for agent, extra in (("cctv-1", ",robots=lidar-1"), ("lidar-1", "")):
        d = colony.add(agent, [_spec(agent, epoch, extra)], start=False)
        d.env = {"COLONYD_ALIGN_S": "0", "COLONYD_OBJECTS_S": "1"}  # sightings align, not maps
        d.start()
    colony.wait_members(2, timeout=20)

    def fused(reports: list[dict]) -> bool:
        lidar = next((r for r in reports if r["agent"] == "lidar-1"), None)
        return lidar is not None and lidar["metrics"]["counts"].get("fix_fused", 0) >= 2

    reports = colony.wait_status(fused, 40, agents=("lidar-1", "cctv-1"))
    lidar = next(r for r in reports if r["agent"] == "lidar-1")
    cctv = next(r for r in reports if r["agent"] == "cctv-1")
    assert cctv["metrics"]["counts"].get("fixes_sent", 0) >= 4, cctv["metrics"]["counts"]
    counts = lidar["metrics"]["counts"]
    assert counts.get("fix_received", 0) >= 4, counts
    assert lidar["alignments"]["cctv-1"]["method"] == "sightings", lidar["alignments"]
    assert set(lidar["colony_frame"]["agents"]) == {"lidar-1", "cctv-1"}, lidar["colony_frame"]
    assert counts.get("fix_fused", 0) >= 2, counts
    assert lidar["pose_error_m"] < 0.2, lidar["pose_error_m"]
