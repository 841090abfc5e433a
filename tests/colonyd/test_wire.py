"""Wire format: round trip, and every hostile input rejected with a reason."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
import zstandard

from colonyd.errors import WireError
from colonyd.wire import MAGIC, VERSION, Codec
from voxel.delta import Delta


def delta(n: int = 100) -> Delta:
    rng = np.random.default_rng(0)
    return Delta(0.1, 3, 4, rng.integers(-50, 50, (n, 3)), rng.normal(size=n).astype(np.float32),
                 np.full(n, 12.5), {"hits": np.arange(n, dtype=np.uint16),
                                    "colour": np.zeros((n, 3), np.uint8)}, time=12.5)


def test_delta_round_trip_is_exact():
    codec = Codec()
    d = delta()
    msg = codec.decode(codec.encode({"t": "delta", "o": "a", "e": 1, "s": 4, "p": 3, "delta": d}))
    got = msg["delta"]
    assert (msg["o"], msg["s"], msg["p"]) == ("a", 4, 3)
    np.testing.assert_array_equal(got.keys, d.keys)
    np.testing.assert_array_equal(got.logodds, d.logodds)
    np.testing.assert_array_equal(got.channels["hits"], d.channels["hits"])
    assert got.channels["colour"].shape == (100, 3)


def frame(body: object, version: int = VERSION) -> bytes:
    return MAGIC + bytes([version, 0]) + zstandard.ZstdCompressor().compress(
        msgpack.packb(body, use_bin_type=True))


@pytest.mark.parametrize(
    ("data", "reason"),
    [
        (b"", "bad-magic"),
        (b"nonsense bytes", "bad-magic"),
        (MAGIC + bytes([9, 0]) + b"x", "bad-version"),
        (MAGIC + bytes([VERSION, 0]) + b"not zstd", "bad-compression"),
        (frame([1, 2, 3]), "bad-kind"),
        (frame({"t": "evil"}), "bad-kind"),
        (frame({"t": "delta", "delta": {"n": 5}}), "bad-delta"),
        (frame({"t": "delta", "delta": {"n": 2, "r": 0.1, "f": 0, "v": 1, "tm": 0.0,
                                        "k": b"\x00" * 47, "l": b"", "lt": b""}}), "bad-delta"),
        (frame({"t": "delta", "delta": {"n": 1, "r": -1.0, "f": 0, "v": 1, "tm": 0.0}}), "bad-delta"),
        (frame({"t": "delta", "delta": {"n": 0, "r": 0.1, "f": 0, "v": 1, "tm": 0.0, "k": b"",
                                        "l": b"", "lt": b"", "c": {"nope": [[], b""]}}}), "bad-delta"),
    ],
)
def test_hostile_input_is_rejected_with_reason(data, reason):
    with pytest.raises(WireError) as info:
        Codec().decode(data)
    assert info.value.reason == reason


def test_decompression_bomb_is_rejected_without_allocating():
    bomb = MAGIC + bytes([VERSION, 0]) + zstandard.ZstdCompressor().compress(b"\x00" * (8 << 20))
    with pytest.raises(WireError, match="expected at most 1048576 bytes") as info:
        Codec(max_bytes=1 << 20).decode(bomb)
    assert info.value.reason == "oversized"


def test_colony_key_authenticates():
    signed = Codec("secret").encode({"t": "hb", "a": "x"})
    assert Codec("secret").decode(signed)["a"] == "x"
    with pytest.raises(WireError, match="signature") as info:
        Codec("other").decode(signed)
    assert info.value.reason == "bad-signature"
    with pytest.raises(WireError) as info:
        Codec("secret").decode(Codec().encode({"t": "hb", "a": "x"}))
    assert info.value.reason == "unauthenticated"
    tampered = bytearray(signed)
    tampered[-1] ^= 1
    with pytest.raises(WireError, match="signature"):
        Codec("secret").decode(bytes(tampered))


def test_encoding_from_many_threads_at_once():
    import threading

    codec, d, errors = Codec(), delta(5000), []

    def work() -> None:
        try:
            for _ in range(30):
                msg = codec.decode(codec.encode({"t": "delta", "o": "a", "delta": d}))
                assert len(msg["delta"]) == 5000
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=work) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
