"""The offline A/B harness of the paper experiment, on a few seconds of path."""

from __future__ import annotations

import json

from colonyd.bench.paper_offline import main


def test_paper_offline_runs_both_robots_alone_and_with_the_others_map(tmp_path):
    out = tmp_path / "ab.jsonl"
    got = main(["--seed", "1", "--duration", "3", "--json", str(out)])
    for key in ("lidar_alone", "depth_alone", "depth_with_lidar", "lidar_with_depth"):
        assert 0.0 <= got[key] < 0.5, key
    # from mid-path on, every scan of each robot was tried against the other's map
    for counts in (got["depth_counts"], got["lidar_counts"]):
        assert sum(counts.values()) > 0
    # the filter's claimed covariance against its error (truth for evaluation only)
    for run in ("lidar_alone", "depth_alone", "depth_with_lidar", "lidar_with_depth"):
        honest = got[f"{run}_consistency"]
        assert honest["nees_mean"] > 0.0 and 0.0 <= honest["nees_over"] <= 1.0, run
        assert 0.0 < honest["sigma_m"] < 0.5 and 0.0 <= honest["error_m"] < 0.5, run
    assert got["peer_covariance"] is True  # the daemon's behaviour: the peer's own pose error too
    assert json.loads(out.read_text().splitlines()[-1]) == got
