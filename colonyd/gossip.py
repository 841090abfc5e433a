"""Gossip: publish own deltas, fold peers' deltas into their layers, repair gaps, serve catch-up.

Everything on the wire is the colony protocol (`protocol/`, docs/PROTOCOL.md): VoxelDelta on
`<origin>/delta`, Heartbeat on `<origin>/heartbeat`, SnapshotRequest/Reply and
DeltaRangeRequest/Reply through the `<server>/snapshot/<layer>` and `<server>/deltas/<layer>`
queryables. Layer versions on the wire are the origin's delta sequence numbers.
"""

from __future__ import annotations

import logging
import math
import queue
import random
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh

from colonyd.errors import ColonydError, WireError
from colonyd.frames import FRAME_ID, Assembler, Sender, concat
from colonyd.layers import Layer, Layers, relabel
from colonyd.membership import Membership
from colonyd.metrics import Metrics
from protocol import (
    DeltaRangeReply,
    DeltaRangeRequest,
    Heartbeat,
    LayerVersion,
    Message,
    OwnOriginError,
    ProtocolError,
    Receiver,
    SnapshotReply,
    SnapshotRequest,
    VoxelDelta,
    delta_messages,
    split_delta,
)
from protocol.codec import FRAME_OVERHEAD
from protocol.deltacodec import MIN_PART_BODY
from protocol.keyexpr import parse_key, query_declaration, query_key, topic_key, topic_subscription
from voxel.delta import Delta

log = logging.getLogger(__name__)

#: Most parts of one reply a requester accepts (a snapshot of a full budget is far fewer).
MAX_REPLY_PARTS = 4096


@dataclass
class Repair:
    """A request to bring the layer of `origin` up to the best version the colony reports."""

    origin: str
    servers: list[str]


class Inbox:
    """Bounded queue of raw messages with a byte budget: a flood drops, never grows memory."""

    def __init__(self, size: int, max_bytes: int, metrics: Metrics) -> None:
        self._q: queue.Queue[tuple[str, str, bytes]] = queue.Queue(maxsize=size)
        self._bytes = 0
        self._max = max_bytes
        self._lock = threading.Lock()
        self._metrics = metrics

    def put(self, kind: str, key: str, raw: bytes) -> None:
        with self._lock:
            if self._bytes + len(raw) > self._max:
                self._metrics.add("inbox_dropped")
                return
            self._bytes += len(raw)
        try:
            self._q.put_nowait((kind, key, raw))
        except queue.Full:
            with self._lock:
                self._bytes -= len(raw)
            self._metrics.add("inbox_dropped")

    def get(self, timeout: float) -> tuple[str, str, bytes] | None:
        try:
            item = self._q.get(timeout=timeout)
        except queue.Empty:
            return None
        with self._lock:
            self._bytes -= len(item[2])
        return item


def _expect(msg: Message, cls: type[Message], what: str) -> Any:
    if not isinstance(msg, cls):
        text = f"expected a {cls.KIND} message {what}, found {msg.KIND}"
        raise WireError("unexpected-type", text)
    return msg


class Gossip:
    """Own deltas out; peers' deltas, heartbeats and catch-up in; range and snapshot served."""

    def __init__(
        self,
        session: zenoh.Session,
        namespace: str,
        layers: Layers,
        sender: Sender,
        receiver: Receiver,
        metrics: Metrics,
        *,
        epoch: int,
        inbox_size: int = 256,
        inbox_bytes: int = 128 << 20,
        drop_rate: float = 0.0,
        query_timeout_s: float = 5.0,
        chunk_voxels: int = 250_000,
        part_bytes: int = 4 << 20,
    ) -> None:
        self.session = session
        self.namespace = namespace
        self.layers = layers
        self.sender = sender
        self.receiver = receiver
        self.metrics = metrics
        self.own = layers.own_id
        self.epoch = epoch
        self.query_timeout_s = query_timeout_s
        self.chunk_voxels = chunk_voxels
        self.part_bytes = part_bytes
        self.stop = threading.Event()
        self.inbox = Inbox(inbox_size, inbox_bytes, metrics)
        self.parts = Assembler()
        self._drop_rate = drop_rate
        self._rng = random.Random()
        self._serve: queue.Queue[zenoh.Query] = queue.Queue(maxsize=64)
        self._repairs: queue.Queue[Repair] = queue.Queue(maxsize=1024)
        self._repairing: set[str] = set()
        self._repair_lock = threading.Lock()
        self.membership: Membership | None = None
        #: Called (on the inbox thread) with a heartbeat that claims our own origin.
        self.on_own_origin: Callable[[OwnOriginError], None] | None = None
        self.hb_now = threading.Event()  # set on a join: send our heartbeat without waiting
        drop = zenoh.CongestionControl.DROP
        self._publisher = session.declare_publisher(
            topic_key(namespace, self.own, "delta"), congestion_control=drop
        )
        self._hb_publisher = session.declare_publisher(
            topic_key(namespace, self.own, "heartbeat"), congestion_control=drop
        )
        remote = zenoh.Locality.REMOTE
        self._subs = [
            session.declare_subscriber(
                topic_subscription(namespace, "delta"), self._on_delta, allowed_origin=remote
            ),
            session.declare_subscriber(
                topic_subscription(namespace, "heartbeat"), self._on_hb, allowed_origin=remote
            ),
        ]
        self._queryables = [
            session.declare_queryable(query_declaration(namespace, self.own, q), self._on_query)
            for q in ("snapshot", "deltas")
        ]
        self._threads = [
            threading.Thread(target=self._inbox_loop, name="gossip-inbox", daemon=True),
            threading.Thread(target=self._serve_loop, name="gossip-serve", daemon=True),
            threading.Thread(target=self._repair_loop, name="gossip-repair", daemon=True),
        ]

    # -- zenoh callbacks: enqueue only ----------------------------------------------------
    def _on_delta(self, sample: zenoh.Sample) -> None:
        if self._drop_rate and self._rng.random() < self._drop_rate:
            self.metrics.add("dropped_on_purpose")
            return
        self.inbox.put("delta", str(sample.key_expr), sample.payload.to_bytes())

    def _on_hb(self, sample: zenoh.Sample) -> None:
        self.inbox.put("hb", str(sample.key_expr), sample.payload.to_bytes())

    def _on_query(self, query: zenoh.Query) -> None:
        try:
            self._serve.put_nowait(query)
        except queue.Full:
            self.metrics.add("queries_dropped")
            query.drop()

    def on_member_event(self, agent: str, event: str) -> None:
        """Liveliness join: ask the newcomer (or returning peer) what it holds."""
        self.metrics.add(f"member_{event}")
        if event == "join":
            self.inbox.put("join", agent, b"")

    # -- lifecycle ------------------------------------------------------------------------
    def start(self, membership: Membership) -> None:
        self.membership = membership
        for t in self._threads:
            t.start()

    def close(self) -> None:
        self.stop.set()
        for t in self._threads:
            if t.is_alive():
                t.join(timeout=2.0)
        for obj in [*self._subs, *self._queryables, self._publisher, self._hb_publisher]:
            try:
                obj.undeclare()
            except Exception as exc:
                log.debug("undeclare: %s", exc)

    # -- outgoing -------------------------------------------------------------------------
    def publish_own(self, prev: int, seq: int, delta: Delta, created: float) -> int:
        """Publish an own delta (already logged) as VoxelDelta parts; returns the bytes sent."""
        own = self.layers.own
        with own.lock:  # the number is taken (it is in the log) whatever happens next
            own.seq = seq
            own.epoch = self.epoch
        wire = relabel(delta, prev, seq, time=created)
        whole = VoxelDelta(origin=self.own, time=created, frame_id=FRAME_ID, delta=wire)
        payloads = self.sender.encode_all([whole])  # one encoding in the common case
        if len(payloads[0]) > self.part_bytes:  # too large for one frame: cut into parts
            msgs = delta_messages(
                origin=self.own, epoch=self.epoch, seq=0, time=created, frame_id=FRAME_ID,
                delta=wire, max_bytes=self.part_bytes,
            )
            payloads = self.sender.encode_all(msgs)
        own.remember(prev, seq, wire)
        for payload in payloads:
            self._publisher.put(payload)
        sent = sum(len(p) for p in payloads)
        self.metrics.add("deltas_published")
        self.metrics.add("bytes_published", sent)
        return sent

    def heartbeat(self, kind: str, pose: list[float]) -> None:
        """Publish what this daemon is and holds: kind, pose, every layer's (epoch, seq)."""
        layers = [
            LayerVersion(origin=o, epoch=e, version=s)
            for o, (e, s) in list(self.layers.versions().items())[:4096]
        ]
        position = tuple(float(x) for x in pose[:3])
        msg = Heartbeat(
            **self.sender.header(), kind=kind, frame_id=FRAME_ID, layers=layers,
            position=position if len(position) == 3 and all(map(math.isfinite, position)) else None,
        )
        payload = self.sender.encode(msg)
        self._hb_publisher.put(payload)
        self.metrics.add("bytes_published", len(payload))

    # -- incoming -------------------------------------------------------------------------
    def _inbox_loop(self) -> None:
        while not self.stop.is_set():
            item = self.inbox.get(timeout=0.2)
            if item is None:
                continue
            kind, key, raw = item
            try:
                if kind == "delta":
                    self._handle_delta(key, raw)
                elif kind == "hb":
                    self._handle_hb(key, raw)
                elif kind == "join":
                    self._handle_join(key)
            except OwnOriginError as exc:
                self.metrics.reject(exc.reason)
                if self.on_own_origin is not None and exc.kind == Heartbeat.KIND:
                    self.on_own_origin(exc)
                else:
                    log.warning("rejected %s on %s: %s", kind, key, exc)
            except (ProtocolError, WireError) as exc:
                self.metrics.reject(exc.reason)
                log.warning("rejected %s on %s: %s", kind, key, exc)
            except (ColonydError, ValueError) as exc:
                self.metrics.reject("invalid")
                log.warning("rejected %s on %s: %s", kind, key, exc)
            except Exception:  # never let one message kill the worker
                self.metrics.reject("internal")
                log.exception("failed to handle %s on %s", kind, key)

    def _handle_delta(self, key: str, raw: bytes) -> None:
        msg = _expect(self.receiver.decode(raw, key_expr=key), VoxelDelta, f"on {key}")
        if not msg.exact:
            raise WireError("inexact", "expected an exact delta, found a free-space summary")
        d = msg.delta
        self._admit(msg.origin, msg.epoch, [d])
        self._accept(msg, raw)  # only now: a frame refused above moved no window
        delta = self.parts.add(
            (msg.origin, msg.epoch, d.from_version, d.to_version), msg.part, msg.parts, d
        )
        if delta is not None:
            self._offer(msg.origin, msg.epoch, delta)

    def _accept(self, msg: Message, raw: bytes) -> None:
        """Take a frame that passed every check: its replay window moves, its bytes count."""
        self.receiver.accept(msg)
        self.metrics.add("bytes_received", len(raw))

    def _admit(self, origin: str, epoch: int, deltas: list[Delta], replace: bool = False) -> None:
        """Raise WireError unless `deltas` (a snapshot if `replace`) may enter `origin`'s layer."""
        for d in deltas:
            prev, seq = d.from_version, d.to_version
            if not (0 <= prev < seq) or epoch <= 0:
                raise WireError("bad-header", f"delta header invalid: epoch {epoch} {prev}->{seq}")
        self.layers.admit(origin, deltas, replace=replace)

    def _offer(self, origin: str, epoch: int, delta: Delta) -> None:
        """Fold a whole delta of `origin`'s layer (epoch `epoch`, covering (from, to]) into it."""
        self._admit(origin, epoch, [delta])
        layer = self.layers.get(origin, delta.resolution)
        result = layer.offer(epoch, delta.from_version, delta.to_version, delta, delta.time)
        now = time.time()
        if result.outcome == "duplicate":
            self.metrics.add("duplicates")
        elif result.outcome == "stale-epoch":
            self.metrics.add("stale_epoch")
        for s, c in result.drained:
            self.metrics.sample(origin, s, c, now)
        if result.drained:
            self.metrics.add("deltas_applied", len(result.drained))
        if result.missing is not None:
            self.metrics.add("gaps")
            self.request_repair(origin, [origin])

    def _handle_hb(self, key: str, raw: bytes) -> None:
        msg = _expect(self.receiver.decode(raw, key_expr=key), Heartbeat, f"on {key}")
        self._accept(msg, raw)
        if self.membership is None:
            return
        member = self.membership.heard(msg.origin, msg)
        self._compare(msg.origin, member.layers)

    def _handle_join(self, agent: str) -> None:
        """A member joined (or came back): tell it what we hold right away."""
        self.metrics.add("joins")
        # The joiner's own heartbeat drives our comparison; ours, sent now, drives its catch-up.
        self.hb_now.set()

    def _compare(self, agent: str, theirs: dict[str, tuple[int, int]]) -> None:
        """Schedule a repair for every origin where `agent` holds more than we do."""
        for origin, version in theirs.items():
            if origin == self.own:
                continue
            layer = self.layers.find(origin)
            mine = (layer.epoch, layer.seq) if layer else (0, 0)
            if version > mine:
                self.request_repair(origin, [agent])

    # -- repair ---------------------------------------------------------------------------
    def request_repair(self, origin: str, servers: list[str]) -> None:
        with self._repair_lock:
            if origin in self._repairing:
                return
            self._repairing.add(origin)
        try:
            self._repairs.put_nowait(Repair(origin, servers))
        except queue.Full:
            with self._repair_lock:
                self._repairing.discard(origin)

    def _repair_loop(self) -> None:
        while not self.stop.is_set():
            try:
                rep = self._repairs.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                self._repair(rep)
            except Exception:
                log.exception("repair of %s failed", rep.origin)
            finally:
                with self._repair_lock:
                    self._repairing.discard(rep.origin)

    def _repair(self, rep: Repair) -> None:
        servers = list(rep.servers)
        want_epoch, want_seq = 0, 0
        if self.membership is not None:
            want_epoch, want_seq, holders = self.membership.best(rep.origin)
            servers = holders + [s for s in servers if s not in holders]
        layer = self.layers.find(rep.origin)
        for server in servers[:3]:
            if self.stop.is_set():
                return
            have = (layer.epoch, layer.seq) if layer else (0, 0)
            if want_epoch and (want_epoch, want_seq) <= have and not (layer and layer.pending):
                return
            if layer and layer.seq > 0 and want_epoch in (0, layer.epoch):
                if self._fetch_range(server, rep.origin, layer, want_seq):
                    layer = self.layers.find(rep.origin)
                    if layer is not None and not layer.pending:
                        return
            if self._fetch_snapshot(server, rep.origin):
                return

    def _ask(self, server: str, query: str, layer: str, request: Any, cls: type[Message]) -> list[Any]:
        """Send a request frame to `server`'s queryable; the replies of type `cls` for `layer`
        and this request (every other reply is rejected and counted)."""
        replies = self.session.get(
            query_key(self.namespace, server, query, layer),  # type: ignore[arg-type]
            payload=self.sender.encode(request),
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=self.query_timeout_s,
        )
        out: list[Message] = []
        for reply in replies:
            if reply.ok is None:
                continue
            raw = reply.ok.payload.to_bytes()
            try:
                if len(out) >= MAX_REPLY_PARTS:
                    raise WireError("oversized", f"expected at most {MAX_REPLY_PARTS} replies")
                msg = self.receiver.decode(raw, key_expr=str(reply.ok.key_expr))
                if not (isinstance(msg, cls) and msg.layer == layer  # type: ignore[attr-defined]
                        and msg.request_id == request.request_id):  # type: ignore[attr-defined]
                    text = (f"expected a {cls.KIND} for layer {layer!r}, request "
                            f"{request.request_id}, found a {msg.KIND}")
                    raise WireError("bad-reply", text)
                self._accept(msg, raw)
                out.append(msg)
            except (ProtocolError, WireError) as exc:
                self.metrics.reject(exc.reason)
                log.warning("rejected a %s reply from %s: %s", query, server, exc)
        return out

    @staticmethod
    def _complete(msgs: list[Any], what: str) -> bool:
        """True if `msgs` are every part of one reply, each once."""
        if not msgs:
            return False
        parts = {m.parts for m in msgs}
        indices = {m.part for m in msgs}
        if len(parts) != 1 or len(indices) != len(msgs) or len(msgs) != parts.pop():
            log.info("incomplete %s reply: %d parts received", what, len(msgs))
            return False
        return True

    def _fetch_range(self, server: str, origin: str, layer: Layer, want: int) -> bool:
        want = max(want, max((p for p, *_ in layer.pending.values()), default=0), layer.seq + 1)
        rid = self._rng.getrandbits(63)
        request = DeltaRangeRequest(
            **self.sender.header(), layer=origin, request_id=rid,
            from_version=layer.seq, to_version=want, max_part_bytes=self.part_bytes,
        )
        msgs = self._ask(server, "deltas", origin, request, DeltaRangeReply)
        self.metrics.add("range_repairs")
        if not self._complete(msgs, "range") or not all(m.complete for m in msgs):
            return False
        groups: dict[tuple[int, int], list[tuple[int, Delta]]] = {}
        for m in msgs:
            if m.delta is not None:
                d = m.delta
                groups.setdefault((d.from_version, d.to_version), []).append((m.part, d))
        epochs = {m.layer_epoch for m in msgs}
        if len(epochs) != 1:
            self.metrics.reject("bad-parts")
            return False
        epoch = epochs.pop()
        got = 0
        for versions in sorted(groups, key=lambda v: v[1]):
            try:
                delta = concat([d for _, d in sorted(groups[versions], key=lambda x: x[0])])
                self._offer(origin, epoch, delta)
                got += 1
            except (ProtocolError, WireError) as exc:
                self.metrics.reject(exc.reason)
                log.warning("range reply from %s refused: %s", server, exc)
                return False
        return got > 0

    def _fetch_snapshot(self, server: str, origin: str) -> bool:
        t0 = time.monotonic()
        rid = self._rng.getrandbits(63)
        request = SnapshotRequest(
            **self.sender.header(), layer=origin, request_id=rid, max_part_bytes=self.part_bytes
        )
        msgs = self._ask(server, "snapshot", origin, request, SnapshotReply)
        if not self._complete(msgs, "snapshot"):
            return False
        states = {(m.layer_epoch, m.delta.from_version, m.delta.to_version) for m in msgs}
        if len(states) != 1:
            self.metrics.reject("bad-snapshot")
            return False
        epoch, start, seq = states.pop()
        if epoch <= 0 or start != 0:
            self.metrics.reject("bad-snapshot")
            return False
        chunks = [m.delta for m in sorted(msgs, key=lambda m: m.part)]
        try:
            self._admit(origin, epoch, chunks, replace=True)
        except WireError as exc:
            self.metrics.reject(exc.reason)
            log.warning("snapshot of %s from %s refused: %s", origin, server, exc)
            return False
        layer = self.layers.get(origin, chunks[0].resolution)
        voxels = layer.install_snapshot(epoch, seq, chunks)
        dt = time.monotonic() - t0
        self.metrics.add("snapshots_installed")
        self.metrics.catchup(origin, voxels, dt)
        log.info("caught up %s from %s: %d voxels at seq %d in %.3f s", origin, server, voxels,
                 seq, dt)
        return True

    # -- serving --------------------------------------------------------------------------
    def _serve_loop(self) -> None:
        while not self.stop.is_set():
            try:
                query = self._serve.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                self._answer(query)
            except (ProtocolError, WireError) as exc:
                self.metrics.reject(exc.reason)
                log.warning("rejected a query on %s: %s", query.key_expr, exc)
            except Exception:
                log.exception("failed to answer %s", query.selector)
            finally:
                query.drop()

    def _answer(self, query: zenoh.Query) -> None:
        key = str(query.key_expr)
        parsed = parse_key(key)
        if parsed.origin != self.own or parsed.layer is None:
            raise WireError("bad-query", f"expected a query for {self.own!r}, found {key!r}")
        if query.payload is None:
            raise WireError("bad-query", f"expected a request frame as the payload of {key!r}")
        raw = query.payload.to_bytes()
        msg = self.receiver.decode(raw)  # the requester's frame: its origin is not the key's
        cls = SnapshotRequest if parsed.kind == "snapshot" else DeltaRangeRequest
        request = _expect(msg, cls, f"on {key}")
        if request.layer != parsed.layer:
            text = f"expected layer {parsed.layer!r}, found {request.layer!r}"
            raise WireError("bad-query", text)
        self._accept(request, raw)
        layer = self.layers.find(request.layer)
        if parsed.kind == "snapshot":
            if layer is not None and layer.seq > 0:
                self._serve_snapshot(query, key, layer, request)
            return
        self._serve_range(query, key, layer, request)

    def _layer_epoch(self, layer: Layer) -> int:
        return self.epoch if layer.origin == self.own else layer.epoch

    def _fit(self, request: Any, chunks: list[Delta],
             make: Callable[[int, int, Delta], Message]) -> list[bytes]:
        """Reply frames `make(part, parts, chunk)` of `chunks`, each frame within the request's
        `max_part_bytes` (and ours): parts that come out too large are cut finer and re-encoded
        (one encoding per part in the common case)."""
        max_frame = min(self.part_bytes, request.max_part_bytes)
        limit = max_frame - FRAME_OVERHEAD - 128  # >= 640: max_part_bytes is at least 1024
        while True:
            frames = self.sender.encode_all(
                [make(i, len(chunks), c) for i, c in enumerate(chunks)]
            )
            big = [i for i, f in enumerate(frames) if len(f) > max_frame]
            if not big:
                return frames
            if limit < MIN_PART_BODY:
                text = f"expected parts within {max_frame} bytes, found a voxel too large for one"
                raise WireError("oversized", text)
            for i in reversed(big):
                chunks[i:i + 1] = split_delta(chunks[i], limit)
            limit //= 2  # still too large next time: the frame around a body grew, cut finer

    def _reply(self, query: zenoh.Query, key: str, frames: list[bytes]) -> None:
        for frame in frames:
            query.reply(key, frame)
            self.metrics.add("bytes_served", len(frame))

    def _serve_snapshot(self, query: zenoh.Query, key: str, layer: Layer, request: Any) -> None:
        epoch, seq, chunks = layer.snapshot(self.chunk_voxels)
        if layer.origin == self.own:
            epoch = self.epoch
        common = {"origin": self.own, "layer": layer.origin, "request_id": request.request_id,
                  "frame_id": FRAME_ID, "layer_epoch": epoch}
        frames = self._fit(request, chunks, lambda i, n, c: SnapshotReply(
            **common, time=time.time(), part=i, parts=n, delta=c))
        self._reply(query, key, frames)
        self.metrics.add("snapshots_served")

    def _serve_range(self, query: zenoh.Query, key: str, layer: Layer | None, request: Any) -> None:
        """Deltas of (from_version, min(to_version, newest)]: none if that range is empty
        (`complete`, no delta), `complete` False if it is no longer held or the layer is not."""
        deltas = None
        epoch = 0
        if layer is not None and layer.seq > 0:
            epoch = self._layer_epoch(layer)
            deltas = layer.range(request.from_version, request.to_version)
        common = {"origin": self.own, "layer": request.layer, "request_id": request.request_id,
                  "frame_id": FRAME_ID, "layer_epoch": epoch}
        if not deltas:
            msg = DeltaRangeReply(**common, time=time.time(), complete=deltas is not None)
            self._reply(query, key, self.sender.encode_all([msg]))
            return
        frames = self._fit(request, list(deltas), lambda i, n, c: DeltaRangeReply(
            **common, time=time.time(), part=i, parts=n, delta=c))
        self._reply(query, key, frames)
        self.metrics.add("ranges_served")
