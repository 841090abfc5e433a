"""`ros2:` source: a robot's ROS 2 topics read straight off its rmw_zenoh graph (no ROS install)."""

from __future__ import annotations

import logging
import os
import queue
import threading
import time as clock
from collections import Counter, deque
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh
import zenoh.ext
from pydantic import Field

from plugins import rmw
from plugins.adapter import SensorAdapter, load_adapter
from plugins.checks import as_intrinsics
from plugins.depth import DepthFrame
from plugins.errors import SensorInputError, SourceError, SourceSpecError
from plugins.lidar import Cloud, Scan
from plugins.observation import Observation
from plugins.rosbag import CLOUD, IMAGE, INFO, ODOM, SCAN, cloud_points
from plugins.spec import Options, SourceSpec, parse_options
from plugins.stream import SourceContext, StreamStats
from plugins.tf import TfGapError, TfTree, transform_matrix

log = logging.getLogger(__name__)

TF = "tf2_msgs/msg/TFMessage"
#: Nominal intrinsics of a depth camera until its first CameraInfo arrives (never used to map).
_NOMINAL_K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
#: Roles read transient-local (a late subscriber gets the publisher's cache).
LATCHED = ("tf_static", "camera_info")
#: Sensor messages waiting for their transforms, at most.
PENDING = 64
#: Seconds without a single sample on any topic after which the source says so (and again at
#: every multiple): a wrong topic, ROS domain or router endpoint otherwise waited in silence.
QUIET_S = 10.0


class WrongTypeError(SensorInputError):
    """A sample's key names another message type than its topic should carry."""


class CdrError(SensorInputError):
    """A payload that does not decode as CDR of its type (truncated, garbage)."""


class TooLargeError(SensorInputError):
    """A sample larger than the source accepts."""


class QueueFullError(SensorInputError):
    """A sample dropped because the mapping thread is behind and the queue is full."""


class Ros2Options(Options):
    """Options of `ros2:`."""

    scan: str | None = Field(None, description="sensor_msgs/LaserScan topic")
    cloud: str | None = Field(None, description="sensor_msgs/PointCloud2 topic")
    depth: str | None = Field(
        None, description="sensor_msgs/Image depth topic (16UC1 millimetres or 32FC1 metres)"
    )
    camera_info: str | None = Field(
        None, description="sensor_msgs/CameraInfo topic of the depth camera (needed with depth)"
    )
    odom: str | None = Field(None, description="nav_msgs/Odometry topic (body pose, odometry)")
    tf: bool = Field(True, description="read /tf and /tf_static for frames not in Odometry")
    frame: str | None = Field(
        None,
        description="fixed frame the map is built in (e.g. map); none: the Odometry's frame",
    )
    domain: int = Field(0, ge=0, le=232, description="ROS_DOMAIN_ID of the robot's graph")
    connect: str | None = Field(
        None,
        description="Zenoh endpoint of the robot's rmw_zenoh router (e.g. tcp/localhost:7447), "
        "opened as its own session; none: the daemon's own Zenoh session",
    )
    max_range: float = Field(30.0, gt=0, description="sensor range, metres")
    stride: int = Field(1, ge=1, description="depth: take every stride-th pixel on each axis")
    queue: int = Field(200, ge=1, description="samples waiting for the mapping thread, at most")
    queue_mb: float = Field(
        256.0, gt=0, description="bytes of samples waiting for the mapping thread, MiB, at most"
    )
    max_mb: float = Field(64.0, gt=0, description="largest sample taken, MiB (bigger: dropped)")
    tf_wait: float = Field(
        0.5, ge=0, description="seconds a reading waits for the transforms at its time"
    )
    tf_tolerance: float = Field(
        0.1, ge=0, description="after tf_wait, newest transforms up to this old (s) still do"
    )
    frames: int | None = Field(
        None, ge=1, description="stop after this many frames; none: run until stopped"
    )


@dataclass(frozen=True)
class _Sample:
    """One sample as received: which subscription, key, payload and attachment bytes."""

    role: str
    key: str
    payload: bytes
    attachment: bytes | None
    received: float  # monotonic seconds


@dataclass
class _Reading:
    """A decoded sensor message waiting for the transforms at its time."""

    msg: Any
    stamp: float
    frame_id: str
    received: float  # monotonic seconds, when Zenoh handed it over
    data: Any = None  # what was decoded already: depth pixels, or cloud points and intensity


def stamp_of(header: Any) -> float:
    """Seconds of a std_msgs/Header stamp."""
    return int(header.stamp.sec) + int(header.stamp.nanosec) * 1e-9


def depth_pixels(msg: Any) -> np.ndarray:
    """A depth Image as raw uint16 (16UC1, millimetres) or float32 metres (32FC1), (H, W)."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    dtype: np.dtype[Any]
    if msg.encoding in ("16UC1", "mono16"):
        dtype = np.dtype(">u2" if msg.is_bigendian else "<u2")
    elif msg.encoding == "32FC1":
        dtype = np.dtype(">f4" if msg.is_bigendian else "<f4")
    else:
        msg_ = f"Image.encoding: expected 16UC1 or 32FC1 depth, found {msg.encoding!r}"
        raise SensorInputError(msg_)
    data = np.asarray(msg.data, dtype=np.uint8)
    if h <= 0 or w <= 0 or step < w * dtype.itemsize or data.size < h * step:
        msg_ = (
            f"Image: expected {h} rows of {step} >= {w} x {dtype.itemsize} bytes, found {data.size}"
        )
        raise SensorInputError(msg_)
    rows = data[: h * step].reshape(h, step)[:, : w * dtype.itemsize]
    pixels = np.ascontiguousarray(rows).view(dtype).reshape(h, w)
    return pixels.astype(np.uint16 if dtype.kind == "u" else np.float32)


class Ros2Source:
    """Observations from one sensor topic of a ROS 2 robot on rmw_zenoh.

    Subscribes hash-agnostic (`<domain>/<topic>/*/*`; Humble sends no type hash) and checks the
    type on each sample; takes both attachment formats; declares a node and a subscription token
    per topic so that `ros2 node list` and `ros2 topic info` see it. Every sample goes through one
    bounded queue; anything rejected (wrong type, bad attachment or CDR, too large, queue full,
    TF gap) is logged and counted in `stats.reasons`, never raised.
    """

    def __init__(
        self, options: Ros2Options, *, context: SourceContext | None = None, spec: str = ""
    ) -> None:
        sensors = [
            (name, topic, kind)
            for name, topic, kind in (
                ("scan", options.scan, SCAN),
                ("cloud", options.cloud, CLOUD),
                ("depth", options.depth, IMAGE),
            )
            if topic
        ]
        if len(sensors) != 1:
            msg = f"{spec}: expected exactly one of scan=, cloud=, depth=, found {len(sensors)}"
            raise SourceSpecError(msg)
        if options.depth and not options.camera_info:
            msg = f"{spec}: expected camera_info= with depth=, found none"
            raise SourceSpecError(msg)
        if options.frame is None and not options.odom:
            msg = f"{spec}: expected frame= (the fixed frame, e.g. map) or odom=, found neither"
            raise SourceSpecError(msg)
        self.options = options
        self.spec = spec or "ros2:"
        self.context = context or SourceContext()
        self.sensor, topic, self.kind = sensors[0]
        self.topics: dict[str, tuple[str, str]] = {self.sensor: (topic, self.kind)}
        if options.camera_info:
            self.topics["camera_info"] = (options.camera_info, INFO)
        if options.odom:
            self.topics["odom"] = (options.odom, ODOM)
        if options.tf:
            self.topics["tf"] = ("/tf", TF)
            self.topics["tf_static"] = ("/tf_static", TF)
        for role, (name, kind) in self.topics.items():
            try:
                rmw.topic_name(name)
                rmw.type_hash(kind)
            except SensorInputError as exc:
                msg = f"{spec}: option {role!r}: {exc}"
                raise SourceSpecError(msg) from None
        self.adapter: SensorAdapter = self._make_adapter(_NOMINAL_K)
        self.stats = StreamStats()
        self.received: Counter[str] = Counter()  # samples per role
        self.tree = TfTree()
        self._queue: queue.Queue[_Sample] = queue.Queue(maxsize=options.queue)
        self._pending: deque[_Reading] = deque()
        self._K: np.ndarray | None = None
        self._fixed = options.frame.strip("/") if options.frame else None
        self._body: tuple[str, str] | None = None  # odometry frame, body frame
        self._lock = threading.Lock()
        self._handled_until = 0.0  # receive time of the newest sample handled
        self._queued_bytes = 0

    #: Runs until stopped (or `frames`): a daemon gives it a mapping thread of its own.
    live = True

    def _make_adapter(self, K: np.ndarray) -> SensorAdapter:
        r = self.options.max_range
        if self.kind == SCAN:
            return load_adapter("lidar2d", range_max=r)
        if self.kind == CLOUD:
            return load_adapter("lidar3d", range_max=r)
        return load_adapter(
            "depth",
            K=K,
            depth_scale=0.001,
            invalid=(0,),
            max_range=r,
            stride=self.options.stride,
        )

    def __len__(self) -> int:
        return self.options.frames or 0

    # -- receiving (Zenoh callback threads: cheap, bounded, never raising) -----------------
    def _receive(self, role: str, sample: Any) -> None:
        key = str(sample.key_expr)
        try:
            size = len(sample.payload)
            if size > self.options.max_mb * (1 << 20):
                msg = f"expected at most {self.options.max_mb} MiB, found {size / (1 << 20):.1f}"
                raise TooLargeError(msg)
            attachment = sample.attachment
            item = _Sample(
                role,
                key,
                sample.payload.to_bytes(),
                None if attachment is None else attachment.to_bytes(),
                clock.monotonic(),
            )
            with self._lock:
                if self._queued_bytes + size > self.options.queue_mb * (1 << 20):
                    msg = (
                        f"expected room in the queue of {self.options.queue_mb} MiB, found it full"
                    )
                    raise QueueFullError(msg)
                self._queued_bytes += size
            try:
                self._queue.put_nowait(item)
            except queue.Full:
                with self._lock:
                    self._queued_bytes -= size
                msg = f"expected room in the queue of {self.options.queue}, found it full"
                raise QueueFullError(msg) from None
        except SensorInputError as exc:
            self._reject(key, exc)
        except Exception as exc:  # noqa: BLE001 - a callback must never raise into Zenoh
            self._reject(key, exc)

    def _reject(self, where: str, exc: Exception) -> None:
        """Count a rejected sample by reason; log the first few of each reason, then every 100th."""
        with self._lock:
            self.stats.skipped += 1
            reason = type(exc).__name__
            self.stats.reasons[reason] += 1
            n = self.stats.reasons[reason]
            if len(self.stats.first_errors) < 10:
                self.stats.first_errors.append(f"{where}: {exc}")
        if n <= 3 or n % 100 == 0:
            log.warning("%s: rejected %s (%s #%d): %s", self.spec, where, reason, n, exc)

    # -- the mapping thread --------------------------------------------------------------
    def __iter__(self) -> Iterator[Observation]:
        session, own = self._session()
        entities = self._declare(session)
        stop = self.context.stop
        delivered = 0
        began, said = clock.monotonic(), 0
        try:
            while not stop.is_set():
                item: _Sample | None
                try:
                    item = self._queue.get(timeout=0.1)
                except queue.Empty:
                    item = None
                    quiet = int((clock.monotonic() - began) / QUIET_S)
                    if quiet > said and not self.received and not self.stats.skipped:
                        said = quiet
                        log.warning("%s", self._quiet(quiet * QUIET_S))
                ready: list[Observation] = []
                if item is not None:
                    with self._lock:
                        self._queued_bytes -= len(item.payload)
                    try:
                        ready += self._handle(item)
                    except SensorInputError as exc:
                        self._reject(item.key, exc)
                ready += self._flush()
                for obs in ready:
                    self.stats.delivered += 1
                    delivered += 1
                    yield obs
                    if self.options.frames is not None and delivered >= self.options.frames:
                        return
        finally:
            for entity in entities:
                try:
                    entity.undeclare()
                except Exception as exc:  # noqa: BLE001 - closing: whatever it was, go on
                    log.debug("undeclare: %s", exc)
            if own:
                session.close()

    def _quiet(self, seconds: float) -> str:
        """What to check when nothing at all arrived within `seconds`."""
        topics = ", ".join(t for t, _ in self.topics.values())
        through = self.options.connect or "the daemon's Zenoh session"
        return (
            f"{self.spec}: nothing received in {seconds:g} s on {topics} (ROS domain "
            f"{self.options.domain}, through {through}): expected the robot's rmw_zenoh graph "
            "to publish them: check the topic names, domain= (the robot's ROS_DOMAIN_ID) and "
            "that its router listens at connect="
        )

    def _session(self) -> tuple[Any, bool]:
        """(session, owned): a new one to `connect`, else the daemon's."""
        if self.options.connect:
            conf = zenoh.Config()
            for key, value in (
                ("mode", '"peer"'),
                ("scouting/multicast/enabled", "false"),
                ("connect/endpoints", f'["{self.options.connect}"]'),
                ("listen/endpoints", '["tcp/127.0.0.1:0"]'),
            ):
                conf.insert_json5(key, value)
            try:
                return zenoh.open(conf), True
            except zenoh.ZError as exc:
                msg = f"{self.spec}: cannot open a Zenoh session to {self.options.connect}: {exc}"
                raise SourceError(msg) from None
        factory = self.context.session
        if factory is None:
            msg = f"{self.spec}: expected connect= (no daemon session to share), found none"
            raise SourceError(msg)
        return factory(), False

    def _declare(self, session: Any) -> list[Any]:
        """Subscribers for every topic, a node token and a subscription token per topic."""
        domain = self.options.domain
        zid = str(session.zid())
        node = f"colonyd_{os.getpid()}_{id(self) % 10000}"
        entities: list[Any] = [
            session.liveliness().declare_token(rmw.node_token(domain, zid, 0, "", node))
        ]
        for role, (topic, _) in self.topics.items():
            key = rmw.any_type_key(domain, topic)

            def callback(sample: Any, role: str = role) -> None:
                self._receive(role, sample)

            if role in LATCHED:  # late joiner: ask transient-local publishers for their cache
                entities.append(
                    zenoh.ext.declare_advanced_subscriber(
                        session,
                        key,
                        callback,
                        allowed_origin=zenoh.Locality.REMOTE,
                        history=zenoh.ext.HistoryConfig(detect_late_publishers=True),
                    )
                )
            else:  # REMOTE: never the daemon's own ROS 2 outputs (its /tf) on a shared session
                entities.append(
                    session.declare_subscriber(key, callback, allowed_origin=zenoh.Locality.REMOTE)
                )
        for i, (role, (topic, kind)) in enumerate(self.topics.items(), start=1):
            latched = role in LATCHED
            qos = rmw.qos_text(reliable=True, transient_local=latched, depth=1 if latched else 10)
            token = rmw.endpoint_token(
                domain, zid, 0, i, rmw.SUBSCRIPTION, "", node, topic, kind, rmw.type_hash(kind), qos
            )
            entities.append(session.liveliness().declare_token(token))
        log.info(
            "%s: subscribed to %s on ROS domain %d as node %s",
            self.spec,
            ", ".join(t for t, _ in self.topics.values()),
            domain,
            node,
        )
        return entities

    def _handle(self, item: _Sample) -> list[Observation]:
        topic, kind = self.topics[item.role]
        self.received[item.role] += 1
        self._handled_until = max(self._handled_until, item.received)
        found, type_hash = rmw.type_of_key(item.key)
        if found != kind:
            msg = f"{topic}: expected {kind}, found {found}"
            raise WrongTypeError(msg)
        want = rmw.type_hash(kind)
        if type_hash not in (want, rmw.NO_HASH):
            msg = f"{topic}: expected type hash {want} of {kind}, found {type_hash}"
            raise WrongTypeError(msg)
        rmw.decode_attachment(item.attachment)
        try:
            msg = rmw.typestore().deserialize_cdr(item.payload, kind)
        except Exception as exc:  # noqa: BLE001 - rosbags raises many types on bad bytes
            text = f"{topic}: expected CDR of {kind}, found {len(item.payload)} bytes ({exc})"
            raise CdrError(text) from None
        if item.role in ("tf", "tf_static"):
            for t in msg.transforms:
                tr, q = t.transform.translation, t.transform.rotation
                pose = transform_matrix(
                    np.array([tr.x, tr.y, tr.z]), np.array([q.x, q.y, q.z, q.w])
                )
                self.tree.set(
                    t.header.frame_id,
                    t.child_frame_id,
                    stamp_of(t.header),
                    pose,
                    static=item.role == "tf_static",
                )
            return []
        if item.role == "odom":
            p, q = msg.pose.pose.position, msg.pose.pose.orientation
            pose = transform_matrix(np.array([p.x, p.y, p.z]), np.array([q.x, q.y, q.z, q.w]))
            parent, child = msg.header.frame_id.strip("/"), msg.child_frame_id.strip("/")
            self.tree.set(parent, child, stamp_of(msg.header), pose, static=False)
            self._body = (parent, child)
            if self._fixed is None:
                self._fixed = parent
            return []
        if item.role == "camera_info":
            K = as_intrinsics(np.asarray(msg.k, np.float64).reshape(3, 3), "CameraInfo.k")
            if self._K is None or not np.array_equal(K, self._K):
                self._K = K
                self.adapter = self._make_adapter(K)
            return []
        frame_id = msg.header.frame_id.strip("/")
        if not frame_id:
            text = f"{topic}: expected a header.frame_id naming the sensor frame, found ''"
            raise SensorInputError(text)
        data: Any = None  # checked now: a bad frame is refused before it waits for TF
        if self.kind == IMAGE:
            data = depth_pixels(msg)
        elif self.kind == CLOUD:
            data = cloud_points(msg)
        self._pending.append(_Reading(msg, stamp_of(msg.header), frame_id, item.received, data))
        while len(self._pending) > PENDING:
            old = self._pending.popleft()
            self._reject(f"{topic}@{old.stamp:.3f}", TfGapError("waited behind newer readings"))
        return []

    def _flush(self) -> list[Observation]:
        """Readings whose transforms are known now (in arrival order), or waited long enough.

        A reading has waited `tf_wait` once every sample received within `tf_wait` after it has
        been handled: a mapping thread that is behind does not turn queued transforms into gaps.
        """
        out: list[Observation] = []
        topic = self.topics[self.sensor][0]
        seen = clock.monotonic() if self._queue.empty() else self._handled_until
        while self._pending:
            reading = self._pending[0]
            waited = seen - reading.received >= self.options.tf_wait
            try:
                out.append(
                    self._observe(reading, tolerance=self.options.tf_tolerance if waited else 0.0)
                )
            except TfGapError as exc:
                if not waited:
                    break
                self._reject(f"{topic}@{reading.stamp:.3f}", exc)
            except SensorInputError as exc:
                self._reject(f"{topic}@{reading.stamp:.3f}", exc)
            self._pending.popleft()
        return out

    def _observe(self, reading: _Reading, tolerance: float) -> Observation:
        if self._fixed is None:
            msg = f"fixed frame: expected an Odometry message on {self.options.odom} first"
            raise TfGapError(msg)
        if self.kind == IMAGE and self._K is None:
            msg = f"expected a CameraInfo on {self.options.camera_info} first, found none"
            raise TfGapError(msg)
        t = reading.stamp
        sensor_pose = self.tree.lookup(self._fixed, reading.frame_id, t, tolerance)
        odometry = None
        if self._body is not None:
            odometry = self.tree.lookup(self._body[0], self._body[1], t, tolerance)
        msg = reading.msg
        where = f"{self.topics[self.sensor][0]}@{t:.3f}"
        if self.kind == SCAN:
            ranges = np.asarray(msg.ranges, np.float64)
            with np.errstate(invalid="ignore"):
                bad = np.isfinite(ranges) & ((ranges > msg.range_max) | (ranges < msg.range_min))
            ranges = np.where(bad | (ranges == -np.inf), np.nan, ranges)
            scan = Scan(
                ranges=ranges,
                angle_min=float(msg.angle_min),
                angle_increment=float(msg.angle_increment),
                intensities=np.asarray(msg.intensities)
                if len(msg.intensities) == len(msg.ranges)
                else None,
            )
            return self.adapter.observe(
                scan, pose=sensor_pose, time=t, odometry=odometry, frame=where
            )
        if self.kind == CLOUD:
            xyz, intensity = reading.data
            return self.adapter.observe(
                Cloud(points=xyz, intensity=intensity),
                pose=sensor_pose,
                time=t,
                odometry=odometry,
                frame=where,
            )
        return self.adapter.observe(
            DepthFrame(depth=reading.data),
            pose=sensor_pose,
            time=t,
            odometry=odometry,
            frame=where,
        )


def open_ros2(spec: SourceSpec, context: SourceContext) -> Ros2Source:
    """The `ros2:` source of a parsed spec."""
    options = parse_options(Ros2Options, spec.options, spec.text)
    return Ros2Source(options, context=context, spec=spec.text)
