"""The pose graph on constructed cases with known answers: a late correction moves the whole
path, no correction leaves the filter's path, every edge's Jacobian, the localiser's record."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.shared import fresh_process
from tests.voxel.localisation.test_scan_match import ROOM, _segments_scan
from voxel.errors import LocalisationError
from voxel.localisation import se2
from voxel.localisation.ekf import PlanarEkf
from voxel.localisation.localiser import ScanLocaliser
from voxel.localisation.odometry import OdometryNoise, synthesise
from voxel.localisation.pose_graph import PoseGraph, variance_components

STEPS = 50
TRUE_STEP = np.array([0.1, 0.0, 0.0])
BIASED_STEP = np.array([0.11, 0.0, 0.0])  # odometry reads 10 % long


def _filter_and_graph() -> tuple[PlanarEkf, PoseGraph]:
    """A filter and its graph driven along a straight 5 m path by 10 %-long odometry."""
    ekf = PlanarEkf(np.zeros(3))
    graph = PoseGraph(ekf.pose, ekf.covariance)
    for _ in range(STEPS):
        ekf.predict(BIASED_STEP)
        graph.step(*ekf.motion_step(BIASED_STEP))
        graph.place(ekf.pose)
    return ekf, graph


def test_a_fix_at_the_end_corrects_the_whole_path_not_only_its_end() -> None:
    ekf, graph = _filter_and_graph()
    online = np.array(graph.online)
    fix, r = np.array([5.0, 0.0, 0.0]), np.diag([1e-4, 1e-4, 1e-6])
    assert ekf.update(fix, r)
    graph.add_absolute(fix, r)
    graph.place(ekf.pose)
    online[-1] = ekf.pose
    smoothed = graph.solve().poses
    truth = np.arange(STEPS + 1)[:, None] * TRUE_STEP
    mid = STEPS // 2
    # the filter corrected its last pose only; the middle keeps the odometry's 0.25 m
    assert abs(online[mid, 0] - truth[mid, 0]) == pytest.approx(0.25, abs=1e-9)
    assert abs(online[-1, 0] - 5.0) < 0.01
    # smoothed: the last pose as the filter's, the error spread back along the path
    assert smoothed[-1] == pytest.approx(ekf.pose, abs=1e-4)
    assert abs(smoothed[mid, 0] - truth[mid, 0]) < 0.01
    errors = np.abs(smoothed[:, 0] - truth[:, 0])
    assert errors.max() < 0.01


def test_without_corrections_the_smoothed_path_is_the_filters() -> None:
    _, graph = _filter_and_graph()
    result = graph.solve()
    np.testing.assert_allclose(result.poses, np.array(graph.online), atol=1e-9)
    assert result.cost_after == pytest.approx(0.0, abs=1e-9)


def test_an_own_map_match_to_the_first_keyframe_closes_the_loop() -> None:
    """A match at the end against the keyframe placed at the start measures the path's length:
    like the fix, it corrects the middle too."""
    ekf = PlanarEkf(np.zeros(3))
    graph = PoseGraph(ekf.pose, ekf.covariance)
    graph.add_keyframe(7, ekf.pose)
    for _ in range(STEPS):
        ekf.predict(BIASED_STEP)
        graph.step(*ekf.motion_step(BIASED_STEP))
        graph.place(ekf.pose)
    # seen in keyframe 7's map (placed at the origin without error): at 5 m
    info = np.array([np.diag([1e4, 1e4, 1e6]), np.diag([3e4, 1e2, 1e5])])
    graph.add_match(np.array([5.0, 0.0, 0.0]), np.diag([1e-4, 1e-4, 1e-6]), [7, 99], info)
    assert graph.edges()["match"] == 1  # keyframe 99 is unknown: placed without error
    smoothed = graph.solve().poses
    truth = np.arange(STEPS + 1) * TRUE_STEP[0]
    assert np.abs(smoothed[:, 0] - truth).max() < 0.01


def test_a_colony_map_off_by_its_offset_is_matched_through_it() -> None:
    """Odometry exact, a shared map off by 10 cm and 1 degree: the offset takes the map's error,
    the path stays where odometry puts it."""
    truth = np.array([[0.1 * i, 0.02 * i, 0.01 * i] for i in range(STEPS + 1)])
    off = np.array([0.1, -0.05, math.radians(1.0)])
    c, s = math.cos(off[2]), math.sin(off[2])
    graph = PoseGraph(truth[0], np.eye(3) * 1e-8)
    graph.reset_offset(np.diag([1.0, 1.0, 0.1]))
    for i in range(1, STEPS + 1):
        graph.step(se2.relative(truth[i - 1], truth[i]), np.eye(3) * 1e-8)
        graph.place(truth[i] + 0.05)  # a poor start for the solve
        if i % 20 == 10:
            x = truth[i]
            z = np.array(
                [c * x[0] - s * x[1] + off[0], s * x[0] + c * x[1] + off[1], x[2] + off[2]]
            )
            graph.add_colony(z, np.diag([1e-4, 1e-4, 1e-6]))
    result = graph.solve()
    np.testing.assert_allclose(result.poses, truth, atol=1e-4)
    np.testing.assert_allclose(result.offsets[0], off, atol=1e-4)


def test_every_edges_gradient_is_the_costs() -> None:
    """The normal equations' gradient (half the cost's) against finite differences of the cost,
    with every kind of edge at a point away from the solution."""
    rng = np.random.default_rng(2)
    graph = PoseGraph(np.array([0.3, -0.2, 0.4]), np.diag([1e-2, 2e-2, 1e-3]))
    graph.add_keyframe(0, np.array([0.31, -0.2, 0.41]))
    for i in range(6):
        graph.step(np.array([0.4, 0.1, 0.3]), np.diag([1e-2, 1e-2, 1e-3]))
        if i == 2:
            graph.add_keyframe(1, graph.online[-1] + 0.01)
    info = np.array(
        [np.diag([2.0, 1.0, 3.0]), np.array([[2.0, 0.5, 0.1], [0.5, 1.0, 0], [0.1, 0, 1]])]
    )
    graph.add_match(graph.online[-1] + 0.03, np.diag([1e-2, 2e-2, 1e-3]), [0, 1], info)
    graph.reset_offset(np.diag([0.1, 0.1, 0.01]))
    graph.add_colony(graph.online[-1] - 0.02, np.diag([1e-2, 1e-2, 1e-3]))
    graph.walk_offset(np.diag([0.01, 0.02, 0.001]))
    graph.add_colony(graph.online[-1] + 0.02, np.diag([1e-2, 1e-2, 1e-3]))
    graph.add_absolute(graph.online[-1] + 0.1, np.diag([1e-2, 1e-2, 1e-3]))
    graph.add_landmark(
        np.array([1.0, 2.0]), np.eye(2) * 1e-2, np.array([3.0, 4.0]), np.eye(2) * 1e-3, 0.5
    )
    poses = np.array(graph.online) + rng.normal(scale=0.05, size=(7, 3))
    offsets = rng.normal(scale=0.05, size=(2, 3))
    x0 = np.concatenate([poses.ravel(), offsets.ravel()])

    def cost(x: np.ndarray) -> float:
        return graph._linearised(x[:21].reshape(7, 3), x[21:].reshape(2, 3))[0]

    _, h, g = graph._linearised(poses, offsets)
    numeric = np.array([(cost(x0 + e) - cost(x0 - e)) / 2e-6 for e in np.eye(len(x0)) * 1e-6])
    np.testing.assert_allclose(2 * g, numeric, rtol=1e-5, atol=1e-4)
    assert np.allclose(h.toarray(), h.toarray().T)


def test_repeated_fixes_share_the_redundancy_as_least_squares_does() -> None:
    """Five equal absolute fixes of one node: each leaves 3 (1 - 1/5) degrees of freedom the
    solve cannot absorb (together 15 - 3), its cost its squared Mahalanobis residual."""
    cov = np.diag([1e-2, 4e-2, 1e-3])
    graph = PoseGraph(np.zeros(3), cov)
    fixes = np.array([[0.1, 0.0, 0.01], [-0.1, 0.2, 0.0], [0.0, -0.2, -0.02], [0.05, 0.0, 0.0]])
    for z in fixes:
        graph.add_absolute(z, cov)
    x = graph.solve().poses
    np.testing.assert_allclose(x[0], fixes.sum(axis=0) / 5, atol=1e-9)  # the mean of 0 and them
    ((blocks, r, info),) = graph.terms(x, np.zeros((0, 3)))
    first = ([(ids[:1], j[:1]) for ids, j in blocks], r[:1], info[:1])
    rest = ([(ids[1:], j[1:]) for ids, j in blocks], r[1:], info[1:])
    found = variance_components({"first": [first], "rest": [rest]}, [], 3)
    assert found["first"][1] == pytest.approx(3 * 4 / 5, rel=1e-9)
    assert found["rest"][1] == pytest.approx(4 * 3 * 4 / 5, rel=1e-9)
    assert (found["first"][2], found["rest"][2]) == (3, 12)
    lr = np.einsum("eij,ej->ei", info, r)
    assert found["first"][0] == pytest.approx(float(r[0] @ lr[0]), rel=1e-9)
    assert found["rest"][0] == pytest.approx(float(np.sum(r[1:] * lr[1:])), rel=1e-9)


def test_the_localiser_records_what_it_fused() -> None:
    rng = np.random.default_rng(4)
    t = np.linspace(0, 2 * math.pi, 120)
    truth = np.column_stack([2.5 * np.cos(t), 1.8 * np.sin(t), np.zeros_like(t)])
    truth[:, 2] = np.arctan2(np.gradient(truth[:, 1]), np.gradient(truth[:, 0]))
    odo = synthesise(truth, OdometryNoise(0.05, 0.05, 0.01, 0.03, 0.02), seed=1)
    loc = ScanLocaliser(planar=True)
    loc.record = True
    est = np.array(
        [
            loc.step(_segments_scan(p, ROOM, noise=0.01, rng=rng), o).pose
            for p, o in zip(truth, odo, strict=True)
        ]
    )
    graph = loc.graph
    assert graph is not None and loc.ekf is not None
    assert graph.nodes == len(truth)
    np.testing.assert_allclose(np.array(graph.online), est)
    edges = graph.edges()
    assert edges["odometry"] == len(truth) - 1
    assert edges["match"] == loc.ekf.accepted  # one edge per fused match
    smoothed = graph.solve().poses
    assert np.linalg.norm(smoothed[-1, :2] - est[-1, :2]) < 0.02  # the filter's last pose
    err_online = np.linalg.norm(est[:, :2] - truth[:, :2], axis=1)
    err_smoothed = np.linalg.norm(smoothed[:, :2] - truth[:, :2], axis=1)
    assert err_smoothed.mean() <= err_online.mean() + 0.005
    assert err_smoothed.max() < 0.1


def test_the_graph_says_when_an_offset_is_missing() -> None:
    graph = PoseGraph(np.zeros(3), np.eye(3))
    with pytest.raises(LocalisationError, match="reset_offset"):
        graph.walk_offset(np.eye(3))
    with pytest.raises(LocalisationError, match="reset_offset"):
        graph.add_colony(np.zeros(3), np.eye(3))


def test_a_keyed_landmark_is_one_variable_counted_once_as_in_the_filter() -> None:
    """50 sightings of a landmark published 0.3 m off (claimed 0.1 m), each good to 2 cm, from
    one node with a 1 m prior, heading known: keyed, the smoothed pose moves as one sighting
    with noise C + R / 50 would (as the filter's), and the landmark's position is solved;
    unkeyed, as 50 independent ones; the gradient is the cost's."""
    c, r, p = 0.1**2, 0.02**2, 1.0
    seen, published = np.array([3.0, 0.0]), np.array([3.3, 0.0])

    def solved(key: int | None) -> tuple[float, np.ndarray]:
        graph = PoseGraph(np.zeros(3), np.diag([p, p, 1e-12]))
        for _ in range(50):
            graph.add_landmark(seen, np.eye(2) * r, published, np.eye(2) * c, 0.0, key=key)
        result = graph.solve()
        return float(result.poses[0, 0]), result.landmarks

    x, landmarks = solved(7)
    noise = c + r / 50
    assert x == pytest.approx(0.3 * p / (p + noise), abs=1e-5)
    np.testing.assert_allclose(landmarks, [[3.0 + x, 0.0]], atol=1e-5)
    x, landmarks = solved(None)
    assert x == pytest.approx(0.3 * p / (p + (c + r) / 50), abs=1e-5)
    assert landmarks.shape == (0, 2)
    # the gradient against finite differences, a widened prior and a second node
    graph = PoseGraph(np.array([0.1, 0.2, 0.3]), np.diag([1e-2, 2e-2, 1e-3]))
    graph.add_landmark(seen, np.eye(2) * r, published, np.eye(2) * c, 0.3, key=1)
    graph.step(np.array([0.4, 0.1, 0.3]), np.diag([1e-2, 1e-2, 1e-3]))
    graph.add_landmark(seen, np.eye(2) * r, published + 0.1, np.diag([4 * c, c]), 0.6, key=1)
    assert graph.edges()["landmark_keyed"] == 2 and graph.landmarks == 1
    rng = np.random.default_rng(3)
    poses = np.array(graph.online) + rng.normal(scale=0.05, size=(2, 3))
    extra = np.array([[3.2, 0.1, 0.05]])
    x0 = np.concatenate([poses.ravel(), extra.ravel()])

    def cost(v: np.ndarray) -> float:
        return graph._linearised(v[:6].reshape(2, 3), v[6:].reshape(1, 3))[0]

    _, h, g = graph._linearised(poses, extra)
    assert np.allclose(h.toarray(), h.toarray().T)
    numeric = np.array([(cost(x0 + e) - cost(x0 - e)) / 2e-6 for e in np.eye(len(x0)) * 1e-6])
    np.testing.assert_allclose(2 * g, numeric, rtol=1e-5, atol=1e-4)
    # without shared variables (a joint graph's view) the keyed sightings are independent edges
    assert len(graph.terms(poses, np.zeros((0, 3)), shared=False)) == 3  # prior, odometry, lm


def test_a_daemon_starts_without_scipy_sparse_and_a_graph_still_solves() -> None:
    """scipy.sparse (~0.5 CPU-s with what it pulls in) loads where a graph is solved, not at every
    daemon's start: a fresh process imports the daemon without it, then smooths a path."""

    code = (
        "import sys, numpy as np\n"
        "import colonyd.daemon, colonyd.cli\n"
        "print('scipy.sparse' in sys.modules)\n"
        "from voxel.localisation.ekf import PlanarEkf\n"
        "from voxel.localisation.pose_graph import PoseGraph\n"
        "ekf = PlanarEkf(np.zeros(3))\n"
        "g = PoseGraph(ekf.pose, ekf.covariance)\n"
        "for _ in range(5):\n"
        "    ekf.predict(np.array([0.1, 0.0, 0.0]))\n"
        "    g.step(*ekf.motion_step(np.array([0.1, 0.0, 0.0])))\n"
        "ekf.update(np.array([0.4, 0.0, 0.0]), np.eye(3) * 1e-6)\n"
        "g.add_absolute(np.array([0.4, 0.0, 0.0]), np.eye(3) * 1e-6)\n"
        "g.place(ekf.pose)\n"
        "print(round(float(g.solve().poses[-1, 0]), 3), 'scipy.sparse' in sys.modules)\n"
    )
    stdout = fresh_process(code)
    assert stdout.split("\n")[:2] == ["False", "0.4 True"], stdout
