"""Frame error: a transform's error moved to a point, to another centre and between frames, and
an alignment's honest covariance from its residuals, checked against known answers and sampling."""

from __future__ import annotations

import math

import numpy as np
import pytest

from voxel.errors import LocalisationError
from voxel.localisation import frame_error


def _rigid(x: float, y: float, yaw: float) -> np.ndarray:
    t = np.eye(4)
    t[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    t[:2, 3] = (x, y)
    return t


def test_a_yaw_error_moves_a_far_pose_by_its_lever() -> None:
    yaw_only = np.diag([0.0, 0.0, 0.01**2])
    at = frame_error.at(yaw_only, np.array([3.0, 4.0]))
    # a rotation by e about the origin moves (3, 4) by e * (-4, 3)
    np.testing.assert_allclose(at, 1e-4 * np.array([[16, -12, -4], [-12, 9, 3], [-4, 3, 1]]))
    about = frame_error.about(yaw_only, np.array([5.0, 0.0]))  # rotating about (5, 0)
    np.testing.assert_allclose(np.diag(about), [0.0, 25e-4, 1e-4])
    # the same error, seen at its own centre, has no translation
    np.testing.assert_allclose(frame_error.at(about, np.array([5.0, 0.0]))[:2, :2], 0, atol=1e-15)
    with pytest.raises(LocalisationError, match="finite 3x3"):
        frame_error.at(np.eye(2), np.zeros(2))


def test_an_error_moved_between_frames_matches_sampling() -> None:
    rng = np.random.default_rng(1)
    t = _rigid(2.0, -3.0, 0.7)  # takes B's points into A's
    cov_b = np.array([[4e-4, 1e-4, 0.0], [1e-4, 1e-4, 0.0], [0.0, 0.0, 3e-5]])
    samples = rng.multivariate_normal(np.zeros(3), cov_b, 4000)
    seen = np.array(
        [frame_error.difference(t, t @ _rigid(*d)) for d in samples]  # t Exp(d): error in B
    )
    np.testing.assert_allclose(np.cov(seen.T), frame_error.moved(cov_b, t), atol=2e-5)


def test_an_alignments_covariance_is_its_residual_not_residual_over_root_n() -> None:
    fit = np.diag([1e-8, 4e-8, 1e-9])  # a least-squares fit of thousands of pairs
    cov = frame_error.from_residuals(fit, 0.05, np.zeros(2))
    assert math.sqrt(cov[0, 0]) == pytest.approx(math.hypot(0.05, 0.01))  # rmse, plus the floor
    assert math.sqrt(cov[1, 1]) == pytest.approx(math.hypot(0.1, 0.01))  # the fit's shape kept
    scattered = frame_error.from_residuals(fit, 0.05, np.zeros(2), np.array([0.0, 0.0, 0.02]))
    assert scattered[2, 2] == pytest.approx(cov[2, 2] + 0.02**2)
    assert np.all(np.diag(frame_error.from_residuals(fit, 0.0, np.zeros(2))) > 0)  # the floor
    np.testing.assert_allclose(
        np.diag(frame_error.floored(np.zeros((3, 3)))), np.diag(frame_error.FLOOR)
    )
    with pytest.raises(LocalisationError, match="residual >= 0"):
        frame_error.from_residuals(fit, math.nan, np.zeros(2))


def test_a_matrix_that_is_nearly_a_covariance_is_made_one() -> None:
    good = np.diag([0.01, 0.04, 1e-4])
    np.testing.assert_array_equal(frame_error.positive(good), good)  # a covariance: unchanged
    # eigenvalues 0.024 and -0.004 along (1, 1) and (1, -1): the negative one raised to zero
    bad = np.array([[0.01, 0.014, 0.0], [0.014, 0.01, 0.0], [0.0, 0.0, 1e-4]])
    want = np.array([[0.012, 0.012, 0.0], [0.012, 0.012, 0.0], [0.0, 0.0, 1e-4]])
    fixed = frame_error.positive(bad)
    np.testing.assert_allclose(fixed, want, atol=1e-15)
    assert np.linalg.eigvalsh(fixed).min() >= -1e-18
    with pytest.raises(LocalisationError, match="finite 3x3"):
        frame_error.positive(np.full((3, 3), np.inf))
