"""Sparse block storage: dense blocks of voxels addressed by integer block keys, one numpy array per
channel."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from voxel import kernels
from voxel import keys as vk
from voxel.errors import InputError

#: Block side lengths as powers of two per axis. Cubes (4x4x4) suit 3D sensors; planar blocks
#: (8x8x1) suit layers mapped by a 2D scanner, whose voxels all lie in one z layer; slabs
#: (4x4x1) suit a 3D LiDAR at fine resolution, whose long, thin, mostly level rays fill 22 % of
#: a cube and 40 % of a slab (docs/BENCHMARKS.md).
CUBE = (2, 2, 2)
PLANAR = (3, 3, 0)
SLAB = (2, 2, 0)
BLOCK_SHAPES = {"cube": CUBE, "planar": PLANAR, "slab": SLAB}

#: Channel name -> (dtype, trailing shape, fill value). Core channels always exist; the others are
#: allocated the first time they are used.
CORE_CHANNELS: dict[str, tuple[np.dtype, tuple[int, ...], float]] = {
    "logodds": (np.dtype(np.float32), (), np.nan),  # NaN = unknown
    "version": (np.dtype(np.uint32), (), 0),
    "last_time": (np.dtype(np.uint32), (), 0),  # ms since the grid's time base, last change
}
RICH_CHANNELS: dict[str, tuple[np.dtype, tuple[int, ...], float]] = {
    "first_time": (np.dtype(np.float64), (), 0.0),
    "hits": (np.dtype(np.uint16), (), 0),
    "misses": (np.dtype(np.uint16), (), 0),
    "colour": (np.dtype(np.uint8), (3,), 0),
    "normal": (np.dtype(np.float32), (3,), 0.0),
    "class_ids": (np.dtype(np.int16), (-1,), -1),
    "class_probs": (np.dtype(np.float32), (-1,), 0.0),
    # sub-voxel surface: the published mean hit offset from the centre, 1/254 voxel (voxel.surface)
    "surface": (np.dtype(np.int8), (3,), 0),
}
#: Channels only the grid that integrates uses: never carried by deltas (voxel.delta).
LOCAL_CHANNELS: dict[str, tuple[np.dtype, tuple[int, ...], float]] = {
    "surface_mean": (np.dtype(np.int16), (3,), 0),  # its running mean, 1/65532 voxel
    "surface_weight": (np.dtype(np.uint16), (), 0),  # scans fused into `surface_mean`
    "surface_version": (np.dtype(np.uint32), (), 0),  # version `surface` last changed at
}
SCALAR_SPEC = (np.dtype(np.float32), (), np.nan)


def shape_for(sensor_kind: str) -> str:
    """The block shape that holds a layer mapped by one kind of sensor in the least memory:
    planar for a 2D LiDAR, slab for a 3D LiDAR, cube otherwise (docs/VOXEL.md, "Storage")."""
    return {"lidar2d": "planar", "lidar3d": "slab"}.get(sensor_kind, "cube")


def block_shifts(shape: str | tuple[int, int, int]) -> tuple[int, int, int]:
    """Per-axis shifts of a block shape: a name in BLOCK_SHAPES or side lengths (powers of two,
    1-8)."""
    if isinstance(shape, str):
        if shape not in BLOCK_SHAPES:
            msg = (
                f"block shape must be one of {sorted(BLOCK_SHAPES)} or three side lengths, "
                f"found {shape!r}"
            )
            raise InputError(msg)
        return BLOCK_SHAPES[shape]
    sides = tuple(shape)
    if len(sides) != 3 or any(
        not isinstance(x, (int, np.integer)) or x not in (1, 2, 4, 8) for x in sides
    ):
        msg = f"block sides must be three of 1, 2, 4, 8 voxels, found {shape!r}"
        raise InputError(msg)
    return tuple(int(x).bit_length() - 1 for x in sides)  # type: ignore[return-value]


def split_keys(
    keys: np.ndarray, shifts: tuple[int, int, int] = CUBE
) -> tuple[np.ndarray, np.ndarray]:
    """Packed block keys (N,) and in-block offsets (N,) of voxel keys (N, 3)."""
    k = np.asarray(keys, dtype=np.int64)
    sx, sy, sz = shifts
    blocks = vk.pack(np.stack([k[:, 0] >> sx, k[:, 1] >> sy, k[:, 2] >> sz], axis=1))
    offsets = ((k[:, 0] & ((1 << sx) - 1)) << (sy + sz)) | ((k[:, 1] & ((1 << sy) - 1)) << sz)
    offsets |= k[:, 2] & ((1 << sz) - 1)
    return blocks, offsets


#: `count_blocks` counts in a dense box when it has at most this many cells per key (+ slack).
DENSE_BLOCKS_PER_KEY = 4


def count_blocks(
    keys: np.ndarray | Sequence[np.ndarray], shifts: tuple[int, int, int] = CUBE
) -> int:
    """Distinct blocks holding voxel keys (N, 3), or the keys of several arrays together (the
    parts of a snapshot, one at a time: never concatenated): marked in a dense box of blocks
    when they fill it well (a map's voxels do), else counted by sorting."""
    parts = [np.asarray(keys)] if isinstance(keys, np.ndarray) else [np.asarray(k) for k in keys]
    parts = [k for k in parts if k.shape[0]]
    n = sum(k.shape[0] for k in parts)
    if n == 0:
        return 0
    # one column at a time: reductions along axis 0 of an (N, 3) array are several times slower;
    # a shift keeps the order, so the blocks' bounds are the voxels' bounds shifted
    lo = [min(int(k[:, i].min()) for k in parts) >> s for i, s in enumerate(shifts)]
    hi = [max(int(k[:, i].max()) for k in parts) >> s for i, s in enumerate(shifts)]
    dims = [h - x + 1 for h, x in zip(hi, lo, strict=True)]
    cells = dims[0] * dims[1] * dims[2]
    if cells > DENSE_BLOCKS_PER_KEY * n + 4096:
        packed = [
            np.unique(vk.pack(np.stack([k[:, i] >> s for i, s in enumerate(shifts)], axis=1)))
            for k in parts
        ]
        return int(np.unique(np.concatenate(packed)).size)
    box = np.zeros(cells, dtype=bool)
    for k in parts:
        lin = (k[:, 0].astype(np.int64) >> shifts[0]) - lo[0]
        lin *= dims[1]
        lin += (k[:, 1].astype(np.int64) >> shifts[1]) - lo[1]
        lin *= dims[2]
        lin += (k[:, 2].astype(np.int64) >> shifts[2]) - lo[2]
        box[lin] = True
    return int(np.count_nonzero(box))


def join_keys(
    blocks: np.ndarray, offsets: np.ndarray, shifts: tuple[int, int, int] = CUBE
) -> np.ndarray:
    """Voxel keys (N, 3) from packed block keys (N,) and offsets (N,)."""
    sx, sy, sz = shifts
    base = vk.unpack(blocks)
    off = np.asarray(offsets, dtype=np.int64)
    base[:, 0] = (base[:, 0] << sx) + (off >> (sy + sz))
    base[:, 1] = (base[:, 1] << sy) + ((off >> sz) & ((1 << sy) - 1))
    base[:, 2] = (base[:, 2] << sz) + (off & ((1 << sz) - 1))
    return base


class BlockStore:
    """Slots of one block of voxels each, with per-channel arrays of shape (capacity, block voxels,
    ...)."""

    def __init__(
        self, class_k: int = 3, capacity: int = 64, shifts: tuple[int, int, int] = CUBE
    ) -> None:
        self.class_k = class_k
        self.shifts: tuple[int, int, int] = (int(shifts[0]), int(shifts[1]), int(shifts[2]))
        self.block_voxels = 1 << sum(self.shifts)
        self.capacity = capacity
        self.count = 0  # slots ever used (high-water mark)
        self.free_slots: list[int] = []
        self.sorted_keys = np.empty(0, dtype=np.int64)  # packed block keys, sorted
        self.sorted_slots = np.empty(0, dtype=np.int64)
        self.slot_keys = np.full(capacity, -1, dtype=np.int64)  # slot -> packed block key (-1 free)
        self.slot_version = np.zeros(capacity, dtype=np.uint32)  # highest voxel version in the slot
        self.channels: dict[str, np.ndarray] = {}
        for name, spec in CORE_CHANNELS.items():
            self.channels[name] = self._new_array(spec, capacity)

    # -- channel management -------------------------------------------------------------------
    def _shape(self, tail: tuple[int, ...]) -> tuple[int, ...]:
        return tuple(self.class_k if t == -1 else t for t in tail)

    def _new_array(self, spec: tuple[np.dtype, tuple[int, ...], float], n: int) -> np.ndarray:
        dtype, tail, fill = spec
        return np.full((n, self.block_voxels, *self._shape(tail)), fill, dtype=dtype)

    @staticmethod
    def spec(name: str) -> tuple[np.dtype, tuple[int, ...], float]:
        if name in CORE_CHANNELS:
            return CORE_CHANNELS[name]
        if name in RICH_CHANNELS:
            return RICH_CHANNELS[name]
        if name in LOCAL_CHANNELS:
            return LOCAL_CHANNELS[name]
        return SCALAR_SPEC

    def channel(self, name: str) -> np.ndarray:
        """The array of channel `name`, allocated on first use."""
        arr = self.channels.get(name)
        if arr is None:
            arr = self._new_array(self.spec(name), self.capacity)
            self.channels[name] = arr
        return arr

    def reset_slots(self, slots: np.ndarray) -> None:
        for name, arr in self.channels.items():
            arr[slots] = self.spec(name)[2]
        self.slot_version[slots] = 0

    def _grow(self, needed: int) -> None:
        new_cap = max(needed, self.capacity * 2)
        for name, arr in self.channels.items():
            grown = self._new_array(self.spec(name), new_cap)
            grown[: self.capacity] = arr
            self.channels[name] = grown
        keys = np.full(new_cap, -1, dtype=np.int64)
        keys[: self.capacity] = self.slot_keys
        self.slot_keys = keys
        versions = np.zeros(new_cap, dtype=np.uint32)
        versions[: self.capacity] = self.slot_version
        self.slot_version = versions
        self.capacity = new_cap

    def split(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Packed block keys and in-block offsets of voxel keys (N, 3), in this store's block
        shape."""
        return split_keys(keys, self.shifts)

    def offset_keys(self) -> np.ndarray:
        """Keys (block voxels, 3) of each in-block offset in a block at key (0, 0, 0)."""
        corner = vk.pack(np.zeros((1, 3), dtype=np.int64))
        return join_keys(
            np.repeat(corner, self.block_voxels), np.arange(self.block_voxels), self.shifts
        )

    def join(self, blocks: np.ndarray, offsets: np.ndarray) -> np.ndarray:
        """Voxel keys (N, 3) of packed block keys and in-block offsets."""
        return join_keys(blocks, offsets, self.shifts)

    # -- lookup -------------------------------------------------------------------------------
    def lookup(self, blocks: np.ndarray) -> np.ndarray:
        """Slots of packed block keys; -1 where the block does not exist."""
        blocks = np.asarray(blocks, dtype=np.int64)
        if self.sorted_keys.size == 0:
            return np.full(blocks.shape, -1, dtype=np.int64)
        idx = np.searchsorted(self.sorted_keys, blocks)
        idx = np.minimum(idx, self.sorted_keys.size - 1)
        found = self.sorted_keys[idx] == blocks
        return np.where(found, self.sorted_slots[idx], -1)

    def ensure(self, blocks: np.ndarray) -> np.ndarray:
        """Slots of unique packed block keys, creating missing blocks."""
        compiled = None if self.free_slots else kernels.index()
        if compiled is not None:
            arr = np.asarray(blocks, dtype=np.int64)
            found, new_keys, keys, held, ok = compiled(
                self.sorted_keys, self.sorted_slots, arr, self.count
            )
            if ok:
                n_new = int(new_keys.size)
                if n_new:
                    if self.count + n_new > self.capacity:
                        self._grow(self.count + n_new)
                    self.slot_keys[self.count : self.count + n_new] = new_keys
                    self.count += n_new
                    self.sorted_keys, self.sorted_slots = keys, held
                slots: np.ndarray = found
                return slots
        slots = self.lookup(blocks)
        missing = slots < 0
        n_new = int(missing.sum())
        if n_new:
            new_keys = np.asarray(blocks, dtype=np.int64)[missing]
            reuse = min(n_new, len(self.free_slots))
            taken = [self.free_slots.pop() for _ in range(reuse)]
            fresh = n_new - reuse
            if self.count + fresh > self.capacity:
                self._grow(self.count + fresh)
            new_slots = np.concatenate(
                [np.asarray(taken, dtype=np.int64), np.arange(self.count, self.count + fresh)]
            )
            self.count += fresh
            if reuse:
                self.reset_slots(new_slots[:reuse])
            self.slot_keys[new_slots] = new_keys
            slots[missing] = new_slots
            all_keys = np.concatenate([self.sorted_keys, new_keys])
            all_slots = np.concatenate([self.sorted_slots, new_slots])
            order = np.argsort(all_keys, kind="stable")
            self.sorted_keys = all_keys[order]
            self.sorted_slots = all_slots[order]
        return slots

    def release(self, slots: np.ndarray) -> None:
        """Free slots (their blocks become unknown)."""
        slots = np.asarray(slots, dtype=np.int64)
        if slots.size == 0:
            return
        self.reset_slots(slots)
        gone = np.isin(self.sorted_slots, slots)
        self.sorted_keys = self.sorted_keys[~gone]
        self.sorted_slots = self.sorted_slots[~gone]
        self.slot_keys[slots] = -1
        self.free_slots.extend(int(s) for s in slots)

    def shrink(self) -> bool:
        """Return memory: when at most half of the slots hold blocks, move the used slots to
        the front of new arrays just large enough for them (slot numbers change). Returns
        whether it did."""
        used = self.sorted_slots
        n = int(used.size)
        if n * 2 > self.capacity or self.capacity <= 64:
            return False
        cap = max(64, n + n // 4)
        for name, arr in self.channels.items():
            fresh = self._new_array(self.spec(name), cap)
            fresh[:n] = arr[used]
            self.channels[name] = fresh
        keys = np.full(cap, -1, dtype=np.int64)
        keys[:n] = self.slot_keys[used]
        versions = np.zeros(cap, dtype=np.uint32)
        versions[:n] = self.slot_version[used]
        self.slot_keys, self.slot_version = keys, versions
        self.sorted_slots = np.arange(n, dtype=np.int64)
        self.free_slots = []
        self.count, self.capacity = n, cap
        return True

    def allocated_bytes(self) -> int:
        """Bytes of every array the store holds (capacity, not only used slots)."""
        arrays = [*self.channels.values(), self.slot_keys, self.slot_version]
        return sum(int(a.nbytes) for a in arrays) + int(
            self.sorted_keys.nbytes + self.sorted_slots.nbytes
        )

    def used_slots(self) -> np.ndarray:
        """Slots that hold a block, in block-key order."""
        return self.sorted_slots

    def nbytes(self) -> int:
        """Bytes held by the channel arrays of used slots plus the index."""
        index = (
            self.sorted_keys.itemsize
            + self.sorted_slots.itemsize
            + self.slot_keys.itemsize
            + self.slot_version.itemsize
        )
        per_slot = sum(int(arr[0].nbytes) for arr in self.channels.values()) + index
        return per_slot * len(self.sorted_slots)
