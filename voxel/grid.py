"""The information-rich voxel grid of one layer: integration steps, queries, versions and files."""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from voxel import keys as vk
from voxel.blocks import BlockStore, block_shifts
from voxel.channels import CLASS_RATE, fuse_channels
from voxel.delta import Delta, best_classes, delta_of, merge_delta, same_content
from voxel.depth import back_project
from voxel.errors import DeltaError, InputError
from voxel.history import History, ObjectTags, Observer
from voxel.occupancy import (
    FORGET_EPSILON,
    FREE_STATE,
    LOGODDS_QUANTUM,
    OCCUPIED,
    UNKNOWN,
    UPDATE_CHUNK,
    Evidence,
    UpdateRule,
    decayed,
    quantise_logodds,
    states,
    update_occupancy,
)
from voxel.octomap_io import read_bt, write_bt
from voxel.ply import write_ply
from voxel.raycast import ray_keys, trace
from voxel.scan import CLEAR_SUBDIVISION, Scan, as_points, sort_beams
from voxel.sensor import SensorModel
from voxel.snapshot import load_grid, save_grid
from voxel.surface import CHANNEL as SURFACE
from voxel.surface import MEAN as SURFACE_MEAN
from voxel.surface import SPARSE as SPARSE_SURFACE
from voxel.surface import VERSION as SURFACE_VERSION
from voxel.surface import WEIGHT as SURFACE_WEIGHT
from voxel.surface import wire_offsets
from voxel.timebase import TIME_SPAN_MS, TimeBase, quantise_time

__all__ = [
    "CLASS_RATE",
    "CLEAR_SUBDIVISION",
    "DEFAULT_SENSOR",
    "FORGET_EPSILON",
    "FREE_STATE",
    "LOGODDS_QUANTUM",
    "OCCUPIED",
    "TIME_SPAN_MS",
    "UNKNOWN",
    "UPDATE_CHUNK",
    "IntegrationReport",
    "VoxelGrid",
    "quantise_logodds",
    "quantise_time",
]

DEFAULT_SENSOR = SensorModel()
#: Forgets whose voxels `delta_since` still carries after their blocks were freed.
TOMBSTONES = 64


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


class VoxelGrid:
    """Sparse blocks of dense voxels holding log-odds occupancy and rich per-voxel channels.

    One grid is one layer with a single writer. Every change bumps the grid version; each voxel
    remembers the version of its last change, so `delta_since` returns exactly what changed and
    `apply` is idempotent and order-independent. `block_shape` is "cube" (4x4x4, for 3D sensors),
    "planar" (8x8x1, for a layer mapped by a 2D scanner), "slab" (4x4x1, for a 3D LiDAR) or three
    side lengths.

    With `surface`, every integration also keeps each hit voxel's running mean of its hit
    points (the `surface` channel): `surface_points` gives the surface inside a voxel to a
    fraction of its size, as TSDF maps do, where its centre is up to half a voxel off. Off by
    default: it costs 1.2-1.6x the integration time and 11 bytes per voxel slot
    (docs/VOXEL.md); daemons turn it on (`Config.surface`).
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
        seen_log: bool = True,
        surface: bool = False,
    ) -> None:
        if not (
            isinstance(resolution, (int, float)) and math.isfinite(resolution) and resolution > 0
        ):
            msg = f"resolution must be a positive number of metres, found {resolution!r}"
            raise InputError(msg)
        if half_life is not None and not half_life > 0:
            msg = f"half_life must be positive seconds or None, found {half_life!r}"
            raise InputError(msg)
        self.resolution = float(resolution)
        self.half_life = half_life
        self.statistics = statistics
        #: Log voxels seen free for the first time (exact `state_at` for free space; costs
        #: ~50 % more integration time on dense 3D LiDAR, which may turn it off).
        self.seen_log = seen_log
        #: Keep the sub-voxel surface (the mean hit position) of hit voxels.
        self.surface = surface
        #: Deltas carry surface codes only where they changed (`voxel.surface.SPARSE`, off by
        #: default: docs/BENCHMARKS.md, Wire); False: every voxel's codes, 0 for voxels not
        #: occupied, codes following their means whenever a voxel is sent anyway.
        self.sparse_surface = SPARSE_SURFACE
        self.store = BlockStore(class_k=class_k, shifts=block_shifts(block_shape))
        self.history = History(capacity=history_capacity, per_voxel=history_per_voxel)
        self.times = TimeBase(self.store)  # stored times are ms since its base
        self.version = 0
        self.now = 0.0  # latest observation time seen
        #: (version, packed keys, time) of voxels forgotten with their whole block, newest last
        self.tombstones: deque[tuple[int, np.ndarray, float]] = deque(maxlen=TOMBSTONES)

    @property
    def time_base_ms(self) -> int | None:
        """Stored times are milliseconds since this (None before the first time is stored)."""
        return self.times.base_ms

    @time_base_ms.setter
    def time_base_ms(self, value: int | None) -> None:
        self.times.base_ms = value

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
        error: float = 0.0,
        bias: float = 0.0,
        agent_reliability: float = 1.0,
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
        scan = Scan.of(
            points,
            origin,
            time=time,
            reliability=reliability,
            colours=colours,
            normals=normals,
            class_ids=class_ids,
            class_probs=class_probs,
            object_ids=object_ids,
            scalars=scalars,
            no_return=no_return,
        )
        return self.integrate_scan(
            scan,
            sensor,
            agent=agent,
            error=error,
            bias=bias,
            agent_reliability=agent_reliability,
        )

    def integrate_scan(
        self,
        scan: Scan,
        sensor: SensorModel = DEFAULT_SENSOR,
        *,
        agent: str = "self",
        error: float = 0.0,
        bias: float = 0.0,
        agent_reliability: float = 1.0,
    ) -> IntegrationReport:
        """Integrate a validated scan: traverse, update occupancy, fuse channels, record history,
        bump version. Its records carry the provenance (VOXEL.md, "Provenance"): `error` (e, the
        pose error estimate, m), r = the scan's (sensor) reliability x `agent_reliability`, and
        `bias` (b)."""
        beams = sort_beams(
            scan, sensor, self.resolution, distinct=not scan.channels.any, surface=self.surface
        )
        traversal = trace(
            scan.origin,
            beams.hit_keys,
            beams.clear_ends,
            self.resolution,
            self.store.shifts,
            scan.channels.any or self.surface,  # each hit key's voxel is needed
            beams.bounds,
        )
        hit_channels = (
            scan.channels.select(np.flatnonzero(beams.hit_mask))
            if scan.channels.any
            else scan.channels
        )
        time = quantise_time(scan.time)
        if self.surface and self.sparse_surface:
            self._surface_versions()
        version = self.version + 1
        observer = Observer(
            time,
            self.history.agent_code(agent),
            sensor.kind_code,
            scan.reliability * agent_reliability,
            error,
            bias,
            version,
        )
        stamp = self.times.stamp(time)
        rule = UpdateRule(
            Evidence.of(sensor, scan.reliability), self.half_life, self.statistics, self.seen_log
        )
        update = update_occupancy(self.store, traversal, rule, version, time, stamp, self.times)
        fused = fuse_channels(
            self.store,
            traversal.hit_keys,
            traversal.inverse,
            hit_channels,
            statistics=self.statistics,
            version=version,
            stamp=stamp,
            surface=None
            if beams.surface_sums is None or beams.surface_counts is None
            else (beams.surface_sums, beams.surface_counts),
            follow=not self.sparse_surface,
        )
        objects = ObjectTags.of(traversal.hit_keys, traversal.inverse, hit_channels.object_ids)
        self.history.record(update.chunks, observer, rule.evidence, objects)
        if update.changed or fused:
            self.version = version
        self.now = max(self.now, time)
        return IntegrationReport(
            points=scan.points.shape[0],
            hits=beams.hits,
            cleared=beams.cleared,
            invalid=beams.invalid,
            dropped=beams.dropped,
            voxels_hit=traversal.hit_count,
            voxels_free=traversal.free_count,
            voxels_changed=update.changed,
            version=self.version,
        )

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
        """Integrate a depth image (metres, 0/NaN = no reading) seen from camera-to-world `pose`.

        Other keyword arguments go to `integrate` (agent, reliability, ...).
        """
        seen = back_project(depth, intrinsics, pose, colour=colour, labels=labels)
        extra: dict[str, object] = dict(kwargs)
        if seen.colours is not None:
            extra["colours"] = seen.colours
        if seen.class_ids is not None:
            extra["class_ids"] = seen.class_ids
            extra["class_probs"] = seen.class_probs
        return self.integrate(seen.points, seen.origin, time=time, sensor=sensor, **extra)  # type: ignore[arg-type]

    # ---------------------------------------------------------------------------------- queries
    def _lookup(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        blocks, offsets = self.store.split(keys)
        slots = self.store.lookup(blocks)
        return slots, offsets, slots >= 0

    def _decayed(self, lo: np.ndarray, last: np.ndarray, now: float) -> np.ndarray:
        """Log-odds decayed to `now`; with a half-life, evidence decayed below FORGET_EPSILON
        reads as unknown (NaN), as `forget` will make it."""
        out = decayed(lo, last, now, self.half_life, self.times)
        if self.half_life is not None:
            with np.errstate(invalid="ignore"):
                out = np.where(np.abs(out) < FORGET_EPSILON, np.float32(np.nan), out)
        return out

    def logodds_at_keys(self, keys: np.ndarray, now: float | None = None) -> np.ndarray:
        """Log-odds (decayed to `now`, default the latest observation) of voxel keys; NaN
        unknown."""
        keys = np.asarray(keys, dtype=np.int64).reshape(-1, 3)
        slots, offsets, found = self._lookup(keys)
        out = np.full(keys.shape[0], np.nan, dtype=np.float32)
        s, o = slots[found], offsets[found]
        lo = self.store.channels["logodds"][s, o]
        out[found] = self._decayed(
            lo, self.store.channels["last_time"][s, o], self.now if now is None else now
        )
        return out

    def occupancy(self, points: np.ndarray, now: float | None = None) -> np.ndarray:
        """Occupancy probability at world points; NaN where unknown."""
        lo = self.logodds_at_keys(vk.points_to_keys(as_points(points), self.resolution), now)
        prob: np.ndarray = 1.0 / (1.0 + np.exp(-lo.astype(np.float64)))
        return prob

    def state(self, points: np.ndarray, now: float | None = None) -> np.ndarray:
        """UNKNOWN (-1), FREE (0) or OCCUPIED (1) at world points."""
        lo = self.logodds_at_keys(vk.points_to_keys(as_points(points), self.resolution), now)
        return states(lo)

    def _all(self) -> tuple[np.ndarray, np.ndarray]:
        """Decayed log-odds (U, voxels per block) of the used blocks, and their packed block keys
        (U,)."""
        st = self.store
        slots = st.used_slots()
        lo = st.channels["logodds"][slots]
        if self.half_life is not None:
            lo = self._decayed(lo, st.channels["last_time"][slots], self.now)
        return lo, st.slot_keys[slots]

    def _keys_where(self, pred: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        lo, bkeys = self._all()
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
        return int(
            np.count_nonzero(~np.isnan(self.store.channels["logodds"][self.store.used_slots()]))
        )

    @property
    def has_surface(self) -> bool:
        """Whether the grid holds the `surface` channel (it integrates with `surface`, or is a
        replica of a grid that sent it)."""
        return SURFACE in self.store.channels

    def surface_points(self, keys: np.ndarray) -> np.ndarray:
        """Surface points (N, 3) of voxel keys: each voxel's centre plus the mean offset of the
        points that hit it as published (`surface` channel: codes of 1/254 voxel, published in
        steps of `surface.PUBLISH_STEP`, within `surface.PUBLISH_CODES` of the running mean's;
        an occupied voxel's on a replica are the origin's bit for bit); the centre where a voxel
        holds no surface data."""
        keys = np.asarray(keys, dtype=np.int64).reshape(-1, 3)
        out = vk.keys_to_centers(keys, self.resolution)
        arr = self.store.channels.get(SURFACE)
        if arr is None or keys.shape[0] == 0:
            return out
        slots, offsets, found = self._lookup(keys)
        out[found] += wire_offsets(arr[slots[found], offsets[found]], self.resolution)
        return out

    def occupied_surface(self) -> np.ndarray:
        """Surface points (M, 3) of the occupied voxels (`surface_points` of `occupied_keys`)."""
        return self.surface_points(self.occupied_keys())

    def occupied_in_box(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Centres (M, 3) of occupied voxels whose centre lies in the box [lo, hi]."""
        lo = np.asarray(lo, dtype=np.float64).reshape(3)
        hi = np.asarray(hi, dtype=np.float64).reshape(3)
        centres = vk.keys_to_centers(self.occupied_keys(), self.resolution)
        inside = np.all((centres >= lo) & (centres <= hi), axis=1)
        return centres[inside]

    def cast_ray(
        self, origin: np.ndarray, direction: np.ndarray, max_range: float
    ) -> np.ndarray | None:
        """Centre of the first occupied voxel along a ray, or None within max_range."""
        o = np.asarray(origin, dtype=np.float64).reshape(3)
        dvec = np.asarray(direction, dtype=np.float64).reshape(3)
        norm = float(np.linalg.norm(dvec))
        if not norm > 0 or not max_range > 0:
            msg = (
                "cast_ray needs a non-zero direction and positive max_range, "
                f"found {dvec!r}, {max_range!r}"
            )
            raise InputError(msg)
        keys = ray_keys(o, o + dvec / norm * max_range, self.resolution)
        hit = np.flatnonzero(states(self.logodds_at_keys(keys)) == OCCUPIED)
        return None if hit.size == 0 else vk.keys_to_centers(keys[hit[:1]], self.resolution)[0]

    def voxel_history(self, point: np.ndarray) -> np.ndarray:
        """History records (structured array, oldest first) of the voxel containing `point`."""
        key = vk.points_to_keys(as_points(np.asarray(point).reshape(1, 3)), self.resolution)
        return self.history.of_voxel(int(vk.pack(key)[0]))

    def state_at(self, points: np.ndarray, t: float) -> np.ndarray:
        """State of the voxels at `points` as it was at time t.

        From the history where it holds a record at or before t; a voxel without one that is
        free now and last changed at or before t was free then (it never flipped); else unknown.
        """
        keys = vk.points_to_keys(as_points(points), self.resolution)
        out = self.history.state_at_all(vk.pack(keys), t)
        none = out == UNKNOWN
        if none.any():
            slots, offsets, found = self._lookup(keys[none])
            lo = np.full(found.size, np.nan, dtype=np.float32)
            last = np.full(found.size, np.inf)
            lo[found] = self.store.channels["logodds"][slots[found], offsets[found]]
            last[found] = self.times.seconds(
                self.store.channels["last_time"][slots[found], offsets[found]]
            )
            with np.errstate(invalid="ignore"):
                free_then = (lo < 0) & (last <= t)
            out[np.flatnonzero(none)[free_then]] = FREE_STATE
        return out

    def known_at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Keys (N, 3) and log-odds (N,) of every voxel known at time t, as `state_at` answers:
        the log-odds of its last record at or before t, or (no record, free now and last changed
        at or before t) its current log-odds."""
        last = self.history.last_at(t)
        st = self.store
        slots = st.used_slots()
        lo = st.channels["logodds"][slots]
        when = self.times.seconds(st.channels["last_time"][slots])
        with np.errstate(invalid="ignore"):
            b, o = np.nonzero((lo < 0) & (when <= t))
        free_keys = vk.pack(st.join(st.slot_keys[slots[b]], o))
        free_lo = lo[b, o]
        extra = ~np.isin(free_keys, last["key"], assume_unique=True)
        packed = np.concatenate([last["key"], free_keys[extra]])
        values = np.concatenate([last["logodds"], free_lo[extra]]).astype(np.float32)
        return vk.unpack(packed), values

    def changed_between(self, t0: float, t1: float) -> np.ndarray:
        """Keys (M, 3) of voxels whose state changed in (t0, t1]."""
        return vk.unpack(self.history.flips_between(t0, t1))

    def best_classes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Keys (L, 3) of the known voxels that hold a class, in `delta_since(0)`'s order, with
        the most probable class of each (L,) and its probability (L,) (`delta.best_classes`)."""
        return best_classes(self.store)

    def channel_at_keys(self, name: str, keys: np.ndarray) -> np.ndarray:
        """Values of a rich channel (e.g. 'colour', 'class_ids', 'scalar:temp') at voxel keys."""
        if name not in self.store.channels:
            msg = f"channel {name!r} has never been written; present: {sorted(self.store.channels)}"
            raise InputError(msg)
        slots, offsets, found = self._lookup(np.asarray(keys, dtype=np.int64).reshape(-1, 3))
        arr = self.store.channels[name]
        out = np.full((found.size, *arr.shape[2:]), self.store.spec(name)[2], dtype=arr.dtype)
        out[found] = arr[slots[found], offsets[found]]
        return self.times.seconds(out) if name == "last_time" else out

    # ------------------------------------------------------------------------------- forgetting
    def forget(self, now: float | None = None, *, after: float | None = None) -> int:
        """Voxels whose decayed evidence is below FORGET_EPSILON (with a half-life), or that
        nobody observed for `after` seconds, become unknown at a new version (so deltas carry
        them to replicas), their history records go, blocks left empty are freed and the
        storage shrinks when mostly empty. Returns blocks freed."""
        if self.half_life is None and after is None:
            return 0
        now = self.now if now is None else now
        st = self.store
        slots = st.used_slots()
        lo = st.channels["logodds"][slots]
        last = st.channels["last_time"][slots]
        gone = np.zeros(lo.shape, dtype=bool)
        with np.errstate(invalid="ignore"):
            if self.half_life is not None:
                gone |= np.abs(decayed(lo, last, now, self.half_life, self.times)) < FORGET_EPSILON
            if after is not None:
                gone |= (now - self.times.seconds(last) > after) & ~np.isnan(lo)
        if not gone.any():
            return 0
        version = self.version + 1
        b, o = np.nonzero(gone)
        keys = vk.pack(st.join(st.slot_keys[slots[b]], o))
        lo[gone] = np.nan
        st.channels["logodds"][slots] = lo
        for name in (SURFACE, SURFACE_MEAN, SURFACE_WEIGHT):  # observed again: a surface anew
            if name in st.channels:
                st.channels[name][slots[b], o] = 0
        if SURFACE_VERSION in st.channels:  # codes now 0: deltas carry them
            st.channels[SURFACE_VERSION][slots[b], o] = np.uint32(version)
        st.channels["version"][slots[b], o] = np.uint32(version)
        st.channels["last_time"][slots[b], o] = self.times.stamp(quantise_time(now))
        st.slot_version[slots[np.unique(b)]] = np.uint32(version)
        self.version = version
        self.history.drop_keys(keys)
        self.now = max(self.now, quantise_time(now))
        empty = np.isnan(lo).all(axis=1)
        freed = slots[empty]
        in_freed = np.isin(slots[b], freed)
        if in_freed.any():  # their voxels leave the store: deltas still carry them, as unknown
            self.tombstones.append((version, keys[in_freed], quantise_time(now)))
        st.release(freed)
        st.shrink()
        return int(np.count_nonzero(empty))

    def settle(self, version: int) -> None:
        """Drop the tombstones of forgets at or before `version`: every delta that needs them has
        been taken (a daemon calls it with the version it has published)."""
        while self.tombstones and self.tombstones[0][0] <= version:
            self.tombstones.popleft()

    def allocated_bytes(self) -> int:
        """Bytes the grid holds allocated: every voxel-storage array (capacity, not only used
        blocks), the history's record buffer and the forgetting tombstones."""
        tomb = sum(int(k.nbytes) for _v, k, _t in self.tombstones)
        return self.store.allocated_bytes() + self.history.allocated_bytes() + tomb

    # ----------------------------------------------------------------------------------- deltas
    def delta_since(self, version: int) -> Delta:
        """Every voxel changed after `version`, with its absolute current values (voxels
        forgotten with their whole block as unknown, from the last TOMBSTONES forgets)."""
        delta = delta_of(
            self.store,
            self.times,
            version,
            resolution=self.resolution,
            to_version=self.version,
            time=self.now,
            # a replica (it does not integrate the surface) sends every voxel's codes as it holds
            # them: zeroing free voxels' would betray a sparse origin's
            sparse=self.sparse_surface or not self.surface,
        )
        newer = [(k, t) for v, k, t in self.tombstones if v > version]
        if not newer:
            return delta
        packed = np.concatenate([k for k, _t in newer])
        times = np.concatenate([np.full(k.size, t) for k, t in newer])
        packed, first = np.unique(packed[::-1], return_index=True)  # the latest forget of each
        times = times[::-1][first]
        keep = ~np.isin(packed, vk.pack(delta.keys))  # observed again since: the store has it
        packed, times = packed[keep], times[keep]
        if packed.size == 0:
            return delta
        n = packed.size
        channels = {
            name: np.concatenate(
                [
                    values,
                    np.full((n, *values.shape[1:]), self.store.spec(name)[2], dtype=values.dtype),
                ]
            )
            for name, values in delta.channels.items()
        }
        return Delta(
            resolution=delta.resolution,
            from_version=delta.from_version,
            to_version=delta.to_version,
            keys=np.concatenate([delta.keys, vk.unpack(packed)]),
            logodds=np.concatenate([delta.logodds, np.full(n, np.nan, dtype=np.float32)]),
            last_time=np.concatenate([delta.last_time, times]),
            channels=channels,
            time=delta.time,
            surface_mask=None  # forgotten voxels' codes are 0 since: carried
            if delta.surface_mask is None
            else np.r_[delta.surface_mask, np.ones(n, dtype=bool)],
        )

    def _surface_versions(self) -> None:
        """Make the `surface_version` channel (sparse codes) where it is missing, each voxel's
        taken as the version its codes last changed at: codes held without it (replayed from the
        log into a grid without the surface, a dense origin's snapshot) are then carried by
        every delta since before that version and every snapshot; 0 left them out of both."""
        st = self.store
        if SURFACE_VERSION not in st.channels:
            st.channel(SURFACE_VERSION)[...] = st.channels["version"]

    def apply(self, delta: Delta) -> int:
        """Apply a delta: each voxel takes the delta's values unless it already holds a newer
        version.

        Returns the number of voxels that took the delta's values.
        """
        if not math.isclose(delta.resolution, self.resolution, rel_tol=1e-9):
            msg = f"delta resolution {delta.resolution} does not match the grid's {self.resolution}"
            raise DeltaError(msg)
        if self.surface and self.sparse_surface:  # its own codes' versions, for its deltas
            self._surface_versions()
        taken = merge_delta(self.store, self.times, delta)
        self.version = max(self.version, delta.to_version)
        if taken.size:
            self.now = max(self.now, float(np.max(taken)))
        unknown = np.isnan(delta.logodds)
        if taken.size and unknown.any():  # forgotten at the origin: history and blocks go too
            self.history.drop_keys(vk.pack(delta.keys[unknown]))
            st = self.store
            slots = st.lookup(np.unique(st.split(delta.keys[unknown])[0]))
            slots = slots[slots >= 0]
            st.release(slots[np.isnan(st.channels["logodds"][slots]).all(axis=1)])
            st.shrink()
        return int(taken.size)

    def content_equal(self, other: VoxelGrid) -> bool:
        """True when both grids hold the same known voxels with the same values in every channel."""
        return same_content(self.delta_since(0), other.delta_since(0))

    # ------------------------------------------------------------------------------------ files
    def save(self, path: str | Path) -> None:
        """Write a lossless snapshot (a zstd-compressed .npz archive; atomic replace)."""
        save_grid(self, Path(path))

    @classmethod
    def load(cls, path: str | Path) -> VoxelGrid:
        """Read a snapshot written by `save`."""
        return load_grid(Path(path), cls)

    def write_bt(self, path: str | Path) -> None:
        """Export known voxels as an OctoMap binary tree (.bt: maximum-likelihood occupied/free)."""
        lo, bkeys = self._all()
        with np.errstate(invalid="ignore"):
            b, o = np.nonzero(~np.isnan(lo))
        write_bt(path, self.resolution, self.store.join(bkeys[b], o), lo[b, o] >= 0)

    def write_ply(self, path: str | Path) -> None:
        """Export the occupied voxels' surface points (`surface_points`: their centres without the
        surface channel) as a binary PLY point cloud, with colour when known."""
        keys = self.occupied_keys()
        colours = self.channel_at_keys("colour", keys) if "colour" in self.store.channels else None
        write_ply(path, self.surface_points(keys), colours)

    @classmethod
    def from_bt(cls, path: str | Path, *, time: float = 0.0) -> VoxelGrid:
        """A grid holding an OctoMap .bt map: occupied voxels at the hit clamp, free at the miss
        one."""
        bt = read_bt(path)
        grid = cls(bt.resolution)
        lo = np.where(
            bt.occupied,
            quantise_logodds(DEFAULT_SENSOR.log_max),
            quantise_logodds(DEFAULT_SENSOR.log_min),
        )
        grid.apply(Delta(bt.resolution, 0, 1, bt.keys, lo, np.full(len(lo), time)))
        return grid

    def nbytes(self) -> int:
        """Bytes held by voxel storage (channels of used blocks and the block index)."""
        return self.store.nbytes()
