"""The scan matcher's consistency bench, on a few seconds of path."""

from __future__ import annotations

import json

from colonyd.bench.match_nees import main


def test_match_nees_scores_both_robots_against_the_truth_and_their_own_map(tmp_path):
    out = tmp_path / "nees.jsonl"
    got = main(["--seed", "1", "--duration", "3", "--json", str(out)])
    for agent in ("lidar-1", "depth-1"):
        for case in ("truth", "own"):
            every = got[agent][case]["all"]
            assert every["n"] > 10, (agent, case)
            assert 0.0 < every["nees_mean"] < 1e6 and 0.0 <= every["nees_over"] <= 1.0
            assert 0.0 < every["sigma_m"] < 0.5 and 0.0 <= every["error_m"] < 0.5
    assert json.loads(out.read_text().splitlines()[-1]) == got
