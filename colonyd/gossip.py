"""Gossip: publish own deltas, fold peers' deltas into their layers, repair gaps, serve catch-up."""

from __future__ import annotations

import logging
import queue
import re
import random
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh

from colonyd.config import NAME_PATTERN
from colonyd.errors import ColonydError, WireError
from colonyd.layers import Layer, Layers, relabel
from colonyd.membership import Membership
from colonyd.metrics import Metrics
from colonyd.runtime import Keys
from colonyd.wire import Codec

log = logging.getLogger(__name__)


_NAME = re.compile(f"^{NAME_PATTERN}$")


def _name(name: str) -> str:
    """An origin or agent id from a key, if it is a valid name."""
    if not _NAME.match(name):
        raise WireError("bad-name", f"expected an agent id matching {NAME_PATTERN}, found {name[:80]!r}")
    return name


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


class Gossip:
    """Own deltas out; peers' deltas, heartbeats and catch-up in; range and snapshot served."""

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        layers: Layers,
        codec: Codec,
        metrics: Metrics,
        *,
        epoch: int,
        inbox_size: int = 256,
        inbox_bytes: int = 128 << 20,
        max_layers: int = 256,
        max_peer_blocks: int = 100_000,
        drop_rate: float = 0.0,
        query_timeout_s: float = 5.0,
        chunk_voxels: int = 250_000,
    ) -> None:
        self.session = session
        self.keys = keys
        self.layers = layers
        self.codec = codec
        self.metrics = metrics
        self.own = layers.own_id
        self.epoch = epoch
        self.query_timeout_s = query_timeout_s
        self.chunk_voxels = chunk_voxels
        self.stop = threading.Event()
        self.inbox = Inbox(inbox_size, inbox_bytes, metrics)
        self.max_layers = max_layers
        self.max_peer_blocks = max_peer_blocks
        self._drop_rate = drop_rate
        self._rng = random.Random()
        self._serve: queue.Queue[zenoh.Query] = queue.Queue(maxsize=64)
        self._repairs: queue.Queue[Repair] = queue.Queue(maxsize=1024)
        self._repairing: set[str] = set()
        self._repair_lock = threading.Lock()
        self.membership: Membership | None = None
        self.hb_now = threading.Event()  # set on a join: send our heartbeat without waiting
        self._publisher = session.declare_publisher(
            keys.delta(self.own), congestion_control=zenoh.CongestionControl.DROP
        )
        self._hb_publisher = session.declare_publisher(
            keys.heartbeat(self.own), congestion_control=zenoh.CongestionControl.DROP
        )
        remote = zenoh.Locality.REMOTE
        self._subs = [
            session.declare_subscriber(keys.delta("*"), self._on_delta, allowed_origin=remote),
            session.declare_subscriber(keys.heartbeat("*"), self._on_hb, allowed_origin=remote),
        ]
        self._queryables = [
            session.declare_queryable(keys.snapshot(self.own, "*"), self._on_query),
            session.declare_queryable(keys.range(self.own, "*"), self._on_query),
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
    def publish_own(self, prev: int, seq: int, delta: Any, created: float) -> bytes:
        """Encode and publish an own delta (already logged); returns the payload."""
        own = self.layers.own
        with own.lock:  # the number is taken (it is in the log) whatever happens next
            own.seq = seq
            own.epoch = self.epoch
        payload = self.codec.encode(
            {"t": "delta", "o": self.own, "e": self.epoch, "s": seq, "p": prev, "c": created,
             "delta": relabel(delta, prev, seq)}
        )
        own.remember(prev, seq, payload)
        self._publisher.put(payload)
        self.metrics.add("deltas_published")
        self.metrics.add("bytes_published", len(payload))
        return payload

    def heartbeat(self, kind: str, pose: list[float]) -> None:
        layers = {o: [e, s] for o, (e, s) in self.layers.versions().items()}
        payload = self.codec.encode(
            {"t": "hb", "a": self.own, "k": kind, "p": pose, "L": layers, "tm": time.time()}
        )
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
            except WireError as exc:
                self.metrics.reject(exc.reason)
                log.warning("rejected %s from %s: %s", kind, Keys.last(key), exc)
            except (ColonydError, ValueError) as exc:
                self.metrics.reject("invalid")
                log.warning("rejected %s from %s: %s", kind, Keys.last(key), exc)
            except Exception:  # never let one message kill the worker
                self.metrics.reject("internal")
                log.exception("failed to handle %s from %s", kind, Keys.last(key))

    def _handle_delta(self, key: str, raw: bytes) -> None:
        self.metrics.add("bytes_received", len(raw))
        origin = _name(Keys.last(key))
        msg = self.codec.decode(raw)
        self._offer(origin, msg, raw, expect_origin=origin)

    def _offer(self, origin: str, msg: dict[str, Any], raw: bytes, *, expect_origin: str) -> None:
        if msg.get("t") != "delta" or msg.get("o") != expect_origin or "delta" not in msg:
            found = f"kind {msg.get('t')!r} from {msg.get('o')!r}" + ("" if "delta" in msg else " without a delta")
            raise WireError("bad-delta", f"expected a delta message from {expect_origin!r}, found {found}")
        if origin == self.own:
            return
        try:
            epoch, prev, seq = int(msg["e"]), int(msg["p"]), int(msg["s"])
            created = float(msg.get("c", 0.0))
        except (KeyError, TypeError, ValueError):
            raise WireError("bad-header", "delta header needs integer e, p, s") from None
        if not (0 <= prev < seq) or epoch <= 0:
            raise WireError("bad-header", f"delta header invalid: epoch {epoch} {prev}->{seq}")
        delta = msg["delta"]
        layer = self._layer_for(origin, delta.resolution)
        if abs(layer.resolution - delta.resolution) > 1e-12:
            raise WireError("bad-resolution",
                            f"expected resolution {layer.resolution}, found {delta.resolution}")
        self._check_budget(layer, [delta])
        result = layer.offer(epoch, prev, seq, delta, raw, created)
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

    def _layer_for(self, origin: str, resolution: float) -> Layer:
        """The layer of `origin`, created if there is room (a hostile peer cannot invent many)."""
        layer = self.layers.find(origin)
        if layer is None:
            if len(self.layers.all()) > self.max_layers:
                raise WireError("too-many-layers",
                                f"expected at most {self.max_layers} peer layers, found another: {origin!r}")
            if not (0 < resolution <= 10):
                raise WireError("bad-resolution", f"expected a resolution in (0, 10] m, found {resolution}")
            layer = self.layers.get(origin, resolution)
        return layer

    def _check_budget(self, layer: Layer, deltas: list[Any], replace: bool = False) -> None:
        """Refuse what would push peer layers past `max_peer_blocks` (sparse floods)."""
        used = sum(l.blocks() for l in self.layers.all() if l.origin != self.own)
        if replace:
            used -= layer.blocks()
            keys = np.concatenate([d.keys for d in deltas]) if deltas else np.empty((0, 3))
            new = Layer(layer.origin, layer.resolution).new_blocks(keys)
        else:
            new = sum(layer.new_blocks(d.keys) for d in deltas)
        if used + new > self.max_peer_blocks:
            raise WireError("over-budget",
                            f"expected peer layers within {self.max_peer_blocks} blocks, "
                            f"found {used} held + {new} new for {layer.origin!r}")

    def _handle_hb(self, key: str, raw: bytes) -> None:
        agent = _name(Keys.last(key))
        msg = self.codec.decode(raw)
        if msg.get("t") != "hb" or msg.get("a") != agent:
            raise WireError("origin-mismatch", f"expected a heartbeat of {agent!r}")
        if self.membership is None:
            return
        member = self.membership.heard(agent, msg)
        self._compare(agent, member.layers)

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

    def _fetch_range(self, server: str, origin: str, layer: Layer, want: int) -> bool:
        want = max(want, max((p for p, *_ in layer.pending.values()), default=0), layer.seq + 1)
        replies = self.session.get(
            f"{self.keys.range(server, origin)}?have={layer.seq};want={want}",
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=self.query_timeout_s,
        )
        got = 0
        for reply in replies:
            if reply.ok is None:
                continue
            raw = reply.ok.payload.to_bytes()
            self.metrics.add("bytes_received", len(raw))
            try:
                msg = self.codec.decode(raw)
                if msg.get("t") == "none":
                    continue
                self._offer(origin, msg, raw, expect_origin=origin)
                got += 1
            except WireError as exc:
                self.metrics.reject(exc.reason)
        self.metrics.add("range_repairs")
        return got > 0

    def _fetch_snapshot(self, server: str, origin: str) -> bool:
        t0 = time.monotonic()
        replies = self.session.get(
            self.keys.snapshot(server, origin),
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=self.query_timeout_s,
        )
        chunks: dict[int, Any] = {}
        header: tuple[int, int, int] | None = None
        voxel_limit = self.max_peer_blocks * 512  # a layer larger than the budget is refused
        voxels = 0
        for reply in replies:
            if reply.ok is None:
                continue
            raw = reply.ok.payload.to_bytes()
            self.metrics.add("bytes_received", len(raw))
            try:
                msg = self.codec.decode(raw)
            except WireError as exc:
                self.metrics.reject(exc.reason)
                continue
            if msg.get("t") != "snap" or msg.get("o") != origin:
                self.metrics.reject("bad-snapshot")
                continue
            try:
                h = (int(msg["e"]), int(msg["s"]), int(msg["n"]))
                index = int(msg["i"])
            except (KeyError, TypeError, ValueError):
                self.metrics.reject("bad-snapshot")
                continue
            if header is None:
                header = h
            if h != header or not 0 <= index < h[2] or "delta" not in msg or index in chunks:
                self.metrics.reject("bad-snapshot")
                continue
            voxels += len(msg["delta"])
            if voxels > voxel_limit:
                self.metrics.reject("over-budget")
                log.warning("snapshot of %s from %s exceeds %d voxels; refused", origin, server,
                            voxel_limit)
                return False
            chunks[index] = msg["delta"]
        if header is None or len(chunks) != header[2] or header[0] <= 0:
            return False
        epoch, seq, n = header
        resolution = chunks[0].resolution
        layer = self._layer_for(origin, resolution)
        try:
            self._check_budget(layer, list(chunks.values()), replace=True)
        except WireError as exc:
            self.metrics.reject(exc.reason)
            log.warning("snapshot of %s from %s refused: %s", origin, server, exc)
            return False
        voxels = layer.install_snapshot(epoch, seq, [chunks[i] for i in range(n)])
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
            except Exception:
                log.exception("failed to answer %s", query.selector)
            finally:
                query.drop()

    def _answer(self, query: zenoh.Query) -> None:
        key = str(query.key_expr)
        parts = key.split("/")
        origin, what = parts[-1], parts[-3]
        reply_key = key
        if "*" in origin:
            return
        layer = self.layers.find(origin)
        if layer is None or layer.seq == 0:
            query.reply(reply_key, self.codec.encode({"t": "none", "o": origin}))
            return
        if what == "range":
            params = query.parameters
            try:
                have, want = int(params.get("have") or 0), int(params.get("want") or 0)
            except ValueError:
                self.metrics.reject("bad-query")
                return
            raws = layer.range(have, want)
            if raws is None:
                query.reply(reply_key, self.codec.encode({"t": "none", "o": origin}))
                return
            for raw in raws:
                query.reply(reply_key, raw)
            self.metrics.add("ranges_served")
            return
        epoch, seq, chunks = layer.snapshot(self.chunk_voxels)
        if origin == self.own:
            epoch = self.epoch
        for i, chunk in enumerate(chunks):
            payload = self.codec.encode(
                {"t": "snap", "o": origin, "e": epoch, "s": seq, "i": i, "n": len(chunks),
                 "delta": chunk}
            )
            query.reply(reply_key, payload)
            self.metrics.add("bytes_served", len(payload))
        self.metrics.add("snapshots_served")
