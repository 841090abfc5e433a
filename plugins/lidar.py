"""LiDAR adapters: 2D scans over an angular span (LaserScan-like) and 3D point clouds."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from plugins.checks import as_array, as_pose
from plugins.errors import SensorInputError
from plugins.observation import Observation
from voxel.sensor import SensorModel


@dataclass(frozen=True)
class Scan:
    """One 2D scan: ranges (n,) in metres; the angles default to the adapter's."""

    ranges: np.ndarray
    angle_min: float | None = None
    angle_increment: float | None = None
    intensities: np.ndarray | None = None


@dataclass(frozen=True)
class Cloud:
    """One 3D point cloud (N, 3) in the sensor frame; NaN points (organised clouds) are dropped."""

    points: np.ndarray
    intensity: np.ndarray | None = None


#: How far a 2D scanner's beam without a return clears free space by default, metres: indoor
#: scanners see nothing back through doors, windows and glass, and clearing their whole range
#: there (80 m on the Freiburg 079 log) fills the map with unbounded free space.
FREE_RANGE_2D = 10.0


class Lidar2D:
    """Planar laser scanner: beam i points at angle_min + i * angle_increment in the sensor's x-y
    plane.

    A range at or beyond `no_return_range` (default: `range_max`), or +inf, is a beam without a
    return: it clears free space up to `free_range` (default FREE_RANGE_2D, at most `range_max`;
    OctoMap's `maxrange` for beams that saw nothing) and hits nothing. NaN and ranges below
    `range_min` are invalid measurements (REP 117) and are dropped.
    """

    name = "lidar2d"
    kind = "lidar2d"
    labels = False  # its observations carry no class ids (colonyd.daemon: nothing to cluster)

    def __init__(
        self,
        *,
        beams: int | None = None,
        angle_min: float = -math.pi / 2,
        angle_increment: float = math.pi / 360,
        range_min: float = 0.0,
        range_max: float = 30.0,
        no_return_range: float | None = None,
        free_range: float = 0.0,
        mount: np.ndarray | None = None,
        reliability: float = 1.0,
        prob_hit: float = 0.7,
        prob_miss: float = 0.4,
        noise: float = 0.0,
    ) -> None:
        if angle_increment == 0 or not math.isfinite(angle_increment):
            msg = f"angle_increment: expected a finite non-zero angle, found {angle_increment!r}"
            raise SensorInputError(msg)
        if not 0 <= range_min < range_max:
            msg = f"range: expected 0 <= range_min < range_max, found {range_min!r}, {range_max!r}"
            raise SensorInputError(msg)
        self.beams = beams
        self.angle_min, self.angle_increment = float(angle_min), float(angle_increment)
        self.range_min, self.range_max = float(range_min), float(range_max)
        self.no_return_range = float(range_max if no_return_range is None else no_return_range)
        self.mount = np.eye(4) if mount is None else as_pose(mount, "mount")
        self.reliability = float(reliability)
        self.noise = float(noise)
        if not (free_range >= 0 and math.isfinite(free_range)):
            msg = f"free_range: expected metres >= 0 (0: the default), found {free_range!r}"
            raise SensorInputError(msg)
        self.free_range = min(free_range or FREE_RANGE_2D, self.range_max)
        self.sensor_model = SensorModel(
            prob_hit=prob_hit,
            prob_miss=prob_miss,
            max_range=range_max,
            kind="lidar2d",
            free_range=self.free_range,
        )

    def observe(
        self,
        reading: Scan | np.ndarray,
        *,
        pose: np.ndarray | None = None,
        time: float = 0.0,
        odometry: np.ndarray | None = None,
        frame: str = "",
    ) -> Observation:
        """Observation of one scan: points in the sensor's z = 0 plane, no-return beams flagged."""
        if not isinstance(reading, Scan):
            reading = Scan(ranges=reading)
        ranges = as_array(reading.ranges, "ranges", shape=(None,), finite=False)
        if self.beams is not None and ranges.shape[0] != self.beams:
            msg = f"ranges: expected {self.beams} beams, found {ranges.shape[0]}"
            raise SensorInputError(msg)
        if np.any(ranges == -np.inf):
            msg = "ranges: expected non-negative ranges or +inf, found -inf"
            raise SensorInputError(msg)
        a0 = self.angle_min if reading.angle_min is None else float(reading.angle_min)
        da = (
            self.angle_increment
            if reading.angle_increment is None
            else float(reading.angle_increment)
        )
        angles = a0 + da * np.arange(ranges.shape[0])
        with np.errstate(invalid="ignore"):
            no_return = (ranges >= self.no_return_range) | (ranges > self.range_max)
            keep = no_return | ((ranges >= self.range_min) & np.isfinite(ranges))
        r = np.where(no_return, self.range_max, ranges)[keep]
        angles = angles[keep]
        points = np.column_stack([r * np.cos(angles), r * np.sin(angles), np.zeros_like(r)])
        scalars = {}
        if reading.intensities is not None:
            intensity = as_array(
                reading.intensities, "intensities", shape=ranges.shape, finite=False
            )
            scalars["intensity"] = intensity[keep]
        body = np.eye(4) if pose is None else as_pose(pose, "pose")
        return Observation(
            sensor=self.name,
            time=time,
            points=points,
            pose=body @ self.mount,
            no_return=no_return[keep],
            scalars=scalars,
            odometry=odometry,
            frame=frame,
        )


class Lidar3D:
    """3D laser scanner delivering point clouds (optionally with intensity)."""

    name = "lidar3d"
    kind = "lidar3d"
    labels = False  # its observations carry no class ids (colonyd.daemon: nothing to cluster)

    def __init__(
        self,
        *,
        range_min: float = 0.0,
        range_max: float = 100.0,
        mount: np.ndarray | None = None,
        reliability: float = 1.0,
        prob_hit: float = 0.7,
        prob_miss: float = 0.4,
        noise: float = 0.0,
    ) -> None:
        if not 0 <= range_min < range_max:
            msg = f"range: expected 0 <= range_min < range_max, found {range_min!r}, {range_max!r}"
            raise SensorInputError(msg)
        self.range_min, self.range_max = float(range_min), float(range_max)
        self.mount = np.eye(4) if mount is None else as_pose(mount, "mount")
        self.reliability = float(reliability)
        self.noise = float(noise)
        self.sensor_model = SensorModel(
            prob_hit=prob_hit, prob_miss=prob_miss, max_range=range_max, kind="lidar3d"
        )

    def observe(
        self,
        reading: Cloud | np.ndarray,
        *,
        pose: np.ndarray | None = None,
        time: float = 0.0,
        odometry: np.ndarray | None = None,
        frame: str = "",
    ) -> Observation:
        """Observation of one cloud; NaN points and points outside [range_min, range_max] are
        dropped."""
        if not isinstance(reading, Cloud):
            reading = Cloud(points=reading)
        points = as_array(reading.points, "points", shape=(None, 3), finite=False)
        r = np.linalg.norm(points, axis=1)
        with np.errstate(invalid="ignore"):
            keep = np.isfinite(r) & (r >= self.range_min) & (r <= self.range_max) & (r > 0)
        scalars = {}
        if reading.intensity is not None:
            intensity = as_array(
                reading.intensity, "intensity", shape=(points.shape[0],), finite=False
            )
            scalars["intensity"] = intensity[keep]
        body = np.eye(4) if pose is None else as_pose(pose, "pose")
        return Observation(
            sensor=self.name,
            time=time,
            points=points[keep],
            pose=body @ self.mount,
            scalars=scalars,
            odometry=odometry,
            frame=frame,
        )
