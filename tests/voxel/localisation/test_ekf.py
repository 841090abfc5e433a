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


def test_a_shared_maps_error_is_counted_once_however_often_it_is_matched() -> None:
    # Pose prior 2 cm, the map's error 20 cm a priori and truly 20 cm in x: every match reads
    # x = 0.2. Linear answer after n matches of variance r^2: x = 0.2 p^2 / (p^2 + b^2 + r^2/n),
    # so at most 0.2 * 0.02^2 / (0.02^2 + 0.2^2) = 2 mm, where independent updates move 20 cm.
    p, b, r = 0.02, 0.2, 0.01
    f = PlanarEkf(np.zeros(3), covariance=np.diag([p**2, p**2, 1e-6]))
    f.reset_offset(np.diag([b**2, b**2, 1e-6]))
    for _ in range(200):
        assert f.update_offset(np.array([0.2, 0.0, 0.0]), np.eye(3) * r**2)
    expected = 0.2 * p**2 / (p**2 + b**2 + r**2 / 200)
    assert f.pose[0] == pytest.approx(expected, rel=0.05)
    assert f.offset is not None and f.offset.value[0] == pytest.approx(0.2 - expected, rel=0.01)
    # Once the offset is known, an absolute fix of the pose moves the offset with it.
    f.update(np.array([0.05, 0.0, 0.0]), np.eye(3) * 1e-6)
    assert f.pose[0] == pytest.approx(0.05, abs=1e-3)
    assert f.offset.value[0] == pytest.approx(0.15, abs=0.01)
    # A map whose error is small against the pose's uncertainty pulls the pose onto it.
    g = PlanarEkf(np.zeros(3), covariance=np.diag([0.2**2, 0.2**2, 1e-6]))
    g.reset_offset(np.diag([0.01**2, 0.01**2, 1e-6]))
    assert g.update_offset(np.array([0.2, 0.0, 0.0]), np.eye(3) * r**2)
    assert g.pose[0] == pytest.approx(0.2 * 0.04 / (0.04 + 1e-4 + 1e-4), rel=1e-3)
    with pytest.raises(LocalisationError, match="reset_offset"):
        PlanarEkf(np.zeros(3)).update_offset(np.zeros(3), np.eye(3))


def test_an_offset_gate_refuses_a_map_far_beyond_both_errors() -> None:
    f = PlanarEkf(np.zeros(3), covariance=np.diag([1e-4, 1e-4, 1e-6]))
    f.reset_offset(np.diag([1e-4, 1e-4, 1e-6]))
    assert not f.update_offset(np.array([0.5, 0.0, 0.0]), np.eye(3) * 1e-4)
    np.testing.assert_allclose(f.pose, 0.0)
    assert f.rejected == 1


def test_a_landmark_seen_from_the_body_corrects_position_and_heading() -> None:
    # True pose (1, 2, 90 deg); a landmark known at (1, 5): seen 3 m straight ahead.
    truth = np.array([1.0, 2.0, math.pi / 2])
    landmark = np.array([1.0, 5.0])
    seen = np.array([3.0, 0.0])
    f = PlanarEkf(np.array([1.2, 2.0, math.pi / 2]), covariance=np.diag([0.04, 0.04, 1e-6]))
    assert f.update_landmark(seen, np.eye(2) * 1e-6, landmark, np.eye(2) * 1e-6)
    # Known answer: the landmark fixes the position (heading known), x pulled back to 1.0
    np.testing.assert_allclose(f.pose, truth, atol=1e-3)
    # Heading unknown, position known: the bearing fixes it (landmark seen 3 deg to the left,
    # 5 cm noise: gain 0.01 * 9 / (0.01 * 9 + 0.0025) of the way)
    g = PlanarEkf(np.array([1.0, 2.0, math.pi / 2]), covariance=np.diag([1e-8, 1e-8, 0.01]))
    a = math.radians(3.0)
    seen_left = 3.0 * np.array([math.cos(a), math.sin(a)])
    assert g.update_landmark(seen_left, np.eye(2) * 0.05**2, landmark, np.eye(2) * 1e-6)
    assert g.pose[2] == pytest.approx(math.pi / 2 - a * 0.09 / 0.0925, abs=1e-3)
    # A landmark's own uncertainty weighs: known to 20 cm, a 20 cm disagreement moves x by half
    h = PlanarEkf(np.array([1.2, 2.0, math.pi / 2]), covariance=np.diag([0.04, 0.04, 1e-6]))
    assert h.update_landmark(seen, np.eye(2) * 1e-6, landmark, np.eye(2) * 0.04)
    assert h.pose[0] == pytest.approx(1.1, abs=2e-3)


def test_a_landmark_far_from_where_it_should_be_is_gated_out() -> None:
    f = PlanarEkf(np.array([1.0, 2.0, 0.0]), covariance=np.diag([1e-4, 1e-4, 1e-6]))
    assert not f.update_landmark(
        np.array([3.0, 0.0]), np.eye(2) * 1e-4, np.array([5.0, 2.0]), np.eye(2) * 1e-4
    )
    np.testing.assert_allclose(f.pose, [1.0, 2.0, 0.0])
    with pytest.raises(LocalisationError, match="landmark: expected finite"):
        f.update_landmark(np.zeros(3), np.eye(2), np.zeros(2), np.eye(2))
