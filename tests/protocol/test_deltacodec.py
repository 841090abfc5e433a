"""Tests of protocol.deltacodec: round trips, significance, budgets, splits, hostile bodies."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import fields
from protocol.deltacodec import (
    UNKNOWN_CODE,
    Tier,
    decode_delta,
    decode_delta_with_summary,
    dequantise,
    encode_delta,
    encoded_size,
    fit_delta,
    quantise,
    quantum_exponent,
    significance,
    split_delta,
    summarise_free,
)
from protocol.errors import (
    MalformedError,
    OversizedError,
    ProtocolError,
    RangeError,
    UnknownTypeError,
    VersionError,
)
from protocol.limits import DEFAULT_LIMITS, Limits
from tests.protocol.helpers import assert_delta_close, make_delta
from voxel.delta import Delta
from voxel.keys import KEY_MAX, KEY_MIN, pack


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1)


def test_round_trip_with_channels(rng: np.random.Generator) -> None:
    delta = make_delta(rng, 500)
    assert_delta_close(delta, decode_delta(encode_delta(delta)))


@pytest.mark.parametrize("block_shift", [2, 3, 4])
def test_round_trip_dense_and_sparse_blocks(rng: np.random.Generator, block_shift: int) -> None:
    dense = np.stack(np.meshgrid(*[np.arange(-20, 12)] * 3, indexing="ij"), -1).reshape(-1, 3)
    sparse = rng.integers(-5000, 5000, size=(300, 3))
    keys = np.unique(np.r_[dense, sparse], axis=0)
    lo = np.where(rng.random(len(keys)) < 0.3, 1.2, -0.4).astype(np.float32)
    delta = Delta(0.1, 0, 1, keys, lo, np.full(len(keys), 5.0), time=5.0)
    out = decode_delta(encode_delta(delta, block_shift=block_shift))
    assert_delta_close(delta, out)


def test_extreme_keys_round_trip() -> None:
    keys = np.array(
        [
            [KEY_MIN, KEY_MIN, KEY_MIN],
            [KEY_MAX, KEY_MAX, KEY_MAX],
            [KEY_MIN, 0, KEY_MAX],
            [-1, -1, -1],
        ]
    )
    delta = Delta(0.05, 0, 1, keys, [0.5, -0.5, np.nan, 3.0], [1.0, 2.0, np.nan, 4.0], time=4.0)
    assert_delta_close(delta, decode_delta(encode_delta(delta)))


def test_empty_delta_round_trips() -> None:
    delta = Delta(0.05, 4, 9, np.zeros((0, 3)), [], [], time=3.0)
    out = decode_delta(encode_delta(delta))
    assert len(out) == 0 and (out.from_version, out.to_version) == (4, 9)


def test_keys_out_of_range_are_refused() -> None:
    delta = Delta(0.05, 0, 1, [[KEY_MAX + 1, 0, 0]], [0.1], [0.0])
    with pytest.raises(RangeError, match="delta keys must lie in"):
        encode_delta(delta)


def test_duplicate_keys_are_refused() -> None:
    delta = Delta(0.05, 0, 1, [[1, 2, 3], [1, 2, 3]], [0.1, 0.2], [0.0, 0.0])
    with pytest.raises(ValueError, match="unique"):
        encode_delta(delta)


voxel_keys = st.lists(
    st.tuples(*[st.integers(-300, 300)] * 3), min_size=0, max_size=300, unique=True
)


@settings(max_examples=60, deadline=None)
@given(
    keys=voxel_keys,
    seed=st.integers(0, 2**32 - 1),
    scale=st.sampled_from([0.01, 0.5, 3.5, 40.0, 1500.0]),
    block_shift=st.sampled_from([2, 3, 4]),
)
def test_property_round_trip(
    keys: list[tuple[int, int, int]], seed: int, scale: float, block_shift: int
) -> None:
    rng = np.random.default_rng(seed)
    n = len(keys)
    lo = (rng.uniform(-1, 1, n) * scale).astype(np.float32)
    lo[rng.random(n) < 0.1] = np.nan
    lo[rng.random(n) < 0.05] = -1e-6  # tiny negatives stay free
    times = 100.0 + rng.integers(-50_000, 50_000, n) / 1000.0
    delta = Delta(
        0.1,
        3,
        4,
        np.array(keys, dtype=np.int64).reshape(-1, 3),
        lo,
        times,
        time=100.0,
        channels={"hits": rng.integers(0, 60000, n)},
    )
    out = decode_delta(encode_delta(delta, block_shift=block_shift))
    q = 2.0 ** quantum_exponent(lo)
    assert_delta_close(delta, out, q=q)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-2000, 2000, width=32) | st.just(float("nan")), max_size=200))
def test_property_quantisation_keeps_state(values: list[float]) -> None:
    lo = np.array(values, dtype=np.float32)
    q = quantum_exponent(lo)
    back = dequantise(quantise(lo, q), q)
    np.testing.assert_array_equal(np.isnan(back), np.isnan(lo))
    finite = ~np.isnan(lo)
    np.testing.assert_array_equal(back[finite] >= 0, lo[finite] >= 0)
    assert np.all(np.abs(back[finite] - lo[finite]) <= 2.0**q + 1e-6)


def test_octomap_range_quantum_is_one_32nd() -> None:
    assert quantum_exponent(np.array([-1.99, 3.47], dtype=np.float32)) == -5
    assert quantise(np.array([np.nan], dtype=np.float32), -5)[0] == UNKNOWN_CODE


def test_grid_quantum_is_used_for_multiples_of_one_32nd() -> None:
    grid_like = np.array([-63, -1, 0, 5, 127], dtype=np.float32) / 32  # small values, on the grid
    assert quantum_exponent(grid_like) == -5  # the size rule alone would pick a finer quantum
    assert quantum_exponent(np.array([0.25, np.nan], dtype=np.float32)) == -5
    assert quantum_exponent(np.array([128 / 32], dtype=np.float32)) == -4  # beyond 127/32
    assert quantum_exponent(np.array([0.1], dtype=np.float32)) == -10  # off the grid: size rule


def _grid_like_delta(rng: np.random.Generator, n: int = 3000, time: float = 0.0) -> Delta:
    """A delta as `voxel.grid` produces it: log-odds on 1/32, times whole ms (k / 1000.0)."""
    keys = np.unique(rng.integers(-200, 200, size=(n, 3)), axis=0)
    m = keys.shape[0]
    lo = (rng.integers(-64, 112, m) / 32).astype(np.float32)  # OctoMap clamping [-1.99, 3.48]
    lo[rng.random(m) < 0.05] = np.nan
    ms = rng.integers(1_700_000_000_000, 1_700_000_900_000, m)
    first_ms = ms - rng.integers(0, 3_600_000, m)
    channels = {
        "first_time": first_ms / 1000.0,
        "hits": rng.integers(0, 65536, m).astype(np.uint16),
        "misses": rng.integers(0, 65536, m).astype(np.uint16),
        "colour": rng.integers(0, 256, (m, 3)).astype(np.uint8),
        "normal": rng.normal(size=(m, 3)).astype(np.float32),
        "class_ids": rng.integers(-1, 50, (m, 4)).astype(np.int16),
        "class_probs": rng.random((m, 4)).astype(np.float32),
        "scalar:temperature": rng.normal(20, 5, m).astype(np.float32),
        "surface": rng.integers(-127, 128, (m, 3)).astype(np.int8),
    }
    return Delta(0.05, 7, 9, keys, lo, ms / 1000.0, channels=channels, time=time)


@pytest.mark.parametrize("ref", [1_700_000_450.0, 1_700_000_450.0007, 1_700_000_450.125, 0.0, -3.5])
def test_grid_like_delta_round_trips_bit_exactly(rng: np.random.Generator, ref: float) -> None:
    delta = _grid_like_delta(rng, time=ref)
    out = decode_delta(encode_delta(delta))
    ia, ib = np.argsort(pack(delta.keys)), np.argsort(pack(out.keys))
    np.testing.assert_array_equal(out.keys[ib], delta.keys[ia])
    assert out.logodds.dtype == np.float32
    assert np.array_equal(out.logodds[ib], delta.logodds[ia], equal_nan=True)
    assert out.last_time.tobytes() != b"" and np.array_equal(
        out.last_time[ib].view(np.int64), delta.last_time[ia].view(np.int64)
    )  # bit for bit
    assert set(out.channels) == set(delta.channels)
    for name, values in delta.channels.items():
        got = out.channels[name][ib]
        want = values[ia].astype(got.dtype)
        assert got.tobytes() == want.tobytes(), name
    assert (out.time, out.from_version, out.to_version) == (ref, 7, 9)


def test_grid_like_parts_round_trip_bit_exactly(rng: np.random.Generator) -> None:
    delta = _grid_like_delta(rng, n=20_000, time=1_700_000_000.0)
    parts = [decode_delta(encode_delta(p)) for p in split_delta(delta, 20_000)]
    assert len(parts) > 1
    keys = np.concatenate([p.keys for p in parts])
    ia, ib = np.argsort(pack(delta.keys)), np.argsort(pack(keys))
    lo = np.concatenate([p.logodds for p in parts])
    first = np.concatenate([p.channels["first_time"] for p in parts])
    assert np.array_equal(lo[ib], delta.logodds[ia], equal_nan=True)
    assert first[ib].tobytes() == delta.channels["first_time"][ia].tobytes()


def test_times_are_integer_milliseconds_from_the_rounded_reference() -> None:
    from protocol.deltacodec import reference_ms

    assert reference_ms(1_700_000_000.0004) == 1_700_000_000_000
    assert reference_ms(-2.5) == -2500
    times = np.array([1_700_000_000.001, 1_699_999_999.999, 1_700_000_000.0004, np.nan])
    delta = Delta(
        0.1,
        0,
        1,
        np.arange(12).reshape(4, 3),
        np.zeros(4, np.float32),
        times,
        time=1_700_000_000.0004,
    )
    out = decode_delta(encode_delta(delta))
    order = np.argsort(pack(out.keys))
    want = [1_700_000_000.001, 1_699_999_999.999, 1_700_000_000.0]
    assert out.last_time[order][:3].tolist() == want
    assert np.isnan(out.last_time[order][3])


def test_significance_tiers() -> None:
    lo = np.array([1.0, 1.0, -1.0, np.nan, -1.0, -1.0, 2.0], dtype=np.float32)
    prev = np.array([-1.0, 0.5, 0.5, 1.0, np.nan, -0.4, np.nan], dtype=np.float32)
    delta = Delta(0.1, 0, 1, np.arange(21).reshape(7, 3), lo, np.zeros(7))
    tiers = significance(delta, prev)
    assert tiers.tolist() == [
        Tier.OCCUPIED_NEW,
        Tier.OCCUPIED,
        Tier.CLEARED,
        Tier.UNKNOWN,
        Tier.FREE_NEW,
        Tier.FREE,
        Tier.OCCUPIED_NEW,
    ]
    assert significance(delta).tolist() == [1, 1, 5, 3, 5, 5, 1]
    with pytest.raises(ValueError, match="one value per voxel"):
        significance(delta, prev[:3])


def test_wire_order_is_surfaces_first(rng: np.random.Generator) -> None:
    delta = make_delta(rng, 400, channels=False)
    prev = np.where(rng.random(len(delta)) < 0.5, np.nan, -0.3).astype(np.float32)
    out = decode_delta(encode_delta(delta, prev_logodds=prev))
    state = np.where(np.isnan(out.logodds), 1, np.where(out.logodds >= 0, 0, 2))
    # occupied, then unknown, then free: tiers 0,1 | 3 | 4,5 (no clearings: prev never occupied)
    assert np.all(np.diff(state) >= 0)
    body = msgpack.unpackb(encode_delta(delta, prev_logodds=prev))
    assert [s[0] for s in body["sec"]] == sorted(s[0] for s in body["sec"])


def test_bytes_per_voxel_on_dense_free_space() -> None:
    """A free-space cone like a depth frame's: far below one byte per changed voxel."""
    g = np.stack(
        np.meshgrid(np.arange(0, 64), np.arange(-32, 32), np.arange(-16, 16), indexing="ij"), -1
    ).reshape(-1, 3)
    inside = np.abs(g[:, 1]) <= g[:, 0] // 2
    keys = g[inside]
    lo = np.full(len(keys), -0.405, dtype=np.float32)
    lo[keys[:, 0] == 63] = 0.85
    delta = Delta(0.05, 0, 1, keys, lo, np.full(len(keys), 7.0), time=7.0)
    size = encoded_size(delta)
    assert size / len(delta) < 0.1


def test_summary_covers_free_voxels(rng: np.random.Generator) -> None:
    delta = make_delta(rng, 800, channels=False, spread=20)
    summary = summarise_free(delta, 2)
    free = delta.keys[delta.logodds < 0]
    cells = {tuple(c) for c in summary.keys.tolist()}
    assert all(tuple(k) in cells for k in (free >> 2).tolist())
    assert np.all(summary.logodds < 0)
    expanded = summary.expand(exclude=delta.keys[~(delta.logodds < 0)])
    assert np.isin(pack(free), pack(expanded.keys)).all()
    assert len(expanded) <= summary.expanded_count
    with pytest.raises(OversizedError, match="expands to at most"):
        summary.expand(max_voxels=10)


def test_fit_delta_meets_budget_with_summary(rng: np.random.Generator) -> None:
    g = np.stack(np.meshgrid(*[np.arange(0, 40)] * 3, indexing="ij"), -1).reshape(-1, 3)
    keys = g[rng.random(len(g)) < 0.5]
    lo = np.where(keys[:, 2] == 0, 1.5, -rng.uniform(0.1, 2.0, len(keys))).astype(np.float32)
    delta = Delta(0.1, 0, 1, keys, lo, np.full(len(keys), 1.0), time=1.0)
    full = encoded_size(delta)
    budget = full // 4
    exact, summary = fit_delta(delta, budget)
    assert summary is not None
    assert encoded_size(exact, summary=summary) <= budget
    assert exact.occupied.all() and exact.occupied.sum() == delta.occupied.sum()
    _, summary2 = decode_delta_with_summary(encode_delta(exact, summary=summary))
    assert summary2 is not None and summary2.level == summary.level
    np.testing.assert_array_equal(np.sort(pack(summary2.keys)), np.sort(pack(summary.keys)))
    # a generous budget keeps everything
    same, none = fit_delta(delta, full + 10)
    assert none is None and same is delta


def test_split_parts_fit_and_decode_independently(rng: np.random.Generator) -> None:
    delta = make_delta(rng, 20_000, spread=200)
    prev = np.full(len(delta), np.nan, dtype=np.float32)
    parts = split_delta(delta, 20_000, prev_logodds=prev)
    assert len(parts) > 1
    decoded = []
    for part in parts:
        body = encode_delta(part)
        assert len(fields.compress(body)) <= 20_000
        d = decode_delta(body)
        assert (d.from_version, d.to_version) == (delta.from_version, delta.to_version)
        decoded.append(d)
    merged = Delta(
        delta.resolution,
        delta.from_version,
        delta.to_version,
        np.concatenate([d.keys for d in decoded]),
        np.concatenate([d.logodds for d in decoded]),
        np.concatenate([d.last_time for d in decoded]),
        channels={k: np.concatenate([d.channels[k] for d in decoded]) for k in delta.channels},
        time=delta.time,
    )
    assert_delta_close(delta, merged)
    # surfaces first: the first part holds occupied voxels before any free one
    assert decoded[0].occupied[: int(delta.occupied.sum()) // 2 or 1].all()
    with pytest.raises(ValueError, match="max_bytes must be"):
        split_delta(delta, 10)


# --------------------------------------------------------------------------- hostile bodies


def _body(delta: Delta | None = None) -> dict:
    delta = delta or Delta(
        0.1,
        0,
        1,
        [[0, 0, 0], [1, 2, 3], [100, -5, 7]],
        [0.5, -0.5, np.nan],
        [1.0, 1.0, 2.0],
        channels={"hits": [1, 2, 3]},
        time=2.0,
    )
    return msgpack.unpackb(encode_delta(delta))


def _decode(body: dict, limits: Limits = DEFAULT_LIMITS) -> Delta:
    return decode_delta(msgpack.packb(body, use_bin_type=True), limits)


def test_valid_reference_body_decodes() -> None:
    assert len(_decode(_body())) == 3


@pytest.mark.parametrize(
    ("mutate", "error", "match"),
    [
        (lambda b: b.update(v=2), VersionError, "codec version 1, found 2"),
        (lambda b: b.pop("res"), MalformedError, "expected field 'res'"),
        (lambda b: b.update(res="x"), MalformedError, "'res' must be float"),
        (lambda b: b.update(res=-1.0), RangeError, "resolution"),
        (lambda b: b.update(res=float("nan")), RangeError, "resolution"),
        (lambda b: b.update(bs=5), RangeError, "block shift"),
        (lambda b: b.update(q=99), RangeError, "quantum exponent"),
        (lambda b: b.update(n=10**9), OversizedError, "at most 4000000 voxels"),
        (lambda b: b.update(n=4), MalformedError, "holding n=4"),
        (lambda b: b.update(n=2), RangeError, "voxel count: expected an integer in"),
        (lambda b: b.update(to=-1), RangeError, "to_version"),
        (lambda b: b.update(time=float("inf")), RangeError, "finite time"),
        (lambda b: b.update(lo=b"\x00"), MalformedError, "log-odds: expected 3 bytes, found 1"),
        (lambda b: b.update(lo=[1, 2, 3]), MalformedError, "expected binary data"),
        (lambda b: b.update(sec=[[0] * 7] * 9), MalformedError, "at most 6 sections"),
        (lambda b: b.update(sec=["x"]), MalformedError, "expected \\[tier"),
        (lambda b: b["sec"][0].__setitem__(0, 9), RangeError, "tier"),
        (lambda b: b["sec"][0].__setitem__(3, b"\x00" * 5), MalformedError, "blocks: expected"),
        (
            lambda b: b["sec"][0].__setitem__(4, b"\x00\x00" * (len(b["sec"][0][4]) // 2)),
            RangeError,
            "voxels per block",
        ),
        (
            lambda b: b["sec"][0].__setitem__(6, b"\xff\xff" * (len(b["sec"][0][6]) // 2)),
            RangeError,
            "offsets below",
        ),
        (lambda b: b.update(tt=b"\x00" * 3), MalformedError, "8-byte entries"),
        (lambda b: b.update(ti=b"\x07\x07\x07"), RangeError, "time indices below"),
        (lambda b: b.update(ch=[["bogus", 0, b""]]), UnknownTypeError, "bogus"),
        (
            lambda b: b.update(ch=[["hits", 0, b"\x00"]]),
            MalformedError,
            "expected 6 bytes, found 1",
        ),
        (lambda b: b.update(ch=[["class_ids", 99, b""]]), RangeError, "width"),
        (lambda b: b.update(ch=[["colour", 2, b"\x00" * 6]]), RangeError, "expected width 3"),
        (lambda b: b.update(ch=[["hits", 0, b"\x00" * 6]] * 2), MalformedError, "twice"),
        (
            lambda b: b.update(ch=[["surface", 3, b"\x00" * 8 + b"\x80"]]),
            RangeError,
            "surface.*within half a voxel\\), found -128",
        ),
        (lambda b: b.update(ch=[["surface", 1, b"\x00" * 3]]), RangeError, "expected width 3"),
        (lambda b: b.update(ch=[["surface", 3, b"\x00" * 3]]), MalformedError, "expected 9 bytes"),
        (lambda b: b.update(ch=[["hits", 0, b"\x00" * 6]] * 40), OversizedError, "channels"),
        (lambda b: b.update(sum=[9, 0, 0, b"", b"", b"", b"", b"", 0]), RangeError, "level"),
        (lambda b: b.update(sum="x"), MalformedError, "summary"),
    ],
)
def test_hostile_body_rejected(mutate, error: type[ProtocolError], match: str) -> None:
    body = _body()
    mutate(body)
    with pytest.raises(error, match=match):
        _decode(body)


def test_voxels_in_two_sections_rejected() -> None:
    body = _body()
    sec = body["sec"]
    # copy the occupied section's keys over the free section's: same voxel in two sections
    occ = next(s for s in sec if s[0] == Tier.OCCUPIED)
    free = next(s for s in sec if s[0] == Tier.FREE)
    free[1:] = occ[1:]
    with pytest.raises(MalformedError, match="two sections"):
        _decode(body)


def test_blocks_out_of_order_rejected() -> None:
    keys = np.array([[0, 0, 0], [100, 0, 0]])
    body = _body(Delta(0.1, 0, 1, keys, [0.5, 0.5], [1.0, 1.0], time=1.0))
    blocks = np.frombuffer(body["sec"][0][3], dtype="<i4").reshape(3, 2).copy()
    blocks[0, 1] = -blocks[0, 1]
    body["sec"][0][3] = blocks.tobytes()
    with pytest.raises(MalformedError, match="increasing"):
        _decode(body)


def test_voxel_limit_is_enforced_before_allocation() -> None:
    g = np.stack(np.meshgrid(*[np.arange(0, 16)] * 3, indexing="ij"), -1).reshape(-1, 3)
    delta = Delta(0.1, 0, 1, g, np.full(len(g), 0.5), np.zeros(len(g)))
    data = encode_delta(delta)
    with pytest.raises(
        OversizedError, match="at most 1000 voxels \\(decoder limit\\), found n=4096"
    ):
        decode_delta(data, Limits(max_voxels=1000))
    with pytest.raises(OversizedError, match="at most 100 bytes"):
        decode_delta(data, Limits(max_body_bytes=100))


def test_not_msgpack_rejected() -> None:
    with pytest.raises(ProtocolError):
        decode_delta(b"\xc1\x00")
    with pytest.raises(MalformedError, match="msgpack map"):
        decode_delta(msgpack.packb([1, 2]))


def test_bad_block_shift_refused(rng: np.random.Generator) -> None:
    with pytest.raises(ValueError, match="block_shift must be one of"):
        encode_delta(make_delta(rng, 5), block_shift=5)


def test_summary_round_trips_in_body(rng: np.random.Generator) -> None:
    delta = make_delta(rng, 3000, channels=False, spread=30)
    summary = summarise_free(delta, 1)
    exact = delta.select(~(delta.logodds < 0))
    out, back = decode_delta_with_summary(encode_delta(exact, summary=summary))
    assert back is not None and back.level == 1 and len(back) == len(summary)
    np.testing.assert_array_equal(np.sort(pack(back.keys)), np.sort(pack(summary.keys)))
    assert np.all(back.logodds < 0)
    assert back.time == pytest.approx(summary.time, abs=1e-3)
    assert_delta_close(exact, out)


@pytest.mark.parametrize("bs", [2, 3, 4])
def test_dense_deltas_are_ordered_by_placement_as_a_sort_orders_them(bs: int) -> None:
    # a snapshot's voxels fill their blocks: placed in a box of blocks in linear time, the same
    # order as sorting (and the same bytes on the wire), shuffled or not
    from protocol.deltacodec import _composite, _dense_order

    rng = np.random.default_rng(bs)
    keys = np.unique(rng.integers(-30, 30, (150_000, 3)), axis=0)
    rng.shuffle(keys)
    comp = _composite(keys, bs)
    order = _dense_order(comp, bs)
    assert order is not None
    np.testing.assert_array_equal(order, np.argsort(comp))
    assert _dense_order(comp[::50], bs) is None  # sparse: left to the sort
    assert _dense_order(np.r_[comp, comp[:1]], bs) is None  # a duplicate: the encoder refuses it
    delta = Delta(
        0.1, 0, 3, keys, np.full(len(keys), -0.40625, np.float32), np.full(len(keys), 2.0)
    )
    back = decode_delta(encode_delta(delta, block_shift=bs), Limits(max_voxels=1 << 20))
    np.testing.assert_array_equal(back.keys, keys[np.argsort(comp)])
    assert_delta_close(back, delta)
