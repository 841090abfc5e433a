"""ICP, the restricted rigid fit, transforms and covariance on exact constructed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from voxel.registration.icp import Nearest, covariance, fit_rigid, icp, normals
from voxel.registration.transform import apply, euler, rigid, wrap_angle


def test_euler_round_trip_and_wrap() -> None:
    t = rigid(1.0, -2.0, 3.0, roll=0.1, pitch=-0.2, yaw=2.5)
    assert euler(t) == pytest.approx((0.1, -0.2, 2.5))
    assert float(wrap_angle(3 * math.pi)) == pytest.approx(-math.pi)


@pytest.mark.parametrize("dof", [3, 4, 6])
def test_fit_rigid_recovers_a_transform_within_its_degrees_of_freedom(dof: int) -> None:
    p = np.random.default_rng(1).uniform(-5, 5, (200, 3))
    truth = {
        3: rigid(1.0, 2.0, 0.0, yaw=0.7),
        4: rigid(1.0, 2.0, -0.5, yaw=-2.0),
        6: rigid(1.0, 2.0, 0.3, roll=0.2, pitch=-0.1, yaw=1.0),
    }[dof]
    np.testing.assert_allclose(fit_rigid(p, apply(truth, p), dof), truth, atol=1e-9)


def test_icp_converges_from_a_nearby_pose_and_keeps_z_in_3_dof() -> None:
    rng = np.random.default_rng(2)
    target = rng.uniform(-5, 5, (3000, 3))
    truth = rigid(0.15, -0.1, 0.0, yaw=0.03)
    source = apply(np.linalg.inv(truth), target[:1500])
    fit = icp(source, cKDTree(target), target, np.eye(4), 3, start_m=0.5, end_m=0.05)
    np.testing.assert_allclose(fit.transform, truth, atol=1e-6)
    assert fit.rmse < 1e-6 and fit.matched == 1500


def test_covariance_is_small_on_a_corner_and_huge_along_a_corridor() -> None:
    x = np.linspace(0, 10, 101)
    wall = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    corridor = np.concatenate([wall, wall + np.array([0.0, 2.0, 0.0])])
    corner = np.concatenate([wall, wall[:, [1, 0, 2]]])
    for cloud, degenerate in ((corner, False), (corridor, True)):
        tree = cKDTree(cloud)
        n = normals(cloud, tree, cloud, planar_map=True)
        noisy = cloud + np.random.default_rng(3).normal(0, 0.01, cloud.shape) * n
        cov, names = covariance(noisy, cloud, n, 3)
        assert names == ["x", "y", "yaw"]
        assert bool(cov[0, 0] > 1.0) is degenerate
        assert cov[1, 1] < 1e-4


def test_nearest_answers_exactly_as_the_tree_while_points_move() -> None:
    """Nearest reuses look-ups between small moves; every answer (distances and indices, bit for
    bit) is the tree's own, through large and small moves, a shrinking limit and ties (points
    midway between two voxel centres)."""

    class Counting(cKDTree):  # type: ignore[misc]
        looked_up = 0

        def query(self, x: np.ndarray, *args: object, **kwargs: object) -> object:
            Counting.looked_up += len(x)
            return super().query(x, *args, **kwargs)

    rng = np.random.default_rng(3)
    target = np.unique(np.floor(rng.uniform(0, 6, (3000, 3)) / 0.2), axis=0) * 0.2 + 0.1
    tree, counted = cKDTree(target), Counting(target)
    start = np.concatenate([rng.uniform(0, 6, (1500, 3)), target[:300] + np.array([0.1, 0.0, 0.0])])
    nearest = Nearest(counted, target)
    points = start
    for step in range(24):
        move = rigid(*rng.normal(0, 0.3 if step < 4 else 0.002, 3), yaw=rng.normal(0, 0.002))
        points = start if step in (0, 12) else apply(move, points)
        limit = 0.4 * 0.97**step
        expected_d, expected_i = tree.query(points, distance_upper_bound=limit)
        d, i = nearest.query(points, limit)
        assert np.array_equal(d, expected_d) and np.array_equal(i, expected_i), step
    # the reuse did happen: small moves leave most points' neighbours as they were
    assert Counting.looked_up < 0.5 * 24 * len(start)


def test_icp_equals_a_plain_tree_query_loop() -> None:
    """icp with Nearest returns what ICP with a look-up of every point at every iteration does."""
    rng = np.random.default_rng(4)
    target = np.unique(np.floor(rng.uniform(0, 8, (6000, 3)) / 0.1), axis=0) * 0.1 + 0.05
    tree = cKDTree(target)
    source = apply(rigid(0.15, -0.1, 0.05, yaw=0.03), target[rng.choice(len(target), 800)])
    init = np.eye(4)
    t = init.copy()
    for it in range(1, 25):
        limit = 0.1 if it > 12 else 0.4 * (0.1 / 0.4) ** ((it - 1) / 12)
        moved = apply(t, source)
        d, idx = tree.query(moved, distance_upper_bound=limit)
        ok = np.isfinite(d)
        step = fit_rigid(moved[ok], target[idx[ok]], 4)
        t = step @ t
        shift = float(
            np.max(
                np.linalg.norm(
                    apply(step, moved[ok][:: max(1, int(ok.sum()) // 200)])
                    - moved[ok][:: max(1, int(ok.sum()) // 200)],
                    axis=1,
                )
            )
        )
        if it > 12 and shift < 1e-4:
            break
    got = icp(source, tree, target, init, 4, start_m=0.4, end_m=0.1, iterations=24)
    assert np.array_equal(got.transform, t) and got.iterations == it
