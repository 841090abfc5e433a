"""Ray traversal: the voxels each ray passes through (Amanatides-Woo, as OctoMap), vectorised over rays."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from voxel import keys as vk
from voxel.blocks import BLOCK, BLOCK_SHIFT, BLOCK_VOXELS

FREE = np.uint8(1)
HIT = np.uint8(2)

_RUN_DTYPE = {2: np.uint16, 4: np.uint32, 8: np.uint64}[BLOCK]

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


def _ray_setup(origin: np.ndarray, ends: np.ndarray, resolution: float):
    """Per-ray DDA state: start key, end keys, step signs, tMax and tDelta (OctoMap computeRayKeys)."""
    key_o = np.floor(origin / resolution).astype(np.int64)
    key_e = np.floor(ends / resolution).astype(np.int64)
    d = ends - origin
    length = np.linalg.norm(d, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        dn = d / length[:, None]
        step = np.sign(dn).astype(np.int64)
        border = (key_o + 0.5 + 0.5 * step) * resolution
        t_max = np.where(step != 0, (border - origin) / dn, np.inf)
        t_delta = np.where(step != 0, resolution / np.abs(dn), np.inf)
    n_steps = np.abs(key_e - key_o).sum(axis=1)
    return key_o, key_e, step, t_max, t_delta, n_steps


def _walk(
    step_lin: np.ndarray, t_max: np.ndarray, t_delta: np.ndarray, writes: np.ndarray, start: int, visit
) -> None:
    """Advance every ray `writes[i]` voxels from linear index `start`, calling visit(lin) each step.

    Rays are sorted by their number of writes (descending), so the active rays of step k are a
    prefix of the arrays: no compaction, one numpy operation per step for all rays at once.
    """
    order = np.argsort(-writes, kind="stable")
    writes = writes[order]
    if writes.size == 0 or writes[0] <= 0:
        return
    lin_type = np.int32 if start < 2**31 and np.abs(step_lin).max() < 2**30 else np.int64
    sx, sy, sz = (np.ascontiguousarray(step_lin[order, i], dtype=lin_type) for i in range(3))
    tx, ty, tz = (np.ascontiguousarray(t_max[order, i], dtype=np.float32) for i in range(3))
    dx, dy, dz = (np.ascontiguousarray(t_delta[order, i], dtype=np.float32) for i in range(3))
    lin = np.full(writes.size, start, dtype=lin_type)
    ascending = writes[::-1]
    n_max = int(writes[0])
    active = writes.size - np.searchsorted(ascending, np.arange(n_max), side="right")
    a = np.empty(writes.size, dtype=bool)
    d0 = np.empty(writes.size, dtype=bool)
    d1 = np.empty(writes.size, dtype=bool)
    tmp = np.empty(writes.size, dtype=bool)
    for k in range(n_max):
        n = int(active[k])
        a_tx, a_ty, a_tz = tx[:n], ty[:n], tz[:n]
        an, d0n, d1n, tn = a[:n], d0[:n], d1[:n], tmp[:n]
        np.less(a_tx, a_ty, out=an)
        np.less(a_tx, a_tz, out=d0n)
        d0n &= an
        np.less(a_ty, a_tz, out=d1n)
        np.greater(d1n, an, out=d1n)  # d1 = (ty < tz) & ~a
        np.logical_or(d0n, d1n, out=tn)
        a_lin = lin[:n]
        a_lin += np.where(d0n, sx[:n], np.where(d1n, sy[:n], sz[:n]))
        np.add(a_tx, dx[:n], out=a_tx, where=d0n)
        np.add(a_ty, dy[:n], out=a_ty, where=d1n)
        np.logical_not(tn, out=tn)
        np.add(a_tz, dz[:n], out=a_tz, where=tn)
        visit(a_lin)


def trace(
    origin: np.ndarray, ends: np.ndarray, hit_keys: np.ndarray, resolution: float
) -> Traversal:
    """Free voxels along rays origin -> ends (end voxel excluded) and hit voxels `hit_keys`.

    Each voxel appears once however many rays pass it; hits win over free, as in OctoMap.
    """
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    ends = np.asarray(ends, dtype=np.float64).reshape(-1, 3)
    hit_keys = np.asarray(hit_keys, dtype=np.int64).reshape(-1, 3)
    key_o, key_e, step, t_max, t_delta, n_steps = _ray_setup(origin, ends, resolution)
    # A ray whose end lies in the origin voxel marks nothing (OctoMap returns an empty ray).
    writes = np.maximum(n_steps - 1, 0)
    cast = n_steps > 0

    all_keys = np.concatenate([key_o[None, :], key_e, hit_keys]) if ends.size or hit_keys.size else key_o[None, :]
    kmin, kmax = vk.bounds(all_keys)
    lo = (kmin - 1) >> BLOCK_SHIFT << BLOCK_SHIFT
    hi = ((kmax + 1) >> BLOCK_SHIFT << BLOCK_SHIFT) + BLOCK
    dims = hi - lo
    strides = np.array([dims[1] * dims[2], dims[2], 1], dtype=np.int64)
    step_lin = step * strides
    start = int(((key_o - lo) * strides).sum())
    total = int(np.prod(dims))

    if total <= DENSE_LIMIT:
        cells = np.zeros(total, dtype=np.uint8)
        if cast.any():
            cells[start] = FREE
        _walk(step_lin, t_max, t_delta, np.where(cast, writes, 0), start,
              lambda lin: cells.__setitem__(lin, FREE))
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
    _walk(step_lin, t_max, t_delta, np.where(cast, writes, 0), start, lambda lin: visited.append(lin.copy()))
    free_lin = np.unique(np.concatenate(visited)) if visited else np.empty(0, dtype=np.int64)
    free_keys = np.stack(np.unravel_index(free_lin, tuple(int(d) for d in dims)), axis=1) + lo
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
    from voxel.blocks import split_keys

    keys = np.concatenate([free_keys, hit_keys]).astype(np.int64)
    vals = np.concatenate([np.full(len(free_keys), FREE), np.full(len(hit_keys), HIT)]).astype(np.uint8)
    blocks, offsets = split_keys(keys)
    ub, inv = np.unique(blocks, return_inverse=True)
    cells = np.zeros((ub.size, BLOCK_VOXELS), dtype=np.uint8)
    np.maximum.at(cells, (inv, offsets), vals)
    return Traversal(blocks=ub, cells=cells)


def ray_keys(origin: np.ndarray, end: np.ndarray, resolution: float) -> np.ndarray:
    """Keys (M, 3) of the voxels one ray passes, in order from the origin voxel to the end voxel."""
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    end = np.asarray(end, dtype=np.float64).reshape(1, 3)
    key_o, key_e, step, t_max, t_delta, n_steps = _ray_setup(origin, end, resolution)
    out = [key_o.copy()]
    # Walk in key space: a unit stride per axis makes the linear index the key itself.
    cur = key_o.copy()
    tm = t_max[0].copy()
    for _ in range(int(n_steps[0])):
        a = tm[0] < tm[1]
        dim = (0 if tm[0] < tm[2] else 2) if a else (1 if tm[1] < tm[2] else 2)
        cur[dim] += step[0, dim]
        tm[dim] += t_delta[0, dim]
        out.append(cur.copy())
    return np.asarray(out, dtype=np.int64)
