"""Depth back-projection: camera-frame points of valid pixels, and world points with colour and
labels."""

from __future__ import annotations

import numpy as np
import pytest

from voxel.depth import back_project, camera_points
from voxel.errors import InputError

K = np.array([[100.0, 0.0, 2.0], [0.0, 100.0, 1.0], [0.0, 0.0, 1.0]])


def test_camera_points_of_known_pixels_skip_invalid_ones() -> None:
    depth = np.zeros((3, 4))
    depth[1, 2] = 2.0  # the principal point: straight ahead
    depth[2, 3] = 1.0
    depth[0, 0] = np.nan
    points, index = camera_points(depth, K)
    np.testing.assert_allclose(points, [[0.0, 0.0, 2.0], [0.01, 0.01, 1.0]])
    assert index.tolist() == [1 * 4 + 2, 2 * 4 + 3]
    depth[2, 2] = 1.0
    strided, idx = camera_points(depth, K, stride=2)  # rows 0, 2 and columns 0, 2 only
    assert idx.tolist() == [2 * 4 + 2]
    np.testing.assert_allclose(strided, [[0.0, 0.01, 1.0]])


def test_back_project_moves_points_into_the_world_with_colour_and_labels() -> None:
    depth = np.zeros((3, 4))
    depth[2, 3] = 1.0
    pose = np.eye(4)
    pose[:3, 3] = [1.0, 2.0, 3.0]
    colour = np.zeros((3, 4, 3), np.uint8)
    colour[2, 3] = (1, 2, 3)
    labels = np.full((3, 4), -1)
    labels[2, 3] = 7
    seen = back_project(depth, K, pose, colour=colour, labels=labels)
    np.testing.assert_allclose(seen.points, [[1.01, 2.01, 4.0]])
    assert seen.colours.tolist() == [[1, 2, 3]] and seen.class_ids.tolist() == [7]
    with pytest.raises(InputError, match="colour must be an \\(H, W, 3\\) image"):
        back_project(depth, K, pose, colour=colour[:2])


def test_pixel_rays_at_depth_are_the_back_projected_points() -> None:
    from voxel.depth import pixel_rays

    depth = np.full((3, 4), 2.0)
    points, _ = camera_points(depth, K)
    np.testing.assert_allclose(pixel_rays(K, 4, 3) * 2.0, points)
