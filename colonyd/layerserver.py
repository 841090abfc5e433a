"""Layer server: answers peers' snapshot and delta-range queries for every layer this daemon
holds."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

from colonyd.errors import WireError
from colonyd.frames import Sender, accept, expect, frame_of
from colonyd.layers import Layer, Layers
from colonyd.metrics import Metrics
from colonyd.runtime import undeclare
from colonyd.worker import Bounded, Worker
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

#: Most history records one reply carries (a request may ask for fewer).
MAX_HISTORY_RECORDS = 200_000


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
        self._worker: Worker[zenoh.Query] = Worker(
            "gossip-serve",
            self._answer,
            Bounded(64),
            metrics=metrics,
            drops="queries_dropped",
            describe=lambda q: f"a query on {q.key_expr}",
            done=lambda q: q.drop(),
            stop=stop,
        )
        self._queryables = [
            session.declare_queryable(query_declaration(namespace, self.own, q), self._worker.put)
            for q in ("snapshot", "deltas", "history")
        ]

    def start(self) -> None:
        self._worker.start()

    def close(self) -> None:
        self._worker.close()
        undeclare(*self._queryables)

    def _answer(self, query: zenoh.Query) -> None:
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
        layer = self.layers.find(request.layer)
        if parsed.kind == "snapshot":
            if layer is not None and layer.seq > 0:
                self._serve_snapshot(query, key, layer, request)
            return
        if parsed.kind == "history":
            self._serve_history(query, key, layer, request)
            return
        self._serve_range(query, key, layer, request)

    def _layer_epoch(self, layer: Layer) -> int:
        return self.epoch if layer.origin == self.own else layer.epoch

    def _fit(
        self, request: Any, chunks: list[Delta], make: Callable[[int, int, Delta], Message]
    ) -> list[bytes]:
        """Reply frames `make(part, parts, chunk)` of `chunks`, each frame within the request's
        `max_part_bytes` (and ours): parts that come out too large are cut finer and re-encoded
        (one encoding per part in the common case)."""
        max_frame = min(self.part_bytes, request.max_part_bytes)
        limit = max_frame - FRAME_OVERHEAD - 128  # >= 640: max_part_bytes is at least 1024
        while True:
            frames = self.sender.encode_all([make(i, len(chunks), c) for i, c in enumerate(chunks)])
            big = [i for i, f in enumerate(frames) if len(f) > max_frame]
            if not big:
                return frames
            if limit < MIN_PART_BODY:
                text = f"expected parts within {max_frame} bytes, found a voxel too large for one"
                raise WireError("oversized", text)
            for i in reversed(big):
                chunks[i : i + 1] = split_delta(chunks[i], limit)
            limit //= 2  # still too large next time: the frame around a body grew, cut finer

    def _reply(self, query: zenoh.Query, key: str, frames: list[bytes]) -> None:
        for frame in frames:
            query.reply(key, frame)
            self.metrics.add("bytes_served", len(frame))

    def _serve_snapshot(self, query: zenoh.Query, key: str, layer: Layer, request: Any) -> None:
        cpu0 = time.thread_time()
        marks = {"query": time.monotonic()}
        epoch, _seq, chunks = layer.snapshot(self.chunk_voxels)
        marks["snapshot"] = time.monotonic()
        if layer.origin == self.own:
            epoch = self.epoch
        common = {
            "origin": self.own,
            "layer": layer.origin,
            "request_id": request.request_id,
            "frame_id": frame_of(layer.origin),
            "layer_epoch": epoch,
        }
        frames = self._fit(
            request,
            chunks,
            lambda i, n, c: SnapshotReply(**common, time=time.time(), part=i, parts=n, delta=c),
        )
        marks["encoded"] = time.monotonic()
        self._reply(query, key, frames)
        marks["replied"] = time.monotonic()
        marks["serve_cpu_s"] = time.thread_time() - cpu0
        self.metrics.add("snapshots_served")
        self.metrics.served(layer.origin, marks)

    def _serve_range(self, query: zenoh.Query, key: str, layer: Layer | None, request: Any) -> None:
        """Deltas of (from_version, min(to_version, newest)]: none if that range is empty
        (`complete`, no delta), `complete` False if it is no longer held or the layer is not."""
        deltas = None
        epoch = 0
        if layer is not None and layer.seq > 0:
            epoch = self._layer_epoch(layer)
            deltas = layer.range(request.from_version, request.to_version)
        common = {
            "origin": self.own,
            "layer": request.layer,
            "request_id": request.request_id,
            "frame_id": frame_of(request.layer),
            "layer_epoch": epoch,
        }
        if not deltas:
            msg = DeltaRangeReply(**common, time=time.time(), complete=deltas is not None)
            self._reply(query, key, self.sender.encode_all([msg]))
            return
        frames = self._fit(
            request,
            list(deltas),
            lambda i, n, c: DeltaRangeReply(**common, time=time.time(), part=i, parts=n, delta=c),
        )
        self._reply(query, key, frames)
        self.metrics.add("ranges_served")

    def _serve_history(
        self, query: zenoh.Query, key: str, layer: Layer | None, request: Any
    ) -> None:
        """History records of versions above `from_version`, a page of whole versions, in parts
        that each fit `max_part_bytes` (`layer_epoch` 0: the layer is not held)."""
        epoch, page, to, more = 0, None, request.from_version, False
        if layer is not None and layer.seq > 0:
            with layer.lock:
                epoch = self._layer_epoch(layer)
                page, to, more = layer.grid.history.page(
                    request.from_version, min(request.max_records, MAX_HISTORY_RECORDS)
                )
        common = {
            "origin": self.own,
            "layer": request.layer,
            "request_id": request.request_id,
            "layer_epoch": epoch,
            "from_version": request.from_version,
            "to_version": to,
            "more": more,
        }
        pieces: list[HistoryPage | None] = [page if page and page.records.size else None]
        max_frame = min(self.part_bytes, request.max_part_bytes)
        while True:
            frames = self.sender.encode_all(
                [
                    HistoryReply(**common, time=time.time(), part=i, parts=len(pieces), records=p)
                    for i, p in enumerate(pieces)
                ]
            )
            big = [i for i, f in enumerate(frames) if len(f) > max_frame]
            if not big:
                break
            for i in reversed(big):
                p = pieces[i]
                if p is None or p.records.size + p.seen.size < 2:
                    text = (
                        f"expected history parts within {max_frame} bytes, found a record too large"
                    )
                    raise WireError("oversized", text)
                half, seen_half = p.records.size // 2, p.seen.size // 2
                pieces[i : i + 1] = [
                    HistoryPage(p.records[:half], p.agents, p.seen[:seen_half]),
                    HistoryPage(p.records[half:], p.agents, p.seen[seen_half:]),
                ]
        self._reply(query, key, frames)
        self.metrics.add("histories_served")
