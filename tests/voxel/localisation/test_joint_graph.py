"""Tests for the joint two-robot pose graph: constructed cases with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from voxel.errors import LocalisationError
from voxel.localisation import se2
from voxel.localisation.joint_graph import JointGraph, matrices, poses_of
from voxel.localisation.pose_graph import PoseGraph

TIGHT = np.diag([1e-8, 1e-8, 1e-10])


def _matched(alignment: np.ndarray, online: np.ndarray, true: np.ndarray, t: np.ndarray, x):
    """Where the robot at `x` (its frame) matches against a map the peer drew believing it was
    at `online` while it was at `true` (its frame), put in with `alignment` when the frames'
    true transform is `t`: a wall point p seen by both lands at A y° y^-1 T^-1 p."""
    b = matrices(alignment) @ matrices(online) @ np.linalg.inv(matrices(true))
    return poses_of(b @ np.linalg.inv(matrices(t)) @ matrices(x))


def test_inter_edge_moves_the_peer_node_that_built_the_map() -> None:
    # the peer drove straight along x, odometry loose across; its node 3 was 0.1 m off (its
    # frame) when it drew the map there; the robot knows where it is and the transform
    t = np.array([0.5, -1.0, 0.4])
    peer = PoseGraph(np.zeros(3), TIGHT)
    for _ in range(5):
        peer.step(np.array([1.0, 0.0, 0.0]), np.diag([1e-4, 1e-2, 1e-8]))
    online = np.array(peer.online)
    true3 = online[3] + np.array([0.0, -0.1, 0.0])
    x = np.array([2.0, 1.0, 0.2])
    robot = PoseGraph(x, TIGHT)
    joint = JointGraph(robot, peer, t, TIGHT)
    z = _matched(t, online[3], true3, t, x)
    joint.add_inter(0, z, np.diag([1e-8, 1e-8, 1e-8]), np.array([3]), np.array([1.0]))
    out = joint.solve()
    assert out.peer[3] == pytest.approx(true3, abs=1e-3)
    assert out.robot[0] == pytest.approx(x, abs=1e-5)
    assert out.transform == pytest.approx(t, abs=1e-5)
    assert out.cost_after < 1e-3 * out.cost_before
    # the nodes the edge does not name keep to their odometry (0 is held by its prior)
    assert out.peer[0] == pytest.approx(online[0], abs=1e-5)


def test_inter_edges_recover_the_transform_from_a_wrong_alignment() -> None:
    t = np.array([1.0, 2.0, 0.3])
    guess = t + np.array([0.05, -0.04, 0.02])  # the alignment's error
    peer = PoseGraph(np.array([0.5, 0.5, 0.1]), TIGHT)
    peer.step(np.array([1.0, 0.0, 0.1]), TIGHT)
    robot = PoseGraph(np.array([0.0, 0.0, 0.0]), TIGHT)
    for _ in range(3):
        robot.step(np.array([1.0, 0.5, 0.2]), TIGHT)
    online = np.array(peer.online)
    joint = JointGraph(robot, peer, guess, np.diag([0.1**2, 0.1**2, 0.05**2]))
    for node in range(robot.nodes):
        j = node % 2
        z = _matched(guess, online[j], online[j], t, robot.online[node])
        joint.add_inter(node, z, np.diag([1e-6, 1e-6, 1e-7]), np.array([j, 1 - j]), [0.5, 0.5])
    assert joint.edges() == robot.nodes
    out = joint.solve()
    assert out.transform == pytest.approx(t, abs=1e-3)
    assert out.peer == pytest.approx(online, abs=1e-5)
    assert out.robot == pytest.approx(np.array(robot.online), abs=1e-5)


def test_without_inter_edges_each_robot_keeps_its_own_solve() -> None:
    peer = PoseGraph(np.zeros(3), TIGHT)
    peer.step(np.array([1.0, 0.0, 0.0]), np.diag([1e-2, 1e-2, 1e-4]))
    peer.add_absolute(np.array([1.2, 0.1, 0.0]), np.diag([1e-2, 1e-2, 1e-4]))
    robot = PoseGraph(np.ones(3), TIGHT)
    out = JointGraph(robot, peer, np.zeros(3), TIGHT).solve()
    assert out.peer == pytest.approx(peer.solve().poses, abs=1e-6)
    assert out.robot[0] == pytest.approx(np.ones(3), abs=1e-6)
    assert se2.wrap(float(out.transform[2])) == pytest.approx(0.0, abs=1e-6)


def test_inter_edge_rejects_bad_weights_and_nodes() -> None:
    joint = JointGraph(
        PoseGraph(np.zeros(3), TIGHT), PoseGraph(np.zeros(3), TIGHT), np.zeros(3), TIGHT
    )
    with pytest.raises(LocalisationError):
        joint.add_inter(0, np.zeros(3), TIGHT, np.array([0]), np.array([0.5]))
    with pytest.raises(LocalisationError):
        joint.add_inter(0, np.zeros(3), TIGHT, np.array([1]), np.array([1.0]))
    with pytest.raises(LocalisationError):
        joint.add_inter(1, np.zeros(3), TIGHT, np.array([0]), np.array([1.0]))


@pytest.mark.parametrize("inflation", [1.0, 3.0])
def test_a_disagreement_splits_by_the_two_robots_uncertainty(inflation: float) -> None:
    # each robot one node known to 10 cm (x, y), the map 0.1 m off in y: the robot moves by
    # 0.1 / (1 + F) and the peer's node by the rest, F the peer's inflation
    loose = np.diag([0.01, 0.01, 1e-10])
    robot, peer = PoseGraph(np.zeros(3), loose), PoseGraph(np.zeros(3), loose)
    joint = JointGraph(robot, peer, np.zeros(3), TIGHT, peer_inflation=inflation)
    joint.add_inter(0, np.array([0.0, 0.1, 0.0]), TIGHT, np.array([0]), np.array([1.0]))
    out = joint.solve()
    assert out.robot[0] == pytest.approx([0.0, 0.1 / (1 + inflation), 0.0], abs=1e-5)
    assert out.peer[0] == pytest.approx([0.0, -0.1 * inflation / (1 + inflation), 0.0], abs=1e-5)
    with pytest.raises(LocalisationError):
        JointGraph(robot, peer, np.zeros(3), TIGHT, peer_inflation=0.0)


@pytest.mark.parametrize("inflation", [1.0, 10.0])
def test_inflated_inter_edges_pull_less(inflation: float) -> None:
    # both robots and the edge known to 10 cm: each node moves by 0.1 / (2 + F) toward the other
    loose = np.diag([0.01, 0.01, 1e-10])
    robot, peer = PoseGraph(np.zeros(3), loose), PoseGraph(np.zeros(3), loose)
    joint = JointGraph(robot, peer, np.zeros(3), TIGHT, inter_inflation=inflation)
    joint.add_inter(0, np.array([0.0, 0.1, 0.0]), loose, np.array([0]), np.array([1.0]))
    out = joint.solve()
    assert out.robot[0] == pytest.approx([0.0, 0.1 / (2 + inflation), 0.0], abs=1e-5)
    assert out.peer[0] == pytest.approx([0.0, -0.1 / (2 + inflation), 0.0], abs=1e-5)


def test_an_inter_floor_adds_to_the_matchers_covariance() -> None:
    # as the inflation test: an edge of covariance loose + 9 loose pulls as one inflated x10
    loose = np.diag([0.01, 0.01, 1e-10])
    robot, peer = PoseGraph(np.zeros(3), loose), PoseGraph(np.zeros(3), loose)
    joint = JointGraph(robot, peer, np.zeros(3), TIGHT, inter_floor=9 * loose)
    joint.add_inter(0, np.array([0.0, 0.1, 0.0]), loose, np.array([0]), np.array([1.0]))
    out = joint.solve()
    assert out.robot[0] == pytest.approx([0.0, 0.1 / 12, 0.0], abs=1e-5)
    assert out.factors == {} and out.rounds == 1  # no variance components asked for
    with pytest.raises(LocalisationError):
        JointGraph(robot, peer, np.zeros(3), TIGHT, inter_floor=np.eye(2))


def _noisy_pair(rng: np.random.Generator, factor: float, count: int = 100) -> JointGraph:
    """Two robots of `count` nodes each, odometry and a fix per node with the noise they claim,
    every robot node matched against the peer's map its node of the same number drew, those
    matches `factor` times noisier (in variance) than they claim. The peer's online poses and
    the alignment are the truth, so at the truth every match measures the robot's node."""
    step = np.diag([1e-4, 4e-4, 1e-5])
    fix = np.diag([4e-4, 4e-4, 4e-5])
    claimed = np.diag([1e-4, 1e-4, 1e-5])
    graphs, truths = [], []
    for first in (np.zeros(3), np.array([1.0, 2.0, 0.3])):
        truth = [first]
        for _ in range(count - 1):
            truth.append(se2.compose(truth[-1], np.array([0.1, 0.0, 0.02])))
        graph = PoseGraph(first, fix)
        for i in range(1, count):
            u = se2.relative(truth[i - 1], truth[i]) + rng.multivariate_normal(np.zeros(3), step)
            graph.step(u, step)
            graph.place(truth[i])
            graph.add_absolute(truth[i] + rng.multivariate_normal(np.zeros(3), fix), fix)
        graphs.append(graph)
        truths.append(np.array(truth))
    t = np.array([0.5, -0.5, 0.2])
    joint = JointGraph(graphs[0], graphs[1], t, TIGHT)
    for i in range(count):
        z = truths[0][i] + rng.multivariate_normal(np.zeros(3), factor * claimed)
        joint.add_inter(i, z, claimed, np.array([i]), np.array([1.0]))
    return joint


@pytest.mark.parametrize("factor", [1.0, 30.0])
def test_variance_components_recover_how_overconfident_the_matches_are(factor: float) -> None:
    # ~300 residual components per group: an estimate within ~25 % of its factor
    out = _noisy_pair(np.random.default_rng(7), factor).solve(vce=True)
    assert out.factors["inter"] == pytest.approx(factor, rel=0.25)
    assert out.factors["robot"] == pytest.approx(1.0, rel=0.25)
    assert out.factors["peer"] == pytest.approx(1.0, rel=0.25)
    assert 1 < out.rounds <= 8
