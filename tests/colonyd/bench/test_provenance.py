"""The harness's record of which steps hit each voxel (`--joint`), and the steps that stand for
a match."""

from __future__ import annotations

import numpy as np
import pytest

from colonyd.bench import paper_offline
from colonyd.bench.provenance import Provenance, quantile_steps
from plugins.observation import Observation
from voxel.sensor import SensorModel


def _scan(points: np.ndarray, x: float) -> tuple[Observation, np.ndarray]:
    pose = np.eye(4)
    pose[0, 3] = x
    return Observation("lidar", x, points, pose, no_return=np.array([False, False, True])), pose


def test_steps_near_weights_the_steps_that_hit_the_matched_cells():
    prov = Provenance(0.1)
    sensor = SensorModel(max_range=5.0)
    wall = np.array([[2.03, 0.04, 0.31], [2.03, 1.04, 0.31], [2.03, -1.0, 0.3]])  # last: no return
    for step in range(3):  # steps 0 and 2 see the wall's two cells, step 1 only the first
        pts = wall.copy()
        if step == 1:
            pts[1] = [9.0, 9.0, 0.3]  # beyond range: no hit
        obs, pose = _scan(pts, 0.0)
        assert prov.add_observation(obs, pose, sensor, step) == (1 if step == 1 else 2)
    # the scan matched on the first cell (twice) and the second (once); one point found nothing
    seen = np.array([[2.06, 0.02, 0.3], [2.01, 0.07, 0.3], [2.04, 1.01, 0.3], [5.0, 5.0, 0.3]])
    w = prov.steps_near(seen, height=0.3)
    # cell one: steps 0, 1, 2 each 1/3 per point (2 points); cell two: steps 0, 2 each 1/2
    np.testing.assert_allclose(w, [2 / 3 + 1 / 2, 2 / 3, 2 / 3 + 1 / 2])
    assert prov.steps_near(seen, height=1.5).sum() == 0  # out of the band: nothing
    assert prov.steps_near(seen[3:], height=0.3).sum() == 0


def test_a_steps_voxels_are_the_voxels_its_scan_hits_in_the_grid():
    """Provenance sorts a scan's beams as the grid does: a point at the sensor, a no-return and
    two beyond range hit nothing; the rest hit what the grid marks occupied."""
    from voxel.grid import VoxelGrid

    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(1.0, 4.0, 200), rng.uniform(-2, 2, 200), np.zeros(200)])
    pts[:4] = [[0.0, 7.0, 0.0], [0.0, 0.0, 0.0], [2.0, 0.5, 0.0], [9.0, 0.0, 0.0]]
    no_return = np.zeros(200, bool)
    no_return[2] = True
    obs = Observation("lidar", 1.0, pts, np.eye(4), no_return=no_return)
    sensor = SensorModel(max_range=5.0)
    grid = VoxelGrid(0.1)
    grid.integrate(obs.points_world(), obs.origin, time=1.0, sensor=sensor, no_return=no_return)
    hit = Provenance(0.1).add_observation(obs, np.eye(4), sensor, 0)
    assert hit == len(grid.occupied_keys()) == len(np.unique((pts[4:] // 0.1), axis=0))


def test_quantile_steps_stand_for_the_weight_along_the_steps():
    steps, w = quantile_steps(np.array([0.0, 3.0, 0.0, 0.0, 1.0]), 4)
    np.testing.assert_array_equal(steps, [1, 1, 1, 4])
    np.testing.assert_allclose(w, 0.25)
    assert len(quantile_steps(np.zeros(5), 4)[0]) == 0


def test_joint_needs_smooth_and_an_estimated_peer_map():
    with pytest.raises(SystemExit):
        paper_offline.main(["--joint"])
    with pytest.raises(SystemExit):
        paper_offline.main(["--joint", "--smooth", "--perfect-peer"])
