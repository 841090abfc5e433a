"""The information-rich voxel grid of one layer: integration, queries, versions and deltas."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from voxel import keys as vk
from voxel.blocks import BlockStore, block_shifts
from voxel.delta import SCALAR_PREFIX, Delta
from voxel.errors import DeltaError, InputError
from voxel.history import History
from voxel.raycast import FREE, HIT, Traversal, ray_keys, trace
from voxel.sensor import SensorModel

UNKNOWN = np.int8(-1)
FREE_STATE = np.int8(0)
OCCUPIED = np.int8(1)

#: Stored log-odds are multiples of this quantum (and times whole milliseconds), so the wire
#: format carries exactly what the origin holds and every replica is bit-identical.
LOGODDS_QUANTUM = 2.0**-5
_Q_SCALE = np.float32(1.0 / LOGODDS_QUANTUM)


def quantise_logodds(values: np.ndarray) -> np.ndarray:
    """Nearest multiple of LOGODDS_QUANTUM (float32; NaN stays NaN)."""
    return (np.rint(np.asarray(values, dtype=np.float32) * _Q_SCALE) / _Q_SCALE).astype(np.float32)


def quantise_time(t: float) -> float:
    """Time rounded to whole milliseconds, as k / 1000.0."""
    return round(float(t) * 1000.0) / 1000.0


#: Stored times span at most this many ms from the grid's time base (uint32).
TIME_SPAN_MS = 2**32 - 1

#: Beams without a hit are cast once per 1/CLEAR_SUBDIVISION-voxel cell of their truncated ends
#: (one real beam stands for its cell): close to casting every beam (OctoMap's default) at a
#: fraction of the rays where beams are dense, exact where they are sparse.
CLEAR_SUBDIVISION = 3

#: |log-odds| below which a decayed voxel is forgotten (returns to unknown).
FORGET_EPSILON = 0.05
#: Blocks updated per chunk: keeps temporaries small enough to stay in reused memory.
UPDATE_CHUNK = 4096
#: Weight of a new class observation in the per-voxel class distribution.
CLASS_RATE = 0.3

DEFAULT_SENSOR = SensorModel()


class _Evidence(NamedTuple):
    """One scan's log-odds per traversal cell value (0 untouched, FREE, HIT; reliability applied),
    the same on the quantum grid, and the clamping bounds."""

    raw: np.ndarray  # (3,) float32
    step: np.ndarray  # (3,) float32, multiples of LOGODDS_QUANTUM
    low: np.float32
    high: np.float32

    @classmethod
    def of(cls, sensor: SensorModel, reliability: float) -> _Evidence:
        raw = np.zeros(3, dtype=np.float32)
        raw[FREE] = sensor.log_miss * reliability
        raw[HIT] = sensor.log_hit * reliability
        return cls(raw, quantise_logodds(raw), quantise_logodds(np.float32(sensor.log_min)),
                   quantise_logodds(np.float32(sensor.log_max)))


@dataclass(frozen=True)
class IntegrationReport:
    """What one `integrate` call did."""

    points: int  # points given
    hits: int  # points that ended in a hit
    cleared: int  # beams without a hit (no return or beyond max range) that cleared free space
    invalid: int  # NaN/inf points, zero-length rays, keys outside the key space
    dropped: int  # no-return beams that could not be used (sensor without a max range)
    voxels_hit: int
    voxels_free: int
    voxels_changed: int
    version: int


def _as_points(points: np.ndarray, name: str = "points") -> np.ndarray:
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] != 3:
        msg = f"{name} must have shape (N, 3), found {arr.shape}"
        raise InputError(msg)
    if not np.issubdtype(arr.dtype, np.number):
        msg = f"{name} must be numeric, found dtype {arr.dtype}"
        raise InputError(msg)
    return arr.astype(np.float64, copy=False)


def _per_point(values: np.ndarray | None, n: int, name: str, tail: tuple[int, ...] = ()) -> np.ndarray | None:
    if values is None:
        return None
    arr = np.asarray(values)
    if arr.shape != (n, *tail):
        msg = f"{name} must have shape {(n, *tail)} (one row per point), found {arr.shape}"
        raise InputError(msg)
    return arr


class VoxelGrid:
    """Sparse blocks of dense voxels holding log-odds occupancy and rich per-voxel channels.

    One grid is one layer with a single writer. Every change bumps the grid version; each voxel
    remembers the version of its last change, so `delta_since` returns exactly what changed and
    `apply` is idempotent and order-independent. `block_shape` is "cube" (4x4x4, for 3D sensors),
    "planar" (8x8x1, for a layer mapped by a 2D scanner) or three side lengths.
    """

    def __init__(
        self,
        resolution: float,
        *,
        half_life: float | None = None,
        statistics: bool = False,
        class_k: int = 3,
        history_capacity: int = 2_000_000,
        history_per_voxel: int = 16,
        block_shape: str | tuple[int, int, int] = "cube",
    ) -> None:
        if not (isinstance(resolution, (int, float)) and math.isfinite(resolution) and resolution > 0):
            msg = f"resolution must be a positive number of metres, found {resolution!r}"
            raise InputError(msg)
        if half_life is not None and not half_life > 0:
            msg = f"half_life must be positive seconds or None, found {half_life!r}"
            raise InputError(msg)
        self.resolution = float(resolution)
        self.half_life = half_life
        self.statistics = statistics
        self.store = BlockStore(class_k=class_k, shifts=block_shifts(block_shape))
        self.history = History(capacity=history_capacity, per_voxel=history_per_voxel)
        self.version = 0
        self.now = 0.0  # latest observation time seen
        self.time_base_ms: int | None = None  # stored times are ms since this

    # ------------------------------------------------------------------------------ integration
    def integrate(
        self,
        points: np.ndarray,
        origin: np.ndarray,
        *,
        time: float,
        sensor: SensorModel = DEFAULT_SENSOR,
        agent: str = "self",
        reliability: float = 1.0,
        experience: float = 0.0,
        bias: float = 0.0,
        colours: np.ndarray | None = None,
        normals: np.ndarray | None = None,
        class_ids: np.ndarray | None = None,
        class_probs: np.ndarray | None = None,
        object_ids: np.ndarray | None = None,
        scalars: dict[str, np.ndarray] | None = None,
        no_return: np.ndarray | None = None,
    ) -> IntegrationReport:
        """Integrate one scan of world-frame points taken from `origin`.

        Each ray clears the voxels it passes up to its end voxel, which is hit (OctoMap's update:
        each voxel is updated once per scan, hits win over misses). Points beyond the sensor's
        max range and beams flagged `no_return` clear up to max range and hit nothing.
        """
        pts = _as_points(points)
        n = pts.shape[0]
        org = np.asarray(origin, dtype=np.float64).reshape(-1)
        if org.shape != (3,) or not np.all(np.isfinite(org)):
            msg = f"origin must be 3 finite numbers, found {np.asarray(origin)!r}"
            raise InputError(msg)
        if not (math.isfinite(time)):
            msg = f"time must be a finite number of seconds, found {time!r}"
            raise InputError(msg)
        if not 0.0 < reliability <= 1.0:
            msg = f"reliability must be in (0, 1], found {reliability!r}"
            raise InputError(msg)
        colours = _per_point(colours, n, "colours", (3,))
        normals = _per_point(normals, n, "normals", (3,))
        class_ids = _per_point(class_ids, n, "class_ids")
        class_probs = _per_point(class_probs, n, "class_probs")
        object_ids = _per_point(object_ids, n, "object_ids")
        nr = _per_point(no_return, n, "no_return")
        nr = np.zeros(n, dtype=bool) if nr is None else nr.astype(bool)
        scalars = {k: _per_point(v, n, f"scalars[{k!r}]") for k, v in (scalars or {}).items()}

        rows = np.ascontiguousarray(pts.T, dtype=np.float64)  # (3, N): per-axis passes are contiguous
        r2 = rows[0] - org[0]
        r2 *= r2
        for axis in (1, 2):
            t = rows[axis] - org[axis]
            t *= t
            r2 += t
        max2 = sensor.max_range * sensor.max_range
        with np.errstate(invalid="ignore"):
            hit_mask = (r2 > 0) & (r2 <= max2)  # NaN, inf, zero-length and beyond max range fail
        hit_mask &= ~nr
        all_hit = bool(hit_mask.all())
        clear_mask = np.zeros(n, dtype=bool)
        if not all_hit:
            rest = np.flatnonzero(~hit_mask)
            r = np.sqrt(r2[rest])
            with np.errstate(invalid="ignore"):
                valid = np.isfinite(r) & (r > 0)
                clear_mask[rest] = valid & ((r > sensor.max_range) | nr[rest])
        dropped = 0
        if not math.isfinite(sensor.max_range):
            dropped = int(np.count_nonzero(clear_mask))
            clear_mask[:] = False
        inv = 1.0 / self.resolution
        hit_keys = rows * inv if all_hit else np.compress(hit_mask, rows, axis=1) * inv
        np.floor(hit_keys, out=hit_keys)
        if hit_keys.size and (hit_keys.min() < vk.KEY_MIN or hit_keys.max() > vk.KEY_MAX):
            ok = np.all((hit_keys >= vk.KEY_MIN) & (hit_keys <= vk.KEY_MAX), axis=0)
            hit_mask[np.flatnonzero(hit_mask)[~ok]] = False
            hit_keys = hit_keys[:, ok]
        clear_ends = self._clear_ends(rows, org, r2, clear_mask, sensor.max_range) if clear_mask.any() else np.empty((0, 3))
        n_hits = int(hit_keys.shape[1])
        invalid = n - n_hits - int(np.count_nonzero(clear_mask)) - dropped

        want_inverse = any(x is not None for x in (colours, normals, class_ids, object_ids)) or bool(scalars)
        traversal = trace(org, hit_keys, clear_ends, self.resolution, self.store.shifts, want_inverse)
        inverse = traversal.inverse
        uniq = vk.pack(traversal.hit_keys) if object_ids is not None else None

        hit_mask_idx = np.flatnonzero(hit_mask) if want_inverse else None
        rich = {
            "colours": None if colours is None else colours[hit_mask_idx],
            "normals": None if normals is None else normals[hit_mask_idx],
            "class_ids": None if class_ids is None else class_ids[hit_mask_idx],
            "class_probs": None if class_probs is None else class_probs[hit_mask_idx],
            "object_ids": None if object_ids is None else object_ids[hit_mask_idx],
            "scalars": {k: v[hit_mask_idx] for k, v in scalars.items()},
        }
        ev = _Evidence.of(sensor, reliability)
        time = quantise_time(time)
        objects = self._object_lookup(uniq, inverse, rich["object_ids"])
        context = {
            "time": float(time),
            "agent": self.history.agent_code(agent),
            "sensor": sensor.kind_code,
            "reliability": reliability,
            "experience": experience,
            "bias": bias,
            "objects": objects,
            "stamp": self._stamp(time),
        }
        changed = self._update(traversal, float(time), ev, context)
        self._update_rich(traversal.hit_keys, inverse, rich, float(time), bumped=changed > 0)
        self.now = max(self.now, float(time))
        return IntegrationReport(
            points=n,
            hits=n_hits,
            cleared=int(np.count_nonzero(clear_mask)),
            invalid=invalid,
            dropped=dropped,
            voxels_hit=traversal.hit_count,
            voxels_free=traversal.free_count,
            voxels_changed=int(changed),
            version=self.version,
        )

    def _clear_ends(self, rows: np.ndarray, org: np.ndarray, r2: np.ndarray, clear_mask: np.ndarray,
                    max_range: float) -> np.ndarray:
        """End points (M, 3) of the rays of beams without a hit; drops unusable beams from clear_mask.

        Beams are truncated at max range and cast once per 1/CLEAR_SUBDIVISION-voxel cell of their
        ends, one real beam standing for its cell (OctoMap's discretised update does the like):
        distant beams share voxels.
        """
        idx = np.flatnonzero(clear_mask)
        scale = max_range / np.sqrt(r2[idx])
        ends = rows.take(idx, axis=1) - org[:, None]
        ends *= scale
        ends += org[:, None]
        fine = ends * (CLEAR_SUBDIVISION / self.resolution)
        np.floor(fine, out=fine)
        limit = vk.KEY_MAX * CLEAR_SUBDIVISION
        if fine.min() < -limit or fine.max() > limit:
            ok = np.all((fine >= -limit) & (fine <= limit), axis=0)
            clear_mask[idx[~ok]] = False
            ends, fine = ends[:, ok], fine[:, ok]
        return ends.T[vk.one_per_key(fine)]  # one real beam per cell

    def integrate_depth(
        self,
        depth: np.ndarray,
        intrinsics: np.ndarray,
        pose: np.ndarray,
        *,
        time: float,
        sensor: SensorModel = DEFAULT_SENSOR,
        colour: np.ndarray | None = None,
        labels: np.ndarray | None = None,
        **kwargs: object,
    ) -> IntegrationReport:
        """Integrate a depth image (metres, 0/NaN = no reading) seen from camera-to-world `pose`."""
        depth = np.asarray(depth, dtype=np.float64)
        if depth.ndim != 2:
            msg = f"depth must be an (H, W) image, found shape {depth.shape}"
            raise InputError(msg)
        k = np.asarray(intrinsics, dtype=np.float64)
        if k.shape != (3, 3):
            msg = f"intrinsics must be a 3x3 matrix, found shape {k.shape}"
            raise InputError(msg)
        t = np.asarray(pose, dtype=np.float64)
        if t.shape != (4, 4) or not np.all(np.isfinite(t)):
            msg = f"pose must be a finite 4x4 camera-to-world matrix, found shape {t.shape}"
            raise InputError(msg)
        h, w = depth.shape
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(depth) & (depth > 0)
        v, u = np.nonzero(valid)
        z = depth[v, u]
        cam = np.stack([(u - k[0, 2]) * z / k[0, 0], (v - k[1, 2]) * z / k[1, 1], z], axis=1)
        world = cam @ t[:3, :3].T + t[:3, 3]
        extra: dict[str, object] = dict(kwargs)
        if colour is not None:
            c = np.asarray(colour)
            if c.shape[:2] != (h, w) or c.ndim != 3 or c.shape[2] != 3:
                msg = f"colour must be an (H, W, 3) image matching depth {(h, w)}, found {c.shape}"
                raise InputError(msg)
            extra["colours"] = c[v, u]
        if labels is not None:
            lab = np.asarray(labels)
            if lab.shape != (h, w):
                msg = f"labels must be an (H, W) image matching depth {(h, w)}, found {lab.shape}"
                raise InputError(msg)
            extra["class_ids"] = lab[v, u].astype(np.int16)
            extra["class_probs"] = np.ones(z.shape[0], dtype=np.float32)
        return self.integrate(world, t[:3, 3], time=time, sensor=sensor, **extra)  # type: ignore[arg-type]

    def _stamp(self, t: float | np.ndarray) -> np.ndarray:
        """Stored form of times (seconds, whole ms): uint32 ms since the grid's time base.

        The base moves when a time falls outside the 49-day window; voxels older than a moved
        base are kept at the base (their age is then only known to be at least ~24 days).
        """
        ms = np.rint(np.asarray(t, dtype=np.float64) * 1000.0).astype(np.int64)
        if ms.size == 0:
            return ms.astype(np.uint32)
        lo, hi = int(ms.min()), int(ms.max())
        if self.time_base_ms is None:
            self.time_base_ms = lo - lo % 3_600_000
        if lo < self.time_base_ms or hi - self.time_base_ms > TIME_SPAN_MS:
            new_base = lo - lo % 3_600_000 if lo < self.time_base_ms else hi - TIME_SPAN_MS // 2
            self._shift_times(new_base)
        return (ms - self.time_base_ms).clip(0, TIME_SPAN_MS).astype(np.uint32)

    def _shift_times(self, new_base: int) -> None:
        st = self.store
        slots = st.used_slots()
        rel = st.channels["last_time"][slots].astype(np.int64) + (self.time_base_ms - new_base)
        st.channels["last_time"][slots] = rel.clip(0, TIME_SPAN_MS).astype(np.uint32)
        self.time_base_ms = new_base

    def _times(self, stored: np.ndarray) -> np.ndarray:
        """Seconds (float64, exactly k / 1000) of stored times."""
        base = self.time_base_ms or 0
        return (np.asarray(stored).astype(np.int64) + base) / 1000.0

    def _decayed(self, lo: np.ndarray, last: np.ndarray, now: float) -> np.ndarray:
        if self.half_life is None:
            return lo
        dt = np.maximum(now - self._times(last), 0.0)
        return (lo * np.exp2(-dt / self.half_life)).astype(np.float32)

    def _update(self, tr: Traversal, time: float, ev: _Evidence, context: dict) -> int:
        """Apply one scan's hits and misses to the store, in chunks of blocks; returns voxels changed."""
        if tr.blocks.size == 0:
            return 0
        st = self.store
        slots_all = st.ensure(tr.blocks)
        v = np.uint32(self.version + 1)
        count = 0
        for lo_i in range(0, slots_all.size, UPDATE_CHUNK):
            slots = slots_all[lo_i : lo_i + UPDATE_CHUNK]
            cells = tr.cells[lo_i : lo_i + UPDATE_CHUNK]
            count += self._update_chunk(slots, cells, v, time, ev, context)
        if count:
            self.version = int(v)
        return count

    def _update_chunk(
        self, slots: np.ndarray, cells: np.ndarray, v: np.uint32, time: float, ev: _Evidence, context: dict
    ) -> int:
        st = self.store
        lo_arr = st.channels["logodds"]
        old = lo_arr[slots]
        touched = cells != 0
        known = ~np.isnan(old)
        base = np.where(known, old, np.float32(0.0))
        if self.half_life is not None:
            base = self._decayed(base, st.channels["last_time"][slots], time)
            new = quantise_logodds(base + ev.raw[cells])
        else:
            new = base + ev.step[cells]  # base and steps lie on the quantum grid: the sum is exact
        np.clip(new, ev.low, ev.high, out=new)
        new = np.where(touched, new, old)
        if self.half_life is not None or self.statistics:
            changed = touched
        else:
            changed = touched & (~known | (new != old))
        count = int(np.count_nonzero(changed))
        if count == 0:
            return 0
        lo_arr[slots] = new
        ver = st.channels["version"]
        ver[slots] = np.where(changed, v, ver[slots])
        last = st.channels["last_time"]
        last[slots] = np.where(changed, context["stamp"], last[slots])
        st.slot_version[slots[changed.any(axis=1)]] = v
        if self.statistics:
            hit = cells == HIT
            first = st.channel("first_time")
            first[slots] = np.where(touched & ~known, time, first[slots])
            hits = st.channel("hits")
            misses = st.channel("misses")
            hits[slots] = np.minimum(hits[slots].astype(np.int32) + hit, 65535).astype(np.uint16)
            misses[slots] = np.minimum(misses[slots].astype(np.int32) + (cells == FREE), 65535).astype(np.uint16)
        self._record(slots, old, new, changed, cells, ev, context)
        return count

    def _update_rich(self, keys: np.ndarray, inverse: np.ndarray, rich: dict, time: float, bumped: bool) -> None:
        """Fold colour, normals, classes and scalar channels of hit points into their voxels."""
        wanted = [rich["colours"], rich["normals"], rich["class_ids"]] + list(rich["scalars"].values())
        if keys.shape[0] == 0 or inverse is None or all(x is None for x in wanted):
            return
        st = self.store
        blocks, offsets = self.store.split(keys)
        slots = st.lookup(blocks)
        m = keys.shape[0]
        counts = np.bincount(inverse, minlength=m).astype(np.float64)
        weight_arr = st.channel("hits")
        w_old = weight_arr[slots, offsets].astype(np.float64)
        if not self.statistics:  # hits counted here only when statistics did not count them
            weight_arr[slots, offsets] = np.minimum(w_old + 1, 65535).astype(np.uint16)
        else:
            w_old = np.maximum(w_old - 1, 0)
        frac = 1.0 / (w_old + 1.0)

        def mean_of(values: np.ndarray) -> np.ndarray:
            v = values.reshape(values.shape[0], -1).astype(np.float64)
            out = np.stack([np.bincount(inverse, weights=v[:, j], minlength=m) for j in range(v.shape[1])], axis=1)
            return out / counts[:, None]

        if rich["colours"] is not None:
            arr = st.channel("colour")
            frame = mean_of(rich["colours"])
            cur = arr[slots, offsets].astype(np.float64)
            arr[slots, offsets] = np.clip(np.rint(cur + (frame - cur) * frac[:, None]), 0, 255).astype(np.uint8)
        if rich["normals"] is not None:
            arr = st.channel("normal")
            frame = mean_of(rich["normals"])
            cur = arr[slots, offsets].astype(np.float64)
            mixed = cur + (frame - cur) * frac[:, None]
            norm = np.linalg.norm(mixed, axis=1, keepdims=True)
            arr[slots, offsets] = np.where(norm > 0, mixed / np.where(norm > 0, norm, 1), 0).astype(np.float32)
        for name, values in rich["scalars"].items():
            arr = st.channel(SCALAR_PREFIX + name)
            frame = mean_of(np.asarray(values, dtype=np.float64))[:, 0]
            cur = arr[slots, offsets].astype(np.float64)
            cur = np.where(np.isnan(cur), frame, cur)
            arr[slots, offsets] = (cur + (frame - cur) * frac).astype(np.float32)
        if rich["class_ids"] is not None:
            probs = rich["class_probs"]
            probs = np.ones(inverse.size) if probs is None else np.asarray(probs, dtype=np.float64)
            self._update_classes(slots, offsets, inverse, np.asarray(rich["class_ids"], dtype=np.int64), probs)
        self._bump(slots, offsets, time, bumped)

    def _update_classes(
        self, slots: np.ndarray, offsets: np.ndarray, inverse: np.ndarray, cls: np.ndarray, prob: np.ndarray
    ) -> None:
        """Per voxel: the frame's majority class and its mean probability enter a bounded top-k."""
        st = self.store
        labelled = cls >= 0
        if not labelled.any():
            return
        vox, c, p = inverse[labelled], cls[labelled], prob[labelled]
        pair = vox.astype(np.int64) * 65536 + (c & 0xFFFF)
        up, pinv, pcount = np.unique(pair, return_inverse=True, return_counts=True)
        psum = np.bincount(pinv, weights=p)
        pv = up // 65536
        order = np.lexsort((-pcount, pv))  # per voxel, most frequent class first
        first = np.r_[True, pv[order][1:] != pv[order][:-1]]
        best = order[first]
        v_idx = pv[best]
        v_cls = (up[best] % 65536).astype(np.int16)
        v_prob = (psum[best] / pcount[best]).astype(np.float32)
        ids = st.channel("class_ids")
        prs = st.channel("class_probs")
        s, o = slots[v_idx], offsets[v_idx]
        cur_ids = ids[s, o]  # (M, k)
        cur_p = prs[s, o] * np.float32(1.0 - CLASS_RATE)
        match = cur_ids == v_cls[:, None]
        has = match.any(axis=1)
        col = np.where(has, match.argmax(axis=1), cur_p.argmin(axis=1))
        rows = np.arange(col.size)
        replace = ~has
        cur_ids[rows[replace], col[replace]] = v_cls[replace]
        cur_p[rows[replace], col[replace]] = 0.0
        cur_p[rows, col] += np.float32(CLASS_RATE) * v_prob
        ids[s, o] = cur_ids
        prs[s, o] = cur_p

    def _bump(self, slots: np.ndarray, offsets: np.ndarray, time: float, bumped: bool) -> None:
        """Mark voxels as changed in this integration's version (their rich channels changed)."""
        st = self.store
        ver = st.channels["version"]
        if not bumped:
            self.version += 1
        v = np.uint32(self.version)
        ver[slots, offsets] = v
        st.channels["last_time"][slots, offsets] = self._stamp(time)
        st.slot_version[slots] = v

    @staticmethod
    def _object_lookup(uniq: np.ndarray | None, inverse: np.ndarray | None, object_ids: np.ndarray | None):
        """(sorted packed keys, object id per key) of hit voxels carrying an object id, or None."""
        if object_ids is None or inverse is None or uniq is None or uniq.size == 0:
            return None
        per_voxel = np.full(uniq.size, -1, dtype=np.int64)
        per_voxel[inverse] = object_ids  # the last point of a voxel wins
        return uniq, per_voxel

    def _record(
        self, slots: np.ndarray, old: np.ndarray, new: np.ndarray, mask: np.ndarray, cells: np.ndarray,
        ev: _Evidence, context: dict,
    ) -> None:
        """History: every hit voxel and every voxel whose state flipped gets a record.

        Free space seen for the first time (unknown -> free) is not recorded: it is most of every
        scan and carries no event; `state_at` derives it from the voxel's current state.
        """
        with np.errstate(invalid="ignore"):
            keep = (new >= 0) | (old >= 0)  # occupied now, or was (NaN, unknown, is neither)
        keep |= cells == HIT
        keep &= mask
        b, o = np.nonzero(keep)
        if b.size == 0:
            return
        before = old[b, o]
        state = new[b, o] >= 0
        with np.errstate(invalid="ignore"):
            flip = np.isnan(before) | ((before >= 0) != state)
        hit = cells[b, o] == HIT
        keys = vk.pack(self.store.join(self.store.slot_keys[slots[b]], o))
        obj_id = np.full(b.size, -1, dtype=np.int32)
        obj_p = np.zeros(b.size, dtype=np.float32)
        if context["objects"] is not None:
            uniq, per_voxel = context["objects"]
            pos = np.minimum(np.searchsorted(uniq, keys), uniq.size - 1)
            found = uniq[pos] == keys
            obj_id[found] = per_voxel[pos[found]]
            obj_p[found & (obj_id >= 0)] = 1.0
        self.history.append(
            keys,
            time=context["time"],
            agent=context["agent"],
            sensor=context["sensor"],
            evidence=np.where(hit, ev.raw[HIT], ev.raw[FREE]),
            logodds=new[b, o],
            state=np.where(state, OCCUPIED, FREE_STATE),
            flip=flip,
            object_id=obj_id,
            object_prob=obj_p,
            experience=context["experience"],
            reliability=context["reliability"],
            bias=context["bias"],
        )

    # ---------------------------------------------------------------------------------- queries
    def _lookup(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        blocks, offsets = self.store.split(keys)
        slots = self.store.lookup(blocks)
        return slots, offsets, slots >= 0

    def logodds_at_keys(self, keys: np.ndarray, now: float | None = None) -> np.ndarray:
        """Log-odds (decayed to `now`, default the latest observation) of voxel keys; NaN unknown."""
        keys = np.asarray(keys, dtype=np.int64).reshape(-1, 3)
        slots, offsets, found = self._lookup(keys)
        out = np.full(keys.shape[0], np.nan, dtype=np.float32)
        s, o = slots[found], offsets[found]
        lo = self.store.channels["logodds"][s, o]
        out[found] = self._decayed(lo, self.store.channels["last_time"][s, o], self.now if now is None else now)
        return out

    def occupancy(self, points: np.ndarray, now: float | None = None) -> np.ndarray:
        """Occupancy probability at world points; NaN where unknown."""
        lo = self.logodds_at_keys(vk.points_to_keys(_as_points(points), self.resolution), now)
        return 1.0 / (1.0 + np.exp(-lo.astype(np.float64)))

    def state(self, points: np.ndarray, now: float | None = None) -> np.ndarray:
        """UNKNOWN (-1), FREE (0) or OCCUPIED (1) at world points."""
        lo = self.logodds_at_keys(vk.points_to_keys(_as_points(points), self.resolution), now)
        return _states(lo)

    def _all(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Used slots (U,), their decayed log-odds (U, 512)."""
        st = self.store
        slots = st.used_slots()
        lo = st.channels["logodds"][slots]
        if self.half_life is not None:
            lo = self._decayed(lo, st.channels["last_time"][slots], self.now)
        return slots, lo, st.slot_keys[slots]

    def _keys_where(self, pred) -> np.ndarray:
        slots, lo, bkeys = self._all()
        with np.errstate(invalid="ignore"):
            b, o = np.nonzero(pred(lo))
        return self.store.join(bkeys[b], o)

    def occupied_keys(self) -> np.ndarray:
        """Keys (M, 3) of occupied voxels."""
        return self._keys_where(lambda lo: lo >= 0)

    def free_keys(self) -> np.ndarray:
        """Keys (M, 3) of free voxels."""
        return self._keys_where(lambda lo: lo < 0)

    def known_count(self) -> int:
        """Number of voxels that are not unknown."""
        return int(np.count_nonzero(~np.isnan(self.store.channels["logodds"][self.store.used_slots()])))

    def occupied_in_box(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Centres (M, 3) of occupied voxels whose centre lies in the box [lo, hi]."""
        lo = np.asarray(lo, dtype=np.float64).reshape(3)
        hi = np.asarray(hi, dtype=np.float64).reshape(3)
        centres = vk.keys_to_centers(self.occupied_keys(), self.resolution)
        inside = np.all((centres >= lo) & (centres <= hi), axis=1)
        return centres[inside]

    def cast_ray(self, origin: np.ndarray, direction: np.ndarray, max_range: float) -> np.ndarray | None:
        """Centre of the first occupied voxel along a ray, or None within max_range."""
        o = np.asarray(origin, dtype=np.float64).reshape(3)
        dvec = np.asarray(direction, dtype=np.float64).reshape(3)
        norm = float(np.linalg.norm(dvec))
        if not norm > 0 or not max_range > 0:
            msg = f"cast_ray needs a non-zero direction and positive max_range, found {dvec!r}, {max_range!r}"
            raise InputError(msg)
        keys = ray_keys(o, o + dvec / norm * max_range, self.resolution)
        states = _states(self.logodds_at_keys(keys))
        hit = np.flatnonzero(states == OCCUPIED)
        return None if hit.size == 0 else vk.keys_to_centers(keys[hit[:1]], self.resolution)[0]

    def voxel_history(self, point: np.ndarray) -> np.ndarray:
        """History records (structured array, oldest first) of the voxel containing `point`."""
        key = vk.points_to_keys(_as_points(np.asarray(point).reshape(1, 3)), self.resolution)
        return self.history.of_voxel(int(vk.pack(key)[0]))

    def state_at(self, points: np.ndarray, t: float) -> np.ndarray:
        """State of the voxels at `points` as it was at time t.

        From the history where it holds a record at or before t; a voxel without one that is
        free now and last changed at or before t was free then (it never flipped); else unknown.
        """
        keys = vk.points_to_keys(_as_points(points), self.resolution)
        out = self.history.state_at(vk.pack(keys), t)
        none = out == UNKNOWN
        if none.any():
            slots, offsets, found = self._lookup(keys[none])
            lo = np.full(found.size, np.nan, dtype=np.float32)
            last = np.full(found.size, np.inf)
            lo[found] = self.store.channels["logodds"][slots[found], offsets[found]]
            last[found] = self._times(self.store.channels["last_time"][slots[found], offsets[found]])
            with np.errstate(invalid="ignore"):
                free_then = (lo < 0) & (last <= t)
            out[np.flatnonzero(none)[free_then]] = FREE_STATE
        return out

    def changed_between(self, t0: float, t1: float) -> np.ndarray:
        """Keys (M, 3) of voxels whose state changed in (t0, t1]."""
        return vk.unpack(self.history.flips_between(t0, t1))

    def channel_at_keys(self, name: str, keys: np.ndarray) -> np.ndarray:
        """Values of a rich channel (e.g. 'colour', 'class_ids', 'scalar:temp') at voxel keys."""
        if name not in self.store.channels:
            msg = f"channel {name!r} has never been written; present: {sorted(self.store.channels)}"
            raise InputError(msg)
        slots, offsets, found = self._lookup(np.asarray(keys, dtype=np.int64).reshape(-1, 3))
        arr = self.store.channels[name]
        out = np.full((found.size, *arr.shape[2:]), self.store.spec(name)[2], dtype=arr.dtype)
        out[found] = arr[slots[found], offsets[found]]
        return self._times(out) if name == "last_time" else out

    # ------------------------------------------------------------------------------- forgetting
    def forget(self, now: float | None = None) -> int:
        """Voxels whose decayed evidence is ~0 become unknown; empty blocks are freed. Returns blocks freed."""
        if self.half_life is None:
            return 0
        now = self.now if now is None else now
        st = self.store
        slots = st.used_slots()
        lo = st.channels["logodds"][slots]
        eff = self._decayed(lo, st.channels["last_time"][slots], now)
        with np.errstate(invalid="ignore"):
            gone = np.abs(eff) < FORGET_EPSILON
        lo[gone] = np.nan
        st.channels["logodds"][slots] = lo
        empty = np.isnan(lo).all(axis=1)
        st.release(slots[empty])
        return int(np.count_nonzero(empty))

    # ----------------------------------------------------------------------------------- deltas
    def delta_since(self, version: int) -> Delta:
        """Every voxel changed after `version`, with its absolute current values."""
        st = self.store
        slots = st.used_slots()
        slots = slots[st.slot_version[slots] > version]
        ver = st.channels["version"][slots]
        b, o = np.nonzero(ver > version)
        s = slots[b]
        keys = self.store.join(st.slot_keys[s], o)
        channels = {name: arr[s, o] for name, arr in st.channels.items() if name not in ("logodds", "version", "last_time")}
        return Delta(
            resolution=self.resolution,
            from_version=int(version),
            to_version=self.version,
            keys=keys,
            logodds=st.channels["logodds"][s, o],
            last_time=self._times(st.channels["last_time"][s, o]),
            channels=channels,
            time=self.now,
        )

    def apply(self, delta: Delta) -> int:
        """Apply a delta: each voxel takes the delta's values unless it already holds a newer version.

        Returns the number of voxels that took the delta's values.
        """
        if not math.isclose(delta.resolution, self.resolution, rel_tol=1e-9):
            msg = f"delta resolution {delta.resolution} does not match the grid's {self.resolution}"
            raise DeltaError(msg)
        if len(delta) == 0:
            self.version = max(self.version, delta.to_version)
            return 0
        if not vk.in_range(delta.keys).all():
            msg = f"delta keys must lie in [{vk.KEY_MIN}, {vk.KEY_MAX}] on every axis"
            raise DeltaError(msg)
        st = self.store
        blocks, offsets = self.store.split(delta.keys)
        ub, inv = np.unique(blocks, return_inverse=True)
        slots = st.ensure(ub)[inv]
        incoming = np.uint32(delta.to_version)
        take = st.channels["version"][slots, offsets] < incoming
        if not take.any():
            self.version = max(self.version, delta.to_version)
            return 0
        s, o = slots[take], offsets[take]
        st.channels["logodds"][s, o] = delta.logodds[take]
        st.channels["last_time"][s, o] = self._stamp(delta.last_time[take])
        st.channels["version"][s, o] = incoming
        for name, values in delta.channels.items():
            arr = st.channel(name)
            if arr.shape[2:] != values.shape[1:]:
                msg = f"delta channel {name!r} has shape {values.shape[1:]} per voxel, grid holds {arr.shape[2:]}"
                raise DeltaError(msg)
            arr[s, o] = values[take]
        np.maximum.at(st.slot_version, s, incoming)
        self.version = max(self.version, delta.to_version)
        finite = delta.last_time[take]
        if finite.size:
            self.now = max(self.now, float(np.max(finite)))
        return int(take.sum())

    # ------------------------------------------------------------------------------------ files
    def save(self, path: str | Path) -> None:
        """Write a lossless snapshot (atomic replace)."""
        from voxel.snapshot import save_grid

        save_grid(self, Path(path))

    @classmethod
    def load(cls, path: str | Path) -> VoxelGrid:
        """Read a snapshot written by `save`."""
        from voxel.snapshot import load_grid

        return load_grid(Path(path))

    def write_bt(self, path: str | Path) -> None:
        """Export known voxels as an OctoMap binary tree (.bt: maximum-likelihood occupied/free)."""
        from voxel.octomap_io import write_bt

        slots, lo, bkeys = self._all()
        with np.errstate(invalid="ignore"):
            b, o = np.nonzero(~np.isnan(lo))
        write_bt(path, self.resolution, self.store.join(bkeys[b], o), lo[b, o] >= 0)

    def write_ply(self, path: str | Path) -> None:
        """Export occupied voxel centres as a binary PLY point cloud, with colour when known."""
        from voxel.ply import write_ply

        keys = self.occupied_keys()
        colours = self.channel_at_keys("colour", keys) if "colour" in self.store.channels else None
        write_ply(path, vk.keys_to_centers(keys, self.resolution), colours)

    @classmethod
    def from_bt(cls, path: str | Path, *, time: float = 0.0) -> VoxelGrid:
        """A grid holding an OctoMap .bt map: occupied voxels at the hit clamp, free at the miss one."""
        from voxel.octomap_io import read_bt

        bt = read_bt(path)
        grid = cls(bt.resolution)
        lo = np.where(bt.occupied, quantise_logodds(DEFAULT_SENSOR.log_max), quantise_logodds(DEFAULT_SENSOR.log_min))
        grid.apply(Delta(bt.resolution, 0, 1, bt.keys, lo, np.full(len(lo), time)))
        return grid

    def nbytes(self) -> int:
        """Bytes held by voxel storage (channels of used blocks and the block index)."""
        return self.store.nbytes()

    def content_equal(self, other: VoxelGrid) -> bool:
        """True when both grids hold the same known voxels with the same values in every channel."""
        a, b = self.delta_since(0), other.delta_since(0)
        ka, kb = vk.pack(a.keys), vk.pack(b.keys)
        ia, ib = np.argsort(ka), np.argsort(kb)
        ma, mb = ~np.isnan(a.logodds[ia]), ~np.isnan(b.logodds[ib])
        ia, ib = ia[ma], ib[mb]
        if not np.array_equal(ka[ia], kb[ib]):
            return False
        if not (np.array_equal(a.logodds[ia], b.logodds[ib]) and np.array_equal(a.last_time[ia], b.last_time[ib])):
            return False
        for name in set(a.channels) | set(b.channels):
            if name not in a.channels or name not in b.channels:
                return False
            va, vb = a.channels[name][ia], b.channels[name][ib]
            if not np.array_equal(va, vb, equal_nan=va.dtype.kind == "f"):
                return False
        return True


def _states(lo: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return np.where(np.isnan(lo), UNKNOWN, np.where(lo >= 0, OCCUPIED, FREE_STATE)).astype(np.int8)
