"""Planar EKF: a landmark's error estimated in the state is counted once, however often it is
seen; published moves and growth are accounted; the bound holds; bad input is refused."""

from __future__ import annotations

import math

import numpy as np
import pytest

from voxel.errors import LocalisationError
from voxel.localisation.ekf import PlanarEkf

#: The landmark's published position is 0.3 m off in x, claimed to 0.1 m; each sighting is
#: good to 2 cm. The robot stands at the origin facing +x; its heading is known.
TRUE_LM = np.array([3.0, 0.0])
PUBLISHED = np.array([3.3, 0.0])
C = 0.1**2
R = 0.02**2
P = 1.0  # the pose's prior variance in x and y


def _robot() -> PlanarEkf:
    return PlanarEkf(np.zeros(3), covariance=np.diag([P, P, 1e-12]))


def _sight(f: PlanarEkf, times: int, key: int | None, published: np.ndarray = PUBLISHED) -> None:
    seen = TRUE_LM - np.zeros(2)  # the truth seen from the true pose, heading 0: body = world
    for _ in range(times):
        assert f.update_landmark(seen, np.eye(2) * R, published, np.eye(2) * C, key=key)


def test_fifty_sightings_of_one_wrong_landmark_move_the_pose_as_one_prior_allows() -> None:
    # Heading known, the measurement is linear: position + error = published - seen. Counted
    # once, N sightings are one measurement of the landmark with noise C + R/N.
    once, independent = _robot(), _robot()
    _sight(once, 50, key=7)
    _sight(independent, 50, key=None)
    noise = C + R / 50
    gain = P / (P + noise)
    np.testing.assert_allclose(once.pose[:2], [0.3 * gain, 0.0], atol=1e-4)
    np.testing.assert_allclose(np.diag(once.covariance)[:2], P * noise / (P + noise), rtol=1e-3)
    # its claim stays near the landmark's own (0.1 m), not below: the 0.3 m error is 3 sd
    assert math.sqrt(once.covariance[0, 0]) > 0.099
    # independently, 50 sightings claim sqrt((C + R) / 50) = 1.4 cm and follow the landmark
    assert independent.pose[0] == pytest.approx(0.3, abs=2e-3)
    assert math.sqrt(independent.covariance[0, 0]) < 0.015
    # the error's estimate is what the pose did not take
    _, error, cov = once.landmark(7)
    np.testing.assert_allclose(error + once.pose[:2], [0.3, 0.0], atol=1e-4)
    assert cov.shape == (2, 2)
    assert once.landmarks == [7]


def test_two_landmarks_with_their_own_errors_do_reduce_it() -> None:
    f = _robot()
    other_truth = np.array([0.0, 3.0])
    for _ in range(20):
        assert f.update_landmark(TRUE_LM, np.eye(2) * R, PUBLISHED, np.eye(2) * C, key=1)
        seen = np.array([other_truth[0], other_truth[1]])
        assert f.update_landmark(seen, np.eye(2) * R, other_truth, np.eye(2) * C, key=2)
    noise = C + R / 20  # each landmark, counted once, measures position + its error
    np.testing.assert_allclose(np.diag(f.covariance)[:2], 1.0 / (1.0 / P + 2.0 / noise), rtol=1e-3)
    # x: the wrong one (0.3 m off) and the right one averaged: half the pull
    assert f.pose[0] == pytest.approx(0.3 * (1.0 / noise) / (1.0 / P + 2.0 / noise), abs=1e-4)
    assert sorted(f.landmarks) == [1, 2]


def test_a_moved_published_position_shifts_the_error_not_the_pose() -> None:
    a, b = _robot(), _robot()
    _sight(a, 5, key=3)
    _sight(b, 5, key=3)
    moved = PUBLISHED + np.array([0.2, -0.1])  # the peer refined it (or our alignment moved)
    _sight(a, 1, key=3)
    _sight(b, 1, key=3, published=moved)
    np.testing.assert_allclose(b.pose, a.pose, atol=1e-12)
    np.testing.assert_allclose(b.covariance, a.covariance, atol=1e-12)
    np.testing.assert_allclose(b.landmark(3)[1], a.landmark(3)[1] + [0.2, -0.1], atol=1e-12)
    np.testing.assert_allclose(b.landmark(3)[0], moved)


def test_a_grown_published_covariance_widens_and_a_smaller_one_does_not_shrink() -> None:
    # The pose known exactly: each sighting measures the error alone, c' = c R / (c + R).
    f = PlanarEkf(np.zeros(3), covariance=np.eye(3) * 1e-14)
    seen, key = TRUE_LM, 5
    assert f.update_landmark(seen, np.eye(2) * R, PUBLISHED, np.eye(2) * C, key=key)
    c1 = C * R / (C + R)
    np.testing.assert_allclose(f.landmark(key)[2], np.eye(2) * c1, rtol=1e-6)
    grown = np.diag([4 * C, C])  # grew by 3C in x only
    assert f.update_landmark(seen, np.eye(2) * R, PUBLISHED, grown, key=key)
    cx = (c1 + 3 * C) * R / (c1 + 3 * C + R)
    np.testing.assert_allclose(np.diag(f.landmark(key)[2]), [cx, c1 * R / (c1 + R)], rtol=1e-6)
    before = np.diag(f.landmark(key)[2])
    assert f.update_landmark(seen, np.eye(2) * R, PUBLISHED, np.eye(2) * C * 0.01, key=key)
    after = np.diag(f.landmark(key)[2])
    np.testing.assert_allclose(after, before * R / (before + R), rtol=1e-6)  # a plain update


def test_the_least_recently_seen_landmark_is_dropped_beyond_the_bound() -> None:
    f = _robot()
    f.max_landmarks = 2
    for key in (1, 2, 1, 3):  # 2 is the least recently seen when 3 arrives
        assert f.update_landmark(TRUE_LM, np.eye(2) * R, TRUE_LM, np.eye(2) * C, key=key)
    assert f.landmarks == [1, 3]
    # 2 seen again: a new landmark with its published prior; 1 is now the oldest
    assert f.update_landmark(TRUE_LM, np.eye(2) * R, TRUE_LM, np.eye(2) * C, key=2)
    assert f.landmarks == [3, 2]
    np.testing.assert_allclose(f.landmark(2)[1], 0.0, atol=0.05)


def test_a_first_sighting_gated_out_leaves_nothing() -> None:
    f = PlanarEkf(np.zeros(3), covariance=np.diag([1e-4, 1e-4, 1e-6]))
    assert not f.update_landmark(
        TRUE_LM, np.eye(2) * 1e-4, TRUE_LM + np.array([2.0, 0.0]), np.eye(2) * 1e-4, key=9
    )
    assert f.landmarks == []
    np.testing.assert_allclose(f.pose, 0.0)


def test_keyframes_and_an_offset_keep_their_rows_beside_landmarks() -> None:
    f = PlanarEkf(np.zeros(3), covariance=np.diag([0.01, 0.01, 1e-4]))
    f.add_keyframe(0)
    far = TRUE_LM + np.array([4.0, 0.0])  # published 4 m off: an error beyond pi, not a yaw
    assert f.update_landmark(TRUE_LM, np.eye(2) * R, far, np.eye(2) * 16.0, key=4, gate=None)
    published, error, cov = f.landmark(4)
    f.predict(np.array([0.1, 0.0, 0.0]))
    f.add_keyframe(1)
    p = f.covariance
    f.reset_offset(np.eye(3) * 1e-4)
    _, key_error, key_cov = f.keyframe(1)
    np.testing.assert_allclose(key_error, 0.0)
    np.testing.assert_allclose(key_cov, p)  # the pose's, as placed
    np.testing.assert_allclose(f.landmark(4)[1], error)
    np.testing.assert_allclose(f.landmark(4)[2], cov)
    assert error[0] > math.pi  # not wrapped as an angle
    assert f.update_relative(f.pose, np.eye(3) * 1e-4, np.array([1]), np.eye(3)[None])
    assert f.update_offset(f.pose, np.eye(3) * 1e-4)
    assert f.landmark(4)[1][0] > math.pi
    f.keep_keyframes([1])
    assert f.keyframes == [1]
    np.testing.assert_allclose(f.keyframe(1)[2], f.keyframe(1)[2].T)
    assert f.landmarks == [4]
    assert f.update_landmark(TRUE_LM, np.eye(2) * R, far, np.eye(2) * 16.0, key=4, gate=None)
    np.testing.assert_allclose(f.landmark(4)[0], published)


@pytest.mark.parametrize(
    ("seen", "seen_cov", "landmark", "landmark_cov", "message"),
    [
        (np.zeros(3), np.eye(2), np.zeros(2), np.eye(2), r"expected finite .* shapes \(3,\)"),
        (np.zeros(2), np.eye(2), np.array([np.nan, 0.0]), np.eye(2), "expected finite"),
        (np.zeros(2), np.eye(3), np.zeros(2), np.eye(2), r"2x2 covariances"),
        (np.zeros(2), np.eye(2), np.zeros(2), -np.eye(2), "landmark's covariance: .* eigenvalue"),
        (np.zeros(2), [[1, 2], [0, 1]], np.zeros(2), np.eye(2), "sighting's covariance: .* sym"),
    ],
)
def test_bad_landmark_input_says_what_was_expected(
    seen: np.ndarray,
    seen_cov: np.ndarray,
    landmark: np.ndarray,
    landmark_cov: np.ndarray,
    message: str,
) -> None:
    f = PlanarEkf(np.zeros(3))
    with pytest.raises(LocalisationError, match=message):
        f.update_landmark(seen, seen_cov, landmark, landmark_cov, key=1)
    assert f.landmarks == []
