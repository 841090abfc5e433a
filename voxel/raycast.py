"""Ray traversal: the voxels each ray passes through (Amanatides-Woo, as OctoMap), vectorised over rays."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from voxel import keys as vk
from voxel.blocks import BLOCK, BLOCK_SHIFT, BLOCK_VOXELS, split_keys

FREE = np.uint8(1)
HIT = np.uint8(2)

_RUN_DTYPE = {2: np.uint16, 4: np.uint32, 8: np.uint64}[BLOCK]

#: Below this many active rays, remaining face crossings are enumerated in one flat pass.
FLAT_BELOW = 3000

#: Largest dense scratch volume (cells) before traversal falls back to sorting visited keys.
DENSE_LIMIT = 96_000_000


@dataclass
class Traversal:
    """Voxels touched by one scan, grouped by block: 0 untouched, 1 free, 2 hit."""

    blocks: np.ndarray  # (B,) packed block keys
    cells: np.ndarray  # (B, 512) uint8

    @property
    def free_count(self) -> int:
        return int(np.count_nonzero(self.cells == FREE))

    @property
    def hit_count(self) -> int:
        return int(np.count_nonzero(self.cells == HIT))


def _sweep(o: np.ndarray, e: np.ndarray, strides: np.ndarray, visit) -> None:
    """Visit the voxels rays o -> e enter, end voxel excluded; o and e in local voxel units (>= 0).

    A ray enters a new voxel exactly where it crosses a voxel face. For each axis, the crossings
    of the k-th face plane by all rays are computed at once: the plane fixes one key, the other
    two are the ray's coordinates there, which advance by a constant per plane. Rays are sorted
    by their number of crossings, so the rays of plane k are a prefix of the arrays: one numpy
    operation per plane for all rays, about ten per crossing, no branches.
    """
    if e.shape[0] == 0:
        return
    ko = np.floor(o).astype(np.int64)
    ke = np.floor(e).astype(np.int64)
    d = e - o
    counts = np.abs(ke - ko)  # (R, 3) face crossings per axis
    # The crossing that enters the end voxel is the latest one: drop it (OctoMap excludes the end).
    with np.errstate(divide="ignore", invalid="ignore"):
        last_plane = ko + (d > 0) + (counts - 1) * np.sign(d)
        t_last = np.where(counts > 0, (last_plane - o) / d, -np.inf)
    latest = np.argmax(t_last, axis=1)
    has = counts.sum(axis=1) > 0
    counts[np.flatnonzero(has), latest[has]] -= 1
    for a in range(3):
        b, c = [x for x in range(3) if x != a]
        m = counts[:, a]
        order = np.argsort(-m, kind="stable")
        m = m[order]
        if m[0] <= 0:
            continue
        n_rays = int(np.count_nonzero(m))
        order, m = order[:n_rays], m[:n_rays]
        da = d[order, a]
        sgn = np.sign(da)
        rb = d[order, b] / da
        rc = d[order, c] / da
        dist0 = ko[a] + (sgn > 0) - o[a]  # signed distance along axis a to the first face plane
        y = o[b] + dist0 * rb
        z = o[c] + dist0 * rc
        inc_y = sgn * rb
        inc_z = sgn * rc
        step_a = sgn.astype(np.int64) * strides[a]
        plane = ko[a] * strides[a] + step_a
        sb, sc = int(strides[b]), int(strides[c])
        active = n_rays - np.searchsorted(m[::-1], np.arange(int(m[0])), side="right")
        for k in range(int(m[0])):
            n = int(active[k])
            if n < FLAT_BELOW:
                # Few rays left: enumerate all their remaining crossings at once, no loop.
                left = m[:n] - k
                ray = np.repeat(np.arange(n), left)
                j = np.arange(ray.size) - np.repeat(np.cumsum(left) - left, left)
                lin = plane[ray] + j * step_a[ray]
                lin += (y[ray] + j * inc_y[ray]).astype(np.int64) * sb
                lin += (z[ray] + j * inc_z[ray]).astype(np.int64) * sc
                visit(lin)
                break
            lin = plane[:n] + y[:n].astype(np.int64) * sb
            lin += z[:n].astype(np.int64) * sc
            visit(lin)
            y[:n] += inc_y[:n]
            z[:n] += inc_z[:n]
            plane[:n] += step_a[:n]


def trace(
    origin: np.ndarray, ends: np.ndarray, hit_keys: np.ndarray, resolution: float
) -> Traversal:
    """Free voxels along rays origin -> ends (end voxel excluded) and hit voxels `hit_keys`.

    Each voxel appears once however many rays pass it; hits win over free, as in OctoMap.
    """
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    ends = np.asarray(ends, dtype=np.float64).reshape(-1, 3)
    hit_keys = np.asarray(hit_keys, dtype=np.int64).reshape(-1, 3)
    key_o = np.floor(origin * (1.0 / resolution)).astype(np.int64)
    key_e = np.floor(ends * (1.0 / resolution)).astype(np.int64)
    # A ray whose end lies in the origin voxel marks nothing (OctoMap returns an empty ray).
    cast = np.any(key_e != key_o, axis=1)
    all_keys = np.concatenate([key_o[None, :], key_e, hit_keys])
    kmin, kmax = vk.bounds(all_keys)
    lo = (kmin - 1) >> BLOCK_SHIFT << BLOCK_SHIFT
    hi = ((kmax + 1) >> BLOCK_SHIFT << BLOCK_SHIFT) + BLOCK
    dims = hi - lo
    strides = np.array([dims[1] * dims[2], dims[2], 1], dtype=np.int64)
    o_local = origin * (1.0 / resolution) - lo
    e_local = ends[cast] * (1.0 / resolution) - lo
    start = int(((key_o - lo) * strides).sum())
    total = int(np.prod(dims))

    if total <= DENSE_LIMIT:
        cells = np.zeros(total, dtype=np.uint8)
        if cast.any():
            cells[start] = FREE
        _sweep(o_local, e_local, strides, lambda lin: cells.__setitem__(lin, FREE))
        if hit_keys.size:
            cells[((hit_keys - lo) * strides).sum(axis=1)] = HIT
        nb = dims >> BLOCK_SHIFT
        c6 = cells.reshape(nb[0], BLOCK, nb[1], BLOCK, nb[2], BLOCK)
        runs = cells.view(_RUN_DTYPE) != 0  # one flag per BLOCK cells along z
        touched = runs.reshape(nb[0], BLOCK, nb[1], BLOCK, nb[2]).any(axis=(1, 3))
        bx, by, bz = np.nonzero(touched)
        vals = c6[bx, :, by, :, bz, :].reshape(-1, BLOCK_VOXELS)
        bkeys = np.stack([bx, by, bz], axis=1) + (lo >> BLOCK_SHIFT)
        return Traversal(blocks=vk.pack(bkeys), cells=vals)

    # Sparse fallback for very large extents: collect visited indices and sort them once.
    visited: list[np.ndarray] = [np.array([start], dtype=np.int64)] if cast.any() else []
    _sweep(o_local, e_local, strides, lambda lin: visited.append(lin.copy()))
    free_lin = np.unique(np.concatenate(visited)) if visited else np.empty(0, dtype=np.int64)
    free_keys = np.stack(np.unravel_index(free_lin, tuple(int(x) for x in dims)), axis=1) + lo
    return group_cells(free_keys, hit_keys)


def unique_keys(keys: np.ndarray, want_inverse: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """Unique voxel keys (U, 3) in packed-key order, and each input key's index into them.

    Uses a dense marker over the keys' bounding box when it is small (no sort), else np.unique.
    """
    keys = np.asarray(keys, dtype=np.int64).reshape(-1, 3)
    if keys.shape[0] == 0:
        return keys, (np.empty(0, dtype=np.int64) if want_inverse else None)
    lo, hi = vk.bounds(keys)
    dims = hi - lo + 1
    total = int(np.prod(dims))
    if total > DENSE_LIMIT:
        up, inverse = np.unique(vk.pack(keys), return_inverse=True)
        return vk.unpack(up), (inverse if want_inverse else None)
    lin = (keys[:, 0] - lo[0]) * (dims[1] * dims[2]) + (keys[:, 1] - lo[1]) * dims[2] + (keys[:, 2] - lo[2])
    mark = np.zeros(total, dtype=bool)
    mark[lin] = True
    ulin = np.flatnonzero(mark)
    uniq = np.stack(np.unravel_index(ulin, tuple(int(d) for d in dims)), axis=1) + lo
    return uniq, (np.searchsorted(ulin, lin) if want_inverse else None)


def group_cells(free_keys: np.ndarray, hit_keys: np.ndarray) -> Traversal:
    """A Traversal from explicit free and hit voxel keys (hits win)."""
    keys = np.concatenate([free_keys, hit_keys]).astype(np.int64)
    vals = np.concatenate([np.full(len(free_keys), FREE), np.full(len(hit_keys), HIT)]).astype(np.uint8)
    blocks, offsets = split_keys(keys)
    ub, inv = np.unique(blocks, return_inverse=True)
    cells = np.zeros((ub.size, BLOCK_VOXELS), dtype=np.uint8)
    np.maximum.at(cells, (inv, offsets), vals)
    return Traversal(blocks=ub, cells=cells)


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
