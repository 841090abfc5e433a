"""Compact voxel-delta codec: block-grouped sorted keys, quantised log-odds, significance order.

`encode_delta` turns a `voxel.delta.Delta` into the codec body (a msgpack map of binary
columns; the envelope compresses it); `decode_delta` turns hostile bytes back into a Delta.
Layout and tolerances are specified in docs/PROTOCOL.md ("Delta body").
"""

from __future__ import annotations

import itertools
import math
from enum import IntEnum
from typing import Any

import numpy as np

from protocol import fields
from protocol.errors import (
    MalformedError,
    OversizedError,
    RangeError,
    UnknownTypeError,
    VersionError,
)
from protocol.limits import DEFAULT_LIMITS, Limits
from protocol.summary import MAX_LEVEL, FreeSummary
from voxel import kernels, surface
from voxel.delta import CHANNEL_SPECS, SCALAR_PREFIX, Delta
from voxel.errors import DeltaError
from voxel.keys import KEY_MAX, KEY_MIN, pack

#: Version of the delta body layout (field "v").
CODEC_VERSION = 1
#: Blocks are 2**bs voxels a side (bs = "block shift", 2, 3 or 4 on the wire; 16^3 blocks give
#: the smallest deltas). A voxel's offset in its block is (x * E + y) * E + z with E = 2**bs.
BLOCK_SHIFTS = (2, 3, 4)
DEFAULT_BLOCK_SHIFT = 4
#: Quantised log-odds code for "unknown" (NaN).
UNKNOWN_CODE = -128
#: Quantum exponents: log-odds travel as int8 multiples of 2**q, q in [Q_MIN, Q_MAX].
Q_MIN = -12
Q_MAX = 4
#: Relative time (ms) code for a NaN time.
TIME_NAN = np.iinfo(np.int64).min
#: Channel dtypes on the wire (little-endian), by channel name; "first_time" travels like times.
_WIRE_DTYPE = {
    "hits": "<u2",
    "misses": "<u2",
    "colour": "u1",
    "normal": "<f4",
    "class_ids": "<i2",
    "class_probs": "<f4",
    "surface": "i1",
}
_MAX_SECTIONS = 6
#: A block whose section holds at least B^3 / _BITMAP_DIVISOR voxels is sent as a bitmap.
_BITMAP_DIVISOR = 16


class Tier(IntEnum):
    """Significance tiers, sent in this order: surfaces first, then space that became free."""

    OCCUPIED_NEW = 0  # became occupied (was free or unknown)
    OCCUPIED = 1  # occupied, and was occupied (or previous state not known)
    CLEARED = 2  # became free, was occupied
    UNKNOWN = 3  # returned to unknown (forgotten)
    FREE_NEW = 4  # became free, was unknown
    FREE = 5  # free, and was free (or previous state not known)


_FREE_TIERS = (Tier.CLEARED, Tier.FREE_NEW, Tier.FREE)


def significance(delta: Delta, prev_logodds: np.ndarray | None = None) -> np.ndarray:
    """Tier (uint8, `Tier`) of every voxel of `delta`; `prev_logodds`: the values before it."""
    lo = delta.logodds
    with np.errstate(invalid="ignore"):
        occ = lo >= 0
        free = lo < 0
    tier = np.full(lo.shape[0], Tier.UNKNOWN, dtype=np.uint8)
    if prev_logodds is None:
        tier[occ] = Tier.OCCUPIED
        tier[free] = Tier.FREE
        return tier
    prev = _previous(delta, prev_logodds)
    with np.errstate(invalid="ignore"):
        was_occ = prev >= 0
    was_unknown = np.isnan(prev)
    tier[occ & ~was_occ] = Tier.OCCUPIED_NEW
    tier[occ & was_occ] = Tier.OCCUPIED
    tier[free & was_occ] = Tier.CLEARED
    tier[free & was_unknown] = Tier.FREE_NEW
    tier[free & ~was_occ & ~was_unknown] = Tier.FREE
    return tier


def _previous(delta: Delta, prev_logodds: np.ndarray) -> np.ndarray:
    """`prev_logodds` as float32, one per voxel of `delta` (else ValueError)."""
    prev = np.asarray(prev_logodds, dtype=np.float32).reshape(-1)
    if prev.shape[0] != len(delta):
        msg = (
            f"prev_logodds needs one value per voxel: expected {len(delta)}, found {prev.shape[0]}"
        )
        raise ValueError(msg)
    return prev


# --------------------------------------------------------------------------- encoding


#: The grid's own log-odds quantum (`voxel.grid` stores multiples of 2**GRID_Q): deltas whose
#: values all lie on it travel with q = GRID_Q, exactly.
GRID_Q = -5


def quantum_exponent(logodds: np.ndarray) -> int:
    """Quantum exponent of a set of log-odds (NaN ignored).

    GRID_Q (-5) when every finite value is a multiple of 2**-5 with |value| <= 127 * 2**-5 (the
    grid's stored precision: exact on the wire); otherwise the smallest q in [Q_MIN, Q_MAX]
    with 127 * 2**q >= max |finite log-odds|.
    """
    finite = logodds[np.isfinite(logodds)]
    amax = float(np.max(np.abs(finite))) if finite.size else 0.0
    if amax <= 127.0 * 2.0**GRID_Q:
        scaled = finite.astype(np.float64) * 2.0**-GRID_Q
        if np.array_equal(scaled, np.rint(scaled)):
            return GRID_Q
    if amax <= 0.0:
        return Q_MIN
    q = math.ceil(math.log2(amax / 127.0))
    return int(min(max(q, Q_MIN), Q_MAX))


def quantise(logodds: np.ndarray, q: int) -> np.ndarray:
    """int8 codes of log-odds: sign-preserving (negatives never round to 0), NaN -> UNKNOWN_CODE."""
    lo = np.asarray(logodds, dtype=np.float32)
    nan = np.isnan(lo)
    scaled = np.rint(np.where(nan, 0.0, lo) * np.float32(2.0**-q))
    codes = np.clip(scaled, -127, 127).astype(np.int8)
    codes[(lo < 0) & (codes == 0)] = -1
    codes[nan] = UNKNOWN_CODE
    return codes


def dequantise(codes: np.ndarray, q: int) -> np.ndarray:
    """Log-odds (float32) of int8 codes; UNKNOWN_CODE -> NaN."""
    out = codes.astype(np.float32) * np.float32(2.0**q)
    out[codes == UNKNOWN_CODE] = np.nan
    return out


#: Largest |time| in ms that the integer-millisecond time arithmetic handles exactly (2**53).
_MS_EXACT = float(1 << 53)


def reference_ms(ref: float) -> int:
    """The reference time T in whole milliseconds: round(T * 1000) (0 if |T| is beyond 2**53 ms).

    Voxel times travel as integers relative to this, so a time of k / 1000.0 s (whole ms) on the
    sender decodes to exactly k / 1000.0 on the receiver.
    """
    ms = float(ref) * 1000.0
    return int(np.rint(ms)) if abs(ms) < _MS_EXACT else 0


def _relative_ms(times: np.ndarray, ref: float) -> np.ndarray:
    t = np.asarray(times, dtype=np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        ms = np.rint(t * 1000.0)
    bad = ~np.isfinite(ms) | (np.abs(ms) >= _MS_EXACT)
    rel = np.where(bad, 0.0, ms).astype(np.int64) - reference_ms(ref)
    rel[bad] = TIME_NAN
    return rel


def _absolute_times(rel: np.ndarray, ref: float) -> np.ndarray:
    """Seconds of relative ms codes: (T_ms + rel) / 1000.0 in one division; TIME_NAN -> NaN."""
    nan = rel == TIME_NAN
    total = reference_ms(ref) + np.where(nan, 0, rel)  # |T_ms| < 2**53, |rel| <= 2**62: no overflow
    out = total.astype(np.float64) / 1000.0
    out[nan] = np.nan
    return out


def _time_columns(
    times: np.ndarray, ref: float, order: np.ndarray | None = None
) -> tuple[bytes, bytes]:
    """(table, index): unique relative ms times (int64) and each voxel's index into the table,
    voxels in `order` (None: as given)."""
    t = np.asarray(times, dtype=np.float64)
    if t.size == 0:
        return b"", b""
    lo, hi = t.min(), t.max()
    if lo == hi or (np.isnan(lo) and np.isnan(t).all()):  # one time for every voxel: no index
        return _relative_ms(t[:1], ref).astype("<i8").tobytes(), b""
    rel = _relative_ms(t, ref)
    if rel.min() == rel.max():
        return rel[:1].astype("<i8").tobytes(), b""
    if order is not None:
        rel = rel[order]
    table, index = np.unique(rel, return_inverse=True)
    dtype = "u1" if table.size <= 1 << 8 else "<u2" if table.size <= 1 << 16 else "<u4"
    return table.astype("<i8").tobytes(), index.astype(dtype).tobytes()


def _composite(keys: np.ndarray, bs: int) -> np.ndarray:
    """One int64 per key ordering keys by block (x, y, z), then by in-block offset (x-major)."""
    axis = 21 - bs  # bits per axis of a block coordinate
    b = (keys >> bs) - (KEY_MIN >> bs)
    o = keys & ((1 << bs) - 1)
    off = (o[:, 0] << (2 * bs)) | (o[:, 1] << bs) | o[:, 2]
    return (
        (b[:, 0] << (2 * axis + 3 * bs))
        | (b[:, 1] << (axis + 3 * bs))
        | (b[:, 2] << (3 * bs))
        | off
    )


def _block_sort(comp: np.ndarray, bs: int) -> tuple[np.ndarray | None, np.ndarray]:
    """(order, sorted composites) of composites; order None when already sorted.

    Linear time when the keys come grouped by block with offsets ascending (as a block-sparse
    grid lists them): only the blocks are sorted. Otherwise a full sort.
    """
    n = comp.shape[0]
    if n > 1:
        d = np.diff(comp)
        if np.all(d > 0):
            return None, comp
        bc = comp >> (3 * bs)
        brk = np.flatnonzero(bc[1:] != bc[:-1]) + 1
        inner = np.ones(n - 1, dtype=bool)
        inner[brk - 1] = False
        if np.all(d[inner] > 0):
            starts = np.concatenate(([0], brk))
            heads = bc[starts]
            horder = np.argsort(heads)
            sheads = heads[horder]
            if np.all(sheads[1:] > sheads[:-1]):
                lengths = np.diff(np.concatenate((starts, [n])))[horder]
                first = starts[horder]
                perm = np.repeat(first - (np.cumsum(lengths) - lengths), lengths) + np.arange(n)
                return perm, comp[perm]
    elif n <= 1:
        return None, comp
    order = _dense_order(comp, bs)
    if order is None:
        # Stable (a merge sort) finds the sorted runs of a grid's block-ordered voxels.
        order = np.argsort(comp, kind="stable")
    return order, comp[order]


#: `_dense_order` places voxels in a box of blocks with at most this many cells per voxel.
_DENSE_CELLS_PER_VOXEL = 4


def _dense_order(comp: np.ndarray, bs: int) -> np.ndarray | None:
    """argsort of unique composites in linear time when their blocks fill a box well (a whole
    layer's snapshot does): each voxel is placed at its cell of the box; None otherwise."""
    n = comp.shape[0]
    axis, obits = 21 - bs, 3 * bs
    bc = comp >> obits
    amask = (1 << axis) - 1
    cols = [bc >> (2 * axis), (bc >> axis) & amask, bc & amask]
    lo = [int(c.min()) for c in cols]
    dims = [int(c.max()) - x + 1 for c, x in zip(cols, lo, strict=True)]
    cells = dims[0] * dims[1] * dims[2] << obits
    if cells > _DENSE_CELLS_PER_VOXEL * n + 4096:
        return None
    lin = (cols[0] - lo[0]) * dims[1]
    lin += cols[1] - lo[1]
    lin *= dims[2]
    lin += cols[2] - lo[2]
    lin <<= obits
    lin |= comp & ((1 << obits) - 1)
    slot = np.full(cells, -1, dtype=np.int64)
    slot[lin] = np.arange(n)
    order: np.ndarray = slot[slot >= 0]
    # Duplicates share a cell: leave them to the sort, after which encoding refuses them.
    return order if order.shape[0] == n else None


def _encode_keys(comp: np.ndarray, bs: int, level: int = 0) -> list[Any]:
    """Section key columns [n, nblocks, blocks, counts, bitmaps, offsets] of sorted composites."""
    n = comp.shape[0]
    if n and np.any(comp[1:] == comp[:-1]):
        msg = "delta keys must be unique, found duplicates"
        raise DeltaError(msg)
    axis, obits = 21 - bs, 3 * bs
    nvox = 1 << obits
    bc = comp >> obits
    if n:
        starts = np.concatenate(([0], np.flatnonzero(bc[1:] != bc[:-1]) + 1))
    else:
        starts = np.zeros(0, dtype=np.int64)
    counts = np.diff(np.concatenate((starts, [n])))
    bkey = bc[starts]
    amask = (1 << axis) - 1
    blocks = np.stack([bkey >> (2 * axis), (bkey >> axis) & amask, bkey & amask], axis=1) + (
        KEY_MIN >> bs
    )
    dblocks = blocks.copy()
    dblocks[1:] -= blocks[:-1]
    off = comp & (nvox - 1)
    dense_block = counts >= nvox // _BITMAP_DIVISOR
    nd = int(dense_block.sum())
    if nd == 0:
        bitmaps, soff, scounts = b"", off, counts
    else:
        dense_voxel = np.repeat(dense_block, counts)
        rows = np.repeat(np.arange(nd), counts[dense_block])
        bits = np.zeros((nd, nvox), dtype=bool)
        bits[rows, off[dense_voxel]] = True
        bitmaps = np.packbits(bits, axis=1, bitorder="little").tobytes()
        soff, scounts = off[~dense_voxel], counts[~dense_block]
    # offsets of sparse blocks: first offset of a block absolute, the rest as gaps
    gaps = soff.copy()
    gaps[1:] -= soff[:-1]
    if scounts.size:
        sstarts = np.cumsum(scounts) - scounts
        gaps[sstarts] = soff[sstarts]
    return [
        int(n),
        int(starts.shape[0]),
        dblocks.T.astype("<i4").tobytes(),
        counts.astype("<u2").tobytes(),
        bitmaps,
        gaps.astype("<u2").tobytes(),
    ]


def _check_delta_keys(keys: np.ndarray, level: int = 0) -> None:
    lo, hi = KEY_MIN >> level, KEY_MAX >> level
    if keys.size and (keys.min() < lo or keys.max() > hi):
        msg = (
            f"delta keys must lie in [{lo}, {hi}] at level {level}, found [{keys.min()}, "
            f"{keys.max()}]"
        )
        raise RangeError(msg)


def _channel_column(
    name: str, values: np.ndarray, ref: float, present: np.ndarray | None = None
) -> list[Any]:
    k = int(values.shape[1]) if values.ndim == 2 else 0
    if present is not None:  # `surface` of the voxels at `present` alone, and the bitmap
        codes = values[present].astype(_WIRE_DTYPE[name], copy=False).tobytes()
        return [name, k, codes, np.packbits(present, bitorder="little").tobytes()]
    if name == "first_time":
        table, index = _time_columns(values, ref)
        return [name, k, table, index]
    if name.startswith(SCALAR_PREFIX):
        return [name, k, values.astype("<f4", copy=False).tobytes()]
    return [name, k, values.astype(_WIRE_DTYPE[name], copy=False).tobytes()]


def _check_block_shift(bs: int) -> None:
    if bs not in BLOCK_SHIFTS:
        msg = f"block_shift must be one of {BLOCK_SHIFTS}, found {bs}"
        raise ValueError(msg)


def _sections(
    delta: Delta, prev_logodds: np.ndarray | None, bs: int
) -> list[tuple[int, np.ndarray | None, np.ndarray]]:
    """(tier, voxel order or None for "as given", sorted composites) of each non-empty tier."""
    _check_block_shift(bs)
    _check_delta_keys(delta.keys)
    comp_all = _composite(delta.keys, bs)
    tiers = significance(delta, prev_logodds)
    present = np.bincount(tiers, minlength=len(Tier))
    out: list[tuple[int, np.ndarray | None, np.ndarray]] = []
    for tier in Tier:
        if not present[tier]:
            continue
        if present[tier] == tiers.shape[0]:
            order, comp = _block_sort(comp_all, bs)
        else:
            idx = np.flatnonzero(tiers == tier)
            order, comp = _block_sort(comp_all[idx], bs)
            order = idx if order is None else idx[order]
        out.append((int(tier), order, comp))
    return out


def _compiled_columns(
    keys: np.ndarray, lo: np.ndarray | None, prev: np.ndarray | None, bs: int
) -> tuple[list[list[Any]], np.ndarray | None] | None:
    """([tier, key columns of `_encode_keys`...] per section, wire order or None for "as given")
    of valid keys by the compiled kernel, tiers of `lo` (and `prev`; no `lo`: one section, tier
    0), or None to take the numpy path (no kernel, or keys too spread out for it)."""
    kernel = kernels.wire_keys()
    if kernel is None:
        return None
    none = np.zeros(0, dtype=np.float32)
    mode = 0 if lo is None else 1 if prev is None else 2
    # Writable, contiguous: the types the kernel was compiled for (another would compile anew).
    status, identity, perm, table, blocks, counts, bitmaps, gaps = kernel(
        np.require(keys, np.int64, ("C", "W")),
        none if lo is None else np.require(lo, np.float32, ("C", "W")),
        none if prev is None else np.require(prev, np.float32, ("C", "W")),
        mode,
        bs,
    )
    if status == kernels.WIRE_TOO_WIDE:
        return None
    if status == kernels.WIRE_DUPLICATE:
        msg = "delta keys must be unique, found duplicates"
        raise DeltaError(msg)
    blocks = blocks.astype("<i4", copy=False)
    counts = counts.astype("<u2", copy=False)
    gaps = gaps.astype("<u2", copy=False)
    sections: list[list[Any]] = []
    b0 = d0 = g0 = 0
    for tier, n, m, b1, d1, g1 in table.tolist():
        sections.append(
            [
                tier,
                n,
                m,
                blocks[:, b0:b1].tobytes(),
                counts[b0:b1].tobytes(),
                bitmaps[d0:d1].tobytes(),
                gaps[g0:g1].tobytes(),
            ]
        )
        b0, d0, g0 = b1, d1, g1
    return sections, None if identity else perm


def _key_sections(
    delta: Delta, prev_logodds: np.ndarray | None, bs: int
) -> tuple[list[list[Any]], np.ndarray | None]:
    """([tier, key columns...] of each non-empty tier, wire order or None for "as given")."""
    _check_block_shift(bs)
    _check_delta_keys(delta.keys)
    prev = None if prev_logodds is None else _previous(delta, prev_logodds)
    compiled = _compiled_columns(delta.keys, delta.logodds, prev, bs)
    if compiled is not None:
        return compiled
    sections: list[list[Any]] = []
    order_parts: list[np.ndarray] = []
    identity = True
    for tier, order, comp in _sections(delta, prev, bs):
        identity = identity and order is None
        order_parts.append(np.arange(len(delta)) if order is None else order)
        sections.append([tier, *_encode_keys(comp, bs)])
    if identity:
        return sections, None
    return sections, np.concatenate(order_parts)


def wire_order(
    delta: Delta,
    prev_logodds: np.ndarray | None = None,
    block_shift: int = DEFAULT_BLOCK_SHIFT,
) -> np.ndarray:
    """Permutation putting the voxels of `delta` in wire order (tier, then block, then offset)."""
    perm = _key_sections(delta, prev_logodds, block_shift)[1]
    return np.arange(len(delta)) if perm is None else perm


def _summary_keys(keys: np.ndarray, bs: int) -> tuple[list[Any], np.ndarray | None]:
    """(key columns, order or None for "as given") of a summary's keys, one section."""
    compiled = _compiled_columns(keys, None, None, bs)
    if compiled is not None:
        return compiled[0][0][1:], compiled[1]
    order, comp = _block_sort(_composite(keys, bs), bs)
    return _encode_keys(comp, bs), order


def encode_delta(
    delta: Delta,
    *,
    summary: FreeSummary | None = None,
    prev_logodds: np.ndarray | None = None,
    block_shift: int = DEFAULT_BLOCK_SHIFT,
) -> bytes:
    """Codec body of `delta` (and an optional free-space summary), voxels in significance order.

    Exact for keys, occupancy state, channels (times to 1 ms); log-odds to within one quantum
    (see `quantum_exponent`; 2**-5 for OctoMap's clamping range).
    """
    bs = block_shift
    sections, order = _key_sections(delta, prev_logodds, bs)

    def wired(values: np.ndarray) -> np.ndarray:
        return values if order is None else np.take(values, order, axis=0)

    lo = wired(delta.logodds)
    mask = delta.surface_mask
    if mask is not None and bool(mask.all()):
        mask = None  # every voxel's codes: the plain form
    q = quantum_exponent(
        delta.logodds if summary is None else np.r_[delta.logodds, summary.logodds]
    )
    table, index = _time_columns(delta.last_time, delta.time, order)
    body: dict[str, Any] = {
        "v": CODEC_VERSION,
        "res": float(delta.resolution),
        "from": int(delta.from_version),
        "to": int(delta.to_version),
        "time": float(delta.time),
        "bs": bs,
        "q": q,
        "n": len(delta),
        "sec": sections,
        "lo": quantise(lo, q).tobytes(),
        "tt": table,
        "ti": index,
        "ch": [
            _channel_column(
                name,
                wired(values),
                delta.time,
                wired(mask) if name == surface.CHANNEL and mask is not None else None,
            )
            for name, values in sorted(delta.channels.items())
        ],
    }
    if summary is not None and len(summary):
        _check_delta_keys(summary.keys, summary.level)
        columns, sorder = _summary_keys(summary.keys, bs)
        logodds = summary.logodds if sorder is None else summary.logodds[sorder]
        rel = _relative_ms(np.array([summary.time]), delta.time)[0]
        body["sum"] = [
            int(summary.level),
            *columns,
            quantise(logodds, q).tobytes(),
            int(rel),
        ]
    return fields.pack(body)


def encoded_size(
    delta: Delta, *, summary: FreeSummary | None = None, level: int = fields.DEFAULT_LEVEL
) -> int:
    """Bytes of the zstd-compressed codec body of `delta` (what a message body costs)."""
    return len(fields.compress(encode_delta(delta, summary=summary), level))


# ------------------------------------------------------------------ summaries, budgets, splits


def _coarsen(keys: np.ndarray, lo: np.ndarray, shift: int) -> tuple[np.ndarray, np.ndarray]:
    """Cells (keys >> shift, unique) and the highest log-odds of the keys each covers."""
    if keys.shape[0] == 0:
        return np.zeros((0, 3), np.int64), np.zeros(0, np.float32)
    cells = keys >> shift
    packed = pack(cells)
    order = np.argsort(packed)
    ps = packed[order]
    starts = np.flatnonzero(np.r_[True, ps[1:] != ps[:-1]])
    return cells[order[starts]], np.maximum.reduceat(lo[order], starts)


def _summaries(delta: Delta, mask: np.ndarray, levels: tuple[int, ...]) -> list[FreeSummary]:
    """Summaries of the voxels of `delta` at `mask`, one per level (ascending), coarse from fine."""
    keys, lo = delta.keys[mask], delta.logodds[mask]
    times = delta.last_time[mask]
    t = float(np.nanmax(times)) if np.isfinite(times).any() else float(delta.time)
    out, level = [], 0
    for target in sorted(levels):
        if not 1 <= target <= MAX_LEVEL:
            msg = f"summary level must be in [1, {MAX_LEVEL}], found {target}"
            raise ValueError(msg)
        keys, lo = _coarsen(keys, lo, target - level)
        level = target
        out.append(
            FreeSummary(delta.resolution, level, delta.from_version, delta.to_version, keys, lo, t)
        )
    return out


def summarise_free(delta: Delta, level: int, mask: np.ndarray | None = None) -> FreeSummary:
    """Coarse cells (2**level voxels a side) covering the free voxels of `delta` (or of `mask`).

    Each cell takes the highest (least certain) log-odds of the voxels it covers, and the
    summary the latest of their times.
    """
    if mask is None:
        with np.errstate(invalid="ignore"):
            mask = delta.logodds < 0
    return _summaries(delta, mask, (level,))[0]


def fit_delta(
    delta: Delta,
    budget: int,
    *,
    prev_logodds: np.ndarray | None = None,
    levels: tuple[int, ...] = (1, 2, 3, 4),
) -> tuple[Delta, FreeSummary | None]:
    """`delta` reduced to fit `budget` compressed body bytes by summarising free space.

    Tries, in order: the full delta; then (with `prev_logodds`) everything exact but free voxels
    that were already free, those summarised at each of `levels`; then all free space summarised
    at each level; then surfaces and forgotten voxels alone. Returns the first that fits, else
    the smallest. Voxels whose surface codes a sparse `surface` channel carries are kept exact
    whatever their tier (a later delta leaves out codes that did not change since).
    """
    if encoded_size(delta) <= budget:
        return delta, None
    tiers = significance(delta, prev_logodds)
    free = np.isin(tiers, np.array(_FREE_TIERS, dtype=np.uint8))
    if delta.surface_mask is not None:  # codes it carries are never cut: later deltas omit them
        free &= ~delta.surface_mask
    candidates: list[tuple[np.ndarray, np.ndarray]] = []
    refine = (tiers == Tier.FREE) & free
    if prev_logodds is not None and refine.any() and (free & ~refine).any():
        candidates.append((~refine, refine))
    candidates.append((~free, free))
    best: tuple[int, Delta, FreeSummary | None] | None = None
    for keep, summarised in candidates:
        exact = delta.select(keep)
        for summary in _summaries(delta, summarised, levels):
            size = encoded_size(exact, summary=summary)
            if size <= budget:
                return exact, summary
            if best is None or size < best[0]:
                best = (size, exact, summary)
    exact = delta.select(~free)
    size = encoded_size(exact)
    if size <= budget or best is None or size < best[0]:
        return exact, None
    return best[1], best[2]


#: Smallest codec body `split_delta` cuts to (a part holds at least one voxel and the header).
MIN_PART_BODY = 256


def split_delta(
    delta: Delta,
    max_bytes: int,
    *,
    prev_logodds: np.ndarray | None = None,
) -> list[Delta]:
    """`delta` cut into parts whose compressed codec bodies each fit `max_bytes`.

    Parts follow significance order (the first parts carry surfaces) and each is a complete
    Delta with the same versions, so every part can be decoded and applied on its own.
    """
    if max_bytes < MIN_PART_BODY:
        msg = f"max_bytes must be >= {MIN_PART_BODY}, found {max_bytes}"
        raise ValueError(msg)
    total = encoded_size(delta)
    if total <= max_bytes:
        return [delta]
    order = wire_order(delta, prev_logodds)  # parts are runs of blocks: compact, already sorted
    n = order.shape[0]
    pieces = max(2, math.ceil(total / (0.8 * max_bytes)))
    bounds = np.linspace(0, n, pieces + 1).astype(np.int64)
    todo = [(int(a), int(b)) for a, b in itertools.pairwise(bounds) if b > a]
    parts: list[Delta] = []
    while todo:
        a, b = todo.pop(0)
        part = delta.select(order[a:b])
        if encoded_size(part) <= max_bytes:
            parts.append(part)
            continue
        if b - a == 1:
            msg = f"one voxel needs more than max_bytes={max_bytes} bytes"
            raise OversizedError(msg)
        mid = (a + b) // 2
        todo[0:0] = [(a, mid), (mid, b)]
    return parts


# --------------------------------------------------------------------------- decoding


def _bin(obj: list[Any] | dict[str, Any], index: Any, what: str, size: int) -> bytes:
    value = obj.get(index) if isinstance(obj, dict) else obj[index]
    if not isinstance(value, bytes):
        msg = f"{what}: expected binary data, found {type(value).__name__}"
        raise MalformedError(msg)
    if len(value) != size:
        msg = f"{what}: expected {size} bytes, found {len(value)}"
        raise MalformedError(msg)
    return value


def _int(value: Any, what: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        msg = f"{what}: expected an integer in [{lo}, {hi}], found {type(value).__name__}"
        raise MalformedError(msg)
    if not lo <= value <= hi:
        msg = f"{what}: expected an integer in [{lo}, {hi}], found {value}"
        raise RangeError(msg)
    return value


def _decode_keys(
    sec: list[Any], at: int, what: str, bs: int, level: int, max_voxels: int
) -> tuple[np.ndarray, int, np.ndarray | None]:
    """Keys (n, 3) of the key columns sec[at:at+6], validated; returns (keys, n, their
    composites, or None when not computed)."""
    n = _int(sec[at], f"{what} voxel count", 0, max_voxels)
    m = _int(sec[at + 1], f"{what} block count", 0, n)
    if (n == 0) != (m == 0):
        msg = f"{what}: expected blocks if and only if voxels, found {n} voxels in {m} blocks"
        raise MalformedError(msg)
    edge, nvox = 1 << bs, 1 << (3 * bs)
    bitmap_bytes = nvox // 8
    raw_blocks = np.frombuffer(_bin(sec, at + 2, f"{what} blocks", 12 * m), dtype="<i4").reshape(
        3, m
    )
    blocks = np.cumsum(raw_blocks.astype(np.int64), axis=1).T
    bmin, bmax = (KEY_MIN >> level) >> bs, (KEY_MAX >> level) >> bs
    if m and (blocks.min() < bmin or blocks.max() > bmax):
        msg = (
            f"{what}: expected block keys in [{bmin}, {bmax}], found [{blocks.min()}, "
            f"{blocks.max()}]"
        )
        raise RangeError(msg)
    if m > 1:
        axis = 21 - bs
        bkey = (
            ((blocks[:, 0] - bmin) << (2 * axis))
            | ((blocks[:, 1] - bmin) << axis)
            | (blocks[:, 2] - bmin)
        )
        if np.any(bkey[1:] <= bkey[:-1]):
            msg = (
                f"{what}: expected blocks in strictly increasing (x, y, z) order, found a block "
                "out of order"
            )
            raise MalformedError(msg)
    counts = np.frombuffer(_bin(sec, at + 3, f"{what} counts", 2 * m), dtype="<u2").astype(np.int64)
    if m and (counts.min() < 1 or counts.max() > nvox):
        msg = f"{what}: expected 1..{nvox} voxels per block, found {counts.min()}..{counts.max()}"
        raise RangeError(msg)
    if int(counts.sum()) != n:
        msg = f"{what}: expected block counts summing to {n} voxels, found {int(counts.sum())}"
        raise MalformedError(msg)
    dense = counts >= nvox // _BITMAP_DIVISOR
    nd = int(dense.sum())
    bitmaps = np.frombuffer(_bin(sec, at + 4, f"{what} bitmaps", bitmap_bytes * nd), dtype=np.uint8)
    nsparse = n - int(counts[dense].sum())
    raw_gaps = np.frombuffer(_bin(sec, at + 5, f"{what} offsets", 2 * nsparse), dtype="<u2")
    voxels = kernels.wire_voxels()
    if voxels is not None and n:
        ok, keys, comp = voxels(
            np.ascontiguousarray(blocks), counts, bitmaps, raw_gaps, n, bs, KEY_MIN
        )
        if ok:
            return keys, n, comp
    gaps = raw_gaps.astype(np.int64)
    start = np.cumsum(counts) - counts
    if nd == m:
        off = np.empty(n, dtype=np.int64)
        block_of = None
    else:
        off = np.empty(n, dtype=np.int64)
        block_of = np.empty(n, dtype=np.int64)
    if nd:
        # Set bits in order, from the non-zero bytes alone (dense blocks are mostly zero bytes).
        nz = np.flatnonzero(bitmaps)
        r, c = np.nonzero(np.unpackbits(bitmaps[nz][:, None], axis=1, bitorder="little"))
        bit = nz[r] * 8 + c
        rows, cols = bit >> (3 * bs), bit & (nvox - 1)
        pop = np.bincount(rows, minlength=nd)
        if np.any(pop != counts[dense]):
            msg = f"{what}: expected bitmap population to equal block counts, found a mismatch"
            raise MalformedError(msg)
        if block_of is None:  # every block is a bitmap: rows are already in output order
            off[:] = cols
        else:
            didx = np.flatnonzero(dense)
            dstart = np.cumsum(pop) - pop
            pos = start[didx][rows] + (np.arange(rows.shape[0]) - dstart[rows])
            off[pos] = cols
            block_of[pos] = didx[rows]
    if nsparse:
        sidx = np.flatnonzero(~dense)
        scounts = counts[sidx]
        sstart = np.cumsum(scounts) - scounts
        firsts = np.zeros(nsparse, dtype=bool)
        firsts[sstart] = True
        if np.any(gaps[~firsts] == 0):
            msg = f"{what}: expected strictly increasing offsets within a block, found a zero gap"
            raise MalformedError(msg)
        cs = np.cumsum(gaps)
        soff = cs - np.repeat(cs[sstart] - gaps[sstart], scounts)
        if soff.max() >= nvox:
            msg = f"{what}: expected in-block offsets below {nvox}, found {int(soff.max())}"
            raise RangeError(msg)
        if nd == 0:
            off = soff
            block_of = None
        else:
            assert block_of is not None  # nd < m: some blocks are sparse (nd == m leaves none)
            pos = np.repeat(start[sidx] - sstart, scounts) + np.arange(nsparse)
            off[pos] = soff
            block_of[pos] = np.repeat(sidx, scounts)
    base = blocks << bs
    keys = base[block_of] if block_of is not None else np.repeat(base, counts, axis=0)
    keys[:, 0] += off >> (2 * bs)
    keys[:, 1] += (off >> bs) & (edge - 1)
    keys[:, 2] += off & (edge - 1)
    return keys, n, None


def _decode_times(table_raw: Any, index_raw: Any, n: int, ref: float, what: str) -> np.ndarray:
    if not isinstance(table_raw, bytes) or not isinstance(index_raw, bytes):
        msg = f"{what}: expected binary time table and index"
        raise MalformedError(msg)
    if len(table_raw) % 8:
        msg = f"{what}: expected a time table of 8-byte entries, found {len(table_raw)} bytes"
        raise MalformedError(msg)
    table = np.frombuffer(table_raw, dtype="<i8")
    t = table.shape[0]
    if n == 0:
        if t or index_raw:
            msg = f"{what}: expected no times for no voxels, found {t} table entries"
            raise MalformedError(msg)
        return np.zeros(0, dtype=np.float64)
    if t == 0 or t > n:
        msg = f"{what}: expected 1..{n} time table entries, found {t}"
        raise MalformedError(msg)
    if np.any(np.abs(table[table != TIME_NAN]) > (1 << 62)):
        msg = f"{what}: expected relative times within 2**62 ms, found more"
        raise RangeError(msg)
    values = _absolute_times(table, ref)
    if t == 1:
        if index_raw:
            msg = (
                f"{what}: expected no time index for a one-entry table, found {len(index_raw)} "
                "bytes"
            )
            raise MalformedError(msg)
        return np.full(n, values[0])
    dtype = "u1" if t <= 1 << 8 else "<u2" if t <= 1 << 16 else "<u4"
    width = np.dtype(dtype).itemsize
    if len(index_raw) != n * width:
        msg = f"{what}: expected a time index of {n * width} bytes, found {len(index_raw)}"
        raise MalformedError(msg)
    index = np.frombuffer(index_raw, dtype=dtype)
    if int(index.max()) >= t:
        msg = f"{what}: expected time indices below {t}, found {int(index.max())}"
        raise RangeError(msg)
    times: np.ndarray = values[index]
    return times


def _decode_presence(raw: Any, n: int) -> np.ndarray:
    """The `surface` channel's bitmap over a delta's n voxels (least significant bit first)."""
    data = _bin([raw], 0, "delta channel 'surface' bitmap", (n + 7) // 8)
    bits = np.unpackbits(np.frombuffer(data, dtype=np.uint8), bitorder="little")
    if bits[n:].any():
        msg = (
            f"delta channel 'surface' bitmap: expected bits beyond the delta's {n} voxels to be "
            "0, found one set"
        )
        raise MalformedError(msg)
    return bits[:n].astype(bool)


def _decode_surface(entry: list[Any], n: int) -> tuple[np.ndarray, np.ndarray]:
    """Codes (n, 3) and presence (n,) of a `surface` channel carried for some voxels alone: 0 for
    the voxels it does not carry (they keep the receiver's)."""
    present = _decode_presence(entry[3], n)
    m = int(np.count_nonzero(present))
    raw = _bin(entry, 2, f"delta channel 'surface' ({m} voxels in its bitmap)", m * 3)
    values = np.zeros((n, 3), dtype=np.int8)
    values[present] = np.frombuffer(raw, dtype=np.int8).reshape(m, 3)
    return values, present


def _decode_channel(
    entry: Any, n: int, ref: float, limits: Limits
) -> tuple[str, np.ndarray, np.ndarray | None]:
    if not isinstance(entry, list) or len(entry) < 3 or not isinstance(entry[0], str):
        msg = "delta channel: expected [name, k, data...], found something else"
        raise MalformedError(msg)
    name = entry[0]
    if name not in CHANNEL_SPECS and not (
        name.startswith(SCALAR_PREFIX) and len(name) > len(SCALAR_PREFIX)
    ):
        msg = (
            f"delta channel: expected one of {sorted(CHANNEL_SPECS)} or 'scalar:NAME', found "
            f"{name[:64]!r}"
        )
        raise UnknownTypeError(msg)
    dtype, tail = CHANNEL_SPECS.get(name, (np.dtype(np.float32), ()))
    k = _int(entry[1], f"delta channel {name!r} width", 0, limits.max_class_k)
    expected_k = 0 if tail == () else tail[0]
    if (expected_k == -1 and k < 1) or (expected_k not in (-1, k)):
        msg = (
            f"delta channel {name!r}: expected width "
            f"{'1..' + str(limits.max_class_k) if expected_k == -1 else expected_k}, found {k}"
        )
        raise RangeError(msg)
    if name == "first_time":
        if len(entry) != 4:
            msg = (
                f"delta channel 'first_time': expected [name, k, table, index], found {len(entry)} "
                "items"
            )
            raise MalformedError(msg)
        times = _decode_times(entry[2], entry[3], n, ref, "delta channel 'first_time'")
        return name, times, None
    present = None
    if name == surface.CHANNEL and len(entry) == 4:
        values, present = _decode_surface(entry, n)
    elif len(entry) != 3:
        form = (
            "[name, k, data] or [name, k, codes, bitmap]"
            if name == "surface"
            else "[name, k, data]"
        )
        msg = f"delta channel {name!r}: expected {form}, found {len(entry)} items"
        raise MalformedError(msg)
    else:
        wire = "<f4" if name.startswith(SCALAR_PREFIX) else _WIRE_DTYPE[name]
        count = n * max(k, 1)
        raw = _bin(entry, 2, f"delta channel {name!r}", count * np.dtype(wire).itemsize)
        values = np.frombuffer(raw, dtype=wire).astype(dtype)
    if name == "surface" and values.size and int(values.min()) < -surface.WIRE_MAX:
        msg = (
            f"delta channel 'surface': expected codes in [-{surface.WIRE_MAX}, "
            f"{surface.WIRE_MAX}] (within half a voxel), found {int(values.min())}"
        )
        raise RangeError(msg)
    return name, values.reshape((n, k) if k else (n,)), present


def decode_delta_with_summary(
    data: bytes, limits: Limits = DEFAULT_LIMITS
) -> tuple[Delta, FreeSummary | None]:
    """Delta (and free-space summary, if any) of a hostile codec body; ProtocolError if invalid."""
    if len(data) > limits.max_body_bytes:
        msg = f"delta body: expected at most {limits.max_body_bytes} bytes, found {len(data)}"
        raise OversizedError(msg)
    body = fields.as_map(fields.unpack(bytes(data), "delta body", limits), "delta body")
    version = fields.field(body, "v", int, "delta body")
    if version != CODEC_VERSION:
        msg = f"delta body: expected codec version {CODEC_VERSION}, found {version}"
        raise VersionError(msg)
    res = fields.field(body, "res", float, "delta body")
    if not (math.isfinite(res) and 1e-4 <= res <= 1e3):
        msg = f"delta body: expected resolution in [1e-4, 1e3] m, found {res}"
        raise RangeError(msg)
    v_from = _int(
        fields.field(body, "from", int, "delta body"), "delta from_version", 0, (1 << 63) - 1
    )
    v_to = _int(
        fields.field(body, "to", int, "delta body"), "delta to_version", v_from, (1 << 63) - 1
    )
    ref = fields.field(body, "time", float, "delta body")
    if not math.isfinite(ref):
        msg = f"delta body: expected a finite time, found {ref}"
        raise RangeError(msg)
    bs = fields.field(body, "bs", int, "delta body")
    if bs not in BLOCK_SHIFTS:
        msg = f"delta body: expected block shift in {BLOCK_SHIFTS}, found {bs}"
        raise RangeError(msg)
    q = _int(fields.field(body, "q", int, "delta body"), "delta quantum exponent", Q_MIN, Q_MAX)
    n = _int(fields.field(body, "n", int, "delta body"), "delta voxel count", 0, (1 << 63) - 1)
    if n > limits.max_voxels:
        msg = (
            f"delta body: expected at most {limits.max_voxels} voxels (decoder limit), found n={n}"
        )
        raise OversizedError(msg)
    sections = fields.field(body, "sec", list, "delta body")
    if len(sections) > _MAX_SECTIONS:
        msg = f"delta body: expected at most {_MAX_SECTIONS} sections, found {len(sections)}"
        raise MalformedError(msg)
    key_parts = []
    comp_parts: list[np.ndarray | None] = []
    total = 0
    last_tier = -1
    for i, sec in enumerate(sections):
        what = f"delta section {i}"
        if not isinstance(sec, list) or len(sec) != 7:
            msg = (
                f"{what}: expected [tier, n, blocks, block keys, counts, bitmaps, offsets], found "
                f"{type(sec).__name__}"
            )
            raise MalformedError(msg)
        tier = _int(sec[0], f"{what} tier", 0, len(Tier) - 1)
        if tier <= last_tier:
            msg = f"{what}: expected tiers in increasing order, found {tier} after {last_tier}"
            raise MalformedError(msg)
        last_tier = tier
        keys, count, comp = _decode_keys(sec, 1, what, bs, 0, n - total)
        key_parts.append(keys)
        comp_parts.append(comp)
        total += count
    if total != n:
        msg = f"delta body: expected sections holding n={n} voxels, found {total}"
        raise MalformedError(msg)
    keys = np.concatenate(key_parts) if key_parts else np.zeros((0, 3), np.int64)
    if len(key_parts) > 1:
        # Each section is sorted by (block, offset): a stable sort merges the sorted runs.
        known = [c for c in comp_parts if c is not None]
        comp_all = np.concatenate(known) if len(known) == len(comp_parts) else _composite(keys, bs)
        packed = np.sort(comp_all, kind="stable")
        if np.any(packed[1:] == packed[:-1]):
            msg = "delta body: expected each voxel at most once, found a voxel in two sections"
            raise MalformedError(msg)
    codes = np.frombuffer(_bin(body, "lo", "delta log-odds", n), dtype=np.int8)
    logodds = dequantise(codes, q)
    last_time = _decode_times(body.get("tt"), body.get("ti"), n, ref, "delta times")
    channel_list = fields.field(body, "ch", list, "delta body")
    if len(channel_list) > limits.max_channels:
        msg = (
            f"delta body: expected at most {limits.max_channels} channels, found "
            f"{len(channel_list)}"
        )
        raise OversizedError(msg)
    channels: dict[str, np.ndarray] = {}
    present = None
    for entry in channel_list:
        name, values, mask = _decode_channel(entry, n, ref, limits)
        if name in channels:
            msg = f"delta body: expected each channel once, found {name!r} twice"
            raise MalformedError(msg)
        channels[name] = values
        present = mask if mask is not None else present
    summary = None
    if body.get("sum") is not None:
        summary = _decode_summary(body["sum"], res, v_from, v_to, ref, q, bs, limits.max_voxels - n)
    try:
        delta = Delta(
            resolution=res,
            from_version=v_from,
            to_version=v_to,
            keys=keys,
            logodds=logodds,
            last_time=last_time,
            channels=channels,
            time=ref,
            surface_mask=present,
        )
    except DeltaError as exc:
        msg = f"delta body: {exc}"
        raise MalformedError(msg) from None
    return delta, summary


def _decode_summary(
    entry: Any, res: float, v_from: int, v_to: int, ref: float, q: int, bs: int, max_cells: int
) -> FreeSummary:
    what = "delta summary"
    if not isinstance(entry, list) or len(entry) != 9:
        msg = (
            f"{what}: expected [level, n, blocks, block keys, counts, bitmaps, offsets, log-odds, "
            "time]"
        )
        raise MalformedError(msg)
    level = _int(entry[0], f"{what} level", 1, MAX_LEVEL)
    keys, n, _ = _decode_keys(entry, 1, what, bs, level, max(max_cells, 0))
    codes = np.frombuffer(_bin(entry, 7, f"{what} log-odds", n), dtype=np.int8)
    if n and (codes.max() >= 0 or codes.min() == UNKNOWN_CODE):
        msg = f"{what}: expected free (negative) log-odds codes, found {int(codes.max())}"
        raise RangeError(msg)
    rel = _int(entry[8], f"{what} time", -(1 << 62), 1 << 62)
    return FreeSummary(
        resolution=res,
        level=level,
        from_version=v_from,
        to_version=v_to,
        keys=keys,
        logodds=dequantise(codes, q),
        time=float(_absolute_times(np.array([rel], dtype=np.int64), ref)[0]),
    )


def decode_delta(data: bytes, limits: Limits = DEFAULT_LIMITS) -> Delta:
    """Delta of a hostile codec body (a free-space summary, if any, is dropped)."""
    return decode_delta_with_summary(data, limits)[0]
