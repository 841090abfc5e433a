"""A daemon with a `ros2:` source maps a real recording that another process plays as a ROS 2 robot
in rmw_zenoh's wire format: the same map as `colonyd map` of the recording."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
import zenoh.ext
from scipy.spatial import cKDTree

from colonyd.bench.integrate import iou
from colonyd.bench.rosrobot import wait_for_subscriber
from colonyd.mapping import map_source
from plugins.rosbag import cloud_points
from tests.shared import SHARED_DATA
from voxel.octomap_io import read_bt

pytest.importorskip("rosbags")

CARMEN = SHARED_DATA / "carmen" / "freiburg-079-corrected.log.gz"
KITCHEN = SHARED_DATA / "redkitchen-50"
ROOT = Path(__file__).resolve().parents[2]


def play(
    endpoint: str, kind: str, path: Path, stop: int, rate: float, flag: str = "--connect"
) -> subprocess.Popen[bytes]:
    """The robot: a separate process with its own Zenoh session, connected to the daemon (or
    listening on `endpoint`, with `flag="--listen"`)."""
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "colonyd.bench.rosrobot",
            flag,
            endpoint,
            "--stop",
            str(stop),
            "--rate",
            str(rate),
            kind,
            str(path),
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )


def map_live(
    make_colony: Any,
    tmp_path: Path,
    spec: str,
    kind: str,
    path: Path,
    frames: int,
    rate: float,
    resolution: float,
    *,
    env: dict[str, str] | None = None,
    meanwhile: Callable[[str], None] | None = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Occupied keys of the map a daemon made from the played recording, and its source report;
    `meanwhile(endpoint)` runs once the map is complete, before the daemon stops."""
    colony = make_colony("ros2", extra=["--resolution", str(resolution)])
    d = colony.add("robot", [spec], start=False)
    d.env.update({"COLONYD_LOCALISE": "false", "COLONYD_EXPORT_DIR": str(tmp_path / "export")})
    d.env.update(env or {})
    d.start()
    d.wait_listening()
    robot = play(d.endpoint, kind, path, frames, rate)
    out, _ = robot.communicate(timeout=120)
    assert robot.returncode == 0, out.decode(errors="replace")
    reports = colony.wait_status(
        lambda rs: bool(rs) and rs[0]["sources_done"] and not rs[0]["unpublished"], within=30
    )
    assert reports and reports[0]["sources_done"], reports
    source = reports[0]["sources"][0]
    if meanwhile is not None:
        meanwhile(d.endpoint)
    assert d.stop() == 0
    bt = read_bt(tmp_path / "export" / "robot.bt")
    return bt.keys[bt.occupied], source


def late_subscriber(endpoint: str) -> dict[str, Any]:
    """What a ROS 2 subscriber joining now gets: the daemon's tokens (topic -> type and QoS, node
    names) and one decoded message per output topic (transient-local ones from the cache)."""
    from colonyd.runtime import open_session, zenoh_config
    from plugins import rmw

    types = {
        "/colony/map": "nav_msgs/msg/OccupancyGrid",
        "/colony/cloud": "sensor_msgs/msg/PointCloud2",
        "/tf": "tf2_msgs/msg/TFMessage",
        "/colony/objects": "visualization_msgs/msg/MarkerArray",
    }
    got: dict[str, Any] = {}
    session = open_session(
        zenoh_config(mode="peer", listen=["tcp/127.0.0.1:0"], connect=[endpoint])
    )
    try:
        tokens: dict[str, tuple[str, str]] = {}
        nodes: list[str] = []
        deadline = time.monotonic() + 20  # the link and the tokens come up (slowly when loaded)
        while not (nodes and all(t in tokens for t in types)) and time.monotonic() < deadline:
            tokens, nodes = {}, []
            for reply in session.liveliness().get("@ros2_lv/0/**", timeout=2.0):
                key = str(reply.ok.key_expr) if reply.ok is not None else ""
                if "/NN/" in key:
                    nodes.append(key.split("/")[-1])
                elif "/MP/" in key:
                    e = rmw.parse_endpoint(key)
                    tokens[e.topic] = (e.ros_type, e.qos)
            time.sleep(0.1)
        got["tokens"], got["nodes"] = tokens, sorted(nodes)
        done = threading.Event()
        subs = []
        for topic, kind in types.items():

            def on(sample: Any, topic: str = topic, kind: str = kind) -> None:
                rmw.decode_attachment(sample.attachment.to_bytes())
                got.setdefault(
                    topic, rmw.typestore().deserialize_cdr(sample.payload.to_bytes(), kind)
                )
                if all(t in got for t in types):
                    done.set()

            subs.append(
                zenoh.ext.declare_advanced_subscriber(
                    session,
                    rmw.data_key(0, topic, kind, rmw.type_hash(kind)),
                    on,
                    history=zenoh.ext.HistoryConfig(detect_late_publishers=True),
                )
            )
        done.wait(30.0)
    finally:
        session.close()
    return got


def plane_iou(cells: np.ndarray, occupied: np.ndarray) -> float:
    """IoU of occupied grid cells (N, 2 keys) and the xy of occupied voxel keys."""
    plane = np.unique(occupied[:, :2], axis=0)
    return iou(np.column_stack([cells, np.zeros(len(cells), np.int64)]),
               np.column_stack([plane, np.zeros(len(plane), np.int64)]))  # fmt: skip


def grid_cells(grid: Any, resolution: float) -> np.ndarray:
    """Keys (N, 2) of the occupied cells of an OccupancyGrid."""
    cells = np.asarray(grid.data, np.int8).reshape(grid.info.height, grid.info.width)
    iy, ix = np.nonzero(cells == 100)
    corner = np.array([grid.info.origin.position.x, grid.info.origin.position.y])
    return np.round(np.column_stack([ix, iy]) + corner / resolution).astype(np.int64)


@pytest.mark.skipif(not CARMEN.is_file(), reason=f"CARMEN log not found at {CARMEN}")
def test_carmen_log_played_as_laserscan_odometry_tf_maps_like_colonyd_map(
    make_colony: Any, tmp_path: Path
) -> None:
    n = 240
    offline = map_source(f"replay:{CARMEN},stop={n}", 0.1, tmp_path / "offline", progress=False)
    assert offline.frames == n
    ref = read_bt(tmp_path / "offline" / "map.bt")
    occupied = ref.keys[ref.occupied]
    spec = f"ros2:scan=/scan,odom=/odom,frame=map,max_range=80,frames={n},queue=1000"
    received: dict[str, Any] = {}

    def join_late(endpoint: str) -> None:
        """A late subscriber's view, once the daemon's output has its last map (a loaded one
        publishes it a while after the last scan: ask again for up to 30 s)."""
        deadline = time.monotonic() + 30
        while True:
            got = late_subscriber(endpoint)
            grid = got.get("/colony/map")
            done = grid is not None and plane_iou(grid_cells(grid, 0.1), occupied) >= 0.99
            if done or time.monotonic() > deadline:
                received.update(got)
                return
            time.sleep(0.5)

    live, source = map_live(
        make_colony, tmp_path, spec, "carmen", CARMEN, n, 60.0, 0.1,
        env={"COLONYD_ROS2_PUBLISH": "true", "COLONYD_ROS2_PERIOD_S": "0.5"},
        meanwhile=join_late,
    )  # fmt: skip
    assert source["delivered"] == n and source["skipped"] == 0, source
    score = iou(live, occupied)
    print(f"IoU {score:.4f}")  # shown with pytest -s
    assert score >= 0.99, f"occupied IoU {score:.4f} ({len(live)} vs {len(occupied)})"
    # The daemon's ROS 2 outputs, as a subscriber joining late sees them.
    assert received["tokens"]["/colony/map"] == ("nav_msgs/msg/OccupancyGrid", "1:1:1,1:,:,:,,")
    assert "/colony/cloud" in received["tokens"] and "/tf" in received["tokens"]
    assert received["nodes"] == ["colonyd"]
    grid = received["/colony/map"]
    assert grid.header.frame_id == "colony" and grid.info.resolution == pytest.approx(0.1)
    score = plane_iou(grid_cells(grid, 0.1), occupied)
    print(f"IoU {score:.4f}")  # shown with pytest -s
    assert score >= 0.99, f"OccupancyGrid occupied cells IoU {score:.4f}"
    xyz, _ = cloud_points(received["/colony/cloud"])
    # each point in (or, published at +-1/2 voxel, on the face of) an occupied voxel, nearly
    # every occupied voxel holding one; the voxels' surface points (mean hits), not centres
    centres = (live + 0.5) * 0.1
    off, _ = cKDTree(centres).query(xyz, p=np.inf)
    back, _ = cKDTree(xyz).query(centres, p=np.inf)
    assert off.max() <= 0.05 + 1e-5 and np.mean(back <= 0.05 + 1e-5) >= 0.99
    assert len(xyz) <= len(live) * 1.01
    assert np.abs(xyz[:, :2] - (np.floor(xyz[:, :2] / 0.1) + 0.5) * 0.1).max(axis=1).mean() > 0.01
    tf = received["/tf"].transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ("colony", "map")
    markers = received["/colony/objects"].markers  # no objects in a laser log: only DELETEALL
    assert [(m.action, m.header.frame_id) for m in markers] == [(3, "colony")]


@pytest.mark.skipif(not KITCHEN.is_dir(), reason=f"7-Scenes frames not found at {KITCHEN}")
def test_7scenes_played_as_depth_image_camera_info_tf_maps_like_colonyd_map(
    make_colony: Any, tmp_path: Path
) -> None:
    n = 10
    offline = map_source(
        f"replay:{KITCHEN},stop={n},stride=4", 0.05, tmp_path / "offline", progress=False
    )
    assert offline.frames == n
    ref = read_bt(tmp_path / "offline" / "map.bt")
    spec = (
        "ros2:depth=/camera/depth/image_rect_raw,camera_info=/camera/depth/camera_info,"
        f"frame=world,max_range=10,stride=4,frames={n}"
    )
    live, source = map_live(make_colony, tmp_path, spec, "rgbd", KITCHEN, n, 10.0, 0.05)
    assert source["delivered"] == n and source["skipped"] == 0, source
    score = iou(live, ref.keys[ref.occupied])
    print(f"IoU {score:.4f}")  # shown with pytest -s
    assert score >= 0.99, f"occupied IoU {score:.4f} ({len(live)} vs {ref.occupied.sum()})"


def test_hostile_samples_are_counted_and_logged_and_the_source_goes_on(
    make_colony: Any, tmp_path: Path
) -> None:
    """Wrong type, bad hash, truncated CDR, missing or short attachment, unknown encoding, a
    100 MB sample and a TF gap: each rejected with its reason; the frames around them map."""
    from colonyd import rosmsg
    from colonyd.rosgraph import RosNode
    from colonyd.runtime import open_session, zenoh_config
    from plugins import rmw

    colony = make_colony("ros2")
    spec = "ros2:depth=/cam/depth,camera_info=/cam/info,frame=world,tf_wait=0.3,frames=3"
    d = colony.add("robot", [spec], start=False)
    d.env["COLONYD_LOCALISE"] = "false"
    d.start()
    d.wait_listening()
    session = open_session(
        zenoh_config(mode="peer", listen=["tcp/127.0.0.1:0"], connect=[d.endpoint])
    )
    node = RosNode(session, "hostile")
    try:
        image_t, info_t = "sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo"
        tf = node.publisher("/tf", "tf2_msgs/msg/TFMessage", block=True)
        info = node.publisher("/cam/info", info_t, block=True)
        image = node.publisher("/cam/depth", image_t, block=True)
        K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
        depth = np.full((48, 64), 2000, np.uint16)

        def good(t: float, attachment: bytes | None = None) -> None:
            tf.publish(rosmsg.tf_message([rosmsg.transform_stamped(t, "world", "cam", np.eye(4))]))
            info.publish(rosmsg.camera_info(t, "cam", K, 64, 48))
            payload = bytes(
                rmw.typestore().serialize_cdr(rosmsg.depth_image(t, "cam", depth), image_t)
            )
            if attachment is None:
                image.put(payload)
            else:
                session.put(image.key, payload, attachment=attachment)

        # The daemon's subscribers are declared before its subscription tokens: once a token is
        # seen, every topic is subscribed (a fixed sleep lost the first frame when loaded).
        assert wait_for_subscriber(session, 0, "/cam/depth", 30.0), "no subscriber of /cam/depth"
        time.sleep(0.3)  # our publishers' declarations reach the daemon (as rosrobot.play)
        good(100.0)
        raw = bytes(rmw.typestore().serialize_cdr(rosmsg.depth_image(101.0, "cam", depth), image_t))
        gid = b"\x01" * 16
        ok = rmw.Attachment(1, 0, gid).encode()
        odom_key = rmw.data_key(
            0, "/cam/depth", "nav_msgs/msg/Odometry", rmw.type_hash("nav_msgs/msg/Odometry")
        )
        bad_hash = rmw.data_key(0, "/cam/depth", image_t, "RIHS01_" + "0" * 64)
        session.put(odom_key, raw, attachment=ok)  # wrong type for the topic
        session.put(bad_hash, raw, attachment=ok)  # another definition of Image
        session.put(image.key, raw[:40], attachment=ok)  # truncated CDR
        session.put(image.key, raw)  # no attachment
        session.put(image.key, raw, attachment=b"\x00" * 20)  # attachment of unknown format
        rgb = rosmsg.depth_image(101.0, "cam", depth)
        rgb.encoding = "rgb8"
        session.put(image.key, bytes(rmw.typestore().serialize_cdr(rgb, image_t)), attachment=ok)
        session.put(
            image.key,
            bytes(100 << 20),
            attachment=ok,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )  # 100 MB, delivered
        gap = rosmsg.depth_image(500.0, "cam", depth)  # no transform near t = 500
        session.put(  # blocking: behind the 100 MB sample a dropping put lost it when loaded
            image.key,
            bytes(rmw.typestore().serialize_cdr(gap, image_t)),
            attachment=ok,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        colony.wait_status(  # the eight above handled (the 100 MB one takes a while when loaded)
            lambda rs: bool(rs) and sum(rs[0]["sources"][0]["reasons"].values()) >= 8, within=30
        )
        legacy = zenoh.ext.z_serialize(
            ("sequence_number", zenoh.ext.Int64(9), "source_timestamp", zenoh.ext.Int64(0),
             "source_gid", gid)
        ).to_bytes()  # fmt: skip
        good(102.0, attachment=legacy)
        good(103.0)
        reports = colony.wait_status(
            lambda rs: bool(rs) and rs[0]["sources"][0]["delivered"] >= 3, within=30
        )
    finally:
        node.close()
        session.close()
    source = reports[0]["sources"][0]
    assert source["delivered"] == 3, source
    assert source["reasons"] == {
        "WrongTypeError": 2,
        "CdrError": 1,
        "RmwError": 2,
        "SensorInputError": 1,
        "TooLargeError": 1,
        "TfGapError": 1,
    }, source
    assert d.alive()
    logs = d.log_path.read_text()
    for text in (
        "expected sensor_msgs/msg/Image, found nav_msgs/msg/Odometry",
        "expected CDR of sensor_msgs/msg/Image",
        "attachment: expected rmw_zenoh's sequence number, time and GID, found none",
        "expected 16UC1 or 32FC1 depth, found 'rgb8'",
        "expected at most 64.0 MiB, found 100.0",
        "TF gap: world -> cam",
    ):
        assert text in logs, text


@pytest.mark.skipif(not CARMEN.is_file(), reason=f"CARMEN log not found at {CARMEN}")
def test_a_third_party_rmw_zenoh_client_feeds_the_daemon_and_reads_its_map(
    make_colony: Any, tmp_path: Path
) -> None:
    """zenoh-ros2-sdk (PyPI, not ours) publishes scans the daemon maps, and a late subscriber of it
    gets the daemon's OccupancyGrid and PointCloud2."""
    pytest.importorskip("zenoh_ros2_sdk")
    n = 60
    map_source(f"replay:{CARMEN},stop={n}", 0.1, tmp_path / "offline", progress=False)
    ref = read_bt(tmp_path / "offline" / "map.bt")
    occupied = ref.keys[ref.occupied]
    colony = make_colony("ros2")
    spec = f"ros2:scan=/scan,odom=/odom,frame=map,max_range=80,frames={n},queue=1000"
    # A second live source that never gets data, listed first: each live source maps in a
    # thread of its own, so the scans map all the same.
    idle = "ros2:cloud=/points,odom=/odom,frame=map"
    d = colony.add("robot", [idle, spec], start=False)
    d.env.update(
        {
            "COLONYD_LOCALISE": "false",
            "COLONYD_ROS2_PUBLISH": "true",
            "COLONYD_ROS2_PERIOD_S": "0.5",
            "COLONYD_ROS2_MAP_TOPIC": "/colony_map",  # one chunk: the SDK finds the cache of
            "COLONYD_ROS2_CLOUD_TOPIC": "/colony_cloud",  # transient-local topics only then
        }
    )
    d.start()
    d.wait_listening()

    def client(*args: str) -> dict[str, Any]:
        run = subprocess.run(
            [sys.executable, str(Path(__file__).with_name("ros2_sdk_client.py")), args[0],
             str(d.port), str(tmp_path / "msgs"), *args[1:]],
            check=False, cwd=ROOT, capture_output=True, timeout=120,
            env={**os.environ, "PYTHONPATH": str(ROOT)},
        )  # fmt: skip
        assert run.returncode == 0, run.stderr.decode(errors="replace")[-3000:]
        return dict(json.loads(run.stdout.decode().strip().splitlines()[-1]))

    assert client("publish", str(CARMEN), str(n)) == {"published": n}
    reports = colony.wait_status(
        lambda rs: bool(rs) and rs[0]["sources"][1]["delivered"] == n and not rs[0]["unpublished"],
        within=30,
    )
    assert reports[0]["sources"][1]["delivered"] == n, reports[0]["sources"]
    assert reports[0]["sources"][0]["delivered"] == 0 and not reports[0]["sources_done"]
    time.sleep(1.5)  # the last map goes out within ros2_period_s

    def sdk_cells(grid: dict[str, Any]) -> np.ndarray:
        return np.round(np.array(grid["occupied"]) + np.array(grid["corner"]) / 0.1).astype(
            np.int64
        )

    deadline = time.monotonic() + 30  # a loaded daemon publishes its last map later: ask again
    while True:
        got = client("subscribe")
        done = "grid" in got and plane_iou(sdk_cells(got["grid"]), occupied) >= 0.99
        if done or time.monotonic() > deadline:
            break
        time.sleep(0.5)
    assert "grid" in got and "cloud" in got, got
    grid = got["grid"]
    assert grid["frame"] == "colony" and grid["resolution"] == pytest.approx(0.1)
    score = plane_iou(sdk_cells(grid), occupied)
    print(f"IoU {score:.4f}")  # shown with pytest -s
    assert score >= 0.99, f"OccupancyGrid from the SDK: occupied cells IoU {score:.4f}"
    assert got["cloud"]["fields"] == ["x", "y", "z", "rgb"]
    assert got["cloud"]["points"] == pytest.approx(len(occupied), rel=0.01)


@pytest.mark.skipif(not CARMEN.is_file(), reason=f"CARMEN log not found at {CARMEN}")
def test_colonyd_map_reads_a_robot_through_its_own_session(tmp_path: Path) -> None:
    """`connect=`: the source opens its own session to the robot (here the robot listens)."""
    from colonyd.bench.launcher import free_port

    n = 50
    offline = map_source(f"replay:{CARMEN},stop={n}", 0.1, tmp_path / "offline", progress=False)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    robot = play(endpoint, "carmen", CARMEN, n, 50.0, flag="--listen")
    try:
        time.sleep(1.0)  # the robot listens
        spec = f"ros2:scan=/scan,odom=/odom,frame=map,max_range=80,frames={n},connect={endpoint}"
        run = subprocess.run(
            [sys.executable, "-m", "colonyd", "map", "--source", spec, "--out",
             str(tmp_path / "live")],
            check=False, cwd=ROOT, capture_output=True, timeout=120,
        )  # fmt: skip
        assert run.returncode == 0, run.stderr.decode(errors="replace")[-3000:]
        assert f"{n} frames (0 skipped)" in run.stdout.decode()
    finally:
        robot.communicate(timeout=60)
    live = read_bt(tmp_path / "live" / "map.bt")
    ref = read_bt(tmp_path / "offline" / "map.bt")
    assert offline.frames == n
    score = iou(live.keys[live.occupied], ref.keys[ref.occupied])
    print(f"IoU {score:.4f}")  # shown with pytest -s
    assert score >= 0.99, f"occupied IoU {score:.4f}"
