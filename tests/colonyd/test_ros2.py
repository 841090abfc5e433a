"""A daemon with a `ros2:` source maps a real recording that another process plays as a ROS 2 robot
in rmw_zenoh's wire format: the same map as `colonyd map` of the recording."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from colonyd.bench.integrate import iou
from colonyd.mapping import map_source
from tests.shared import SHARED_DATA
from voxel.octomap_io import read_bt

pytest.importorskip("rosbags")

CARMEN = SHARED_DATA / "carmen" / "freiburg-079-corrected.log.gz"
KITCHEN = SHARED_DATA / "redkitchen-50"
ROOT = Path(__file__).resolve().parents[2]


def play(endpoint: str, kind: str, path: Path, stop: int, rate: float) -> subprocess.Popen[bytes]:
    """The robot: a separate process with its own Zenoh session, connected to the daemon."""
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "colonyd.bench.rosrobot",
            "--connect",
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
) -> tuple[np.ndarray, dict[str, Any]]:
    """Occupied keys of the map a daemon made from the played recording, and its source report."""
    colony = make_colony("ros2", extra=["--resolution", str(resolution)])
    d = colony.add("robot", [spec], start=False)
    d.env.update({"COLONYD_LOCALISE": "false", "COLONYD_EXPORT_DIR": str(tmp_path / "export")})
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
    assert d.stop() == 0
    bt = read_bt(tmp_path / "export" / "robot.bt")
    return bt.keys[bt.occupied], source


@pytest.mark.skipif(not CARMEN.is_file(), reason=f"CARMEN log not found at {CARMEN}")
def test_carmen_log_played_as_laserscan_odometry_tf_maps_like_colonyd_map(
    make_colony: Any, tmp_path: Path
) -> None:
    n = 240
    offline = map_source(f"replay:{CARMEN},stop={n}", 0.1, tmp_path / "offline", progress=False)
    assert offline.frames == n
    ref = read_bt(tmp_path / "offline" / "map.bt")
    spec = f"ros2:scan=/scan,odom=/odom,frame=map,max_range=80,frames={n},queue=1000"
    live, source = map_live(make_colony, tmp_path, spec, "carmen", CARMEN, n, 60.0, 0.1)
    assert source["delivered"] == n and source["skipped"] == 0, source
    score = iou(live, ref.keys[ref.occupied])
    assert score >= 0.99, f"occupied IoU {score:.4f} ({len(live)} vs {ref.occupied.sum()})"


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
    assert score >= 0.99, f"occupied IoU {score:.4f} ({len(live)} vs {ref.occupied.sum()})"
