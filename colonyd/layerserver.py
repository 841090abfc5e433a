"""Layer server: answers peers' snapshot and delta-range queries for every layer this daemon
holds."""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh

from colonyd.errors import WireError
from colonyd.frames import Sender, accept, expect, frame_of
from colonyd.layers import Layer, Layers
from colonyd.metrics import Metrics
from colonyd.runtime import undeclare
from colonyd.worker import Bounded, Throttle, Worker, held_text
from protocol import (
    DeltaRangeReply,
    DeltaRangeRequest,
    HistoryReply,
    HistoryRequest,
    Message,
    Receiver,
    SnapshotReply,
    SnapshotRequest,
    split_delta,
)
from protocol.codec import FRAME_OVERHEAD
from protocol.deltacodec import MIN_PART_BODY
from protocol.keyexpr import parse_key, query_declaration
from voxel.delta import Delta
from voxel.history import HistoryPage

log = logging.getLogger(__name__)

#: Most history records one reply carries (a request may ask for fewer).
MAX_HISTORY_RECORDS = 200_000


@dataclass
class Arrived:
    """A query as the Zenoh callback took it."""

    query: zenoh.Query
    at: float  # time.monotonic() then


class Abandoned(Exception):
    """The requester of a query has stopped waiting for its replies (its `timeout_ms` passed)."""


class LayerServer:
    """The `<own>/snapshot/<layer>`, `<own>/deltas/<layer>` and `<own>/history/<layer>`
    queryables (store and forward: any layer held is served), answered in order by one worker."""

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
        chunk_voxels: int = 250_000,
        part_bytes: int = 4 << 20,
        stop: threading.Event | None = None,
    ) -> None:
        self.layers = layers
        self.sender = sender
        self.receiver = receiver
        self.metrics = metrics
        self.own = layers.own_id
        self.epoch = epoch
        self.chunk_voxels = chunk_voxels
        self.part_bytes = part_bytes
        self._log = Throttle()
        self._worker: Worker[Arrived] = Worker(
            "gossip-serve",
            self._answer,
            Bounded(64),
            metrics=metrics,
            drops="queries_dropped",
            describe=lambda a: f"a query on {a.query.key_expr}",
            done=lambda a: a.query.drop(),
            stop=stop,
        )
        self._queryables = [
            session.declare_queryable(query_declaration(namespace, self.own, q), self._arrived)
            for q in ("snapshot", "deltas", "history")
        ]

    def _arrived(self, query: zenoh.Query) -> None:
        """The queryables' callback (a Zenoh thread): stamp and enqueue."""
        self._worker.put(Arrived(query, time.monotonic()))

    def start(self) -> None:
        self._worker.start()

    def close(self) -> None:
        self._worker.close()
        undeclare(*self._queryables)

    def _answer(self, arrived: Arrived) -> None:
        query = arrived.query
        key = str(query.key_expr)
        parsed = parse_key(key)
        if parsed.origin != self.own or parsed.layer is None:
            raise WireError("bad-query", f"expected a query for {self.own!r}, found {key!r}")
        if query.payload is None:
            raise WireError("bad-query", f"expected a request frame as the payload of {key!r}")
        raw = query.payload.to_bytes()
        msg = self.receiver.decode(raw)  # the requester's frame: its origin is not the key's
        requests: dict[str, type[Message]] = {
            "snapshot": SnapshotRequest,
            "deltas": DeltaRangeRequest,
            "history": HistoryRequest,
        }
        cls = requests[parsed.kind]
        request = expect(msg, cls, f"on {key}")
        if request.layer != parsed.layer:
            text = f"expected layer {parsed.layer!r}, found {request.layer!r}"
            raise WireError("bad-query", text)
        accept(self.receiver, self.metrics, request, raw)
        timeout_ms = getattr(request, "timeout_ms", 0)
        deadline = arrived.at + timeout_ms / 1000 if timeout_ms else math.inf
        try:
            _check(deadline, "in the queue")  # waited longer than its requester waits
            layer = self.layers.find(request.layer)
            if parsed.kind == "snapshot":
                if layer is not None and layer.seq > 0:
                    self._serve_snapshot(query, key, layer, request, arrived.at, deadline)
                return
            if parsed.kind == "history":
                self._serve_history(query, key, layer, request, deadline)
                return
            self._serve_range(query, key, layer, request, deadline)
        except Abandoned as exc:
            self.metrics.add("queries_abandoned")
            if (held := self._log.allow("abandoned")) is not None:  # anyone may ask: throttled
                log.info(
                    "stopped answering %s from %s: its requester waited %d ms (%s)%s",
                    key,
                    request.origin,
                    timeout_ms,
                    exc,
                    held_text(held),
                )

    def _layer_epoch(self, layer: Layer) -> int:
        return self.epoch if layer.origin == self.own else layer.epoch

    def _header(self, request: Any, epoch: int, *, framed: bool = True) -> dict[str, Any]:
        """The fields every reply to `request` carries: us, the layer, the request, the layer's
        epoch (0: not held) and, `framed`, the layer's frame."""
        out: dict[str, Any] = {
            "origin": self.own,
            "layer": request.layer,
            "request_id": request.request_id,
            "layer_epoch": epoch,
        }
        if framed:
            out["frame_id"] = frame_of(request.layer)
        return out

    def _fit(
        self,
        request: Any,
        chunks: list[Delta],
        make: Callable[[int, int, Delta], Message],
        deadline: float = math.inf,
        marks: dict[str, float] | None = None,
    ) -> list[bytes]:
        """Reply frames `make(part, parts, chunk)` of `chunks`, each frame within the request's
        `max_part_bytes` (and ours): parts that come out too large are cut finer and re-encoded
        (one encoding per part in the common case). Raises Abandoned before a part once
        `deadline` (time.monotonic()) has passed; `marks` gets "encoded_first", when the first
        part's frame was done."""
        max_frame = min(self.part_bytes, request.max_part_bytes)
        limit = max_frame - FRAME_OVERHEAD - 128  # >= 640: max_part_bytes is at least 1024

        def before(i: int) -> None:
            if i == 1 and marks is not None:
                marks.setdefault("encoded_first", time.monotonic())
            _check(deadline, f"{i} of {len(chunks)} parts encoded")

        def split(chunk: Delta, again: int) -> list[Delta]:
            # still too large the next time: the frame around a body grew, cut finer
            if limit >> again < MIN_PART_BODY:
                text = f"expected parts within {max_frame} bytes, found a voxel too large for one"
                raise WireError("oversized", text)
            return split_delta(chunk, limit >> again)

        return self._frames_within(max_frame, chunks, make, split, before)

    def _frames_within(
        self,
        max_frame: int,
        pieces: list[Any],
        make: Callable[[int, int, Any], Message],
        split: Callable[[Any, int], list[Any]],
        before: Callable[[int], None] | None = None,
    ) -> list[bytes]:
        """Frames of `make(part, parts, piece)` for `pieces`, each within `max_frame` bytes: a
        piece whose frame is larger is replaced by `split(piece, round)` (round 0, 1, ... for
        the times pieces were split before) and every part encoded again. `before(i)` is called
        before the i-th frame is encoded."""
        again = 0
        while True:
            msgs = [make(i, len(pieces), p) for i, p in enumerate(pieces)]
            frames = self.sender.encode_all(msgs, before=before)
            big = [i for i, f in enumerate(frames) if len(f) > max_frame]
            if not big:
                return frames
            for i in reversed(big):
                pieces[i : i + 1] = split(pieces[i], again)
            again += 1

    def _reply(
        self,
        query: zenoh.Query,
        key: str,
        frames: list[bytes],
        deadline: float = math.inf,
        marks: dict[str, float] | None = None,
    ) -> None:
        """Send `frames` (stopping with Abandoned once `deadline` has passed); `marks` gets
        "first_reply", when the first was handed to Zenoh."""
        for i, frame in enumerate(frames):
            _check(deadline, f"{i} of {len(frames)} parts sent")
            query.reply(key, frame)
            self.metrics.add("bytes_served", len(frame))
            if i == 0 and marks is not None:
                marks["first_reply"] = time.monotonic()

    def _serve_snapshot(
        self,
        query: zenoh.Query,
        key: str,
        layer: Layer,
        request: Any,
        arrived: float,
        deadline: float,
    ) -> None:
        """The layer's snapshot in parts; its timeline in `metrics.serves` (also when abandoned):
        "arrived" (the Zenoh callback took the query), "query" (this worker did), "locked" (the
        layer's lock taken), "snapshot" (its content copied), "encoded_first", "encoded" (every
        part's frame), "first_reply", "replied", and the thread's and process's CPU seconds."""
        cpu0, process0 = time.thread_time(), time.process_time()
        marks = {"arrived": arrived, "query": time.monotonic()}
        try:
            try:  # (the own layer's waits for its grid to be logged)
                epoch, _seq, chunks = layer.snapshot(self.chunk_voxels, marks, deadline)
            except TimeoutError as exc:
                raise Abandoned(str(exc)) from None
            marks["snapshot"] = time.monotonic()
            _check(deadline, "snapshot made")
            if layer.origin == self.own:
                epoch = self.epoch
            common = self._header(request, epoch)
            frames = self._fit(
                request,
                chunks,
                lambda i, n, c: SnapshotReply(**common, time=time.time(), part=i, parts=n, delta=c),
                deadline,
                marks,
            )
            marks["encoded"] = time.monotonic()
            marks.setdefault("encoded_first", marks["encoded"])
            self._reply(query, key, frames, deadline, marks)
            marks["replied"] = time.monotonic()
        except Abandoned:
            marks["abandoned"] = time.monotonic()
            raise
        finally:
            marks["serve_cpu_s"] = time.thread_time() - cpu0
            marks["serve_process_cpu_s"] = time.process_time() - process0  # every thread's
            self.metrics.served(layer.origin, marks)
        self.metrics.add("snapshots_served")

    def _serve_range(
        self,
        query: zenoh.Query,
        key: str,
        layer: Layer | None,
        request: Any,
        deadline: float = math.inf,
    ) -> None:
        """Deltas of (from_version, min(to_version, newest)]: none if that range is empty
        (`complete`, no delta), `complete` False if it is no longer held or the layer is not."""
        deltas = None
        epoch = 0
        if layer is not None and layer.seq > 0:
            epoch = self._layer_epoch(layer)
            deltas = layer.range(request.from_version, request.to_version)
        common = self._header(request, epoch)
        if not deltas:
            msg = DeltaRangeReply(**common, time=time.time(), complete=deltas is not None)
            self._reply(query, key, self.sender.encode_all([msg]))
            return
        frames = self._fit(
            request,
            list(deltas),
            lambda i, n, c: DeltaRangeReply(**common, time=time.time(), part=i, parts=n, delta=c),
            deadline,
        )
        self._reply(query, key, frames, deadline)
        self.metrics.add("ranges_served")

    def _serve_history(
        self,
        query: zenoh.Query,
        key: str,
        layer: Layer | None,
        request: Any,
        deadline: float = math.inf,
    ) -> None:
        """History records of versions above `from_version`, a page of whole versions, in parts
        that each fit `max_part_bytes` (`layer_epoch` 0: the layer is not held)."""
        epoch, page, to, more = 0, None, request.from_version, False
        if layer is not None and layer.seq > 0:
            with layer.lock:
                epoch = self._layer_epoch(layer)
                # the own layer's history only as far as its log holds it: versions not yet
                # logged are lost by a SIGKILL and then reused for other scans
                page, to, more = layer.grid.history.page(
                    request.from_version,
                    min(request.max_records, MAX_HISTORY_RECORDS),
                    upto=layer.logged,
                )
        common = {
            **self._header(request, epoch, framed=False),
            "from_version": request.from_version,
            "to_version": to,
            "more": more,
        }
        max_frame = min(self.part_bytes, request.max_part_bytes)

        def halves(p: HistoryPage | None, _again: int) -> list[HistoryPage | None]:
            if p is None or p.records.size + p.seen.size < 2:
                text = f"expected history parts within {max_frame} bytes, found a record too large"
                raise WireError("oversized", text)
            half, seen_half = p.records.size // 2, p.seen.size // 2
            return [
                HistoryPage(p.records[:half], p.agents, p.seen[:seen_half]),
                HistoryPage(p.records[half:], p.agents, p.seen[seen_half:]),
            ]

        frames = self._frames_within(
            max_frame,
            [page if page and page.records.size else None],
            lambda i, n, p: HistoryReply(**common, time=time.time(), part=i, parts=n, records=p),
            halves,
        )
        self._reply(query, key, frames, deadline)
        self.metrics.add("histories_served")


def _check(deadline: float, where: str = "") -> None:
    """Raise Abandoned once `deadline` (time.monotonic()) has passed."""
    if time.monotonic() > deadline:
        raise Abandoned(where)
