"""ROS 1/2 bags read with rosbags ([ros] extra): LaserScan, PointCloud2, depth Image, Odometry."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import Field

from plugins.adapter import SensorAdapter, load_adapter
from plugins.checks import parse_mount, quaternion_to_matrix
from plugins.depth import DepthFrame
from plugins.errors import ParseError, SensorInputError, SourceError, SourceSpecError
from plugins.lidar import Cloud, Scan
from plugins.observation import Observation
from plugins.spec import Options
from plugins.stream import StreamStats

SCAN = "sensor_msgs/msg/LaserScan"
CLOUD = "sensor_msgs/msg/PointCloud2"
IMAGE = "sensor_msgs/msg/Image"
INFO = "sensor_msgs/msg/CameraInfo"
ODOM = "nav_msgs/msg/Odometry"

#: PointCloud2 datatype codes to numpy dtypes.
POINT_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def _any_reader() -> Any:
    """A factory opening a bag with rosbags' AnyReader (ROS 2 Humble types for bags without
    definitions)."""
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        msg = "ROS bags: expected the rosbags package (pip install 'colony[ros]'), found it missing"
        raise SourceError(msg) from None
    typestore = get_typestore(Stores.ROS2_HUMBLE)

    def open_bag(paths: list[Path]) -> Any:
        try:
            return AnyReader(paths, default_typestore=typestore)
        except Exception as exc:  # noqa: BLE001 - rosbags raises its own error types for unreadable bags
            msg = (
                f"{paths[0]}: expected a readable ROS 1 or ROS 2 bag, "
                f"found {type(exc).__name__}: {exc}"
            )
            raise SourceError(msg) from None

    return open_bag


def pose_of_odometry(msg: Any) -> np.ndarray:
    """Body pose (4, 4) of a nav_msgs/Odometry message."""
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    pose = np.eye(4)
    pose[:3, :3] = quaternion_to_matrix(q.x, q.y, q.z, q.w)
    pose[:3, 3] = (p.x, p.y, p.z)
    return pose


def cloud_points(msg: Any, field: str = "PointCloud2") -> tuple[np.ndarray, np.ndarray | None]:
    """(N, 3) xyz and optional (N,) intensity of a PointCloud2 message."""
    fields = {f.name: f for f in msg.fields}
    for name in ("x", "y", "z"):
        if name not in fields:
            msg_ = f"{field}: expected fields x, y, z, found {sorted(fields)}"
            raise SensorInputError(msg_)
    n = int(msg.width) * int(msg.height)
    data = np.asarray(msg.data, dtype=np.uint8)
    if data.size < n * int(msg.point_step):
        msg_ = f"{field}: expected {n} points of {msg.point_step} bytes, found {data.size} bytes"
        raise SensorInputError(msg_)
    order = ">" if msg.is_bigendian else "<"
    names = [name for name in ("x", "y", "z", "intensity") if name in fields]
    for name in names:
        if fields[name].datatype not in POINT_TYPES:
            msg_ = (
                f"{field}.{name}: expected a datatype in {sorted(POINT_TYPES)}, "
                f"found {fields[name].datatype}"
            )
            raise SensorInputError(msg_)
    dtype = np.dtype(
        {
            "names": names,
            "formats": [order + POINT_TYPES[fields[k].datatype] for k in names],
            "offsets": [fields[k].offset for k in names],
            "itemsize": int(msg.point_step),
        }
    )
    rows = data[: n * int(msg.point_step)].view(dtype)
    xyz = np.column_stack([rows[k].astype(np.float64) for k in ("x", "y", "z")])
    intensity = rows["intensity"].astype(np.float32) if "intensity" in names else None
    return xyz, intensity


def depth_image(msg: Any, field: str = "Image") -> np.ndarray:
    """A depth Image message (16UC1 millimetres or 32FC1 metres) as float32 metres."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    dtype: np.dtype[Any]
    if msg.encoding in ("16UC1", "mono16"):
        dtype, scale = np.dtype(">u2" if msg.is_bigendian else "<u2"), 0.001
    elif msg.encoding == "32FC1":
        dtype, scale = np.dtype(">f4" if msg.is_bigendian else "<f4"), 1.0
    else:
        msg_ = f"{field}.encoding: expected 16UC1 or 32FC1 depth, found {msg.encoding!r}"
        raise SensorInputError(msg_)
    if data.size < h * step or step < w * dtype.itemsize:
        msg_ = f"{field}: expected {h} rows of {step} bytes, found {data.size} bytes"
        raise SensorInputError(msg_)
    rows = data[: h * step].reshape(h, step)[:, : w * dtype.itemsize]
    depth = rows.copy().view(dtype).reshape(h, w).astype(np.float32) * np.float32(scale)
    depth[depth <= 0] = np.nan
    return depth


class RosbagOptions(Options):
    """Options of `replay:` for a ROS 1 or ROS 2 bag."""

    topic: str | None = Field(
        None,
        description="sensor topic (LaserScan, PointCloud2 or depth Image); "
        "none: the first LaserScan, else PointCloud2, else Image",
    )
    odom: str | None = Field(
        None, description="Odometry topic giving the poses; none: the first one, if any"
    )
    info: str | None = Field(
        None, description="CameraInfo topic for depth images; none: the first one"
    )
    max_range: float = Field(30.0, description="sensor range, metres")
    mount: str | None = Field(
        None,
        description="the sensor's pose in the robot body (its TF from base_link): "
        "x/y/z/yaw_deg[/pitch_deg/roll_deg]; none: at the body's origin",
    )
    strict: bool = Field(
        False, description="fail on the first bad message instead of skipping and counting it"
    )


class RosbagSource:
    """Observations from one sensor topic of a ROS 1 or ROS 2 bag; poses from an Odometry topic."""

    def __init__(
        self,
        path: str | Path,
        *,
        topic: str | None = None,
        odom: str | None = None,
        info: str | None = None,
        max_range: float = 30.0,
        mount: str | None = None,
        strict: bool = False,
        spec: str = "",
    ) -> None:
        self.path = Path(path)
        if not self.path.exists():
            msg = f"ROS bag: expected a bag file or folder, found nothing at {self.path}"
            raise SourceError(msg)
        self.reader_class = _any_reader()
        self.spec = spec or f"replay:{self.path}"
        self.strict, self.max_range = strict, max_range
        try:
            self.mount = np.eye(4) if mount is None else parse_mount(mount)
        except SensorInputError as exc:
            raise SourceSpecError(str(exc)) from None
        try:
            with self.reader_class([self.path]) as reader:
                types = {c.topic: c.msgtype for c in reader.connections}
                counts = {c.topic: c.msgcount for c in reader.connections}
        except SourceError:
            raise
        except Exception as exc:  # noqa: BLE001 - rosbags' errors for unreadable bags
            msg = (
                f"{self.path}: expected a readable ROS 1 or ROS 2 bag, "
                f"found {type(exc).__name__}: {exc}"
            )
            raise SourceError(msg) from None
        if topic is None:
            for kind in (SCAN, CLOUD, IMAGE):
                topic = next((t for t, m in sorted(types.items()) if m == kind), None)
                if topic is not None:
                    break
        if topic is None or topic not in types or types[topic] not in (SCAN, CLOUD, IMAGE):
            found = {t: m for t, m in types.items() if m in (SCAN, CLOUD, IMAGE)}
            msg = (
                f"{self.path}: expected a LaserScan, PointCloud2 or Image topic, "
                f"found {topic!r} among {found}"
            )
            raise SourceSpecError(msg)
        self.topic, self.kind = topic, types[topic]
        self.odom = (
            odom
            if odom is not None
            else next((t for t, m in sorted(types.items()) if m == ODOM), None)
        )
        self.info = (
            info
            if info is not None
            else next((t for t, m in sorted(types.items()) if m == INFO), None)
        )
        if self.kind == IMAGE and self.info is None:
            msg = (
                f"{self.path}: expected a CameraInfo topic for depth images on {topic}, found none"
            )
            raise SourceSpecError(msg)
        self.count = counts[topic]
        self.adapter: SensorAdapter = self._adapter()
        self.stats = StreamStats()

    def _adapter(self) -> SensorAdapter:
        if self.kind == SCAN:
            return load_adapter("lidar2d", range_max=self.max_range, mount=self.mount)
        if self.kind == CLOUD:
            return load_adapter("lidar3d", range_max=self.max_range, mount=self.mount)
        with self.reader_class([self.path]) as reader:
            conns = [c for c in reader.connections if c.topic == self.info]
            for conn, _, raw in reader.messages(connections=conns):
                info = reader.deserialize(raw, conn.msgtype)
                K = np.asarray(info.k if hasattr(info, "k") else info.K, np.float64).reshape(3, 3)
                return load_adapter("depth", K=K, max_range=self.max_range, mount=self.mount)
        msg = f"{self.path}: expected at least one CameraInfo message on {self.info}, found none"
        raise SourceError(msg)

    def __len__(self) -> int:
        return int(self.count)

    def __iter__(self) -> Iterator[Observation]:
        body = np.eye(4)
        have_odom = False
        with self.reader_class([self.path]) as reader:
            wanted = {self.topic, self.odom}
            conns = [c for c in reader.connections if c.topic in wanted]
            for conn, stamp, raw in reader.messages(connections=conns):
                where = f"{self.path}:{conn.topic}@{stamp}"
                try:
                    msg = reader.deserialize(raw, conn.msgtype)
                    if conn.topic == self.odom:
                        body, have_odom = pose_of_odometry(msg), True
                        continue
                    obs = self._observe(msg, body if have_odom else None, stamp * 1e-9, where)
                except (SensorInputError, ParseError, ValueError, KeyError, AssertionError) as exc:
                    if self.strict:
                        msg_ = f"{where}: {exc}"
                        raise ParseError(msg_) from None
                    self.stats.skip(where, exc)
                    continue
                self.stats.delivered += 1
                yield obs

    def _observe(self, msg: Any, body: np.ndarray | None, time: float, where: str) -> Observation:
        if self.kind == SCAN:
            scan = Scan(
                ranges=np.asarray(msg.ranges, np.float64),
                angle_min=float(msg.angle_min),
                angle_increment=float(msg.angle_increment),
                intensities=np.asarray(msg.intensities)
                if len(msg.intensities) == len(msg.ranges)
                else None,
            )
            return self.adapter.observe(scan, pose=body, time=time, odometry=body, frame=where)
        if self.kind == CLOUD:
            xyz, intensity = cloud_points(msg)
            return self.adapter.observe(
                Cloud(points=xyz, intensity=intensity),
                pose=body,
                time=time,
                odometry=body,
                frame=where,
            )
        return self.adapter.observe(
            DepthFrame(depth=depth_image(msg)), pose=body, time=time, odometry=body, frame=where
        )
