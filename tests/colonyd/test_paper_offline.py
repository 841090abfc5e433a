"""The offline A/B harness of the paper experiment, on a few seconds of path."""

from __future__ import annotations

import json

import numpy as np
import pytest

from colonyd.bench import cctv_offline
from colonyd.bench.paper_offline import main, surfaces
from colonyd.mapping import integrate_observation
from plugins.observation import Observation
from voxel import keys as vk
from voxel import surface
from voxel.grid import VoxelGrid
from voxel.localisation import se2
from voxel.sensor import SensorModel


def test_means_are_the_peer_grids_surface_points_in_the_robots_frame():
    rng = np.random.default_rng(3)
    pose = np.eye(4)
    pose[:3, 3] = [1.0, -0.5, 0.2]
    obs = Observation("lidar", 1.0, rng.uniform(-1.5, 1.5, (400, 3)), pose)
    grid = VoxelGrid(0.1, surface=True)
    integrate_observation(grid, obs, sensor=SensorModel(max_range=3.0), reliability=1.0)
    to_own = se2.to_matrix(np.array([0.3, -0.2, 0.4]))
    got = surfaces(grid, to_own)
    # one scan: each occupied voxel's surface is the mean of its hit points, to the published
    # codes' step (PUBLISH_STEP / 254 of a voxel: 3.1 mm its half per axis at 0.1 m), then put
    # into the robot's frame
    world = obs.points_world()
    keys = vk.pack(vk.points_to_keys(world, 0.1))
    occupied = grid.occupied_keys()
    assert len(occupied) > 50
    means = np.array([world[keys == k].mean(axis=0) for k in vk.pack(occupied)])
    half_step = 0.5 * 0.1 * surface.PUBLISH_STEP / surface.WIRE_SCALE
    want = means @ to_own[:3, :3].T + to_own[:3, 3]
    np.testing.assert_allclose(got, want, atol=half_step * np.sqrt(3) + 1e-5)
    centres = vk.keys_to_centers(occupied, 0.1) @ to_own[:3, :3].T + to_own[:3, 3]
    assert np.median(np.linalg.norm(got - centres, axis=1)) > 0.01  # not the voxels' centres


def test_means_need_the_peer_grid_to_keep_its_surface():
    with pytest.raises(ValueError, match="surface channel"):
        surfaces(VoxelGrid(0.1), np.eye(4))


@pytest.mark.parametrize("run", [main, cctv_offline.main])
def test_peer_points_is_validated(run, capsys):
    with pytest.raises(SystemExit) as exit_:
        run(["--peer-points", "centres,surface"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "--peer-points" in err and "'centres', 'means'" in err and "surface" in err


def test_joint_weighting_is_validated(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--joint-weighting", "matcher,robust"])
    assert exit_.value.code == 2
    assert "--joint-weighting" in capsys.readouterr().err


def test_paper_offline_runs_both_robots_alone_and_with_the_others_map(tmp_path):
    out = tmp_path / "ab.jsonl"
    joint = ["--smooth", "--joint", "--joint-alone", "--joint-weighting", "matcher,cell-vce"]
    got = main(["--seed", "1", "--duration", "3", *joint, "--json", str(out)])
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
    assert got["peer_covariance"] is True  # the daemon's default: the peer's own pose error too
    # --joint: one inter edge per colony edge lidar-1's graph recorded (or none found in the map)
    colony = got["lidar_with_depth_smoothed"]["edges"]["colony"]
    for key in ("joint_smoothed", "joint_smoothed@alone"):
        solved = got[key]
        assert solved["inter"] + solved["unmatched"] == colony, key
        assert 0.0 <= solved["lidar"] < 0.5 and 0.0 <= solved["depth"] < 0.5, key
        assert solved["cost"][1] <= solved["cost"][0] + 1e-6, key
    assert got["joint_smoothed"]["inter"] > 0  # seed 1: lidar-1 fuses depth-1's map in 3 s
    # --joint-weighting: the same edges, the covariances scaled by the factors found
    weighted = got["joint_smoothed@cell-vce"]
    assert weighted["inter"] == got["joint_smoothed"]["inter"]
    assert 0.0 <= weighted["lidar"] < 0.5 and 0.0 <= weighted["depth"] < 0.5
    assert set(weighted["factors"]) == {"robot", "peer", "inter"}
    assert all(f > 0 for f in weighted["factors"].values()) and weighted["rounds"] >= 1
    assert "factors" not in got["joint_smoothed"]  # matcher: the covariances as they were
    assert json.loads(out.read_text().splitlines()[-1]) == got


def test_paper_offline_bounds_diagnostics_run_lidar_against_a_perfect_peer_map():
    got = main(
        [
            "--seed", "1", "--duration", "3", "--perfect-peer", "--lidar-only",
            "--relax", "none,nogate", "--contact", "0.5,0", "--profile", "1", "--keyframes", "60",
        ]
    )  # fmt: skip
    assert "depth_alone" not in got and "depth_with_lidar" not in got  # no estimator for depth-1
    keys = ("lidar_with_depth", "lidar_with_depth@nogate@0.5", "lidar_with_depth@none@0")
    for key in (*keys, "lidar_with_depth@nogate@0"):
        assert 0.0 <= got[key] < 0.5, key
    # from the start, every scan but the first was tried against the peer's map
    assert sum(got["lidar_counts@none@0"].values()) == 29
    assert sum(got["lidar_counts"].values()) == 15
    assert not got["lidar_counts@nogate@0"]["colony_rejected"]  # ungated: nothing refused
    rows = got["lidar_alone_profile"]
    assert [r[0] for r in rows] == [0.0, 1.0, 2.0]
    assert all(len(r) == 7 and r[3] >= 0.0 for r in rows)
    assert got["keyframes"] == 60 and got["perfect_peer"] is True


def test_paper_offline_runs_in_the_sparse_hall_with_the_peers_map_as_centres_and_means():
    args = ["--seed", "1", "--duration", "2", "--world", "hall", "--lidar-only", "--offset-walk"]
    got = main([*args, "--peer-points", "centres,means"])
    assert got["world"] == "hall" and got["offset_walk"] is True  # the colony offset walks
    for key in ("lidar_alone", "depth_alone", "lidar_with_depth", "lidar_with_depth@means"):
        assert 0.0 <= got[key] < 0.5, key
    for key in ("lidar_counts", "lidar_counts@means"):  # from mid-path, against depth-1's map
        assert sum(got[key].values()) > 0, key
    assert got["peer_points"] == ["centres", "means"]


def test_paper_offline_scores_the_smoothed_trajectory_too():
    args = ["--seed", "1", "--duration", "3", "--lidar-only", "--perfect-peer", "--smooth"]
    got = main([*args, "--exact-alignment", "--profile", "1"])
    assert got["smooth"] is True
    for run in ("lidar_alone", "lidar_with_depth"):
        smoothed = got[f"{run}_smoothed"]
        assert 0.0 <= smoothed["ate"] < 0.5 and smoothed["cpu_s"] >= 0.0, run
        assert smoothed["edges"]["odometry"] == 29  # 30 frames: one node each
        assert smoothed["cost"][1] <= smoothed["cost"][0] + 1e-6, run  # the solve lowers it
        assert [r[0] for r in got[f"{run}_smoothed_profile"]] == [0.0, 1.0, 2.0]
    assert got["lidar_alone_smoothed"]["offset"] is None  # alone: no colony offset
    colony = got["lidar_with_depth_smoothed"]["edges"]["colony"]
    assert colony == got["lidar_counts"]["colony_accepted"]  # one edge per fused colony match


def test_paper_offline_walks_by_the_peers_drift_and_widens_depth_1s_own_matches():
    from voxel.localisation.drift import CAP, FLOOR

    args = ["--seed", "1", "--duration", "4", "--peer-walk", "--own-aliasing", "0.042"]
    got = main(args)
    assert got["peer_walk"] is True and got["own_aliasing"] == 0.042
    for key in ("lidar_peer_walk", "depth_peer_walk"):
        walks = got[key]
        assert len(walks) == 2  # the first cut's and the last's
        for walk in walks:  # None while the peer's path is under 2 m, else within the bounds
            assert walk is None or (
                FLOOR.trans <= walk[0] <= CAP.trans and FLOOR.yaw <= walk[1] <= CAP.yaw
            )
    assert 0.0 <= got["lidar_with_depth"] < 0.5 and 0.0 <= got["depth_with_lidar"] < 0.5
