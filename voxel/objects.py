"""Object centroids: clusters of occupied voxels sharing an object class, with covariance, and
the tracker that keeps their ids stable as the map grows."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from voxel import keys as vk
from voxel.errors import InputError

if TYPE_CHECKING:
    from voxel.grid import VoxelGrid


@dataclass(frozen=True)
class ObjectCentroid:
    """One object as seen in one layer: where its voxels are and how spread they are."""

    object_id: int  # stable while the object stays put: class + position quantised to `id_cell`
    class_id: int
    position: np.ndarray  # (3,) metres, layer frame
    covariance: np.ndarray  # (3, 3) of the centroid estimate, m^2
    voxel_count: int
    probability: float  # mean class probability of its voxels
    time: float  # latest change among its voxels


@dataclass(frozen=True)
class LabelledVoxels:
    """The occupied voxels of a grid whose best object class passed `labelled_voxels`' filters."""

    centres: np.ndarray  # (N, 3) metres
    classes: np.ndarray  # (N,) int64, each voxel's most probable class
    probabilities: np.ndarray  # (N,) that class's probability
    times: np.ndarray  # (N,) last observation times
    resolution: float


def labelled_voxels(
    grid: VoxelGrid,
    *,
    min_probability: float = 0.3,
    exclude: frozenset[int] = frozenset(),
) -> LabelledVoxels | None:
    """The occupied, class-labelled voxels of `grid` (copies: the grid may change afterwards),
    None if there are none. Voxels whose best class probability is below `min_probability`, or
    whose class is in `exclude` (structure such as walls and floors), are left out. This is the
    only step of `extract_objects` that reads the grid (a daemon holds its layer's lock for it
    alone, not for the clustering)."""
    if not 0.0 <= min_probability <= 1.0:
        msg = f"need min_probability in [0, 1], found {min_probability!r}"
        raise InputError(msg)
    if "class_ids" not in grid.store.channels:
        return None
    keys = grid.occupied_keys()
    if keys.shape[0] == 0:
        return None
    ids = grid.channel_at_keys("class_ids", keys)
    probs = grid.channel_at_keys("class_probs", keys)
    best = probs.argmax(axis=1)
    rows = np.arange(keys.shape[0])
    cls = ids[rows, best].astype(np.int64)
    p = probs[rows, best]
    keep = (cls >= 0) & (p >= min_probability)
    if exclude:
        keep &= ~np.isin(cls, np.fromiter(exclude, np.int64))
    if not keep.any():
        return None
    keys, cls, p = keys[keep], cls[keep], p[keep]
    times = np.asarray(grid.channel_at_keys("last_time", keys))
    res = grid.resolution
    return LabelledVoxels(vk.keys_to_centers(keys, res), cls, p, times, res)


def cluster_objects(
    voxels: LabelledVoxels | None,
    *,
    min_voxels: int = 4,
    id_cell: float = 0.5,
    link: float = 1.8,
) -> list[ObjectCentroid]:
    """Cluster labelled voxels into objects (DBSCAN per class): voxels within `link` voxels of
    each other (DBSCAN eps; 1.8 joins 26-connected voxels) form a cluster, and clusters smaller
    than `min_voxels` are outliers. The centroid covariance is the voxel scatter over the count,
    plus the voxel quantisation. `object_id` is the class and the centroid's `id_cell` cell
    (`ObjectTracker` keeps ids stable as centroids move). scikit-learn is imported only when
    there is something to cluster (its first import costs ~1 s of CPU)."""
    if min_voxels < 1:
        raise InputError(f"need min_voxels >= 1, found {min_voxels!r}")
    if voxels is None or voxels.classes.size == 0:
        return []
    from sklearn.cluster import DBSCAN

    res = voxels.resolution
    cls, p, times, centres = voxels.classes, voxels.probabilities, voxels.times, voxels.centres
    out: list[ObjectCentroid] = []
    for c in np.unique(cls):  # one pass per class present, vectorised inside
        m = cls == c
        pts = centres[m]
        labels = DBSCAN(eps=link * res, min_samples=1).fit_predict(pts)
        counts = np.bincount(labels)
        for lab in np.flatnonzero(counts >= min_voxels):
            sel = labels == lab
            cluster = pts[sel]
            n = cluster.shape[0]
            mean = cluster.mean(axis=0)
            scatter = np.cov(cluster.T) if n > 1 else np.zeros((3, 3))
            cov = scatter / n + np.eye(3) * (res * res / 12.0)
            cell = np.floor(mean / id_cell).astype(np.int64)
            digest = hashlib.blake2b(f"{int(c)}:{cell.tolist()}".encode(), digest_size=4).digest()
            out.append(
                ObjectCentroid(
                    object_id=int.from_bytes(digest, "little") & 0x7FFFFFFF,
                    class_id=int(c),
                    position=mean,
                    covariance=cov,
                    voxel_count=int(n),
                    probability=float(p[m][sel].mean()),
                    time=float(times[m][sel].max()),
                )
            )
    return out


def extract_objects(
    grid: VoxelGrid,
    *,
    min_probability: float = 0.3,
    min_voxels: int = 4,
    id_cell: float = 0.5,
    exclude: frozenset[int] = frozenset(),
    link: float = 1.8,
) -> list[ObjectCentroid]:
    """Cluster occupied, class-labelled voxels of `grid` into objects (DBSCAN per class):
    `labelled_voxels` then `cluster_objects`, whose docstrings say what each argument does."""
    if min_voxels < 1 or not 0.0 <= min_probability <= 1.0:
        msg = (
            "need min_voxels >= 1 and min_probability in [0, 1], "
            f"found {min_voxels!r}, {min_probability!r}"
        )
        raise InputError(msg)
    voxels = labelled_voxels(grid, min_probability=min_probability, exclude=exclude)
    return cluster_objects(voxels, min_voxels=min_voxels, id_cell=id_cell, link=link)


class ObjectTracker:
    """Stable ids for objects found again and again in a growing map.

    Each object of a new extraction takes the id of the nearest object of the same class in the
    previous list within `gate` metres (nearest pairs first, each id once); the others get new
    ids counting up from `first_id`. Objects not found again are gone.
    """

    def __init__(self, gate: float = 0.75, first_id: int = 1) -> None:
        if gate <= 0 or first_id < 0:
            msg = f"need gate > 0 and first_id >= 0, found {gate!r}, {first_id!r}"
            raise InputError(msg)
        self.gate = gate
        self._next = first_id
        self.objects: list[ObjectCentroid] = []

    def update(self, found: list[ObjectCentroid]) -> list[ObjectCentroid]:
        """`found` with tracked ids (also kept as `objects`)."""
        prev = self.objects
        ids: list[int | None] = [None] * len(found)
        if prev and found:
            a = np.array([o.position for o in prev])
            b = np.array([o.position for o in found])
            dist = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2)
            same = (
                np.array([o.class_id for o in prev])[:, None]
                == np.array([o.class_id for o in found])[None, :]
            )
            dist = np.where(same & (dist <= self.gate), dist, np.inf)
            used = np.zeros(len(prev), bool)
            for flat in np.argsort(dist, axis=None):  # nearest pairs first
                i, j = divmod(int(flat), len(found))
                if not np.isfinite(dist[i, j]):
                    break
                if used[i] or ids[j] is not None:
                    continue
                used[i] = True
                ids[j] = prev[i].object_id
        out = []
        for o, known in zip(found, ids, strict=True):
            oid = known
            if oid is None:
                oid, self._next = self._next, self._next + 1
            out.append(replace(o, object_id=oid))
        self.objects = out
        return out


def moved(a: list[ObjectCentroid], b: list[ObjectCentroid], tolerance: float) -> bool:
    """True if `b` differs from `a`: other ids or classes, or an object moved over `tolerance` m."""
    if [(o.object_id, o.class_id) for o in a] != [(o.object_id, o.class_id) for o in b]:
        return True
    return any(
        float(np.linalg.norm(x.position - y.position)) > tolerance
        for x, y in zip(a, b, strict=True)
    )
