"""Ray traversal: the voxels each ray passes through (Amanatides-Woo, as OctoMap), vectorised over
rays."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from voxel import kernels, scratch
from voxel import keys as vk
from voxel.blocks import CUBE, split_keys

FREE = np.uint8(1)
HIT = np.uint8(2)

#: Cells of one block column along z, read as one unsigned integer to find touched blocks fast.
_RUN_DTYPE = {1: np.uint8, 2: np.uint16, 4: np.uint32, 8: np.uint64}

#: Below this many active crossing sequences, the remaining crossings are enumerated in one pass.
FLAT_BELOW = 3000
#: Crossings enumerated per chunk of that pass.
FLAT_CHUNK = 1 << 14

#: The compiled traversal reads its box for the touched blocks when the box has at most this many
#: 8-byte words of cells per ray crossing (else it marks blocks as it marks cells).
SCAN_RATIO = 1.0

#: Largest dense scratch volume (cells); a scan whose box is larger is split into wedges.
DENSE_LIMIT = 96_000_000
#: Wedges per split, and the fewest rays worth splitting (fewer are traced sparsely).
SPLIT_WAYS = 4
SPLIT_MIN_RAYS = 64


@dataclass
class Traversal:
    """Voxels touched by one scan, grouped by block (0 untouched, 1 free, 2 hit), and its hit
    voxels."""

    blocks: np.ndarray  # (B,) packed block keys
    cells: np.ndarray  # (B, block voxels) uint8
    hit_keys: np.ndarray  # (U, 3) int64 unique hit voxel keys, in packed-key order
    inverse: np.ndarray | None = None  # (N,) each hit point's row in hit_keys, when asked for
    free: int = -1  # FREE cells, when counted on the way (-1: count them when asked)

    @property
    def free_count(self) -> int:
        return self.free if self.free >= 0 else int(np.count_nonzero(self.cells == FREE))

    @property
    def hit_count(self) -> int:
        return int(self.hit_keys.shape[0])


def _sequences(o: np.ndarray, e: np.ndarray, strides: np.ndarray) -> tuple[np.ndarray, ...]:
    """Every (ray, axis) run of face crossings of rays o -> e, end voxel excluded, as arrays.

    Crossing k of a run enters the voxel at linear index
    plane + k * step + floor(y + k * inc_y) * stride_y + floor(z + k * inc_z) * stride_z,
    where the run's axis fixes `plane` exactly and y, z are the ray's other two coordinates
    on that face plane (a coordinate the ray never changes layer in is folded into `plane`, its
    stride 0; z is such a one whenever y is). Runs come sorted by length, longest first.
    """
    ko = np.floor(o).astype(np.int64)
    ke = np.floor(e).astype(np.int64)
    d = e - o
    counts = np.abs(ke - ko)  # (R, 3) face crossings per axis
    stays = counts == 0  # the ray never leaves the origin's voxel layer along this axis
    # The crossing that enters the end voxel is the latest one: drop it (OctoMap excludes the end).
    with np.errstate(divide="ignore", invalid="ignore"):
        last_plane = ko + (d > 0) + (counts - 1) * np.sign(d)
        t_last = np.where(counts > 0, (last_plane - o) / d, -np.inf)
    latest = np.argmax(t_last, axis=1)
    has = np.flatnonzero(counts.sum(axis=1) > 0)
    counts[has, latest[has]] -= 1
    parts: list[list[np.ndarray]] = []
    for a in range(3):
        b, c = [x for x in range(3) if x != a]
        sel = np.flatnonzero(counts[:, a] > 0)
        if sel.size == 0:
            continue
        da = d[sel, a]
        sgn = np.sign(da)
        dist0 = ko[a] + (sgn > 0) - o[a]  # signed distance along axis a to the first face plane
        step = sgn.astype(np.int64) * strides[a]
        plane = ko[a] * strides[a] + step
        # Order the other two axes so that a fixed one comes second (y moves, z may not).
        swap = stays[sel, b] & ~stays[sel, c]
        b_ax = np.where(swap, c, b)
        c_ax = np.where(swap, b, c)
        rb = d[sel, b_ax] / da
        rc = d[sel, c_ax] / da
        fixed = stays[sel, c_ax]
        fixed_b = stays[sel, b_ax]  # only with z fixed too (a ray along one axis)
        # A fixed axis contributes a constant: fold it into the plane term.
        plane += np.where(fixed, ko[c_ax] * strides[c_ax], 0) + np.where(
            fixed_b, ko[b_ax] * strides[b_ax], 0
        )
        parts.append(
            [
                counts[sel, a],
                plane,
                step,
                np.where(fixed_b, 0.5, o[b_ax] + dist0 * rb),
                np.where(fixed_b, 0.0, sgn * rb),
                np.where(fixed, 0.5, o[c_ax] + dist0 * rc),
                np.where(fixed, 0.0, sgn * rc),
                np.where(fixed_b, 0, strides[b_ax]),
                np.where(fixed, 0, strides[c_ax]),
            ]
        )
    if not parts:
        return ()
    cols = [np.concatenate(x) for x in zip(*parts, strict=True)]
    longest = int(cols[0].max())
    # A stable sort of 16-bit integers is a radix sort: much faster than sorting int64.
    order = np.argsort(-(cols[0].astype(np.int16) if longest < 2**15 else cols[0]), kind="stable")
    return tuple(x[order] for x in cols)


def _sweep(
    o: np.ndarray, e: np.ndarray, strides: np.ndarray, visit: Callable[[np.ndarray], None]
) -> None:
    """Visit the linear indices of the voxels rays o -> e enter, end voxel excluded.

    o and e are in local voxel units (>= 0). A ray enters a new voxel exactly where it crosses a
    voxel face; the crossings of one ray with one axis's face planes form a run whose coordinates
    advance by constants. All runs of all axes advance together, one numpy operation per step
    for every run still going (runs are sorted by length, so those are a prefix); when few runs
    remain, their remaining crossings are enumerated at once.
    """
    if e.shape[0] == 0:
        return
    seqs = _sequences(o, e, strides)
    if not seqs:
        return
    m, plane, step, y, inc_y, z, inc_z, sy, sz = seqs
    z_moves = bool(sz.any())  # else every run's z is fixed (a planar scan): skip it
    active = m.size - np.searchsorted(m[::-1], np.arange(int(m[0])), side="right")
    for k in range(int(m[0])):
        n = int(active[k])
        if n < FLAT_BELOW:
            left = m[:n] - k
            ends = np.cumsum(left)
            # Chunks of about FLAT_CHUNK crossings keep the temporaries in cache.
            cuts = np.unique(
                np.searchsorted(
                    ends, np.arange(FLAT_CHUNK, int(ends[-1]), FLAT_CHUNK), side="right"
                )
            )
            for lo, hi in zip([0, *cuts.tolist()], [*cuts.tolist(), n], strict=True):
                if hi > lo:
                    runs = (
                        plane[lo:hi],
                        step[lo:hi],
                        y[lo:hi],
                        inc_y[lo:hi],
                        z[lo:hi],
                        inc_z[lo:hi],
                        sy[lo:hi],
                        sz[lo:hi],
                    )
                    visit(_enumerate(left[lo:hi], runs, z_moves))
            return
        lin = y[:n].astype(np.int64)
        lin *= sy[:n]
        lin += plane[:n]
        if z_moves:
            t = z[:n].astype(np.int64)
            t *= sz[:n]
            lin += t
            z[:n] += inc_z[:n]
        visit(lin)
        y[:n] += inc_y[:n]
        plane[:n] += step[:n]


def _enumerate(left: np.ndarray, runs: tuple[np.ndarray, ...], z_moves: bool) -> np.ndarray:
    """Linear indices of the next `left[i]` crossings of each run, all at once."""
    plane, step, y, inc_y, z, inc_z, sy, sz = runs
    j = np.arange(int(left.sum())) - np.repeat(np.cumsum(left) - left, left)
    lin = np.repeat(plane, left) + j * np.repeat(step, left)
    jf = j.astype(np.float64)
    lin += (np.repeat(y, left) + jf * np.repeat(inc_y, left)).astype(np.int64) * np.repeat(sy, left)
    if z_moves:
        lin += (np.repeat(z, left) + jf * np.repeat(inc_z, left)).astype(np.int64) * np.repeat(
            sz, left
        )
    out: np.ndarray = lin
    return out


def _box(
    origin_key: np.ndarray, *key_rows: np.ndarray, shifts: tuple[int, int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Block-aligned lower corner and dims of a box holding the origin key and key rows (3, N)."""
    lo = origin_key.copy()
    hi = origin_key.copy()
    for rows in key_rows:
        if rows.shape[1]:
            for a in range(3):
                lo[a] = min(lo[a], int(rows[a].min()))
                hi[a] = max(hi[a], int(rows[a].max()))
    # A voxel of margin guards rounding at the box's faces; an axis on which every key is the
    # same needs none (rays stay in that layer, and the sweep folds it in exactly).
    margin = (lo != hi).astype(np.int64)
    sh = np.asarray(shifts, dtype=np.int64)
    lo = (lo - margin) >> sh << sh
    hi = ((hi + margin) >> sh << sh) + (1 << sh)
    return lo, hi - lo


def _box_of_bounds(
    origin_key: np.ndarray, bounds: np.ndarray, shifts: tuple[int, int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """`_box` of the origin key and the lowest and highest keys `bounds` (2, 3) (low > high:
    none), in Python integers: a small scan's box costs microseconds, not a dozen numpy calls."""
    ko = origin_key.tolist()
    (l0, l1, l2), (h0, h1, h2) = np.asarray(bounds, dtype=np.int64).tolist()
    lows, highs = (ko, ko) if l0 > h0 else ([l0, l1, l2], [h0, h1, h2])
    lo = []
    dims = []
    for a in range(3):
        low = min(ko[a], lows[a])
        high = max(ko[a], highs[a])
        margin = int(low != high)
        sh = shifts[a]
        start = (low - margin) >> sh << sh
        lo.append(start)
        dims.append(((high + margin) >> sh << sh) + (1 << sh) - start)
    return np.array(lo, dtype=np.int64), np.array(dims, dtype=np.int64)


def trace(
    origin: np.ndarray,
    hit_keys: np.ndarray,
    clear_ends: np.ndarray,
    resolution: float,
    shifts: tuple[int, int, int] = CUBE,
    want_inverse: bool = False,
    bounds: np.ndarray | None = None,
) -> Traversal:
    """One scan's free and hit voxels: a ray from `origin` to each distinct hit voxel's centre and
    to each of `clear_ends` (world points); free voxels along rays (end voxel excluded), hits win.

    `hit_keys` are the hit points' voxel keys as rows (3, N) (float or int, exact integers).
    Each voxel appears once however many rays pass it, as in OctoMap's update. `bounds` (2, 3),
    when given, are the lowest and highest key of the hits and of the clear ends (saves
    reading them all again).
    """
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    hk = np.asarray(hit_keys, dtype=np.float64).reshape(3, -1)
    clear = np.asarray(clear_ends, dtype=np.float64).reshape(-1, 3)
    inv = 1.0 / resolution
    o_scaled = origin * inv
    key_o = np.floor(o_scaled).astype(np.int64)
    clear_scaled = clear * inv
    if bounds is None:
        clear_keys = np.floor(clear_scaled).astype(np.int64)
        lo, dims = _box(key_o, hk, clear_keys.T, shifts=shifts)
    else:
        lo, dims = _box_of_bounds(key_o, bounds, shifts)
    total = int(dims[0]) * int(dims[1]) * int(dims[2])
    if total > DENSE_LIMIT:
        packed, inverse = np.unique(vk.pack(hk.T.astype(np.int64)), return_inverse=True)
        uniq = vk.unpack(packed)
        blocks, cells = _split(origin, uniq, clear, resolution, shifts)
        return Traversal(
            blocks=blocks, cells=cells, hit_keys=uniq, inverse=inverse if want_inverse else None
        )

    compiled = kernels.trace()
    if compiled is not None:
        sh = np.asarray(shifts, dtype=np.int64)
        n_blocks = total >> (shifts[0] + shifts[1] + shifts[2])
        cells = scratch.take("cells", total, np.uint8)
        marks = scratch.take("marks", n_blocks, np.uint8)
        touched = scratch.take("touched", n_blocks, np.int64)
        blocks, vals, uniq, rows, free = compiled(
            o_scaled - lo,
            np.ascontiguousarray(hk),
            clear_scaled,
            key_o,
            lo,
            dims,
            sh,
            FLAT_BELOW,
            cells,
            marks,
            touched,
            want_inverse,
            SCAN_RATIO,
        )
        scratch.give("cells", cells)
        scratch.give("marks", marks)
        scratch.give("touched", touched)
        return Traversal(
            blocks=blocks,
            cells=vals,
            hit_keys=uniq,
            inverse=rows if want_inverse else None,
            free=free,
        )
    clear_keys = np.floor(clear_scaled).astype(np.int64)
    strides = np.array([dims[1] * dims[2], dims[2], 1], dtype=np.int64)
    buf = np.zeros(-(-total // 8) * 8, dtype=np.uint8)  # whole 8-byte words, for `_marked`
    cells = buf[:total]
    # Exact integers in float64 (below 2**53): the same values as a matmul, without BLAS.
    lin_f = hk[0] * float(strides[0])
    lin_f += hk[1] * float(strides[1])
    lin_f += hk[2]  # strides[2] is 1
    lin_f -= float(strides @ lo)
    lin = lin_f.astype(np.int64)
    cells[lin] = HIT
    hit_lin = _marked(buf)
    local = np.empty((hit_lin.size, 3), dtype=np.int64)
    local[:, 0], rest = np.divmod(hit_lin, strides[0])
    local[:, 1], local[:, 2] = np.divmod(rest, strides[1])
    start = int((key_o - lo) @ strides)
    hit_cast = hit_lin != start  # a ray whose end lies in the origin voxel marks nothing
    clear_cast = np.any(clear_keys != key_o, axis=1)
    ends = np.concatenate([local[hit_cast] + 0.5, clear_scaled[clear_cast] - lo])
    cells[hit_lin] = 0
    _sweep(o_scaled - lo, ends, strides, lambda x: cells.__setitem__(x, FREE))
    if ends.shape[0]:
        cells[start] = FREE
    cells[hit_lin] = HIT
    blocks, vals = _blocks_of(buf, dims, lo, shifts)
    point_rows = np.searchsorted(hit_lin, lin) if want_inverse else None
    return Traversal(blocks=blocks, cells=vals, hit_keys=local + lo, inverse=point_rows)


def _marked(buf: np.ndarray, words: np.ndarray | None = None) -> np.ndarray:
    """Sorted indices of the non-zero cells of a contiguous uint8 array of whole 8-byte words.

    Scans 8 cells per step: far faster than np.flatnonzero when few cells are marked.
    """
    if words is None:
        words = np.flatnonzero(buf.view(np.uint64))
    r, c = np.nonzero(buf.reshape(-1, 8)[words])
    return words[r] * 8 + c


def _blocks_of(
    buf: np.ndarray, dims: np.ndarray, lo: np.ndarray, shifts: tuple[int, int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Packed keys and cells (B, block voxels) of the blocks of a dense box that hold a mark.

    A box with few marks (long rays, thin scans) is read through its marked cells; a well
    filled one block column by block column.
    """
    sx, sy, sz = shifts
    nb = dims >> np.asarray(shifts)
    cells = buf[: int(np.prod(dims))]
    c6 = cells.reshape(nb[0], 1 << sx, nb[1], 1 << sy, nb[2], 1 << sz)
    words = np.flatnonzero(buf.view(np.uint64))
    if words.size * 48 << sz < cells.size:
        lin = _marked(buf, words)
        x, rest = np.divmod(lin, dims[1] * dims[2])
        y, z = np.divmod(rest, dims[2])
        x >>= sx
        x *= nb[1]
        x += y >> sy
        x *= nb[2]
        x += z >> sz
        mark = np.zeros(int(np.prod(nb)), dtype=bool)
        mark[x] = True
        bx, rest = np.divmod(np.flatnonzero(mark), nb[1] * nb[2])
        by, bz = np.divmod(rest, nb[2])
    else:
        runs = cells.view(_RUN_DTYPE[1 << sz]) != 0  # one flag per block column along z
        r5 = runs.reshape(nb[0], 1 << sx, nb[1], 1 << sy, nb[2])
        rows = r5[:, 0].copy()  # OR over the block's x and y offsets: elementwise on views, fast
        for i in range(1, 1 << sx):
            rows |= r5[:, i]
        touched = rows[:, :, 0].copy()
        for i in range(1, 1 << sy):
            touched |= rows[:, :, i]
        bx, by, bz = np.nonzero(touched)
    return _gather(c6, bx, by, bz, lo, shifts)


def _gather(
    c6: np.ndarray,
    bx: np.ndarray,
    by: np.ndarray,
    bz: np.ndarray,
    lo: np.ndarray,
    shifts: tuple[int, int, int],
) -> tuple[np.ndarray, np.ndarray]:
    vals = c6[bx, :, by, :, bz, :].reshape(bx.size, 1 << sum(shifts))
    bkeys = np.stack([bx, by, bz], axis=1) + (lo >> np.asarray(shifts))
    return vk.pack(bkeys), vals


def _split(
    origin: np.ndarray,
    uniq: np.ndarray,
    clear: np.ndarray,
    resolution: float,
    shifts: tuple[int, int, int],
) -> tuple[np.ndarray, np.ndarray]:
    """Blocks and cells of rays to unique hit voxels `uniq` (U, 3) and to `clear` ends whose box is
    too large for one dense scratch volume: the rays are split into wedges around the origin (by
    angle about the box's thinnest axis), each traced on its own, and the results merged (a
    voxel's marks combine, hits win). A few rays with a huge box are traced sparsely."""
    n_hit = uniq.shape[0]
    if n_hit + clear.shape[0] < SPLIT_MIN_RAYS:
        return _trace_sparse(origin, uniq, clear, resolution, shifts)
    o = origin * (1.0 / resolution)
    dirs = np.concatenate([uniq + 0.5, clear * (1.0 / resolution)]) - o
    extent = dirs.max(axis=0) - dirs.min(axis=0)
    a, b = [x for x in range(3) if x != int(np.argmin(extent))]
    order = np.argsort(np.arctan2(dirs[:, b], dirs[:, a]), kind="stable")
    blocks: list[np.ndarray] = []
    cells: list[np.ndarray] = []
    for part in np.array_split(order, SPLIT_WAYS):
        hits, clears = part[part < n_hit], part[part >= n_hit] - n_hit
        tr = trace(origin, uniq[hits].T, clear[clears], resolution, shifts)
        blocks.append(tr.blocks)
        cells.append(tr.cells)
    all_blocks = np.concatenate(blocks)
    order = np.argsort(all_blocks, kind="stable")
    sorted_blocks = all_blocks[order]
    starts = np.flatnonzero(np.r_[True, sorted_blocks[1:] != sorted_blocks[:-1]])
    return sorted_blocks[starts], np.maximum.reduceat(np.concatenate(cells)[order], starts, axis=0)


def _trace_sparse(
    origin: np.ndarray,
    uniq: np.ndarray,
    clear: np.ndarray,
    resolution: float,
    shifts: tuple[int, int, int],
) -> tuple[np.ndarray, np.ndarray]:
    """Blocks and cells of a few rays with a huge box: visited keys are collected and sorted."""
    o_scaled = origin * (1.0 / resolution)
    key_o = np.floor(o_scaled).astype(np.int64)
    clear_scaled = clear * (1.0 / resolution)
    clear_keys = np.floor(clear_scaled).astype(np.int64)
    lo, dims = _box(key_o, uniq.T, clear_keys.T, shifts=(0, 0, 0))
    strides = np.array([dims[1] * dims[2], dims[2], 1], dtype=np.int64)
    hit_cast = np.any(uniq != key_o, axis=1)
    clear_cast = np.any(clear_keys != key_o, axis=1)
    ends = np.concatenate([uniq[hit_cast] + 0.5 - lo, clear_scaled[clear_cast] - lo])
    visited: list[np.ndarray] = [np.array([int((key_o - lo) @ strides)])] if ends.shape[0] else []
    _sweep(o_scaled - lo, ends, strides, lambda x: visited.append(x.copy()))
    free_lin = np.unique(np.concatenate(visited)) if visited else np.empty(0, dtype=np.int64)
    free_keys = np.stack(np.unravel_index(free_lin, tuple(int(x) for x in dims)), axis=1) + lo
    return group_cells(free_keys, uniq, shifts)


def group_cells(
    free_keys: np.ndarray, hit_keys: np.ndarray, shifts: tuple[int, int, int] = CUBE
) -> tuple[np.ndarray, np.ndarray]:
    """Packed block keys and cells (B, block voxels) of explicit free and hit voxel keys (hits
    win)."""
    keys = np.concatenate([free_keys, hit_keys]).astype(np.int64)
    vals = np.concatenate([np.full(len(free_keys), FREE), np.full(len(hit_keys), HIT)]).astype(
        np.uint8
    )
    blocks, offsets = split_keys(keys, shifts)
    ub, inv = np.unique(blocks, return_inverse=True)
    cells = np.zeros((ub.size, 1 << sum(shifts)), dtype=np.uint8)
    np.maximum.at(cells, (inv, offsets), vals)
    return ub, cells


def ray_keys(origin: np.ndarray, end: np.ndarray, resolution: float) -> np.ndarray:
    """Keys (M, 3) of the voxels one ray passes, in order from the origin voxel to the end voxel.

    Every face crossing enters a voxel: per axis the crossings form an arithmetic sequence of ray
    parameters, so all of them are computed at once and merged by parameter.
    """
    o = np.asarray(origin, dtype=np.float64).reshape(3) * (1.0 / resolution)
    e = np.asarray(end, dtype=np.float64).reshape(3) * (1.0 / resolution)
    ko = np.floor(o).astype(np.int64)
    ke = np.floor(e).astype(np.int64)
    d = e - o
    params = [np.zeros(1)]
    keys = [ko[None, :]]
    for a in range(3):
        m = int(abs(ke[a] - ko[a]))
        if m == 0:
            continue
        sgn = 1 if d[a] > 0 else -1
        j = np.arange(m)
        t = (ko[a] + (sgn > 0) + sgn * j - o[a]) / d[a]
        entered = np.floor(o + t[:, None] * d).astype(np.int64)
        entered[:, a] = ko[a] + sgn * (j + 1)  # the plane fixes this axis exactly
        params.append(t)
        keys.append(entered)
    order = np.argsort(np.concatenate(params), kind="stable")
    return np.concatenate(keys)[order]
