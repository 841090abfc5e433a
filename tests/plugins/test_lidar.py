"""Tests of the 2D and 3D LiDAR adapters against known scenes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from plugins.checks import pose_matrix
from plugins.errors import SensorInputError
from plugins.lidar import Cloud, Lidar2D, Lidar3D, Scan
from plugins.sim import make_rig, render
from plugins.world import World, _walls


def square_room(open_side: bool = False) -> World:
    walls = _walls(-3.0, -3.0, 3.0, 3.0, 2.5)
    return World(name="square", boxes=walls[:-1] if open_side else walls, floor=0.0)


def test_scan_of_a_square_room_gives_its_walls() -> None:
    rig, params = make_rig("lidar2d")
    lidar = Lidar2D(**params)
    body = pose_matrix(0.5, -0.3, 0.0, 0.3)
    reading = render(square_room(), "lidar2d", rig, body @ rig.mount, np.random.default_rng(0), 0.0)
    obs = lidar.observe(reading, pose=body @ rig.mount)
    pts = obs.points_world()
    assert len(obs) == 360 and not obs.no_return.any()
    assert np.abs(np.maximum(np.abs(pts[:, 0]), np.abs(pts[:, 1])) - 3.0).max() < 1e-3
    np.testing.assert_allclose(pts[:, 2], 0.3, atol=1e-9)
    on = {
        "x=+3": pts[:, 0] > 2.999,
        "x=-3": pts[:, 0] < -2.999,
        "y=+3": pts[:, 1] > 2.999,
        "y=-3": pts[:, 1] < -2.999,
    }
    for wall, mask in on.items():
        assert mask.sum() > 20, wall
        # each wall is seen along a stretch (the 270 degree scanner sees the wall behind it only in
        # part)
        other = pts[mask, 1] if wall.startswith("x") else pts[mask, 0]
        assert np.ptp(other) > 1.0, wall


def test_no_return_beams_are_flagged_and_reach_max_range() -> None:
    rig, params = make_rig("lidar2d")
    lidar = Lidar2D(**params)
    reading = render(
        square_room(open_side=True), "lidar2d", rig, rig.mount, np.random.default_rng(0), 0.0
    )
    obs = lidar.observe(reading)
    assert obs.no_return.sum() > 50
    np.testing.assert_allclose(np.linalg.norm(obs.points[obs.no_return], axis=1), lidar.range_max)
    assert np.all(obs.points[obs.no_return, 0] > 0)  # the open wall is x = +3


def test_laser_scan_semantics() -> None:
    lidar = Lidar2D(
        angle_min=0.0,
        angle_increment=math.pi / 2,
        range_min=0.1,
        range_max=10.0,
        no_return_range=8.0,
    )
    obs = lidar.observe(
        Scan(ranges=np.array([1.0, np.inf, np.nan, 0.05, 9.0]), intensities=np.arange(5.0))
    )
    # NaN and below range_min dropped; inf and >= no_return_range flagged
    assert len(obs) == 3
    np.testing.assert_array_equal(obs.no_return, [False, True, True])
    np.testing.assert_allclose(obs.points[0], [1.0, 0.0, 0.0])
    np.testing.assert_allclose(obs.points[1], [0.0, 10.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(obs.scalars["intensity"], [0.0, 1.0, 4.0])


def test_scan_errors_are_named() -> None:
    with pytest.raises(SensorInputError, match="ranges: expected 360 beams, found 359"):
        Lidar2D(beams=360).observe(np.ones(359))
    with pytest.raises(SensorInputError, match=r"ranges: expected shape \(N\), found \(2, 2\)"):
        Lidar2D().observe(np.ones((2, 2)))
    with pytest.raises(
        SensorInputError, match="ranges: expected non-negative ranges or \\+inf, found -inf"
    ):
        Lidar2D().observe(np.array([1.0, -np.inf]))
    with pytest.raises(SensorInputError, match="range: expected 0 <= range_min < range_max"):
        Lidar2D(range_min=5.0, range_max=1.0)


def test_3d_cloud_of_a_plane_at_known_distance() -> None:
    world = World(name="floor", floor=0.0)
    rig, params = make_rig("lidar3d")
    lidar = Lidar3D(**params)
    reading = render(world, "lidar3d", rig, rig.mount, np.random.default_rng(0), 0.0)
    obs = lidar.observe(reading, pose=rig.mount)
    pts = obs.points_world()
    assert len(obs) == 7 * 512  # 7 of the 8 downward rings hit the floor within 30 m (-1 deg: 46 m)
    assert np.abs(pts[:, 2]).max() < 1e-3
    assert "intensity" in obs.scalars


def test_3d_cloud_drops_nan_and_out_of_range() -> None:
    lidar = Lidar3D(range_min=0.5, range_max=10.0)
    cloud = np.array([[1.0, 0, 0], [np.nan, 0, 0], [0.1, 0, 0], [20.0, 0, 0], [0, 2.0, 0]])
    obs = lidar.observe(Cloud(points=cloud, intensity=np.arange(5.0)))
    np.testing.assert_allclose(obs.points, [[1.0, 0, 0], [0, 2.0, 0]])
    np.testing.assert_allclose(obs.scalars["intensity"], [0.0, 4.0])
    with pytest.raises(SensorInputError, match=r"points: expected shape \(N, 3\), found \(5,\)"):
        lidar.observe(np.ones(5))
    with pytest.raises(SensorInputError, match=r"intensity: expected shape \(5\), found \(4,\)"):
        lidar.observe(Cloud(points=cloud, intensity=np.ones(4)))
