"""Planar EKF: prediction follows the motion model, updates weigh by covariance, the gate rejects
outliers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.shared import fresh_process
from voxel.errors import LocalisationError
from voxel.localisation.ekf import GATE_3DOF, MotionNoise, PlanarEkf


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


def test_a_shared_maps_error_that_grows_is_process_noise_and_never_shrinks() -> None:
    # The map's error is a random walk: when its sources say it is now known to b^2 + d (a peer
    # got lost) the filter adds Q = d to the offset's covariance, whatever it had learnt, and
    # keeps its mean and its correlation with the pose.
    p, b, r = 0.02, 0.1, 0.01
    f = PlanarEkf(np.zeros(3), covariance=np.diag([p**2, p**2, 1e-6]))
    prior = np.diag([b**2, b**2, 1e-6])
    f.reset_offset(prior)
    for _ in range(20):
        assert f.update_offset(np.array([0.03, 0.0, 0.0]), np.eye(3) * r**2)
    learnt = f.offset
    assert learnt is not None and learnt.covariance[0, 0] < b**2 / 4  # the matches taught it
    pose, cov = f.pose, f.covariance
    d = np.diag([0.05**2, 0.02**2, 1e-5])
    np.testing.assert_allclose(f.widen_offset(prior + d), d, atol=1e-15)
    widened = f.offset
    assert widened is not None
    np.testing.assert_allclose(widened.covariance, learnt.covariance + d, atol=1e-15)
    np.testing.assert_allclose(widened.accounted, prior + d, atol=1e-15)
    np.testing.assert_array_equal(widened.value, learnt.value)
    np.testing.assert_array_equal(widened.cross, learnt.cross)
    np.testing.assert_array_equal(f.pose, pose)
    np.testing.assert_array_equal(f.covariance, cov)
    # The peer is sure of itself again: no evidence that the map here improved, nothing changes;
    # the same covariance twice adds nothing; then only growth beyond the most accounted counts.
    assert not f.widen_offset(prior).any() and not f.widen_offset(prior + d).any()
    np.testing.assert_allclose(f.offset.covariance, widened.covariance, atol=1e-15)
    np.testing.assert_allclose(f.widen_offset(prior + 2 * d), d, atol=1e-15)
    # Growth in one direction and shrinking in another: only the positive part is added.
    g = PlanarEkf(np.zeros(3))
    g.reset_offset(np.diag([0.01, 0.04, 1e-4]))
    np.testing.assert_allclose(
        g.widen_offset(np.diag([0.04, 0.01, 1e-4])), np.diag([0.03, 0.0, 0.0]), atol=1e-15
    )
    # ... also when the growth is not along an axis: R diag(0.02, -0.02) R^T, R 45 degrees.
    h = PlanarEkf(np.zeros(3))
    h.reset_offset(np.diag([0.05, 0.05, 1e-4]))
    q = h.widen_offset(np.array([[0.05, 0.02, 0.0], [0.02, 0.05, 0.0], [0.0, 0.0, 1e-4]]))
    np.testing.assert_allclose(q[:2, :2], [[0.01, 0.01], [0.01, 0.01]], atol=1e-12)
    assert h.offset is not None
    np.testing.assert_allclose(h.offset.covariance[:2, :2], [[0.06, 0.01], [0.01, 0.06]])


def test_a_widened_offset_lets_a_disagreeing_map_move_the_pose_less() -> None:
    # Linear known answer (pose and offset uncorrelated, yaw 0 at the origin): one match of
    # variance r^2 moves the pose by p^2 / (p^2 + b^2 + q + r^2) of the disagreement once the
    # offset's prior b^2 was widened by q.
    p, b, q, r = 0.05, 0.05, 0.1**2, 0.01
    for widen, expected in (
        (0.0, p**2 / (p**2 + b**2 + r**2)),
        (q, p**2 / (p**2 + b**2 + q + r**2)),
    ):
        f = PlanarEkf(np.zeros(3), covariance=np.diag([p**2, p**2, 1e-6]))
        f.reset_offset(np.diag([b**2, b**2, 1e-6]))
        f.widen_offset(np.diag([b**2 + widen, b**2 + widen, 1e-6]))
        assert f.update_offset(np.array([0.1, 0.0, 0.0]), np.eye(3) * r**2)
        assert f.pose[0] == pytest.approx(0.1 * expected, rel=1e-9)


def test_an_offset_walk_is_a_turn_and_shift_about_the_agent_that_only_widens() -> None:
    # Offset mean zero, the agent at (4, 0): a turn d about the agent moves the map at the
    # origin by (0, -4 d), so the offset (about the origin) gains y variance 16 q_yaw and a
    # y-yaw covariance -4 q_yaw; mean, correlations, pose untouched.
    f = PlanarEkf(np.zeros(3), covariance=np.diag([1e-4, 1e-4, 1e-6]))
    with pytest.raises(LocalisationError, match="reset_offset"):
        f.walk_offset(np.eye(3), np.zeros(2))
    f.reset_offset(np.diag([0.01, 0.01, 1e-4]))
    assert f.update_offset(np.array([0.02, 0.0, 0.0]), np.eye(3) * 1e-4)
    before, pose, cov = f.offset, f.pose, f.covariance
    assert before is not None
    f.reset_offset(np.diag([0.01, 0.01, 1e-4]))  # mean zero again, for the known answer
    zero = f.offset
    assert zero is not None
    qx, qy, qa = 0.001, 0.002, 0.0001
    q = f.walk_offset(np.diag([qx, qy, qa]), np.array([4.0, 0.0]))
    expected = np.array([[qx, 0.0, 0.0], [0.0, qy + 16 * qa, -4 * qa], [0.0, -4 * qa, qa]])
    np.testing.assert_allclose(q, expected, atol=1e-15)
    after = f.offset
    assert after is not None
    np.testing.assert_allclose(after.covariance, zero.covariance + expected, atol=1e-15)
    np.testing.assert_array_equal(after.value, zero.value)
    np.testing.assert_array_equal(after.cross, zero.cross)
    np.testing.assert_array_equal(after.accounted, zero.accounted)  # widen_offset's, apart
    np.testing.assert_array_equal(f.pose, pose)
    np.testing.assert_array_equal(f.covariance, cov)
    for bad, about, says in (
        (np.diag([-1.0, 0.0, 0.0]), np.zeros(2), "semi-definite"),
        (np.eye(3), np.array([np.nan, 0.0]), "finite point"),
    ):
        with pytest.raises(LocalisationError, match=says):
            f.walk_offset(bad, about)


def test_a_walking_offset_learns_a_second_places_map_error_instead_of_dragging_the_pose() -> None:
    # A peer's map off by +6 cm in x at place A (x = 0) and by -4 cm at place B (x = 4 m). The
    # agent knows itself to 1 cm and its odometry is nearly exact (its own map holds it), so
    # the truth stays at the estimate. At A the offset learns +6 cm. At B, a rigid offset
    # (no walk) has pinned pose + offset to millimetres: the 10 cm disagreement is refused by
    # the gate, and without the gate goes into the pose. With the walk over the 4 m (6 cm of
    # standard deviation) the offset learns -4 cm and the pose stays within a centimetre.
    motion = MotionNoise(trans=0.002, rot=0.001, rot_per_m=0.001, still=1e-10)
    r = np.eye(3) * 0.01**2
    walk = np.diag([0.03**2, 0.03**2, 0.01**2]) * 4.0

    def at_b(walked: bool, gate: float | None) -> tuple[PlanarEkf, int, np.ndarray]:
        f = PlanarEkf(np.zeros(3), covariance=np.diag([1e-4, 1e-4, 1e-6]), motion=motion)
        f.reset_offset(np.diag([0.1**2, 0.1**2, 1e-4]))
        for _ in range(30):
            assert f.update_offset(np.array([0.06, 0.0, 0.0]), r)
        for _ in range(40):
            f.predict(np.array([0.1, 0.0, 0.0]))
        if walked:
            f.walk_offset(walk, f.pose[:2])
        arrived = f.pose
        fused = sum(
            f.update_offset(np.array([4.0 - 0.04, 0.0, 0.0]), r, gate=gate) for _ in range(20)
        )
        return f, fused, arrived

    rigid, fused, arrived = at_b(walked=False, gate=GATE_3DOF)
    assert fused == 0 and abs(arrived[0] - 4.0) < 0.001
    np.testing.assert_array_equal(rigid.pose, arrived)
    dragged, _, _ = at_b(walked=False, gate=None)
    assert dragged.pose[0] < 4.0 - 0.05  # most of the 10 cm went into the pose
    walked, fused, _ = at_b(walked=True, gate=GATE_3DOF)
    offset = walked.offset
    assert fused == 20 and offset is not None
    assert abs(walked.pose[0] - 4.0) < 0.01
    assert offset.value[0] == pytest.approx(-0.04, abs=0.01)


def test_an_offset_covariance_that_is_not_one_is_refused_and_changes_nothing() -> None:
    f = PlanarEkf(np.zeros(3))
    with pytest.raises(LocalisationError, match="reset_offset"):
        f.widen_offset(np.eye(3))
    f.reset_offset(np.eye(3) * 0.01)
    before = f.offset
    for bad, says in (
        (np.full((3, 3), np.nan), "finite 3x3"),
        (np.eye(2), r"finite 3x3 covariance, found shape \(2, 2\)"),
        (np.array([[0.01, 0.005, 0.0], [0.0, 0.01, 0.0], [0.0, 0.0, 0.01]]), "symmetric"),
        (np.array([[0.01, 0.1, 0.0], [0.1, 0.01, 0.0], [0.0, 0.0, 0.01]]), "semi-definite"),
        (np.diag([-1.0, 0.01, 0.01]), "semi-definite"),
    ):
        with pytest.raises(LocalisationError, match=says):
            f.widen_offset(bad)
        with pytest.raises(LocalisationError, match=says):
            PlanarEkf(np.zeros(3)).reset_offset(bad)
    after = f.offset
    assert before is not None and after is not None
    np.testing.assert_array_equal(after.covariance, before.covariance)
    np.testing.assert_array_equal(after.accounted, before.accounted)
    f.widen_offset(np.eye(3) * 0.01 + 1e-12 * np.triu(np.ones((3, 3)), 1))  # rounding: kept


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


def _walk(f: PlanarEkf, steps: int, key_every: int, first_key: int = 0) -> list[int]:
    """Drive `f` straight along x by 0.1 m steps, a keyframe every `key_every` steps, every step
    matched (exactly, 1 cm) against the newest keyframe only. The keyframes' ids."""
    keys = [first_key]
    f.add_keyframe(first_key)
    for i in range(1, steps + 1):
        f.predict(np.array([0.1, 0.0, 0.0]))
        info = np.eye(3)[None]
        assert f.update_relative(f.pose, np.eye(3) * 1e-4, np.array([keys[-1]]), info)
        if i % key_every == 0:
            keys.append(first_key + len(keys))
            f.add_keyframe(keys[-1])
    return keys


def test_own_map_matches_measure_the_error_grown_since_the_keyframe() -> None:
    # Known answer (one keyframe, no turn, its heading known so that no lever mixes): the
    # keyframe's error is the pose's at its time (P_ref), odometry adds Q, and a match against
    # it measures only the growth: the covariance becomes P_ref + (Q^-1 + R^-1)^-1, never
    # below what the keyframe had.
    p_ref = np.diag([0.01, 0.02, 0.0])
    f = PlanarEkf(np.zeros(3), covariance=p_ref, motion=MotionNoise(rot=0.0, rot_per_m=0.0))
    f.add_keyframe(0)
    f.predict(np.array([1.0, 0.0, 0.0]))
    q = f.covariance - p_ref
    r = np.diag([1e-4, 4e-4, 1e-6])
    assert f.update_relative(np.array([1.05, 0.0, 0.0]), r, np.array([0]), np.eye(3)[None])
    np.testing.assert_allclose(
        f.covariance, p_ref + np.linalg.inv(np.linalg.inv(q) + np.linalg.inv(r)), atol=1e-9
    )
    # The pose moves by the growth's share of the disagreement.
    gain = q[0, 0] / (q[0, 0] + r[0, 0])
    assert f.pose[0] == pytest.approx(1.0 + 0.05 * gain, abs=1e-9)


def test_own_map_alone_lets_the_covariance_grow_like_odometry() -> None:
    f = PlanarEkf(np.zeros(3))
    _walk(f, 50, key_every=3)
    at_5m = f.covariance
    _walk(f, 50, key_every=3, first_key=100)
    at_10m = f.covariance
    # Absolute fusion would hold it at ~1 cm^2 / n; relative, it grows with the distance driven.
    assert at_5m[1, 1] > 1e-3  # over 3 cm across the path after 5 m
    assert at_10m[1, 1] > 1.5 * at_5m[1, 1]
    assert at_10m[2, 2] > at_5m[2, 2] > 1e-4


def test_a_revisit_of_an_old_keyframe_closes_the_loop() -> None:
    f = PlanarEkf(np.zeros(3), covariance=np.diag([1e-4, 1e-4, 1e-6]))
    keys = _walk(f, 60, key_every=3)
    before = f.covariance
    assert before[1, 1] > 0.01  # > 10 cm after 6 m of own-map matches
    # Back near the start (same heading, drifted 0.3 m in y), a match against the first
    # keyframe alone: the pose is pulled onto it and the covariance shrinks to about the
    # keyframe's own plus the match's.
    f.kf.x = np.array([[0.2], [0.3], [0.0]])
    assert f.update_relative(
        np.array([0.2, 0.0, 0.0]), np.eye(3) * 1e-4, np.array([keys[0]]), np.eye(3)[None], gate=None
    )
    assert abs(f.pose[1]) < 0.02
    assert f.covariance[1, 1] < 0.05 * before[1, 1]
    # The recent keyframes, correlated with the pose, moved with it.
    _, error, _ = f.keyframe(keys[-1])
    assert error[1] == pytest.approx(-0.3, abs=0.03)


def test_an_absolute_fix_after_drift_is_accepted_and_the_own_map_follows() -> None:
    f = PlanarEkf(np.zeros(3), covariance=np.diag([1e-4, 1e-4, 1e-6]))
    keys = _walk(f, 80, key_every=3)
    sd = math.sqrt(f.covariance[1, 1])
    assert sd > 0.1  # honest after 8 m of odometry and own-map matches
    # A colony fix 25 cm across the path, known to 3 cm: within the gate, and it moves the pose.
    fix = f.pose + np.array([0.0, 0.25, 0.0])
    assert f.update(fix, np.diag([0.03**2, 0.03**2, 1e-4]))
    assert f.pose[1] == pytest.approx(0.25, abs=0.02)
    # The newest keyframes were placed with (nearly) the pose's error: they are corrected too,
    # so the next match against them (reading the pose in their uncorrected map) does not pull
    # the estimate back.
    _, error, _ = f.keyframe(keys[-1])
    assert error[1] == pytest.approx(0.25, abs=0.03)
    seen = f.seen_from(keys[-1])
    assert seen[1] == pytest.approx(0.0, abs=0.03)  # where the pose appears in that map
    assert f.update_relative(seen, np.eye(3) * 1e-4, np.array([keys[-1]]), np.eye(3)[None])
    assert f.pose[1] == pytest.approx(0.25, abs=0.02)
    # The old filter (own-map matches fused as absolute poses) was millimetres sure and
    # refused the same fix.
    g = PlanarEkf(np.zeros(3), covariance=np.diag([1e-4, 1e-4, 1e-6]))
    for _ in range(80):
        g.predict(np.array([0.1, 0.0, 0.0]))
        g.update(g.pose, np.eye(3) * 1e-4)
    assert not g.update(g.pose + np.array([0.0, 0.25, 0.0]), np.diag([0.03**2, 0.03**2, 1e-4]))


def test_keyframes_enter_and_leave_with_the_pose_correlation() -> None:
    f = PlanarEkf(np.zeros(3), covariance=np.diag([0.01, 0.02, 0.001]))
    f.reset_offset(np.eye(3) * 0.04)
    f.add_keyframe(7)
    pose, error, cov = f.keyframe(7)
    np.testing.assert_allclose(pose, f.pose)
    np.testing.assert_allclose(cov, f.covariance)
    np.testing.assert_allclose(error, 0.0)
    f.add_keyframe(8)
    f.keep_keyframes([8])
    assert f.keyframes == [8]
    assert f.offset is not None
    np.testing.assert_allclose(f.offset.covariance, np.eye(3) * 0.04)
    # A keyframe unknown to the filter counts as placed without error: an absolute update.
    g = PlanarEkf(np.zeros(3), covariance=np.eye(3) * 0.01)
    assert g.update_relative(
        np.array([0.2, 0.0, 0.0]), np.eye(3) * 0.01, np.array([3]), np.eye(3)[None]
    )
    np.testing.assert_allclose(g.pose, [0.1, 0.0, 0.0], atol=1e-9)


def test_the_filter_starts_without_scipy_stats_and_filterpys_likelihood_still_works() -> None:
    """filterpy.kalman is imported without scipy.stats or scipy.ndimage (~1 s of CPU at every
    daemon start): a fresh process builds, predicts and updates a filter without them,
    filterpy's own likelihood loads scipy.stats when called and gives the real value, and
    filterpy.stats and filterpy.discrete_bayes are the real modules after."""

    code = (
        "import sys, math, numpy as np\n"
        "from voxel.localisation.ekf import PlanarEkf\n"
        "f = PlanarEkf(np.zeros(3))\n"
        "f.predict(np.array([0.1, 0.0, 0.01]))\n"
        "f.update(np.array([0.1, 0.0, 0.0]), np.eye(3) * 0.01)\n"
        "print('scipy.stats' in sys.modules or 'scipy.ndimage' in sys.modules)\n"
        "import filterpy.kalman.EKF as ekf\n"
        "print(ekf.logpdf(x=np.array([0.1]), cov=np.array([[1.0]])))\n"
        "import filterpy.stats, filterpy.discrete_bayes\n"
        "print(hasattr(filterpy.stats, 'multivariate_gaussian'), 'scipy.stats' in sys.modules,"
        " hasattr(filterpy.discrete_bayes, 'predict'), 'scipy.ndimage' in sys.modules)\n"
    )
    stdout = fresh_process(code)
    before, value, after = stdout.split("\n")[:3]
    assert before == "False", stdout
    assert float(value) == pytest.approx(-0.5 * math.log(2 * math.pi) - 0.005, abs=1e-12)
    assert after == "True True True True", stdout
