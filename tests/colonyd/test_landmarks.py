"""Landmarks: identified objects that aligned peers know, in our frame with their error, and the
estimator corrected by seeing them (paper Alg. 3)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from colonyd.alignment import ColonyFrame
from colonyd.estimator import ScanEstimator
from colonyd.landmarks import colony_landmarks
from colonyd.layers import Layer
from colonyd.objects import CLUSTER_IDS, OwnObjects
from plugins.observation import ObjectDetection, Observation
from protocol import ObjectCentroid as WireObject
from voxel.localisation.ekf import PlanarEkf


def _rigid(x: float, y: float, yaw: float) -> np.ndarray:
    t = np.eye(4)
    t[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    t[:2, 3] = (x, y)
    return t


def _object(object_id: int, x: float, y: float, var: float = 1e-4) -> WireObject:
    cov = [var, 0, 0, 0, var, 0, 0, 0, var]
    return WireObject(object_id=object_id, class_id=5, position=(x, y, 1.0), covariance=cov,
                      voxel_count=0, time=0.0)  # fmt: skip


def test_a_peers_identified_objects_are_landmarks_in_our_frame_with_the_alignments_error():
    # The colony frame is the CCTV's; ours is 2 m along its x and turned 90 degrees; the
    # alignment is known to 0.01 rad in yaw (about the colony's origin).
    frame = ColonyFrame(
        "cctv",
        {"cctv": np.eye(4), "me": _rigid(2.0, 0.0, math.pi / 2), "far": np.eye(4)},
        {"me": np.diag([0.0, 0.0, 1e-4])},
    )
    lists = {
        "cctv": [_object(7, 2.0, 3.0), _object(CLUSTER_IDS + 1, 0.0, 0.0)],  # a cluster: no id
        "me": [_object(8, 0.0, 0.0)],  # our own objects are not landmarks
        "stranger": [_object(9, 0.0, 0.0)],  # not aligned with us
    }
    known = colony_landmarks(frame, "me", lists)
    assert set(known) == {7}
    xy, cov, via = known[7]
    assert via is None  # the alignment's error is in the covariance
    np.testing.assert_allclose(xy, [3.0, 0.0], atol=1e-12)  # (2, 3) in the colony: 3 m ahead
    # the yaw error e about the colony's origin moves the landmark by e (-3, 2) there, e (2, 3)
    # here; plus the CCTV's own 1 cm
    np.testing.assert_allclose(cov, 1e-4 * np.array([[4, 6], [6, 9]]) + 1e-4 * np.eye(2))
    assert colony_landmarks(ColonyFrame("cctv", {"cctv": np.eye(4)}), "me", lists) == {}


def test_an_estimator_that_sees_a_known_landmark_is_pulled_onto_it():
    est = ScanEstimator(planar=False, mount=np.eye(4))
    est.localiser.ekf = PlanarEkf(np.array([0.3, 0.0, 0.0]), np.diag([0.04, 0.04, 1e-6]))
    seen = np.eye(4)
    seen[:3, 3] = (2.0, 0.5, 0.2)  # truly at the origin: the landmark is at (2, 0.5)
    obs = Observation(
        sensor="depth",
        time=0.0,
        points=np.zeros((0, 3)),
        pose=np.eye(4),
        objects=(ObjectDetection(4, 5, seen), ObjectDetection(5, 5, seen)),  # 5 is unknown
    )
    est.landmarks(obs, {4: (np.array([2.0, 0.5]), np.eye(2) * 1e-6)})
    assert est.counts()["landmark_accepted"] == 1
    # prior 20 cm, the sighting 2 cm + 2 % of 2.07 m: pulled most of the way back
    sd = 0.02 + 0.02 * float(np.linalg.norm(seen[:3, 3]))
    r = sd**2 + 1e-6
    assert abs(est.localiser.ekf.pose[0] - 0.3 * r / (0.04 + r)) < 1e-3


def test_a_fixed_cameras_marker_is_published_no_surer_than_one_sighting():
    """A fixed camera sees a marker from one place every frame: 30 identical sightings share one
    error, so the published mean keeps a single sighting's covariance (turned into the world),
    not a thirtieth of it (the scatter is zero: 1 cm claimed for a marker 0.45 m off)."""
    objects = OwnObjects(frozenset())
    camera = np.eye(4)  # optical frame: its z axis (the ray) along world x
    camera[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    seen = np.eye(4)
    seen[:3, 3] = (0.0, 0.0, 10.0)  # 10 m ahead: world (10, 0, 0)
    sighting = np.diag([1e-4, 1e-4, 0.25])  # 0.5 m along the ray, 1 cm across
    for t in range(30):
        obs = Observation(
            sensor="cctv",
            time=float(t),
            points=np.zeros((0, 3)),
            pose=camera,
            objects=(ObjectDetection(7, 5, seen, covariance=sighting),),
        )
        objects.observe(obs)
    (found,) = objects.refresh(Layer("cctv", 0.1))
    np.testing.assert_allclose(found.position, [10.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(found.covariance, np.diag([0.25, 1e-4, 1e-4]) + 1e-4 * np.eye(3))


def test_a_robot_confident_to_3cm_is_not_dragged_by_a_far_markers_range_error():
    """The CCTV's marker 0.1 m off along its ray (its range from 22 px, 5 m: 0.11 m claimed):
    a robot known to 3 cm that sees it from 2 m moves by the known gain, under 1 cm; with the
    mean's scatter alone (1 cm) it was pulled 2 cm by one sighting."""

    def landmark_after(landmark_cov: np.ndarray) -> float:
        est = ScanEstimator(planar=False, mount=np.eye(4))
        est.localiser.ekf = PlanarEkf(np.zeros(3), np.diag([9e-4, 9e-4, 1e-8]))
        seen = np.eye(4)
        seen[:3, 3] = (2.0, 0.0, 0.0)  # truly 2 m ahead: the true landmark is at (2, 0)
        obs = Observation(sensor="depth", time=0.0, points=np.zeros((0, 3)), pose=np.eye(4),
                          objects=(ObjectDetection(4, 5, seen),))  # fmt: skip
        est.landmarks(obs, {4: (np.array([2.1, 0.0]), landmark_cov)})  # ray along x
        assert est.counts()["landmark_accepted"] == 1
        return float(est.localiser.ekf.pose[0])

    r = (0.02 + 0.02 * 2.0) ** 2
    along = (5.0 * 0.5 / 22.0) ** 2 + 1e-4
    moved = landmark_after(np.diag([along, 2e-4]))
    assert abs(moved - 0.1 * 9e-4 / (9e-4 + r + along)) < 1e-4 and moved < 0.01
    assert landmark_after(np.eye(2) * 1e-4) > 0.015  # the old claim


def test_with_landmark_errors_an_estimator_counts_a_markers_error_once_under_its_id():
    """The object's id keys its error in the filter (`ScanParams.landmark_errors`): 20
    sightings of a marker published 0.3 m off (claimed 0.1 m) leave a robot known to 0.5 m
    as one sighting with the marker's covariance would (claiming about 0.1 m, the error 3 sd);
    without the option, as 20 (claiming 2.6 cm, the error 11 sd)."""

    def after(errors: bool) -> tuple[float, float, list[int]]:
        est = ScanEstimator(planar=False, mount=np.eye(4))
        est.localiser.params = replace(est.localiser.params, landmark_errors=errors)
        est.localiser.ekf = PlanarEkf(np.zeros(3), np.diag([0.25, 0.25, 1e-10]))
        seen = np.eye(4)
        seen[:3, 3] = (2.0, 0.0, 0.0)  # truly 2 m ahead: the true landmark is at (2, 0)
        obs = Observation(sensor="depth", time=0.0, points=np.zeros((0, 3)), pose=np.eye(4),
                          objects=(ObjectDetection(4, 5, seen),))  # fmt: skip
        for _ in range(20):
            est.landmarks(obs, {4: (np.array([2.3, 0.0]), np.eye(2) * 0.01)})
        assert est.counts()["landmark_accepted"] == 20
        ekf = est.localiser.ekf
        return float(ekf.pose[0]), float(ekf.covariance[0, 0]), ekf.landmarks

    r = (0.02 + 0.02 * 2.0) ** 2
    once, independent = (0.01 + r / 20), (0.01 + r) / 20  # as one measurement's noise
    x, var, keys = after(True)
    assert keys == [4]
    assert abs(x - 0.3 * 0.25 / (0.25 + once)) < 1e-3
    assert abs(var - 0.25 * once / (0.25 + once)) < 1e-5
    x, var, keys = after(False)
    assert keys == []
    assert abs(x - 0.3 * 0.25 / (0.25 + independent)) < 1e-3
    assert abs(var - 0.25 * independent / (0.25 + independent)) < 1e-5
