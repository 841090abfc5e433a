"""Compiled kernels (numba, the optional `fast` extra) for integration's hot loops, loaded lazily.

`sweep()` (the traversal's dense sweep) and `occupancy()` (the occupancy update of a chunk of
blocks) return a compiled kernel, or None when numba is absent, fails, or `COLONY_JIT=0`; the
callers then run their pure-numpy path, which gives bit-identical results (the kernels repeat
its floating-point operations one for one). Importing numba and loading the cached machine code
take ~0.5 s of CPU, so nothing here happens at import: `warm()` does it, off the hot path (a
daemon calls it in a background thread once ready), and the first call otherwise.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

#: Environment variable that turns the compiled kernels off ("0"), e.g. to compare both paths.
JIT_ENV = "COLONY_JIT"

_lock = threading.Lock()
#: Name -> compiled kernel (None: numba absent); empty until loaded.
_compiled: dict[str, Callable[..., Any] | None] = {}


def enabled() -> bool:
    """True unless the compiled kernels are turned off with COLONY_JIT=0."""
    return os.environ.get(JIT_ENV, "1") != "0"


def _get(name: str) -> Callable[..., Any] | None:
    if not enabled():
        return None
    if "sweep" not in _compiled:
        _load()
    return _compiled[name]


def sweep() -> Callable[..., Any] | None:
    """The compiled dense sweep (see `_sweep_dense`), or None to use the numpy path."""
    return _get("sweep")


def occupancy() -> Callable[..., Any] | None:
    """The compiled occupancy update of a chunk of blocks (see `_update_blocks`), or None."""
    return _get("occupancy")


def warm() -> bool:
    """Import numba and load (or compile and cache) the kernels now; True when they are in use."""
    return sweep() is not None


def _try_out(sweep: Callable[..., Any], update: Callable[..., Any]) -> None:
    """One tiny call of each kernel: compiles (or loads) them, so a failure shows here."""
    sweep(
        np.array([0.5, 0.5, 0.5]),
        np.array([[3.5, 2.5, 0.5]]),
        np.array([16, 4, 1], dtype=np.int64),
        np.array([4, 4, 4], dtype=np.int64),
        np.array([1, 1, 1], dtype=np.int64),
        3000,
        np.zeros(64, dtype=np.uint8),
        np.zeros(0, dtype=np.int64),
        0,
    )
    lo = np.full((1, 1), np.nan, dtype=np.float32)
    stamp = np.zeros((1, 1), dtype=np.uint32)
    steps = np.zeros(3, dtype=np.float32)
    bound = np.float32(1.0)
    slots = np.zeros(1, dtype=np.int64)
    cells = np.ones((1, 1), dtype=np.uint8)
    update(lo, stamp.copy(), stamp, stamp[0], slots, cells, steps, -bound, bound, 1, 0)


def _load() -> None:
    with _lock:
        if "sweep" in _compiled:
            return
        found: dict[str, Callable[..., Any] | None] = {"occupancy": None, "sweep": None}
        try:
            import numba
        except ImportError:
            _compiled.update(found)
            return
        try:
            try:
                jit = numba.njit(cache=True, nogil=True)
                kernels = jit(_update_blocks), jit(_sweep_dense)
            except RuntimeError:  # no writable cache directory: compile at every start
                log.warning("numba cannot cache here (set NUMBA_CACHE_DIR); compiling in memory")
                jit = numba.njit(nogil=True)
                kernels = jit(_update_blocks), jit(_sweep_dense)
            _try_out(kernels[1], kernels[0])
            found = {"occupancy": kernels[0], "sweep": kernels[1]}
        except Exception as exc:  # noqa: BLE001 - any numba failure leaves the numpy path
            log.warning("compiled kernels unavailable, using numpy: %s", exc)
        # "sweep" last: callers test for it before asking for the others.
        _compiled["occupancy"] = found["occupancy"]
        _compiled["sweep"] = found["sweep"]


def _sweep_dense(
    o: np.ndarray,
    ends: np.ndarray,
    strides: np.ndarray,
    dims: np.ndarray,
    shifts: np.ndarray,
    flat_below: int,
    cells: np.ndarray,
    hit_lin: np.ndarray,
    start: int,
) -> np.ndarray:
    """Mark FREE the cells of a dense box (row-major, `cells` uint8) that rays o -> ends enter,
    end voxel excluded, leaving HIT cells (already marked, at `hit_lin`) as they are; the origin
    voxel `start` (-1 none) is free when any ray is cast. Returns the sorted row-major indices
    of the blocks (side 1 << shifts) holding a mark.

    Written for numba: the arithmetic of `raycast._sequences`, `_sweep` and `_enumerate` per
    run, in the same order, so the visited voxels are bit-identical to the numpy path's. Runs
    step by accumulation up to the step `k_flat` at which the numpy sweep has fewer than
    `flat_below` runs left, and are enumerated by multiplication from there, as it does.
    """
    n_rays = ends.shape[0]
    ko0 = np.int64(np.floor(o[0]))
    ko1 = np.int64(np.floor(o[1]))
    ko2 = np.int64(np.floor(o[2]))
    ko = np.array([ko0, ko1, ko2], dtype=np.int64)
    nb = np.empty(3, dtype=np.int64)
    for a in range(3):
        nb[a] = dims[a] >> shifts[a]
    bstride = np.array([nb[1] * nb[2], nb[2], 1], dtype=np.int64)
    marks = np.zeros(nb[0] * nb[1] * nb[2], dtype=np.uint8)
    counts = np.empty((n_rays, 3), dtype=np.int64)
    # Pass 1: each ray's crossings per axis, the end voxel's crossing dropped.
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
    for r in range(n_rays):
        for a in range(3):
            if counts[r, a] > 0:
                hist[counts[r, a]] += 1
                runs += 1
    k_flat = 0
    if runs >= flat_below:
        seen = 0
        for v in range(longest, 0, -1):
            seen += hist[v]
            if seen >= flat_below:
                k_flat = v
                break
    touched = np.empty(marks.size, dtype=np.int64)
    n_touched = 0
    # Hit cells and the origin voxel mark their blocks.
    for i in range(hit_lin.size):
        x = hit_lin[i] // strides[0]
        rest = hit_lin[i] - x * strides[0]
        y = rest // strides[1]
        z = rest - y * strides[1]
        blk = (x >> shifts[0]) * bstride[0] + (y >> shifts[1]) * bstride[1] + (z >> shifts[2])
        if marks[blk] == 0:
            marks[blk] = 1
            touched[n_touched] = blk
            n_touched += 1
    if n_rays > 0 and start >= 0:
        if cells[start] == 0:
            cells[start] = 1
        blk = (ko0 >> shifts[0]) * bstride[0] + (ko1 >> shifts[1]) * bstride[1] + (ko2 >> shifts[2])
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
            y = y0
            z = z0
            for k in range(m):
                if k < k_flat:
                    yv = np.int64(y)
                    zv = np.int64(z)
                    y += inc_y
                    z += inc_z
                else:
                    jf = np.float64(k - k_flat)
                    yv = np.int64(y + jf * inc_y)
                    zv = np.int64(z + jf * inc_z)
                xa = ko[a] + (k + 1) * isgn
                xb = ko[b] if stay_b else yv
                xc = ko[c] if stay_c else zv
                lin = xa * strides[a] + xb * strides[b] + xc * strides[c]
                if cells[lin] != 0:
                    continue  # marked before, and so was its block
                cells[lin] = 1
                blk = (
                    (xa >> shifts[a]) * bstride[a]
                    + (xb >> shifts[b]) * bstride[b]
                    + (xc >> shifts[c]) * bstride[c]
                )
                if marks[blk] == 0:
                    marks[blk] = 1
                    touched[n_touched] = blk
                    n_touched += 1
    return np.sort(touched[:n_touched])


def _update_blocks(
    logodds: np.ndarray,
    version: np.ndarray,
    last_time: np.ndarray,
    slot_version: np.ndarray,
    slots: np.ndarray,
    cells: np.ndarray,
    steps: np.ndarray,
    low: np.float32,
    high: np.float32,
    v: int,
    stamp: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """One scan's occupancy update of blocks `slots` (cells (B, V): 0 untouched, else the
    index of its log-odds step), without decay or statistics, as `occupancy._update_chunk`'s
    numpy path does it: each touched voxel's value becomes clip(value or 0 + step); changed
    voxels take version `v` and time `stamp`; nothing is written when nothing changed.
    Returns log-odds before and after (B, V), the changed mask and the count of changed."""
    n_blocks, n_vox = cells.shape
    old = np.empty((n_blocks, n_vox), dtype=np.float32)
    new = np.empty((n_blocks, n_vox), dtype=np.float32)
    changed = np.zeros((n_blocks, n_vox), dtype=np.bool_)
    count = 0
    for i in range(n_blocks):
        s = slots[i]
        for j in range(n_vox):
            before = logodds[s, j]
            old[i, j] = before
            c = cells[i, j]
            if c == 0:
                new[i, j] = before
                continue
            known = not np.isnan(before)
            after = (before if known else np.float32(0.0)) + steps[c]
            after = min(max(after, low), high)
            new[i, j] = after
            if not known or after != before:
                changed[i, j] = True
                count += 1
    if count == 0:
        return old, new, changed, 0
    for i in range(n_blocks):
        s = slots[i]
        hit_block = False
        for j in range(n_vox):
            if cells[i, j] != 0:
                logodds[s, j] = new[i, j]
            if changed[i, j]:
                version[s, j] = v
                last_time[s, j] = stamp
                hit_block = True
        if hit_block:
            slot_version[s] = v
    return old, new, changed, count
