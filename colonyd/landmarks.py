"""Landmarks: objects whose identity a sensor gives (ArUco markers) and whose position aligned
peers know, in this agent's frame with covariance (paper Alg. 3)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from colonyd.alignment import ColonyFrame
from colonyd.fixes import through
from colonyd.objects import CLUSTER_IDS
from protocol import ObjectCentroid as WireObject
from voxel.localisation import frame_error
from voxel.localisation.localiser import Through

#: A landmark the colony knows: (x, y) in our frame, its 2x2 covariance, and the alignment it
#: came through when its covariance leaves the alignment's error out (`framed`), else None.
Known = tuple[np.ndarray, np.ndarray, Through | None]


def colony_landmarks(
    frame: ColonyFrame,
    own: str,
    lists: Mapping[str, Sequence[WireObject]],
    framed: bool = False,
) -> dict[int, Known]:
    """Object id -> (x, y) in our frame, its 2x2 covariance and (with `framed`) the alignment it
    came through, for every identified object (an id a sensor gave, below `CLUSTER_IDS`) of
    every peer aligned with us: the peer's own covariance of it, turned into our frame, plus
    the alignment's error at that point, or with `framed` without it (the filter estimates the
    alignment's error as one state, `ScanParams.alignment_frames`). An object several peers
    know is taken from the one that knows it best (with the alignment's error)."""
    mine = frame.transforms.get(own)
    if mine is None:
        return {}
    back = np.linalg.inv(mine)
    out: dict[int, Known] = {}
    best_trace: dict[int, float] = {}
    for origin, objects in lists.items():
        theirs = frame.transforms.get(origin)
        if origin == own or theirs is None:
            continue
        to_own = back @ theirs
        via = through(frame, own, origin) if framed else None
        error = frame_error.moved(frame.covariance(own) + frame.covariance(origin), back)
        rot = to_own[:2, :2]
        for o in objects:
            if not 0 <= o.object_id < CLUSTER_IDS:
                continue
            xy = (to_own[:3, :3] @ np.asarray(o.position, float) + to_own[:3, 3])[:2]
            own_cov = np.asarray(o.covariance, float).reshape(3, 3)[:2, :2]
            w, v = np.linalg.eigh(0.5 * (own_cov + own_cov.T))  # a peer's word: made PSD
            own_cov = (v * np.clip(w, 1e-6, None)) @ v.T
            own_cov = rot @ own_cov @ rot.T
            cov = own_cov + frame_error.at(error, xy)[:2, :2]
            best = best_trace.get(o.object_id)
            if best is None or np.trace(cov) < best:
                best_trace[o.object_id] = float(np.trace(cov))
                out[o.object_id] = (xy, cov, None) if via is None else (xy, own_cov, via)
    return out
