"""Smoke test of the surface-matching benchmark (colonyd/bench/surface_match.py)."""

from __future__ import annotations

from colonyd.bench.surface_match import run


def test_a_scan_matched_to_surface_points_lands_closer_than_to_voxel_centres() -> None:
    out = run(seed=1, poses=4, reach=4.0)
    assert out["surface_failed"] == 0 and out["centres_failed"] == 0
    assert out["surface_median_m"] < 0.005 < 0.03 < out["centres_median_m"]  # type: ignore[operator]
