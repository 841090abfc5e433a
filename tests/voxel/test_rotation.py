"""Quaternions (x, y, z, w) and matrices: one convention, checked at every caller with a known
rotation."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from colonyd.mapping import tum_line
from plugins.checks import quaternion_to_matrix as checked_quaternion_to_matrix
from plugins.errors import SensorInputError
from plugins.rosbag import pose_of_odometry
from protocol.messages import Pose
from voxel.rotation import matrix_to_quaternion, quaternion_to_matrix

#: 90 degrees about +z: +x turns into +y, +y into -x.
QUARTER_Z = (0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4))
QUARTER_Z_MATRIX = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def test_known_rotation_turns_x_into_y() -> None:
    m = quaternion_to_matrix(QUARTER_Z)
    np.testing.assert_allclose(m, QUARTER_Z_MATRIX, atol=1e-12)
    np.testing.assert_allclose(m @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(matrix_to_quaternion(QUARTER_Z_MATRIX), QUARTER_Z, atol=1e-12)


def test_quaternions_from_matrices_have_w_non_negative() -> None:
    rng = np.random.default_rng(3)
    for raw in rng.normal(size=(200, 4)):
        q = raw / np.linalg.norm(raw)
        back = matrix_to_quaternion(quaternion_to_matrix(q))
        assert back[3] >= 0
        np.testing.assert_allclose(back, q if q[3] >= 0 else -q, atol=1e-9)


def test_protocol_transform_uses_the_same_convention() -> None:
    pose = Pose(
        origin="r1", time=1.0, frame_id="map", position=(1.0, 2.0, 3.0), orientation=QUARTER_Z
    )
    np.testing.assert_allclose(pose.matrix()[:3, :3], QUARTER_Z_MATRIX, atol=1e-12)
    t = np.eye(4)
    t[:3, :3] = QUARTER_Z_MATRIX
    np.testing.assert_allclose(Pose.split_matrix(t)["orientation"], QUARTER_Z, atol=1e-12)


def test_sensor_inputs_use_the_same_convention() -> None:
    np.testing.assert_allclose(
        checked_quaternion_to_matrix(*QUARTER_Z), QUARTER_Z_MATRIX, atol=1e-12
    )
    # unnormalised input is normalised first, as before
    np.testing.assert_allclose(
        checked_quaternion_to_matrix(*(2 * np.array(QUARTER_Z))), QUARTER_Z_MATRIX, atol=1e-12
    )
    x, y, z, w = QUARTER_Z
    msg = SimpleNamespace(
        pose=SimpleNamespace(
            pose=SimpleNamespace(
                position=SimpleNamespace(x=1.0, y=2.0, z=3.0),
                orientation=SimpleNamespace(x=x, y=y, z=z, w=w),
            )
        )
    )
    np.testing.assert_allclose(pose_of_odometry(msg)[:3, :3], QUARTER_Z_MATRIX, atol=1e-12)
    with pytest.raises(SensorInputError, match="expected a non-zero finite quaternion"):
        checked_quaternion_to_matrix(0.0, 0.0, 0.0, 0.0)


def test_trajectory_lines_use_the_same_convention() -> None:
    pose = np.eye(4)
    pose[:3, :3] = QUARTER_Z_MATRIX
    fields = [float(v) for v in tum_line(0.0, pose).split()]
    np.testing.assert_allclose(fields[4:], QUARTER_Z, atol=1e-9)


def test_conversions_equal_scipys_rotation() -> None:
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(5)
    axes = [[0, 0, 0, 1], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 0], [0.5, -0.5, 0.5, 0]]
    for q in np.vstack([rng.normal(size=(500, 4)), axes]):
        np.testing.assert_allclose(
            quaternion_to_matrix(q), Rotation.from_quat(q).as_matrix(), atol=1e-15
        )
        m = Rotation.from_quat(q).as_matrix()  # w = 0 too: the first non-zero one positive
        np.testing.assert_array_equal(
            matrix_to_quaternion(m), Rotation.from_matrix(m).as_quat(canonical=True)
        )


def test_a_zero_or_non_finite_quaternion_is_an_input_error() -> None:
    from voxel.errors import InputError

    for bad in [(0.0, 0.0, 0.0, 0.0), (math.nan, 0.0, 0.0, 1.0), (math.inf, 0.0, 0.0, 1.0)]:
        with pytest.raises(InputError, match="expected a non-zero finite quaternion"):
            quaternion_to_matrix(bad)
