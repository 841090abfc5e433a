"""End to end with the real grid: integrate, send deltas as frames, apply in any order, compare."""

from __future__ import annotations

import numpy as np
import pytest

from protocol.codec import decode, delta_messages, encode
from tests.protocol.helpers import KEY

grid_module = pytest.importorskip("voxel.grid")
VoxelGrid = grid_module.VoxelGrid


def _scan(rng: np.random.Generator, origin: np.ndarray, n: int = 3000) -> np.ndarray:
    """Points on the walls of a 6 x 4 x 3 m box seen from `origin`."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    lo, hi = np.array([-3.0, -2.0, 0.0]), np.array([3.0, 2.0, 3.0])
    with np.errstate(divide="ignore"):
        t = np.where(d > 0, (hi - origin) / d, (lo - origin) / d)
    return origin + d * np.min(t, axis=1, keepdims=True)


def test_replica_built_from_frames_matches_origin() -> None:
    rng = np.random.default_rng(11)
    origin_grid = VoxelGrid(0.1)
    replica = VoxelGrid(0.1)
    version = 0
    frames: list[bytes] = []
    seq = 0
    for i in range(4):
        sensor_at = np.array([-1.0 + 0.5 * i, 0.2 * i, 1.2])
        origin_grid.integrate(_scan(rng, sensor_at), sensor_at, time=100.0 + i)
        delta = origin_grid.delta_since(version)
        version = origin_grid.version
        msgs = delta_messages(
            origin="r1",
            epoch=1,
            seq=seq,
            time=100.0 + i,
            frame_id="map",
            delta=delta,
            max_bytes=4096,
        )
        seq += len(msgs)
        frames += [encode(m, key=KEY) for m in msgs]
    assert len(frames) > 4  # some deltas were split
    for i in rng.permutation(len(frames)):  # any order
        replica.apply(decode(frames[i], key=KEY).delta)
    assert replica.version == origin_grid.version
    occ_a, occ_b = origin_grid.occupied_keys(), replica.occupied_keys()
    free_a, free_b = origin_grid.free_keys(), replica.free_keys()
    assert occ_a.shape[0] > 100 and free_a.shape[0] > 1000
    np.testing.assert_array_equal(np.unique(occ_a, axis=0), np.unique(occ_b, axis=0))
    np.testing.assert_array_equal(np.unique(free_a, axis=0), np.unique(free_b, axis=0))
    keys = np.concatenate([occ_a, free_a])
    la, lb = origin_grid.logodds_at_keys(keys), replica.logodds_at_keys(keys)
    assert np.max(np.abs(la - lb)) <= 2.0**-5
