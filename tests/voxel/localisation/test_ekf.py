"""Planar EKF: prediction follows the motion model, updates weigh by covariance, the gate rejects
outliers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from voxel.errors import LocalisationError
from voxel.localisation.ekf import MotionNoise, PlanarEkf


def test_predict_composes_the_increment_and_grows_the_covariance() -> None:
    f = PlanarEkf(np.array([1.0, 2.0, math.pi / 2]))
    f.predict(np.array([1.0, 0.0, 0.0]))
    np.testing.assert_allclose(f.pose, [1.0, 3.0, math.pi / 2], atol=1e-12)
    f.predict(np.array([0.0, 0.0, math.pi]))
    assert f.pose[2] == pytest.approx(-math.pi / 2)  # wrapped
    p1 = f.covariance
    f.predict(np.array([1.0, 0.0, 0.0]))
    assert np.all(np.diag(f.covariance) > np.diag(p1))
    # moving along -y (heading -pi/2): uncertainty in heading shows up in x
    assert f.covariance[0, 0] > f.covariance[1, 1]


def test_no_odometry_widens_by_the_configured_amount() -> None:
    f = PlanarEkf(np.zeros(3), motion=MotionNoise(no_odometry=0.5))
    f.predict(None)
    np.testing.assert_allclose(f.pose, 0.0)
    np.testing.assert_allclose(np.diag(f.covariance), 0.25 + 1e-6)


def test_update_with_equal_covariance_lands_halfway_and_wraps() -> None:
    f = PlanarEkf(np.array([0.0, 0.0, math.pi - 0.05]), covariance=np.eye(3) * 0.01)
    assert f.update(np.array([0.2, -0.2, -math.pi + 0.05]), np.eye(3) * 0.01)
    np.testing.assert_allclose(f.pose[:2], [0.1, -0.1], atol=1e-9)
    assert abs(f.pose[2]) == pytest.approx(
        math.pi, abs=1e-9
    )  # halfway across the wrap, not through 0
    np.testing.assert_allclose(f.covariance, np.eye(3) * 0.005, atol=1e-12)


def test_gate_rejects_an_outlier_and_keeps_the_state() -> None:
    f = PlanarEkf(np.zeros(3), covariance=np.eye(3) * 1e-4)
    assert not f.update(np.array([1.0, 0.0, 0.0]), np.eye(3) * 1e-4)
    np.testing.assert_allclose(f.pose, 0.0)
    assert (f.accepted, f.rejected) == (0, 1)
    assert f.update(np.array([1.0, 0.0, 0.0]), np.eye(3) * 1e-4, gate=None)


def test_errors_say_what_was_expected() -> None:
    f = PlanarEkf(np.zeros(3))
    with pytest.raises(LocalisationError, match=r"expected 3 finite numbers \(dx, dy, dyaw\)"):
        f.predict(np.array([np.nan, 0.0, 0.0]))
    with pytest.raises(LocalisationError, match=r"finite 3x3 covariance, found .* shape \(2, 2\)"):
        f.update(np.zeros(3), np.eye(2))
