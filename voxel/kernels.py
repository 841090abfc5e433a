"""Compiled kernels (numba, the optional `fast` extra) for integration's hot loops, loaded lazily.

`beams()` (a scan's beams sorted), `trace()` (a scan's whole dense traversal: hits, rays, blocks
touched), `index()` (the block store's lookup and insertion) and `update()` (the occupancy update
of a chunk of blocks and the voxels the history records) return a compiled kernel, or None when
numba is absent, fails, or `COLONY_JIT=0` (read at import); the callers then run their pure-numpy
path, which gives bit-identical results (the kernels repeat its floating-point operations one for
one). Importing numba and loading the cached machine code take ~0.5 s of CPU, so nothing here
happens at import: `warm()` does it, off the hot path (a daemon calls it in a background thread
once ready), and the first call otherwise. Compiling them (nothing cached yet) takes ~36 s of CPU
(measured, docs/DAEMON.md): after `load_in_background()` (a daemon) a call never waits for that,
it starts the loading in a thread and answers None (the numpy path) until it is done.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from voxel import keys as vk
from voxel.record import RECORD_DTYPE

log = logging.getLogger(__name__)

#: Environment variable that turns the compiled kernels off ("0"), e.g. to compare both paths.
JIT_ENV = "COLONY_JIT"

#: Packed keys (voxel.keys): bits per axis and the offset added to each axis.
_AXIS_BITS = vk.AXIS_BITS
_AXIS_OFFSET = 1 << (_AXIS_BITS - 1)
#: Multipliers of `keys.one_per_key`'s hash rounds.
_HASH = vk._HASH_MULTIPLIERS
#: Entries of the sorting's cache of recent hit keys (`_sort_beams`, distinct).
_RECENT_BITS = 12
_RECENT = 1 << _RECENT_BITS
#: The low bit of every byte of a 64-bit (32-bit) word.
_LOW_BITS = np.uint64(0x0101010101010101)
_LOW_BITS32 = np.uint32(0x01010101)

_lock = threading.Lock()
_start_lock = threading.Lock()
#: Name -> compiled kernel (None: numba absent); empty until loaded.
_compiled: dict[str, Callable[..., Any] | None] = {}


class _Loading:
    """How kernels not loaded yet are loaded: by the first call (`background` False), or in
    `thread`, started by the first call, while callers take the numpy path."""

    def __init__(self) -> None:
        self.background = False
        self.thread: threading.Thread | None = None


_loading = _Loading()


class _Switch:
    """Whether the compiled kernels are used: COLONY_JIT read once, at import (every kernel
    fetch reading the environment cost ~1 us, five times a scan)."""

    def __init__(self) -> None:
        self.on = os.environ.get(JIT_ENV, "1") != "0"


_switch = _Switch()


def enabled() -> bool:
    """True unless the compiled kernels are turned off (COLONY_JIT=0 when the process started;
    tests switch `_switch.on` to run both paths)."""
    return _switch.on


def _get(name: str) -> Callable[..., Any] | None:
    if not enabled():
        return None
    if "trace" not in _compiled:
        if not _loading.background:
            _load()
        else:
            _load_soon()
            return None
    return _compiled[name]


def load_in_background() -> None:
    """From now on a kernel not loaded yet is loaded in a thread while its callers take the numpy
    path: a daemon's first scan must not hold its map for a compilation."""
    _loading.background = True


def _load_soon() -> None:
    with _start_lock:  # not `_lock`: a loading in progress holds that one
        if _loading.thread is not None:
            return
        thread = threading.Thread(target=_load, name="kernels-load", daemon=True)
        _loading.thread = thread
    thread.start()


def trace() -> Callable[..., Any] | None:
    """The compiled dense traversal (see `_trace_box`), or None to use the numpy path."""
    return _get("trace")


def beams() -> Callable[..., Any] | None:
    """The compiled sorting of a scan's beams (see `_sort_beams`), or None."""
    return _get("beams")


def update() -> Callable[..., Any] | None:
    """The compiled occupancy update of a chunk of blocks (see `_update_records`), or None."""
    return _get("update")


def surface() -> Callable[..., Any] | None:
    """The compiled fusion of a scan's hit points into the surface means (see
    `_fuse_surface`), or None."""
    return _get("surface")


def records() -> Callable[..., Any] | None:
    """The compiled writing of a chunk's history records (see `_fill_records`), or None."""
    return _get("records")


def index() -> Callable[..., Any] | None:
    """The compiled lookup and insertion of sorted block keys (see `_index_blocks`) once the
    kernels are loaded, else None; never starts their loading: a replica inserting the blocks of
    its first snapshot would otherwise share the interpreter with numba's import (~0.5 s of CPU)
    halfway through the install (a daemon without sources then never loads them)."""
    return _compiled.get("index") if enabled() else None


def loaded() -> bool:
    """True once the kernels were loaded (or found unavailable): numba's objects are in place."""
    return "trace" in _compiled


def warm() -> bool:
    """Import numba and load (or compile and cache) the kernels now; True when they are in use."""
    if not enabled():
        return False
    _load()
    return _compiled["trace"] is not None


def _try_out(
    trace: Callable[..., Any],
    update: Callable[..., Any],
    beams: Callable[..., Any],
    index: Callable[..., Any],
    records: Callable[..., Any],
) -> None:
    """One tiny call of each kernel: compiles (or loads) them, so a failure shows here."""
    index(np.array([2, 5], dtype=np.int64), np.array([0, 1], dtype=np.int64), np.arange(4), 2)
    one = np.zeros(1, dtype=np.float32)
    records(
        np.zeros(2, dtype=RECORD_DTYPE),
        1,
        np.zeros(1, dtype=np.int64),
        one,
        one,
        np.zeros(1, dtype=np.bool_),
        np.zeros(0, dtype=np.int32),
        one[:0],
        (0.0, 0, 0, np.float32(-0.4), np.float32(0.8), 0.0, 1.0, 0.0, 1),
    )
    beams(
        np.array([[1.0, 2.0, 0.5], [40.0, 0.0, 0.0]]),
        np.zeros(3),
        np.array([False, True]),
        30.0,
        10.0,
        20.0,
        60.0,
        float(vk.KEY_MIN),
        float(vk.KEY_MAX),
        float(vk.KEY_MAX * 3),
        True,
        True,
    )
    trace(
        np.array([0.5, 0.5, 0.5]),
        np.array([[3.0], [2.0], [0.0]]),
        np.zeros((0, 3)),
        np.zeros(3, dtype=np.int64),
        np.zeros(3, dtype=np.int64),
        np.array([4, 4, 4], dtype=np.int64),
        np.array([1, 1, 1], dtype=np.int64),
        3000,
        np.zeros(64, dtype=np.uint8),
        np.zeros(8, dtype=np.uint8),
        np.zeros(8, dtype=np.int64),
        True,
        1.0,
    )
    lo = np.full((1, 1), np.nan, dtype=np.float32)
    stamp = np.zeros((1, 1), dtype=np.uint32)
    update(
        lo,
        stamp.copy(),
        stamp,
        stamp[0],
        np.zeros(1, dtype=np.int64),
        np.zeros(1, dtype=np.int64),
        np.ones((1, 1), dtype=np.uint8),
        np.zeros(3, dtype=np.float32),
        np.float32(-1.0),
        np.float32(1.0),
        1,
        0,
        np.zeros(3, dtype=np.int64),
        True,
    )


def _compiled_or_in_memory(
    numba: Any, sources: tuple[Callable[..., Any], ...]
) -> tuple[Callable[..., Any], ...]:
    """`sources` to be compiled by numba (lazily, at their first call), their machine code
    cached on disk, or kept in memory where no cache directory is writable. The helpers they
    call (`_HELPERS`) are bound to their names in this module first, compiled to be inlined
    into their callers (numba resolves a kernel's globals when it compiles it, and calls only
    compiled functions; inlined, a helper costs no call in the kernels' inner loops)."""
    inline = numba.njit(nogil=True, inline="always")
    globals().update({name: inline(f) for name, f in _HELPERS.items()})
    try:
        jit = numba.njit(cache=True, nogil=True)
        return tuple(jit(f) for f in sources)
    except RuntimeError:  # no writable cache directory: compile at every start
        log.warning("numba cannot cache here (set NUMBA_CACHE_DIR); compiling in memory")
        jit = numba.njit(nogil=True)
        return tuple(jit(f) for f in sources)


def _load() -> None:
    with _lock:
        if "trace" in _compiled:
            return
        # "trace" last: callers test for it first
        names = ("beams", "update", "index", "records", "surface", "trace")
        found: dict[str, Callable[..., Any] | None] = dict.fromkeys(names)
        try:
            import numba
        except ImportError:
            _compiled.update(found)
            return
        try:
            sources = (
                _trace_box,
                _update_records,
                _sort_beams,
                _index_blocks,
                _fill_records,
                _fuse_surface,
            )
            kernels = _compiled_or_in_memory(numba, sources)
            _try_out(*kernels[:5])
            _try_surface(kernels[5])
            found = {"trace": kernels[0], "update": kernels[1], "beams": kernels[2]}
            found["index"] = kernels[3]
            found["records"] = kernels[4]
            found["surface"] = kernels[5]
        except Exception as exc:  # noqa: BLE001 - any numba failure leaves the numpy path
            log.warning("compiled kernels unavailable, using numpy: %s", exc)
        for name in names:
            _compiled[name] = found[name]


def _try_surface(fuse: Callable[..., Any]) -> None:
    """One tiny call of the surface fusion (compiles or loads it)."""
    fuse(
        np.zeros((1, 1, 3), dtype=np.int16),
        np.zeros((1, 1), dtype=np.uint16),
        np.zeros((1, 1, 3), dtype=np.int8),
        np.zeros(1, dtype=np.int64),
        np.zeros(1, dtype=np.int64),
        np.zeros(1, dtype=np.int64),
        np.zeros((1, 3)),
        np.ones(1, dtype=np.int64),
        np.zeros(1, dtype=np.bool_),
        65532.0,
        32766.0,
        258.0,
        127.0,
        16,
        16.0,
    )


def _fuse_surface(
    means: np.ndarray,
    weights: np.ndarray,
    published: np.ndarray,
    slots: np.ndarray,
    offsets: np.ndarray,
    inverse: np.ndarray,
    sums: np.ndarray,
    counts: np.ndarray,
    sent: np.ndarray,
    store_scale: float,
    store_max: float,
    store_step: float,
    wire_max: float,
    publish: int,
    publish_step: float,
) -> np.ndarray:
    """`surface.fuse_surface` in one pass (the same floating-point operations in the same
    order): the running means (`means`, int16 (slots, voxels, 3)) and weights of the hit voxels
    at (`slots`, `offsets`) take the mean of the groups of points `inverse` maps to them
    (`sums` (H, 3), `counts` (H,)); published codes (multiples of `publish_step`) follow where
    they differ and the voxel is new, `sent` anyway, or its mean moved `publish` codes from
    them. Returns the mask of voxels whose published codes changed."""
    m = slots.shape[0]
    acc = np.zeros((m, 3), dtype=np.float64)
    pts = np.zeros(m, dtype=np.float64)
    for i in range(inverse.shape[0]):
        r = inverse[i]
        acc[r, 0] += sums[i, 0]
        acc[r, 1] += sums[i, 1]
        acc[r, 2] += sums[i, 2]
        pts[r] += np.float64(counts[i])
    moved = np.zeros(m, dtype=np.bool_)
    rounded = np.empty(3, dtype=np.int64)
    for r in range(m):
        sl = slots[r]
        o = offsets[r]
        w = np.int64(weights[sl, o])
        weights[sl, o] = np.uint16(w + 1 if w < 65535 else 65535)
        far = False
        differ = False
        for a in range(3):
            frame = acc[r, a] / pts[r]
            cur = np.float64(means[sl, o, a]) / store_scale
            cur += (frame - cur) / (np.float64(w) + 1.0)
            new = min(max(np.rint(cur * store_scale), -store_max), store_max)
            means[sl, o, a] = np.int16(new)
            code = min(max(np.rint(np.float64(np.int16(new)) / store_step), -wire_max), wire_max)
            steps = np.rint(code / publish_step) * publish_step
            rounded[a] = np.int64(min(max(steps, -wire_max), wire_max))
            old = np.int64(published[sl, o, a])
            if abs(np.int64(code) - old) >= publish:
                far = True
            if rounded[a] != old:
                differ = True
        if w == 0 or (differ and (far or sent[r])):
            for a in range(3):
                published[sl, o, a] = np.int8(rounded[a])
            moved[r] = True
    return moved


def _trace_box(
    o: np.ndarray,
    hk: np.ndarray,
    clear_scaled: np.ndarray,
    key_o: np.ndarray,
    lo: np.ndarray,
    dims: np.ndarray,
    shifts: np.ndarray,
    flat_below: int,
    cells: np.ndarray,
    marks: np.ndarray,
    touched: np.ndarray,
    want_rows: bool,
    scan_ratio: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """One scan's traversal in a dense box (lower corner `lo`, block-aligned, sides `dims`), as
    `raycast.trace`'s numpy path computes it: hit voxels at keys `hk` (3, H) (exact integers in
    float64), rays from `o` (box-local, in voxels) to each distinct hit voxel's centre and to the
    ends `clear_scaled` (M, 3) (world, in voxels; cast unless in the origin's voxel `key_o`)
    mark FREE the voxels they enter, end voxel excluded, hits win; the origin voxel is free when
    any ray is cast.

    `cells` (uint8, at least the box's cells), `marks` (uint8, at least its blocks) are zero and
    `touched` (int64, at least its blocks) is any: scratch buffers reused across scans, left
    zero again on return. Returns the packed keys (B,) of the touched blocks, sorted, their cells
    (B, block voxels), the distinct hit keys (U, 3) int64 in packed order, each hit's row in
    them (H,; with `want_rows`, else empty), and the count of FREE cells.

    Written for numba: the arithmetic of `raycast._sequences`, `_sweep` and `_enumerate` per run,
    in the same order, so the visited voxels are bit-identical to the numpy path's. Runs step by
    accumulation up to the step `k_flat` at which the numpy sweep has fewer than `flat_below` runs
    left, and are enumerated by multiplication from there, as it does.

    A scan whose box has at most `scan_ratio` 8-byte words of cells per crossing (dense: depth
    frames, 2D scans) marks cells without reading them, two runs at a time, and finds its blocks
    by reading the box after; a sparser one (a few long rays in a large box) marks each new
    cell's block as it goes. Both give the same result.
    """
    s2 = np.int64(1)
    s1 = dims[2]
    s0 = dims[1] * dims[2]
    strides = np.array([s0, s1, s2], dtype=np.int64)
    base = lo[0] * s0 + lo[1] * s1 + lo[2]
    nb = np.empty(3, dtype=np.int64)
    for a in range(3):
        nb[a] = dims[a] >> shifts[a]
    bstride = np.array([nb[1] * nb[2], nb[2], 1], dtype=np.int64)
    n_touched = 0
    # Hit voxels: mark them, and their blocks; distinct ones in row-major (= packed key) order.
    n_hits = hk.shape[1]
    uniq = np.empty(min(n_hits, 4096), dtype=np.int64)  # grows: hits share voxels
    n_uniq = 0
    for i in range(n_hits):
        lin = np.int64(hk[0, i]) * s0 + np.int64(hk[1, i]) * s1 + np.int64(hk[2, i]) - base
        if cells[lin] == 0:
            cells[lin] = 2  # HIT
            if n_uniq == uniq.size:
                grown = np.empty(min(n_hits, 2 * uniq.size), dtype=np.int64)
                grown[:n_uniq] = uniq
                uniq = grown
            uniq[n_uniq] = lin
            n_uniq += 1
    hit_lin = np.sort(uniq[:n_uniq])
    rows = np.empty(n_hits if want_rows else 0, dtype=np.int64)
    if want_rows:
        for i in range(n_hits):
            lin = np.int64(hk[0, i]) * s0 + np.int64(hk[1, i]) * s1 + np.int64(hk[2, i]) - base
            rows[i] = np.searchsorted(hit_lin, lin)
    hit_keys = np.empty((n_uniq, 3), dtype=np.int64)
    ko0 = np.int64(np.floor(o[0]))
    ko1 = np.int64(np.floor(o[1]))
    ko2 = np.int64(np.floor(o[2]))
    ko = np.array([ko0, ko1, ko2], dtype=np.int64)
    start = (key_o[0] - lo[0]) * s0 + (key_o[1] - lo[1]) * s1 + (key_o[2] - lo[2])
    # Ray ends: each distinct hit voxel's centre (unless it is the origin's voxel), each clear end
    # outside the origin's voxel.
    n_clear = clear_scaled.shape[0]
    ends = np.empty((n_uniq + n_clear, 3), dtype=np.float64)
    n_rays = 0
    for i in range(n_uniq):
        x = hit_lin[i] // s0
        rest = hit_lin[i] - x * s0
        y = rest // s1
        z = rest - y * s1
        hit_keys[i, 0] = x + lo[0]
        hit_keys[i, 1] = y + lo[1]
        hit_keys[i, 2] = z + lo[2]
        if hit_lin[i] != start:
            ends[n_rays, 0] = x + 0.5
            ends[n_rays, 1] = y + 0.5
            ends[n_rays, 2] = z + 0.5
            n_rays += 1
    for i in range(n_clear):
        cast = False
        for a in range(3):
            if np.int64(np.floor(clear_scaled[i, a])) != key_o[a]:
                cast = True
        if cast:
            for a in range(3):
                ends[n_rays, a] = clear_scaled[i, a] - np.float64(lo[a])
            n_rays += 1
    # Pass 1: each ray's crossings per axis, the end voxel's crossing dropped.
    counts = np.empty((n_rays, 3), dtype=np.int64)
    longest = 0
    for r in range(n_rays):
        best = -np.inf
        latest = -1
        for a in range(3):
            d = ends[r, a] - o[a]
            c = abs(np.int64(np.floor(ends[r, a])) - ko[a])
            counts[r, a] = c
            if c > 0:
                sgn = np.sign(d)
                last_plane = np.float64(ko[a] + (1 if d > 0 else 0)) + np.float64(c - 1) * sgn
                t = (last_plane - o[a]) / d
                if latest < 0 or t > best:
                    best = t
                    latest = a
        if latest >= 0:
            counts[r, latest] -= 1
        for a in range(3):
            longest = max(longest, counts[r, a])
    hist = np.zeros(longest + 1, dtype=np.int64)
    runs = 0
    crossings = 0
    for r in range(n_rays):
        for a in range(3):
            if counts[r, a] > 0:
                hist[counts[r, a]] += 1
                runs += 1
                crossings += counts[r, a]
    k_flat = 0
    if runs >= flat_below:
        seen = 0
        for v in range(longest, 0, -1):
            seen += hist[v]
            if seen >= flat_below:
                k_flat = v
                break
    # A dense scan (its box not much larger than its crossings) marks cells only, its blocks are
    # found by scanning the box after; a sparse one marks the blocks of the cells it marks.
    total = dims[0] * dims[1] * dims[2]
    if np.float64(total >> 3) <= scan_ratio * np.float64(crossings):
        # Each run's constants, axis by axis (neighbouring rays' runs side by side, of similar
        # lengths), as in the sparse sweep below.
        r_m = np.empty(runs, dtype=np.int64)
        r_lin = np.empty(runs, dtype=np.int64)
        r_sa = np.empty(runs, dtype=np.int64)
        r_sb = np.empty(runs, dtype=np.int64)
        r_sc = np.empty(runs, dtype=np.int64)
        r_y = np.empty(runs, dtype=np.float64)
        r_iy = np.empty(runs, dtype=np.float64)
        r_z = np.empty(runs, dtype=np.float64)
        r_iz = np.empty(runs, dtype=np.float64)
        n_r = 0
        for a in range(3):
            for r in range(n_rays):
                m = counts[r, a]
                if m <= 0:
                    continue
                b, c, stay_b, stay_c, isgn, y0, inc_y, z0, inc_z = _run_start(ends, r, a, o, ko)
                r_y[n_r] = y0
                r_iy[n_r] = inc_y
                r_z[n_r] = z0
                r_iz[n_r] = inc_z
                r_m[n_r] = m
                r_sa[n_r] = strides[a] * isgn
                # A fixed axis has a zero stride and its key in the constant term.
                r_sb[n_r] = 0 if stay_b else strides[b]
                r_sc[n_r] = 0 if stay_c else strides[c]
                r_lin[n_r] = (
                    (ko[a] + isgn) * strides[a]
                    + (ko[b] * strides[b] if stay_b else 0)
                    + (ko[c] * strides[c] if stay_c else 0)
                )
                n_r += 1
        if n_rays > 0:
            cells[start] = 1  # FREE
        # Crossings before k_flat accumulate (the numpy sweep's steps), two runs at a time: each
        # run's coordinates are a chain of additions, and two chains overlap in the CPU. Cells are
        # marked FREE unconditionally (a store, no load or branch); hits are marked again after.
        i = 0
        while i < runs:
            j = i + 1 if i + 1 < runs else i
            ma = min(r_m[i], k_flat)
            mb = min(r_m[j], k_flat) if j != i else 0
            la = r_lin[i]
            sa_a = r_sa[i]
            sb_a = r_sb[i]
            sc_a = r_sc[i]
            ya = r_y[i]
            iya = r_iy[i]
            za = r_z[i]
            iza = r_iz[i]
            lb = r_lin[j]
            sa_b = r_sa[j]
            sb_b = r_sb[j]
            sc_b = r_sc[j]
            yb = r_y[j]
            iyb = r_iy[j]
            zb = r_z[j]
            izb = r_iz[j]
            both = min(ma, mb)
            if sc_a == 0 and sc_b == 0:  # z fixed in both (a planar scan): y alone moves
                for _ in range(both):
                    yva = np.int64(ya)
                    ya += iya
                    yvb = np.int64(yb)
                    yb += iyb
                    cells[la + yva * sb_a] = 1
                    cells[lb + yvb * sb_b] = 1
                    la += sa_a
                    lb += sa_b
            else:
                for _ in range(both):
                    yva = np.int64(ya)
                    zva = np.int64(za)
                    ya += iya
                    za += iza
                    yvb = np.int64(yb)
                    zvb = np.int64(zb)
                    yb += iyb
                    zb += izb
                    cells[la + yva * sb_a + zva * sc_a] = 1
                    cells[lb + yvb * sb_b + zvb * sc_b] = 1
                    la += sa_a
                    lb += sa_b
            for _ in range(both, ma):
                yva = np.int64(ya)
                zva = np.int64(za)
                ya += iya
                za += iza
                cells[la + yva * sb_a + zva * sc_a] = 1
                la += sa_a
            for _ in range(both, mb):
                yvb = np.int64(yb)
                zvb = np.int64(zb)
                yb += iyb
                zb += izb
                cells[lb + yvb * sb_b + zvb * sc_b] = 1
                lb += sa_b
            r_lin[i] = la
            r_y[i] = ya
            r_z[i] = za
            if j != i:
                r_lin[j] = lb
                r_y[j] = yb
                r_z[j] = zb
            i += 2
        # Crossings from k_flat on multiply (the numpy sweep's flat pass): no chain between them.
        for i in range(runs):
            m = r_m[i]
            if m <= k_flat:
                continue
            la = r_lin[i]
            sa_a = r_sa[i]
            sb_a = r_sb[i]
            sc_a = r_sc[i]
            ya = r_y[i]
            iya = r_iy[i]
            za = r_z[i]
            iza = r_iz[i]
            if sc_a == 0:
                for k in range(m - k_flat):
                    yva = np.int64(ya + np.float64(k) * iya)
                    cells[la + yva * sb_a] = 1
                    la += sa_a
            else:
                for k in range(m - k_flat):
                    jf = np.float64(k)
                    yva = np.int64(ya + jf * iya)
                    zva = np.int64(za + jf * iza)
                    cells[la + yva * sb_a + zva * sc_a] = 1
                    la += sa_a
        for i in range(n_uniq):
            cells[hit_lin[i]] = 2  # HIT: hits win
        # The touched blocks: the box read in words of one block's run (a block's cells lie in
        # runs along z, or along y and z when the box is one block high), a non-zero word marks
        # its block; then the marks in block order.
        whole_box = dims[2] == (np.int64(1) << shifts[2])
        run_len = np.int64(1) << (shifts[1] + shifts[2] if whole_box else shifts[2])
        ws = 8 if run_len % 8 == 0 else (4 if run_len % 4 == 0 else 1)
        if whole_box:
            n_rows = dims[0]
            row_len = s0
            sh_in = shifts[1] + shifts[2]
        else:
            n_rows = dims[0] * dims[1]
            row_len = dims[2]
            sh_in = shifts[2]
        n_w = row_len // ws
        w64 = cells[: cells.size - cells.size % 8].view(np.uint64)
        w32 = cells[: cells.size - cells.size % 4].view(np.uint32)
        for row in range(n_rows):
            if whole_box:
                bbase = (row >> shifts[0]) * bstride[0]
            else:
                x = row // dims[1]
                y = row - x * dims[1]
                bbase = (x >> shifts[0]) * bstride[0] + (y >> shifts[1]) * bstride[1]
            w0 = row * n_w
            if ws == 8:
                for q in range(n_w):
                    if w64[w0 + q] != 0:
                        marks[bbase + ((q << 3) >> sh_in)] = 1
            elif ws == 4:
                for q in range(n_w):
                    if w32[w0 + q] != 0:
                        marks[bbase + ((q << 2) >> sh_in)] = 1
            else:
                for q in range(n_w):
                    if cells[w0 + q] != 0:
                        marks[bbase + (q >> sh_in)] = 1
        for t in range(nb[0] * nb[1] * nb[2]):
            if marks[t] != 0:
                touched[n_touched] = t
                n_touched += 1
    else:
        for i in range(n_uniq):
            x = hit_lin[i] // s0
            rest = hit_lin[i] - x * s0
            y = rest // s1
            z = rest - y * s1
            blk = (x >> shifts[0]) * bstride[0] + (y >> shifts[1]) * bstride[1] + (z >> shifts[2])
            if marks[blk] == 0:
                marks[blk] = 1
                touched[n_touched] = blk
                n_touched += 1
        if n_rays > 0:
            if cells[start] == 0:
                cells[start] = 1  # FREE
            blk = (
                (ko0 >> shifts[0]) * bstride[0]
                + (ko1 >> shifts[1]) * bstride[1]
                + (ko2 >> shifts[2])
            )
            if marks[blk] == 0:
                marks[blk] = 1
                touched[n_touched] = blk
                n_touched += 1
        # Pass 2: every run, as `_sequences` sets it up and `_sweep` / `_enumerate` step it.
        for r in range(n_rays):
            for a in range(3):
                m = counts[r, a]
                if m <= 0:
                    continue
                b, c, stay_b, stay_c, isgn, y0, inc_y, z0, inc_z = _run_start(ends, r, a, o, ko)
                # Per run constants; the axis-a term of the linear index advances by one stride
                # per crossing. Crossings before k_flat accumulate, later ones multiply (as numpy).
                sa = strides[a] * isgn
                sb = strides[b]
                sc = strides[c]
                lin_a = (ko[a] + isgn) * strides[a]
                fixed = (ko[b] * sb if stay_b else 0) + (ko[c] * sc if stay_c else 0)
                blk_a = bstride[a]
                blk_b = bstride[b]
                blk_c = bstride[c]
                sh_a = shifts[a]
                sh_b = shifts[b]
                sh_c = shifts[c]
                y = y0
                z = z0
                split = min(m, k_flat)
                # Branch-free: a fixed axis has a zero stride and its key in a constant offset.
                sb_e = 0 if stay_b else sb
                sc_e = 0 if stay_c else sc
                off_b = ko[b] if stay_b else 0
                off_c = ko[c] if stay_c else 0
                xa = ko[a] + isgn
                base_lin = lin_a + fixed
                for _ in range(split):  # accumulate (the numpy sweep's steps)
                    yv = np.int64(y)
                    zv = np.int64(z)
                    y += inc_y
                    z += inc_z
                    lin = base_lin + yv * sb_e + zv * sc_e
                    base_lin += sa
                    xa_k = xa
                    xa += isgn
                    if cells[lin] != 0:
                        continue  # marked before, and so was its block
                    cells[lin] = 1  # FREE
                    blk = (
                        (xa_k >> sh_a) * blk_a
                        + ((off_b if stay_b else yv) >> sh_b) * blk_b
                        + ((off_c if stay_c else zv) >> sh_c) * blk_c
                    )
                    if marks[blk] == 0:
                        marks[blk] = 1
                        touched[n_touched] = blk
                        n_touched += 1
                for k in range(split, m):  # multiply (the numpy sweep's flat pass)
                    jf = np.float64(k - k_flat)
                    yv = np.int64(y + jf * inc_y)
                    zv = np.int64(z + jf * inc_z)
                    lin = base_lin + yv * sb_e + zv * sc_e
                    base_lin += sa
                    xa_k = xa
                    xa += isgn
                    if cells[lin] != 0:
                        continue  # marked before, and so was its block
                    cells[lin] = 1  # FREE
                    blk = (
                        (xa_k >> sh_a) * blk_a
                        + ((off_b if stay_b else yv) >> sh_b) * blk_b
                        + ((off_c if stay_c else zv) >> sh_c) * blk_c
                    )
                    if marks[blk] == 0:
                        marks[blk] = 1
                        touched[n_touched] = blk
                        n_touched += 1
    # Gather the touched blocks' cells, in block order, and leave the scratch zero.
    order = np.sort(touched[:n_touched])
    sx = shifts[0]
    sy = shifts[1]
    sz = shifts[2]
    n_vox = np.int64(1) << (sx + sy + sz)
    out = np.empty((n_touched, n_vox), dtype=np.uint8)
    blocks = np.empty(n_touched, dtype=np.int64)
    off_x = (lo[0] >> sx) + _AXIS_OFFSET
    off_y = (lo[1] >> sy) + _AXIS_OFFSET
    off_z = (lo[2] >> sz) + _AXIS_OFFSET
    # A block's cells lie in runs along z (along y and z when the box is one block high):
    # copied, counted and cleared 8 or 4 at a time when the runs allow it.
    whole = dims[2] == (np.int64(1) << sz)
    run = np.int64(1) << (sy + sz if whole else sz)
    word = 8 if run % 8 == 0 else (4 if run % 4 == 0 else 1)
    if cells.size % 8 != 0:
        word = 1
    cells64 = cells[: cells.size - cells.size % 8].view(np.uint64)
    cells32 = cells[: cells.size - cells.size % 8].view(np.uint32)
    out64 = out.reshape(n_touched * n_vox).view(np.uint64) if word == 8 else cells64[:0]
    out32 = out.reshape(n_touched * n_vox).view(np.uint32) if word == 4 else cells32[:0]
    n_free = 0
    for i in range(n_touched):
        t = order[i]
        marks[t] = 0
        bx = t // bstride[0]
        rest = t - bx * bstride[0]
        by = rest // bstride[1]
        bz = rest - by * bstride[1]
        blocks[i] = ((bx + off_x) << (2 * _AXIS_BITS)) | ((by + off_y) << _AXIS_BITS) | (bz + off_z)
        if word == 1:
            j = 0
            for ox in range(np.int64(1) << sx):
                row_x = ((bx << sx) + ox) * s0
                for oy in range(np.int64(1) << sy):
                    row_y = row_x + ((by << sy) + oy) * s1 + (bz << sz)
                    for oz in range(np.int64(1) << sz):
                        c = cells[row_y + oz]
                        out[i, j] = c
                        n_free += c == 1
                        cells[row_y + oz] = 0
                        j += 1
            continue
        j = i * n_vox
        for ox in range(np.int64(1) << sx):
            row_x = ((bx << sx) + ox) * s0
            for oy in range(1 if whole else np.int64(1) << sy):
                start = row_x + ((by << sy) + oy) * s1 + (bz << sz)
                # Cells are 0, 1 (FREE) or 2 (HIT): the low bit of each byte counts FREE.
                if word == 8:
                    for r in range(start >> 3, (start + run) >> 3):
                        v = cells64[r]
                        out64[j >> 3] = v
                        n_free += ((v & _LOW_BITS) * _LOW_BITS) >> 56
                        cells64[r] = 0
                        j += 8
                else:
                    for r in range(start >> 2, (start + run) >> 2):
                        v = cells32[r]
                        out32[j >> 2] = v
                        n_free += (((v & _LOW_BITS32) * _LOW_BITS32) >> 24) & 0xFF
                        cells32[r] = 0
                        j += 4
    return blocks, out, hit_keys, rows, n_free


def _run_start(ends: np.ndarray, r: int, a: int, o: np.ndarray, ko: np.ndarray) -> tuple[Any, ...]:
    """The set-up of ray `r`'s run of crossings along axis `a` (`ends` (R, 3) and the origin `o`
    box-local, in voxels; `ko` the origin's voxel), as `raycast._sequences` computes it: the two
    other axes b and c (a fixed one second), whether each stays in the origin's voxel row, the
    step's sign (int), and the coordinates along b and c at the first crossing and their
    increments per crossing (0.5 and 0 on a fixed axis). Shared by both passes of `_trace_box`
    (compiled with it, `_load`)."""
    b = 1 if a == 0 else 0
    c = 1 if a == 2 else 2
    d_a = ends[r, a] - o[a]
    stay_b = np.int64(np.floor(ends[r, b])) == ko[b]
    stay_c = np.int64(np.floor(ends[r, c])) == ko[c]
    if stay_b and not stay_c:
        b, c = c, b
        stay_b, stay_c = stay_c, stay_b
    sgn = np.sign(d_a)
    isgn = np.int64(sgn)
    dist0 = np.float64(ko[a] + (1 if sgn > 0 else 0)) - o[a]
    rb = (ends[r, b] - o[b]) / d_a
    rc = (ends[r, c] - o[c]) / d_a
    y0 = 0.5 if stay_b else o[b] + dist0 * rb
    inc_y = 0.0 if stay_b else sgn * rb
    z0 = 0.5 if stay_c else o[c] + dist0 * rc
    inc_z = 0.0 if stay_c else sgn * rc
    return b, c, stay_b, stay_c, isgn, y0, inc_y, z0, inc_z


#: Helpers the kernels call, as written (`_compiled_or_in_memory` compiles them first).
_HELPERS: dict[str, Callable[..., Any]] = {"_run_start": _run_start}


def _update_records(
    logodds: np.ndarray,
    version: np.ndarray,
    last_time: np.ndarray,
    slot_version: np.ndarray,
    slot_keys: np.ndarray,
    slots: np.ndarray,
    cells: np.ndarray,
    steps: np.ndarray,
    low: np.float32,
    high: np.float32,
    v: int,
    stamp: int,
    shifts: np.ndarray,
    seen: bool,
) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One scan's occupancy update of blocks `slots` (cells (B, V): 0 untouched, else the index
    of its log-odds step), without decay or statistics, and the voxels the history records, as
    `occupancy._update_numpy` and `_worth_recording` compute them: each touched voxel's value
    becomes clip(value or 0 + step); changed voxels take version `v` and time `stamp`; nothing
    is written when nothing changed.

    Returns the count of changed voxels and, in block then offset order, the packed keys, log-odds
    before and after and hit flags of the changed voxels that are hit, occupied now or were
    occupied, and (with `seen`) the packed keys of the voxels that went unknown -> free."""
    n_blocks, n_vox = cells.shape
    # One pass; the outputs are cut to size at the end (at most one entry per touched cell).
    keys = np.empty(n_blocks * n_vox, dtype=np.int64)
    old = np.empty(keys.size, dtype=np.float32)
    new = np.empty(keys.size, dtype=np.float32)
    hit = np.empty(keys.size, dtype=np.bool_)
    fresh = np.empty(keys.size if seen else 0, dtype=np.int64)
    count = 0
    sx = shifts[0]
    sy = shifts[1]
    sz = shifts[2]
    mask = np.int64((1 << _AXIS_BITS) - 1)
    # A voxel's packed key is its block's first voxel's packed key plus its offset's: the fields
    # do not carry into each other.
    offs = np.empty(n_vox, dtype=np.int64)
    for j in range(n_vox):
        offs[j] = (
            ((j >> (sy + sz)) << (2 * _AXIS_BITS))
            | (((j >> sz) & ((1 << sy) - 1)) << _AXIS_BITS)
            | (j & ((1 << sz) - 1))
        )
    k = 0
    f = 0
    for i in range(n_blocks):
        s = slots[i]
        bkey = slot_keys[s]
        bx = ((bkey >> (2 * _AXIS_BITS)) & mask) - _AXIS_OFFSET
        by = ((bkey >> _AXIS_BITS) & mask) - _AXIS_OFFSET
        bz = (bkey & mask) - _AXIS_OFFSET
        first = (
            ((bx << sx) + _AXIS_OFFSET) << (2 * _AXIS_BITS)
            | (((by << sy) + _AXIS_OFFSET) << _AXIS_BITS)
            | ((bz << sz) + _AXIS_OFFSET)
        )
        changed_block = False
        for j in range(n_vox):
            c = cells[i, j]
            if c == 0:
                continue
            before = logodds[s, j]
            known = not np.isnan(before)
            after = (before if known else np.float32(0.0)) + steps[c]
            after = min(max(after, low), high)
            if known and after == before:
                continue
            logodds[s, j] = after
            version[s, j] = v
            last_time[s, j] = stamp
            count += 1
            changed_block = True
            keep = after >= 0 or before >= 0 or c == 2
            is_fresh = seen and not known and after < 0
            if keep or is_fresh:
                packed = first + offs[j]
                if keep:
                    keys[k] = packed
                    old[k] = before
                    new[k] = after
                    hit[k] = c == 2
                    k += 1
                if is_fresh:
                    fresh[f] = packed
                    f += 1
        if changed_block:
            slot_version[s] = v
    return count, keys[:k], old[:k], new[:k], hit[:k], fresh[:f]


def _sort_beams(
    points: np.ndarray,
    org: np.ndarray,
    nr: np.ndarray,
    max_range: float,
    no_return_range: float,
    inv: float,
    fine_scale: float,
    key_min: float,
    key_max: float,
    fine_limit: float,
    distinct: bool,
    surface: bool,
) -> tuple[
    np.ndarray, np.ndarray, np.ndarray, int, int, bool, np.ndarray, int, np.ndarray, np.ndarray
]:
    """A scan's beams sorted as `scan.sort_beams` sorts them (the same floating-point operations
    in the same order): points (N, 3) seen from `org`, `nr` the no-return flags; `inv` is
    1 / resolution, `fine_scale` CLEAR_SUBDIVISION / resolution, keys must lie in
    [key_min, key_max] and fine clear cells in [-fine_limit, fine_limit].

    Returns the hit keys (3, H) float64, the hit mask (N,), the clear ends (M, 3) (one beam per
    fine cell, chosen as `keys.one_per_key` chooses), the counts of clearing and dropped beams,
    False when the clear cells span too much for one packed index (then nothing is valid: the
    caller uses the numpy path), the bounds (2, 3) int64 of the hit keys and of the clear
    ends' keys (floor(end * inv)), for the traversal's box (a bound is empty: low > high), and
    the count of hit points. With `distinct`, a hit key equal to one of the recent ones (a small
    cache: neighbouring pixels of a depth image share voxels) is left out: the hit keys are then
    the same set with fewer repeats (H <= the count of hit points), in the same order. With
    `surface`, also each hit key's sums (H, 3) of its points' offsets from their voxel's centre
    in voxels (x * inv - floor(x * inv) - 0.5), and its count of points
    (H,): a repeated key's point adds to the column it repeats (else both are empty)."""
    n = points.shape[0]
    max2 = max_range * max_range
    hit_mask = np.zeros(n, dtype=np.bool_)
    clear_at = np.empty(n, dtype=np.int64)  # the clearing beams, and their lengths
    clear_range = np.empty(n, dtype=np.float64)
    # floor(x) lies in [key_min, key_max] exactly when key_min <= x < key_max + 1.
    k_top = key_max + 1.0
    hit_keys = np.empty((3, n), dtype=np.float64)
    # The hit keys' bounds, in registers through the loop.
    lo0 = lo1 = lo2 = np.int64(np.iinfo(np.int64).max)
    hi0 = hi1 = hi2 = np.int64(np.iinfo(np.int64).min)
    # Recent hit keys (packed, -1 none), by hash: a direct-mapped cache, a miss only repeats a key.
    recent = np.full(_RECENT if distinct else 1, -1, dtype=np.int64)
    recent_col = np.full(_RECENT if distinct else 1, -1, dtype=np.int64)  # their columns
    sums = np.empty((n if surface else 0, 3), dtype=np.float64)
    counts = np.empty(n if surface else 0, dtype=np.int64)
    # A hit lies within max range of the origin: when that ball lies inside the key space (a
    # voxel to spare for rounding), every hit's key does, and its test is left out.
    inside = True
    for a in range(3):
        reach = max_range * inv + 1.0
        if not (org[a] * inv - reach >= key_min and org[a] * inv + reach < k_top):
            inside = False
    n_hit = 0
    n_out = 0
    n_clear = 0
    for i in range(n):
        t = points[i, 0] - org[0]
        d2 = t * t
        t = points[i, 1] - org[1]
        d2 += t * t
        t = points[i, 2] - org[2]
        d2 += t * t
        # Tests combined without branches (`&`): most points pass them all.
        if (d2 > 0) & (d2 <= max2) & (not nr[i]):
            x0 = points[i, 0] * inv
            x1 = points[i, 1] * inv
            x2 = points[i, 2] * inv
            if inside or (
                (x0 >= key_min)
                & (x0 < k_top)
                & (x1 >= key_min)
                & (x1 < k_top)
                & (x2 >= key_min)
                & (x2 < k_top)
            ):
                hit_mask[i] = True
                n_hit += 1
                k0 = np.floor(x0)
                k1 = np.floor(x1)
                k2 = np.floor(x2)
                i0 = np.int64(k0)
                i1 = np.int64(k1)
                i2 = np.int64(k2)
                if distinct:
                    packed = (
                        ((i0 + _AXIS_OFFSET) << (2 * _AXIS_BITS))
                        | ((i1 + _AXIS_OFFSET) << _AXIS_BITS)
                        | (i2 + _AXIS_OFFSET)
                    )
                    h = ((packed * np.int64(_HASH[0])) >> (64 - _RECENT_BITS)) & (_RECENT - 1)
                    if recent[h] == packed:
                        if surface:
                            c = recent_col[h]
                            sums[c, 0] += x0 - k0 - 0.5
                            sums[c, 1] += x1 - k1 - 0.5
                            sums[c, 2] += x2 - k2 - 0.5
                            counts[c] += 1
                        continue  # a repeated key: in the bounds already
                    recent[h] = packed
                    recent_col[h] = n_out
                lo0 = i0 if i0 < lo0 else lo0
                hi0 = i0 if i0 > hi0 else hi0
                lo1 = i1 if i1 < lo1 else lo1
                hi1 = i1 if i1 > hi1 else hi1
                lo2 = i2 if i2 < lo2 else lo2
                hi2 = i2 if i2 > hi2 else hi2
                hit_keys[0, n_out] = k0
                hit_keys[1, n_out] = k1
                hit_keys[2, n_out] = k2
                if surface:
                    sums[n_out, 0] = x0 - k0 - 0.5
                    sums[n_out, 1] = x1 - k1 - 0.5
                    sums[n_out, 2] = x2 - k2 - 0.5
                    counts[n_out] = 1
                n_out += 1
        else:
            r = np.sqrt(d2)
            if np.isfinite(r) and r > 0 and (r > max_range or nr[i]):
                clear_at[n_clear] = i
                clear_range[n_clear] = r
                n_clear += 1
    if n_out < n:
        hit_keys = hit_keys[:, :n_out].copy()
    bounds = np.empty((2, 3), dtype=np.int64)
    bounds[0, 0] = lo0
    bounds[0, 1] = lo1
    bounds[0, 2] = lo2
    bounds[1, 0] = hi0
    bounds[1, 1] = hi1
    bounds[1, 2] = hi2
    dropped = 0
    if not np.isfinite(no_return_range):  # then no max range either: only no-returns
        dropped = n_clear
        n_clear = 0
    ends = np.empty((n_clear, 3), dtype=np.float64)
    fine = np.empty((n_clear, 3), dtype=np.float64)
    m = 0
    if n_clear:
        for c in range(n_clear):
            i = clear_at[c]
            limit = no_return_range if nr[i] and no_return_range < max_range else max_range
            scale = limit / clear_range[c]
            inside = True
            for a in range(3):
                e = points[i, a] - org[a]
                e *= scale
                e += org[a]
                ends[m, a] = e
                f = np.floor(e * fine_scale)
                fine[m, a] = f
                if f < -fine_limit or f > fine_limit:
                    inside = False
            if inside:
                m += 1
    cleared = m
    # One beam per fine cell, the last of its cell, in order (as keys.one_per_key picks them):
    # one pass from the last beam back over a hash table of the cells seen (linear probing).
    chosen = np.empty(m, dtype=np.int64)
    n_c = 0
    if m:
        lo = np.empty(3, dtype=np.int64)
        span = np.empty(3, dtype=np.int64)
        for a in range(3):
            mn = fine[0, a]
            mx = fine[0, a]
            for i in range(m):
                mn = min(mn, fine[i, a])
                mx = max(mx, fine[i, a])
            lo[a] = np.int64(mn)
            span[a] = np.int64(mx) - lo[a] + 1
        if np.float64(span[0]) * np.float64(span[1]) * np.float64(span[2]) > 2.0**62:
            return (
                hit_keys,
                hit_mask,
                ends[:0],
                cleared,
                dropped,
                False,
                bounds,
                n_hit,
                sums[:0].copy(),
                counts[:0].copy(),
            )
        lin = np.empty(m, dtype=np.int64)
        for i in range(m):
            lin[i] = (
                np.int64(fine[i, 0] - lo[0]) * (span[1] * span[2])
                + np.int64(fine[i, 1] - lo[1]) * span[2]
                + np.int64(fine[i, 2] - lo[2])
            )
        bits = 2
        while (np.int64(1) << (bits - 2)) <= m:
            bits += 1
        bits = max(4, bits)  # max(4, m.bit_length() + 2): a table at most a quarter full
        table = np.full(np.int64(1) << bits, -1, dtype=np.int64)
        mask = (np.int64(1) << bits) - 1
        mult = np.int64(_HASH[0])
        last = np.zeros(m, dtype=np.bool_)
        # From the last beam back: the first of a cell seen is its last beam (one_per_key's).
        for i in range(m - 1, -1, -1):
            key = lin[i]
            s = ((key * mult) >> (64 - bits)) & mask
            while True:
                v = table[s]
                if v == key:
                    break
                if v < 0:
                    table[s] = key
                    last[i] = True
                    break
                s = (s + 1) & mask
        for i in range(m):
            if last[i]:
                chosen[n_c] = i
                n_c += 1
    picked = np.empty((n_c, 3), dtype=np.float64)
    for i in range(n_c):
        for a in range(3):
            e = ends[chosen[i], a]
            picked[i, a] = e
            k = np.int64(np.floor(e * inv))
            bounds[0, a] = min(bounds[0, a], k)
            bounds[1, a] = max(bounds[1, a], k)
    if surface:
        sums = sums[:n_out].copy()
        counts = counts[:n_out].copy()
    return hit_keys, hit_mask, picked, cleared, dropped, True, bounds, n_hit, sums, counts


def _index_blocks(
    sorted_keys: np.ndarray, sorted_slots: np.ndarray, blocks: np.ndarray, first_free: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:
    """Slots of sorted, unique packed block keys `blocks` in a store's index (`sorted_keys`,
    with `sorted_slots`), as `BlockStore.ensure` computes them without free slots to reuse:
    missing blocks take slots `first_free`, `first_free` + 1, ... in key order. One merge walk.

    Returns the slots, the new blocks' keys, the index with them (the inputs themselves when
    none is new), and False when `blocks` are not sorted and unique (then nothing is valid)."""
    n_old = sorted_keys.size
    m = blocks.size
    slots = np.empty(m, dtype=np.int64)
    i = 0
    n_new = 0
    for j in range(m):
        b = blocks[j]
        if j > 0 and b <= blocks[j - 1]:
            return slots, blocks[:0], sorted_keys, sorted_slots, False
        while i < n_old and sorted_keys[i] < b:
            i += 1
        if i < n_old and sorted_keys[i] == b:
            slots[j] = sorted_slots[i]
        else:
            slots[j] = first_free + n_new
            n_new += 1
    if n_new == 0:
        return slots, blocks[:0], sorted_keys, sorted_slots, True
    new_keys = np.empty(n_new, dtype=np.int64)
    keys = np.empty(n_old + n_new, dtype=np.int64)
    held = np.empty(n_old + n_new, dtype=np.int64)
    i = 0
    k = 0
    out = 0
    for j in range(m):
        b = blocks[j]
        if slots[j] < first_free:
            continue  # held already
        while i < n_old and sorted_keys[i] < b:
            keys[out] = sorted_keys[i]
            held[out] = sorted_slots[i]
            i += 1
            out += 1
        keys[out] = b
        held[out] = slots[j]
        new_keys[k] = b
        k += 1
        out += 1
    while i < n_old:
        keys[out] = sorted_keys[i]
        held[out] = sorted_slots[i]
        i += 1
        out += 1
    return slots, new_keys, keys, held, True


def _fill_records(
    buf: np.ndarray,
    start: int,
    keys: np.ndarray,
    before: np.ndarray,
    after: np.ndarray,
    hit: np.ndarray,
    object_id: np.ndarray,
    object_prob: np.ndarray,
    shared: tuple[float, int, int, np.float32, np.float32, float, float, float, int],
) -> None:
    """Write one chunk's history records (RECORD_DTYPE) at `buf[start:]`, as `History.record`'s
    numpy path writes them: keys, log-odds after, the evidence of a hit or a miss, the state
    after and whether it flipped, object tags (none: `object_id` empty) and the columns the
    scan shares: `shared` = (time, agent, sensor, miss evidence, hit evidence, error,
    reliability, bias, version)."""
    time, agent, sensor, ev_free, ev_hit, error, reliability, bias, version = shared
    tagged = object_id.size == keys.size
    for i in range(keys.size):
        r = buf[start + i]
        r.key = keys[i]
        r.time = time
        r.agent = agent
        r.sensor = sensor
        r.evidence = ev_hit if hit[i] else ev_free
        a = after[i]
        b = before[i]
        r.logodds = a
        occupied = a >= 0
        r.state = 1 if occupied else 0
        r.flip = np.isnan(b) or ((b >= 0) != occupied)
        r.object_id = object_id[i] if tagged else -1
        r.object_prob = object_prob[i] if tagged else 0.0
        r.error = error
        r.reliability = reliability
        r.bias = bias
        r.version = version


# ------------------------------------------------------------------------------------------------
# The delta codec's key columns (protocol.deltacodec), loaded apart from the integration kernels
# above (their own lock and cache entry; the same COLONY_JIT switch and background mode).

_codec_lock = threading.Lock()
#: "keys", "voxels" -> the compiled `_wire_keys`, `_wire_voxels` (None: numba absent or failing);
#: empty until loaded.
_codec_compiled: dict[str, Callable[..., Any] | None] = {}


def wire_keys() -> Callable[..., Any] | None:
    """The compiled wire order and key columns of a delta (see `_wire_keys`), or None to use the
    numpy path. Loaded by the first call; after `load_in_background()` (a daemon) only by
    `warm_codec()`: a call never starts the loading, or a newcomer's first snapshot would decode
    beside numba's import (~0.3 s more CPU, a 1 M-voxel catch-up 0.43 -> 0.6 s)."""
    if not enabled():
        return None
    if "keys" not in _codec_compiled:
        if _loading.background:
            return None
        _load_codec()
    return _codec_compiled["keys"]


def wire_voxels() -> Callable[..., Any] | None:
    """The compiled keys of a decoded section (see `_wire_voxels`), or None to use the numpy
    path; loaded as `wire_keys()` loads."""
    return _codec_compiled["voxels"] if wire_keys() is not None else None


def warm_codec() -> bool:
    """Import numba and load (or compile and cache) the codec's kernel now, as `warm()` does the
    integration's; True when it is in use."""
    if not enabled():
        return False
    _load_codec()
    return _codec_compiled["keys"] is not None


def _load_codec() -> None:
    with _codec_lock:
        if "keys" in _codec_compiled:
            return
        found: dict[str, Callable[..., Any] | None] = {"keys": None, "voxels": None}
        try:
            import numba
        except ImportError:
            _codec_compiled.update(found)
            return
        try:
            keys, voxels = _compiled_or_in_memory(numba, (_wire_keys, _wire_voxels))
            one = np.zeros(2, dtype=np.float32)
            keys(np.array([[0, 0, 0], [5, 0, 1]], dtype=np.int64), one, one, 2, 4)
            voxels(  # bitmaps and gaps as a decoder has them: read-only views of bytes
                np.zeros((1, 3), dtype=np.int64),
                np.ones(1, dtype=np.int64),
                np.frombuffer(b"", dtype=np.uint8),
                np.frombuffer(b"\0\0", dtype="<u2"),
                1,
                4,
                vk.KEY_MIN,
            )
            found = {"keys": keys, "voxels": voxels}
        except Exception as exc:  # noqa: BLE001 - any numba failure leaves the numpy path
            log.warning("compiled codec kernels unavailable, using numpy: %s", exc)
        _codec_compiled["voxels"] = found["voxels"]
        _codec_compiled["keys"] = found["keys"]  # last: callers test for it first


#: Tiers of `protocol.deltacodec.Tier`, by value.
_OCCUPIED_NEW, _OCCUPIED, _CLEARED, _UNKNOWN, _FREE_NEW, _FREE = range(6)
#: `_wire_keys`' status: done, keys too spread out for its packed sort keys, a key twice.
WIRE_OK, WIRE_TOO_WIDE, WIRE_DUPLICATE = range(3)
#: A block with at least (block voxels) / this many voxels travels as a bitmap (as deltacodec).
_WIRE_BITMAP_DIVISOR = 16


def _wire_keys(
    keys: np.ndarray, lo: np.ndarray, prev: np.ndarray, mode: int, bs: int
) -> tuple[int, bool, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Wire order and key columns of keys (n, 3) (int64, within the key range), as
    `protocol.deltacodec` computes them: voxels by significance tier, then block (2**bs a side,
    x, y, z) and in-block offset (x-major), one section per tier present. `mode` 0: one section
    (a summary's keys; `lo`, `prev` unused); 1: tiers of the log-odds `lo` (float32); 2: tiers of
    `lo` and the values before, `prev` (float32).

    Returns (status, identity, perm, sections, blocks, counts, bitmaps, gaps): status WIRE_OK,
    else nothing else is valid (WIRE_TOO_WIDE: the caller takes the numpy path; WIRE_DUPLICATE:
    a key twice); identity when the keys are in wire order already; perm (n,) the wire order;
    per section a row of sections (S, 6): tier, voxels, blocks, and the ends of its blocks, of
    its bitmaps and of its gaps in the next columns; blocks (3, M) int32 each section's block
    keys, the first absolute and the rest as differences; counts (M,) uint16 voxels per block;
    bitmaps (D, block voxels / 8) uint8 of the dense blocks (bit order little); gaps (G,)
    uint16 the offsets of the sparse blocks' voxels, the first of a block absolute, the rest as
    differences. One sort: an LSD radix sort of one int64 per voxel (tier, block in the keys'
    box of blocks, offset)."""
    n = keys.shape[0]
    obits = 3 * bs
    nvox = np.int64(1) << obits
    emask = (np.int64(1) << bs) - 1
    perm = np.empty(n, dtype=np.int64)
    sections = np.zeros((0, 6), dtype=np.int64)
    blocks = np.zeros((3, 0), dtype=np.int32)
    counts = np.zeros(0, dtype=np.uint16)
    bitmaps = np.zeros((0, nvox >> 3), dtype=np.uint8)
    gaps = np.zeros(0, dtype=np.uint16)
    if n == 0:
        return WIRE_OK, True, perm, sections, blocks, counts, bitmaps, gaps
    bmin = np.empty(3, dtype=np.int64)
    bmax = np.empty(3, dtype=np.int64)
    for a in range(3):
        bmin[a] = keys[0, a] >> bs
        bmax[a] = bmin[a]
    for i in range(1, n):
        for a in range(3):
            b = keys[i, a] >> bs
            if b < bmin[a]:
                bmin[a] = b
            elif b > bmax[a]:
                bmax[a] = b
    dx = bmax[0] - bmin[0] + 1
    dy = bmax[1] - bmin[1] + 1
    dz = bmax[2] - bmin[2] + 1
    cells = dx * dy * dz
    if np.float64(dx) * np.float64(dy) * np.float64(dz) * np.float64(nvox) * 6.0 > 2.0**62:
        return WIRE_TOO_WIDE, False, perm, sections, blocks, counts, bitmaps, gaps
    # One sort key per voxel; in order already (and so distinct) when each exceeds the last.
    ka = np.empty(n, dtype=np.int64)
    present = np.zeros(6, dtype=np.int64)
    ordered = True
    last = np.int64(-1)
    for i in range(n):
        t = 0
        if mode != 0:
            v = lo[i]
            if v >= 0:
                t = _OCCUPIED if mode == 1 or prev[i] >= 0 else _OCCUPIED_NEW
            elif v < 0:
                if mode == 1:
                    t = _FREE
                else:
                    p = prev[i]
                    t = _CLEARED if p >= 0 else (_FREE_NEW if np.isnan(p) else _FREE)
            else:
                t = _UNKNOWN
        present[t] += 1
        x = keys[i, 0]
        y = keys[i, 1]
        z = keys[i, 2]
        lin = ((x >> bs) - bmin[0]) * dy + ((y >> bs) - bmin[1])
        lin = lin * dz + ((z >> bs) - bmin[2])
        off = ((x & emask) << (2 * bs)) | ((y & emask) << bs) | (z & emask)
        k = ((t * cells + lin) << obits) | off
        ka[i] = k
        if k <= last:
            ordered = False
        last = max(last, k)
        perm[i] = i
    if not ordered:
        # LSD radix sort over the bits in use (`last` is the largest key), digits of up to 12
        # bits (fewer for small n); every digit's histogram in one pass.
        bits = 1
        while (np.int64(1) << bits) <= last:
            bits += 1
        widest = 8
        while widest < 12 and (np.int64(1) << widest) < n:
            widest += 1
        passes = (bits + widest - 1) // widest
        d = (bits + passes - 1) // passes
        dmask = (np.int64(1) << d) - 1
        kb = np.empty(n, dtype=np.int64)
        ib = np.empty(n, dtype=np.int64)
        hist = np.zeros((passes, (np.int64(1) << d) + 1), dtype=np.int64)
        for i in range(n):
            k = ka[i]
            for q in range(passes):
                hist[q, ((k >> (q * d)) & dmask) + 1] += 1
        for q in range(passes):
            h = hist[q]
            if h.max() == n:  # every voxel has this digit: nothing moves
                continue
            for j in range(1, h.size):
                h[j] += h[j - 1]
            shift = q * d
            for i in range(n):
                j = (ka[i] >> shift) & dmask
                at = h[j]
                h[j] = at + 1
                kb[at] = ka[i]
                ib[at] = perm[i]
            ka, kb = kb, ka
            perm, ib = ib, perm
    # Blocks: runs of one (tier, block), a section per tier; a key twice is refused.
    n_sec = 0
    for t in range(6):
        if present[t]:
            n_sec += 1
    start = np.empty(n + 1, dtype=np.int64)
    start[0] = 0
    n_blocks = 1
    for i in range(1, n):
        if ka[i] == ka[i - 1]:
            return WIRE_DUPLICATE, False, perm, sections, blocks, counts, bitmaps, gaps
        if (ka[i] >> obits) != (ka[i - 1] >> obits):
            start[n_blocks] = i
            n_blocks += 1
    start[n_blocks] = n
    dense_at = nvox // _WIRE_BITMAP_DIVISOR
    n_dense = 0
    dense_voxels = 0
    for b in range(n_blocks):
        c = start[b + 1] - start[b]
        if c >= dense_at:
            n_dense += 1
            dense_voxels += c
    sections = np.zeros((n_sec, 6), dtype=np.int64)
    blocks = np.empty((3, n_blocks), dtype=np.int32)
    counts = np.empty(n_blocks, dtype=np.uint16)
    bitmaps = np.zeros((n_dense, nvox >> 3), dtype=np.uint8)
    gaps = np.empty(n - dense_voxels, dtype=np.uint16)
    s = -1
    tier_now = -1
    px = py = pz = np.int64(0)
    nd = 0
    ng = 0
    for b in range(n_blocks):
        head = ka[start[b]] >> obits
        t = head // cells
        lin = head - t * cells
        bz = lin % dz
        lin //= dz
        by = lin % dy
        bx = lin // dy + bmin[0]
        by += bmin[1]
        bz += bmin[2]
        if t != tier_now:
            s += 1
            tier_now = t
            sections[s, 0] = t
            blocks[0, b] = bx
            blocks[1, b] = by
            blocks[2, b] = bz
        else:
            blocks[0, b] = bx - px
            blocks[1, b] = by - py
            blocks[2, b] = bz - pz
        px = bx
        py = by
        pz = bz
        c = start[b + 1] - start[b]
        counts[b] = c
        sections[s, 1] += c
        sections[s, 2] += 1
        if c >= dense_at:
            for i in range(start[b], start[b + 1]):
                off = ka[i] & (nvox - 1)
                bitmaps[nd, off >> 3] |= np.uint8(1 << (off & 7))
            nd += 1
        else:
            prior = np.int64(0)
            for i in range(start[b], start[b + 1]):
                off = ka[i] & (nvox - 1)
                gaps[ng] = off - prior
                prior = off
                ng += 1
        sections[s, 3] = b + 1
        sections[s, 4] = nd
        sections[s, 5] = ng
    return WIRE_OK, ordered, perm, sections, blocks, counts, bitmaps, gaps


def _wire_voxels(
    blocks: np.ndarray,
    counts: np.ndarray,
    bitmaps: np.ndarray,
    gaps: np.ndarray,
    n: int,
    bs: int,
    key_min: int,
) -> tuple[bool, np.ndarray, np.ndarray]:
    """Keys (n, 3) of one section's voxels from its validated blocks (m, 3) (int64 keys) and
    counts (m,) (int64, 1..block voxels, summing to n), dense blocks' bitmaps (uint8, bit order
    little) and sparse blocks' offset gaps (uint16), as `protocol.deltacodec` decodes them; and
    each voxel's composite (its `_composite` with `key_min` the smallest key). False when the
    bitmaps or gaps are not valid (a bitmap's population is not its block's count, a zero gap
    after a block's first, an offset beyond the block): then nothing is valid and the caller's
    numpy path says why."""
    m = counts.shape[0]
    obits = 3 * bs
    nvox = np.int64(1) << obits
    emask = (np.int64(1) << bs) - 1
    axis = 21 - bs
    bb = nvox >> 3
    dense_at = nvox // _WIRE_BITMAP_DIVISOR
    keys = np.empty((n, 3), dtype=np.int64)
    comp = np.empty(n, dtype=np.int64)
    bmin = key_min >> bs
    at = 0
    nd = 0
    ng = 0
    for b in range(m):
        c = counts[b]
        bx = blocks[b, 0]
        by = blocks[b, 1]
        bz = blocks[b, 2]
        head = (((bx - bmin) << (2 * axis)) | ((by - bmin) << axis) | (bz - bmin)) << obits
        x0 = bx << bs
        y0 = by << bs
        z0 = bz << bs
        if c >= dense_at:
            base = nd * bb
            found = 0
            for j in range(bb):
                byte = np.int64(bitmaps[base + j])
                while byte != 0 and found < c:
                    low = byte & -byte
                    bit = 0
                    while (np.int64(1) << bit) != low:
                        bit += 1
                    off = (j << 3) + bit
                    keys[at + found, 0] = x0 + (off >> (2 * bs))
                    keys[at + found, 1] = y0 + ((off >> bs) & emask)
                    keys[at + found, 2] = z0 + (off & emask)
                    comp[at + found] = head | off
                    found += 1
                    byte ^= low
                if byte != 0:
                    return False, keys, comp
            if found != c:
                return False, keys, comp
            nd += 1
        else:
            pos = np.int64(-1)
            for i in range(c):
                g = np.int64(gaps[ng])
                ng += 1
                if i > 0 and g == 0:
                    return False, keys, comp
                pos = g if i == 0 else pos + g
                if pos >= nvox:
                    return False, keys, comp
                keys[at + i, 0] = x0 + (pos >> (2 * bs))
                keys[at + i, 1] = y0 + ((pos >> bs) & emask)
                keys[at + i, 2] = z0 + (pos & emask)
                comp[at + i] = head | pos
        at += c
    return True, keys, comp
