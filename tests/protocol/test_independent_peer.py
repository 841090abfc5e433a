"""An independent decoder written from docs/PROTOCOL.md alone (plain Python, no numpy, no
protocol internals) must read what the reference encoder writes."""

from __future__ import annotations

import hashlib
import hmac
import math
import struct

import msgpack
import numpy as np
import pytest
import zstandard
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

from protocol.codec import encode
from protocol.deltacodec import summarise_free
from protocol.messages import VoxelDelta
from tests.protocol.helpers import KEY, make_delta


def peer_decode_frame(
    frame: bytes, key: bytes | None, identity: bytes | None = None
) -> tuple[int, list, dict]:
    """§2-§4: prefix, tag, signature (verified when the origin's `identity` key is given, or
    the key a Heartbeat carries), envelope, body."""
    magic, version, mtype, flags, reserved = struct.unpack_from("<4sBBBB", frame)
    assert magic == b"CLNY" and version == 1 and reserved == 0 and flags & 0xF0 == 0
    end = len(frame)
    if flags & 1:
        end -= 32
        tag = hmac.new(key, frame[:end], hashlib.sha256).digest()
        assert hmac.compare_digest(tag, frame[end:])
    signature = None
    if flags & 8:
        signature = frame[end - 64 : end]
        end -= 64
    origin, epoch, seq, time, body = msgpack.unpackb(frame[8:end], raw=False)
    if (flags >> 1) & 3 == 1:
        assert zstandard.get_frame_parameters(body).content_size < 1 << 26
        body = zstandard.ZstdDecompressor().decompress(body)
    decoded = msgpack.unpackb(body, raw=False)
    public = identity or (decoded.get("identity") if mtype == 10 else None)
    if public is not None:
        assert signature is not None, "expected a signed frame"
        Ed25519PublicKey.from_public_bytes(public).verify(signature, frame[:end])
    return mtype, [origin, epoch, seq, time], decoded


def _ints(fmt: str, data: bytes) -> list[int]:
    size = struct.calcsize(fmt)
    return [v[0] for v in struct.iter_unpack("<" + fmt, data)] if size else []


def peer_keys(sec: list, bs: int) -> list[tuple[int, int, int]]:
    """§6 "Keys of a section": blocks (planar deltas), counts, bitmaps, list offsets."""
    n, m, blocks, counts, bitmaps, offsets = sec
    raw = _ints("i", blocks)
    xs, ys, zs = raw[:m], raw[m : 2 * m], raw[2 * m :]
    cnt = _ints("H", counts)
    edge, nvox = 1 << bs, 1 << (3 * bs)
    gaps = _ints("H", offsets)
    keys, bx, by, bz, bit_at, gap_at = [], 0, 0, 0, 0, 0
    for j in range(m):
        bx, by, bz = bx + xs[j], by + ys[j], bz + zs[j]
        if cnt[j] >= nvox // 16:
            bitmap = bitmaps[bit_at : bit_at + nvox // 8]
            bit_at += nvox // 8
            offs = [o for o in range(nvox) if bitmap[o // 8] >> (o % 8) & 1]
        else:
            offs, o = [], 0
            for i in range(cnt[j]):
                o = gaps[gap_at + i] if i == 0 else o + gaps[gap_at + i]
                offs.append(o)
            gap_at += cnt[j]
        assert len(offs) == cnt[j]
        for o in offs:
            keys.append(
                (bx * edge + o // (edge * edge), by * edge + o // edge % edge, bz * edge + o % edge)
            )
    assert len(keys) == n
    return keys


def peer_delta(body: bytes) -> dict:
    d = msgpack.unpackb(body, raw=False)
    assert d["v"] == 1
    keys = [k for sec in d["sec"] for k in peer_keys(sec[1:], d["bs"])]
    step = 2.0 ** d["q"]
    lo = [math.nan if c == -128 else c * step for c in struct.unpack(f"<{d['n']}b", d["lo"])]
    table = _ints("q", d["tt"])
    if len(table) == 1:
        idx = [0] * d["n"]
    else:
        idx = _ints("B" if len(table) <= 256 else "H" if len(table) <= 65536 else "I", d["ti"])
    t_ms = round(d["time"] * 1000) if abs(d["time"] * 1000) < 2**53 else 0
    times = [math.nan if table[i] == -(2**63) else (t_ms + table[i]) / 1000.0 for i in idx]
    channels = {}
    for entry in d["ch"]:
        if entry[0] == "hits":
            channels["hits"] = _ints("H", entry[2])
    out = {"keys": keys, "logodds": lo, "last_time": times, "channels": channels}
    if d.get("sum"):
        level, *cols = d["sum"]
        out["summary"] = (level, peer_keys(cols[:6], d["bs"]))
    return out


@pytest.mark.parametrize("key", [None, KEY])
def test_independent_peer_reads_reference_frames(key: bytes | None) -> None:
    rng = np.random.default_rng(21)
    for n, spread in ((1, 3), (40, 4), (3000, 12), (200, 2000)):
        delta = make_delta(rng, n, spread=spread)
        free = delta.logodds < 0
        msgs = [
            VoxelDelta(origin="r1", time=delta.time, frame_id="map", delta=delta),
            VoxelDelta(
                origin="r1",
                time=delta.time,
                frame_id="map",
                delta=delta.select(~free),
                free_summary=summarise_free(delta, 2),
            ),
        ]
        for msg in msgs:
            mtype, header, body = peer_decode_frame(encode(msg, key=key), key)
            assert mtype == 3 and header == ["r1", 0, 0, delta.time] and body["frame_id"] == "map"
            got = peer_delta(body["delta"])
            want = msg.delta
            pos = {k: i for i, k in enumerate(map(tuple, want.keys.tolist()))}
            assert sorted(got["keys"]) == sorted(pos)
            for k, lo, t, hits in zip(
                got["keys"], got["logodds"], got["last_time"], got["channels"]["hits"], strict=True
            ):
                i = pos[k]
                ref = float(want.logodds[i])
                assert math.isnan(lo) == math.isnan(ref)
                if not math.isnan(ref):
                    assert (lo >= 0) == (ref >= 0) and abs(lo - ref) <= 2.0**-5
                assert abs(t - want.last_time[i]) <= 5e-4
                if round(want.last_time[i] * 1000) / 1000.0 == want.last_time[i]:
                    assert t == want.last_time[i]  # whole milliseconds travel exactly
                assert hits == want.channels["hits"][i]
            if msg.free_summary is not None and len(msg.free_summary):
                level, cells = got["summary"]
                assert level == 2
                assert sorted(cells) == sorted(map(tuple, msg.free_summary.keys.tolist()))
