"""Inbox: peers' deltas, heartbeats, pushed history and joins, queued by Zenoh callbacks and
handled in order."""

from __future__ import annotations

import logging
import math
import random
import threading
from collections.abc import Callable, Sequence

import numpy as np
import zenoh

from colonyd.alignment import MAX_OFFER_COVARIANCE, MAX_OFFER_M, Alignments, edge_from_offer
from colonyd.errors import WireError
from colonyd.frames import Assembler, accept, expect, frame_of
from colonyd.layers import BLOCK_VOXELS
from colonyd.membership import Membership
from colonyd.metrics import Metrics
from colonyd.objects import PeerObjects
from colonyd.replicas import Replicas
from colonyd.runtime import undeclare
from colonyd.threadclock import stamp
from colonyd.worker import Bounded, Throttle, Worker, held_text
from protocol import (
    AlignOffer,
    Heartbeat,
    HistoryReply,
    Objects,
    OwnOriginError,
    Pose,
    PoseFix,
    ProtocolError,
    Receiver,
    VoxelDelta,
)
from protocol.codec import peek
from protocol.keyexpr import topic_subscription
from voxel.localisation import frame_error

log = logging.getLogger(__name__)

#: The smallest x, y (m^2) and yaw (rad^2) variance a PoseFix may claim: a fix claiming certainty
#: would override every other measurement.
MIN_FIX_VARIANCE = 1e-6

#: The largest position (m^2) and angle (rad^2) variances a Pose may claim: beyond, a covariance
#: says nothing a map can use (100 m, a full turn) and only risks overflow downstream.
MAX_POSE_VARIANCE = (1e4, 1e4, 1e4, (2 * math.pi) ** 2, (2 * math.pi) ** 2, (2 * math.pi) ** 2)

#: Relative tolerance of a Pose covariance's asymmetry and negative eigenvalues (of its largest
#: variance): rounding in the sender's filter, not a matrix that is not a covariance.
POSE_COVARIANCE_TOLERANCE = 1e-6


def check_pose_covariance(
    values: Sequence[float], reason: str = "bad-pose-covariance"
) -> np.ndarray:
    """The 6x6 covariance (x y z roll pitch yaw) of a Pose or a PoseFix, checked: finite,
    symmetric and positive semi-definite within `POSE_COVARIANCE_TOLERANCE`, variances within
    `MAX_POSE_VARIANCE` (all zeros: a sender without one). WireError(`reason`) saying what was
    found otherwise."""
    c = np.asarray(values, np.float64)
    if c.shape != (36,) or not np.all(np.isfinite(c)):
        text = f"expected 36 finite covariance values, found shape {c.shape} or non-finite ones"
        raise WireError(reason, text)
    c = c.reshape(6, 6)
    d = np.diag(c)
    if np.any(d < 0) or np.any(d > MAX_POSE_VARIANCE):
        text = (
            f"expected variances in [0, {MAX_POSE_VARIANCE}] (x y z roll pitch yaw), found "
            f"{', '.join(f'{v:.3g}' for v in d)}"
        )
        raise WireError(reason, text)
    found = frame_error.problem(c, POSE_COVARIANCE_TOLERANCE)
    if found is not None:
        raise WireError(reason, found)
    return c


#: The largest position (m, per axis) a Pose, PoseFix, Heartbeat or listed object may claim:
#: the AlignOffer bound (beyond the Earth, so that a site frame in projected coordinates
#: passes); beyond, a position says nothing about a robot and inflates what is computed from it
#: (a peer's drift path, the colony's objects). Object covariances: the offers' bound too.
MAX_POSITION_M = MAX_OFFER_M


def check_positions(positions: object, reason: str, what: str) -> None:
    """WireError(`reason`) unless every coordinate of `positions` (one or several x, y, z) is
    within `MAX_POSITION_M` m."""
    p = np.abs(np.asarray(positions, np.float64))
    if p.size and not p.max() <= MAX_POSITION_M:
        text = f"expected {what} within {MAX_POSITION_M:g} m per axis, found {p.max():.3g} m"
        raise WireError(reason, text)


#: An inbox item: (kind "delta" | "hb" | "objects" | "align" | "pose" | "fix" | "history" |
#: "join", key expression or agent, raw frame, a delta's hand-off marks so far: `threadclock`
#: stamps of the callback thread's last return ("idle"), our callback entered and it queued).
Item = tuple[str, str, bytes, dict[str, float]]


class Inbox:
    """Subscribes to every peer's deltas, heartbeats, object lists and alignments; a bounded queue
    (count and bytes: a flood drops, never grows memory) and one worker decode and fold them in."""

    def __init__(
        self,
        session: zenoh.Session,
        namespace: str,
        replicas: Replicas,
        receiver: Receiver,
        metrics: Metrics,
        objects: PeerObjects,
        alignments: Alignments,
        *,
        request_repair: Callable[[str, list[str]], None],
        send_heartbeat: Callable[[], None],
        on_own_origin: Callable[[OwnOriginError], None] | None = None,
        on_fix: Callable[[PoseFix], None] | None = None,
        on_history: Callable[[HistoryReply], None] | None = None,
        admit_history: Callable[[HistoryReply], None] | None = None,
        size: int = 256,
        max_bytes: int = 128 << 20,
        drop_rate: float = 0.0,
        stop: threading.Event | None = None,
    ) -> None:
        self.replicas = replicas
        self.objects = objects
        self.alignments = alignments
        self.receiver = receiver
        self.metrics = metrics
        #: a whole delta holds at most the peer budget's voxels (`Layers.admit` refuses more)
        self.parts = Assembler(max_voxels=replicas.layers.max_peer_blocks * BLOCK_VOXELS)
        self.membership: Membership | None = None
        self._request_repair = request_repair
        self._send_heartbeat = send_heartbeat
        #: Called (on the inbox thread) with a heartbeat that claims our own origin.
        self._on_own_origin = on_own_origin
        #: Called (on the inbox thread) with a validated PoseFix whose target is this daemon.
        self._on_fix = on_fix
        #: Called (on the inbox thread) with a validated pushed history (history push, opt-in:
        #: without it the inbox does not subscribe to `<origin>/history`).
        self._on_history = on_history
        #: Called (on the inbox thread) with a pushed history before it is accepted: raises
        #: WireError if `on_history` could not take it (a refused frame moves no window).
        self._admit_history = admit_history
        self._drop_rate = drop_rate
        self._log = Throttle()  # a flood of refusals logs a line per reason now and then
        self._rng = random.Random()
        #: Per Zenoh callback thread: its clocks when our callback last returned ("idle").
        self._idle = threading.local()
        #: The inbox thread's clocks when it last began to wait for an item ("waited").
        self._waited: dict[str, float] = {}
        self._worker: Worker[Item] = Worker(
            "gossip-inbox",
            self._handle,
            Bounded(size, max_bytes, weigh=lambda item: len(item[2])),
            metrics=metrics,
            hostile=True,
            drops="inbox_dropped",
            describe=lambda item: f"{item[0]} on {item[1]}",
            idle=self._wait,
            stop=stop,
            label=lambda item: f"inbox-{item[0]}",
        )
        remote = zenoh.Locality.REMOTE
        self._subs = [
            session.declare_subscriber(
                topic_subscription(namespace, "delta"), self._on_delta, allowed_origin=remote
            ),
            session.declare_subscriber(
                topic_subscription(namespace, "heartbeat"), self._on_hb, allowed_origin=remote
            ),
            session.declare_subscriber(
                topic_subscription(namespace, "objects"), self._on_objects, allowed_origin=remote
            ),
            session.declare_subscriber(
                topic_subscription(namespace, "align"), self._on_align, allowed_origin=remote
            ),
            session.declare_subscriber(
                topic_subscription(namespace, "pose"), self._on_pose, allowed_origin=remote
            ),
            session.declare_subscriber(
                topic_subscription(namespace, "fix"), self._on_fix_sample, allowed_origin=remote
            ),
        ]
        if on_history is not None:
            self._subs.append(
                session.declare_subscriber(
                    topic_subscription(namespace, "history"),
                    self._on_history_sample,
                    allowed_origin=remote,
                )
            )

    # -- zenoh callbacks: enqueue only ----------------------------------------------------
    def _on_delta(self, sample: zenoh.Sample) -> None:
        marks = dict(getattr(self._idle, "marks", {}))
        stamp(marks, "entered")
        if self._drop_rate and self._rng.random() < self._drop_rate:
            self.metrics.add("dropped_on_purpose")
            return
        raw = sample.payload.to_bytes()
        stamp(marks, "queued")
        self._worker.put(("delta", str(sample.key_expr), raw, marks))
        idle: dict[str, float] = {}
        stamp(idle, "idle")
        self._idle.marks = idle

    def _on_hb(self, sample: zenoh.Sample) -> None:
        self._put("hb", sample)

    def _on_objects(self, sample: zenoh.Sample) -> None:
        self._put("objects", sample)

    def _on_align(self, sample: zenoh.Sample) -> None:
        self._put("align", sample)

    def _on_pose(self, sample: zenoh.Sample) -> None:
        self._put("pose", sample)

    def _on_fix_sample(self, sample: zenoh.Sample) -> None:
        self._put("fix", sample)

    def _put(self, kind: str, sample: zenoh.Sample) -> None:
        self._worker.put((kind, str(sample.key_expr), sample.payload.to_bytes(), {}))

    def _on_history_sample(self, sample: zenoh.Sample) -> None:
        self._put("history", sample)

    def on_member_event(self, agent: str, event: str) -> None:
        """Liveliness join: ask the newcomer (or returning peer) what it holds."""
        self.metrics.add(f"member_{event}")
        if event == "join":
            self._worker.put(("join", agent, b"", {}))

    # -- lifecycle ------------------------------------------------------------------------
    def start(self, membership: Membership) -> None:
        self.membership = membership
        self._worker.start()

    def close(self) -> None:
        self._worker.close()
        undeclare(*self._subs)

    # -- the worker -----------------------------------------------------------------------
    def _handle(self, item: Item) -> None:
        kind, key, raw, marks = item
        try:
            if kind == "delta":
                self._handle_delta(key, raw, marks)
            elif kind == "hb":
                self._handle_hb(key, raw)
            elif kind == "objects":
                self._handle_objects(key, raw)
            elif kind == "align":
                self._handle_align(key, raw)
            elif kind == "pose":
                self._handle_pose(key, raw)
            elif kind == "fix":
                self._handle_fix(key, raw)
            elif kind == "history":
                self._handle_history(key, raw)
            elif kind == "join":
                self._handle_join(key)
        except OwnOriginError as exc:
            self.metrics.reject(exc.reason)
            if self._on_own_origin is not None and exc.kind == Heartbeat.KIND:
                self._on_own_origin(exc)
            elif (held := self._log.allow(exc.reason)) is not None:
                log.warning("rejected %s on %s: %s%s", kind, key, exc, held_text(held))

    def _wait(self) -> None:
        """The inbox thread is about to wait for an item: its clocks then ("waited")."""
        waited: dict[str, float] = {}
        stamp(waited, "waited")
        self._waited = waited

    def _handle_delta(self, key: str, raw: bytes, marks: dict[str, float]) -> None:
        marks.update(self._waited)
        stamp(marks, "dequeued")
        msg = expect(self.receiver.decode(raw, key_expr=key), VoxelDelta, f"on {key}")
        stamp(marks, "decoded")
        if not msg.exact:
            raise WireError("inexact", "expected an exact delta, found a free-space summary")
        d = msg.delta
        with self.replicas.layers.apply_lock:  # no range applied between admission and offer
            self.replicas.admit(msg.origin, msg.epoch, [d])
            whole = (msg.origin, msg.epoch, d.from_version, d.to_version)
            self.parts.check(whole, msg.part, msg.parts, d)  # its parts' count, their voxels
            accept(self.receiver, self.metrics, msg, raw)  # only now: a refusal moved no window
            stamp(marks, "admitted")
            delta = self.parts.add(whole, msg.part, msg.parts, d)
            if delta is None:
                return
            gap = self.replicas.offer(msg.origin, msg.epoch, delta, admitted=msg.parts == 1)
        if gap:
            self._request_repair(msg.origin, [msg.origin])
        stamp(marks, "applied")
        self.metrics.stage("in", msg.origin, delta.to_version, marks)

    def _handle_hb(self, key: str, raw: bytes) -> None:
        msg = expect(self.receiver.decode(raw, key_expr=key), Heartbeat, f"on {key}")
        if msg.position is not None:
            check_positions(msg.position, "bad-heartbeat", "a heartbeat's position")
        if self.membership is not None:
            self.membership.admit(msg.origin)  # bounded: a flood of made-up agents is refused
        accept(self.receiver, self.metrics, msg, raw)
        if self.membership is None:
            return
        layers = self.replicas.layers
        held: set[str] = set()  # what we hold remembered first, when not all can be
        if len(msg.layers) > self.membership.max_listed:
            held = {x.origin for x in layers.all() if x.origin != layers.own_id}
        member = self.membership.heard(msg.origin, msg, held)
        if member is None:  # no room after all (tokens came back since `admit`): not recorded
            return
        for origin in msg.forgotten:  # a tombstone travels with every member's heartbeat
            if self.replicas.layers.forget_agent(origin):
                log.warning("forgot the layer of %s (tombstone from %s)", origin, msg.origin)
        own_entry = next((e for e in msg.layers if e.origin == msg.origin), None)
        layer = self.replicas.layers.find(msg.origin)
        if own_entry is not None and layer is not None and layer.half_life != own_entry.half_life:
            layer.set_half_life(own_entry.half_life)  # only the origin says how its layer decays
        self._compare(msg.origin, member.layers)

    def _handle_objects(self, key: str, raw: bytes) -> None:
        try:
            claimed = peek(raw, self.receiver.limits).origin
        except ProtocolError:
            claimed = None  # `decode` says what is wrong with it, and counts it
        if claimed is not None:
            self.objects.allow(claimed)  # before the body is parsed: the cost is there
        msg = expect(self.receiver.decode(raw, key_expr=key), Objects, f"on {key}")
        self.objects.charge(msg.origin, len(msg.objects))
        if msg.objects:
            check_positions([o.position for o in msg.objects], "bad-objects", "object positions")
            covariance = np.abs(np.array([o.covariance for o in msg.objects], np.float64))
            if not covariance.max() <= MAX_OFFER_COVARIANCE:
                text = (
                    f"expected object covariance entries within {MAX_OFFER_COVARIANCE:g}, found "
                    f"{covariance.max():.3g}"
                )
                raise WireError("bad-objects", text)
        if self.membership is None or not self.membership.known(msg.origin):
            raise WireError("unknown-member", f"expected objects of a member, found {msg.origin!r}")
        self.objects.admit(msg.origin, self.membership.known)  # gone agents' lists make room
        accept(self.receiver, self.metrics, msg, raw)
        cut = self.objects.put(msg.origin, msg.objects)
        if cut:  # the peers' objects bound reached: the longest lists cut to a fair share
            self.metrics.add("objects_cut", cut)
        self.metrics.add("objects_received")

    def _handle_align(self, key: str, raw: bytes) -> None:
        msg = expect(self.receiver.decode(raw, key_expr=key), AlignOffer, f"on {key}")
        edge = edge_from_offer(msg)
        self.alignments.admit(edge)
        accept(self.receiver, self.metrics, msg, raw)
        self.alignments.put(edge)
        self.metrics.add("align_received")

    def _handle_pose(self, key: str, raw: bytes) -> None:
        msg = expect(self.receiver.decode(raw, key_expr=key), Pose, f"on {key}")
        if msg.frame_id != frame_of(msg.origin):
            text = f"expected a pose in {frame_of(msg.origin)!r}, found frame {msg.frame_id!r}"
            raise WireError("bad-pose", text)
        check_positions(msg.position, "bad-pose", "a pose's position")
        check_pose_covariance(msg.covariance)  # a bad one: the whole Pose ignored, counted
        if self.membership is None or self.membership.find(msg.origin) is None:
            raise WireError("unknown-member", f"expected a pose of a member, found {msg.origin!r}")
        accept(self.receiver, self.metrics, msg, raw)
        self.membership.posed(msg.origin, msg)

    def _handle_fix(self, key: str, raw: bytes) -> None:
        msg = expect(self.receiver.decode(raw, key_expr=key), PoseFix, f"on {key}")
        if msg.frame_id != frame_of(msg.origin):
            text = f"expected a fix in {frame_of(msg.origin)!r}, found frame {msg.frame_id!r}"
            raise WireError("bad-fix", text)
        check_positions(msg.position, "bad-fix", "a fix's position")
        check_pose_covariance(msg.covariance, "bad-fix")  # the filter's measurement noise
        variances = [msg.covariance[i] for i in (0, 7, 35)]  # x, y, yaw
        if not all(v >= MIN_FIX_VARIANCE for v in variances):
            text = (
                f"expected x, y and yaw variances >= {MIN_FIX_VARIANCE}, found "
                f"{', '.join(f'{v:.3g}' for v in variances)}"
            )
            raise WireError("bad-fix", text)
        if self.membership is None or self.membership.find(msg.origin) is None:
            raise WireError("unknown-member", f"expected a fix from a member, found {msg.origin!r}")
        accept(self.receiver, self.metrics, msg, raw)
        if msg.target != self.replicas.layers.own_id:
            self.metrics.add("fix_for_others")
            return
        self.metrics.add("fix_received")
        if self._on_fix is not None:
            self._on_fix(msg)

    def _handle_history(self, key: str, raw: bytes) -> None:
        msg = expect(self.receiver.decode(raw, key_expr=key), HistoryReply, f"on {key}")
        if msg.layer != msg.origin or msg.request_id != 0 or msg.parts != 1:
            text = (
                "expected a pushed history of the origin's own layer (request id 0, one part), "
                f"found layer {msg.layer!r} from {msg.origin!r}, request {msg.request_id}, "
                f"{msg.parts} parts"
            )
            raise WireError("bad-history", text)
        if self._admit_history is not None:
            self._admit_history(msg)
        accept(self.receiver, self.metrics, msg, raw)
        if msg.records is not None and self._on_history is not None:
            self._on_history(msg)

    def _handle_join(self, agent: str) -> None:
        """A member joined (or came back): tell it what we hold right away."""
        self.metrics.add("joins")
        # The joiner's own heartbeat drives our comparison; ours, sent now, drives its catch-up.
        self._send_heartbeat()

    def _compare(self, agent: str, theirs: dict[str, tuple[int, int]]) -> None:
        """Schedule a repair for every origin where `agent` holds more than we do."""
        layers = self.replicas.layers
        for origin, version in theirs.items():
            if origin == layers.own_id or origin in layers.forgotten:
                continue
            layer = layers.find(origin)
            mine = (layer.epoch, layer.seq) if layer else (0, 0)
            if version > mine:
                self._request_repair(origin, [agent])
