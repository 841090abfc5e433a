"""Landmarks: objects whose identity a sensor gives (ArUco markers) and whose position aligned
peers know, in this agent's frame with covariance (paper Alg. 3)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from colonyd.alignment import ColonyFrame
from colonyd.objects import CLUSTER_IDS
from protocol import ObjectCentroid as WireObject
from voxel.localisation import frame_error


def colony_landmarks(
    frame: ColonyFrame, own: str, lists: Mapping[str, Sequence[WireObject]]
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Object id -> (x, y) in our frame and its 2x2 covariance, for every identified object
    (an id a sensor gave, below `CLUSTER_IDS`) of every peer aligned with us: the peer's own
    covariance of it, turned into our frame, plus the alignment's error at that point. An
    object several peers know is taken from the one that knows it best."""
    mine = frame.transforms.get(own)
    if mine is None:
        return {}
    back = np.linalg.inv(mine)
    out: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for origin, objects in lists.items():
        theirs = frame.transforms.get(origin)
        if origin == own or theirs is None:
            continue
        to_own = back @ theirs
        error = frame_error.moved(frame.covariance(own) + frame.covariance(origin), back)
        rot = to_own[:2, :2]
        for o in objects:
            if not 0 <= o.object_id < CLUSTER_IDS:
                continue
            xy = (to_own[:3, :3] @ np.asarray(o.position, float) + to_own[:3, 3])[:2]
            own_cov = np.asarray(o.covariance, float).reshape(3, 3)[:2, :2]
            w, v = np.linalg.eigh(0.5 * (own_cov + own_cov.T))  # a peer's word: made PSD
            own_cov = (v * np.clip(w, 1e-6, None)) @ v.T
            cov = rot @ own_cov @ rot.T + frame_error.at(error, xy)[:2, :2]
            best = out.get(o.object_id)
            if best is None or np.trace(cov) < np.trace(best[1]):
                out[o.object_id] = (xy, cov)
    return out
