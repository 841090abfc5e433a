"""The daemon on the wire: protocol frames out, one Receiver in, exact replicas, rejections."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from colonyd.errors import WireError
from colonyd.frames import SEQ_BLOCK, Assembler, Sender, colony_key, get_receiver
from colonyd.grid import new_grid
from colonyd.layers import Layer, relabel
from protocol import (
    AuthError,
    DecompressionBombError,
    Heartbeat,
    KeyExprError,
    LayerVersion,
    ProtocolError,
    ReplayError,
    VoxelDelta,
    delta_messages,
    peek,
)
from protocol.keyexpr import topic_key
from voxel.delta import Delta

SECRET = "correct horse battery staple"


def grid_deltas(n: int = 4, points: int = 400) -> tuple[object, list[Delta]]:
    """An origin grid and the deltas it published (as the daemon labels them: (i, i+1])."""
    grid, out, v = new_grid(0.1), [], 0
    rng = np.random.default_rng(3)
    for i in range(n):
        pts = rng.uniform(-3, 3, (points, 3))
        grid.integrate(
            pts,
            np.zeros(3),
            time=1_700_000_000.0 + i * 0.25 + 0.0004,
            colours=rng.integers(0, 256, (points, 3), dtype=np.uint8),
        )
        out.append(relabel(grid.delta_since(v), i, i + 1, time=1_700_000_001.5))
        v = grid.version
    return grid, out


def test_colony_key_is_sha256_of_the_secret() -> None:
    import hashlib

    assert colony_key(None) is None and colony_key("") is None
    assert colony_key(SECRET) == hashlib.sha256(SECRET.encode()).digest()
    assert len(colony_key("short")) == 32  # any passphrase gives a valid 32-byte protocol key


def test_replica_through_protocol_frames_is_identical_to_origin() -> None:
    origin, deltas = grid_deltas()
    sender = Sender("a", 1_700_000_000_123_456, key=colony_key(SECRET))
    receiver = get_receiver(SECRET, 64, "me")
    replica = Layer("a", 0.1)
    assembler = Assembler()
    key = topic_key("site", "a", "delta")
    for d in deltas:
        msgs = delta_messages(
            origin="a", epoch=sender.epoch, seq=0, time=1.0, frame_id="map", delta=d, max_bytes=4096
        )  # small parts: exercise reassembly
        frames = sender.encode_all(msgs)
        for frame in reversed(frames):  # parts in any order
            msg = receiver.decode(frame, key_expr=key)
            assert isinstance(msg, VoxelDelta) and msg.epoch == 1_700_000_000_123_456
            whole = assembler.add(
                (msg.origin, msg.epoch, msg.delta.from_version, msg.delta.to_version),
                msg.part,
                msg.parts,
                msg.delta,
            )
            if whole is not None:
                assert (
                    replica.offer(msg.epoch, whole.from_version, whole.to_version, whole).outcome
                    == "applied"
                )
    assert replica.seq == len(deltas)
    assert replica.grid.content_equal(origin)  # bit for bit: log-odds, times, channels
    own = Layer("a", 0.1)
    own.grid = origin
    assert replica.digest() == own.digest()


def test_frame_numbers_are_shared_and_reserved_ahead() -> None:
    reserved: list[int] = []
    s = Sender("a", 5, first_seq=100, reserve=reserved.append)
    assert s.take() == 100 and reserved == [101 + SEQ_BLOCK]
    assert s.take(3) == 101 and s.take() == 104 and len(reserved) == 1
    # a restart resumes at the reservation: never a seq the previous run may have used
    restarted = Sender("a", 5, first_seq=reserved[-1])
    assert restarted.take() > 104


def test_heartbeat_round_trip_and_replay_rejected() -> None:
    s = Sender("b", 7, key=colony_key(SECRET))
    r = get_receiver(SECRET, 64, "me")
    frame = s.encode(
        Heartbeat(
            **s.header(),
            kind="robot",
            frame_id="map",
            position=(1.0, 2.0, 0.0),
            layers=[LayerVersion(origin="a", epoch=3, version=9)],
        )
    )
    msg = r.receive(frame, key_expr=topic_key("site", "b", "heartbeat"))
    assert isinstance(msg, Heartbeat) and msg.layers[0].version == 9
    with pytest.raises(ReplayError):
        r.decode(frame)


def test_colony_key_authenticates() -> None:
    signed = Sender("x", 1, key=colony_key(SECRET))
    hb = Heartbeat(**signed.header(), kind="robot", frame_id="map")
    with pytest.raises(AuthError, match="tag does not match") as info:
        get_receiver("another secret", 64, "me").decode(signed.encode(hb))
    assert info.value.reason == "auth"
    open_ = Sender("x", 1)
    with pytest.raises(AuthError, match="found no tag"):
        get_receiver(SECRET, 64, "me").decode(open_.encode(hb))
    with pytest.raises(AuthError, match="found a tag"):
        get_receiver(None, 64, "me").decode(signed.encode(hb))


@pytest.mark.parametrize(
    ("data", "reason"),
    [
        (b"", "truncated"),
        (b"nonsense bytes", "malformed"),
        (b"CLNY\x09\x03\x00\x00" + b"\x00" * 8, "version"),
        (b"CLNY\x01\x63\x00\x00" + b"\x00" * 8, "unknown_type"),
        (b"CLNY\x01\x03\x02\x00\x95\xa1a\x01\x01\xcb" + b"\x00" * 8 + b"\xc4\x04nope", "malformed"),
    ],
)
def test_hostile_input_is_rejected_with_reason(data: bytes, reason: str) -> None:
    r = get_receiver(None, 64, "me")
    with pytest.raises(ProtocolError) as info:
        r.decode(data)
    assert info.value.reason == reason
    assert r.rejected[reason] == 1


def test_frame_on_another_origins_key_is_rejected() -> None:
    s = Sender("evil", 1)
    frame = s.encode(Heartbeat(**s.header(), kind="robot", frame_id="map"))
    with pytest.raises(KeyExprError, match="belongs to origin 'a'"):
        get_receiver(None, 64, "me").decode(frame, key_expr=topic_key("site", "a", "heartbeat"))


def test_decompression_bomb_is_rejected_without_allocating() -> None:
    import msgpack
    import zstandard

    body = zstandard.ZstdCompressor().compress(b"\x00" * (8 << 20))  # declares 8 MiB
    envelope = msgpack.packb(["a", 1, 1, 1.0, body], use_bin_type=True)
    frame = b"CLNY\x01\x03\x02\x00" + envelope  # VoxelDelta, zstd body
    with pytest.raises(DecompressionBombError) as info:
        get_receiver(None, 1, "me").decode(frame)  # 1 MiB decoded at most
    assert info.value.reason == "decompression_bomb"


def test_assembler_is_bounded_and_checks_parts() -> None:
    _, (d,) = grid_deltas(1)
    a = Assembler(max_open=2)
    halves = [d.select(np.arange(len(d)) < len(d) // 2), d.select(np.arange(len(d)) >= len(d) // 2)]
    for i in range(3):
        assert a.add(("o", 1, 0, i + 1), 0, 2, halves[0]) is None
    assert a.add(("o", 1, 0, 1), 1, 2, halves[1]) is None  # evicted: the first never completes
    whole = a.add(("o", 1, 0, 3), 1, 2, halves[1])
    assert whole is not None and len(whole) == len(d)
    with pytest.raises(WireError, match="expected 2 parts"):
        a.add(("o", 1, 0, 1), 0, 3, halves[0])


def test_encoding_from_many_threads_at_once() -> None:
    _, deltas = grid_deltas(1, 2000)
    s, r, errors = Sender("a", 1, key=colony_key(SECRET)), get_receiver(SECRET, 64, "me"), []

    def work() -> None:
        try:
            for _ in range(20):
                msg = r.receive(s.encode(VoxelDelta(**s.header(), frame_id="map", delta=deltas[0])))
                assert len(msg.delta) == len(deltas[0])
        except Exception as exc:  # noqa: BLE001  # pragma: no cover - a thread's failure, reported below
            errors.append(exc)

    threads = [threading.Thread(target=work) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert peek(s.encode(Heartbeat(**s.header(), kind="robot", frame_id="map"))).seq == 120


def test_protocol_doc_states_how_the_key_is_derived() -> None:
    from pathlib import Path

    doc = (Path(__file__).parents[2] / "docs" / "PROTOCOL.md").read_text()
    phrase = "correct horse battery staple"
    assert f"passphrase `{phrase}` gives the key\n`{colony_key(phrase).hex()}`" in doc
