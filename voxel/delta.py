"""Voxel deltas: absolute new values of the voxels that changed between two grid versions."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from voxel import keys as vk
from voxel import surface
from voxel.blocks import CORE_CHANNELS, LOCAL_CHANNELS, BlockStore
from voxel.errors import DeltaError
from voxel.timebase import TimeBase

#: Optional per-voxel channels a delta may carry, with dtype and trailing shape.
#: `class_ids`/`class_probs` have a trailing dimension k (top-k object classes); a scalar channel
#: named NAME travels as "scalar:NAME" with shape (N,) float32. `surface` carries wire codes
#: (voxel.surface: offsets of the mean hit point from the voxel's centre, 1/254 voxel each).
CHANNEL_SPECS: dict[str, tuple[np.dtype, tuple[int, ...]]] = {
    "first_time": (np.dtype(np.float64), ()),
    "hits": (np.dtype(np.uint16), ()),
    "misses": (np.dtype(np.uint16), ()),
    "colour": (np.dtype(np.uint8), (3,)),
    "normal": (np.dtype(np.float32), (3,)),
    "class_ids": (np.dtype(np.int16), (-1,)),
    "class_probs": (np.dtype(np.float32), (-1,)),
    "surface": (np.dtype(np.int8), (3,)),
}
SCALAR_PREFIX = "scalar:"


def channel_spec(name: str) -> tuple[np.dtype, tuple[int, ...]]:
    """Dtype and trailing shape of a delta channel; -1 stands for any length."""
    if name.startswith(SCALAR_PREFIX) and len(name) > len(SCALAR_PREFIX):
        return np.dtype(np.float32), ()
    try:
        return CHANNEL_SPECS[name]
    except KeyError:
        msg = (
            f"unknown delta channel {name!r}; expected one of {sorted(CHANNEL_SPECS)} or "
            "'scalar:NAME'"
        )
        raise DeltaError(msg) from None


@dataclass
class Delta:
    """The voxels of one layer that changed in (from_version, to_version], with absolute values.

    `logodds` is NaN for a voxel that returned to unknown. Every voxel of a delta takes
    `to_version` as its version when applied, so applying deltas twice or out of order gives
    the same layer: a voxel keeps the value of the highest version that reached it.

    `surface_mask` (N,) bool, with the `surface` channel: the voxels whose codes the delta
    carries, the others' codes unchanged since `from_version` (they keep what the receiver
    holds; their rows of the channel are not read). None: every voxel's codes are carried.
    """

    resolution: float
    from_version: int
    to_version: int
    keys: np.ndarray  # (N, 3) int64 voxel keys
    logodds: np.ndarray  # (N,) float32, NaN = unknown
    last_time: np.ndarray  # (N,) float64 seconds
    channels: dict[str, np.ndarray] = field(default_factory=dict)
    time: float = 0.0
    surface_mask: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.keys = np.asarray(self.keys, dtype=np.int64).reshape(-1, 3)
        n = self.keys.shape[0]
        self.logodds = np.asarray(self.logodds, dtype=np.float32).reshape(-1)
        self.last_time = np.asarray(self.last_time, dtype=np.float64).reshape(-1)
        if self.logodds.shape[0] != n or self.last_time.shape[0] != n:
            msg = (
                f"delta arrays must have one row per key: {n} keys, "
                f"found {self.logodds.shape[0]} logodds and {self.last_time.shape[0]} times"
            )
            raise DeltaError(msg)
        if not self.resolution > 0:
            msg = f"delta resolution must be positive, found {self.resolution!r}"
            raise DeltaError(msg)
        if self.to_version < self.from_version:
            msg = (
                "delta to_version must be >= from_version, "
                f"found {self.from_version} -> {self.to_version}"
            )
            raise DeltaError(msg)
        for name, values in list(self.channels.items()):
            dtype, tail = channel_spec(name)
            if name == surface.CHANNEL:
                surface.check_codes(values)
            arr = np.asarray(values, dtype=dtype)
            if (
                arr.shape[:1] != (n,)
                or len(arr.shape) != 1 + len(tail)
                or any(t not in (-1, s) for t, s in zip(tail, arr.shape[1:], strict=True))
            ):
                msg = f"delta channel {name!r} must have shape ({n}, {tail}), found {arr.shape}"
                raise DeltaError(msg)
            self.channels[name] = arr
        if self.surface_mask is not None:
            mask = np.asarray(self.surface_mask)
            if surface.CHANNEL not in self.channels or mask.dtype != np.bool_ or mask.shape != (n,):
                msg = (
                    f"delta surface_mask must be ({n},) bool with a {surface.CHANNEL!r} channel, "
                    f"found {mask.shape} {mask.dtype} with channels {sorted(self.channels)}"
                )
                raise DeltaError(msg)
            self.surface_mask = mask

    def __len__(self) -> int:
        return int(self.keys.shape[0])

    @property
    def occupied(self) -> np.ndarray:
        """Mask of voxels that are occupied (log-odds >= 0) after this delta."""
        with np.errstate(invalid="ignore"):
            return self.logodds >= 0.0

    def select(self, mask: np.ndarray | slice) -> Delta:
        """The part of this delta at `mask` (a boolean mask, index array or slice), same
        versions."""
        return Delta(
            resolution=self.resolution,
            from_version=self.from_version,
            to_version=self.to_version,
            keys=self.keys[mask],
            logodds=self.logodds[mask],
            last_time=self.last_time[mask],
            channels={k: v[mask] for k, v in self.channels.items()},
            time=self.time,
            surface_mask=None if self.surface_mask is None else self.surface_mask[mask],
        )


def delta_of(
    store: BlockStore,
    times: TimeBase,
    version: int,
    *,
    resolution: float,
    to_version: int,
    time: float,
    sparse: bool = True,
) -> Delta:
    """Every voxel of `store` changed after `version`, with its absolute current values.

    `sparse`: surface codes only of the voxels whose codes changed after `version` (by the
    store's `surface_version`; every voxel's when it has none), as held; else every voxel's, 0
    for voxels that are not occupied (the dense form, for an origin that publishes it)."""
    slots = store.used_slots()
    slots = slots[store.slot_version[slots] > version]
    ver = store.channels["version"][slots]
    b, o = np.nonzero(ver > version)
    s = slots[b]
    # Keys from each block's corner plus its offset's place: unpacking per block, not per voxel
    # (a 10 M-voxel snapshot otherwise builds several (N, 3) temporaries).
    corners = vk.unpack(store.slot_keys[slots]) << np.asarray(store.shifts, dtype=np.int64)
    keys = corners[b]
    keys += store.offset_keys()[o]
    channels = {
        name: arr[s, o]
        for name, arr in store.channels.items()
        if name not in CORE_CHANNELS and name not in LOCAL_CHANNELS
    }
    logodds = store.channels["logodds"][s, o]
    codes = channels.get(surface.CHANNEL)
    mask = None
    changed = store.channels.get(surface.VERSION)
    if codes is not None and sparse and changed is not None:
        mask = changed[s, o] > version  # codes as held, carried where they changed
    elif codes is not None and not sparse:  # a surface is what an occupied voxel has: free
        with np.errstate(invalid="ignore"):  # ones travel as 0
            codes[~(logodds >= 0)] = 0
    return Delta(
        resolution=resolution,
        from_version=int(version),
        to_version=to_version,
        keys=keys,
        logodds=logodds,
        last_time=times.seconds(store.channels["last_time"][s, o]),
        channels=channels,
        time=time,
        surface_mask=mask,
    )


def best_classes(store: BlockStore) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The known voxels of `store` that hold a class, in the order `delta_of(store, ..., 0)`
    lists them: keys (L, 3), the most probable class of each (L,) int16 and its probability
    (L,) float32 (the column of its highest `class_probs`); none without a class channel."""
    ids, probs = store.channels.get("class_ids"), store.channels.get("class_probs")
    if ids is None or probs is None:
        return np.empty((0, 3), np.int64), np.empty(0, np.int16), np.empty(0, np.float32)
    slots = store.used_slots()
    slots = slots[store.slot_version[slots] > 0]
    p = probs[slots]
    column = p.argmax(axis=2)[..., None]
    classes = np.take_along_axis(ids[slots], column, axis=2)[..., 0].astype(np.int16)
    with np.errstate(invalid="ignore"):
        known = ~np.isnan(store.channels["logodds"][slots])
    b, o = np.nonzero((store.channels["version"][slots] > 0) & known & (classes >= 0))
    corners = vk.unpack(store.slot_keys[slots]) << np.asarray(store.shifts, dtype=np.int64)
    keys = corners[b]
    keys += store.offset_keys()[o]
    best = np.take_along_axis(p, column, axis=2)[..., 0]
    return keys, classes[b, o], best[b, o].astype(np.float32)


def merge_delta(store: BlockStore, times: TimeBase, delta: Delta) -> np.ndarray:
    """Write a delta's voxels into `store` where it is newer than the stored voxel (by version).

    Returns the delta's times (seconds) of the voxels that took its values.
    """
    if len(delta) == 0:
        return np.empty(0)
    if not vk.in_range(delta.keys).all():
        msg = (
            f"delta keys must lie in [{vk.KEY_MIN}, {vk.KEY_MAX}] on every axis, "
            f"found [{delta.keys.min()}, {delta.keys.max()}]"
        )
        raise DeltaError(msg)
    blocks, offsets = store.split(delta.keys)
    ub, inv = vk.unique_packed(blocks)
    slots = store.ensure(ub)[inv]
    incoming = np.uint32(delta.to_version)
    take = store.channels["version"][slots, offsets] < incoming
    if not take.any():
        return np.empty(0)
    s, o = slots[take], offsets[take]
    store.channels["logodds"][s, o] = delta.logodds[take]
    store.channels["last_time"][s, o] = times.stamp(delta.last_time[take])
    store.channels["version"][s, o] = incoming
    for name, values in delta.channels.items():
        arr = store.channel(name)
        if arr.shape[2:] != values.shape[1:]:
            msg = (
                f"delta channel {name!r} has shape {values.shape[1:]} per voxel, grid holds "
                f"{arr.shape[2:]}"
            )
            raise DeltaError(msg)
        if name == surface.CHANNEL:  # the codes carried alone (a sparse origin: their version)
            carried = take if delta.surface_mask is None else take & delta.surface_mask
            cs, co = slots[carried], offsets[carried]
            arr[cs, co] = values[carried]
            if surface.VERSION in store.channels:
                store.channels[surface.VERSION][cs, co] = incoming
            continue
        arr[s, o] = values[take]
    np.maximum.at(store.slot_version, s, incoming)
    taken: np.ndarray = delta.last_time[take]
    return taken


def same_content(a: Delta, b: Delta) -> bool:
    """True when two full deltas hold the same known voxels with the same values in every
    channel."""
    ka, kb = vk.pack(a.keys), vk.pack(b.keys)
    ia, ib = np.argsort(ka), np.argsort(kb)
    ma, mb = ~np.isnan(a.logodds[ia]), ~np.isnan(b.logodds[ib])
    ia, ib = ia[ma], ib[mb]
    if not np.array_equal(ka[ia], kb[ib]):
        return False
    if not (
        np.array_equal(a.logodds[ia], b.logodds[ib])
        and np.array_equal(a.last_time[ia], b.last_time[ib])
    ):
        return False
    for name in set(a.channels) | set(b.channels):
        if name not in a.channels or name not in b.channels:
            return False
        va, vb = a.channels[name][ia], b.channels[name][ib]
        if not np.array_equal(va, vb, equal_nan=va.dtype.kind == "f"):
            return False
    return True
