"""The alignment fixes and landmarks come through, given apart from their own covariance
(`through`, `ScanParams.alignment_frames`): the same total as before, and the localiser keeping
its error as one state per origin, reset and widened, its pose graph following."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from colonyd.alignment import ColonyFrame
from colonyd.estimator import ScanEstimator
from colonyd.fixes import fix_in_own_frame, through
from colonyd.landmarks import colony_landmarks
from plugins.observation import ObjectDetection, Observation
from protocol import ObjectCentroid as WireObject
from voxel.localisation import frame_error
from voxel.localisation.ekf import PlanarEkf
from voxel.localisation.localiser import ScanLocaliser, Through
from voxel.localisation.pose_graph import PoseGraph


def _rigid(x: float, y: float, yaw: float) -> np.ndarray:
    t = np.eye(4)
    t[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    t[:2, 3] = (x, y)
    return t


#: The colony frame is the CCTV's; ours is 2 m along its x and turned 90 degrees, known to
#: 0.01 rad in yaw about the colony's origin.
FRAME = ColonyFrame(
    "cctv",
    {"cctv": np.eye(4), "me": _rigid(2.0, 0.0, math.pi / 2)},
    {"me": np.diag([1e-6, 1e-6, 1e-4])},
)


def test_a_fix_through_an_alignment_leaves_its_error_apart_and_the_total_is_the_same() -> None:
    body = _rigid(2.0, 3.0, 0.3)  # the robot seen by the CCTV
    cov = np.diag([1e-4, 2e-4, 0.05**2, 0.05**2, 0.05**2, 0.07**2])
    added = fix_in_own_frame(FRAME, "me", "cctv", body, cov)
    apart = fix_in_own_frame(FRAME, "me", "cctv", body, cov, alignment=False)
    via = through(FRAME, "me", "cctv")
    assert added is not None and apart is not None and via is not None
    np.testing.assert_allclose(apart[0], added[0])
    np.testing.assert_allclose(apart[1][:2, :2], np.diag([2e-4, 1e-4]), atol=1e-12)  # turned
    np.testing.assert_allclose(added[1], apart[1] + frame_error.at(via.covariance, apart[0][:2]))
    assert via.origin == "cctv"
    moved = ColonyFrame("cctv", {**FRAME.transforms, "me": _rigid(2.0, 0.01, math.pi / 2)})
    other = through(moved, "me", "cctv")
    assert other is not None and other.alignment != via.alignment  # a new alignment
    assert through(FRAME, "me", "stranger") is None


def test_a_landmark_through_an_alignment_leaves_its_error_apart() -> None:
    cov = [1e-4, 0, 0, 0, 1e-4, 0, 0, 0, 1e-4]
    marker = WireObject(object_id=7, class_id=5, position=(2.0, 3.0, 1.0), covariance=cov,
                        voxel_count=0, time=0.0)  # fmt: skip
    lists = {"cctv": [marker]}
    added = colony_landmarks(FRAME, "me", lists)[7]
    apart = colony_landmarks(FRAME, "me", lists, framed=True)[7]
    via = apart[2]
    assert added[2] is None and via is not None and via.origin == "cctv"
    np.testing.assert_allclose(apart[0], added[0])
    np.testing.assert_allclose(apart[1], np.eye(2) * 1e-4, atol=1e-12)
    np.testing.assert_allclose(
        added[1], apart[1] + frame_error.at(via.covariance, apart[0])[:2, :2]
    )


def _localiser(record: bool) -> ScanLocaliser:
    loc = ScanLocaliser(planar=True)
    loc.params = replace(loc.params, alignment_frames=True)
    pose, cov = np.array([5.0, 0.0, 0.0]), np.diag([0.05**2, 0.05**2, 0.02**2])
    loc.ekf = PlanarEkf(pose, cov)
    loc.history.append((0.0, pose))
    if record:
        loc.graph = PoseGraph(pose, cov)
    return loc


def test_the_localiser_keeps_one_error_per_alignment_resets_widens_and_its_graph_follows() -> None:
    loc = _localiser(record=True)
    a = np.diag([1e-6, 1e-6, 1e-4])
    fix = np.diag([1e-4, 1e-4, 0.07**2])
    z = np.array([5.0 * math.cos(0.01), 5.0 * math.sin(0.01), 0.01])  # through a turned frame
    for _ in range(10):
        assert loc.fix(z, fix, 0.0, Through("cctv", b"first", a))
    assert loc.ekf is not None and loc.graph is not None
    key = ("alignment", "cctv")
    assert loc.ekf.frames == [key]
    learnt = loc.ekf.frame(key)
    assert learnt is not None and learnt.value[2] > 0.004  # the frame took part of the turn
    assert loc.graph.offsets == 1 and loc.graph.edges()["colony"] == 10
    # the graph solves what the filter fused: the same pose and frame error
    solved = loc.graph.solve()
    np.testing.assert_allclose(solved.poses[-1], loc.ekf.pose, atol=2e-3)
    np.testing.assert_allclose(solved.offsets[0], learnt.value, atol=2e-3)
    # a larger claim for the same alignment widens it (the graph walks to a new variable)
    assert loc.fix(z, fix, 0.0, Through("cctv", b"first", a * 2))
    widened = loc.ekf.frame(key)
    assert widened is not None and loc.graph.offsets == 2
    assert widened.accounted[2, 2] == 2e-4
    # a new alignment: a new error, zero
    assert loc.fix(np.array([5.0, 0.0, 0.0]), fix, 0.0, Through("cctv", b"second", a))
    fresh = loc.ekf.frame(key)
    assert fresh is not None and loc.graph.offsets == 3
    assert fresh.accounted[2, 2] == 1e-4


def test_an_estimator_passes_the_alignment_of_its_landmarks() -> None:
    est = ScanEstimator(planar=False, mount=np.eye(4))
    est.localiser = _localiser(record=False)
    assert est.framed
    seen = np.eye(4)
    seen[:3, 3] = (2.0, 0.5, 0.2)
    obs = Observation(
        sensor="depth",
        time=0.0,
        points=np.zeros((0, 3)),
        pose=np.eye(4),
        objects=(ObjectDetection(4, 5, seen),),
    )
    via = Through("cctv", b"a", np.diag([1e-6, 1e-6, 1e-4]))
    est.landmarks(obs, {4: (np.array([7.0, 0.5]), np.eye(2) * 1e-4, via)})
    assert est.counts()["landmark_accepted"] == 1
    ekf = est.localiser.ekf
    assert ekf is not None and ekf.frames == [("alignment", "cctv")] and ekf.landmarks == [4]


def test_an_alignment_compares_by_identity_and_a_bad_claim_leaves_the_frames_order_alone() -> None:
    """`Through` holds an array: compared and hashed by identity, never raising; a widening or a
    walk with a bad covariance raises before it marks its frame as used, so the frame dropped
    next (the least recently used) is the same as without the bad call."""
    import pytest

    from voxel.errors import LocalisationError

    a = through(FRAME, "me", "cctv")
    b = through(FRAME, "me", "cctv")
    assert a is not None and b is not None
    assert a == a and a != b and len({a, b}) == 2  # (a dataclass with eq would raise here)
    ekf = PlanarEkf(np.zeros(3))
    ekf.max_frames = 2
    ekf.reset_frame("old", np.eye(3) * 1e-4)
    ekf.reset_frame("new", np.eye(3) * 1e-4)
    with pytest.raises(LocalisationError, match="non-finite"):
        ekf.widen_frame("old", np.full((3, 3), np.nan))
    with pytest.raises(LocalisationError, match="finite point"):
        ekf.walk_frame("old", np.eye(3) * 1e-6, np.array([np.inf, 0.0]))
    ekf.reset_frame("third", np.eye(3) * 1e-4)  # drops the least recently used: "old"
    assert ekf.frames == ["new", "third"]
