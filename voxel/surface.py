"""Sub-voxel surface positions: each voxel's running mean of its hit points, as an offset from
its centre."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from voxel import kernels
from voxel import keys as vk
from voxel.blocks import BlockStore
from voxel.errors import DeltaError

if TYPE_CHECKING:
    from voxel.delta import Delta

#: Codes: an offset of `code / WIRE_SCALE` voxels per axis, code in [-WIRE_MAX, WIRE_MAX] (int8,
#: -128 never valid): 1/254 of a voxel, 0.39 mm at 10 cm, within half a voxel (this grid
#: publishes multiples of PUBLISH_STEP of them). The `surface` channel holds the codes as
#: published (deltas carry them exactly for occupied voxels, 0 for the others, so a replica
#: holds an occupied voxel's values bit for bit).
WIRE_SCALE = 254
WIRE_MAX = 127
#: The running mean behind them is int16 multiples of 1/(WIRE_SCALE * STORE_STEP) voxel (1.5 um
#: at 10 cm): its rounding then neither stalls nor walks (in int8 each update would round by up
#: to 0.2 mm and stop moving once (frame - mean) / weight < 0.2 mm).
STORE_STEP = 258
STORE_SCALE = WIRE_SCALE * STORE_STEP
STORE_MAX = WIRE_MAX * STORE_STEP
#: Published codes are multiples of PUBLISH_STEP (1/16 voxel: 3.1 mm at 5 cm, 6.3 mm at 10 cm;
#: +-127 where rounding reaches +-128): a code sent is then one of 17 values, not 255, and zstd
#: codes each in ~4 bits instead of ~8 (docs/BENCHMARKS.md, wire). Receivers decode any code.
PUBLISH_STEP = 16
#: A voxel's published code takes its mean's (rounded to PUBLISH_STEP) at its first hit, in
#: every scan whose delta carries the voxel anyway (its occupancy or other channels changed: the
#: same bytes), and alone once the mean is PUBLISH_CODES codes from it on an axis: a mean that
#: moves by a fraction of a step a scan does not make the voxel travel again by itself.
PUBLISH_CODES = 16
#: Channel names: the published codes (int8 (3,), a delta channel), the running mean (int16
#: (3,)) and the count of scans fused into it (uint16, its weight); the last two are the
#: integrating grid's own, never sent.
CHANNEL = "surface"
MEAN = "surface_mean"
WEIGHT = "surface_weight"
#: The version at which a voxel's published codes last changed (uint32, kept by sparse origins
#: alone, never sent): a delta after version V carries the codes of only the voxels whose codes
#: changed after V (`voxel.delta.delta_of`; PROTOCOL.md §6, "surface"). A replica keeps none: it
#: serves ranges from the deltas it took and snapshots (from version 0) with every code.
VERSION = "surface_version"
#: An origin's deltas carry codes only where they changed (sparse), and a code moves only at its
#: voxel's first hit and PUBLISH_CODES away; off by default (False: every delta carries every
#: voxel's codes, 0 for voxels that are not occupied, and codes follow their means whenever
#: the voxel is sent anyway): on the kitchen frames it leaves 1.20 bytes per changed voxel,
#: not the <= 1.0 its rule asked (docs/BENCHMARKS.md, Wire). Receivers take both forms.
SPARSE = False


def to_wire(stored: np.ndarray) -> np.ndarray:
    """Codes (int8) of running means (int16)."""
    codes = np.rint(np.asarray(stored, dtype=np.float64) / STORE_STEP)
    out: np.ndarray = np.clip(codes, -WIRE_MAX, WIRE_MAX).astype(np.int8)
    return out


def publish(codes: np.ndarray) -> np.ndarray:
    """Codes (int8) as published: `codes` rounded to multiples of PUBLISH_STEP, within
    [-WIRE_MAX, WIRE_MAX]."""
    steps = np.rint(np.asarray(codes, dtype=np.float64) / PUBLISH_STEP) * PUBLISH_STEP
    out: np.ndarray = np.clip(steps, -WIRE_MAX, WIRE_MAX).astype(np.int8)
    return out


def check_codes(codes: np.ndarray) -> None:
    """DeltaError unless every code lies in [-WIRE_MAX, WIRE_MAX] (within half a voxel)."""
    arr = np.asarray(codes)
    if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
        msg = "surface codes must be finite integers, found NaN or infinity"
        raise DeltaError(msg)
    if arr.size and (int(arr.min()) < -WIRE_MAX or int(arr.max()) > WIRE_MAX):
        msg = (
            f"surface codes must lie in [-{WIRE_MAX}, {WIRE_MAX}] (within half a voxel), found "
            f"[{int(arr.min())}, {int(arr.max())}]"
        )
        raise DeltaError(msg)


def wire_offsets(codes: np.ndarray, resolution: float) -> np.ndarray:
    """Offsets (N, 3) in metres of wire codes."""
    out: np.ndarray = np.asarray(codes, dtype=np.float64) * (resolution / WIRE_SCALE)
    return out


def delta_surface(delta: Delta) -> np.ndarray:
    """Surface points (N, 3) of a delta's voxels: centre + the `surface` channel's offset (the
    centres when the delta carries none)."""
    out = vk.keys_to_centers(delta.keys, delta.resolution)
    codes = delta.channels.get(CHANNEL)
    if codes is not None:
        out += wire_offsets(codes, delta.resolution)
    return out


def fuse_surface(
    store: BlockStore,
    slots: np.ndarray,
    offsets: np.ndarray,
    inverse: np.ndarray,
    sums: np.ndarray,
    counts: np.ndarray,
    sent: np.ndarray,
) -> np.ndarray:
    """Fold one scan's hit points into the running means of their voxels' surfaces.

    The voxels at (`slots`, `offsets`) (U,) are the scan's hit voxels, `inverse` (H,) the row
    in them of each group of hit points, `sums` (H, 3) the sums of the groups' offsets from
    their voxel's centre in voxels (x / resolution - floor(x / resolution) - 0.5 per axis) and
    `counts` (H,) their sizes; `sent` (U,) marks the voxels this scan's delta carries anyway. A
    scan is one sample of weight 1, its points' mean, as colours and normals are fused (the
    weight is the count of scans, saturating at 65535). A voxel's published code (`publish` of
    its mean's) is set at its first hit, when it differs and the voxel is `sent`, and when the
    mean is PUBLISH_CODES from it on an axis. Returns a mask (U,) of the voxels whose
    published codes changed (the others need no new version).
    """
    compiled = kernels.surface()
    if compiled is not None:
        fused: np.ndarray = compiled(
            store.channel(MEAN),
            store.channel(WEIGHT),
            store.channel(CHANNEL),
            np.ascontiguousarray(slots, dtype=np.int64),
            np.ascontiguousarray(offsets, dtype=np.int64),
            np.ascontiguousarray(inverse, dtype=np.int64),
            np.ascontiguousarray(sums, dtype=np.float64),
            np.ascontiguousarray(counts, dtype=np.int64),
            np.ascontiguousarray(sent, dtype=np.bool_),
            float(STORE_SCALE),
            float(STORE_MAX),
            float(STORE_STEP),
            float(WIRE_MAX),
            PUBLISH_CODES,
            float(PUBLISH_STEP),
        )
        return fused
    m = slots.shape[0]
    points = np.bincount(inverse, weights=counts, minlength=m)
    frame = np.stack(
        [np.bincount(inverse, weights=sums[:, j], minlength=m) for j in range(3)], axis=1
    ).astype(np.float64)
    frame /= points[:, None]
    weights = store.channel(WEIGHT)
    w_old = weights[slots, offsets]
    weights[slots, offsets] = np.minimum(w_old.astype(np.int64) + 1, 65535).astype(np.uint16)
    means = store.channel(MEAN)
    cur = means[slots, offsets].astype(np.float64) / STORE_SCALE
    cur += (frame - cur) / (w_old.astype(np.float64) + 1.0)[:, None]
    new = np.clip(np.rint(cur * STORE_SCALE), -STORE_MAX, STORE_MAX).astype(np.int16)
    means[slots, offsets] = new
    codes = to_wire(new).astype(np.int64)
    rounded = publish(codes)
    published = store.channel(CHANNEL)
    old = published[slots, offsets].astype(np.int64)
    differ = (rounded.astype(np.int64) != old).any(axis=1)
    far = np.abs(codes - old).max(axis=1) >= PUBLISH_CODES
    moved: np.ndarray = (w_old == 0) | (differ & (far | np.asarray(sent, dtype=bool)))
    published[slots[moved], offsets[moved]] = rounded[moved]
    return moved
