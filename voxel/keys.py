"""Integer voxel keys: points to keys, packing into int64, block and offset split."""

from __future__ import annotations

import numpy as np

#: Bits per axis in a packed key; keys span [-2**20, 2**20) voxels on each axis.
AXIS_BITS = 21
AXIS_OFFSET = 1 << (AXIS_BITS - 1)
AXIS_MASK = (1 << AXIS_BITS) - 1
KEY_MIN = -AXIS_OFFSET
KEY_MAX = AXIS_OFFSET - 1


def points_to_keys(points: np.ndarray, resolution: float) -> np.ndarray:
    """Voxel keys (N, 3) int64 of points (N, 3): floor(p * (1 / resolution)), as OctoMap computes
    them."""
    scaled = np.asarray(points, dtype=np.float64) * (1.0 / resolution)
    return np.floor(scaled, out=scaled).astype(np.int64)


def keys_to_centers(keys: np.ndarray, resolution: float) -> np.ndarray:
    """Centres (N, 3) float64 of voxel keys (N, 3)."""
    return (np.asarray(keys, dtype=np.float64) + 0.5) * resolution


def pack(keys: np.ndarray) -> np.ndarray:
    """Pack keys (N, 3) into one int64 each; the order of packed keys is x-major, then y, then z."""
    k = np.asarray(keys, dtype=np.int64) + AXIS_OFFSET
    return (k[:, 0] << (2 * AXIS_BITS)) | (k[:, 1] << AXIS_BITS) | k[:, 2]


def unpack(packed: np.ndarray) -> np.ndarray:
    """Inverse of `pack`: (N,) int64 to keys (N, 3) int64."""
    p = np.asarray(packed, dtype=np.int64)
    out = np.empty((p.shape[0], 3), dtype=np.int64)
    out[:, 0] = (p >> (2 * AXIS_BITS)) & AXIS_MASK
    out[:, 1] = (p >> AXIS_BITS) & AXIS_MASK
    out[:, 2] = p & AXIS_MASK
    return out - AXIS_OFFSET


#: `unique_packed` counts in a dense box when it has at most this many cells per key (+ slack).
DENSE_CELLS_PER_KEY = 4


def unique_packed(packed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """np.unique(packed, return_inverse=True) of packed keys, in linear time when the keys fill
    their bounding box well (a map's blocks do): marks in a dense box instead of a sort."""
    p = np.asarray(packed, dtype=np.int64).reshape(-1)
    n = p.shape[0]
    if n < 64:
        ub, inv = np.unique(p, return_inverse=True)
        return ub, inv.reshape(-1)
    # one axis at a time: reductions along axis 0 of an (N, 3) array are several times slower
    cols = [(p >> (2 * AXIS_BITS)) & AXIS_MASK, (p >> AXIS_BITS) & AXIS_MASK, p & AXIS_MASK]
    lo = [int(c.min()) for c in cols]
    dims = [int(c.max()) - x + 1 for c, x in zip(cols, lo, strict=True)]
    cells = dims[0] * dims[1] * dims[2]
    if cells > DENSE_CELLS_PER_KEY * n + 4096:
        ub, inv = np.unique(p, return_inverse=True)
        return ub, inv.reshape(-1)
    lin = cols[0] - lo[0]
    lin *= dims[1]
    lin += cols[1] - lo[1]
    lin *= dims[2]
    lin += cols[2] - lo[2]
    first = np.full(cells, -1, dtype=np.int64)
    first[lin] = np.arange(n)
    held = np.flatnonzero(first >= 0)  # box order is packed order (x-major)
    rank = np.empty(cells, dtype=np.int64)
    rank[held] = np.arange(held.size)
    return p[first[held]], rank[lin]


def in_range(keys: np.ndarray) -> np.ndarray:
    """Mask of keys (N, 3) that fit the packed key space."""
    k = np.asarray(keys)
    if k.size == 0 or (k.min() >= KEY_MIN and k.max() <= KEY_MAX):
        return np.ones(k.shape[0], dtype=bool)
    inside: np.ndarray = np.all((k >= KEY_MIN) & (k <= KEY_MAX), axis=1)
    return inside


_HASH_MULTIPLIERS = (
    -7046029254386353131,
    -4658895280553007687,
    7640891576956012809,
    -8350542686271633251,
)


def one_per_key(keys: np.ndarray) -> np.ndarray:
    """Indices, ascending, of the last row of each distinct key of integer keys (3, N).

    Rows are hashed into a table about four times their number; each slot keeps its last writer
    (so a key's winner is its last row) and rows whose key differs from their slot's winner (a
    collision) go round again with another hash. Only the chosen indices are sorted.
    """
    k = np.asarray(keys)
    n = k.shape[1]
    if n == 0:
        return np.empty(0, dtype=np.int64)
    lo = [int(k[a].min()) for a in range(3)]
    span = [int(k[a].max()) - lo[a] + 1 for a in range(3)]
    lin = (k[0] - lo[0]).astype(np.int64) * (span[1] * span[2])
    lin += (k[1] - lo[1]).astype(np.int64) * span[2]
    lin += (k[2] - lo[2]).astype(np.int64)
    bits = max(4, int(n).bit_length() + 2)
    table = np.empty(1 << bits, dtype=np.int64)
    pending = np.arange(n)
    chosen: list[np.ndarray] = []
    for r in range(64):
        mult = _HASH_MULTIPLIERS[r % len(_HASH_MULTIPLIERS)] + 2 * (r // len(_HASH_MULTIPLIERS))
        with np.errstate(over="ignore"):
            slot = ((lin[pending] * mult) >> (64 - bits)) & ((1 << bits) - 1)
        table[slot] = pending
        winner = table[slot]
        chosen.append(pending[winner == pending])
        pending = pending[lin[winner] != lin[pending]]
        if pending.size == 0:
            break
    else:  # pragma: no cover - 64 rounds of collisions: fall back to sorting what is left
        _, last = np.unique(lin[pending][::-1], return_index=True)
        chosen.append(pending[::-1][last])
    return np.sort(np.concatenate(chosen))
