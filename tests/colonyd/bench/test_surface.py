"""The harness prototype of the surface channel: the mean hit point per voxel, and the offline
harnesses' `--peer-points` option."""

from __future__ import annotations

import numpy as np
import pytest

from colonyd.bench import cctv_offline, paper_offline
from colonyd.bench.surface import SurfaceMeans
from colonyd.mapping import integrate_observation
from plugins.observation import Observation
from voxel import keys as vk
from voxel.grid import VoxelGrid
from voxel.sensor import SensorModel


def test_means_of_known_points_over_two_scans_and_centres_where_no_hit():
    surface = SurfaceMeans(0.1)
    origin = np.zeros(3)
    first = np.array([[0.51, 0.22, 0.05], [0.57, 0.28, 0.07], [9.0, 0.0, 0.0], [np.nan, 0, 0]])
    assert surface.add(first, origin, max_range=5.0) == 2  # beyond range and NaN: no hit
    assert surface.add(np.array([[0.53, 0.21, 0.03], [-0.31, 0.44, 0.15]]), origin) == 2
    keys = np.array([[5, 2, 0], [-4, 4, 1], [7, 7, 7]])
    got = surface.points(keys)
    # three hits in two scans: each scan one sample, its points' mean (as the grid's channel)
    np.testing.assert_allclose(got[0], [(0.54 + 0.53) / 2, (0.25 + 0.21) / 2, (0.06 + 0.03) / 2])
    np.testing.assert_allclose(got[1], [-0.31, 0.44, 0.15])
    np.testing.assert_allclose(got[2], [0.75, 0.75, 0.75])  # no hit: its centre
    assert len(surface) == 2


def test_means_are_of_the_hits_the_grid_saw_at_the_given_pose():
    rng = np.random.default_rng(3)
    pts = rng.uniform(-2.0, 2.0, (500, 3))
    no_return = np.zeros(500, bool)
    no_return[:50] = True  # no return: cleared, not hit
    pose = np.eye(4)
    pose[:3, 3] = [1.0, -0.5, 0.2]
    obs = Observation("lidar", 1.0, pts, pose, no_return=no_return)
    sensor = SensorModel(max_range=3.0)
    grid, surface = VoxelGrid(0.1), SurfaceMeans(0.1)
    integrate_observation(grid, obs, sensor=sensor, reliability=1.0)
    surface.add_observation(obs, obs.pose, sensor)
    world = obs.points_world()[50:]
    near = np.linalg.norm(world - pose[:3, 3], axis=1) <= 3.0
    hit = np.unique(vk.points_to_keys(world[near], 0.1), axis=0)
    assert len(surface) == len(hit)
    occupied = grid.occupied_keys()
    means = surface.points(occupied)
    # each occupied voxel's mean lies inside it (not its centre: a few random points each)
    assert np.array_equal(vk.points_to_keys(means, 0.1), occupied)
    assert not np.allclose(means, vk.keys_to_centers(occupied, 0.1))


@pytest.mark.parametrize("main", [paper_offline.main, cctv_offline.main])
def test_peer_points_is_validated(main, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--peer-points", "centres,surface"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "--peer-points" in err and "'centres', 'means'" in err and "surface" in err
