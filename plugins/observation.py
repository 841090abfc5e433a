"""Observation: one sensor reading turned into points in the sensor frame plus everything known
about it."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from plugins.checks import as_array, as_intrinsics, as_pose
from plugins.errors import SensorInputError
from voxel.delta import Delta

#: Label of a detection that is another agent's marker (followed by the agent id); its pose is
#: that agent's body pose in the camera frame.
AGENT_LABEL = "agent:"


@dataclass(frozen=True)
class ObjectDetection:
    """An object seen by a sensor: identity, class and pose in the sensor frame."""

    object_id: int
    class_id: int
    pose: np.ndarray  # (4, 4) object-to-sensor
    probability: float = 1.0
    label: str = ""
    corners: np.ndarray | None = None  # (4, 2) image corners of a fiducial, if any
    #: (3, 3) covariance of `position` in the sensor frame, if the sensor knows its error
    covariance: np.ndarray | None = None

    @property
    def position(self) -> np.ndarray:
        """Object centre in the sensor frame (3,)."""
        return self.pose[:3, 3]


@dataclass(frozen=True)
class DepthView:
    """A depth image with its intrinsics, for projective integration."""

    depth: np.ndarray  # (H, W) float32 metres, NaN = no reading
    K: np.ndarray  # (3, 3)
    image: np.ndarray | None = None  # (H, W, 3) uint8 colour registered to depth, if any


@dataclass(frozen=True)
class Observation:
    """Points in the sensor frame, the sensor's pose guess and optional per-point channels.

    `pose` is sensor-to-world (4x4, the agent's current guess: reference poses for recordings,
    dead reckoning in the simulator). `no_return[i]` marks a beam without a return; its point is
    the beam direction scaled to the sensor's maximum range, to be cleared but not hit.
    `delta`, instead of points, carries voxels integrated elsewhere (the `bulk:` source), to be
    applied to a grid as they are.
    """

    sensor: str
    time: float
    points: np.ndarray  # (N, 3) float64, sensor frame
    pose: np.ndarray  # (4, 4) sensor-to-world guess
    colours: np.ndarray | None = None  # (N, 3) uint8
    class_ids: np.ndarray | None = None  # (N,) int32, -1 = none
    class_probs: np.ndarray | None = None  # (N,) float32
    normals: np.ndarray | None = None  # (N, 3) float32, sensor frame
    scalars: dict[str, np.ndarray] = field(default_factory=dict)  # name -> (N,)
    no_return: np.ndarray | None = None  # (N,) bool
    odometry: np.ndarray | None = None  # (4, 4) odometry pose of the agent body, if any
    objects: tuple[ObjectDetection, ...] = ()
    depth: DepthView | None = None
    truth: np.ndarray | None = None  # (4, 4) true sensor pose, when a simulator knows it
    frame: str = ""  # where the reading came from (file, line, index)
    delta: Delta | None = None  # ready-made voxels instead of points (bulk source)

    def __post_init__(self) -> None:
        points = as_array(self.points, "points", shape=(None, 3))
        n = points.shape[0]
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "pose", as_pose(self.pose, "pose"))
        if not np.isfinite(self.time):
            msg = f"time: expected a finite number, found {self.time!r}"
            raise SensorInputError(msg)
        checks = {
            "colours": ((n, 3), np.uint8),
            "class_ids": ((n,), np.int32),
            "class_probs": ((n,), np.float32),
            "normals": ((n, 3), np.float32),
            "no_return": ((n,), np.bool_),
        }
        for name, (shape, dtype) in checks.items():
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, as_array(value, name, shape=shape, dtype=dtype))
        scalars = {}
        for name, value in self.scalars.items():
            scalars[name] = as_array(
                value, f"scalars[{name!r}]", shape=(n,), dtype=np.float32, finite=False
            )
        object.__setattr__(self, "scalars", scalars)
        for name in ("odometry", "truth"):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, as_pose(value, name))
        if self.depth is not None:
            as_intrinsics(self.depth.K, "depth.K")
        if self.delta is not None and not isinstance(self.delta, Delta):
            msg = f"delta: expected a voxel.delta.Delta, found {type(self.delta).__name__}"
            raise SensorInputError(msg)

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def origin(self) -> np.ndarray:
        """Sensor position in the world frame (3,)."""
        return self.pose[:3, 3].copy()

    def points_world(self, pose: np.ndarray | None = None) -> np.ndarray:
        """Points (N, 3) in the world frame, with `pose` (default: the observation's own guess)."""
        T = self.pose if pose is None else pose
        world: np.ndarray = self.points @ T[:3, :3].T + T[:3, 3]
        return world

    def normals_world(self, pose: np.ndarray | None = None) -> np.ndarray | None:
        """Normals (N, 3) rotated into the world frame, or None."""
        if self.normals is None:
            return None
        T = self.pose if pose is None else pose
        world: np.ndarray = (self.normals @ T[:3, :3].T).astype(np.float32)
        return world
