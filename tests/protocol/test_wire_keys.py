"""The delta codec's compiled key columns (`voxel.kernels.wire_keys`) against its numpy path:
the same bytes, byte for byte, on real and random deltas."""

from __future__ import annotations

import threading
from collections.abc import Callable

import msgpack
import numpy as np
import pytest

from colonyd.bench.wire import scenarios
from protocol.deltacodec import (
    decode_delta,
    decode_delta_with_summary,
    encode_delta,
    summarise_free,
    wire_order,
)
from protocol.errors import ProtocolError
from tests.protocol.helpers import assert_delta_close, make_delta
from tests.shared import SHARED_DATA
from voxel import kernels
from voxel.delta import Delta
from voxel.errors import DeltaError
from voxel.grid import VoxelGrid
from voxel.keys import KEY_MAX, KEY_MIN


@pytest.fixture
def both(monkeypatch: pytest.MonkeyPatch) -> Callable[[Callable[[], bytes]], bytes]:
    """Runs an encoding on the compiled path and on the numpy path; asserts the same bytes."""
    pytest.importorskip("numba")
    monkeypatch.setattr(kernels, "_loading", kernels._Loading())  # no background mode here

    def run(encode: Callable[[], bytes]) -> bytes:
        monkeypatch.setattr(kernels._switch, "on", True)
        assert kernels.wire_keys() is not None
        compiled = encode()
        monkeypatch.setattr(kernels._switch, "on", False)
        assert kernels.wire_keys() is None
        numpy = encode()
        monkeypatch.setattr(kernels._switch, "on", True)
        assert compiled == numpy
        return compiled

    return run


@pytest.fixture(scope="module")
def kitchen() -> list[tuple[Delta, np.ndarray]]:
    """The first real kitchen frames' deltas as the wire bench makes them, with each voxel's
    value before (a peer's replica)."""
    found = [s for s in scenarios(SHARED_DATA) if s.name == "redkitchen50_0.05"]
    if not found:
        pytest.skip(f"no redkitchen-50 frames under {SHARED_DATA}")
    grid, mirror = VoxelGrid(0.05), VoxelGrid(0.05)
    out = []
    for i, frame in enumerate(found[0].frames()):
        if i == 4:
            break
        version = grid.version
        frame.integrate(grid, 1_700_000_000.0 + 0.1 * i)
        delta = grid.delta_since(version)
        out.append((delta, mirror.logodds_at_keys(delta.keys)))
        mirror.apply(delta)
    # and the whole map at once, as a snapshot sends it
    out.append((grid.delta_since(0), np.full(len(grid.delta_since(0)), np.nan, np.float32)))
    return out


@pytest.mark.parametrize("block_shift", [2, 3, 4])
def test_real_kitchen_deltas_encode_to_the_same_bytes_on_both_paths(
    both: Callable[[Callable[[], bytes]], bytes],
    kitchen: list[tuple[Delta, np.ndarray]],
    block_shift: int,
) -> None:
    for delta, prev in kitchen:
        for p in (None, prev):
            data = both(
                lambda d=delta, p=p: encode_delta(d, prev_logodds=p, block_shift=block_shift)
            )
            assert_delta_close(delta, decode_delta(data))
        summary = summarise_free(delta, 2)
        data = both(lambda d=delta, s=summary: encode_delta(d, summary=s, block_shift=block_shift))
        back, summary_back = decode_delta_with_summary(data)
        assert_delta_close(delta, back)
        assert summary_back is not None
        assert np.array_equal(
            np.sort(summary_back.keys.view("i8,i8,i8"), axis=0),
            np.sort(summary.keys.view("i8,i8,i8"), axis=0),
        )


@pytest.mark.parametrize("block_shift", [2, 3, 4])
@pytest.mark.parametrize("seed", range(6))
def test_random_deltas_encode_to_the_same_bytes_on_both_paths(
    both: Callable[[Callable[[], bytes]], bytes], block_shift: int, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    delta = make_delta(
        rng, [1, 40, 3000, 20000, 5000, 700][seed], spread=[1, 5, 40, 30, 2000, 9][seed]
    )
    prev = rng.uniform(-2, 2, len(delta)).astype(np.float32)
    prev[rng.random(len(delta)) < 0.3] = np.nan
    for p in (None, prev):
        data = both(lambda p=p: encode_delta(delta, prev_logodds=p, block_shift=block_shift))
        assert_delta_close(delta, decode_delta(data))
    assert np.array_equal(np.sort(wire_order(delta, prev)), np.arange(len(delta)))


def test_keys_in_wire_order_already_and_an_empty_delta(
    both: Callable[[Callable[[], bytes]], bytes],
) -> None:
    keys = np.stack(np.meshgrid(*[np.arange(-40, -8)] * 3, indexing="ij"), -1).reshape(-1, 3)
    lo = np.full(len(keys), 0.5, np.float32)
    delta = Delta(0.1, 0, 1, keys, lo, np.full(len(keys), 2.0), time=2.0)
    assert_delta_close(delta, decode_delta(both(lambda: encode_delta(delta, block_shift=2))))
    empty = Delta(0.1, 0, 1, keys[:0], lo[:0], np.zeros(0), time=2.0)
    assert len(decode_delta(both(lambda: encode_delta(empty)))) == 0


def test_keys_at_both_ends_of_the_key_range_take_the_numpy_path(
    both: Callable[[Callable[[], bytes]], bytes],
) -> None:
    keys = np.array([[KEY_MAX, KEY_MAX, KEY_MAX], [KEY_MIN, KEY_MIN, KEY_MIN], [0, 5, -3]])
    lo = np.array([1.0, -1.0, np.nan], np.float32)
    delta = Delta(0.1, 0, 1, keys, lo, np.full(3, 2.0), time=2.0)
    assert_delta_close(delta, decode_delta(both(lambda: encode_delta(delta))))


@pytest.mark.parametrize("jit", ["1", "0"])
def test_duplicate_keys_are_refused_on_both_paths(
    monkeypatch: pytest.MonkeyPatch, jit: str
) -> None:
    pytest.importorskip("numba")
    monkeypatch.setattr(kernels, "_loading", kernels._Loading())
    monkeypatch.setattr(kernels._switch, "on", jit == "1")
    keys = np.array([[1, 2, 3], [40, 9, 9], [1, 2, 3], [0, 0, 0]])
    delta = Delta(0.05, 0, 1, keys, [0.1, 0.2, 0.3, -1.0], np.zeros(4))
    with pytest.raises(DeltaError, match="unique"):
        encode_delta(delta)


def test_in_background_mode_the_codec_waits_for_warm_codec_and_never_starts_the_loading(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    pytest.importorskip("numba")
    monkeypatch.setattr(kernels._switch, "on", True)
    monkeypatch.setattr(kernels, "_codec_compiled", {})
    monkeypatch.setattr(kernels, "_loading", kernels._Loading())
    kernels.load_in_background()
    delta = make_delta(np.random.default_rng(3), 2000)
    before = {t.name for t in threading.enumerate()}
    numpy = encode_delta(delta)  # a newcomer's first decode must not share the core with numba
    decoded = decode_delta(numpy)
    assert kernels.wire_keys() is None and kernels.wire_voxels() is None
    assert "keys" not in kernels._codec_compiled
    assert {t.name for t in threading.enumerate()} <= before  # no loading thread either
    assert kernels.warm_codec()  # the daemon's warm-up thread loads them
    assert kernels.wire_keys() is not None and kernels.wire_voxels() is not None
    assert encode_delta(delta) == numpy
    again = decode_delta(numpy)
    assert np.array_equal(again.keys, decoded.keys)


def _decoded(data: bytes, monkeypatch: pytest.MonkeyPatch, jit: str) -> Delta | str:
    monkeypatch.setattr(kernels._switch, "on", jit == "1")
    try:
        return decode_delta(data)
    except ProtocolError as exc:
        return f"{type(exc).__name__}: {exc}"
    finally:
        monkeypatch.setattr(kernels._switch, "on", True)


def _same_decoding(data: bytes, monkeypatch: pytest.MonkeyPatch) -> Delta | str:
    """The decoding of `data` (or its error) on the compiled path, asserted equal to numpy's."""
    pytest.importorskip("numba")
    monkeypatch.setattr(kernels, "_loading", kernels._Loading())
    assert kernels.warm_codec()
    compiled = _decoded(data, monkeypatch, "1")
    numpy = _decoded(data, monkeypatch, "0")
    if isinstance(compiled, str) or isinstance(numpy, str):
        assert compiled == numpy
        return compiled
    assert np.array_equal(compiled.keys, numpy.keys)
    assert np.array_equal(compiled.logodds, numpy.logodds, equal_nan=True)
    assert np.array_equal(compiled.last_time, numpy.last_time, equal_nan=True)
    return compiled


@pytest.mark.parametrize("block_shift", [2, 3, 4])
def test_real_and_random_deltas_decode_the_same_on_both_paths(
    monkeypatch: pytest.MonkeyPatch, kitchen: list[tuple[Delta, np.ndarray]], block_shift: int
) -> None:
    rng = np.random.default_rng(block_shift)
    cases = [*kitchen, (make_delta(rng, 20000, spread=30), None), (make_delta(rng, 50), None)]
    for delta, prev in cases:
        data = encode_delta(delta, prev_logodds=prev, block_shift=block_shift)
        back = _same_decoding(data, monkeypatch)
        assert isinstance(back, Delta)
        assert_delta_close(delta, back)


@pytest.mark.parametrize(
    ("column", "change"),
    [
        (5, "flip"),  # a bitmap bit more or less than the block's count
        (6, "zero"),  # a zero gap after a block's first offset
        (6, "big"),  # an offset beyond the block
    ],
)
def test_hostile_bitmaps_and_gaps_are_refused_alike_on_both_paths(
    monkeypatch: pytest.MonkeyPatch, column: int, change: str
) -> None:
    rng = np.random.default_rng(7)
    dense = np.stack(np.meshgrid(*[np.arange(0, 12)] * 3, indexing="ij"), -1).reshape(-1, 3)
    sparse = rng.integers(-3000, 3000, size=(400, 3))
    keys = np.unique(np.r_[dense, sparse], axis=0)
    lo = np.where(rng.random(len(keys)) < 0.5, 1.0, -1.0).astype(np.float32)
    # and in each section a sparse block of several voxels
    runs = np.array([[x, x, z] for x in (5000, 6000) for z in range(10)])
    keys = np.r_[keys, runs]
    lo = np.r_[lo, np.repeat(np.array([1.0, -1.0], np.float32), 10)]
    body = msgpack.unpackb(encode_delta(Delta(0.1, 0, 1, keys, lo, np.zeros(len(keys)))), raw=False)
    for sec in body["sec"]:
        raw = bytearray(sec[column])
        assert raw, "the test delta has both dense and sparse blocks in every section"
        if change == "flip":
            raw[len(raw) // 2] ^= 0x10
        elif change == "zero":
            counts = np.frombuffer(sec[4], dtype="<u2")
            sparse_counts = counts[counts < (1 << 12) // 16]
            second = int(np.argmax(sparse_counts > 1))
            at = int(sparse_counts[:second].sum()) + 1  # a block's second offset
            raw[2 * at : 2 * at + 2] = b"\0\0"
        else:
            raw[-2:] = (60000).to_bytes(2, "little")
        sec[column] = bytes(raw)
    out = _same_decoding(msgpack.packb(body, use_bin_type=True), monkeypatch)
    assert isinstance(out, str), "a corrupted body must be refused"
