"""Tests of the simulated world's ray caster and renderer."""

from __future__ import annotations

import numpy as np
import pytest

from plugins.errors import SourceSpecError
from plugins.world import CLASSES, Box, Cylinder, World, get_world


def test_box_cylinder_and_floor_distances() -> None:
    world = World(
        name="t",
        boxes=[Box((3.0, -1.0, 0.0), (4.0, 1.0, 2.0), CLASSES["box"], 1)],
        cylinders=[Cylinder((0.0, 5.0), 0.5, 0.0, 2.0, CLASSES["cylinder"], 2)],
        floor=0.0,
    )
    origin = np.array([0.0, 0.0, 1.0])
    dirs = np.array(
        [
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, -1.0],
            [0.0, -1.0, 0.0],
            [-1.0, 0.0, 0.5],
            [0, 0, 1.0],
        ]
    )
    hits = world.cast(origin, dirs)
    np.testing.assert_allclose(hits.t[:4], [3.0, 4.5, 1.0, np.inf])
    np.testing.assert_allclose(hits.t[4], np.inf)
    np.testing.assert_array_equal(
        hits.class_id[:4], [CLASSES["box"], CLASSES["cylinder"], CLASSES["floor"], -1]
    )
    np.testing.assert_array_equal(hits.object_id[:3], [1, 2, -1])
    np.testing.assert_allclose(hits.normal[:3], [[-1, 0, 0], [0, -1, 0], [0, 0, 1]], atol=1e-12)


def test_nearest_of_overlapping_objects_wins() -> None:
    world = World(
        name="t",
        boxes=[Box((5.0, -1, -1), (6.0, 1, 1), 1), Box((2.0, -1, -1), (2.5, 1, 1), 2)],
        floor=None,
    )
    hits = world.cast(np.zeros(3), np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]))
    np.testing.assert_allclose(hits.t, [2.0, np.inf])
    assert hits.class_id[0] == 2


def test_many_rays_at_once_match_analytic_distances() -> None:
    world = World(name="t", floor=0.0)
    rng = np.random.default_rng(0)
    d = rng.normal(size=(100000, 3))
    d[:, 2] = -np.abs(d[:, 2]) - 0.01
    hits = world.cast(np.array([0.0, 0.0, 2.0]), d)
    np.testing.assert_allclose(hits.t, 2.0 / -d[:, 2])


def test_builtin_worlds_and_objects() -> None:
    office = get_world("office")
    objects = office.objects()
    assert {10, 11, 12, 13} <= set(objects) and len(office.markers) == 16
    assert all(objects[m.object_id][0] == CLASSES["landmark"] for m in office.markers)
    with pytest.raises(
        SourceSpecError, match=r"world: expected one of \['hall', 'office', 'room'\], found 'mars'"
    ):
        get_world("mars")


def test_furnished_room_walls_and_furniture_at_known_distances() -> None:
    from plugins.world import FURNISHED_SHIFT, furnished_room

    room = furnished_room()
    sx, sy, sz = FURNISHED_SHIFT
    origin = np.array([0.0, 0.0, 1.0])
    dirs = np.array(
        [[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0, 0, -1.0], [0.0, -1.0, 0.0]]
    )
    t = room.cast(origin, dirs).t
    # +x wall, the shelf on the -x wall (x = -2.9), +y wall, ceiling, floor, the chair (y = -1.9)
    np.testing.assert_allclose(
        t, [4.0 + sx, 2.9 - sx, 3.0 + sy, 1.8 + sz, 1.0 - sz, 1.9 - sy], atol=1e-12
    )
