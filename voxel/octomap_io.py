"""OctoMap binary tree files (.bt): occupied and free voxels written and read in pure numpy."""

from __future__ import annotations

import math
from dataclasses import dataclass
from os import PathLike
from pathlib import Path

import numpy as np

from voxel.errors import FileFormatError, InputError

#: Depth of an OctoMap tree; our keys are voxels at this (the finest) depth.
TREE_DEPTH = 16
#: OctoMap's key of a voxel is ours (floor(coord / resolution)) plus this offset.
KEY_OFFSET = 1 << (TREE_DEPTH - 1)
#: Default cap on the voxels `read_bt` expands pruned leaves into.
MAX_VOXELS = 50_000_000

FILE_HEADER = b"# Octomap OcTree binary file"
TREE_ID = "OcTree"
_MAX_HEADER_BYTES = 1 << 16

# 2-bit codes of a child in an inner node's record (OccupancyOcTreeBase::writeBinaryNode).
_FREE, _OCCUPIED, _INNER = 1, 2, 3

StrPath = str | PathLike[str]


@dataclass(frozen=True, eq=False)
class BtMap:
    """Known voxels of an OctoMap file at the finest depth; keys are floor(coord / resolution)."""

    resolution: float
    keys: np.ndarray  # (N, 3) int64
    occupied: np.ndarray  # (N,) bool


@dataclass(frozen=True, eq=False)
class BtLeaves:
    """Leaves of an OctoMap tree as stored: minimum-corner key, depth (16 = one voxel), state."""

    resolution: float
    keys: np.ndarray  # (N, 3) int64, minimum corner in finest-depth keys
    depth: np.ndarray  # (N,) uint8 in 1..16; a leaf spans 2**(16 - depth) voxels per axis
    occupied: np.ndarray  # (N,) bool


def write_bt(path: StrPath, resolution: float, keys: np.ndarray, occupied: np.ndarray) -> None:
    """Write voxels (keys (N, 3) int64, occupied (N,) bool; others free) as a pruned .bt file.

    A key given twice is occupied if any of its entries is.
    """
    res = float(resolution)
    if not math.isfinite(res) or res <= 0.0:
        msg = f"expected a finite resolution > 0, found {resolution!r}"
        raise InputError(msg) from None
    keys = np.asarray(keys)
    occupied = np.asarray(occupied)
    if keys.ndim != 2 or keys.shape[1] != 3 or not np.issubdtype(keys.dtype, np.integer):
        msg = f"expected integer keys of shape (N, 3), found {keys.dtype} {keys.shape}"
        raise InputError(msg) from None
    if occupied.shape != (keys.shape[0],) or occupied.dtype != np.bool_:
        msg = (
            f"expected a bool occupied mask of shape ({keys.shape[0]},), "
            f"found {occupied.dtype} {occupied.shape}"
        )
        raise InputError(msg) from None
    internal = keys.astype(np.int64) + KEY_OFFSET
    outside = np.any((internal < 0) | (internal >= 1 << TREE_DEPTH), axis=1)
    if outside.any():
        bad = keys[np.argmax(outside)].tolist()
        msg = (
            f"expected keys in [{-KEY_OFFSET}, {KEY_OFFSET - 1}] (OctoMap's 16-level tree), "
            f"found {int(outside.sum())} outside, e.g. {bad}"
        )
        raise InputError(msg) from None
    codes, first = np.unique(_interleave(internal), return_inverse=True)
    occ = np.bincount(first, weights=occupied, minlength=codes.shape[0]) > 0
    data, size = _encode_tree(codes, occ)
    header = (
        f"{FILE_HEADER.decode()}\n# written by colony\n"
        f"id {TREE_ID}\nsize {size}\nres {res!r}\ndata\n"
    )
    Path(path).write_bytes(header.encode("ascii") + data)


def read_bt(path: StrPath, *, max_voxels: int = MAX_VOXELS) -> BtMap:
    """Read a .bt file into finest-depth voxels; pruned leaves expand to all their voxels."""
    leaves = read_bt_leaves(path)
    total = sum(
        int(np.count_nonzero(leaves.depth == d)) * 8 ** (TREE_DEPTH - d)
        for d in range(1, TREE_DEPTH + 1)
    )
    if total > max_voxels:
        msg = (
            f"{path}: expected at most max_voxels={max_voxels} voxels after expanding pruned "
            f"leaves, found {total}; use read_bt_leaves or raise max_voxels"
        )
        raise FileFormatError(msg) from None
    parts_keys, parts_occ = [], []
    for d in range(1, TREE_DEPTH + 1):
        sel = leaves.depth == d
        if not sel.any():
            continue
        side = np.arange(1 << (TREE_DEPTH - d), dtype=np.int64)
        offsets = np.stack(np.meshgrid(side, side, side, indexing="ij"), axis=-1).reshape(-1, 3)
        parts_keys.append((leaves.keys[sel][:, None, :] + offsets[None, :, :]).reshape(-1, 3))
        parts_occ.append(np.repeat(leaves.occupied[sel], offsets.shape[0]))
    if not parts_keys:
        return BtMap(leaves.resolution, np.empty((0, 3), np.int64), np.empty(0, bool))
    return BtMap(leaves.resolution, np.concatenate(parts_keys), np.concatenate(parts_occ))


def read_bt_leaves(path: StrPath) -> BtLeaves:
    """Read the leaves of a .bt file as stored, without expanding pruned ones."""
    raw = Path(path).read_bytes()
    resolution, size, start = _parse_header(raw, path)
    data = raw[start:]
    if size == 0:
        if data:
            msg = f"{path}: expected no tree data for 'size 0', found {len(data)} bytes"
            raise FileFormatError(msg) from None
        empty = np.empty(0, dtype=np.int64)
        return BtLeaves(resolution, empty.reshape(0, 3), empty.astype(np.uint8), empty.astype(bool))
    prefix, depth, occupied, nodes = _decode_tree(data, path)
    if nodes != size:
        msg = f"{path}: expected {size} tree nodes (header 'size'), found {nodes}"
        raise FileFormatError(msg) from None
    internal = _deinterleave(prefix << (3 * (TREE_DEPTH - depth.astype(np.int64))))
    return BtLeaves(resolution, internal - KEY_OFFSET, depth.astype(np.uint8), occupied)


def _spread_table() -> np.ndarray:
    """Bits of each byte value spread to every third bit (the Morton pattern of one axis)."""
    values = np.arange(256, dtype=np.int64)
    spread = np.zeros(256, dtype=np.int64)
    for bit in range(8):
        spread |= ((values >> bit) & 1) << (3 * bit)
    return spread


_SPREAD = _spread_table()
# For each 12-bit Morton chunk (four levels), the 4-bit x, y and z it holds.
_COMPACT = np.stack(
    [
        np.bitwise_or.reduce(
            [((np.arange(4096) >> (3 * bit + axis)) & 1) << bit for bit in range(4)], axis=0
        )
        for axis in range(3)
    ]
).astype(np.int64)


def _interleave(keys: np.ndarray) -> np.ndarray:
    """Morton codes (N,) of internal keys (N, 3): per level, child index x | y << 1 | z << 2."""
    code = np.zeros(keys.shape[0], dtype=np.int64)
    for axis in range(3):
        k = keys[:, axis]
        code |= (_SPREAD[k & 255] | (_SPREAD[k >> 8] << 24)) << axis
    return code


def _deinterleave(code: np.ndarray) -> np.ndarray:
    """Inverse of `_interleave`: Morton codes (N,) to internal keys (N, 3)."""
    keys = np.zeros((code.shape[0], 3), dtype=np.int64)
    for chunk in range(4):
        part = (code >> (12 * chunk)) & 4095
        for axis in range(3):
            keys[:, axis] |= _COMPACT[axis][part] << (4 * chunk)
    return keys


def _encode_tree(codes: np.ndarray, occupied: np.ndarray) -> tuple[bytes, int]:
    """Pruned tree records in OctoMap's depth-first order, and its node count, of sorted codes."""
    if codes.shape[0] == 0:
        return b"", 0
    # Bottom-up pruning: eight sibling leaves in the same state become one leaf (not the root).
    leaves: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    prefix, occ = codes, occupied
    for depth in range(TREE_DEPTH, 1, -1):
        parent, start, count = np.unique(prefix >> 3, return_index=True, return_counts=True)
        n_occ = np.add.reduceat(occ.astype(np.int64), start)
        collapse = (count == 8) & ((n_occ == 0) | (n_occ == 8))
        keep = ~np.repeat(collapse, count)
        leaves[depth] = (prefix[keep], occ[keep])
        prefix, occ = parent[collapse], n_occ[collapse] == 8
    leaves[1] = (prefix, occ)
    # Inner nodes per depth, bottom-up, each with its 2-bit-per-child record.
    inner: dict[int, np.ndarray] = {TREE_DEPTH: np.empty(0, dtype=np.int64)}
    records, order_code, order_depth = [], [], []
    for depth in range(TREE_DEPTH - 1, -1, -1):
        below, (leaf_prefix, leaf_occ) = inner[depth + 1], leaves[depth + 1]
        nodes = np.unique(np.concatenate([below >> 3, leaf_prefix >> 3]))
        inner[depth] = nodes
        children = np.concatenate([below, leaf_prefix])
        child_code = np.concatenate(
            [np.full(below.shape[0], _INNER), np.where(leaf_occ, _OCCUPIED, _FREE)]
        ).astype(np.int64)
        idx = np.searchsorted(nodes, children >> 3)
        bits = child_code << (2 * (children & 7))
        records.append(np.bincount(idx, weights=bits, minlength=nodes.shape[0]).astype(np.int64))
        order_code.append(nodes << (3 * (TREE_DEPTH - depth)))
        order_depth.append(np.full(nodes.shape[0], depth))
    # Depth-first pre-order: by the node's first voxel, then parents before children.
    all_records = np.concatenate(records)
    order = np.lexsort((np.concatenate(order_depth), np.concatenate(order_code)))
    n_leaves = sum(p.shape[0] for p, _ in leaves.values())
    return all_records[order].astype("<u2").tobytes(), all_records.shape[0] + n_leaves


def _decode_tree(data: bytes, path: StrPath) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Leaves (prefix code, depth, occupied) and node count of the tree records in `data`."""
    words = np.frombuffer(data, dtype="<u2", count=len(data) // 2).astype(np.int64)
    child = (words[:, None] >> (2 * np.arange(8))) & 3
    n_inner = np.count_nonzero(child == _INNER, axis=1)
    # Pending subtrees after each record (OctoMap reads depth-first); the tree ends at zero.
    pending = 1 + np.cumsum(n_inner - 1)
    done = np.flatnonzero(pending == 0)
    if done.shape[0] == 0:
        msg = f"{path}: truncated tree data: expected more node records after {len(data)} bytes"
        raise FileFormatError(msg) from None
    n = int(done[0]) + 1
    if len(data) != 2 * n:
        msg = (
            f"{path}: expected the file to end after the tree ({2 * n} bytes of data), "
            f"found {len(data) - 2 * n} more bytes"
        )
        raise FileFormatError(msg) from None
    child, n_inner, pending = child[:n], n_inner[:n], pending[:n]
    before = np.concatenate([[1], pending])  # pending subtrees before record i; before[n] = 0
    # A record's subtree ends at the first later record that sees one pending subtree fewer.
    index = np.arange(n + 1, dtype=np.int64)
    keyed = np.sort(before * (n + 1) + index)
    end = keyed[np.searchsorted(keyed, (before[:n] - 1) * (n + 1) + index[:n], side="right")] % (
        n + 1
    )
    opened = np.cumsum(np.ones(n, dtype=np.int64) - np.bincount(end, minlength=n + 1)[:n])
    depth = opened - 1
    if depth.max() >= TREE_DEPTH:
        deepest = int(depth.max())
        msg = (
            f"{path}: expected a tree of {TREE_DEPTH} levels, found inner nodes at depth {deepest}"
        )
        raise FileFormatError(msg) from None
    # Parent: the last earlier record one level up; child rank from the pending-subtree count.
    keyed = np.sort(depth * n + index[:n])
    parent = keyed[np.searchsorted(keyed, (depth - 1) * n + index[:n], side="left") - 1] % n
    parent[0] = 0
    rank = pending[parent] - before[:n]
    inner_slots = np.argsort(child != _INNER, axis=1, kind="stable")
    slot = inner_slots[parent, np.clip(rank, 0, 7)]
    prefix = np.zeros(n, dtype=np.int64)
    for d in range(1, TREE_DEPTH):
        sel = depth == d
        prefix[sel] = (prefix[parent[sel]] << 3) | slot[sel]
    rec, pos = np.nonzero((child == _FREE) | (child == _OCCUPIED))
    leaf_prefix = (prefix[rec] << 3) | pos
    return leaf_prefix, depth[rec] + 1, child[rec, pos] == _OCCUPIED, n + rec.shape[0]


def _parse_header(raw: bytes, path: StrPath) -> tuple[float, int, int]:
    """Resolution, node count and data offset of a .bt file's text header."""
    if not raw.startswith(FILE_HEADER):
        expected = FILE_HEADER.decode()
        msg = f"{path}: expected the first line to start with {expected!r}, found {raw[:40]!r}"
        raise FileFormatError(msg) from None
    fields: dict[bytes, bytes] = {}
    pos = raw.find(b"\n") + 1
    while True:
        end = raw.find(b"\n", pos, _MAX_HEADER_BYTES)
        if pos == 0 or end < 0:
            msg = (
                f"{path}: truncated header: expected a 'data' line within {_MAX_HEADER_BYTES} bytes"
            )
            raise FileFormatError(msg) from None
        tokens = raw[pos:end].split()
        pos = end + 1
        if not tokens or tokens[0].startswith(b"#"):
            continue
        if tokens[0] == b"data":
            break
        if tokens[0] in (b"id", b"size", b"res"):  # OctoMap skips unknown keywords too
            fields[tokens[0]] = b" ".join(tokens[1:])
    tree_id = fields.get(b"id", b"").decode("ascii", "replace")
    if tree_id != TREE_ID:
        msg = f"{path}: expected 'id {TREE_ID}', found {tree_id!r}"
        raise FileFormatError(msg) from None
    text_size = fields.get(b"size", b"").decode("ascii", "replace")
    if not text_size.isdigit():
        msg = f"{path}: expected 'size' to be a node count >= 0, found {text_size!r}"
        raise FileFormatError(msg) from None
    text_res = fields.get(b"res", b"").decode("ascii", "replace")
    try:
        resolution = float(text_res)
    except ValueError:
        resolution = math.nan
    if not math.isfinite(resolution) or resolution <= 0.0:
        msg = f"{path}: expected 'res' to be a resolution > 0, found {text_res!r}"
        raise FileFormatError(msg) from None
    return resolution, int(text_size), pos
