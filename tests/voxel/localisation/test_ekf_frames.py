"""Planar EKF: the error of an alignment that fixes and landmarks come through, one state per
frame, counted once: a single measurement weighs as with the alignment's error added, many do
not drag the pose into it; landmarks and fixes share it; resets, widening and the bound."""

from __future__ import annotations

import math

import numpy as np
import pytest

from voxel.errors import LocalisationError
from voxel.localisation import frame_error
from voxel.localisation.ekf import COLONY, PlanarEkf

#: The alignment is turned 0.01 rad about our origin (claimed to 0.01 rad, 1 mm in x and y);
#: the robot stands at (5, 0) facing +x, known to 5 cm; a fix is good to 1 cm and 0.01 rad.
YAW = 0.01
ALIGNMENT = np.diag([1e-6, 1e-6, 0.01**2])
TRUE = np.array([5.0, 0.0, 0.0])
P = np.diag([0.05**2, 0.05**2, 1e-6])
FIX = np.diag([0.01**2, 0.01**2, 0.01**2])


def _moved(pose: np.ndarray, yaw: float = YAW) -> np.ndarray:
    """`pose` seen through a frame turned `yaw` about the origin."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([c * pose[0] - s * pose[1], s * pose[0] + c * pose[1], pose[2] + yaw])


def _robot() -> PlanarEkf:
    return PlanarEkf(TRUE.copy(), covariance=P.copy())


def test_one_fix_through_a_frame_weighs_as_one_with_the_alignments_error_added() -> None:
    # Linear-Gaussian: marginalising the frame's error out of one measurement is adding its
    # covariance there (frame_error.at): the same pose and covariance either way.
    framed, added = _robot(), _robot()
    z = _moved(TRUE)
    framed.reset_frame("cctv", ALIGNMENT)
    assert framed.update_frame("cctv", z, FIX)
    assert added.update(z, FIX + frame_error.at(ALIGNMENT, TRUE[:2]))
    np.testing.assert_allclose(framed.pose, added.pose, atol=1e-6)
    np.testing.assert_allclose(framed.covariance, added.covariance, atol=1e-9)


def _batch(framed: bool, fixes: int) -> np.ndarray:
    """The known answer of the linearised problem (pose, frame error) solved at once: the
    priors' and the fixes' information summed, the fixes as the pose moved by the frame's
    error (framed) or with the alignment's covariance added to each (not)."""
    r0 = _moved(TRUE) - TRUE
    j = np.array([[1.0, 0.0, -TRUE[1]], [0.0, 1.0, TRUE[0]], [0.0, 0.0, 1.0]])
    if framed:
        h = np.hstack([np.eye(3), j])
        prior = np.zeros((6, 6))
        prior[:3, :3], prior[3:, 3:] = np.linalg.inv(P_LOOSE), np.linalg.inv(ALIGNMENT)
        ri = np.linalg.inv(FIX_FLAT)
    else:
        h, prior = np.eye(3), np.linalg.inv(P_LOOSE)
        ri = np.linalg.inv(FIX_FLAT + j @ ALIGNMENT @ j.T)
    info = prior + fixes * h.T @ ri @ h
    out: np.ndarray = np.linalg.solve(info, fixes * h.T @ ri @ r0)
    return out


#: A heading known to 0.02 rad and fixes claimed as the daemon's flat model (1 cm, 4 degrees).
P_LOOSE = np.diag([0.05**2, 0.05**2, 0.02**2])
FIX_FLAT = np.diag([0.01**2, 0.01**2, 0.07**2])


def test_fifty_fixes_through_one_turned_alignment_move_the_pose_as_its_covariance_allows() -> None:
    # The fixes put the robot 5 cm off in y (0.01 rad at 5 m). Added to each fix, the
    # alignment's error is counted 50 times: the robot follows the turned frame (4.9 cm),
    # claiming 7 mm. As one state, the fixes measure pose and frame error together: the pose
    # takes what its prior allows against the frame's (2.3 cm), the frame's yaw the rest.
    framed = PlanarEkf(TRUE.copy(), covariance=P_LOOSE.copy())
    added = PlanarEkf(TRUE.copy(), covariance=P_LOOSE.copy())
    framed.reset_frame("cctv", ALIGNMENT)
    z = _moved(TRUE)
    for _ in range(50):
        assert framed.update_frame("cctv", z, FIX_FLAT)
        assert added.update(z, FIX_FLAT + frame_error.at(ALIGNMENT, TRUE[:2]))
    want_added, want = _batch(False, 50), _batch(True, 50)
    assert want_added[1] > 0.048 and 0.02 < want[1] < 0.025  # the known answers
    np.testing.assert_allclose(added.pose - TRUE, want_added, atol=5e-4)
    np.testing.assert_allclose(framed.pose - TRUE, want[:3], atol=5e-4)
    error = framed.frame("cctv")
    assert error is not None
    np.testing.assert_allclose(error.value, want[3:], atol=5e-4)
    assert error.value[2] > 0.005  # half the turn is the frame's
    # and the pose still claims the 3.4 cm its prior and the frame's allow, not 7 mm
    assert math.sqrt(framed.covariance[1, 1]) > 0.03
    assert math.sqrt(added.covariance[1, 1]) < 0.008


def test_a_landmark_through_a_frame_weighs_as_one_with_the_alignments_error_added() -> None:
    framed, added = _robot(), _robot()
    published = _moved(np.array([5.0, 5.0, 0.0]))[:2]  # truly at (5, 5): seen at (0, 5)
    seen, r, own = np.array([0.0, 5.0]), np.eye(2) * 0.02**2, np.eye(2) * 0.01**2
    framed.reset_frame("cctv", ALIGNMENT)
    assert framed.update_landmark(seen, r, published, own, frame="cctv")
    shared = frame_error.at(ALIGNMENT, published)[:2, :2]
    assert added.update_landmark(seen, r, published, own + shared)
    np.testing.assert_allclose(framed.pose, added.pose, atol=1e-6)
    np.testing.assert_allclose(framed.covariance, added.covariance, atol=1e-9)


def test_landmarks_and_fixes_through_one_frame_share_its_error() -> None:
    # A robot known to 1 mm sees three landmarks (each published to 1 cm) through the turned
    # frame, 4-9 cm off: they teach the filter the frame's error (0.01 rad). Then it is lost
    # (30 cm) and gets fixes through that frame: moved back by the error learnt, they put it
    # where it is. With the alignment's error in each landmark and each fix instead, the
    # landmarks' states take the turn each as their own and the fixes put the robot where the
    # turned frame says (5 cm off).
    results = {}
    for shared in (True, False):
        f = PlanarEkf(TRUE.copy(), covariance=np.diag([1e-6, 1e-6, 1e-8]))
        if shared:
            f.reset_frame("cctv", ALIGNMENT)
        own, r = np.eye(2) * 0.01**2, np.eye(2) * 0.01**2
        for _ in range(10):
            for key, where in ((1, (9.0, 4.0)), (2, (9.0, -4.0)), (3, (2.0, 4.0))):
                truth = np.array(where)
                published = _moved(np.array([*truth, 0.0]))[:2]
                seen = truth - TRUE[:2]  # heading 0: body = world
                if shared:
                    assert f.update_landmark(seen, r, published, own, key=key, frame="cctv")
                else:
                    at = frame_error.at(ALIGNMENT, published)[:2, :2]
                    assert f.update_landmark(seen, r, published, own + at, key=key)
        if shared:
            learnt = f.frame("cctv")
            assert learnt is not None
            assert learnt.value[2] == pytest.approx(YAW, abs=1e-3)
        f.kf.P = np.diag([0.3**2, 0.3**2, 0.02**2])  # lost: a new prior, independent
        f._cross[:] = 0.0
        for _ in range(20):
            if shared:
                assert f.update_frame("cctv", _moved(TRUE), FIX_FLAT)
            else:
                assert f.update(_moved(TRUE), FIX_FLAT + frame_error.at(ALIGNMENT, TRUE[:2]))
        results[shared] = f.pose
    np.testing.assert_allclose(results[True][:2], TRUE[:2], atol=0.01)
    assert results[False][1] > 0.04


def test_a_frame_is_reset_when_its_alignment_changes_and_widened_when_its_claim_grows() -> None:
    f = _robot()
    f.reset_frame("cctv", ALIGNMENT)
    for _ in range(5):
        assert f.update_frame("cctv", _moved(TRUE), FIX)
    learnt = f.frame("cctv")
    assert learnt is not None and np.abs(learnt.cross).max() > 0
    q = f.widen_frame("cctv", ALIGNMENT + np.diag([0.0, 0.0, 1e-4]))
    np.testing.assert_allclose(q, np.diag([0.0, 0.0, 1e-4]), atol=1e-15)
    widened = f.frame("cctv")
    assert widened is not None
    np.testing.assert_allclose(widened.value, learnt.value)  # the mean stays
    np.testing.assert_allclose(widened.covariance, learnt.covariance + q, atol=1e-15)
    assert not f.widen_frame("cctv", ALIGNMENT).any()  # a smaller claim is no evidence
    f.reset_frame("cctv", ALIGNMENT * 4)  # a new alignment: a new error
    new = f.frame("cctv")
    assert new is not None
    np.testing.assert_array_equal(new.value, np.zeros(3))
    np.testing.assert_allclose(new.covariance, ALIGNMENT * 4)
    np.testing.assert_array_equal(new.cross, np.zeros((3, 3)))


def test_frames_are_keyed_bounded_and_the_colony_offset_is_one_of_them() -> None:
    f = _robot()
    f.max_frames = 2
    f.reset_offset(ALIGNMENT)
    f.reset_frame("cctv", ALIGNMENT)
    assert f.frames == [COLONY, "cctv"]
    assert f.update_frame("cctv", _moved(TRUE), FIX)  # cctv used last
    f.reset_frame("peer", ALIGNMENT)  # a third: the least recently used goes
    assert f.frames == ["cctv", "peer"] and f.offset is None
    assert len(f._mean) == 6
    with pytest.raises(LocalisationError, match="reset_offset"):
        f.update_offset(TRUE, FIX)
    with pytest.raises(LocalisationError, match="reset_frame"):
        f.update_frame("stranger", TRUE, FIX)
    with pytest.raises(LocalisationError, match="reset_frame"):
        f.update_landmark(np.ones(2), np.eye(2), np.ones(2), np.eye(2), frame="stranger")
    with pytest.raises(LocalisationError, match="frame 'x'"):
        f.reset_frame("x", -np.eye(3))
    # keyframes after the frames still address their own rows
    f.add_keyframe(4)
    placed, _, cov = f.keyframe(4)
    np.testing.assert_allclose(placed, f.pose)
    np.testing.assert_allclose(cov, f.covariance)


def test_a_keyed_landmarks_error_follows_a_move_of_its_truth_not_of_a_new_alignment() -> None:
    # A landmark published at p through the frame, then at p + 10 cm: through the same
    # alignment that is the same truth published elsewhere, so its error's mean shifts by the
    # move; through a new alignment (the frame reset since) the move is the alignment's, which
    # the reset frame carries, so its error's mean stays.
    seen, r, own = np.array([0.0, 5.0]), np.eye(2) * 0.02**2, np.eye(2) * 0.01**2
    first = np.array([5.0, 5.0])
    moved = first + np.array([0.1, 0.0])
    errors = {}
    for reset in (False, True):
        f = _robot()
        f.reset_frame("cctv", ALIGNMENT)
        assert f.update_landmark(seen, r, first, own, key=7, frame="cctv")
        before = f.landmark(7)[1].copy()
        if reset:
            f.reset_frame("cctv", ALIGNMENT)  # a new alignment of the same origin
        f.update_landmark(seen, r, moved, own, key=7, frame="cctv", gate=None)
        errors[reset] = (before, f.landmark(7))
    (before, (published, after, _)) = errors[False]
    np.testing.assert_allclose(published, moved)
    # shifted by the move, then corrected a little by the sighting (cm-level, not 10 cm)
    assert after[0] - before[0] == pytest.approx(0.1, abs=0.03)
    (before, (published, after, _)) = errors[True]
    np.testing.assert_allclose(published, moved)
    assert abs(after[0] - before[0]) < 0.03
