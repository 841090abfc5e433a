"""The layer server's replies on a real Zenoh session (loopback, no multicast): snapshot and
history answers cut into parts that each fit the requester's `max_part_bytes`, and whole."""

from __future__ import annotations

import threading

import numpy as np
import zenoh

from colonyd.frames import Sender, get_receiver
from colonyd.historysync import join_pages
from colonyd.layers import Layers
from colonyd.layerserver import LayerServer
from colonyd.metrics import Metrics
from colonyd.runtime import open_session, zenoh_config
from protocol import HistoryReply, HistoryRequest, Message, SnapshotReply, SnapshotRequest
from protocol.codec import decode
from protocol.keyexpr import query_key
from voxel.grid import VoxelGrid
from voxel.history import History

NS = "test-layerserver"


def _ask(session: zenoh.Session, kind: str, request: Message) -> list[tuple[int, Message]]:
    out = []
    for reply in session.get(
        query_key(NS, "a", kind, "a"),
        payload=Sender("asker", 1).encode(request),
        consolidation=zenoh.ConsolidationMode.NONE,
        timeout=20.0,
    ):
        assert reply.ok is not None
        raw = reply.ok.payload.to_bytes()
        out.append((len(raw), decode(raw)))
    return out


def test_replies_too_large_for_a_part_are_cut_until_every_part_fits() -> None:
    layers = Layers("a", 0.1)
    layer = layers.get("a")
    origin = np.array([0.05, 0.05, 0.05])
    for t in range(40):  # a wall moving away: a few thousand history records and voxels
        wall = np.column_stack([np.full(60, 1.05 + 0.1 * t), np.arange(60) * 0.1, np.zeros(60)])
        layer.grid.integrate(wall, origin, time=float(t))
    layer.seq = 1
    session = open_session(zenoh_config(listen=["tcp/127.0.0.1:0"]))
    stop = threading.Event()
    server = LayerServer(
        session,
        NS,
        layers,
        Sender("a", 3),
        get_receiver(None, 64.0, "a"),
        Metrics(),
        epoch=3,
        stop=stop,
    )
    server.start()
    try:
        header = Sender("asker", 1).header()
        small = {"layer": "a", "request_id": 7, "max_part_bytes": 1024}
        history = _ask(session, "history", HistoryRequest(**header, **small, from_version=0))
        assert len(history) > 2 and all(size <= 1024 for size, _ in history)
        replies = [m for _, m in history if isinstance(m, HistoryReply)]
        assert len(replies) == len(history) and all(m.layer_epoch == 3 for m in replies)
        assert sorted(m.part for m in replies) == list(range(len(replies)))
        page = join_pages(replies)
        assert page is not None
        merged = History()
        merged.merge(page)
        held = layer.grid.history
        assert merged.size == held.size > 1000 and merged.seen().size == held.seen().size
        for got, want in ((merged.view(), held.view()), (merged.seen(), held.seen())):
            np.testing.assert_array_equal(np.sort(got["key"]), np.sort(want["key"]))
        snapshot = _ask(session, "snapshot", SnapshotRequest(**header, **small))
        assert len(snapshot) > 2 and all(size <= 1024 for size, _ in snapshot)
        rebuilt = VoxelGrid(0.1)
        for _, m in snapshot:
            assert isinstance(m, SnapshotReply) and m.frame_id and m.delta is not None
            rebuilt.apply(m.delta)
        np.testing.assert_array_equal(
            np.sort(rebuilt.occupied_keys(), axis=0), np.sort(layer.grid.occupied_keys(), axis=0)
        )
    finally:
        stop.set()
        server.close()
        session.close()


def test_the_own_layers_history_is_served_only_as_far_as_its_log_holds_it() -> None:
    """Versions not yet logged are lost by a SIGKILL and then reused for other scans: a peer
    that took their history would keep records the origin no longer has (and miss the new
    ones of the same versions). The own layer answers up to its logged version only."""
    layers = Layers("a", 0.1)
    layer = layers.get("a")
    origin = np.array([0.05, 0.05, 0.05])
    for t in range(10):
        wall = np.column_stack([np.full(20, 1.05 + 0.1 * t), np.arange(20) * 0.1, np.zeros(20)])
        layer.grid.integrate(wall, origin, time=float(t))
        if t == 4:
            logged = int(layer.grid.version)
    layer.seq, layer.logged = 1, logged
    session = open_session(zenoh_config(listen=["tcp/127.0.0.1:0"]))
    stop = threading.Event()
    server = LayerServer(
        session, NS, layers, Sender("a", 3), get_receiver(None, 64.0, "a"), Metrics(), epoch=3,
        stop=stop,
    )  # fmt: skip
    server.start()
    try:
        header = Sender("asker", 1).header()
        ask = {"layer": "a", "request_id": 7, "from_version": 0}
        replies = [m for _, m in _ask(session, "history", HistoryRequest(**header, **ask))]
        assert all(isinstance(m, HistoryReply) for m in replies)
        page = join_pages(replies)
        assert page is not None and page.records.size > 0
        assert int(page.records["version"].max()) <= logged < int(layer.grid.version)
        assert all(m.to_version <= logged and not m.more for m in replies)
        held = layer.grid.history.view()
        assert page.records.size == int((held["version"] <= logged).sum())
    finally:
        stop.set()
        server.close()
        session.close()
