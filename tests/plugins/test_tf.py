"""The TF tree: chains of static and timed transforms, interpolation, and gaps named."""

from __future__ import annotations

import math

import numpy as np
import pytest

from plugins.checks import pose_matrix
from plugins.errors import SensorInputError
from plugins.tf import TfGapError, TfTree


def test_lookup_composes_a_chain_through_a_common_ancestor() -> None:
    tree = TfTree()
    map_odom = pose_matrix(1.0, 2.0, 0.0, 0.3)
    mount = pose_matrix(0.1, 0.0, 0.2, 0.0)
    cam = pose_matrix(0.0, 0.1, 0.5, -0.2)
    tree.set("map", "odom", 10.0, map_odom, static=False)
    tree.set("odom", "base_link", 10.0, pose_matrix(3.0, 0.0, 0.0, 1.0), static=False)
    tree.set("base_link", "laser", 0.0, mount, static=True)
    tree.set("base_link", "camera", 0.0, cam, static=True)
    want = map_odom @ pose_matrix(3.0, 0.0, 0.0, 1.0) @ mount
    np.testing.assert_allclose(tree.lookup("map", "laser", 10.0), want, atol=1e-12)
    np.testing.assert_allclose(
        tree.lookup("camera", "laser", 10.0), np.linalg.inv(cam) @ mount, atol=1e-12
    )
    np.testing.assert_allclose(tree.lookup("/map", "map", 3.0), np.eye(4))


def test_lookup_interpolates_between_stamps_and_refuses_outside() -> None:
    tree = TfTree()
    tree.set("odom", "base", 1.0, pose_matrix(0.0, 0.0, 0.0, 0.0), static=False)
    tree.set("odom", "base", 2.0, pose_matrix(2.0, 0.0, 0.0, 0.2), static=False)
    mid = tree.lookup("odom", "base", 1.5)
    assert mid[0, 3] == pytest.approx(1.0)
    assert math.atan2(mid[1, 0], mid[0, 0]) == pytest.approx(0.1, abs=1e-3)
    with pytest.raises(TfGapError, match=r"odom -> base known for 1.000..2.000 s, wanted at 2.050"):
        tree.lookup("odom", "base", 2.05)
    assert tree.lookup("odom", "base", 2.05, tolerance=0.1)[0, 3] == pytest.approx(2.0)
    with pytest.raises(TfGapError, match="no transform chain"):
        tree.lookup("map", "base", 1.5)


def test_history_is_bounded_and_loops_and_self_edges_are_refused() -> None:
    tree = TfTree(history=5, max_frames=3)
    for i in range(20):
        tree.set("odom", "base", float(i), np.eye(4), static=False)
    assert tree.newest("base") == 19.0
    with pytest.raises(TfGapError):
        tree.lookup("odom", "base", 10.0)
    with pytest.raises(SensorInputError, match="loop"):
        tree.set("base", "odom", 0.0, np.eye(4), static=True)
    with pytest.raises(SensorInputError, match="two different frame ids"):
        tree.set("a", "a", 0.0, np.eye(4), static=True)
    tree.set("base", "laser", 0.0, np.eye(4), static=True)
    tree.set("base", "cam", 0.0, np.eye(4), static=True)
    with pytest.raises(SensorInputError, match="at most 3 frames"):
        tree.set("base", "imu", 0.0, np.eye(4), static=True)


def test_edges_above_the_common_ancestor_are_not_needed() -> None:
    tree = TfTree()
    tree.set("colony", "map", 1e9, np.eye(4), static=False)  # another clock: never at t = 5
    tree.set("map", "base", 5.0, pose_matrix(1.0, 0.0, 0.0, 0.0), static=False)
    tree.set("base", "laser", 0.0, np.eye(4), static=True)
    assert tree.lookup("map", "laser", 5.0)[0, 3] == pytest.approx(1.0)
    with pytest.raises(TfGapError, match="colony -> map"):
        tree.lookup("colony", "laser", 5.0)
