"""Provenance: the pose error, reliability and bias an agent's history records carry."""

from __future__ import annotations

import numpy as np

from colonyd.layers import Layer
from voxel import keys as vk


def pose_error(covariance: np.ndarray | None) -> float:
    """e: the position error estimate (metres) of a 6x6 pose covariance, sqrt of the trace of its
    position block; 0 without a covariance."""
    if covariance is None:
        return 0.0
    trace = float(np.trace(np.asarray(covariance, dtype=np.float64)[:3, :3]))
    return float(np.sqrt(trace)) if np.isfinite(trace) and trace > 0 else 0.0


def agent_reliability(weights: dict[str, float], agent: str, kind: str) -> float:
    """r's agent part: the configured reliability weight of `agent` (by id, else by kind; 1.0
    when none), clipped to [0, 1] for the record."""
    return float(min(max(weights.get(agent, weights.get(kind, 1.0)), 0.0), 1.0))


def agent_bias(own: Layer, peers: list[Layer], transforms: dict[str, np.ndarray]) -> float | None:
    """b: how much more often this agent calls a voxel occupied than its aligned peers do, over
    the voxels both observed: mean of (occupied here) - (occupied there), in [-1, 1]. Positive:
    it sees obstacles where peers see free space (phantom returns, a dirty lens); negative: it
    misses obstacles peers see. None without an aligned peer that shares a known voxel.

    `transforms` take each agent's frame into the colony frame (the own one included)."""
    t_own = transforms.get(own.origin)
    if t_own is None:
        return None
    mine = own.full()
    known = ~np.isnan(mine.logodds)
    own_keys = vk.pack(mine.keys[known])
    order = np.argsort(own_keys)
    own_keys, own_occ = own_keys[order], (mine.logodds[known] >= 0)[order]
    diffs: list[np.ndarray] = []
    for peer in peers:
        t_peer = transforms.get(peer.origin)
        if t_peer is None or peer.origin == own.origin or own_keys.size == 0:
            continue
        full = peer.full()
        seen = ~np.isnan(full.logodds)
        into_own = np.linalg.inv(t_own) @ t_peer
        centres = vk.keys_to_centers(full.keys[seen], peer.resolution)
        keys = vk.pack(vk.points_to_keys(centres @ into_own[:3, :3].T + into_own[:3, 3],
                                         own.resolution))  # fmt: skip
        pos = np.minimum(np.searchsorted(own_keys, keys), own_keys.size - 1)
        both = own_keys[pos] == keys
        diffs.append(own_occ[pos[both]].astype(np.float64) - (full.logodds[seen][both] >= 0))
    if not diffs or sum(d.size for d in diffs) == 0:
        return None
    return float(np.concatenate(diffs).mean())
