"""Tests of protocol.codec: frames of every message type, hostile frames, authentication."""

from __future__ import annotations

import struct

import msgpack
import numpy as np
import pytest
import zstandard
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import fields
from protocol.auth import ReplayWindow
from protocol.codec import (
    COMPRESSION_ZSTD,
    FLAG_AUTH,
    MAGIC,
    PREFIX,
    decode,
    delta_messages,
    encode,
    peek,
)
from protocol.errors import (
    AuthError,
    DecompressionBombError,
    MalformedError,
    OversizedError,
    ProtocolError,
    RangeError,
    ReplayError,
    TruncatedError,
    UnknownTypeError,
    VersionError,
)
from protocol.keyexpr import NAME_PATTERN
from protocol.limits import Limits
from protocol.messages import ObjectCentroid, Objects, Pose, VoxelDelta
from tests.protocol.helpers import KEY, assert_delta_close, make_delta, sample_messages


def _same(a, b) -> None:
    assert type(a) is type(b)
    da, db = (
        a.model_dump(exclude={"delta", "free_summary", "records"}),
        b.model_dump(exclude={"delta", "free_summary", "records"}),
    )
    assert da == db
    if getattr(a, "records", None) is not None:
        ra, rb = a.records.records, b.records.records
        ra, rb = (r[np.lexsort((r["key"], r["version"]))] for r in (ra, rb))
        assert ra.tobytes() == rb.tobytes() and a.records.agents == b.records.agents
    if getattr(a, "delta", None) is not None:
        assert_delta_close(a.delta, b.delta)
    else:
        assert getattr(b, "delta", None) is None


@pytest.mark.parametrize("key", [None, KEY])
@pytest.mark.parametrize("compression", ["zstd", "none"])
def test_every_message_type_round_trips(key: bytes | None, compression: str) -> None:
    for msg in sample_messages():
        frame = encode(msg, key=key, compression=compression)
        _same(msg, decode(frame, key=key))


def test_epoch_is_64_bit() -> None:
    epoch = 1_700_000_000_123_456  # a microsecond clock, as colonyd uses
    for e in (epoch, (1 << 63) - 1):
        msg = Pose(origin="r1", epoch=e, seq=2, time=3.0, frame_id="map", position=(0, 0, 0))
        assert decode(encode(msg)).epoch == e
        assert peek(encode(msg)).epoch == e


def test_peek_reads_envelope_without_body() -> None:
    msg = sample_messages()[1]
    info = peek(encode(msg, key=KEY))
    assert (info.kind, info.origin, info.epoch, info.seq, info.authenticated) == (
        "pose",
        "robot-1",
        3,
        41,
        True,
    )


def _pose_frame(**kw) -> bytes:
    msg = Pose(origin="r1", epoch=1, seq=2, time=3.0, frame_id="map", position=(0.0, 0.0, 0.0))
    return encode(msg, **kw)


def _frame(
    mtype: int = 2, flags: int = 0, envelope: object = None, version: int = 1, tail: bytes = b""
) -> bytes:
    if envelope is None:
        body = msgpack.packb({"frame_id": "map", "position": [0.0, 0.0, 0.0]})
        envelope = ["r1", 1, 2, 3.0, body]
    return (
        PREFIX.pack(MAGIC, version, mtype, flags, 0)
        + msgpack.packb(envelope, use_bin_type=True)
        + tail
    )


def test_reference_frame_decodes() -> None:
    assert isinstance(decode(_frame()), Pose)


@pytest.mark.parametrize(
    ("data", "error", "match"),
    [
        (b"", TruncatedError, "at least 8 bytes of prefix, found 0"),
        (b"CLNY\x01", TruncatedError, "found 5"),
        (b"XXXX\x01\x02\x00\x00\x90", MalformedError, "expected magic b'CLNY', found b'XXXX'"),
        (_frame(version=2), VersionError, "protocol version 1, found 2"),
        (_frame(mtype=0), UnknownTypeError, "message type in .*found 0"),
        (_frame(mtype=200), UnknownTypeError, "found 200"),
        (_frame(flags=0x80), MalformedError, "reserved flag bits"),
        (_frame(flags=0x06), UnknownTypeError, "compression 0 \\(none\\) or 1 \\(zstd\\), found 3"),
        (_frame()[:-3], TruncatedError, "msgpack"),
        (_frame(tail=b"\x00"), MalformedError, "trailing"),
        (
            _frame(envelope=[1, 2]),
            MalformedError,
            "\\[origin, epoch, seq, time, body\\], found 2 items",
        ),
        (_frame(envelope={"a": 1}), MalformedError, "found dict"),
        (_frame(envelope=["bad/origin", 1, 2, 3.0, b""]), RangeError, "origin matching"),
        (_frame(envelope=["r1", -1, 2, 3.0, b""]), RangeError, "epoch in"),
        (_frame(envelope=["r1", 1 << 63, 2, 3.0, b""]), RangeError, "epoch in"),
        (_frame(envelope=["r1", 1, "x", 3.0, b""]), MalformedError, "integer seq"),
        (_frame(envelope=["r1", 1, 2, 3, b""]), MalformedError, "float time, found int"),
        (_frame(envelope=["r1", 1, 2, float("nan"), b""]), RangeError, "finite time"),
        (_frame(envelope=["r1", 1, 2, 3.0, "text"]), MalformedError, "binary body, found str"),
        (_frame(envelope=["r1", 1, 2, 3.0, b"\xc1"]), MalformedError, "msgpack type byte"),
        (
            _frame(envelope=["r1", 1, 2, 3.0, msgpack.packb([1])]),
            MalformedError,
            "pose body: expected a msgpack map",
        ),
        (
            _frame(envelope=["r1", 1, 2, 3.0, msgpack.packb({"frame_id": "map"})]),
            MalformedError,
            "position",
        ),
        (
            _frame(
                envelope=[
                    "r1",
                    1,
                    2,
                    3.0,
                    msgpack.packb({"frame_id": "m/x", "position": [0, 0, 0]}),
                ]
            ),
            RangeError,
            "frame_id",
        ),
        (
            _frame(
                envelope=[
                    "r1",
                    1,
                    2,
                    3.0,
                    msgpack.packb({"frame_id": "m", "position": [0, 0, 1e400]}),
                ]
            ),
            RangeError,
            "position",
        ),
        (
            _frame(
                envelope=[
                    "r1",
                    1,
                    2,
                    3.0,
                    msgpack.packb(
                        {"frame_id": "m", "position": [0, 0, 0], "orientation": [0, 0, 0, 2]}
                    ),
                ]
            ),
            RangeError,
            "unit quaternion",
        ),
        (
            _frame(
                envelope=[
                    "r1",
                    1,
                    2,
                    3.0,
                    msgpack.packb(
                        {"frame_id": "m", "position": [0, 0, 0], "covariance": [0.0] * 40}
                    ),
                ]
            ),
            OversizedError,
            "covariance",
        ),
        (_frame(flags=COMPRESSION_ZSTD << 1), MalformedError, "expected a zstd frame"),
        (
            _frame(mtype=3, envelope=["r1", 1, 2, 3.0, msgpack.packb({"frame_id": "m"})]),
            MalformedError,
            "field 'delta'",
        ),
        (
            _frame(
                mtype=3, envelope=["r1", 1, 2, 3.0, msgpack.packb({"frame_id": "m", "delta": 5})]
            ),
            MalformedError,
            "binary 'delta'",
        ),
    ],
)
def test_hostile_frames_rejected(data: bytes, error: type[ProtocolError], match: str) -> None:
    with pytest.raises(error, match=match):
        decode(data)


def test_not_bytes_rejected() -> None:
    with pytest.raises(MalformedError, match="frame must be bytes, found str"):
        decode("CLNY")  # type: ignore[arg-type]


def test_unknown_body_fields_are_ignored() -> None:
    body = msgpack.packb({"frame_id": "map", "position": [0.0, 0.0, 0.0], "future_field": [1, 2]})
    assert isinstance(decode(_frame(envelope=["r1", 1, 2, 3.0, body])), Pose)


def test_oversized_frame_rejected() -> None:
    frame = _pose_frame()
    with pytest.raises(OversizedError, match=f"at most 20 bytes, found {len(frame)}"):
        decode(frame, limits=Limits(max_message_bytes=20))


def _zstd_frame(envelope_body: bytes) -> bytes:
    return _frame(flags=COMPRESSION_ZSTD << 1, envelope=["r1", 1, 2, 3.0, envelope_body])


def test_decompression_bomb_rejected_from_header() -> None:
    bomb = zstandard.ZstdCompressor(level=19).compress(b"\x00" * (80 << 20))
    assert len(bomb) < 10_000
    with pytest.raises(DecompressionBombError, match="declares 83886080"):
        decode(_zstd_frame(bomb))


def test_zstd_without_content_size_rejected() -> None:
    hidden = zstandard.ZstdCompressor(write_content_size=False).compress(b"\x00" * 1000)
    with pytest.raises(MalformedError, match="declares its content size"):
        decode(_zstd_frame(hidden))


def test_zstd_lying_about_content_size_rejected() -> None:
    body = msgpack.packb({"frame_id": "map", "position": [0.0, 0.0, 0.0]})
    good = fields.compress(body)
    liar = bytearray(good)
    # frame header descriptor with single-segment flag: content size byte follows the descriptor
    liar[5] = (liar[5] + 7) % 256
    with pytest.raises(ProtocolError):
        decode(_zstd_frame(bytes(liar)))


def test_zstd_trailing_data_rejected() -> None:
    body = fields.compress(msgpack.packb({"frame_id": "map", "position": [0.0, 0.0, 0.0]}))
    with pytest.raises(MalformedError, match="zstd"):
        decode(_zstd_frame(body + body))


def test_huge_zstd_window_rejected() -> None:
    params = zstandard.ZstdCompressionParameters(window_log=17, compression_level=3)
    data = zstandard.ZstdCompressor(compression_params=params).compress(b"\x01" * (1 << 17))
    with pytest.raises(DecompressionBombError, match="window"):
        decode(_zstd_frame(data), limits=Limits(max_window_bytes=1 << 10))


def test_uncompressed_body_over_limit_rejected() -> None:
    frame = _pose_frame(compression="none")
    with pytest.raises(OversizedError, match="body: expected at most 10 bytes"):
        decode(frame, limits=Limits(max_body_bytes=10))


def test_msgpack_object_bomb_rejected() -> None:
    body = b"\xdd" + struct.pack(">I", 2_000_000) + b"\x90" * 2_000_000  # 2M empty arrays
    frame = _frame(envelope=["r1", 1, 2, 3.0, body])
    with pytest.raises(OversizedError, match="msgpack objects"):
        decode(frame)


def test_msgpack_deep_nesting_rejected() -> None:
    body = b"\x91" * 100 + b"\xc0"
    with pytest.raises(MalformedError, match="nesting depth"):
        decode(_frame(envelope=["r1", 1, 2, 3.0, body]))


def test_msgpack_extension_rejected() -> None:
    body = msgpack.packb({"frame_id": msgpack.ExtType(5, b"x"), "position": [0, 0, 0]})
    with pytest.raises(UnknownTypeError, match="extension"):
        decode(_frame(envelope=["r1", 1, 2, 3.0, body]))


# --------------------------------------------------------------------------- authentication


def test_authenticated_frame_requires_key_and_vice_versa() -> None:
    signed = _pose_frame(key=KEY)
    plain = _pose_frame()
    assert signed[6] & FLAG_AUTH and not plain[6] & FLAG_AUTH
    with pytest.raises(AuthError, match="expected an authenticated frame"):
        decode(plain, key=KEY)
    with pytest.raises(AuthError, match="no colony key configured"):
        decode(signed)
    with pytest.raises(AuthError, match="tag does not match"):
        decode(signed, key=b"another-colony-key-000000000000")


def test_every_tampered_byte_is_detected() -> None:
    signed = _pose_frame(key=KEY)
    for i in range(len(signed)):
        tampered = bytearray(signed)
        tampered[i] ^= 0x01
        with pytest.raises(ProtocolError):
            decode(bytes(tampered), key=KEY)
    with pytest.raises(ProtocolError):
        decode(signed[:-1], key=KEY)


def test_flag_stripping_is_detected() -> None:
    signed = bytearray(_pose_frame(key=KEY))
    signed[6] &= ~FLAG_AUTH
    with pytest.raises(AuthError):
        decode(bytes(signed[:-32]), key=KEY)


def test_short_key_refused() -> None:
    with pytest.raises(AuthError, match="at least 16 bytes"):
        _pose_frame(key=b"short")


def test_replays_detected() -> None:
    window = ReplayWindow(window=64)
    frames = [
        encode(
            Pose(origin="r1", epoch=1, seq=s, time=1.0, frame_id="m", position=(0, 0, 0)), key=KEY
        )
        for s in range(5)
    ]
    for f in frames[::-1]:  # out of order is fine
        decode(f, key=KEY, replay=window)
    with pytest.raises(ReplayError, match="seq 2 of epoch 1 was already accepted"):
        decode(frames[2], key=KEY, replay=window)
    old_epoch = encode(
        Pose(origin="r1", epoch=0, seq=99, time=1.0, frame_id="m", position=(0, 0, 0)), key=KEY
    )
    with pytest.raises(ReplayError, match="expected epoch >= 1, found epoch 0"):
        decode(old_epoch, key=KEY, replay=window)


def test_replay_window_edges() -> None:
    w = ReplayWindow(window=8, max_origins=2)
    w.check("a", 1, 100)
    with pytest.raises(ReplayError, match="older than the replay window"):
        w.check("a", 1, 92)
    w.check("a", 1, 93)
    w.check("a", 1, 1000)  # big jump forward
    with pytest.raises(ReplayError):
        w.check("a", 1, 1000)
    w.check("a", 2, 0)  # restart with a new epoch
    w.check("b", 1, 0)
    w.check("c", 1, 0)  # evicts the least recently updated origin
    w.check("a", 0, 0)  # "a" was forgotten: accepted again (bounded memory)
    with pytest.raises(ValueError, match="window must be >= 1"):
        ReplayWindow(window=0)


# --------------------------------------------------------------------------- deltas in frames


def test_delta_messages_split_and_budget() -> None:
    rng = np.random.default_rng(3)
    delta = make_delta(rng, 30_000, spread=300, channels=False)
    msgs = delta_messages(
        origin="r1", epoch=1, seq=10, time=delta.time, frame_id="map", delta=delta, max_bytes=16_000
    )
    assert len(msgs) > 1
    assert [m.seq for m in msgs] == list(range(10, 10 + len(msgs)))
    assert all(m.parts == len(msgs) for m in msgs) and [m.part for m in msgs] == list(
        range(len(msgs))
    )
    total = 0
    for m in msgs:
        frame = encode(m, key=KEY)
        assert len(frame) <= 16_000
        out = decode(frame, key=KEY)
        assert isinstance(out, VoxelDelta) and out.exact
        total += len(out.delta)
    assert total == len(delta)
    dense = make_delta(rng, 30_000, spread=25, channels=False)
    budgeted = delta_messages(
        origin="r1",
        epoch=1,
        seq=0,
        time=delta.time,
        frame_id="map",
        delta=dense,
        budget=40_000,
        max_bytes=1 << 20,
    )
    assert len(budgeted) == 1
    frame = encode(budgeted[0])
    out = decode(frame)
    assert not out.exact and out.free_summary is not None
    assert out.delta.occupied.sum() == dense.occupied.sum()
    assert len(frame) <= 40_000 + 256


def test_summary_gets_its_own_part_when_the_last_part_is_full() -> None:
    rng = np.random.default_rng(4)
    dense = make_delta(rng, 30_000, spread=25, channels=False)
    msgs = delta_messages(
        origin="r1",
        epoch=1,
        seq=0,
        time=dense.time,
        frame_id="map",
        delta=dense,
        budget=40_000,
        max_bytes=8_000,
    )
    assert len(msgs) > 1
    assert all(m.free_summary is None for m in msgs[:-1])
    last = decode(encode(msgs[-1]))
    assert last.free_summary is not None and last.parts == len(msgs)
    for m in msgs:
        assert len(encode(m)) <= 8_000


def test_peek_rejects_truncated_tagged_frame() -> None:
    signed = _pose_frame(key=KEY)
    with pytest.raises(TruncatedError, match="32-byte tag"):
        peek(signed[: PREFIX.size + 10])


def test_largest_objects_list_decodes_and_one_more_is_refused() -> None:
    obj = ObjectCentroid(
        object_id=1,
        class_id=2,
        class_name="chair",
        position=(1.0, 2.0, 3.0),
        covariance=[0.1] * 9,
        voxel_count=100,
        time=1.0,
    )
    msg = Objects(origin="r1", time=1.0, frame_id="map", objects=[obj] * 16_384)
    assert len(decode(encode(msg)).objects) == 16_384
    body = msgpack.packb({"frame_id": "map", "objects": [obj.model_dump()] * 16_385})
    with pytest.raises(OversizedError, match="objects"):
        decode(_frame(mtype=4, envelope=["r1", 1, 2, 3.0, body]))


# --------------------------------------------------------------------------- property tests


names = st.from_regex(f"^{NAME_PATTERN}$", fullmatch=True).filter(lambda s: "\n" not in s)
finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
vec3 = st.tuples(finite, finite, finite)
headers = st.fixed_dictionaries(
    {
        "origin": names,
        "epoch": st.integers(0, 2**32 - 1),
        "seq": st.integers(0, 2**63 - 1),
        "time": finite,
    }
)
objects = st.builds(
    ObjectCentroid,
    object_id=st.integers(0, 2**63 - 1),
    class_id=st.integers(0, 65535),
    class_name=st.text(max_size=40),
    position=vec3,
    covariance=st.lists(finite, min_size=9, max_size=9),
    voxel_count=st.integers(0, 2**32 - 1),
    time=finite,
)


@settings(max_examples=80, deadline=None)
@given(
    header=headers,
    frame_id=names,
    position=vec3,
    cov=st.lists(finite, min_size=36, max_size=36),
    key=st.sampled_from([None, KEY]),
    compression=st.sampled_from(["zstd", "none"]),
)
def test_property_pose_round_trip(header, frame_id, position, cov, key, compression) -> None:
    msg = Pose(
        **header,
        frame_id=frame_id,
        position=position,
        orientation=(0.0, 0.6, 0.0, 0.8),
        covariance=cov,
    )
    assert decode(encode(msg, key=key, compression=compression), key=key) == msg


@settings(max_examples=40, deadline=None)
@given(header=headers, frame_id=names, objs=st.lists(objects, max_size=30))
def test_property_objects_round_trip(header, frame_id, objs) -> None:
    msg = Objects(**header, frame_id=frame_id, objects=objs)
    assert decode(encode(msg)) == msg


def test_replay_window_is_thread_safe() -> None:
    import threading

    window = ReplayWindow(window=1 << 16)
    accepted: list[int] = []
    lock = threading.Lock()

    def worker() -> None:
        for seq in range(2000):
            try:
                window.check("r1", 1, seq)
            except ReplayError:
                continue
            with lock:
                accepted.append(seq)

    threads = [threading.Thread(target=worker) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(accepted) == list(range(2000))  # every seq accepted exactly once
