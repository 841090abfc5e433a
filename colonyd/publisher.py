"""Publisher: this daemon's own deltas and heartbeats, out to the colony."""

from __future__ import annotations

import math
import threading

import numpy as np
import zenoh

from colonyd.alignment import Edge, offer_of
from colonyd.frames import Sender, frame_of
from colonyd.layers import Layers, relabel
from colonyd.metrics import Metrics
from colonyd.runtime import undeclare
from colonyd.threadclock import stamp
from protocol import (
    Heartbeat,
    HistoryReply,
    LayerVersion,
    ObjectCentroid,
    Objects,
    Pose,
    PoseFix,
    VoxelDelta,
    delta_messages,
)
from protocol.keyexpr import Topic, topic_key
from voxel.delta import Delta

#: Most layers one heartbeat lists.
MAX_HEARTBEAT_LAYERS = 4096
#: Most history records (and seen entries) one pushed frame carries; the rest goes next time.
MAX_PUSH_RECORDS = 200_000


class Publisher:
    """Puts own deltas on `<own>/delta`, heartbeats on `<own>/heartbeat`, the own object list on
    `<own>/objects` and alignments on `<own>/align` (dropped, never blocking, when the network
    is congested)."""

    def __init__(
        self,
        session: zenoh.Session,
        namespace: str,
        layers: Layers,
        sender: Sender,
        metrics: Metrics,
        *,
        epoch: int,
        part_bytes: int = 4 << 20,
    ) -> None:
        self.layers = layers
        self.sender = sender
        self.metrics = metrics
        self.own = layers.own_id
        self.epoch = epoch
        self.part_bytes = part_bytes
        self.hb_now = threading.Event()  # set on a join: send our heartbeat without waiting

        def publisher(topic: Topic) -> zenoh.Publisher:
            return session.declare_publisher(
                topic_key(namespace, self.own, topic),
                congestion_control=zenoh.CongestionControl.DROP,
            )

        self._deltas = publisher("delta")
        self._heartbeats = publisher("heartbeat")
        self._objects = publisher("objects")
        self._align = publisher("align")
        self._pose = publisher("pose")
        self._fix = publisher("fix")
        self._history = publisher("history")
        #: The highest own history version pushed (`push_history`); what the layer held logged
        #: at start (restored from the state directory) is for replicas to page. Versions above
        #: the logged one (integrated before the publisher was built) are pushed once logged: it
        #: started at the history's newest, and their records were never pushed.
        own = layers.own
        newest = own.grid.history.newest_version()
        self.history_pushed = newest if own.logged is None else min(newest, own.logged)

    def publish_own(
        self,
        prev: int,
        seq: int,
        delta: Delta,
        created: float,
        encoded: tuple[Delta, list[bytes]] | None = None,
        marks: dict[str, float] | None = None,
    ) -> int:
        """Publish an own delta (already logged) as VoxelDelta parts; returns the bytes sent.

        `encoded` is what `encode_own` made of it (while the log flushed), else it is made here.
        `marks` gets the monotonic times of the hand-offs (`Metrics.stages`).
        """
        marks = {} if marks is None else marks
        own = self.layers.own
        # The number is taken (it is in the log) whatever happens next. One attribute is set
        # atomically: no need to wait for the grid's lock, which the mapping thread holds while
        # it integrates a scan (up to tens of ms on a busy core, seconds while kernels load).
        if own.epoch == self.epoch:
            own.seq = seq
        else:
            with own.lock:
                own.seq = seq
                own.epoch = self.epoch
        stamp(marks, "numbered")
        wire, payloads = encoded or self.encode_own(prev, seq, delta, created)
        stamp(marks, "encoded")
        own.remember(prev, seq, wire)
        stamp(marks, "put")
        for payload in payloads:
            self._deltas.put(payload)
        stamp(marks, "sent")
        sent = sum(len(p) for p in payloads)
        self.metrics.add("deltas_published")
        self.metrics.add("bytes_published", sent)
        return sent

    def push_history(self, upto: int) -> int:
        """Put the own layer's history records of versions not pushed yet, up to version `upto`
        (logged: a SIGKILL loses versions after it, and they are reused), on `<own>/history`
        (a HistoryReply with request id 0, one part; history push, opt-in). A frame too large
        is not sent: replicas page those versions with HistoryRequest. Returns records sent."""
        own = self.layers.own
        with own.lock:
            page, to, more = own.grid.history.page(self.history_pushed, MAX_PUSH_RECORDS, upto=upto)
        after = self.history_pushed
        if to == after:
            return 0
        self.history_pushed = to
        msg = HistoryReply(
            **self.sender.header(),
            layer=self.own,
            request_id=0,
            layer_epoch=self.epoch,
            from_version=after,
            to_version=to,
            more=more,
            records=page if page.records.size + page.seen.size else None,
        )
        payload = self.sender.encode(msg)
        if len(payload) > self.part_bytes:
            self.metrics.add("history_push_oversized")
            return 0
        self._history.put(payload)
        n = int(page.records.size + page.seen.size)
        self.metrics.add("history_pushed", n)
        self.metrics.add("bytes_published", len(payload))
        return n

    def encode_own(
        self, prev: int, seq: int, delta: Delta, created: float
    ) -> tuple[Delta, list[bytes]]:
        """The delta as labelled on the wire and its frames (one, or parts when large); sends
        nothing and changes no layer (so it may run before the delta is logged)."""
        wire = relabel(delta, prev, seq, time=created)
        whole = VoxelDelta(origin=self.own, time=created, frame_id=frame_of(self.own), delta=wire)
        payloads = self.sender.encode_all([whole])  # one encoding in the common case
        if len(payloads[0]) > self.part_bytes:  # too large for one frame: cut into parts
            msgs = delta_messages(
                origin=self.own,
                epoch=self.epoch,
                seq=0,
                time=created,
                frame_id=frame_of(self.own),
                delta=wire,
                max_bytes=self.part_bytes,
            )
            payloads = self.sender.encode_all(msgs)
        return wire, payloads

    def heartbeat(self, kind: str, pose: list[float]) -> None:
        """Publish what this daemon is and holds: kind, pose, every layer's (epoch, seq)."""
        decay = self.layers.half_lives()
        layers = [
            LayerVersion(origin=o, epoch=e, version=s, half_life=decay.get(o))
            for o, (e, s) in list(self.layers.versions().items())[:MAX_HEARTBEAT_LAYERS]
        ]
        position = tuple(float(x) for x in pose[:3])
        msg = Heartbeat(
            **self.sender.header(),
            kind=kind,
            frame_id=frame_of(self.own),
            layers=layers,
            forgotten=sorted(self.layers.forgotten)[:MAX_HEARTBEAT_LAYERS],
            identity=self.sender.identity,
            position=position if len(position) == 3 and all(map(math.isfinite, position)) else None,
        )
        payload = self.sender.encode(msg)
        self._heartbeats.put(payload)
        self.metrics.add("bytes_published", len(payload))
        self.metrics.add("bytes_heartbeat", len(payload))

    def publish_objects(self, objects: list[ObjectCentroid]) -> None:
        """Publish the own layer's full object list (in its frame)."""
        msg = Objects(**self.sender.header(), frame_id=frame_of(self.own), objects=objects)
        payload = self.sender.encode(msg)
        self._objects.put(payload)
        self.metrics.add("objects_published")
        self.metrics.add("bytes_published", len(payload))

    def publish_align(self, edge: Edge) -> None:
        """Offer an own alignment (a peer's frame into ours) to the colony."""
        payload = self.sender.encode(offer_of(edge, self.sender.header()))
        self._align.put(payload)
        self.metrics.add("align_published")
        self.metrics.add("bytes_published", len(payload))

    def publish_pose(self, pose: np.ndarray, covariance: np.ndarray | None) -> None:
        """Publish the own pose estimate (sensor pose in our frame) with its 6x6 covariance."""
        cov = np.zeros(36) if covariance is None else np.asarray(covariance, float).ravel()
        msg = Pose(
            **self.sender.header(),
            frame_id=frame_of(self.own),
            **Pose.split_matrix(pose),
            covariance=[float(x) for x in cov],
        )
        payload = self.sender.encode(msg)
        self._pose.put(payload)
        self.metrics.add("bytes_published", len(payload))

    def publish_fix(
        self,
        target: str,
        pose: np.ndarray,
        covariance: np.ndarray,
        stamp: float,
        marker_id: int,
        confidence: float,
    ) -> None:
        """Tell `target` where we saw it: its body pose in our frame at `stamp` (PoseFix)."""
        msg = PoseFix(
            **self.sender.header(),
            target=target,
            frame_id=frame_of(self.own),
            stamp=stamp,
            **PoseFix.split_matrix(pose),
            covariance=[float(x) for x in np.asarray(covariance, float).ravel()],
            marker_id=marker_id,
            confidence=confidence,
        )
        payload = self.sender.encode(msg)
        self._fix.put(payload)
        self.metrics.add("fixes_sent")
        self.metrics.add("bytes_published", len(payload))

    def close(self) -> None:
        undeclare(
            self._deltas,
            self._heartbeats,
            self._objects,
            self._align,
            self._pose,
            self._fix,
            self._history,
        )
