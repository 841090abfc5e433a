"""The sensor-bias bench, on a few seconds of path."""

from __future__ import annotations

import json

import numpy as np

from colonyd.bench.match_bias import main, surfaces
from plugins.world import get_world


def test_exact_surfaces_lie_on_the_world_with_outward_normals() -> None:
    target = surfaces(get_world("office"), 0.1)
    assert len(target.points) == len(target.normals) > 10000
    np.testing.assert_allclose(np.linalg.norm(target.normals, axis=1), 1.0)
    # from just outside a sample of points, along the inward normal, the world's surface is
    # hit 5 cm away (the point lies on it, its normal points out), except where the point is on
    # an edge (grazed) or a face hidden inside a joined wall
    world = get_world("office")
    sample = range(0, len(target.points), 997)
    t = np.array(
        [
            world.cast(target.points[i] + 0.05 * target.normals[i], -target.normals[i][None, :]).t[
                0
            ]
            for i in sample
        ]
    )
    assert np.mean(np.abs(t - 0.05) < 1e-9) > 0.8, t


def test_match_bias_measures_both_robots_from_their_true_poses(tmp_path) -> None:
    out = tmp_path / "bias.jsonl"
    got = main(["--seed", "1", "--duration", "3", "--json", str(out)])
    for agent in ("lidar-1", "depth-1"):
        for target in ("world", "truth_map"):
            s = got[agent][target]
            assert s["n"] > 10, (agent, target)
            # from the true pose against exact surfaces: offsets of millimetres, not centimetres
            assert all(abs(v) < 10.0 for v in s["mean"][:2]), (agent, target, s)
            assert len(s["standard_error"]) == len(s["claimed_sd"]) == 3
    assert json.loads(out.read_text().splitlines()[-1]) == got
