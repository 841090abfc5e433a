"""The paper benchmark's claims, on constructed results and trajectories (no daemons)."""

from __future__ import annotations

import numpy as np

from colonyd.bench.paper import claims, growth_after_contact
from colonyd.tracks import Track, write_tum


def _write(out, run: str, slope: float) -> None:
    """lidar-1's TUM files in `run`: a curvy true path, the estimate off sideways by a drift that
    grows by `slope` m per second after t = 5 s."""
    track = Track("2D LiDAR", 0.0)
    for i in range(40):
        t = i * 0.5
        truth = np.eye(4)
        truth[:3, 3] = [t, np.sin(t / 3.0), 0.0]
        estimate = truth.copy()
        estimate[1, 3] += slope * max(0.0, t - 5.0) * (1 if i % 2 else -1)
        track.times.append(t)
        track.truth.append(truth)
        track.estimate.append(estimate)
    write_tum(track, out / run, "lidar-1")


def _results(alone: float, shared: float, cctv: float) -> dict:
    def m(ate: float, contact: float | None) -> dict:
        return {
            "ate_rmse_m": ate,
            "final_error_m": ate,
            "max_error_after_contact_m": None,
            "first_contact_s": contact,
        }

    return {
        "runs": {
            "lidar-alone": {"lidar-1": m(alone, None)},
            "lidar+depth": {"lidar-1": m(shared, 5.0)},
            "lidar+depth+cctv": {"lidar-1": m(cctv, 5.0)},
        }
    }


def test_claims_hold_and_fail_as_the_figures_say(tmp_path):
    _write(tmp_path, "lidar+depth", 0.0)
    _write(tmp_path, "lidar+depth+cctv", 0.0)
    good = claims(_results(0.2, 0.08, 0.05), tmp_path)
    assert good["ratio_shared_to_alone"] == 0.4
    assert good["shared_halves_ate"] and good["cctv_no_worse"]
    assert good["no_growth_after_contact"]
    bad = claims(_results(0.2, 0.15, 0.2), tmp_path)
    assert not bad["shared_halves_ate"] and not bad["cctv_no_worse"]


def test_growth_after_contact_follows_the_error_trend(tmp_path):
    _write(tmp_path, "flat", 0.0)
    _write(tmp_path, "drifting", 0.02)  # 0.02 m/s for 14.5 s after contact
    assert abs(growth_after_contact(tmp_path, "flat", "lidar-1", 5.0)) < 1e-3
    rise = growth_after_contact(tmp_path, "drifting", "lidar-1", 5.0)
    assert 0.1 < rise < 0.4
    assert growth_after_contact(tmp_path, "drifting", "lidar-1", None) is None
    assert growth_after_contact(tmp_path, "drifting", "lidar-1", 19.5) is None  # < 3 poses after
