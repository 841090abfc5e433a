"""A peer written from docs/PROTOCOL.md alone (msgpack, zstd, hmac, zenoh; no protocol package)
talks to a real daemon: key derivation, signatures, reply keys, range edge cases, small parts,
the apply rule. Its requests are unsigned (requests may be); every frame of the daemon is signed."""

from __future__ import annotations

import hashlib
import hmac
import itertools
import json
import math
import struct
import threading
import time

import msgpack
import zenoh

from tests.protocol.test_independent_peer import peer_decode_frame, peer_delta

PASSPHRASE = "correct horse battery staple"
SNAPSHOT_REQUEST, SNAPSHOT_REPLY, RANGE_REQUEST, RANGE_REPLY, HEARTBEAT = 6, 7, 8, 9, 10


class Peer:
    """§2-§5 by hand: frames of origin 'peer', replies decoded with the §6 decoder."""

    def __init__(self, endpoint: str, namespace: str) -> None:
        self.key = hashlib.sha256(PASSPHRASE.encode()).digest()  # §4: the passphrase's SHA-256
        self.ns = namespace
        self.seq = 0
        self.identities: dict[str, bytes] = {}  # pinned from heartbeats (trust on first use)
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("listen/endpoints", json.dumps(["tcp/127.0.0.1:0"]))
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        self.session = zenoh.open(conf)

    def frame(self, mtype: int, body: dict) -> bytes:
        self.seq += 1
        prefix = b"CLNY" + bytes([1, mtype, 0x01, 0])  # authenticated, uncompressed
        envelope = msgpack.packb(
            ["peer", 1, self.seq, time.time(), msgpack.packb(body, use_bin_type=True)],
            use_bin_type=True,
        )
        data = prefix + envelope
        return data + hmac.new(self.key, data, hashlib.sha256).digest()

    def ask(self, server: str, query: str, layer: str, mtype: int, body: dict) -> list:
        """(reply key, frame size, decoded envelope and body) of every reply."""
        key = f"colony/{self.ns}/{server}/{query}/{layer}"
        out = []
        for reply in self.session.get(
            key,
            payload=self.frame(mtype, body),
            timeout=30.0,  # the query ends once 'a' answered, however long a loaded one takes
            consolidation=zenoh.ConsolidationMode.NONE,
        ):
            assert reply.ok is not None
            raw = reply.ok.payload.to_bytes()
            rtype, header, decoded = peer_decode_frame(raw, self.key, self.identities[server])
            out.append((str(reply.ok.key_expr), len(raw), rtype, header, decoded))
        return out

    def heartbeat_of(self, agent: str) -> dict:
        got: list[bytes] = []
        ready = threading.Event()

        def keep(sample: zenoh.Sample) -> None:
            got.append(sample.payload.to_bytes())
            ready.set()

        sub = self.session.declare_subscriber(f"colony/{self.ns}/{agent}/heartbeat", keep)
        try:
            assert ready.wait(30.0), f"no heartbeat of {agent}"
        finally:
            sub.undeclare()
        mtype, header, body = peer_decode_frame(got[0], self.key)  # verified with its identity
        assert mtype == HEARTBEAT and header[0] == agent and len(body["identity"]) == 32
        self.identities[agent] = body["identity"]
        return body


def apply(replica: dict, delta: dict) -> None:
    """§5 apply rule, per voxel: absolute values; -128 (NaN) makes a voxel unknown."""
    for k, lo in zip(delta["keys"], delta["logodds"], strict=True):
        if math.isnan(lo):
            replica.pop(k, None)
        else:
            replica[k] = lo


def test_a_peer_from_the_document_talks_to_a_daemon(make_colony):
    colony = make_colony("doc", extra=["--colony-key", PASSPHRASE])
    colony.add("a", ["synthetic:scans=6,rate=8,points=300,seed=3"])
    colony.wait_converged(30)
    peer = Peer(colony.daemons["a"].endpoint, colony.namespace)
    try:
        hb = peer.heartbeat_of("a")
        (mine,) = [lv for lv in hb["layers"] if lv["origin"] == "a"]
        epoch, version = mine["epoch"], mine["version"]
        assert version >= 2
        # an empty range: one complete reply with no delta, on the query's key, from 'a'
        replies = peer.ask(
            "a",
            "deltas",
            "a",
            RANGE_REQUEST,
            {"layer": "a", "request_id": 7, "from_version": version, "to_version": version},
        )
        assert len(replies) == 1
        key, _, rtype, header, body = replies[0]
        assert key == f"colony/{colony.namespace}/a/deltas/a" and header[0] == "a"
        assert rtype == RANGE_REPLY and body["request_id"] == 7
        assert body.get("complete", True) is True and body.get("delta") is None
        assert body["layer_epoch"] == epoch
        # a range reaching beyond the newest version ends at it; applied in order from 0,
        # it gives the layer the snapshot holds
        replies = peer.ask(
            "a",
            "deltas",
            "a",
            RANGE_REQUEST,
            {"layer": "a", "request_id": 8, "from_version": 0, "to_version": version + 1000},
        )
        parts = sorted((b.get("part", 0), b) for *_, b in replies)
        assert [p for p, _ in parts] == list(range(len(parts)))
        assert all(b.get("parts", 1) == len(parts) and b.get("complete", True) for _, b in parts)
        deltas = [peer_delta(b["delta"]) for _, b in parts]
        versions = [
            (msgpack.unpackb(b["delta"])["from"], msgpack.unpackb(b["delta"])["to"])
            for _, b in parts
        ]
        assert versions[0][0] == 0 and versions[-1][1] == version
        assert all(a[1] == b[0] for a, b in itertools.pairwise(versions))  # contiguous
        from_ranges: dict = {}
        for d in deltas:
            apply(from_ranges, d)
        # a snapshot in parts of at most 1024 bytes (the smallest max_part_bytes)
        replies = peer.ask(
            "a",
            "snapshot",
            "a",
            SNAPSHOT_REQUEST,
            {"layer": "a", "request_id": 9, "max_part_bytes": 1024},
        )
        assert len(replies) > 1 and all(size <= 1024 for _, size, *_ in replies)
        bodies = [b for *_, b in replies]
        assert sorted(b.get("part", 0) for b in bodies) == list(range(len(bodies)))
        snapshot: dict = {}
        for b in bodies:
            assert b["layer_epoch"] == epoch and msgpack.unpackb(b["delta"])["to"] == version
            apply(snapshot, peer_delta(b["delta"]))
        assert snapshot == from_ranges and len(snapshot) > 100
    finally:
        peer.session.close()


def test_unknown_voxels_and_missing_channels_as_the_document_says() -> None:
    """-128 makes a voxel unknown (a block left all unknown is freed, channels and all); a
    channel a delta does not carry keeps its values."""
    import numpy as np

    from protocol.codec import encode
    from protocol.messages import VoxelDelta
    from voxel.delta import Delta
    from voxel.grid import VoxelGrid

    keys = np.array([[1, 2, 3], [4, 5, 6]])
    first = Delta(
        0.1,
        0,
        1,
        keys,
        np.array([0.5, -0.25], np.float32),
        np.array([1.0, 1.0]),
        {"hits": np.array([3, 7], np.uint16)},
        1.0,
    )
    second = Delta(
        0.1, 1, 2, keys, np.array([np.nan, -0.25], np.float32), np.array([2.0, 2.0]), {}, 2.0
    )
    grid = VoxelGrid(0.1)
    peer: dict = {}
    hits: dict = {}
    for d in (first, second):
        grid.apply(d)
        _, _, body = peer_decode_frame(
            encode(VoxelDelta(origin="r", time=d.time, frame_id="map", delta=d)), None
        )
        decoded = peer_delta(body["delta"])
        apply(peer, decoded)
        hits.update(zip(decoded["keys"], decoded["channels"].get("hits", []), strict=False))
    ref = grid.delta_since(0)
    known = ~np.isnan(ref.logodds)
    assert peer == {
        tuple(k): float(lo)
        for k, lo in zip(ref.keys[known].tolist(), ref.logodds[known], strict=True)
    }
    assert peer == {(4, 5, 6): -0.25}
    row = int(np.flatnonzero((ref.keys == [4, 5, 6]).all(1))[0])
    assert ref.channels["hits"][row] == hits[(4, 5, 6)] == 7  # not carried again: kept
    assert not (ref.keys == [1, 2, 3]).all(1).any()  # forgotten: its block was freed
    _ = struct  # the peer decoder's struct use lives in tests.protocol.test_independent_peer
