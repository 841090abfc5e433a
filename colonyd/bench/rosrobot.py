"""A ROS 2 robot without ROS: plays a recording as rmw_zenoh topics (tests, demos, benchmarks).

    python -m colonyd.bench.rosrobot --connect tcp/127.0.0.1:7447 carmen LOG [--stop 300]
    python -m colonyd.bench.rosrobot --listen tcp/127.0.0.1:7447 rgbd FOLDER [--stop 30]

CARMEN logs become /scan (LaserScan, frame laser), /odom (Odometry odom -> base_link from the
log's wheel odometry), /tf (map -> odom, so that map -> laser is the log's reference pose) and
/tf_static (base_link -> laser). 7-Scenes folders become a depth Image (16UC1) with its
CameraInfo and /tf world -> camera (the reference pose). Everything goes out in rmw_zenoh's wire
format (keys with type hashes, 33-byte attachments, liveliness tokens) from a node named `robot`.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from colonyd import rosmsg
from colonyd.rosgraph import RosNode, RosPublisher
from colonyd.runtime import open_session, zenoh_config
from plugins import rmw
from plugins.carmen import NO_RETURN, CarmenSource
from plugins.checks import pose_matrix
from plugins.sevenscenes import RgbdSource, read_depth_png, read_matrix

#: The laser's place on the robot (base_link -> laser) in the played CARMEN log.
LASER_MOUNT = pose_matrix(0.12, 0.0, 0.25, 0.0)
SCAN, ODOM = "sensor_msgs/msg/LaserScan", "nav_msgs/msg/Odometry"
TF = "tf2_msgs/msg/TFMessage"
IMAGE, INFO = "sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo"
DEPTH_TOPIC, INFO_TOPIC = "/camera/depth/image_rect_raw", "/camera/depth/camera_info"


def carmen_messages(
    log: Path, start: int = 0, stop: int | None = None
) -> Iterator[list[tuple[str, Any]]]:
    """Per scan of a CARMEN log: [(topic, message)] in publishing order (TF, odometry, scan)."""
    source = CarmenSource(log, start=start, stop=stop)
    inv_mount = np.linalg.inv(LASER_MOUNT)
    for record in source.records():
        t = record.time
        reference = pose_matrix(*record.pose[:2], 0.0, record.pose[2])
        odom = pose_matrix(*record.odometry[:2], 0.0, record.odometry[2])
        map_from_odom = reference @ inv_mount @ np.linalg.inv(odom)
        n = len(record.ranges)
        ranges = np.where(record.ranges >= NO_RETURN, np.inf, record.ranges)
        yield [
            ("/tf", rosmsg.tf_message([rosmsg.transform_stamped(t, "map", "odom", map_from_odom)])),
            ("/odom", rosmsg.odometry(t, "odom", "base_link", odom)),
            ("/scan", rosmsg.laser_scan(t, "laser", ranges, -math.pi / 2, math.pi / n, NO_RETURN)),
        ]


def rgbd_messages(
    folder: Path, start: int = 0, stop: int | None = None
) -> Iterator[list[tuple[str, Any]]]:
    """Per frame of a 7-Scenes folder: [(topic, message)] (TF, camera info, depth image)."""
    source = RgbdSource(folder, start=start, stop=stop)
    K = read_matrix(folder / "camera-intrinsics.txt", (3, 3))
    for frame in source.frames:
        pose = read_matrix(frame.pose, (4, 4)) if isinstance(frame.pose, Path) else frame.pose
        depth = read_depth_png(frame.depth).astype(np.uint16)
        t = 1_700_000_000.0 + frame.time
        h, w = depth.shape
        yield [
            ("/tf", rosmsg.tf_message([rosmsg.transform_stamped(t, "world", "camera", pose)])),
            (INFO_TOPIC, rosmsg.camera_info(t, "camera", K, w, h)),
            (DEPTH_TOPIC, rosmsg.depth_image(t, "camera", depth)),
        ]


def wait_for_subscriber(session: Any, domain: int, topic: str, timeout: float) -> bool:
    """True once some node holds a subscription token for `topic` (as `ros2 topic info` sees)."""
    deadline = time.monotonic() + timeout
    want = "/" + rmw.topic_name(topic)
    while time.monotonic() < deadline:
        for reply in session.liveliness().get(f"{rmw.ADMIN}/{domain}/**", timeout=1.0):
            if reply.ok is None:
                continue
            try:
                endpoint = rmw.parse_endpoint(str(reply.ok.key_expr))
            except rmw.RmwError:
                continue
            if endpoint.kind == rmw.SUBSCRIPTION and endpoint.topic == want:
                return True
        time.sleep(0.1)
    return False


def play(
    session: Any,
    frames: Iterator[list[tuple[str, Any]]],
    types: dict[str, str],
    *,
    rate: float,
    domain: int = 0,
    static: list[Any] | None = None,
) -> int:
    """Publish every frame's messages at `rate` frames per second; the number of frames."""
    node = RosNode(session, "robot", domain)
    try:
        pubs: dict[str, RosPublisher] = {
            topic: node.publisher(topic, kind, block=True) for topic, kind in types.items()
        }
        if static:
            latched = node.publisher(TF_STATIC, TF, transient_local=True, depth=1)
            latched.publish(rosmsg.tf_message(static))
        time.sleep(0.3)  # let the publishers' declarations reach the subscribers
        n = 0
        began = time.monotonic()
        for messages in frames:
            for topic, msg in messages:
                pubs[topic].publish(msg)
            n += 1
            delay = began + n / rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        time.sleep(0.5)  # a reliable put is queued, not yet delivered: let it drain
        return n
    finally:
        node.close()


TF_STATIC = "/tf_static"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--connect", action="append", default=[], help="Zenoh endpoint to connect to")
    p.add_argument(
        "--listen", default="tcp/127.0.0.1:0", help="Zenoh endpoint to listen on (the robot's)"
    )
    p.add_argument("--domain", type=int, default=0)
    p.add_argument("--rate", type=float, default=50.0, help="frames per second")
    p.add_argument("--start", type=int, default=0)
    p.add_argument("--stop", type=int, default=None)
    p.add_argument("--wait", type=float, default=20.0, help="seconds to wait for a subscriber")
    p.add_argument("kind", choices=["carmen", "rgbd"])
    p.add_argument("path", type=Path)
    args = p.parse_args(argv)
    session = open_session(zenoh_config(mode="peer", listen=[args.listen], connect=args.connect))
    try:
        if args.kind == "carmen":
            frames = carmen_messages(args.path, args.start, args.stop)
            types = {"/tf": TF, "/odom": ODOM, "/scan": SCAN}
            static = [rosmsg.transform_stamped(0.0, "base_link", "laser", LASER_MOUNT)]
            sensor = "/scan"
        else:
            frames = rgbd_messages(args.path, args.start, args.stop)
            types = {"/tf": TF, INFO_TOPIC: INFO, DEPTH_TOPIC: IMAGE}
            static, sensor = [], DEPTH_TOPIC
        if not wait_for_subscriber(session, args.domain, sensor, args.wait):
            sys.stderr.write(f"no subscriber to {sensor} within {args.wait:.0f} s\n")
            return 1
        n = play(session, frames, types, rate=args.rate, domain=args.domain, static=static)
        sys.stdout.write(f"published {n} frames\n")
        return 0
    finally:
        session.close()


if __name__ == "__main__":
    sys.exit(main())
