"""Rich channels: per-point colour, normals, classes, object ids and scalars, fused into voxels."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from voxel.blocks import BlockStore
from voxel.delta import SCALAR_PREFIX
from voxel.surface import VERSION as SURFACE_VERSION
from voxel.surface import fuse_surface

#: Weight of a new class observation in the per-voxel class distribution.
CLASS_RATE = 0.3


@dataclass(frozen=True)
class PointChannels:
    """Optional per-point channels of a scan, one row per point (or per hit point once selected)."""

    colours: np.ndarray | None = None  # (N, 3) 0-255
    normals: np.ndarray | None = None  # (N, 3)
    class_ids: np.ndarray | None = None  # (N,) -1 = none
    class_probs: np.ndarray | None = None  # (N,) default 1
    object_ids: np.ndarray | None = None  # (N,) -1 = none; history only
    scalars: dict[str, np.ndarray] = field(default_factory=dict)  # name -> (N,)

    @property
    def any(self) -> bool:
        """True when some channel needs to know which voxel each hit point fell in."""
        return any(
            x is not None for x in (self.colours, self.normals, self.class_ids, self.object_ids)
        ) or bool(self.scalars)

    @property
    def fused(self) -> bool:
        """True when some channel is folded into voxel channels (object ids and probabilities alone
        are not)."""
        return any(x is not None for x in (self.colours, self.normals, self.class_ids)) or bool(
            self.scalars
        )

    def select(self, rows: np.ndarray) -> PointChannels:
        """The channels of the points at `rows` (index array)."""

        def pick(values: np.ndarray | None) -> np.ndarray | None:
            return None if values is None else values[rows]

        return PointChannels(
            pick(self.colours),
            pick(self.normals),
            pick(self.class_ids),
            pick(self.class_probs),
            pick(self.object_ids),
            {k: v[rows] for k, v in self.scalars.items()},
        )


def fuse_channels(
    store: BlockStore,
    hit_keys: np.ndarray,
    inverse: np.ndarray | None,
    channels: PointChannels,
    *,
    statistics: bool,
    version: int,
    stamp: np.ndarray,
    surface: tuple[np.ndarray, np.ndarray] | None = None,
    follow: bool = True,
) -> bool:
    """Fold the channels of one scan's hit points into the running means and top-k of their voxels.

    `hit_keys` (U, 3) are the hit voxels, `inverse` (H,) each hit point's row in them and
    `channels` one row per hit point; `surface`, when given, per row of `inverse` the sums
    (H, 3) of its points' offsets from their voxel's centre in voxels and its count of points
    (H,) (`voxel.scan.Beams`; a row per point when channels are given); `follow`: a voxel's
    published code follows its mean's rounding whenever the voxel takes the version anyway
    (with codes sent with every voxel, it costs nothing; with codes sent only where they
    changed, it does, and `follow` is off). Voxels that took values
    get `version` and the time `stamp` (for the surface alone: those whose wire codes changed).
    Returns whether anything was written.
    """
    if hit_keys.shape[0] == 0 or inverse is None or (not channels.fused and surface is None):
        return False
    blocks, offsets = store.split(hit_keys)
    slots = store.lookup(blocks)
    m = hit_keys.shape[0]
    moved = None
    if surface is not None:
        # this scan's delta carries these voxels anyway: their occupancy changed, or (fused
        # channels) every hit voxel takes the version below
        sent = channels.fused | (store.channels["version"][slots, offsets] == np.uint32(version))
        if not follow:  # deltas carry only codes that changed: no code moves for free
            sent = np.zeros_like(sent)
        moved = fuse_surface(store, slots, offsets, inverse, *surface, sent)
        if not follow:  # codes sent where they changed: when they did
            store.channel(SURFACE_VERSION)[slots[moved], offsets[moved]] = np.uint32(version)
    if not channels.fused:
        assert moved is not None
        if not moved.any():
            return False
        s, o = slots[moved], offsets[moved]
        v = np.uint32(version)
        store.channels["version"][s, o] = v
        store.channels["last_time"][s, o] = stamp
        store.slot_version[s] = v
        return True
    counts = np.bincount(inverse, minlength=m).astype(np.float64)
    weight_arr = store.channel("hits")
    w_old = weight_arr[slots, offsets].astype(np.float64)
    if not statistics:  # hits counted here only when statistics did not count them
        weight_arr[slots, offsets] = np.minimum(w_old + 1, 65535).astype(np.uint16)
    else:
        w_old = np.maximum(w_old - 1, 0)
    frac = 1.0 / (w_old + 1.0)

    def mean_of(values: np.ndarray) -> np.ndarray:
        v = values.reshape(values.shape[0], -1).astype(np.float64)
        out = np.stack(
            [np.bincount(inverse, weights=v[:, j], minlength=m) for j in range(v.shape[1])], axis=1
        )
        return out / counts[:, None]

    if channels.colours is not None:
        arr = store.channel("colour")
        frame = mean_of(channels.colours)
        cur = arr[slots, offsets].astype(np.float64)
        arr[slots, offsets] = np.clip(np.rint(cur + (frame - cur) * frac[:, None]), 0, 255).astype(
            np.uint8
        )
    if channels.normals is not None:
        arr = store.channel("normal")
        frame = mean_of(channels.normals)
        cur = arr[slots, offsets].astype(np.float64)
        mixed = cur + (frame - cur) * frac[:, None]
        norm = np.linalg.norm(mixed, axis=1, keepdims=True)
        arr[slots, offsets] = np.where(norm > 0, mixed / np.where(norm > 0, norm, 1), 0).astype(
            np.float32
        )
    for name, values in channels.scalars.items():
        arr = store.channel(SCALAR_PREFIX + name)
        frame = mean_of(np.asarray(values, dtype=np.float64))[:, 0]
        cur = arr[slots, offsets].astype(np.float64)
        cur = np.where(np.isnan(cur), frame, cur)
        arr[slots, offsets] = (cur + (frame - cur) * frac).astype(np.float32)
    if channels.class_ids is not None:
        probs = channels.class_probs
        probs = np.ones(inverse.size) if probs is None else np.asarray(probs, dtype=np.float64)
        _fuse_classes(
            store, slots, offsets, inverse, np.asarray(channels.class_ids, dtype=np.int64), probs
        )
    v = np.uint32(version)
    store.channels["version"][slots, offsets] = v
    store.channels["last_time"][slots, offsets] = stamp
    store.slot_version[slots] = v
    return True


def _fuse_classes(
    store: BlockStore,
    slots: np.ndarray,
    offsets: np.ndarray,
    inverse: np.ndarray,
    cls: np.ndarray,
    prob: np.ndarray,
) -> None:
    """Per voxel: the frame's majority class and its mean probability enter a bounded top-k."""
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
    ids = store.channel("class_ids")
    prs = store.channel("class_probs")
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
