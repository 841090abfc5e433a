"""Provenance of history records: pose error, agent reliability, bias against aligned peers."""

from __future__ import annotations

import numpy as np
import pytest

from colonyd.layers import Layer
from colonyd.provenance import agent_bias, agent_reliability, pose_error
from voxel.delta import Delta

RES = 0.1


def _layer(origin: str, keys: np.ndarray, logodds: np.ndarray) -> Layer:
    layer = Layer(origin, RES)
    layer.grid.apply(Delta(RES, 0, 1, keys, logodds, np.zeros(len(keys))))
    return layer


def test_pose_error_and_agent_reliability() -> None:
    cov = np.diag([0.04, 0.05, 0.0, 0.1, 0.1, 0.1])
    assert pose_error(cov) == pytest.approx(0.3) and pose_error(None) == 0.0
    assert pose_error(np.full((6, 6), np.nan)) == 0.0
    weights = {"r1": 0.5, "cctv": 2.0}
    assert agent_reliability(weights, "r1", "ground") == 0.5
    assert agent_reliability(weights, "c1", "cctv") == 1.0  # clipped into [0, 1]
    assert agent_reliability({}, "r2", "ground") == 1.0


def test_bias_is_how_much_more_often_an_agent_calls_voxels_occupied() -> None:
    keys = np.array([[i, 0, 0] for i in range(10)])
    truth = np.where(np.arange(10) < 5, 2.0, -1.0).astype(np.float32)  # 5 occupied, 5 free
    phantom = truth.copy()
    phantom[5:7] = 2.0  # sees two obstacles that are not there
    shift = np.eye(4)
    shift[0, 3] = 1.0  # the peer's frame is 1 m (10 voxels) along x from the colony frame
    own = _layer("a", keys, phantom)
    peer = _layer("b", keys - [10, 0, 0], truth)
    transforms = {"a": np.eye(4), "b": shift}
    assert agent_bias(own, [own, peer], transforms) == pytest.approx(2 / 10)
    assert agent_bias(peer, [own], {"a": np.linalg.inv(shift), "b": np.eye(4)}) == pytest.approx(
        -2 / 10
    )
    assert agent_bias(own, [peer], {"a": np.eye(4)}) is None  # the peer is not aligned
