"""A ROS 2 client built on a third-party rmw_zenoh library (PyPI `zenoh-ros2-sdk`), run as its own
process by test_ros2.py: `publish` plays CARMEN scans as LaserScan + Odometry + TF; `subscribe`
joins late and prints what it got from the daemon's transient-local map and cloud as JSON.

The SDK computes type hashes from .msg files, which it would clone from GitHub; they are written
here from rosbags' type store instead (definitions only: the SDK does keys, hashes, tokens,
attachments and CDR itself)."""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from plugins import rmw
from plugins.carmen import NO_RETURN, CarmenSource
from plugins.checks import pose_matrix
from voxel.rotation import matrix_to_quaternion

TYPES = (
    "sensor_msgs/msg/LaserScan",
    "nav_msgs/msg/Odometry",
    "tf2_msgs/msg/TFMessage",
    "nav_msgs/msg/OccupancyGrid",
    "sensor_msgs/msg/PointCloud2",
)


def write_definitions(root: Path) -> None:
    """One .msg file per type (and every type it uses) under root/<pkg>/msg/."""
    store = rmw.typestore()
    for name in TYPES:
        text, _ = store.generate_msgdef(name, ros_version=2)
        parts = text.split("=" * 80 + "\n")
        defs = {name: parts[0]}
        for part in parts[1:]:
            head, _, body = part.partition("\n")
            pkg, typ = head.removeprefix("MSG: ").split("/")
            defs[f"{pkg}/msg/{typ}"] = body
        for full, body in defs.items():
            pkg, _, typ = full.split("/")
            path = root / pkg / "msg" / f"{typ}.msg"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(body.strip() + "\n")


def publish(port: int, log: str, frames: int) -> dict[str, Any]:
    from zenoh_ros2_sdk import ROS2Publisher, ZenohSession

    def pub(topic: str, kind: str) -> Any:
        return ROS2Publisher(topic, kind, router_port=port, node_name="sdk_robot")

    scan = pub("/scan", TYPES[0])
    odom = pub("/odom", TYPES[1])
    tf = pub("/tf", TYPES[2])
    t = ZenohSession.get_instance(router_port=port).store.types

    def stamp(s: float) -> Any:
        ns = round(s * 1e9)
        return t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
            frame_id="",
        )

    def header(s: float, frame: str) -> Any:
        h = stamp(s)
        h.frame_id = frame
        return h

    def pose_of(m: np.ndarray) -> tuple[Any, Any]:
        q = matrix_to_quaternion(m[:3, :3])
        return (
            (float(m[0, 3]), float(m[1, 3]), float(m[2, 3])),
            t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        )

    from colonyd.bench.rosrobot import wait_for_subscriber

    session = ZenohSession.get_instance(router_port=port).session
    if not wait_for_subscriber(session, 0, "/scan", 20.0):  # as a publisher waiting for matches
        return {"published": 0, "error": "no subscriber to /scan"}
    time.sleep(0.5)
    n = 0
    for record in CarmenSource(Path(log), stop=frames).records():
        s = record.time
        ref = pose_matrix(record.pose[0], record.pose[1], 0.0, record.pose[2])
        odo = pose_matrix(record.odometry[0], record.odometry[1], 0.0, record.odometry[2])
        (x, y, z), q = pose_of(ref @ np.linalg.inv(odo))
        v = t["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)
        tf.publish(
            transforms=[
                t["geometry_msgs/msg/TransformStamped"](
                    header=header(s, "map"),
                    child_frame_id="odom",
                    transform=t["geometry_msgs/msg/Transform"](translation=v, rotation=q),
                )
            ]
        )
        (x, y, z), q = pose_of(odo)
        zero = t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        odom.publish(
            header=header(s, "odom"),
            child_frame_id="laser",
            pose=t["geometry_msgs/msg/PoseWithCovariance"](
                pose=t["geometry_msgs/msg/Pose"](
                    position=t["geometry_msgs/msg/Point"](x=x, y=y, z=z), orientation=q
                ),
                covariance=np.zeros(36),
            ),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](
                twist=t["geometry_msgs/msg/Twist"](linear=zero, angular=zero),
                covariance=np.zeros(36),
            ),
        )
        k = len(record.ranges)
        scan.publish(
            header=header(s, "laser"),
            angle_min=-math.pi / 2,
            angle_max=-math.pi / 2 + math.pi / k * (k - 1),
            angle_increment=math.pi / k,
            time_increment=0.0,
            scan_time=0.0,
            range_min=0.0,
            range_max=NO_RETURN,
            ranges=np.where(record.ranges >= NO_RETURN, np.inf, record.ranges).astype(np.float32),
            intensities=np.zeros(0, np.float32),
        )
        n += 1
        time.sleep(1 / 40)
    time.sleep(1.0)
    return {"published": n}


def subscribe(port: int) -> dict[str, Any]:
    from zenoh_ros2_sdk import ROS2Subscriber

    got: dict[str, Any] = {}
    attempts = 0
    while len(got) < 2 and attempts < 3:  # the SDK's history query has 2 s timeouts: a busy
        attempts += 1  # machine can miss it, and the daemon republishes only on change
        subs = [
            ROS2Subscriber(
                topic,
                kind,
                lambda msg, topic=topic: got.__setitem__(topic, msg),
                router_port=port,
                node_name="sdk_viewer",
                qos="1:1:1,1:,:,:,,",  # reliable, transient local, depth 1: like RViz2 for /map
            )
            for topic, kind in (("/colony_map", TYPES[3]), ("/colony_cloud", TYPES[4]))
        ]
        deadline = time.monotonic() + 5
        while len(got) < 2 and time.monotonic() < deadline:
            time.sleep(0.1)
        for sub in subs:
            sub.close()
    out: dict[str, Any] = {"hashes": [s.type_hash for s in subs], "attempts": attempts}
    grid = got.get("/colony_map")
    if grid is not None:
        cells = np.asarray(grid.data, np.int8).reshape(grid.info.height, grid.info.width)
        iy, ix = np.nonzero(cells == 100)
        corner = (grid.info.origin.position.x, grid.info.origin.position.y)
        out["grid"] = {
            "frame": grid.header.frame_id,
            "resolution": grid.info.resolution,
            "occupied": np.column_stack([ix, iy]).tolist(),
            "corner": corner,
        }
    cloud = got.get("/colony_cloud")
    if cloud is not None:
        out["cloud"] = {
            "points": int(cloud.width) * int(cloud.height),
            "fields": [f.name for f in cloud.fields],
        }
    return out


def main() -> int:
    mode, port, msgdir = sys.argv[1], int(sys.argv[2]), Path(sys.argv[3])
    write_definitions(msgdir)
    from zenoh_ros2_sdk import ZenohSession, get_registry

    get_registry(str(msgdir))
    try:
        result = (
            publish(port, sys.argv[4], int(sys.argv[5])) if mode == "publish" else subscribe(port)
        )
    finally:
        ZenohSession.get_instance(router_port=port).close()
    sys.stdout.write(json.dumps(result) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
