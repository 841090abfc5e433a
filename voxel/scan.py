"""One scan's input, validated, and its beams sorted into hits, clearing beams, invalid and dropped
ones."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from voxel import kernels
from voxel import keys as vk
from voxel.channels import PointChannels
from voxel.errors import InputError
from voxel.sensor import SensorModel

#: Beams without a hit are cast once per 1/CLEAR_SUBDIVISION-voxel cell of their truncated ends
#: (one real beam stands for its cell): close to casting every beam (OctoMap's default) at a
#: fraction of the rays where beams are dense, exact where they are sparse.
CLEAR_SUBDIVISION = 3


def as_points(points: np.ndarray, name: str = "points") -> np.ndarray:
    """`points` as an (N, 3) float64 array; InputError when the shape or type is wrong."""
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] != 3:
        msg = f"{name} must have shape (N, 3), found {arr.shape}"
        raise InputError(msg)
    if not np.issubdtype(arr.dtype, np.number):
        msg = f"{name} must be numeric, found dtype {arr.dtype}"
        raise InputError(msg)
    return arr.astype(np.float64, copy=False)


def per_point(
    values: np.ndarray | None, n: int, name: str, tail: tuple[int, ...] = ()
) -> np.ndarray | None:
    """`values` as an array of one row per point (shape (n, *tail)), or None when not given."""
    return None if values is None else rows_of(values, n, name, tail)


def rows_of(values: np.ndarray, n: int, name: str, tail: tuple[int, ...] = ()) -> np.ndarray:
    """`values` as an array of one row per point (shape (n, *tail)); InputError otherwise."""
    arr = np.asarray(values)
    if arr.shape != (n, *tail):
        msg = f"{name} must have shape {(n, *tail)} (one row per point), found {arr.shape}"
        raise InputError(msg)
    return arr


@dataclass(frozen=True)
class Scan:
    """One scan of world-frame points taken from `origin`, validated."""

    points: np.ndarray  # (N, 3) float64
    origin: np.ndarray  # (3,) float64, finite
    time: float  # seconds, finite
    reliability: float  # in (0, 1]
    no_return: np.ndarray  # (N,) bool: beams that returned nothing
    channels: PointChannels

    @classmethod
    def of(
        cls,
        points: np.ndarray,
        origin: np.ndarray,
        *,
        time: float,
        reliability: float,
        colours: np.ndarray | None = None,
        normals: np.ndarray | None = None,
        class_ids: np.ndarray | None = None,
        class_probs: np.ndarray | None = None,
        object_ids: np.ndarray | None = None,
        scalars: dict[str, np.ndarray] | None = None,
        no_return: np.ndarray | None = None,
    ) -> Scan:
        """Check every input against the points; InputError says what was expected and what was
        found."""
        pts = as_points(points)
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
        colours = per_point(colours, n, "colours", (3,))
        normals = per_point(normals, n, "normals", (3,))
        class_ids = per_point(class_ids, n, "class_ids")
        class_probs = per_point(class_probs, n, "class_probs")
        object_ids = per_point(object_ids, n, "object_ids")
        nr = per_point(no_return, n, "no_return")
        checked = {k: rows_of(v, n, f"scalars[{k!r}]") for k, v in (scalars or {}).items()}
        return cls(
            pts,
            org,
            time,
            reliability,
            np.zeros(n, dtype=bool) if nr is None else nr.astype(bool),
            PointChannels(colours, normals, class_ids, class_probs, object_ids, checked),
        )


@dataclass(frozen=True)
class Beams:
    """A scan's beams sorted by what they do to the map."""

    hit_keys: (
        np.ndarray
    )  # (3, H) float64 voxel keys (floored) of the points that hit, one row per axis
    hit_mask: np.ndarray  # (N,) bool: the points that hit
    clear_ends: np.ndarray  # (M, 3) ends of the rays that only clear (one per fine cell)
    cleared: int  # beams without a hit (no return or beyond max range) that clear free space
    invalid: int  # NaN/inf points, zero-length rays, keys outside the key space
    dropped: int  # no-return beams that cannot be used (sensor without a max range)
    #: (2, 3) int64 lowest and highest voxel key of the hits and clear ends, when known
    bounds: np.ndarray | None = None
    #: Points that hit, when `hit_keys` holds fewer columns (repeated keys left out); else -1
    hit_points: int = -1
    #: With `surface`: per column of `hit_keys`, the sums (H, 3) of its points' offsets from
    #: their voxel's centre in voxels (x / resolution - floor(x / resolution) - 0.5 per axis)
    #: and its count of points (H,)
    surface_sums: np.ndarray | None = None
    surface_counts: np.ndarray | None = None

    @property
    def hits(self) -> int:
        """Points that hit."""
        return self.hit_points if self.hit_points >= 0 else int(self.hit_keys.shape[1])


def sort_beams(
    scan: Scan,
    sensor: SensorModel,
    resolution: float,
    distinct: bool = False,
    surface: bool = False,
) -> Beams:
    """Hits end within max range; beams beyond it clear up to max range, beams without a return
    up to the sensor's `no_return_range`. With `distinct` (a scan whose points' rows are not
    needed, i.e. without channels), the compiled path may leave repeated hit keys out. With
    `surface`, the beams carry the sums of the hit points' offsets in their voxels, per hit key
    column (a left-out repeat's point in the column it repeats)."""
    compiled = kernels.beams()
    if compiled is not None:
        hit_keys, hit_mask, ends, cleared, dropped, ok, bounds, n_hit, sums, counts = compiled(
            np.ascontiguousarray(scan.points),
            scan.origin,
            scan.no_return,
            float(sensor.max_range),
            float(sensor.no_return_range),
            1.0 / resolution,
            CLEAR_SUBDIVISION / resolution,
            float(vk.KEY_MIN),
            float(vk.KEY_MAX),
            float(vk.KEY_MAX * CLEAR_SUBDIVISION),
            distinct,
            surface,
        )
        if ok:
            invalid = scan.points.shape[0] - n_hit - cleared - dropped
            if not surface:
                sums = counts = None
            return Beams(
                hit_keys, hit_mask, ends, cleared, invalid, dropped, bounds, n_hit, sums, counts
            )
    n = scan.points.shape[0]
    org, nr = scan.origin, scan.no_return
    rows = np.ascontiguousarray(
        scan.points.T, dtype=np.float64
    )  # (3, N): per-axis passes are contiguous
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
    if not math.isfinite(sensor.no_return_range):  # then no max range either: only no-returns
        dropped = int(np.count_nonzero(clear_mask))
        clear_mask[:] = False
    inv = 1.0 / resolution
    hit_keys = rows * inv if all_hit else np.compress(hit_mask, rows, axis=1) * inv
    sums = hit_keys.copy() if surface else None
    np.floor(hit_keys, out=hit_keys)
    if sums is not None:  # x - floor(x) - 0.5: the offset from the voxel's centre
        sums -= hit_keys
        sums -= 0.5
    if hit_keys.size and (hit_keys.min() < vk.KEY_MIN or hit_keys.max() > vk.KEY_MAX):
        ok = np.all((hit_keys >= vk.KEY_MIN) & (hit_keys <= vk.KEY_MAX), axis=0)
        hit_mask[np.flatnonzero(hit_mask)[~ok]] = False
        hit_keys = hit_keys[:, ok]
        sums = None if sums is None else sums[:, ok]
    sums = None if sums is None else sums.T
    if clear_mask.any():
        limit: float | np.ndarray = sensor.max_range
        if sensor.no_return_range < sensor.max_range and nr.any():
            limit = np.where(nr[clear_mask], sensor.no_return_range, sensor.max_range)
        clear_ends = _clear_ends(rows, org, r2, clear_mask, limit, resolution)
    else:
        clear_ends = np.empty((0, 3))
    cleared = int(np.count_nonzero(clear_mask))
    invalid = n - int(hit_keys.shape[1]) - cleared - dropped
    counts = None if sums is None else np.ones(sums.shape[0], dtype=np.int64)
    return Beams(
        hit_keys,
        hit_mask,
        clear_ends,
        cleared,
        invalid,
        dropped,
        surface_sums=sums,
        surface_counts=counts,
    )


def _clear_ends(
    rows: np.ndarray,
    org: np.ndarray,
    r2: np.ndarray,
    clear_mask: np.ndarray,
    max_range: float | np.ndarray,
    resolution: float,
) -> np.ndarray:
    """End points (M, 3) of the rays of beams without a hit; drops unusable beams from clear_mask.

    Beams are truncated at max range (one for all, or one per clearing beam) and cast once per
    1/CLEAR_SUBDIVISION-voxel cell of their ends, one real beam standing for its cell (OctoMap's
    discretised update does the like): distant beams share voxels.
    """
    idx = np.flatnonzero(clear_mask)
    scale = max_range / np.sqrt(r2[idx])
    ends = rows.take(idx, axis=1) - org[:, None]
    ends *= scale
    ends += org[:, None]
    fine = ends * (CLEAR_SUBDIVISION / resolution)
    np.floor(fine, out=fine)
    limit = vk.KEY_MAX * CLEAR_SUBDIVISION
    if fine.min() < -limit or fine.max() > limit:
        ok = np.all((fine >= -limit) & (fine <= limit), axis=0)
        clear_mask[idx[~ok]] = False
        ends, fine = ends[:, ok], fine[:, ok]
    picked: np.ndarray = ends.T[vk.one_per_key(fine)]  # one real beam per cell
    return picked
