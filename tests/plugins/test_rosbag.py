"""Tests of the ROS bag reader on bags written here with rosbags (ROS 2 and ROS 1)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="rosbags is the [ros] extra")

from rosbags.typesys import Stores, get_typestore

from plugins.errors import SourceError, SourceSpecError
from plugins.rosbag import RosbagSource
from plugins.source import open_source

TS2 = get_typestore(Stores.ROS2_HUMBLE)
TS1 = get_typestore(Stores.ROS1_NOETIC)


def header(ts, stamp: float, frame: str = "base"):
    Time = ts.types["builtin_interfaces/msg/Time"]
    Header = ts.types["std_msgs/msg/Header"]
    sec = int(stamp)
    t = Time(sec=sec, nanosec=int((stamp - sec) * 1e9))
    if ts is TS1:
        return Header(seq=0, stamp=t, frame_id=frame)
    return Header(stamp=t, frame_id=frame)


def laser_scan(ts, stamp: float, ranges: np.ndarray):
    LaserScan = ts.types["sensor_msgs/msg/LaserScan"]
    n = len(ranges)
    return LaserScan(
        header=header(ts, stamp),
        angle_min=-math.pi / 2,
        angle_max=math.pi / 2,
        angle_increment=math.pi / (n - 1),
        time_increment=0.0,
        scan_time=0.1,
        range_min=0.05,
        range_max=20.0,
        ranges=ranges.astype(np.float32),
        intensities=np.zeros(0, np.float32),
    )


def odometry(ts, stamp: float, x: float):
    m = ts.types
    pose = m["geometry_msgs/msg/Pose"](
        position=m["geometry_msgs/msg/Point"](x=x, y=0.0, z=0.0),
        orientation=m["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
    )
    pwc = m["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36))
    vec = m["geometry_msgs/msg/Vector3"]
    twist = m["geometry_msgs/msg/Twist"](
        linear=vec(x=0.0, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=0.0)
    )
    twc = m["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36))
    return m["nav_msgs/msg/Odometry"](
        header=header(ts, stamp, "odom"), child_frame_id="base", pose=pwc, twist=twc
    )


def point_cloud(ts, stamp: float, xyz: np.ndarray, truncate: bool = False):
    m = ts.types
    PF = m["sensor_msgs/msg/PointField"]
    fields = [
        PF(name=n, offset=4 * i, datatype=7, count=1)
        for i, n in enumerate(["x", "y", "z", "intensity"])
    ]
    data = np.column_stack([xyz, np.arange(len(xyz))]).astype("<f4").tobytes()
    raw = np.frombuffer(data, np.uint8)
    if truncate:
        raw = raw[:-5]
    return m["sensor_msgs/msg/PointCloud2"](
        header=header(ts, stamp),
        height=1,
        width=len(xyz),
        fields=fields,
        is_bigendian=False,
        point_step=16,
        row_step=16 * len(xyz),
        data=raw.copy(),
        is_dense=True,
    )


def write_ros2(path: Path, items: list[tuple[str, float, object]]) -> None:
    from rosbags.rosbag2 import Writer

    with Writer(path, version=8) as writer:
        conns = {}
        for topic, stamp, msg in items:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msg.__msgtype__, typestore=TS2)
            writer.write(conns[topic], int(stamp * 1e9), TS2.serialize_cdr(msg, msg.__msgtype__))


def test_ros2_laser_scans_with_odometry(tmp_path: Path) -> None:
    ranges = np.full(181, 2.0)
    ranges[90] = np.inf
    items = []
    for i in range(5):
        items.append(("/odom", i * 0.1, odometry(TS2, i * 0.1, x=0.5 * i)))
        items.append(("/scan", i * 0.1 + 0.01, laser_scan(TS2, i * 0.1 + 0.01, ranges)))
    write_ros2(tmp_path / "bag", items)
    source = open_source(f"replay:{tmp_path / 'bag'},max_range=20")
    assert isinstance(source, RosbagSource) and source.topic == "/scan" and source.odom == "/odom"
    scans = list(source)
    assert len(scans) == len(source) == 5
    for i, obs in enumerate(scans):
        np.testing.assert_allclose(obs.origin, [0.5 * i, 0.0, 0.0])
        assert obs.no_return.sum() == 1
        np.testing.assert_allclose(
            np.linalg.norm(obs.points[~obs.no_return], axis=1), 2.0, rtol=1e-6
        )
        assert obs.time == pytest.approx(i * 0.1 + 0.01)


def test_ros2_point_clouds_bad_frame_skipped(tmp_path: Path) -> None:
    xyz = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [np.nan, 0.0, 0.0]])
    items = [
        ("/points", 0.1, point_cloud(TS2, 0.1, xyz)),
        ("/points", 0.2, point_cloud(TS2, 0.2, xyz, truncate=True)),
        ("/points", 0.3, point_cloud(TS2, 0.3, xyz)),
    ]
    write_ros2(tmp_path / "bag", items)
    source = RosbagSource(tmp_path / "bag")
    clouds = list(source)
    assert len(clouds) == 2 and source.stats.skipped == 1
    np.testing.assert_allclose(clouds[0].points, xyz[:2], rtol=1e-6)
    np.testing.assert_allclose(clouds[0].scalars["intensity"], [0.0, 1.0])
    assert "expected 3 points of 16 bytes, found 43 bytes" in source.stats.first_errors[0]


def test_ros2_depth_images_need_camera_info(tmp_path: Path) -> None:
    m = TS2.types
    depth = np.full((4, 6), 1500, "<u2")
    image = m["sensor_msgs/msg/Image"](
        header=header(TS2, 0.1),
        height=4,
        width=6,
        encoding="16UC1",
        is_bigendian=0,
        step=12,
        data=np.frombuffer(depth.tobytes(), np.uint8).copy(),
    )
    roi = m["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    K = np.array([100.0, 0, 3, 0, 100.0, 2, 0, 0, 1])
    info = m["sensor_msgs/msg/CameraInfo"](
        header=header(TS2, 0.1),
        height=4,
        width=6,
        distortion_model="plumb_bob",
        d=np.zeros(5),
        k=K,
        r=np.eye(3).reshape(-1),
        p=np.zeros(12),
        binning_x=0,
        binning_y=0,
        roi=roi,
    )
    write_ros2(tmp_path / "only_image", [("/depth", 0.1, image)])
    with pytest.raises(
        SourceSpecError, match="expected a CameraInfo topic for depth images on /depth, found none"
    ):
        RosbagSource(tmp_path / "only_image")
    write_ros2(tmp_path / "bag", [("/info", 0.05, info), ("/depth", 0.1, image)])
    obs = list(RosbagSource(tmp_path / "bag"))
    assert len(obs) == 1 and len(obs[0]) == 24
    np.testing.assert_allclose(obs[0].points[:, 2], 1.5)


def test_ros1_bag(tmp_path: Path) -> None:
    from rosbags.rosbag1 import Writer

    path = tmp_path / "run.bag"
    msg = laser_scan(TS1, 1.0, np.full(11, 3.0))
    with Writer(path) as writer:
        conn = writer.add_connection("/base_scan", msg.__msgtype__, typestore=TS1)
        writer.write(conn, int(1e9), TS1.serialize_ros1(msg, msg.__msgtype__))
    scans = list(open_source(f"replay:{path}"))
    assert len(scans) == 1 and len(scans[0]) == 11
    np.testing.assert_allclose(np.linalg.norm(scans[0].points, axis=1), 3.0, rtol=1e-6)


def test_bad_bags(tmp_path: Path) -> None:
    bad = tmp_path / "broken.bag"
    bad.write_bytes(b"not a bag at all")
    with pytest.raises(
        SourceError, match=r"broken\.bag: expected a readable ROS 1 or ROS 2 bag, found"
    ):
        RosbagSource(bad)
    write_ros2(tmp_path / "bag", [("/odom", 0.1, odometry(TS2, 0.1, 0.0))])
    with pytest.raises(
        SourceSpecError, match="expected a LaserScan, PointCloud2 or Image topic, found None"
    ):
        RosbagSource(tmp_path / "bag")


def test_sensor_mount_moves_the_scans_into_the_body(tmp_path: Path) -> None:
    ranges = np.full(181, 2.0)
    items = [
        ("/odom", 0.0, odometry(TS2, 0.0, x=1.0)),
        ("/scan", 0.01, laser_scan(TS2, 0.01, ranges)),
    ]
    write_ros2(tmp_path / "bag", items)
    plain = next(iter(open_source(f"replay:{tmp_path / 'bag'}")))
    (mounted,) = list(open_source(f"replay:{tmp_path / 'bag'},mount=0.2/0/0.3/90"))
    np.testing.assert_allclose(plain.origin, [1.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(mounted.origin, [1.2, 0.0, 0.3], atol=1e-9)
    np.testing.assert_allclose(mounted.pose[:3, 0], [0.0, 1.0, 0.0], atol=1e-9)  # turned 90°
    with pytest.raises(SourceSpecError, match=r"mount: expected x/y/z/yaw_deg.*found '1/2'"):
        open_source(f"replay:{tmp_path / 'bag'},mount=1/2")
