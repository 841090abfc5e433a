"""Tests of the depth camera adapter's geometry and input checks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from plugins.checks import pose_matrix
from plugins.depth import DepthCamera, DepthFrame, fov_of
from plugins.errors import SensorInputError
from plugins.sim import OPTICAL, render
from plugins.world import CLASSES, Box, World

K = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])


def test_plane_at_known_distance_comes_back_within_a_millimetre() -> None:
    # a wall whose face is the plane x = 2.0, camera at the origin looking along +x, rendered by
    # ray casting
    world = World(
        name="plane", boxes=[Box((2.0, -5.0, -5.0), (2.5, 5.0, 5.0), CLASSES["wall"])], floor=None
    )
    camera = DepthCamera(fov=math.radians(70), width=160, height=120, max_range=8.0)
    from plugins.sim import Rig

    v, u = np.mgrid[0:120, 0:160]
    dirs = np.stack(
        [
            (u - camera.K[0, 2]) / camera.K[0, 0],
            (v - camera.K[1, 2]) / camera.K[1, 1],
            np.ones((120, 160)),
        ],
        -1,
    )
    rig = Rig(dirs.reshape(-1, 3), OPTICAL, (120, 160), camera.K)
    pose = pose_matrix(0.0, 0.0, 1.0, 0.0) @ OPTICAL
    reading = render(world, "depth", rig, pose, np.random.default_rng(0), 0.0)
    obs = camera.observe(reading, pose=pose_matrix(0.0, 0.0, 1.0, 0.0) @ OPTICAL)
    assert len(obs) == 120 * 160
    world_points = obs.points_world()
    assert np.abs(world_points[:, 0] - 2.0).max() < 1e-3
    np.testing.assert_allclose(
        obs.points[:, 2], 2.0, atol=1e-3
    )  # camera z = distance to a fronto-parallel plane
    assert obs.class_ids is not None and set(np.unique(obs.class_ids)) == {CLASSES["wall"]}


def test_fov_intrinsics_follow_algorithm_1() -> None:
    camera = DepthCamera(fov=math.radians(90), width=640, height=480)
    assert camera.K[0, 0] == pytest.approx(320.0)  # 0.5 * w / tan(45 deg)
    assert camera.K[1, 1] == pytest.approx(320.0)
    assert (camera.K[0, 2], camera.K[1, 2]) == (320.0, 240.0)
    assert fov_of(camera.K, 640) == pytest.approx(math.radians(90))


def test_raw_millimetres_and_invalid_values() -> None:
    depth = np.full((480, 640), 1500, np.uint16)
    depth[0, :10] = 0
    depth[1, :5] = 65535
    camera = DepthCamera(K=K)
    obs = camera.observe(depth)
    assert len(obs) == 480 * 640 - 15
    np.testing.assert_allclose(obs.points[:, 2], 1.5)
    centre = obs.points[np.argmin(np.abs(obs.points[:, 0]) + np.abs(obs.points[:, 1]))]
    np.testing.assert_allclose(centre, [0.0, 0.0, 1.5])


def test_back_projection_of_a_known_pixel() -> None:
    depth = np.full((480, 640), np.nan, np.float32)
    depth[100, 500] = 2.0
    obs = DepthCamera(K=K).observe(depth)
    np.testing.assert_allclose(
        obs.points, [[(500 - 320) * 2.0 / 585, (100 - 240) * 2.0 / 585, 2.0]]
    )
    assert obs.depth is not None and obs.depth.depth.shape == (480, 640)


def test_colour_labels_and_stride() -> None:
    depth = np.ones((4, 6), np.float32)
    colour = np.zeros((4, 6, 3), np.uint8)
    colour[..., 2] = 200
    labels = np.arange(24).reshape(4, 6)
    obs = DepthCamera(K=K, stride=2).observe(DepthFrame(depth=depth, colour=colour, labels=labels))
    assert len(obs) == 6
    assert obs.colours is not None and np.all(obs.colours[:, 2] == 200)
    assert obs.class_ids is not None and sorted(obs.class_ids.tolist()) == [0, 2, 4, 12, 14, 16]


def test_bad_inputs_are_named() -> None:
    camera = DepthCamera(K=K)
    with pytest.raises(
        SensorInputError, match=r"depth: expected a \(H, W\) depth image, found shape \(4,\)"
    ):
        camera.observe(np.ones(4))
    with pytest.raises(
        SensorInputError, match="depth: expected an integer or float depth image, found dtype bool"
    ):
        camera.observe(np.ones((2, 2), bool))
    with pytest.raises(
        SensorInputError, match=r"colour: expected shape \(2, 2, 3\), found \(2, 3, 3\)"
    ):
        camera.observe(DepthFrame(depth=np.ones((2, 2)), colour=np.zeros((2, 3, 3))))
    with pytest.raises(
        SensorInputError,
        match="expected intrinsics K or a horizontal field of view fov, found neither",
    ):
        DepthCamera()
    with pytest.raises(SensorInputError, match=r"K: expected \[\[fx, 0, cx\]"):
        DepthCamera(K=np.zeros((3, 3)))
    with pytest.raises(
        SensorInputError, match=r"fov: expected a horizontal field of view in \(0, pi\)"
    ):
        DepthCamera(fov=4.0)
