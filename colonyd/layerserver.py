"""Layer server: answers peers' snapshot and delta-range queries for every layer this daemon holds."""

from __future__ import annotations

import threading
import time
from typing import Any

import zenoh

from colonyd.errors import WireError
from colonyd.frames import FRAME_ID, Sender, accept, expect
from colonyd.layers import Layer, Layers
from colonyd.metrics import Metrics
from colonyd.runtime import undeclare
from colonyd.worker import Bounded, Worker
from protocol import (
    DeltaRangeReply,
    DeltaRangeRequest,
    Receiver,
    SnapshotReply,
    SnapshotRequest,
    split_delta,
)
from protocol.codec import FRAME_OVERHEAD
from protocol.keyexpr import parse_key, query_declaration


class LayerServer:
    """The `<own>/snapshot/<layer>` and `<own>/deltas/<layer>` queryables (store and forward:
    any layer held is served), answered in order by one worker."""

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
            "gossip-serve", self._answer, Bounded(64), metrics=metrics, drops="queries_dropped",
            describe=lambda q: f"a query on {q.key_expr}", done=lambda q: q.drop(), stop=stop,
        )
        self._queryables = [
            session.declare_queryable(query_declaration(namespace, self.own, q), self._worker.put)
            for q in ("snapshot", "deltas")
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
        cls = SnapshotRequest if parsed.kind == "snapshot" else DeltaRangeRequest
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
        self._serve_range(query, key, layer, request)

    def _layer_epoch(self, layer: Layer) -> int:
        return self.epoch if layer.origin == self.own else layer.epoch

    def _part_limit(self, request: Any) -> int:
        return max(1024, min(self.part_bytes, request.max_part_bytes) - FRAME_OVERHEAD - 128)

    def _serve_snapshot(self, query: zenoh.Query, key: str, layer: Layer, request: Any) -> None:
        epoch, _seq, chunks = layer.snapshot(self.chunk_voxels)
        if layer.origin == self.own:
            epoch = self.epoch
        limit = self._part_limit(request)
        while True:  # one encoding per part unless a part is too large (then cut it, re-encode)
            msgs = [
                SnapshotReply(
                    origin=self.own, time=time.time(), layer=layer.origin,
                    request_id=request.request_id, frame_id=FRAME_ID, layer_epoch=epoch,
                    part=i, parts=len(chunks), delta=chunk,
                )
                for i, chunk in enumerate(chunks)
            ]
            frames = self.sender.encode_all(msgs)
            big = [i for i, f in enumerate(frames) if len(f) > request.max_part_bytes]
            if not big:
                break
            for i in reversed(big):
                chunks[i:i + 1] = split_delta(chunks[i], limit)
        for frame in frames:
            query.reply(key, frame)
            self.metrics.add("bytes_served", len(frame))
        self.metrics.add("snapshots_served")

    def _serve_range(self, query: zenoh.Query, key: str, layer: Layer | None, request: Any) -> None:
        deltas = None
        epoch = 0
        if layer is not None and layer.seq > 0:
            epoch = self._layer_epoch(layer)
            deltas = layer.range(request.from_version, request.to_version)
        common = {"layer": request.layer, "request_id": request.request_id, "frame_id": FRAME_ID,
                  "layer_epoch": epoch}
        if deltas is None:
            msgs = [DeltaRangeReply(origin=self.own, time=time.time(), **common, complete=False)]
        else:
            limit = self._part_limit(request)
            pieces = [p for d in deltas for p in split_delta(d, limit)]
            msgs = [
                DeltaRangeReply(origin=self.own, time=time.time(), **common, part=i,
                                parts=len(pieces), delta=p)
                for i, p in enumerate(pieces)
            ]
        frames = self.sender.encode_all(msgs)
        for frame in frames:
            query.reply(key, frame)
            self.metrics.add("bytes_served", len(frame))
        if deltas is not None:
            self.metrics.add("ranges_served")
