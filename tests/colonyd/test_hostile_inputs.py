"""Hostile input a daemon's inbox, membership and catch-up take in-process, on real (loopback, no
scouting) Zenoh sessions and real frames: refused, bounded, and leaving nothing behind."""

from __future__ import annotations

import functools
import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import SimpleNamespace

import numpy as np
import zenoh

from colonyd.alignment import Alignments
from colonyd.catchup import CatchUp
from colonyd.errors import WireError
from colonyd.frames import Sender, colony_key
from colonyd.inbox import Inbox, Item
from colonyd.layers import BLOCK_VOXELS, Layer, Layers
from colonyd.membership import Membership
from colonyd.metrics import Metrics
from colonyd.objects import MAX_PEER_OBJECTS, PeerObjects
from colonyd.replicas import Replicas
from colonyd.runtime import open_session, zenoh_config
from protocol import (
    AlignOffer,
    DeltaRangeReply,
    Heartbeat,
    HistoryReply,
    LayerVersion,
    ObjectCentroid,
    Objects,
    Pose,
    PoseFix,
    ProtocolError,
    Receiver,
    SnapshotReply,
    SnapshotRequest,
    VoxelDelta,
    decode,
)
from protocol.identity import Signer, Trust
from protocol.keyexpr import alive_key, query_key, topic_key
from voxel import keys as vk
from voxel.delta import Delta
from voxel.history import MAX_AGENTS, HistoryPage
from voxel.record import RECORD_DTYPE

NS = "hostile-in"
KEY = colony_key("correct horse battery staple")


def _endpoint() -> str:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return f"tcp/127.0.0.1:{port}"


@contextmanager
def _sessions(n: int) -> Iterator[list[zenoh.Session]]:
    """`n` sessions on loopback, the first listening and the others connected to it."""
    ep = _endpoint()
    sessions = [open_session(zenoh_config(listen=[ep]))]
    try:
        for _ in range(n - 1):
            sessions.append(open_session(zenoh_config(listen=["tcp/127.0.0.1:0"], connect=[ep])))
        yield sessions
    finally:
        for s in sessions:
            s.close()


def _until(check: Callable[[], bool], seconds: float = 10.0) -> bool:
    deadline = time.monotonic() + seconds
    while not check():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


def _daemon(
    session: zenoh.Session, *, max_members: int = 256, key: bytes | None = KEY
) -> SimpleNamespace:
    """The receiving side of daemon "me" (a colony closed with `key`, identities on first use):
    its inbox (not started: items are handed to it as its worker would), membership and what
    they fill."""
    metrics = Metrics()
    layers = Layers("me", 0.1, max_peer_blocks=1000)
    replicas = Replicas(layers, metrics)
    trust = Trust("tofu")
    receiver = Receiver(key=key, own="me", trust=trust)
    alignments = Alignments()
    peer_objects = PeerObjects()
    inbox = Inbox(
        session,
        NS,
        replicas,
        receiver,
        metrics,
        peer_objects,
        alignments,
        request_repair=lambda origin, servers: None,
        send_heartbeat=lambda: None,
    )
    membership = Membership(session, NS, "me", inbox.on_member_event, max_members)
    inbox.membership = membership

    def feed(kind: str, agent: str, raw: bytes) -> None:
        item: Item = (kind, topic_key(NS, agent, {"hb": "heartbeat"}.get(kind, kind)), raw, {})
        try:
            inbox._handle(item)
        except Exception as exc:  # noqa: BLE001 - as the inbox's worker takes a refusal
            inbox._worker._failed(item, exc)

    return SimpleNamespace(
        metrics=metrics,
        layers=layers,
        replicas=replicas,
        alignments=alignments,
        peer_objects=peer_objects,
        trust=trust,
        receiver=receiver,
        inbox=inbox,
        membership=membership,
        feed=feed,
        close=lambda: (membership.close(), inbox.close()),
    )


def _heartbeat(agent: str, signer: Signer, seq: int = 1, key: bytes | None = KEY) -> bytes:
    sender = Sender(agent, 7, key=key, signer=signer, first_seq=seq)
    hb = Heartbeat(
        **sender.header(), kind="robot", frame_id=f"{agent}.odom", identity=signer.public
    )
    return sender.encode(hb)


def test_liveliness_tokens_of_strangers_leave_no_members_behind() -> None:
    """Liveliness tokens are not authenticated (no colony key reaches them): a stranger that
    declares and undeclares made-up agent ids must not grow the member table without end."""
    with _sessions(3) as (mine, real, stranger):
        d = _daemon(mine)
        try:
            b = Membership(real, NS, "b", lambda agent, event: None)
            assert _until(lambda: d.membership.find("b") is not None)
            tokens = [
                stranger.liveliness().declare_token(alive_key(NS, f"x{i}")) for i in range(40)
            ]
            assert _until(lambda: len(d.membership.alive()) == 41)
            for token in tokens:
                token.undeclare()
            assert _until(lambda: d.membership.alive() == ["b"])
            time.sleep(0.2)  # any late leave event
            assert [m.agent for m in d.membership.table()] == ["b"]
            b.close()
        finally:
            d.close()


def test_heartbeats_of_made_up_agents_fill_no_more_than_max_members() -> None:
    """A key holder (or anyone, in an open colony) sending heartbeats under ever new agent ids:
    the table keeps at most `max_members` heard members, forgetting those without a liveliness
    token first; when every one holds a token a newcomer is refused before it is accepted (no
    replay window moved, no key pinned)."""
    with _sessions(2) as (mine, other):
        d = _daemon(mine, max_members=4)
        try:
            tokens = [other.liveliness().declare_token(alive_key(NS, "real"))]
            assert _until(lambda: d.membership.alive() == ["real"])
            d.feed("hb", "real", _heartbeat("real", Signer.generate()))
            for i in range(10):  # no tokens: the least recently seen of them makes room
                d.feed("hb", f"fake{i}", _heartbeat(f"fake{i}", Signer.generate()))
            table = {m.agent for m in d.membership.table()}
            assert table == {"real", "fake7", "fake8", "fake9"}, table
            tokens += [
                other.liveliness().declare_token(alive_key(NS, f"fake{i}")) for i in (7, 8, 9)
            ]
            assert _until(lambda: len(d.membership.alive()) == 4)
            d.feed("hb", "late", _heartbeat("late", Signer.generate()))
            assert d.metrics.rejected["too-many-members"] == 1
            assert d.membership.find("late") is None
            assert "late" not in d.trust.pins()
            assert d.receiver.accepted["heartbeat"] == 11
            # its window did not move: the same frame numbers are still fresh for it
            d.receiver.replay.peek("late", 7, 1)
            assert "late" not in d.receiver.replay._state
            for token in tokens:
                token.undeclare()
        finally:
            d.close()


def test_a_token_between_admit_and_heard_evicts_no_live_member() -> None:
    """A heard member without a token makes room for a newcomer (`admit`), but its token comes
    back before the newcomer's heartbeat is recorded (`heard`): no live member may be forgotten
    for it (the least recently seen one was, and its heartbeats were then refused as one too
    many: a stranger timing tokens could lock real members out one by one)."""
    with _sessions(2) as (mine, other):
        d = _daemon(mine, max_members=2)
        try:
            tokens = [other.liveliness().declare_token(alive_key(NS, "real"))]
            assert _until(lambda: d.membership.alive() == ["real"])
            real = Signer.generate()
            d.feed("hb", "real", _heartbeat("real", real))
            d.feed("hb", "ghost", _heartbeat("ghost", Signer.generate()))  # no token
            d.membership.admit("new")  # room: the ghost has no token
            tokens.append(other.liveliness().declare_token(alive_key(NS, "ghost")))
            assert _until(lambda: sorted(d.membership.alive()) == ["ghost", "real"])
            signer = Signer.generate()
            hb = Heartbeat(
                **Sender("new", 7, key=KEY, signer=signer).header(),
                kind="robot",
                frame_id="new.odom",
                identity=signer.public,
            )
            d.membership.heard("new", hb)
            table = {m.agent for m in d.membership.table()}
            assert table == {"real", "ghost"}, table  # "new" not recorded: no room after all
            assert len([m for m in d.membership.table() if m.heard]) <= 2
            d.feed("hb", "real", _heartbeat("real", real, seq=2))  # still a member: accepted
            assert d.metrics.rejected["too-many-members"] == 0
            assert d.receiver.accepted["heartbeat"] == 3
            for token in tokens:
                token.undeclare()
        finally:
            d.close()


def _block_delta(x0: int, to_version: int) -> Delta:
    """51,200 voxels filling 800 4x4x4 blocks (a box 40 x 40 x 32 from x = `x0`), occupied."""
    g = np.stack(np.meshgrid(np.arange(40), np.arange(40), np.arange(32), indexing="ij"), -1)
    keys = g.reshape(-1, 3) + np.array([x0, 0, 0])
    n = len(keys)
    return Delta(0.1, to_version - 1, to_version, keys, np.full(n, 1.0, np.float32), np.ones(n))


def _parts(sender: Sender, delta: Delta, indices: list[int], parts: int) -> list[bytes]:
    return [
        sender.encode(
            VoxelDelta(**sender.header(), frame_id="evil.odom", part=i, parts=parts, delta=delta)
        )
        for i in indices
    ]


def _introduce(d: SimpleNamespace, origin: str = "evil") -> tuple[Signer, Sender]:
    """A peer `origin` with a fresh key, introduced to `d` by its heartbeat, and its sender
    (epoch 7, frames from seq 10)."""
    signer = Signer.generate()
    d.feed("hb", origin, _heartbeat(origin, signer))
    return signer, Sender(origin, 7, key=KEY, signer=signer, first_seq=10)


def _first_delta(d: SimpleNamespace, sender: Sender) -> Layer | None:
    """`sender`'s first delta (version 1, one voxel) fed to `d`: the replica of its layer."""
    d.feed("delta", sender.origin, _one_part(sender, Delta(0.1, 0, 1, [[0, 0, 0]], [1.0], [1.7e9])))
    return d.layers.find(sender.origin)


def _one_part(sender: Sender, delta: Delta) -> bytes:
    """`delta` as one frame of `sender` (a split delta of one part)."""
    return _parts(sender, delta, [0], 1)[0]


def _state(layer: Layer) -> tuple[int, int, str]:
    """What a refused delta must leave as it was: the replica's seq, blocks and digest."""
    return layer.seq, layer.blocks(), layer.digest()


def test_parts_of_split_deltas_hold_no_more_voxels_than_the_peer_budget() -> None:
    """A peer (a key holder, or anyone in an open colony) sends parts of a delta of 1000 parts,
    each part within the peer budget (1000 blocks: 64,000 voxels) but never the last: a few KB
    of zstd each, they must not pile up decoded (each part of a real attack: 4 million voxels,
    ~150 MB). Parts beyond what a whole delta may hold are refused before they are accepted,
    and parts of many deltas are dropped oldest first."""
    with _sessions(1) as (mine,):
        d = _daemon(mine)
        try:
            _, sender = _introduce(d)
            budget = d.layers.max_peer_blocks * BLOCK_VOXELS
            for i, frame in enumerate(_parts(sender, _block_delta(0, 1), list(range(10)), 1000)):
                d.feed("delta", "evil", frame)
                held = sum(len(x) for p in d.inbox.parts._open.values() for x in p.got.values())
                assert held <= budget, f"{held} voxels held after part {i}"
                assert d.inbox.parts.voxels == held  # its running count, kept as parts come
            assert d.metrics.rejected["over-budget"] == 9
            assert d.receiver.accepted["delta"] == 1  # the refused parts moved no window
            d.receiver.replay.peek("evil", 7, 11)
            for v in range(2, 12):  # parts of ten deltas: the oldest make room
                d.feed("delta", "evil", _parts(sender, _block_delta(0, v), [0], 2)[0])
                held = sum(len(x) for p in d.inbox.parts._open.values() for x in p.got.values())
                assert held <= budget, f"{held} voxels held after delta {v}"
                assert d.inbox.parts.voxels == held  # its running count, kept as parts come
            assert d.layers.find("evil") is None  # nothing applied
        finally:
            d.close()


def test_a_part_of_another_count_is_refused_before_it_moves_the_window() -> None:
    """Part 1 of 5 of a delta whose part 0 said 3 parts: refused (`bad-parts`) with no side
    effect: the sender's replay window stays where its last accepted frame left it."""
    with _sessions(1) as (mine,):
        d = _daemon(mine)
        try:
            _, sender = _introduce(d)
            small = Delta(0.1, 0, 1, [[0, 0, 0], [1, 0, 0]], [1.0, 1.0], [1.0, 1.0])
            d.feed("delta", "evil", _parts(sender, small, [0], 3)[0])  # seq 10
            d.feed("delta", "evil", _parts(sender, small, [1], 5)[0])  # seq 11: refused
            assert d.metrics.rejected["bad-parts"] == 1
            assert d.receiver.accepted["delta"] == 1
            d.receiver.replay.peek("evil", 7, 11)  # still fresh: the window did not move
        finally:
            d.close()


def _serve(session: zenoh.Session, signer: Signer, frames: Callable[[int, Sender], list[bytes]]):
    """A hostile holder "evil": its snapshot queryable for its own layer answers every request
    with `frames(request_id, sender)`."""
    sender = Sender("evil", 7, key=KEY, signer=signer, first_seq=100)

    def answer(query: zenoh.Query) -> None:
        request = decode(query.payload.to_bytes(), key=KEY)
        for frame in frames(request.request_id, sender):
            query.reply(query.key_expr, frame)
        query.drop()

    return session.declare_queryable(query_key(NS, "evil", "snapshot", "evil"), answer)


def _answers(session: zenoh.Session) -> bool:
    """True once "evil"'s snapshot queryable answers `session` (its answer taken by nobody)."""
    probe = Sender("probe", 1, key=KEY)
    request = SnapshotRequest(**probe.header(), layer="evil", request_id=1)
    key = query_key(NS, "evil", "snapshot", "evil")
    replies = session.get(key, payload=probe.encode(request), timeout=1.0)
    return any(r.ok is not None for r in replies)


def _snapshot_reply(sender: Sender, rid: int, delta: Delta, part: int, parts: int) -> bytes:
    return sender.encode(
        SnapshotReply(
            **sender.header(),
            layer="evil",
            request_id=rid,
            frame_id="evil.odom",
            layer_epoch=7,
            part=part,
            parts=parts,
            delta=delta,
        )
    )


def _ask(d: SimpleNamespace, session: zenoh.Session, part_bytes: int) -> list:
    me = Sender("me", 1, key=KEY)
    catchup = CatchUp(session, NS, d.replicas, me, d.receiver, d.metrics, part_bytes=part_bytes)
    request = SnapshotRequest(
        **me.header(), layer="evil", request_id=5, max_part_bytes=catchup.part_bytes
    )
    return catchup.ask("evil", "snapshot", "evil", request, SnapshotReply, timeout_s=5.0)


def test_reply_frames_larger_than_the_request_allows_are_refused() -> None:
    """The protocol: every reply frame is at most the request's `max_part_bytes`. A holder that
    sends larger ones is refused, before its frame is decoded."""
    with _sessions(2) as (mine, evil):
        d = _daemon(mine)
        signer = Signer.generate()
        d.feed("hb", "evil", _heartbeat("evil", signer))
        rng = np.random.default_rng(1)
        keys = rng.integers(-1000, 1000, (3000, 3))
        keys = np.unique(keys, axis=0)
        n = len(keys)
        big = Delta(0.1, 0, 1, keys, rng.uniform(-2, 3, n).astype(np.float32), rng.uniform(0, 9, n))
        q = _serve(evil, signer, lambda rid, s: [_snapshot_reply(s, rid, big, 0, 1)])
        try:
            assert _until(lambda: _answers(mine))
            assert len(_snapshot_reply(Sender("evil", 7), 5, big, 0, 1)) > 4096
            replies = _ask(d, mine, part_bytes=4096)
            assert replies == []
            assert d.metrics.rejected["oversized"] == 1
            assert d.receiver.accepted["snapshot_reply"] == 0
        finally:
            q.undeclare()
            d.close()


def test_snapshot_replies_hold_no_more_voxels_than_the_peer_budget() -> None:
    """A hostile holder answers a snapshot request with 10 parts of 51,200 voxels each (a few KB
    of zstd each; a real attack: 4096 parts of 4 million voxels), more than the peer budget
    (64,000 voxels) could ever admit: the requester stops taking them once past the budget,
    and decodes none after."""
    with _sessions(2) as (mine, evil):
        d = _daemon(mine)
        signer = Signer.generate()
        d.feed("hb", "evil", _heartbeat("evil", signer))
        parts = [_block_delta(64 * i, 1) for i in range(10)]
        parts = [Delta(0.1, 0, 1, p.keys, p.logodds, p.last_time) for p in parts]
        q = _serve(
            evil,
            signer,
            lambda rid, s: [_snapshot_reply(s, rid, p, i, 10) for i, p in enumerate(parts)],
        )
        try:
            assert _until(lambda: _answers(mine))
            replies = _ask(d, mine, part_bytes=4 << 20)
            held = sum(len(r.delta) for r in replies)
            assert held <= d.layers.max_peer_blocks * BLOCK_VOXELS, held
            assert d.metrics.rejected["over-budget"] == 9
            assert len(replies) == 1
            assert d.receiver.accepted["snapshot_reply"] == 0  # the caller takes them, if whole
        finally:
            q.undeclare()
            d.close()


def test_signed_frames_replayed_in_an_open_colony_are_refused() -> None:
    """An open colony (no key; the default) with identities on first use (the default): a
    stranger cannot sign as a pinned agent, but must not replay its old signed frames either: an
    old alignment offer replayed after its withdrawal would bring back an alignment its origin
    took back, an old object list the list that replaced it."""
    with _sessions(1) as (mine,):
        d = _daemon(mine, key=None)
        try:
            signer = Signer.generate()
            d.feed("hb", "a", _heartbeat("a", signer, key=None))
            a = Sender("a", 7, signer=signer, first_seq=2)

            def offer(confidence: float) -> bytes:
                return a.encode(
                    AlignOffer(
                        **a.header(),
                        target="b",
                        source_frame="a.odom",
                        target_frame="b.odom",
                        position=(1.0, 2.0, 0.0),
                        covariance=list(np.eye(6).ravel() * 1e-4),
                        confidence=confidence,
                    )
                )

            def objects(n: int) -> bytes:
                listed = [
                    ObjectCentroid(
                        object_id=i, class_id=3, position=(i, 0.0, 0.0), voxel_count=9, time=1.0
                    )
                    for i in range(n)
                ]
                return a.encode(Objects(**a.header(), frame_id="a.odom", objects=listed))

            old_offer, withdrawal, old_list, new_list = (
                offer(0.9),
                offer(0.0),
                objects(2),
                objects(0),
            )
            for frame, kind in ((old_offer, "align"), (withdrawal, "align")):
                d.feed(kind, "a", frame)
            assert d.alignments.edges() == []  # withdrawn
            d.feed("objects", "a", old_list)
            d.feed("objects", "a", new_list)
            assert d.peer_objects.get("a") == []
            d.feed("align", "a", old_offer)  # the stranger replays what it recorded
            d.feed("objects", "a", old_list)
            assert d.alignments.edges() == []
            assert d.peer_objects.get("a") == []
            assert d.metrics.rejected["replay"] == 2
        finally:
            d.close()


def test_deltas_a_replica_cannot_store_are_refused_before_they_change_it() -> None:
    """Valid on the wire, but not storable: a layer version of 2^32 or more (the grid keeps 32-bit
    versions; it used to allocate the delta's blocks, then fail) and a voxel without a time (the
    NaN time code; it used to write the log-odds, then fail on the time). Both are refused at
    admission: the replica is as it was, no block allocated, no window moved, and the layer
    takes its next real delta."""
    with _sessions(1) as (mine,):
        d = _daemon(mine)
        try:
            _, sender = _introduce(d)

            layer = _first_delta(d, sender)
            before = _state(layer)
            far = Delta(0.1, 1, 1 << 32, [[400, 400, 400]], [1.0], [1.7e9])
            untimed = Delta(0.1, 1, 2, [[0, 0, 0], [8, 0, 0]], [2.0, 1.0], [np.nan, 1.7e9])
            future = Delta(0.1, 1, 2, [[0, 0, 0]], [2.0], [1e13])
            for bad in (far, untimed, future):
                d.feed("delta", "evil", _one_part(sender, bad))
            assert _state(layer) == before
            assert d.metrics.rejected["bad-header"] == 1
            assert d.metrics.rejected["bad-time"] == 2
            assert d.metrics.rejected["internal"] == 0
            assert d.receiver.accepted["delta"] == 1
            d.feed(
                "delta",
                "evil",
                _one_part(sender, Delta(0.1, 1, 2, [[0, 0, 0]], [2.0], [1.7e9 + 1])),
            )
            assert layer.seq == 2 and d.receiver.accepted["delta"] == 2
        finally:
            d.close()


def test_channels_a_replica_cannot_hold_are_refused_before_they_change_it() -> None:
    """Channels valid on the wire that a replica's grid cannot take: class lists of another
    width than its (3; it used to write the log-odds, then fail on the channel, leaving the
    replica half-applied and the delta failing again on every repair), and scalar channels of
    ever new names (each one an array as large as the layer: a few bytes of wire each, they
    were a memory bomb outside the block budget). Refused at admission, replica unchanged."""
    with _sessions(1) as (mine,):
        d = _daemon(mine)
        try:
            _, sender = _introduce(d)

            layer = _first_delta(d, sender)
            before = _state(layer)
            keys, one = [[0, 0, 0], [9, 9, 9]], [1.7e9, 1.7e9]
            wide = {
                "class_ids": np.array([[1, 2, 3, 4, 5]] * 2, np.int16),
                "class_probs": np.full((2, 5), 0.2, np.float32),
            }
            d.feed(
                "delta",
                "evil",
                _one_part(sender, Delta(0.1, 1, 2, keys, [2.0, 1.0], one, channels=wide)),
            )
            assert _state(layer) == before
            assert d.metrics.rejected["bad-channel"] == 1
            for v in range(2, 6):  # 31 new scalar channels a delta, at one voxel
                names = {f"scalar:t{v}_{i}": np.array([1.0], np.float32) for i in range(31)}
                delta = Delta(0.1, v - 1, v, [[0, 0, v]], [1.0], [1.7e9], channels=names)
                d.feed("delta", "evil", _one_part(sender, delta))
            held = [n for n in layer.grid.store.channels if n.startswith("scalar:")]
            assert len(held) <= 32, f"{len(held)} scalar channels held"
            assert d.metrics.rejected["bad-channel"] == 1 + 3
            assert d.metrics.rejected["internal"] == d.metrics.rejected["invalid"] == 0
        finally:
            d.close()


def test_an_absurd_alignment_offer_cannot_break_the_colony_frame() -> None:
    """An AlignOffer is finite by the protocol, yet one with a translation of 1e200 m (or
    variances of 1e300) overflowed the colony frame's error propagation: `colony()` raised on
    every call, and with it the fixes (mapping stopped while one was pending), status, exports
    and ROS outputs. Such an offer is refused (`bad-align`); the frame stays computable."""
    with _sessions(1) as (mine,):
        d = _daemon(mine)
        try:
            cov = list(np.diag([1e-3, 1e-3, 1e-3, 1e-4, 1e-4, 1e-4]).ravel())

            def offer(agent: str, target: str, position: tuple, covariance: list) -> bytes:
                signer = Signer.generate()
                d.feed("hb", agent, _heartbeat(agent, signer))
                s = Sender(agent, 7, key=KEY, signer=signer, first_seq=2)
                msg = AlignOffer(
                    **s.header(),
                    target=target,
                    source_frame=f"{agent}.odom",
                    target_frame=f"{target}.odom",
                    position=position,
                    covariance=covariance,
                    confidence=0.8,
                )
                return s.encode(msg)

            d.feed("align", "a", offer("a", "b", (1.0, 0.0, 0.0), cov))
            d.feed("align", "b", offer("b", "c", (1.0, 0.0, 0.0), cov))
            d.feed("align", "x", offer("x", "a", (1e200, 0.0, 0.0), cov))
            d.feed("align", "y", offer("y", "c", (2.0, 0.0, 0.0), list(np.eye(6).ravel() * 1e300)))
            frame = d.alignments.colony(["a", "b", "c"])
            assert sorted(frame.transforms) == ["a", "b", "c"]
            assert all(np.isfinite(c).all() for c in frame.covariances.values())
            assert d.metrics.rejected["bad-align"] == 2
        finally:
            d.close()


@functools.cache
def _objects_at(x: float) -> tuple[ObjectCentroid, ...]:
    return tuple(
        ObjectCentroid(object_id=i, class_id=3, position=(i, x, 0.0), voxel_count=9, time=1.0)
        for i in range(16_384)
    )


def _max_objects(x: float) -> list[ObjectCentroid]:
    """16,384 objects (the most one list holds) at (i, `x`, 0), validated once per `x` in this
    module (~0.2 CPU-s a list; a frame encodes them again each time, with its own header)."""
    return list(_objects_at(x))


def test_peers_object_lists_are_bounded_together() -> None:
    """Object lists of at most 16,384 objects each, from up to 256 peers: a few hundred KB of
    wire each, ~2 KB of memory an object once decoded (~8 GB for 256 full lists, outside every
    budget). Together they hold at most `MAX_PEER_OBJECTS`: a list past that is kept, the
    longest lists (its own included) cut to a fair share, and a peer may still replace its own
    list (making room)."""
    with _sessions(1) as (mine,):
        d = _daemon(mine)
        try:
            listed = _max_objects(0.0)
            n = MAX_PEER_OBJECTS // len(listed) + 1
            senders = []
            for k in range(n):
                signer = Signer.generate()
                d.feed("hb", f"p{k}", _heartbeat(f"p{k}", signer))
                senders.append(Sender(f"p{k}", 7, key=KEY, signer=signer, first_seq=2))

            def send(k: int, objects: list) -> None:
                s = senders[k]
                msg = Objects(**s.header(), frame_id=f"p{k}.odom", objects=objects)
                d.feed("objects", f"p{k}", s.encode(msg))

            for k in range(n):
                send(k, listed)
            held = sum(len(d.peer_objects.get(o)) for o in d.peer_objects.origins())
            assert held <= MAX_PEER_OBJECTS, held
            assert d.metrics.rejected["over-budget"] == 0
            assert d.receiver.accepted["objects"] == n
            share = MAX_PEER_OBJECTS // n
            assert {len(d.peer_objects.get(f"p{k}")) for k in range(n)} == {share}
            send(0, listed[:10])  # p0 replaces its list by a shorter one: room for the others'
            send(n - 1, listed)
            assert len(d.peer_objects.get(f"p{n - 1}")) == len(listed)  # 10 + 3 shares + it fit
        finally:
            d.close()


def test_pushed_history_pages_of_ever_new_agents_keep_the_agent_table_bounded() -> None:
    """History pages each naming 4096 new agents (the most a page's table holds) for one record
    each: the replica's history table grew without end, and once past 65,536 names (records
    code agents in 16 bits) every further page failed (an internal error, its names appended all
    the same). Now a page that would take the table past `MAX_AGENTS` is refused whole."""
    from colonyd.historysync import HistorySync

    with _sessions(1) as (mine,):
        d = _daemon(mine)
        try:
            _, sender = _introduce(d)
            layer = _first_delta(d, sender)
            sync = HistorySync(
                d.layers, SimpleNamespace(), d.metrics, period_s=0, stop=threading.Event()
            )
            d.inbox._admit_history = lambda msg: sync.admit(
                layer, msg.layer_epoch, msg.from_version, msg.records
            )  # as the daemon checks a pushed page (`Gossip._admit_history`)
            d.inbox._on_history = lambda msg: sync.offer(
                layer, msg.layer_epoch, msg.from_version, msg.records
            )  # as the daemon takes a pushed page (`Gossip._take_history`)
            for p in range(18):
                rec = np.zeros(4096, RECORD_DTYPE)
                rec["key"] = vk.pack(np.stack([np.arange(4096), np.zeros(4096), np.zeros(4096)], 1))
                rec["agent"] = np.arange(4096)
                rec["version"] = p + 1
                rec["reliability"] = 1.0
                page = HistoryPage(rec, [f"g{p}_{i}" for i in range(4096)])
                reply = HistoryReply(**sender.header(), layer="evil", request_id=0, layer_epoch=7,
                                     from_version=0, to_version=p + 1, records=page)  # fmt: skip
                d.feed("history", "evil", sender.encode(reply))
            assert len(layer.grid.history.agents) <= MAX_AGENTS == 4096
            assert d.metrics.rejected["internal"] == 0
            assert d.metrics.rejected["bad-history"] == 17
            # refused before accepted: the 17 refused frames (seq 12 to 28) moved no window
            assert d.receiver.accepted["history_reply"] == 1
            for seq in range(12, 29):
                d.receiver.replay.peek("evil", 7, seq)
        finally:
            d.close()


def test_a_pulled_history_page_of_too_many_agents_is_a_counted_refusal() -> None:
    """A holder answers history pulls with a page that would take the replica's agent table past
    `MAX_AGENTS`: refused and counted (`bad-history`) like a pushed one. The pull raised, and the
    history thread logged the error with its stack every round, counted nowhere."""
    from colonyd.historysync import HistorySync

    with _sessions(2) as (mine, evil):
        d = _daemon(mine)
        _, sender = _introduce(d)
        layer = _first_delta(d, sender)
        with layer.lock:
            for i in range(MAX_AGENTS):
                layer.grid.history.agent_code(f"g{i}")  # the table full already

        def answer(query: zenoh.Query) -> None:
            request = decode(query.payload.to_bytes(), key=KEY)
            rec = np.zeros(1, RECORD_DTYPE)
            rec["version"] = 1
            reply = HistoryReply(**sender.header(), layer="evil", request_id=request.request_id,
                                 layer_epoch=7, from_version=request.from_version, to_version=1,
                                 records=HistoryPage(rec, ["one-more"]))  # fmt: skip
            query.reply(query.key_expr, sender.encode(reply))
            query.drop()

        queryable = evil.declare_queryable(query_key(NS, "evil", "history", "evil"), answer)
        try:
            me = Sender("me", 1, key=KEY)
            catchup = CatchUp(mine, NS, d.replicas, me, d.receiver, d.metrics)
            sync = HistorySync(d.layers, catchup, d.metrics, period_s=0, stop=threading.Event())
            assert _until(lambda: sync.pull(layer) == 0 and d.metrics.rejected["bad-history"] > 0)
            assert "one-more" not in layer.grid.history.agents
            assert d.metrics.rejected["internal"] == 0
        finally:
            queryable.undeclare()
            d.close()


def test_a_flood_of_refused_frames_does_not_flood_the_log(caplog) -> None:
    """A stranger without the colony key puts junk on a delta key as fast as it can: every frame
    is refused and counted, but the log gets a few lines per reason, not one per frame (it was
    one warning a frame: a disk filled by anyone who reaches the network)."""
    import logging

    with _sessions(1) as (mine,):
        d = _daemon(mine)
        try:
            stranger = Sender("x", 1)  # no key
            unkeyed = stranger.encode(Heartbeat(**stranger.header(), kind="r", frame_id="x.odom"))
            with caplog.at_level(logging.WARNING):
                for _ in range(300):
                    d.feed("delta", "x", unkeyed)
                    d.feed("delta", "x", b"CLNY")
            assert d.metrics.rejected["auth"] == 300
            assert d.metrics.rejected["truncated"] == 300
            lines = [r for r in caplog.records if r.levelno >= logging.WARNING]
            assert len(lines) <= 6, f"{len(lines)} lines, the first: {lines[0].getMessage()}"
        finally:
            d.close()


def _catchup(d: SimpleNamespace, session: zenoh.Session) -> CatchUp:
    return CatchUp(session, NS, d.replicas, Sender("me", 1, key=KEY), d.receiver, d.metrics)


def test_snapshot_replies_refused_as_a_whole_move_no_window() -> None:
    """A holder answers snapshot requests with replies each valid alone but refused as a whole:
    two of three parts (incomplete), a snapshot not from version 0, and one past the peer budget
    (refused at admission). Nothing is installed and no reply frame is accepted: the holder's
    replay window stays where its heartbeat left it (it moved for each reply, then the reply
    was refused)."""
    small = Delta(0.1, 0, 3, [[0, 0, 0], [1, 0, 0]], [1.0, 1.0], [1.7e9, 1.7e9])
    late = Delta(0.1, 2, 3, [[0, 0, 0]], [1.0], [1.7e9])
    big = [Delta(0.1, 0, 3, p.keys, p.logodds, p.last_time)
           for p in (_block_delta(0, 1), _block_delta(64, 1))]  # fmt: skip
    answers = [
        lambda rid, s: [_snapshot_reply(s, rid, small, i, 3) for i in (0, 1)],
        lambda rid, s: [_snapshot_reply(s, rid, late, 0, 1)],
        lambda rid, s: [_snapshot_reply(s, rid, b, i, 2) for i, b in enumerate(big)],
    ]
    with _sessions(2) as (mine, evil):
        d = _daemon(mine)
        signer = Signer.generate()
        d.feed("hb", "evil", _heartbeat("evil", signer))
        current: list = [answers[0]]
        q = _serve(evil, signer, lambda rid, s: current[0](rid, s))  # noqa: PLW0108 - late
        try:
            assert _until(lambda: _answers(mine))
            catchup = _catchup(d, mine)
            for answer in answers:
                current[0] = answer
                assert not catchup._fetch_snapshot("evil", "evil", time.monotonic())
            assert d.layers.find("evil") is None
            assert d.metrics.rejected["bad-snapshot"] == 1
            assert d.metrics.rejected["over-budget"] == 1
            assert d.receiver.accepted["snapshot_reply"] == 0
            assert "evil" in d.receiver.replay._state  # its heartbeat's
            for seq in range(100, 110):  # every reply frame the holder sent is still fresh
                d.receiver.replay.peek("evil", 7, seq)
            current[0] = lambda rid, s: [_snapshot_reply(s, rid, small, 0, 1)]
            assert catchup._fetch_snapshot("evil", "evil", time.monotonic())
            assert d.receiver.accepted["snapshot_reply"] == 1
        finally:
            q.undeclare()
            d.close()


def test_positions_beyond_the_earth_are_refused() -> None:
    """Finite on the wire, meaningless for a robot: a Pose at 1e300 m (it went into the peer's
    drift path: a walk of 1e300 m per metre), a PoseFix, a heartbeat's position and an object at
    1e12 m, an object covariance of 1e300. Each is refused (past `MAX_POSITION_M`, the
    AlignOffer bound) before it is accepted; a position of 1e7 m (projected site coordinates)
    passes."""
    with _sessions(2) as (mine, other):
        d = _daemon(mine)
        token = other.liveliness().declare_token(alive_key(NS, "a"))
        try:
            assert _until(lambda: d.membership.alive() == ["a"])
            signer = Signer.generate()
            d.feed("hb", "a", _heartbeat("a", signer))
            a = Sender("a", 7, key=KEY, signer=signer, first_seq=2)
            cov = list(np.diag([0.01, 0.01, 0.01, 0.001, 0.001, 0.001]).ravel())

            def pose(x: float) -> bytes:
                msg = Pose(**a.header(), frame_id="a.odom", position=(x, 0, 0), covariance=cov)
                return a.encode(msg)

            def fix(x: float) -> bytes:
                msg = PoseFix(**a.header(), target="me", frame_id="a.odom", stamp=1.7e9,
                              position=(x, 0, 0), covariance=cov)  # fmt: skip
                return a.encode(msg)

            def objects(x: float, c: float = 0.0) -> bytes:
                listed = [ObjectCentroid(object_id=1, class_id=3, position=(0, x, 0),
                                         covariance=[c] * 9, voxel_count=9, time=1.0)]  # fmt: skip
                return a.encode(Objects(**a.header(), frame_id="a.odom", objects=listed))

            def heartbeat(x: float) -> bytes:
                hb = Heartbeat(**a.header(), kind="robot", frame_id="a.odom", position=(0, 0, x))
                return a.encode(hb)

            for x in (0.0, 1.0, 2.0):
                d.feed("pose", "a", pose(x))
            walk_before = d.membership.pose_drifts().get("a")
            bad = {
                "pose": pose(1e300),
                "fix": fix(1e12),
                "objects": objects(1e12),
                "hb": heartbeat(-1e300),
            }
            for kind, frame in bad.items():
                d.feed(kind, "a", frame)
            d.feed("objects", "a", objects(1.0, 1e300))
            for reason in ("bad-pose", "bad-fix", "bad-heartbeat"):
                assert d.metrics.rejected[reason] == 1, reason
            assert d.metrics.rejected["bad-objects"] == 2
            assert d.receiver.accepted["pose"] == 3
            assert d.receiver.accepted["objects"] == d.receiver.accepted["fix"] == 0
            assert d.receiver.accepted["heartbeat"] == 1
            assert d.membership.find("a").pose == [2.0, 0.0, 0.0]
            walk = d.membership.pose_drifts().get("a")
            assert (walk is None) == (walk_before is None)
            assert d.peer_objects.get("a") == []
            d.feed("pose", "a", pose(1e7))
            d.feed("objects", "a", objects(-1e7, 1e3))
            assert d.membership.find("a").pose == [1e7, 0.0, 0.0]
            assert len(d.peer_objects.get("a")) == 1
        finally:
            token.undeclare()
            d.close()


def test_a_member_that_never_answers_cannot_stall_repairs() -> None:
    """Member "evil" lists 40 made-up layers in its heartbeat and claims a version of "b"'s
    layer far beyond b's, while its queryables never answer. Each repair waited the query
    timeout on it (then its doubling), one repair at a time: b's real layer waited behind
    them all. Now a holder that gave nothing usable rests as long as its query took: b's layer
    is caught up from b after one query to evil, and evil's claim brings no snapshot again."""
    with _sessions(2) as (mine, other):
        d = _daemon(mine)
        held: list = []
        asked = {"evil": 0, "b": 0}
        b_signer, evil_signer = Signer.generate(), Signer.generate()
        b = Sender("b", 7, key=KEY, signer=b_signer, first_seq=100)
        layer = Delta(0.1, 0, 3, [[0, 0, 0], [1, 0, 0]], [1.0, 1.0], [1.7e9, 1.7e9])

        def silent(query: zenoh.Query) -> None:
            asked["evil"] += 1
            held.append(query)  # never answered, never dropped: the requester waits it out

        def serve_b(query: zenoh.Query) -> None:
            asked["b"] += 1
            request = decode(query.payload.to_bytes(), key=KEY)
            if isinstance(request, SnapshotRequest):
                reply = SnapshotReply(**b.header(), layer="b", request_id=request.request_id,
                                      frame_id="b.odom", layer_epoch=7, delta=layer)  # fmt: skip
            else:
                reply = DeltaRangeReply(**b.header(), layer="b", request_id=request.request_id,
                                        frame_id="b.odom", layer_epoch=7)  # fmt: skip
            query.reply(query.key_expr, b.encode(reply))
            query.drop()

        def heartbeat(agent: str, signer: Signer, seq: int, layers: dict) -> bytes:
            s = Sender(agent, 7, key=KEY, signer=signer, first_seq=seq)
            listed = [LayerVersion(origin=o, epoch=e, version=v) for o, (e, v) in layers.items()]
            hb = Heartbeat(**s.header(), kind="robot", frame_id=f"{agent}.odom",
                           identity=signer.public, layers=listed)  # fmt: skip
            return s.encode(hb)

        tokens = [other.liveliness().declare_token(alive_key(NS, a)) for a in ("evil", "b")]
        queryables = [
            other.declare_queryable(f"colony/{NS}/evil/**", silent),
            other.declare_queryable(f"colony/{NS}/b/**", serve_b),
        ]
        me = Sender("me", 1, key=KEY)
        catchup = CatchUp(mine, NS, d.replicas, me, d.receiver, d.metrics, query_timeout_s=0.5)
        try:
            assert _until(lambda: sorted(d.membership.alive()) == ["b", "evil"])
            d.inbox._request_repair = catchup.request
            catchup.start(d.membership)
            made_up = {f"f{i}": (1, 5) for i in range(40)}
            d.feed("hb", "evil", heartbeat("evil", evil_signer, 1, {**made_up, "b": (7, 10**6)}))
            d.feed("hb", "b", heartbeat("b", b_signer, 1, {"b": (7, 3)}))
            ok = _until(lambda: (r := d.layers.find("b")) is not None and r.seq == 3, 8.0)
            assert ok, (asked, d.metrics.counts)
            assert asked["evil"] <= 2, asked
            assert d.metrics.counts["snapshots_installed"] == 1
            for seq in range(2, 5):  # evil's claim again: b says it holds nothing newer
                d.feed("hb", "evil", heartbeat("evil", evil_signer, seq, {"b": (7, 10**6)}))
                assert _until(catchup.idle)
            assert d.metrics.counts["snapshots_installed"] == 1
        finally:
            catchup.close()
            for q in queryables:
                q.undeclare()
            for t in tokens:
                t.undeclare()
            held.clear()
            d.close()


def _full_list(sender: Sender, x: float = 0.0) -> bytes:
    frame_id = f"{sender.origin}.odom"
    return sender.encode(Objects(**sender.header(), frame_id=frame_id, objects=_max_objects(x)))


def test_full_object_lists_back_to_back_cannot_hold_the_inbox() -> None:
    """A member sends object lists of 16,384 objects (the protocol's most; ~0.4 s of decoding
    each on the inbox's one thread) back to back: every one was decoded, and the inbox served
    nothing else. Past its allowance (`OBJECTS_BURST` at once, `OBJECTS_PER_S` a second; a list
    refused once parsed is charged too: it cost as much) its lists are refused before their
    body is parsed (`too-often`, not `bad-objects`), until it has earned some back; another
    member's list passes meanwhile."""
    from colonyd.objects import OBJECTS_BURST, OBJECTS_PER_S

    with _sessions(1) as (mine,):
        d = _daemon(mine)
        now = [1000.0]
        d.peer_objects._clock = lambda: now[0]
        try:
            senders = {}
            for agent in ("p", "q"):
                signer = Signer.generate()
                d.feed("hb", agent, _heartbeat(agent, signer))
                senders[agent] = Sender(agent, 7, key=KEY, signer=signer, first_seq=2)
            p = senders["p"]
            d.feed("objects", "p", _full_list(p, 1e12))  # parsed, refused: its cost charged
            for _ in range(3):
                d.feed("objects", "p", _full_list(p, 1e12))
            assert d.metrics.rejected["bad-objects"] == 1
            assert d.metrics.rejected["too-often"] == 3
            assert d.receiver.accepted["objects"] == 0
            d.feed("objects", "q", _full_list(senders["q"]))
            assert d.receiver.accepted["objects"] == 1
            now[0] += OBJECTS_BURST / OBJECTS_PER_S / 2  # half a list's worth earned back
            d.feed("objects", "p", _full_list(p, 1.0))
            assert d.receiver.accepted["objects"] == 2
            assert d.peer_objects.get("p")[0].position == (0.0, 1.0, 0.0)
        finally:
            d.close()


def test_a_strangers_frame_is_refused_before_its_body_is_parsed() -> None:
    """An open colony trusting identities on first use: a stranger's frame under an origin not
    introduced (or a pinned one's, without its key) was decompressed and parsed whole (up to
    ~0.5 s for the largest bodies) before its signature was checked. The signature is now
    checked first: a frame whose body is garbage is refused for its identity, not its body."""
    receiver = Receiver(own="me", trust=Trust("tofu"))
    stranger = Sender("zz", 7, signer=Signer.generate(), first_seq=2)
    raw = bytearray(_full_list(stranger))
    body = raw.find(b"zz") + 40  # inside the body (the envelope: origin, epoch, seq, time)
    raw[body : body + 64] = bytes(64)
    try:
        receiver.decode(bytes(raw))
        raise AssertionError("a stranger's frame was accepted")
    except ProtocolError as exc:
        assert exc.reason == "unknown_identity", exc


def test_range_replies_refused_at_admission_move_no_window() -> None:
    """A holder answers a range request with two deltas: the first fine, the second with a
    voxel time no replica can keep (refused at admission, `bad-time`). The range is refused as
    a whole before any of it is applied or accepted: the layer is as it was and every reply
    frame of the holder is still fresh (each moved its window, then the second was refused
    after the first was applied)."""
    with _sessions(2) as (mine, evil):
        d = _daemon(mine)
        signer, sender = _introduce(d)
        _first_delta(d, sender)
        replier = Sender("evil", 7, key=KEY, signer=signer, first_seq=100)
        good = Delta(0.1, 1, 2, [[1, 0, 0]], [1.0], [1.7e9])
        bad = Delta(0.1, 2, 3, [[2, 0, 0]], [1.0], [1e13])

        def answer(query: zenoh.Query) -> None:
            request = decode(query.payload.to_bytes(), key=KEY)
            for i, delta in enumerate((good, bad)):
                reply = DeltaRangeReply(**replier.header(), layer="evil",
                                        request_id=request.request_id, frame_id="evil.odom",
                                        layer_epoch=7, part=i, parts=2, delta=delta)  # fmt: skip
                query.reply(query.key_expr, replier.encode(reply))
            query.drop()

        q = evil.declare_queryable(query_key(NS, "evil", "deltas", "evil"), answer)
        try:
            catchup = _catchup(d, mine)
            layer = d.layers.find("evil")
            assert _until(lambda: catchup._fetch_range("evil", "evil", layer, 3) == "failed"
                          and d.metrics.rejected["bad-time"] >= 1)  # fmt: skip
            assert layer.seq == 1
            assert d.receiver.accepted["delta_range_reply"] == 0
            for seq in range(100, 102):
                d.receiver.replay.peek("evil", 7, seq)
        finally:
            q.undeclare()
            d.close()


def test_replies_behind_the_window_when_taken_are_still_taken() -> None:
    """Replies are recorded only once their query passed as a whole; meanwhile their holder may
    have sent more than the replay window's frames (deltas, other requesters' replies) and the
    inbox accepted them: the replies, answers to a fresh random request id, are taken without
    being recorded rather than refused as replays (a busy holder's snapshots would never be
    taken). Any other frame so old is a replay as before."""
    receiver = Receiver(key=KEY, own="me", trust=Trust("tofu"))
    signer = Signer.generate()
    receiver.receive(_heartbeat("evil", signer))
    holder = Sender("evil", 7, key=KEY, signer=signer, first_seq=100)
    small = Delta(0.1, 0, 1, [[0, 0, 0]], [1.0], [1.7e9])
    reply = receiver.decode(_snapshot_reply(holder, 5, small, 0, 1))
    later = Sender("evil", 7, key=KEY, signer=signer, first_seq=100 + 5000)
    receiver.receive(_parts(later, small, [0], 1)[0])  # the holder's delta, 5000 frames on
    receiver.accept(reply, answer=True)
    assert receiver.accepted["snapshot_reply"] == 1
    try:
        receiver.accept(reply)
        raise AssertionError("a frame older than the window was accepted")
    except ProtocolError as exc:
        assert exc.reason == "replay"


def test_replies_behind_the_window_when_they_arrive_are_still_taken() -> None:
    """A holder encodes a snapshot's parts up front, then sends them; its deltas and heartbeats
    (and other requesters' replies) go on meanwhile, and the inbox accepts them. Parts that are
    more than the replay window behind its newest frame when they are decoded are answers to our
    fresh random request id all the same: `ask` takes them (as `take` does), rather than
    refusing every part of a busy holder's snapshot as a replay."""
    small = Delta(0.1, 0, 3, [[0, 0, 0], [1, 0, 0]], [1.0, 1.0], [1.7e9, 1.7e9])
    with _sessions(2) as (mine, evil):
        d = _daemon(mine)
        signer = Signer.generate()
        d.feed("hb", "evil", _heartbeat("evil", signer, seq=100 + 5000))  # 5000 frames on
        assert d.receiver.accepted["heartbeat"] == 1
        q = _serve(evil, signer, lambda rid, s: [_snapshot_reply(s, rid, small, 0, 1)])
        try:
            assert _until(lambda: _answers(mine))
            catchup = _catchup(d, mine)
            assert catchup._fetch_snapshot("evil", "evil", time.monotonic())
            assert d.receiver.accepted["snapshot_reply"] == 1
            assert d.metrics.rejected["replay"] == 0
            try:  # any other frame so old is a replay as before
                d.receiver.decode(
                    _snapshot_reply(
                        Sender("evil", 7, key=KEY, signer=signer, first_seq=100), 5, small, 0, 1
                    )
                )
                raise AssertionError("a frame older than the window was decoded")
            except ProtocolError as exc:
                assert exc.reason == "replay"
        finally:
            q.undeclare()
            d.close()


def test_a_range_reply_that_came_in_part_goes_on_to_the_snapshot() -> None:
    """A slow holder's range reply came in part only (its last part not there within the query
    timeout: a range of up to `ring_size` large deltas over a slow link). That is no hostile
    silence: the repair goes on to the holder's snapshot (whose timeout doubles), as it did
    before holders were rested, rather than resting the holder and asking the same range again
    at the next repair, never repairing a layer that stopped changing."""
    from colonyd.catchup import Repair

    with _sessions(2) as (mine, evil):
        d = _daemon(mine)
        signer, sender = _introduce(d)
        _first_delta(d, sender)
        replier = Sender("evil", 7, key=KEY, signer=signer, first_seq=100)
        step = Delta(0.1, 1, 2, [[1, 0, 0]], [1.0], [1.7e9])
        whole = Delta(0.1, 0, 3, [[0, 0, 0], [1, 0, 0]], [1.0, 1.0], [1.7e9, 1.7e9])

        def answer(query: zenoh.Query) -> None:
            request = decode(query.payload.to_bytes(), key=KEY)
            if isinstance(request, SnapshotRequest):
                frame = _snapshot_reply(replier, request.request_id, whole, 0, 1)
            else:  # part 0 of 2: part 1 still on its way when the query ends
                reply = DeltaRangeReply(**replier.header(), layer="evil",
                                        request_id=request.request_id, frame_id="evil.odom",
                                        layer_epoch=7, part=0, parts=2, delta=step)  # fmt: skip
                frame = replier.encode(reply)
            query.reply(query.key_expr, frame)
            query.drop()

        q = evil.declare_queryable(f"colony/{NS}/evil/**", answer)
        try:
            assert _until(lambda: _answers(mine))
            catchup = _catchup(d, mine)
            assert d.layers.find("evil").seq == 1
            catchup._repair(Repair("evil", ["evil"], time.monotonic()))
            assert d.layers.find("evil").seq == 3, d.metrics.counts
            assert d.metrics.counts["snapshots_installed"] == 1
        finally:
            q.undeclare()
            d.close()


def test_a_holder_slower_than_the_timeout_to_its_first_part_is_waited_for_longer() -> None:
    """A holder makes and encodes a big layer's whole snapshot before it sends the first part
    (BENCHMARKS: 10 M voxels, "35 of 40 parts encoded" when the requester's 5 s had passed), and
    stops, sending nothing, once the requester's timeout (`timeout_ms`) has passed. Nothing
    comes, as from a silent holder; the next request must wait longer (`snapshot_timeout`), or
    the layer is never caught up: here the holder needs 0.45 s and the base timeout is 0.3 s."""
    whole = Delta(0.1, 0, 3, [[0, 0, 0], [1, 0, 0]], [1.0, 1.0], [1.7e9, 1.7e9])
    with _sessions(2) as (mine, evil):
        d = _daemon(mine)
        signer = Signer.generate()
        d.feed("hb", "evil", _heartbeat("evil", signer))
        replier = Sender("evil", 7, key=KEY, signer=signer, first_seq=100)
        served: list[int] = []

        def answer(query: zenoh.Query) -> None:
            request = decode(query.payload.to_bytes(), key=KEY)
            if request.request_id != 1:  # not `_answers`' probe
                if request.timeout_ms < 450:  # abandoned at the requester's deadline: no reply
                    query.drop()
                    return
                time.sleep(0.45)
                served.append(request.timeout_ms)
            query.reply(query.key_expr, _snapshot_reply(replier, request.request_id, whole, 0, 1))
            query.drop()

        q = evil.declare_queryable(query_key(NS, "evil", "snapshot", "evil"), answer)
        try:
            assert _until(lambda: _answers(mine))
            me = Sender("me", 1, key=KEY)
            catchup = CatchUp(mine, NS, d.replicas, me, d.receiver, d.metrics, query_timeout_s=0.3)
            got = [catchup._fetch_snapshot("evil", "evil", time.monotonic()) for _ in range(3)]
            assert any(got), got
            assert d.layers.find("evil").seq == 3
            assert served and served[0] >= 450
        finally:
            q.undeclare()
            d.close()


def _box(x0: int, blocks_z: int, version: int, origin_seq: int = 0) -> Delta:
    """A box 40 x 40 x (4 `blocks_z`) voxels from x = `x0`: 100 `blocks_z` 4x4x4 blocks,
    covering (`version` - 1, `version`]."""
    g = np.stack(
        np.meshgrid(np.arange(40), np.arange(40), np.arange(4 * blocks_z), indexing="ij"), -1
    )
    keys = g.reshape(-1, 3) + np.array([x0, 0, 0])
    n = len(keys)
    return Delta(0.1, version - 1, version, keys, np.full(n, 1.0, np.float32), np.full(n, 1.7e9))


def test_a_live_delta_between_a_ranges_admission_and_its_offer_rests_no_holder() -> None:
    """`_fetch_range` admitted a holder's range as a whole, took it, then offered its deltas
    one by one, each admitted again: a live delta of another peer applied in between (the inbox
    runs on its own thread) could take the budget the range was admitted for, and the offer
    failed (`over-budget`): the legitimate holder was rested, for every layer, and part of
    its range may have been applied. The interleaving is forced at the one point it can
    happen: the catch-up's receiver (a subclass whose `accept` starts the other peer's real
    delta frame through the real inbox on another thread, and waits up to 0.5 s for it) is
    the only stand-in. Now a range is admitted and applied under the layers' apply lock, which
    the inbox holds from a delta's admission to its offer: the range is taken whole, its
    holder not rested, and the live delta comes after it (refused, `over-budget`, as the
    budget is full: first come, first served, the budget never exceeded)."""
    with _sessions(2) as (mine, evil):
        d = _daemon(mine)  # a peer budget of 1000 blocks
        signer, sender = _introduce(d)
        _first_delta(d, sender)  # evil's layer at version 1: one block
        _, b = _introduce(d, "b")
        replier = Sender("evil", 7, key=KEY, signer=signer, first_seq=100)
        ranged = _box(0, 6, 2)  # 600 blocks: fits the budget alone
        live = _box(1000, 5, 1)  # b's first delta, 500 blocks: fits alone too, not both
        live_frame = _one_part(b, live)

        def answer(query: zenoh.Query) -> None:
            request = decode(query.payload.to_bytes(), key=KEY)
            reply = DeltaRangeReply(**replier.header(), layer="evil",
                                    request_id=request.request_id, frame_id="evil.odom",
                                    layer_epoch=7, delta=ranged)  # fmt: skip
            query.reply(query.key_expr, replier.encode(reply))
            query.drop()

        fed: list[threading.Thread] = []

        class Racing(Receiver):
            def accept(self, msg, *, answer=False) -> None:
                super().accept(msg, answer=answer)
                if answer and not fed:  # between the range's admission and its offer
                    fed.append(threading.Thread(target=d.feed, args=("delta", "b", live_frame)))
                    fed[0].start()
                    fed[0].join(0.5)  # done unless it waits for the range to be applied

        q = evil.declare_queryable(query_key(NS, "evil", "deltas", "evil"), answer)
        try:
            receiver = Racing(key=KEY, own="me", trust=d.trust)
            catchup = CatchUp(mine, NS, d.replicas, Sender("me", 1, key=KEY), receiver, d.metrics)
            layer = d.layers.find("evil")
            assert _until(lambda: _answers_range(mine))
            found = catchup._fetch_range("evil", "evil", layer, 2)
            fed[0].join(5.0)
            assert found == "taken", (found, d.metrics.rejected)
            assert "evil" not in catchup._resting
            assert d.layers.find("evil").seq == 2
            blocks = sum(x.blocks() for x in d.layers.all() if x.origin != "me")
            assert blocks <= d.layers.max_peer_blocks, blocks
            assert d.layers.find("b") is None or d.layers.find("b").seq == 0
            assert d.metrics.rejected["over-budget"] == 1  # b's live delta, after the range
        finally:
            q.undeclare()
            d.close()


def _answers_range(session: zenoh.Session) -> bool:
    """True once "evil"'s range queryable answers `session` (its answer taken by nobody)."""
    from protocol import DeltaRangeRequest

    probe = Sender("probe", 1, key=KEY)
    request = DeltaRangeRequest(**probe.header(), layer="evil", request_id=1, from_version=0,
                                to_version=1)  # fmt: skip
    key = query_key(NS, "evil", "deltas", "evil")
    return any(
        r.ok is not None for r in session.get(key, payload=probe.encode(request), timeout=1.0)
    )


def _objects(count: int, x: float = 0.0) -> list[ObjectCentroid]:
    return [
        ObjectCentroid(object_id=i, class_id=3, position=(i, x, 0.0), voxel_count=9, time=1.0)
        for i in range(count)
    ]


def _listing(d: SimpleNamespace, agents: list[str]) -> Callable[[str, list], None]:
    """Introduce `agents` to `d`; the function that feeds `d` an object list of one of them."""
    senders = {}
    for agent in agents:
        signer = Signer.generate()
        d.feed("hb", agent, _heartbeat(agent, signer))
        senders[agent] = Sender(agent, 7, key=KEY, signer=signer, first_seq=2)

    def send(agent: str, objects: list) -> None:
        s = senders[agent]
        d.feed("objects", agent, s.encode(Objects(**s.header(), frame_id=f"{agent}.odom",
                                                  objects=objects)))  # fmt: skip

    return send


def test_a_member_with_many_changing_objects_keeps_every_list() -> None:
    """A legitimate member with 2000 objects that change at every refresh of `objects_s` = 0.5 s
    (4000 objects a second), beside two members with a few hundred objects every 2 s (the
    default), for 20 s: its allowance was 2048 objects a second whatever the colony, so once
    its first 16,384 were spent, about half of its lists were refused (`too-often`). The
    allowance is now the inbox's objects rate shared among the peers spending theirs: every
    list passes."""
    with _sessions(1) as (mine,):
        d = _daemon(mine)
        now = [1000.0]
        d.peer_objects._clock = lambda: now[0]
        try:
            send = _listing(d, ["busy", "q", "r"])
            busy, few = _objects(2000), _objects(300)
            for step in range(40):  # 0.5 s each
                send("busy", busy)
                if step % 4 == 0:
                    send("q", few)
                    send("r", few)
                now[0] += 0.5
            assert d.metrics.rejected["too-often"] == 0, d.metrics.rejected
            assert d.receiver.accepted["objects"] == 40 + 2 * 10
        finally:
            d.close()


def test_the_peers_objects_bound_is_shared_fairly() -> None:
    """Peers' lists hold at most `max_objects` together; once full, the first peers kept theirs
    and every later peer's list was refused whole (`over-budget`): in a colony of 256 robots
    with more than 256 objects each, the last robots' lists were never kept. Now a list that
    does not fit is kept, and room is made, by trimming the lists above a fair share (the bound
    over the peers holding lists) to it, the new one included, largest first: each peer keeps
    at least its share (its first objects, in its order), nothing is refused for the bound."""
    with _sessions(1) as (mine,):
        d = _daemon(mine)
        d.peer_objects.max_objects = 1000
        try:
            send = _listing(d, [f"p{k}" for k in range(5)])
            for k in range(3):
                send(f"p{k}", _objects(300))
            assert [len(d.peer_objects.get(f"p{k}")) for k in range(3)] == [300] * 3
            send("p3", _objects(300))  # share 250: the four of them at 250
            assert [len(d.peer_objects.get(f"p{k}")) for k in range(4)] == [250] * 4
            send("p4", _objects(100))  # share 200: within it, kept whole; the others at 225
            held = [len(d.peer_objects.get(f"p{k}")) for k in range(5)]
            assert sum(held) <= 1000 and held[4] == 100 and min(held[:4]) >= 200, held
            send("p0", _objects(10))  # a peer that shrinks makes room for the others' next
            send("p1", _objects(300))
            held = [len(d.peer_objects.get(f"p{k}")) for k in range(5)]
            assert sum(held) <= 1000 and held[0] == 10 and held[1] >= 225, held
            assert d.peer_objects.get("p1")[0].object_id == 0  # its first objects kept
            assert d.metrics.rejected["over-budget"] == 0
            assert d.receiver.accepted["objects"] == 7
        finally:
            d.close()


def test_peers_flooding_object_lists_together_get_the_inbox_rate_and_no_more() -> None:
    """Ten peers (a key holder's made-up identities, or ten members) each sending full lists
    every 0.1 s for 20 s: the lists passed hold at most the shared rate's objects over that
    time plus one full list a peer (its first), however many peers share it."""
    now = [0.0]
    objects = PeerObjects(clock=lambda: now[0])
    passed = 0
    for _ in range(200):
        for k in range(10):
            try:
                objects.allow(f"p{k}")
            except WireError:
                continue
            objects.charge(f"p{k}", objects.burst)
            passed += objects.burst
        now[0] += 0.1
    assert passed <= objects.per_s * now[0] + 10 * objects.burst, passed
    assert objects.rate() == objects.per_s / 10


def test_members_without_layers_keep_no_robot_out() -> None:
    """The daemon bounded the members whose heartbeats it keeps by `max_layers`: members that
    hold no layer (CCTV daemons that publish none, command-line clients) filled that table,
    every one alive, and a robot's heartbeats were then refused (`too-many-members`): no repair
    of its layer. Members are now bounded by `max_members` (default 1024) and peer layers by
    `max_layers`, separately: a daemon that holds at most 2 peer layers hears 5 cameras and
    then a robot."""
    from colonyd.config import Config
    from colonyd.daemon import member_table

    with _sessions(2) as (mine, other):
        d = _daemon(mine)
        cfg = Config(agent_id="me", namespace=NS, max_layers=2)
        table = member_table(mine, cfg, lambda agent, event: None)
        d.inbox.membership = table
        agents = [f"cam{i}" for i in range(5)] + ["robot"]
        tokens = [other.liveliness().declare_token(alive_key(NS, a)) for a in agents]
        try:
            assert _until(lambda: len(table.alive()) == len(agents))
            signers = {agent: Signer.generate() for agent in agents}
            for agent in agents:
                d.feed("hb", agent, _heartbeat(agent, signers[agent]))
            assert d.metrics.rejected["too-many-members"] == 0, d.metrics.rejected
            assert table.find("robot") is not None and table.find("robot").heard
            # what a member's heartbeat lists is remembered up to max_layers + 1, its own first
            s = Sender("robot", 7, key=KEY, signer=signers["robot"], first_seq=5)
            listed = [LayerVersion(origin=f"l{i}", epoch=1, version=1) for i in range(100)]
            listed.append(LayerVersion(origin="robot", epoch=7, version=3))
            hb = Heartbeat(**s.header(), kind="robot", frame_id="robot.odom", layers=listed)
            d.feed("hb", "robot", s.encode(hb))
            kept = table.find("robot").layers
            assert len(kept) == 3 and kept["robot"] == (7, 3), kept
        finally:
            for t in tokens:
                t.undeclare()
            table.close()
            d.close()


class _Racing(Replicas):
    """Replicas whose admission of a snapshot (`admit(replace=True)`: the catch-up's, before
    the snapshot is built and installed) runs `race` on another thread, then waits up to 0.5 s
    for it: the one stand-in, forcing the interleaving at the one point it can happen (the
    frames, sessions, inbox, layers and catch-up are real)."""

    def __init__(self, d: SimpleNamespace, race: Callable[[], None]) -> None:
        super().__init__(d.layers, d.metrics)
        self._race = race
        self.raced: list[threading.Thread] = []

    def admit(self, origin, epoch, deltas, replace=False) -> None:
        super().admit(origin, epoch, deltas, replace)
        if replace and not self.raced:
            self.raced.append(threading.Thread(target=self._race))
            self.raced[0].start()
            self.raced[0].join(0.5)  # done unless it waits for the install


def _tombstone(agent: str, signer: Signer, forgotten: list[str], seq: int) -> bytes:
    sender = Sender(agent, 7, key=KEY, signer=signer, first_seq=seq)
    hb = Heartbeat(**sender.header(), kind="robot", frame_id=f"{agent}.odom", forgotten=forgotten)
    return sender.encode(hb)


def test_a_tombstone_during_a_snapshot_install_leaves_the_layer_forgotten() -> None:
    """A snapshot was admitted (the layer not forgotten), then installed outside the layers'
    apply lock: a tombstone (`forget_agent`, carried by another member's heartbeat) that came
    between the two dropped nothing yet held, and the install then made the layer again, a
    forgotten agent's layer held (and served) until the next tombstone. Now the install is
    committed under the apply lock, after checking the layer is still not forgotten (refused,
    `forgotten`, its frames not accepted). Real sessions, frames, inbox, layers and catch-up;
    `_Racing` forces the interleaving."""
    chunk = Delta(0.1, 0, 3, [[0, 0, 0], [1, 0, 0]], [1.0, 1.0], [1.7e9, 1.7e9])
    with _sessions(2) as (mine, evil):
        d = _daemon(mine)
        signer = Signer.generate()
        d.feed("hb", "evil", _heartbeat("evil", signer))
        b = Signer.generate()
        d.feed("hb", "b", _heartbeat("b", b))
        q = _serve(evil, signer, lambda rid, s: [_snapshot_reply(s, rid, chunk, 0, 1)])
        try:
            assert _until(lambda: _answers(mine))
            replicas = _Racing(d, lambda: d.feed("hb", "b", _tombstone("b", b, ["evil"], 2)))
            catchup = CatchUp(mine, NS, replicas, Sender("me", 1, key=KEY), d.receiver, d.metrics)
            installed = catchup._fetch_snapshot("evil", "evil", time.monotonic())
            replicas.raced[0].join(5.0)
            assert "evil" in d.layers.forgotten
            assert d.layers.find("evil") is None, d.layers.find("evil").seq
            assert not installed
            assert d.metrics.rejected["forgotten"] == 1
            assert d.receiver.accepted["snapshot_reply"] == 0  # refused: no window moved
            d.receiver.replay.peek("evil", 7, 100)
        finally:
            q.undeclare()
            d.close()


def test_a_live_delta_during_a_snapshot_install_cannot_overshoot_the_budget() -> None:
    """A snapshot was admitted against the peer budget, then installed outside the apply lock:
    a live delta of another peer admitted and applied between the two took the room the
    snapshot was admitted for, and both held more blocks than `max_peer_blocks`. The install
    is now committed under the apply lock after checking the budget again with the blocks its
    grid holds: the snapshot (which came second to the budget) is refused, `over-budget`, and
    the budget is never exceeded. `_Racing` forces the interleaving."""
    with _sessions(2) as (mine, evil):
        d = _daemon(mine)  # a peer budget of 1000 blocks
        signer = Signer.generate()
        d.feed("hb", "evil", _heartbeat("evil", signer))
        _, b = _introduce(d, "b")
        snap = _box(0, 6, 3)  # 600 blocks: fits the budget alone
        snap = Delta(0.1, 0, 3, snap.keys, snap.logodds, snap.last_time)
        live = _one_part(b, _box(1000, 5, 1))  # b's first delta, 500 blocks: fits alone too
        q = _serve(evil, signer, lambda rid, s: [_snapshot_reply(s, rid, snap, 0, 1)])
        try:
            assert _until(lambda: _answers(mine))
            replicas = _Racing(d, lambda: d.feed("delta", "b", live))
            catchup = CatchUp(mine, NS, replicas, Sender("me", 1, key=KEY), d.receiver, d.metrics)
            installed = catchup._fetch_snapshot("evil", "evil", time.monotonic())
            replicas.raced[0].join(5.0)
            blocks = sum(x.blocks() for x in d.layers.all() if x.origin != "me")
            assert blocks <= d.layers.max_peer_blocks, blocks
            assert d.layers.find("b").seq == 1  # first come, first served
            assert not installed and d.metrics.rejected["over-budget"] == 1
            assert d.layers.find("evil") is None or d.layers.find("evil").seq == 0
        finally:
            q.undeclare()
            d.close()


def test_liveliness_tokens_held_by_a_stranger_keep_the_table_bounded() -> None:
    """A member known from its liveliness token alone was kept while its token lived: a
    stranger declaring ever more made-up tokens (and holding them) grew the member table
    without end (each a join). Now at most `max_members` such members are kept, the oldest
    forgotten for a new one; a member whose heartbeat was verified is never forgotten for
    them, and a token-only member's later heartbeat still makes it a member."""
    with _sessions(3) as (mine, real, stranger):
        d = _daemon(mine, max_members=4)
        tokens: list = []
        try:
            b = Membership(real, NS, "b", lambda agent, event: None)
            assert _until(lambda: d.membership.find("b") is not None)
            d.feed("hb", "b", _heartbeat("b", Signer.generate()))
            for i in range(40):
                tokens.append(stranger.liveliness().declare_token(alive_key(NS, f"x{i}")))
            assert _until(lambda: d.membership.find("x39") is not None)
            time.sleep(0.2)  # any late join
            table = {m.agent for m in d.membership.table()}
            assert table == {"b", "x36", "x37", "x38", "x39"}, sorted(table)
            assert d.membership.find("b").alive and d.membership.find("b").heard
            d.feed("hb", "x38", _heartbeat("x38", Signer.generate()))  # heard now: kept
            for i in range(40, 44):
                tokens.append(stranger.liveliness().declare_token(alive_key(NS, f"x{i}")))
            assert _until(lambda: d.membership.find("x43") is not None)
            time.sleep(0.2)
            table = {m.agent for m in d.membership.table()}
            assert table == {"b", "x38", "x40", "x41", "x42", "x43"}, sorted(table)
            for token in tokens:
                token.undeclare()
            tokens.clear()
            assert _until(lambda: d.membership.alive() == ["b"])
            time.sleep(0.2)
            assert {m.agent for m in d.membership.table()} == {"b", "x38"}
            b.close()
        finally:
            for token in tokens:
                token.undeclare()
            d.close()


def test_a_heartbeat_listing_too_many_layers_keeps_those_held_first() -> None:
    """A member's heartbeat is remembered to hold at most `max_layers` + 1 layers: those past
    it were dropped in the sender's order, so a member listing many layers this daemon does not
    hold first hid what it holds of the layers this daemon does (their repairs ask the members
    that report more). Now the sender's own comes first, then the layers held here, then the
    rest in the sender's order."""
    from colonyd.config import Config
    from colonyd.daemon import member_table

    with _sessions(1) as (mine,):
        d = _daemon(mine)
        table = member_table(mine, Config(agent_id="me", namespace=NS, max_layers=2),
                             lambda agent, event: None)  # fmt: skip
        d.inbox.membership = table
        try:
            for origin in ("l50", "l70"):  # the peer layers this daemon holds
                _, sender = _introduce(d, origin)
                assert _first_delta(d, sender) is not None
            signer = Signer.generate()
            d.feed("hb", "robot", _heartbeat("robot", signer))
            s = Sender("robot", 7, key=KEY, signer=signer, first_seq=5)
            listed = [LayerVersion(origin=f"l{i}", epoch=7, version=9) for i in range(100)]
            listed += [LayerVersion(origin="me", epoch=1, version=1),
                       LayerVersion(origin="robot", epoch=7, version=3)]  # fmt: skip
            hb = Heartbeat(**s.header(), kind="robot", frame_id="robot.odom", layers=listed)
            d.feed("hb", "robot", s.encode(hb))
            kept = table.find("robot").layers
            assert kept == {"robot": (7, 3), "l50": (7, 9), "l70": (7, 9)}, kept
        finally:
            table.close()
            d.close()


def test_a_peer_flooding_object_lists_alone_gets_no_more_than_a_peers_rate() -> None:
    """The objects rate (16,384 a second, ~0.36 s of the inbox's second) is shared by the
    peers spending theirs: a peer flooding alone (a key holder, a member gone wrong) took all
    of it, where 2048 a second was its bound before. A peer's share is now also at most
    `PEER_OBJECTS_PER_S` (8192: a full list at every default 2 s refresh, ~0.18 s of the
    inbox's second): it passes at most that over 20 s, plus its first full list; the member
    with 2000 objects changing every 0.5 s (4000 a second) still passes every list, alone or
    beside three others doing as much."""
    from colonyd.objects import PEER_OBJECTS_PER_S

    now = [0.0]
    objects = PeerObjects(clock=lambda: now[0])
    passed = 0
    for _ in range(200):  # a full list every 0.1 s
        try:
            objects.allow("flood")
        except WireError:
            pass
        else:
            objects.charge("flood", objects.burst)
            passed += objects.burst
        now[0] += 0.1
    assert passed <= PEER_OBJECTS_PER_S * now[0] + 2 * objects.burst, passed
    assert min(PEER_OBJECTS_PER_S / 4000, PEER_OBJECTS_PER_S / (objects.burst / 2.0)) >= 1.0
    for peers in (1, 4):
        busy = PeerObjects(clock=lambda: now[0])
        for _ in range(40):
            for k in range(peers):
                busy.allow(f"b{k}")  # raises if refused
                busy.charge(f"b{k}", 2000)
            now[0] += 0.5


def test_a_busy_member_gets_its_allowance_back_soon_after_a_flood_stops() -> None:
    """Nine peers (made-up identities of a key holder, or members gone wrong) flood full object
    lists every 0.1 s for 10 s beside a member whose 2000 objects change at every 0.5 s refresh.
    While the flood lasts the member keeps its share (a tenth of `OBJECTS_PER_S`). The share
    counted every peer whose allowance was not full again: the flooders, deep in debt, counted
    for ~20 s after their last list, and 13 of the member's next 20 lists were refused. It now
    counts the peers sending (a list charged within `SENDING_S`; the idle ones at
    1/`IDLE_WEIGHT`): `SENDING_S` after the flood's last list, plus the member's debt (at most
    one of its lists) at `PEER_OBJECTS_PER_S`, every list of the member passes again."""
    from colonyd.objects import PEER_OBJECTS_PER_S, SENDING_S

    now = [0.0]
    objects = PeerObjects(clock=lambda: now[0])

    def send(origin: str, count: int) -> bool:
        try:
            objects.allow(origin)
        except WireError:
            return False
        objects.charge(origin, count)
        return True

    passed = 0
    for step in range(100):  # the flood: 10 s
        for k in range(9):
            send(f"f{k}", objects.burst)
        if step % 5 == 0 and send("busy", 2000):
            passed += 2000
        now[0] += 0.1
    assert objects.rate() == objects.per_s / 10
    assert passed >= objects.rate() * now[0], passed  # its share while the flood lasts
    stopped = now[0]
    settled = stopped + SENDING_S + 2000 / PEER_OBJECTS_PER_S
    refused = after = 0
    while now[0] < stopped + 20.0:  # the member goes on, every 0.5 s
        ok = send("busy", 2000)
        if now[0] >= settled:
            after += 1
            refused += not ok
        now[0] += 0.5
    assert after >= 20 and refused == 0, (refused, after)
    assert objects.rate() == PEER_OBJECTS_PER_S  # its full share: nine idle peers at 1/16 each


def test_a_member_refused_beside_a_flood_keeps_its_share() -> None:
    """Nine peers flood full object lists every 0.1 s; a member tries its full list every 2 s
    (its share, a tenth of `OBJECTS_PER_S`, earns one every 10 s). Its refused tries count as
    sending (`SENDING_S`): it keeps a full share and passes one list every ~10 s, where an idle
    peer would earn 1/`IDLE_WEIGHT` of one. One that stopped in debt comes back the same way."""
    now = [0.0]
    objects = PeerObjects(clock=lambda: now[0])

    def send(origin: str) -> bool:
        try:
            objects.allow(origin)
        except WireError:
            return False
        objects.charge(origin, objects.burst)
        return True

    passed = {"big": 0, "back": 0}
    send("back")  # its allowance spent, then silent for a minute
    for step in range(1200):  # 120 s
        for k in range(9):
            send(f"f{k}")
        if step % 20 == 0:
            passed["big"] += send("big")
            if step >= 600:
                passed["back"] += send("back")
        now[0] += 0.1
    share = objects.per_s / 11
    assert passed["big"] >= int(share * now[0] / objects.burst) - 1, passed
    assert passed["back"] >= int(share * 60.0 / objects.burst) - 1, passed
    assert objects.rate() == share


def test_object_lists_of_agents_no_longer_members_keep_no_member_out() -> None:
    """Peers' object lists were kept for `max_members` origins and never dropped: once that
    many agents had sent one (made-up identities, each introduced by one heartbeat, or robots
    come and gone), every later member's list was refused (`too-many-layers`) for as long as
    the daemon ran, though those agents had long left the member table. A list is now taken
    from a member only (`unknown-member`), and a list of an agent no longer a member makes
    room for a member's."""
    with _sessions(2) as (mine, other):
        d = _daemon(mine, max_members=4)
        d.peer_objects.max_origins = 4
        tokens = [other.liveliness().declare_token(alive_key(NS, "real"))]
        try:
            assert _until(lambda: d.membership.alive() == ["real"])
            ghosts = [f"g{i}" for i in range(4)]
            send = _listing(d, ghosts)  # introduced: members (heard, no token)
            for g in ghosts:
                send(g, _objects(3))
            assert d.peer_objects.origins() == ghosts
            real = _listing(d, ["real"])  # its heartbeat: the least recently seen ghost goes
            assert d.membership.find("g0") is None
            real("real", _objects(3))
            assert len(d.peer_objects.get("real")) == 3, d.metrics.rejected
            assert "g0" not in d.peer_objects.origins()
            send("g0", _objects(3))  # pinned still, a member no more: refused
            assert d.metrics.rejected["unknown-member"] == 1
            assert d.metrics.rejected["too-many-layers"] == 0
        finally:
            for t in tokens:
                t.undeclare()
            d.close()
