"""The `ros2:` source on its own: spec checks, and PointCloud2 / 32FC1 depth / TF / Humble keys
over two real Zenoh sessions on loopback."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from colonyd import rosmsg
from colonyd.bench.launcher import free_port
from colonyd.bench.rosrobot import wait_for_subscriber
from colonyd.rosgraph import RosNode
from colonyd.runtime import open_session, zenoh_config
from plugins.checks import pose_matrix
from plugins.errors import SourceSpecError
from plugins.observation import Observation
from plugins.source import open_source

pytest.importorskip("rosbags")


@pytest.mark.parametrize(
    ("spec", "match"),
    [
        ("ros2:odom=/odom", "exactly one of scan=, cloud=, depth="),
        ("ros2:scan=/a,cloud=/b,odom=/odom", "exactly one of scan=, cloud=, depth="),
        ("ros2:depth=/d,frame=map", "expected camera_info= with depth="),
        ("ros2:scan=/scan", "expected frame= .* or odom="),
        ("ros2:scan=/sc an,frame=map", "option 'scan': topic: expected a ROS 2 topic name"),
        ("ros2:scan=/scan,frame=map,queue=0", "option 'queue'"),
    ],
)
def test_bad_specs_say_what_was_expected(spec: str, match: str) -> None:
    with pytest.raises(SourceSpecError, match=match):
        open_source(spec)


@pytest.fixture
def sessions() -> Iterator[tuple[Any, Any]]:
    """A robot session listening on loopback and a mapping session connected to it."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    robot = open_session(zenoh_config(listen=[endpoint]))
    mapper = open_session(zenoh_config(listen=["tcp/127.0.0.1:0"], connect=[endpoint]))
    try:
        yield robot, mapper
    finally:
        mapper.close()
        robot.close()


def collect(spec: str, sessions: tuple[Any, Any], frames: int, publish: Any) -> list[Observation]:
    """Observations of `spec` read through the mapping session while `publish()` runs in a
    thread, once the robot session sees the source's subscription (a fixed 1 s could lose the
    first frames to a source still starting on a loaded machine)."""
    robot, mapper = sessions
    options = dict(kv.split("=", 1) for kv in spec.split(":", 1)[1].split(","))
    sensor = next(options[k] for k in ("scan", "cloud", "depth") if k in options)
    stop = threading.Event()
    source = open_source(spec, session=lambda: mapper, stop=stop)
    timer = threading.Timer(30.0, stop.set)
    timer.start()
    out: list[Observation] = []

    def when_subscribed() -> None:
        if wait_for_subscriber(robot, 0, sensor, 25.0):  # (else: too few frames, said below)
            publish()

    thread = threading.Thread(target=when_subscribed)
    thread.start()
    try:
        for obs in source:
            out.append(obs)
            if len(out) >= frames:
                break
    finally:
        stop.set()
        timer.cancel()
        thread.join()
    return out


def test_a_source_that_hears_nothing_says_what_to_check(
    sessions: tuple[Any, Any], monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A wrong topic, domain or router endpoint waited in silence (`colonyd map` with nobody
    publishing ran until killed): after QUIET_S without a sample the source says what to check."""
    import plugins.ros2

    monkeypatch.setattr(plugins.ros2, "QUIET_S", 0.3)
    _, mapper = sessions
    stop = threading.Event()
    source = open_source("ros2:scan=/nobody,odom=/odom,domain=7", session=lambda: mapper, stop=stop)
    thread = threading.Thread(target=lambda: list(source))
    with caplog.at_level("WARNING", logger="plugins.ros2"):
        thread.start()
        try:
            deadline = time.monotonic() + 20.0
            while "nothing received" not in caplog.text and time.monotonic() < deadline:
                time.sleep(0.05)
        finally:
            stop.set()
            thread.join(10.0)
    assert not thread.is_alive()
    assert (
        "nothing received in 0.3 s on /nobody, /odom, /tf, /tf_static (ROS domain 7, through the "
        "daemon's Zenoh session): expected the robot's rmw_zenoh graph to publish them"
    ) in caplog.text


def test_point_clouds_are_placed_by_tf_at_their_stamps(sessions: tuple[Any, Any]) -> None:
    robot, mapper = sessions
    node = RosNode(robot, "lidar")
    mount = pose_matrix(0.2, 0.0, 0.5, 0.3)
    body = [pose_matrix(float(i), 0.5 * i, 0.0, 0.1 * i) for i in range(3)]
    xyz = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.5], [3.0, -1.0, 0.2]])

    def publish() -> None:
        static = node.publisher(
            "/tf_static", "tf2_msgs/msg/TFMessage", transient_local=True, depth=1
        )
        odom = node.publisher("/odom", "nav_msgs/msg/Odometry")
        cloud = node.publisher("/points", "sensor_msgs/msg/PointCloud2")
        static.publish(rosmsg.tf_message([rosmsg.transform_stamped(0, "base", "lidar", mount)]))
        time.sleep(0.3)
        for i, pose in enumerate(body):
            odom.publish(rosmsg.odometry(10.0 + i, "odom", "base", pose))
            cloud.publish(rosmsg.point_cloud(10.0 + i, "lidar", xyz, None))

    try:
        got = collect("ros2:cloud=/points,odom=/odom,max_range=50", (robot, mapper), 3, publish)
    finally:
        node.close()
    assert len(got) == 3
    for i, obs in enumerate(got):
        assert obs.time == pytest.approx(10.0 + i)
        np.testing.assert_allclose(obs.points_world(), xyz @ (body[i] @ mount)[:3, :3].T
                                   + (body[i] @ mount)[:3, 3], atol=1e-5)  # fmt: skip
        np.testing.assert_allclose(obs.odometry, body[i], atol=1e-9)


def test_float_depth_and_humble_keys_without_type_hash(sessions: tuple[Any, Any]) -> None:
    robot, mapper = sessions
    node = RosNode(robot, "camera", type_hashes=False)  # as Humble's rmw_zenoh keys them
    K = np.array([[50.0, 0.0, 16.0], [0.0, 50.0, 12.0], [0.0, 0.0, 1.0]])
    depth = np.full((24, 32), 1.5, np.float32)
    depth[0, 0] = np.nan

    def publish() -> None:
        tf = node.publisher("/tf", "tf2_msgs/msg/TFMessage")
        info = node.publisher("/cam/info", "sensor_msgs/msg/CameraInfo")
        image = node.publisher("/cam/depth", "sensor_msgs/msg/Image")
        pose = pose_matrix(1.0, 2.0, 1.0, 0.5)
        for i in range(2):
            tf.publish(rosmsg.tf_message([rosmsg.transform_stamped(5.0 + i, "map", "cam", pose)]))
            info.publish(rosmsg.camera_info(5.0 + i, "cam", K, 32, 24))
            image.publish(rosmsg.depth_image(5.0 + i, "cam", depth))

    try:
        got = collect(
            "ros2:depth=/cam/depth,camera_info=/cam/info,frame=map", (robot, mapper), 2, publish
        )
    finally:
        node.close()
    assert len(got) == 2
    assert len(got[0]) == 24 * 32 - 1
    np.testing.assert_allclose(got[0].points[:, 2], 1.5)
    assert got[0].depth is not None
    np.testing.assert_allclose(got[0].depth.K, K)
    np.testing.assert_allclose(got[1].origin, [1.0, 2.0, 1.0], atol=1e-9)
