"""Fuzz test: random and mutated frames (COLONY_FUZZ_CASES, `make fuzz` runs 100,000); the decoder
raises only ProtocolErrors."""

from __future__ import annotations

import os
import random
import time
from collections import Counter
from collections.abc import Callable

import msgpack
import numpy as np

from protocol import fields
from protocol.auth import compute_tag
from protocol.codec import COMPRESSION_ZSTD, MAGIC, PREFIX, decode, encode
from protocol.deltacodec import encode_delta, summarise_free
from protocol.errors import ProtocolError
from protocol.limits import Limits
from protocol.messages import MESSAGE_TYPES
from tests.protocol.helpers import KEY, make_delta, sample_messages

#: Frames per run: a quick default; `make fuzz` sets COLONY_FUZZ_CASES=100000 for the full run.
N_CASES = int(os.environ.get("COLONY_FUZZ_CASES", "10000"))
#: Tight limits so that a mutation that survives reaches the limit checks quickly.
LIMITS = Limits(
    max_message_bytes=1 << 20, max_body_bytes=1 << 20, max_voxels=200_000, max_list=4096
)


def _frame(
    mtype: int, body: bytes, *, compress: bool, key: bytes | None, origin: str = "robot-1"
) -> bytes:
    flags = (COMPRESSION_ZSTD << 1 if compress else 0) | (1 if key else 0)
    if compress:
        body = fields.compress(body)
    frame = PREFIX.pack(MAGIC, 1, mtype, flags, 0) + msgpack.packb(
        [origin, 3, 41, 1.5, body], use_bin_type=True
    )
    return frame + compute_tag(key, frame) if key else frame


def _random_value(r: random.Random) -> object:
    pick = r.randrange(9)
    if pick == 0:
        return r.randrange(-(2**63), 2**64)
    if pick == 1:
        return r.choice([0.0, -1.0, 1e300, float("nan"), float("inf"), r.random()])
    if pick == 2:
        return r.randbytes(r.randrange(0, 40))
    if pick == 3:
        return "".join(r.choice("ab/*$#é\x00") for _ in range(r.randrange(0, 10)))
    if pick == 4:
        return [_random_value(r) for _ in range(r.randrange(0, 4))] if r.random() < 0.5 else []
    if pick == 5:
        return {"k": r.randrange(10)}
    if pick == 6:
        return None
    if pick == 7:
        return r.random() < 0.5
    return r.randrange(0, 300)


def _mutate_bytes(r: random.Random, data: bytes) -> bytes:
    b = bytearray(data)
    for _ in range(r.randrange(1, 5)):
        op = r.randrange(6)
        if not b:
            b.extend(r.randbytes(r.randrange(1, 8)))
            continue
        i = r.randrange(len(b))
        if op == 0:
            b[i] ^= 1 << r.randrange(8)
        elif op == 1:
            b[i] = r.choice([0x00, 0xFF, 0x7F, 0x80, 0xC1, 0xDD, 0xDF, 0xC6, r.randrange(256)])
        elif op == 2:
            del b[i : i + r.randrange(1, 16)]
        elif op == 3:
            b[i:i] = r.randbytes(r.randrange(1, 16))
        elif op == 4:
            j = r.randrange(len(b))
            b[i:i] = b[j : j + r.randrange(1, 32)]
        else:
            del b[i:]
    return bytes(b)


def _mutate_structure(r: random.Random, obj: object, depth: int = 0) -> object:
    """Replace, drop or add one field somewhere inside a msgpack map/list."""
    if isinstance(obj, dict) and obj:
        key = r.choice(list(obj))
        out = dict(obj)
        op = r.randrange(4)
        if op == 0:
            del out[key]
        elif op == 1 or depth > 3:
            out[key] = _random_value(r)
        elif op == 2:
            out[key] = _mutate_structure(r, out[key], depth + 1)
        else:
            out[r.choice(["extra", key + "_", "v"])] = _random_value(r)
        return out
    if isinstance(obj, list) and obj:
        out = list(obj)
        i = r.randrange(len(out))
        op = r.randrange(3)
        if op == 0:
            del out[i]
        elif op == 1 or depth > 3:
            out[i] = _random_value(r)
        else:
            out[i] = _mutate_structure(r, out[i], depth + 1)
        return out
    if isinstance(obj, bytes):
        return _mutate_bytes(r, obj)
    return _random_value(r)


def test_fuzz_decoder_raises_only_protocol_errors() -> None:
    r = random.Random(20261122)
    rng = np.random.default_rng(5)
    messages = sample_messages(rng)
    frames = [encode(m, compression=c) for m in messages for c in ("zstd", "none")]
    signed = [encode(m, key=KEY) for m in messages]
    bodies = [
        (type(m).TYPE, msgpack.unpackb(fields.pack(_plain_body(m)), raw=False)) for m in messages
    ]
    delta_blobs = [
        encode_delta(make_delta(rng, n, channels=bool(n % 2)), block_shift=2 + n % 3)
        for n in (1, 7, 40, 90, 300)
    ]
    summarised = make_delta(rng, 200, channels=False, spread=10)
    free = summarised.logodds < 0
    delta_blobs.append(
        encode_delta(summarised.select(~free), summary=summarise_free(summarised, 1))
    )

    def random_bytes() -> tuple[bytes, bytes | None]:
        head = r.choice(
            [
                b"",
                MAGIC,
                MAGIC + b"\x01",
                PREFIX.pack(MAGIC, 1, r.randrange(1, 10), r.randrange(4), 0),
            ]
        )
        return head + r.randbytes(r.randrange(0, 200)), None

    def mutated_frame() -> tuple[bytes, bytes | None]:
        return _mutate_bytes(r, r.choice(frames)), None

    def mutated_signed() -> tuple[bytes, bytes | None]:
        return _mutate_bytes(r, r.choice(signed)), KEY

    def mutated_body() -> tuple[bytes, bytes | None]:
        mtype, body = r.choice(bodies)
        raw = fields.pack(body)
        key = KEY if r.random() < 0.2 else None
        return _frame(mtype, _mutate_bytes(r, raw), compress=r.random() < 0.5, key=key), key

    def mutated_fields() -> tuple[bytes, bytes | None]:
        mtype, body = r.choice(bodies)
        if r.random() < 0.1:
            mtype = r.choice(list(MESSAGE_TYPES))
        raw = msgpack.packb(_mutate_structure(r, body), use_bin_type=True)
        return _frame(mtype, raw, compress=r.random() < 0.3, key=None), None

    def mutated_delta() -> tuple[bytes, bytes | None]:
        blob = r.choice(delta_blobs)
        if r.random() < 0.5:
            blob = _mutate_bytes(r, blob)
        else:
            blob = msgpack.packb(
                _mutate_structure(r, msgpack.unpackb(blob, raw=False)), use_bin_type=True
            )
        body = fields.pack({"frame_id": "map", "part": 0, "parts": 1, "delta": blob})
        return _frame(3, body, compress=False, key=None), None

    generators: list[Callable[[], tuple[bytes, bytes | None]]] = [
        random_bytes,
        mutated_frame,
        mutated_signed,
        mutated_body,
        mutated_fields,
        mutated_delta,
        mutated_delta,
    ]
    outcomes: Counter[str] = Counter()
    crashes: list[tuple[bytes, BaseException]] = []
    start = time.process_time()  # CPU time: robust to other processes sharing the machine
    for _ in range(N_CASES):
        data, key = r.choice(generators)()
        try:
            decode(data, key=key, limits=LIMITS)
            outcomes["accepted"] += 1
        except ProtocolError as exc:
            outcomes[type(exc).__name__] += 1
        except Exception as exc:  # noqa: BLE001 - the point of the test
            crashes.append((data, exc))
    elapsed = time.process_time() - start
    assert not crashes, (
        f"{len(crashes)} crashes, first: {crashes[0][1]!r} on {crashes[0][0][:80].hex()}"
    )
    assert sum(outcomes.values()) == N_CASES
    assert outcomes["accepted"] > 0 and len(outcomes) >= 6, outcomes
    assert elapsed < 60, f"fuzz run took {elapsed:.1f} s of CPU time"


def _plain_body(msg) -> dict:
    from protocol.codec import _body

    return _body(msg)
