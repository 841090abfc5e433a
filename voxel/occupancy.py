"""Log-odds occupancy: the quantum, states, decay, and one scan's update of the stored voxels."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from voxel import kernels
from voxel import keys as vk
from voxel.blocks import BlockStore
from voxel.raycast import FREE, HIT, Traversal
from voxel.sensor import SensorModel
from voxel.timebase import TimeBase

UNKNOWN = np.int8(-1)
FREE_STATE = np.int8(0)
OCCUPIED = np.int8(1)

#: Stored log-odds are multiples of this quantum (and times whole milliseconds), so the wire
#: format carries exactly what the origin holds and every replica is bit-identical.
LOGODDS_QUANTUM = 2.0**-5
_Q_SCALE = np.float32(1.0 / LOGODDS_QUANTUM)

#: |log-odds| below which a decayed voxel is forgotten (returns to unknown).
FORGET_EPSILON = 0.05
#: Blocks updated per chunk: keeps temporaries small enough to stay in reused memory.
UPDATE_CHUNK = 4096


def quantise_logodds(values: npt.ArrayLike) -> np.ndarray:
    """Nearest multiple of LOGODDS_QUANTUM (float32; NaN stays NaN)."""
    scaled: np.ndarray = np.rint(np.asarray(values, dtype=np.float32) * _Q_SCALE)
    return (scaled / _Q_SCALE).astype(np.float32)


def states(lo: np.ndarray) -> np.ndarray:
    """UNKNOWN (NaN), FREE_STATE (< 0) or OCCUPIED (>= 0) of log-odds, as int8."""
    with np.errstate(invalid="ignore"):
        return np.where(np.isnan(lo), UNKNOWN, np.where(lo >= 0, OCCUPIED, FREE_STATE)).astype(
            np.int8
        )


def decayed(
    lo: np.ndarray, last: np.ndarray, now: float, half_life: float | None, times: TimeBase
) -> np.ndarray:
    """Log-odds `lo` stored at times `last` (stored form), decayed to `now` (unchanged without a
    half-life)."""
    if half_life is None:
        return lo
    dt = np.maximum(now - times.seconds(last), 0.0)
    return (lo * np.exp2(-dt / half_life)).astype(np.float32)


class Evidence(NamedTuple):
    """One scan's log-odds per traversal cell value (0 untouched, FREE, HIT; reliability applied),
    the same on the quantum grid, and the clamping bounds."""

    raw: np.ndarray  # (3,) float32
    step: np.ndarray  # (3,) float32, multiples of LOGODDS_QUANTUM
    low: np.ndarray  # () float32
    high: np.ndarray  # () float32

    @classmethod
    def of(cls, sensor: SensorModel, reliability: float) -> Evidence:
        """The evidence of `sensor` at `reliability` (cached: its arrays are shared, not to be
        written)."""
        return _evidence(sensor, float(reliability))

    @classmethod
    def compute(cls, sensor: SensorModel, reliability: float) -> Evidence:
        raw = np.zeros(3, dtype=np.float32)
        raw[FREE] = sensor.log_miss * reliability
        raw[HIT] = sensor.log_hit * reliability
        return cls(
            raw,
            quantise_logodds(raw),
            quantise_logodds(np.float32(sensor.log_min)),
            quantise_logodds(np.float32(sensor.log_max)),
        )


@functools.lru_cache(maxsize=256)
def _evidence(sensor: SensorModel, reliability: float) -> Evidence:
    # Not made read-only: numba would compile its kernels again for read-only arrays.
    return Evidence.compute(sensor, reliability)


class Changes(NamedTuple):
    """Voxels of one chunk of blocks that the history may record: every touched voxel whose
    value was written, with its log-odds before and after and whether it was hit."""

    keys: np.ndarray  # (M,) packed voxel keys
    before: np.ndarray  # (M,) float32, NaN = was unknown
    after: np.ndarray  # (M,) float32
    hit: np.ndarray  # (M,) bool
    seen: np.ndarray  # (F,) packed keys of the voxels that went unknown -> free


@dataclass
class OccupancyUpdate:
    """What one scan's occupancy update did: voxels changed, and per chunk the changes worth a
    record."""

    changed: int
    chunks: list[Changes]


@dataclass(frozen=True)
class UpdateRule:
    """How a layer updates: evidence of the scan, decay, and whether counts are kept."""

    evidence: Evidence
    half_life: float | None
    statistics: bool
    seen: bool = True  # log voxels seen free for the first time (History's seen log)


def update_occupancy(
    store: BlockStore,
    traversal: Traversal,
    rule: UpdateRule,
    version: int,
    time: float,
    stamp: np.ndarray,
    times: TimeBase,
) -> OccupancyUpdate:
    """Apply one scan's hits and misses to `store` in chunks of blocks (OctoMap's rule, one update
    per voxel, hits win); changed voxels take `version` and the time `stamp`."""
    update = OccupancyUpdate(0, [])
    if traversal.blocks.size == 0:
        return update
    slots_all = store.ensure(traversal.blocks)
    v = np.uint32(version)
    for lo_i in range(0, slots_all.size, UPDATE_CHUNK):
        slots = slots_all[lo_i : lo_i + UPDATE_CHUNK]
        cells = traversal.cells[lo_i : lo_i + UPDATE_CHUNK]
        _update_chunk(store, slots, cells, rule, v, time, stamp, times, update)
    return update


def _update_chunk(
    store: BlockStore,
    slots: np.ndarray,
    cells: np.ndarray,
    rule: UpdateRule,
    v: np.uint32,
    time: float,
    stamp: np.ndarray,
    times: TimeBase,
    update: OccupancyUpdate,
) -> None:
    ev = rule.evidence
    compiled = kernels.update() if rule.half_life is None and not rule.statistics else None
    if compiled is not None:
        count, keys, before, after, hit, seen = compiled(
            store.channels["logodds"],
            store.channels["version"],
            store.channels["last_time"],
            store.slot_version,
            store.slot_keys,
            slots,
            cells,
            ev.step,
            np.float32(ev.low),
            np.float32(ev.high),
            int(v),
            int(stamp),
            np.asarray(store.shifts, dtype=np.int64),
            rule.seen,
        )
        if count:
            update.changed += count
            update.chunks.append(Changes(keys, before, after, hit, seen))
        return
    old, new, changed, count = _update_numpy(store, slots, cells, rule, v, time, stamp, times)
    if count == 0:
        return
    update.changed += count
    update.chunks.append(_worth_recording(store, slots, old, new, changed, cells, rule.seen))


def _update_numpy(
    store: BlockStore,
    slots: np.ndarray,
    cells: np.ndarray,
    rule: UpdateRule,
    v: np.uint32,
    time: float,
    stamp: np.ndarray,
    times: TimeBase,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The update of one chunk in numpy (any rule): log-odds before and after, changed mask and
    count; the store is written only when something changed."""
    ev = rule.evidence
    lo_arr = store.channels["logodds"]
    old = lo_arr[slots]
    touched = cells != 0
    known = ~np.isnan(old)
    base = np.where(known, old, np.float32(0.0))
    if rule.half_life is not None:
        base = decayed(base, store.channels["last_time"][slots], time, rule.half_life, times)
        new = quantise_logodds(base + ev.raw[cells])
    else:
        new = base + ev.step[cells]  # base and steps lie on the quantum grid: the sum is exact
    np.clip(new, ev.low, ev.high, out=new)
    new = np.where(touched, new, old)
    if rule.half_life is not None or rule.statistics:
        changed = touched
    else:
        changed = touched & (~known | (new != old))
    count = int(np.count_nonzero(changed))
    if count == 0:
        return old, new, changed, 0
    lo_arr[slots] = new
    ver = store.channels["version"]
    ver[slots] = np.where(changed, v, ver[slots])
    last = store.channels["last_time"]
    last[slots] = np.where(changed, stamp, last[slots])
    store.slot_version[slots[changed.any(axis=1)]] = v
    if rule.statistics:
        _count(store, slots, cells, touched & ~known, time)
    return old, new, changed, count


def _count(
    store: BlockStore, slots: np.ndarray, cells: np.ndarray, first_seen: np.ndarray, time: float
) -> None:
    """Statistics: first observation time, hit and miss counts (saturating)."""
    hit = cells == HIT
    first = store.channel("first_time")
    first[slots] = np.where(first_seen, time, first[slots])
    hits = store.channel("hits")
    misses = store.channel("misses")
    hits[slots] = np.minimum(hits[slots].astype(np.int32) + hit, 65535).astype(np.uint16)
    misses[slots] = np.minimum(misses[slots].astype(np.int32) + (cells == FREE), 65535).astype(
        np.uint16
    )


def _worth_recording(
    store: BlockStore,
    slots: np.ndarray,
    old: np.ndarray,
    new: np.ndarray,
    changed: np.ndarray,
    cells: np.ndarray,
    seen: bool = True,
) -> Changes:
    """Changed voxels that are hit, occupied now or were occupied (see `History.record`), and
    apart, only their keys, the voxels seen for the first time as free (unknown -> free: most of
    a scan, so the history keeps them in a compact log)."""
    with np.errstate(invalid="ignore"):
        keep = (new >= 0) | (old >= 0)  # occupied now, or was (NaN, unknown, is neither)
        fresh = changed & np.isnan(old) & (new < 0) if seen else None
    keep |= cells == HIT
    keep &= changed
    b, o = np.nonzero(keep)
    keys = (
        vk.pack(store.join(store.slot_keys[slots[b]], o)) if b.size else np.empty(0, dtype=np.int64)
    )
    fresh_keys = np.empty(0, dtype=np.int64)
    if fresh is not None:
        fb, fo = np.nonzero(fresh)
        if fb.size:
            fresh_keys = vk.pack(store.join(store.slot_keys[slots[fb]], fo))
    return Changes(keys, old[b, o], new[b, o], cells[b, o] == HIT, fresh_keys)
