"""The colony map a daemon cuts for its estimator: peers' occupied voxels in our frame, made
again only when an alignment changes or the robot's scans would reach past the cut."""

from __future__ import annotations

import numpy as np

from colonyd.alignment import ColonyFrame
from colonyd.colonymap import ColonyMaps
from colonyd.layers import Layers
from voxel.delta import Delta


def _layers() -> Layers:
    layers = Layers("me", 0.1)
    peer = layers.get("peer")
    x = np.arange(-30, 30)
    keys = np.column_stack([x, np.full(len(x), 20), np.full(len(x), 3)])  # a wall at y = 2.05
    peer.grid.apply(Delta(0.1, 0, 1, keys, np.full(len(x), 2.0), np.ones(len(x))))
    peer.seq = 1
    return layers


def _frame(dx: float) -> ColonyFrame:
    t = np.eye(4)
    t[0, 3] = dx
    return ColonyFrame("me", {"me": np.eye(4), "peer": t})


def test_the_cut_holds_the_peers_wall_in_our_frame_and_is_kept_until_something_changes() -> None:
    layers = _layers()
    maps = ColonyMaps("me", planar=True, height=0.3, sensor_range=2.0)
    cut = maps.refresh(layers, _frame(1.03), np.eye(4))
    assert cut is not None and cut.sources == ("peer",) and cut.tree is not None
    np.testing.assert_allclose(cut.points[:, 1], 2.05)  # the wall, on the scan plane
    np.testing.assert_allclose(cut.points[:, 2], 0.3)
    assert cut.points[:, 0].min() >= -4.0 and cut.points[:, 0].max() <= 4.0  # range + 2 m
    steps = (cut.points[:, 0] - 0.08) / 0.1  # centres k * 0.1 + 0.05, moved 1.03 m
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-6)
    assert maps.refresh(layers, _frame(1.03), np.eye(4)) is cut  # nothing changed: kept
    moved = maps.refresh(layers, _frame(1.3), np.eye(4))  # a new alignment: cut again
    assert moved is not cut and moved.alignment != cut.alignment
    far = np.eye(4)
    far[0, 3] = 1.5  # moved less than 2 m: its scans stay inside the cut
    assert maps.refresh(layers, _frame(1.3), far) is moved
    far[0, 3] = 2.5  # moved 2.5 m: its scans would reach past the cut, made again around it
    assert maps.refresh(layers, _frame(1.3), far) is not moved
    report = maps.report()
    assert report is not None and report["sources"] == ["peer"] and report["points"] > 0
    alone = ColonyFrame("me", {"me": np.eye(4)})  # not aligned with anyone: no colony map
    assert maps.refresh(layers, alone, np.eye(4)) is None and maps.report() is None
