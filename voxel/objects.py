"""Object centroids: clusters of occupied voxels sharing an object class, with covariance."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
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


def extract_objects(
    grid: VoxelGrid, *, min_probability: float = 0.3, min_voxels: int = 4, id_cell: float = 0.5
) -> list[ObjectCentroid]:
    """Cluster occupied, class-labelled voxels of `grid` into objects (DBSCAN per class).

    Voxels whose best class probability is below `min_probability` are ignored; clusters of
    26-connected voxels (DBSCAN with eps = 1.8 voxels) smaller than `min_voxels` are outliers.
    The centroid covariance is the voxel scatter over the count, plus the voxel quantisation.
    """
    from sklearn.cluster import DBSCAN  # type: ignore[import-untyped]

    if min_voxels < 1 or not 0.0 <= min_probability <= 1.0:
        msg = f"need min_voxels >= 1 and min_probability in [0, 1], found {min_voxels!r}, {min_probability!r}"
        raise InputError(msg)
    if "class_ids" not in grid.store.channels:
        return []
    keys = grid.occupied_keys()
    if keys.shape[0] == 0:
        return []
    ids = grid.channel_at_keys("class_ids", keys)
    probs = grid.channel_at_keys("class_probs", keys)
    best = probs.argmax(axis=1)
    rows = np.arange(keys.shape[0])
    cls = ids[rows, best].astype(np.int64)
    p = probs[rows, best]
    keep = (cls >= 0) & (p >= min_probability)
    keys, cls, p = keys[keep], cls[keep], p[keep]
    times = grid.channel_at_keys("last_time", keys) if keys.size else np.empty(0)
    res = grid.resolution
    centres = vk.keys_to_centers(keys, res)
    out: list[ObjectCentroid] = []
    for c in np.unique(cls):  # one pass per class present, vectorised inside
        m = cls == c
        pts = centres[m]
        labels = DBSCAN(eps=1.8 * res, min_samples=1).fit_predict(pts / 1.0)
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
