"""ICP, the restricted rigid fit, transforms and covariance on exact constructed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from voxel.registration.icp import covariance, fit_rigid, icp, normals
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
