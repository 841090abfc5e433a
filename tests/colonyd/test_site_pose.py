"""Surveyed site poses: an agent with `site_pose` offers it as a sure alignment to the anchor, and
every daemon, including one that joins later, puts that agent in the site frame."""

from __future__ import annotations

import numpy as np
import pytest

from colonyd.config import load_config
from colonyd.errors import ConfigError
from voxel.rotation import euler_pose


def test_site_pose_needs_an_anchor_and_four_or_six_numbers():
    with pytest.raises(ConfigError, match="anchor"):
        load_config(None, agent_id="b", site_pose=[1, 2, 0, 90])
    with pytest.raises(ConfigError, match="4 numbers"):
        load_config(None, agent_id="b", anchor="a", site_pose=[1, 2, 0])
    with pytest.raises(ConfigError, match="anchor 'a' itself"):
        load_config(None, agent_id="a", anchor="a", site_pose=[1, 2, 0, 90])
    cfg = load_config(None, agent_id="b", anchor="a", site_pose=[1, 2, 0.5, 90, 0, 0])
    assert np.allclose(cfg.site_matrix(), euler_pose(1, 2, 0.5, np.pi / 2))


def _frame_of(report: dict, agent: str) -> np.ndarray | None:
    matrix = report["colony_frame"]["agents"].get(agent)
    return None if matrix is None else np.asarray(matrix)


def test_surveyed_agent_is_in_the_site_frame_everywhere_and_for_a_late_joiner(make_colony):
    colony = make_colony("site", extra=["--no-multicast"])
    env = {"COLONYD_ANCHOR": "a", "COLONYD_ALIGN_S": "0.3"}
    for agent, pose in (("a", None), ("b", "[1.5, -2.0, 0.0, 90.0]"), ("c", None)):
        d = colony.add(agent, start=False)
        d.env.update(env)
        if pose is not None:
            d.env["COLONYD_SITE_POSE"] = pose
        d.start()
        if agent == "b":  # c joins once b's first offer is long gone
            colony.wait_members(2)
            colony.wait_status(
                lambda rs: all(_frame_of(r, "b") is not None for r in rs), agents=("a", "b")
            )
    want = euler_pose(1.5, -2.0, 0.0, np.pi / 2)

    def placed(reports: list[dict]) -> bool:
        frames = [_frame_of(r, "b") for r in reports]
        return len(reports) == 3 and all(f is not None and np.allclose(f, want) for f in frames)

    reports = colony.wait_status(placed, within=20)
    assert placed(reports), [(r["agent"], r["colony_frame"]) for r in reports]
    assert {r["colony_frame"]["root"] for r in reports} == {"a"}
