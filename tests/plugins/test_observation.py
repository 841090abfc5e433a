"""Tests of Observation validation and frame transforms."""

from __future__ import annotations

import numpy as np
import pytest

from plugins.checks import pose_matrix, quaternion_to_matrix
from plugins.errors import SensorInputError
from plugins.observation import Observation
from voxel.rotation import matrix_to_quaternion


def test_points_world_applies_the_pose() -> None:
    pose = pose_matrix(1.0, 2.0, 3.0, np.pi / 2)
    obs = Observation(
        sensor="x", time=0.0, points=[[1.0, 0.0, 0.0]], pose=pose, normals=[[1.0, 0.0, 0.0]]
    )
    np.testing.assert_allclose(obs.points_world(), [[1.0, 3.0, 3.0]], atol=1e-12)
    np.testing.assert_allclose(obs.normals_world(), [[0.0, 1.0, 0.0]], atol=1e-6)
    np.testing.assert_allclose(obs.origin, [1.0, 2.0, 3.0])


def test_wrong_point_shape_names_the_field() -> None:
    with pytest.raises(SensorInputError, match=r"points: expected shape \(N, 3\), found \(4, 2\)"):
        Observation(sensor="x", time=0.0, points=np.zeros((4, 2)), pose=np.eye(4))


def test_nan_points_are_rejected() -> None:
    with pytest.raises(SensorInputError, match="points: expected finite values, found 1 NaN"):
        Observation(sensor="x", time=0.0, points=[[0.0, np.nan, 1.0]], pose=np.eye(4))


def test_per_point_channels_must_match_the_points() -> None:
    with pytest.raises(SensorInputError, match=r"colours: expected shape \(2, 3\), found \(3, 3\)"):
        Observation(
            sensor="x", time=0.0, points=np.zeros((2, 3)), pose=np.eye(4), colours=np.zeros((3, 3))
        )
    with pytest.raises(
        SensorInputError, match=r"scalars\['temp'\]: expected shape \(2\), found \(1,\)"
    ):
        Observation(
            sensor="x", time=0.0, points=np.zeros((2, 3)), pose=np.eye(4), scalars={"temp": [1.0]}
        )


def test_pose_must_be_rigid() -> None:
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(SensorInputError, match=r"pose: expected a rotation matrix"):
        Observation(sensor="x", time=0.0, points=np.zeros((0, 3)), pose=bad)
    bad = np.eye(4)
    bad[3, 0] = 1.0
    with pytest.raises(SensorInputError, match=r"pose: expected last row \[0, 0, 0, 1\]"):
        Observation(sensor="x", time=0.0, points=np.zeros((0, 3)), pose=bad)
    with pytest.raises(SensorInputError, match="time: expected a finite number"):
        Observation(sensor="x", time=float("nan"), points=np.zeros((0, 3)), pose=np.eye(4))


def test_quaternion_round_trip() -> None:
    rng = np.random.default_rng(1)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = -q if q[3] < 0 else q
        np.testing.assert_allclose(matrix_to_quaternion(quaternion_to_matrix(*q)), q, atol=1e-9)
