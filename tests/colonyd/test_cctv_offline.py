"""The CCTV's offline harness on a few seconds of path: fixes made as the daemon makes them,
sightings that align the robots, fixes fused, the colony map the alignment brings."""

from __future__ import annotations

from colonyd.bench.cctv_offline import main


def test_cctv_offline_aligns_by_sightings_then_fuses_fixes_and_matches_the_colony_map():
    args = ["--seed", "1", "--duration", "7", "--variants", "fixes,map"]
    got = main([*args, "--peer-points", "centres,means"])
    errors = got["fix_errors_lidar-1"]
    assert errors["n"] >= errors["images"] > 0  # the old model: every board seen is a fix
    assert 0.0 < errors["rms_xy_m"] < 0.1 and errors["nees_xy_mean"] > 0.0
    aligned = got["lidar_alignment"]  # by sightings, before the fixes are fused
    assert aligned is not None and 0.0 < aligned["at_s"] < 7.0
    assert abs(aligned["x_m"]) < 0.1 and abs(aligned["y_m"]) < 0.1
    fused, _, stale = got["lidar_fixes_fixes"]
    assert fused > 0 and stale == 0
    assert got["lidar_map_fixes"] == [0, 0, 0]  # the map run takes no fix: they only align it
    assert sum(got["lidar_map_counts"].values()) > 0 and got["lidar_map_map_from"] is not None
    # the maps as their voxels' surface points (the grids' surface channel)
    assert sum(got["lidar_map@means_counts"].values()) > 0 and "lidar_fixes@means" not in got
    for key in ("lidar_fixes", "lidar_map", "depth_with_fixes", "lidar_map@means"):
        assert 0.0 <= got[key] < 0.5, key


def test_cctv_offline_new_model_sends_one_fix_per_image_and_raw_cctv_map_is_matched():
    args = ["--seed", "1", "--duration", "7", "--fix-model", "new", "--cctv-map", "raw"]
    got = main([*args, "--variants", "map-cctv"])
    errors = got["fix_errors_lidar-1"]
    assert errors["n"] == errors["images"] > 0
    assert got["fix_model"] == "new" and got["cctv_map"] == "raw"
    assert got["lidar_map-cctv_counts"]["colony_accepted"] > 0  # the raw points matched
    assert 0.0 <= got["lidar_map-cctv"] < 0.5


def test_cctv_offline_alignment_state_fuses_fixes_through_the_frames_error():
    got = main(["--seed", "1", "--duration", "7", "--variants", "fixes", "--alignment", "state"])
    assert got["alignment"] == "state"
    fused, _, stale = got["lidar_fixes_fixes"]
    assert fused > 0 and stale == 0
    aligned = got["lidar_alignment"]  # the filter estimated the alignment's error
    assert aligned is not None and aligned["estimated_yaw_sd_deg"] > 0.0
    assert 0.0 <= got["lidar_fixes"] < 0.5
