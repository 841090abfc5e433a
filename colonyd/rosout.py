"""ROS 2 outputs of a daemon: the fused map as OccupancyGrid and PointCloud2, object centroids as
MarkerArray, the colony frame on /tf; all rmw_zenoh publishers of one node (docs/ROS2.md)."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from colonyd import rosmsg
from colonyd.rosgraph import RosNode

log = logging.getLogger(__name__)

GRID, CLOUD = "nav_msgs/msg/OccupancyGrid", "sensor_msgs/msg/PointCloud2"
MARKERS, TF = "visualization_msgs/msg/MarkerArray", "tf2_msgs/msg/TFMessage"
#: Largest OccupancyGrid published (cells); a bigger one is refused with an error line.
MAX_CELLS = 16_000_000


@dataclass(frozen=True)
class Ros2Outputs:
    """What to publish where (the daemon's `ros2_*` settings)."""

    domain: int = 0
    node: str = "colonyd"
    map_topic: str = "/colony/map"
    cloud_topic: str = "/colony/cloud"
    objects_topic: str = "/colony/objects"
    frame: str = "colony"
    robot_frame: str = "map"
    grid_z_min: float = -0.5
    grid_z_max: float = 2.0
    max_points: int = 2_000_000
    type_hashes: bool = True


def occupancy_cells(
    keys: np.ndarray, logodds: np.ndarray, resolution: float, z_min: float, z_max: float
) -> tuple[np.ndarray, np.ndarray]:
    """2D projection of voxels with centres in [z_min, z_max]: (H, W) int8 cells (100 occupied
    anywhere in the column, 0 known free, -1 unknown) and the (x, y) of cell (0, 0)'s corner."""
    z = (keys[:, 2] + 0.5) * resolution
    band = (z >= z_min) & (z <= z_max)
    k, lo = keys[band], logodds[band]
    if len(k) == 0:
        return np.full((1, 1), -1, np.int8), np.zeros(2)
    lo_xy = k[:, :2].min(axis=0)
    ix, iy = (k[:, 0] - lo_xy[0]).astype(np.int64), (k[:, 1] - lo_xy[1]).astype(np.int64)
    h, w = int(iy.max()) + 1, int(ix.max()) + 1
    if h * w > MAX_CELLS:
        msg = f"occupancy grid: expected at most {MAX_CELLS} cells, found {h} x {w}"
        raise ValueError(msg)
    cells = np.full((h, w), -1, np.int8)
    cells[iy, ix] = 0
    occ = lo >= 0
    cells[iy[occ], ix[occ]] = 100
    return cells, lo_xy.astype(np.float64) * resolution


def height_colours(z: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 colours ramping blue -> green -> red from the lowest to the highest z."""
    if len(z) == 0:
        return np.zeros((0, 3), np.uint8)
    t = (z - z.min()) / max(float(np.ptp(z)), 1e-9)
    rgb = np.column_stack(
        [np.clip(2 * t - 1, 0, 1), 1 - np.abs(2 * t - 1), np.clip(1 - 2 * t, 0, 1)]
    )
    return (rgb * 255).astype(np.uint8)


class RosPublishers:
    """The daemon's ROS 2 node: transient-local map, cloud and markers (RViz2 subscribing late gets
    the last ones), /tf colony -> robot frame. Large messages block rather than drop."""

    def __init__(self, session: Any, out: Ros2Outputs) -> None:
        self.out = out
        self.node = RosNode(session, out.node, out.domain, type_hashes=out.type_hashes)
        latched = {"transient_local": True, "depth": 1, "block": True}
        self.grid = self.node.publisher(out.map_topic, GRID, **latched)
        self.cloud = self.node.publisher(out.cloud_topic, CLOUD, **latched)
        self.markers = self.node.publisher(out.objects_topic, MARKERS, **latched)
        self.tf = self.node.publisher("/tf", TF, depth=100)
        self.capped = 0

    def publish_map(
        self,
        keys: np.ndarray,
        logodds: np.ndarray,
        resolution: float,
        points: np.ndarray,
    ) -> int:
        """OccupancyGrid and PointCloud2 of a fused map (colony frame); the bytes sent. The cloud
        holds `points` (M, 3), those of the occupied voxels (log-odds >= 0, in order:
        `layers.fused_surface`, their centres where no layer keeps surfaces)."""
        out, now = self.out, time.time()
        cells, corner = occupancy_cells(keys, logodds, resolution, out.grid_z_min, out.grid_z_max)
        origin = np.array([corner[0], corner[1], 0.0])
        sent = self.grid.publish(rosmsg.occupancy_grid(now, out.frame, cells, resolution, origin))
        if len(points) > out.max_points:
            self.capped += 1
            if self.capped == 1 or self.capped % 100 == 0:
                log.warning(
                    "ROS 2 cloud: %d occupied voxels, publishing every %d-th (ros2_max_points %d)",
                    len(points),
                    -(-len(points) // out.max_points),
                    out.max_points,
                )
            points = points[:: -(-len(points) // out.max_points)]
        cloud = rosmsg.point_cloud(now, out.frame, points, height_colours(points[:, 2]))
        return sent + self.cloud.publish(cloud)

    def publish_objects(self, positions: np.ndarray, ids: list[int], size: float) -> int:
        now = time.time()
        msg = rosmsg.sphere_markers(now, self.out.frame, "colony_objects", positions, ids, size)
        return self.markers.publish(msg)

    def publish_frame(self, colony_from_robot: np.ndarray) -> int:
        """/tf: the colony frame -> this robot's map frame (where its own layer is built)."""
        t = rosmsg.transform_stamped(
            time.time(), self.out.frame, self.out.robot_frame, colony_from_robot
        )
        return self.tf.publish(rosmsg.tf_message([t]))

    def close(self) -> None:
        self.node.close()
