"""Points adapter: readings that are already points in the sensor frame (the synthetic and bulk
sources)."""

from __future__ import annotations

import numpy as np

from plugins.checks import as_pose
from plugins.observation import Observation
from voxel.sensor import SensorModel


class PointsAdapter:
    """Takes (N, 3) sensor-frame points as they are; OctoMap's default sensor model, kind `sim`."""

    kind = "sim"
    labels = False  # its observations carry no class ids (colonyd.daemon: nothing to cluster)

    def __init__(self, name: str, *, reliability: float = 1.0, noise: float = 0.0) -> None:
        self.name = name
        self.sensor_model = SensorModel(kind="sim")
        self.reliability = float(reliability)
        self.noise = float(noise)

    def observe(
        self,
        reading: np.ndarray,
        *,
        pose: np.ndarray | None = None,
        time: float = 0.0,
        odometry: np.ndarray | None = None,
        frame: str = "",
    ) -> Observation:
        """Observation of points (N, 3) in the sensor frame; `pose` is the sensor's pose guess."""
        body = np.eye(4) if pose is None else as_pose(pose, "pose")
        return Observation(
            sensor=self.name, time=time, points=reading, pose=body, odometry=odometry, frame=frame
        )
