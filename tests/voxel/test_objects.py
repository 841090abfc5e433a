"""Tests of object centroid extraction."""

from __future__ import annotations

import numpy as np
import pytest

from voxel.errors import InputError
from voxel.grid import VoxelGrid
from voxel.objects import extract_objects


def box_surface(centre: np.ndarray, size: float, n: int = 30) -> np.ndarray:
    """Points on the six faces of a cube."""
    u = np.linspace(-size / 2, size / 2, n)
    a, b = np.meshgrid(u, u)
    a, b = a.ravel(), b.ravel()
    h = np.full_like(a, size / 2)
    faces = [
        np.stack(f, 1)
        for f in ((h, a, b), (-h, a, b), (a, h, b), (a, -h, b), (a, b, h), (a, b, -h))
    ]
    return np.concatenate(faces) + centre


def test_two_labelled_boxes_give_two_centroids():
    grid = VoxelGrid(0.05)
    boxes = {3: np.array([2.013, 0.507, 0.311]), 9: np.array([-1.487, 1.209, 0.411])}
    for t, (cls, centre) in enumerate(boxes.items()):
        pts = box_surface(centre, 0.4)
        for origin in (np.array([0.01, 0.02, 0.03]), centre + np.array([0.0, 0.0, 1.5])):
            grid.integrate(
                pts,
                origin,
                time=float(t),
                class_ids=np.full(len(pts), cls),
                class_probs=np.full(len(pts), 0.9),
            )
    # an unlabelled wall must not become an object
    wall = np.stack(
        [
            np.full(400, 4.013),
            np.repeat(np.linspace(-1, 1, 20), 20),
            np.tile(np.linspace(0, 1, 20), 20),
        ],
        1,
    )
    grid.integrate(wall, np.zeros(3), time=5.0)
    objects = extract_objects(grid, min_probability=0.2)
    assert sorted(o.class_id for o in objects) == [3, 9]
    for o in objects:
        assert np.linalg.norm(o.position - boxes[o.class_id]) < 0.03
        assert o.voxel_count > 50
        assert np.all(np.linalg.eigvalsh(o.covariance) > 0)
    again = extract_objects(grid, min_probability=0.2)
    assert [o.object_id for o in again] == [o.object_id for o in objects]


def test_no_classes_no_objects_and_bad_arguments():
    grid = VoxelGrid(0.1)
    grid.integrate(box_surface(np.array([1.0, 0, 0]), 0.4), np.zeros(3), time=0.0)
    assert extract_objects(grid) == []
    with pytest.raises(InputError, match="min_voxels >= 1"):
        extract_objects(grid, min_voxels=0)
