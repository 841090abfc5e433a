"""Scan-to-map matching on constructed rooms and corridors with known answers; the scan localiser
beats odometry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from voxel.errors import LocalisationError
from voxel.localisation import se2
from voxel.localisation.localiser import ScanLocaliser
from voxel.localisation.odometry import OdometryNoise, synthesise
from voxel.localisation.scan_match import LocalMap, match, orient


def _segments_scan(
    pose: np.ndarray,
    walls: list[tuple[tuple[float, float], tuple[float, float]]],
    beams: int = 360,
    noise: float = 0.0,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Body-frame points of a 360-degree 2D scan from planar `pose` against wall segments
    (vectorised)."""
    a = pose[2] + np.linspace(-math.pi, math.pi, beams, endpoint=False)
    d = np.column_stack([np.cos(a), np.sin(a)])
    o = pose[:2]
    best = np.full(beams, np.inf)
    for (x1, y1), (x2, y2) in walls:
        e = np.array([x2 - x1, y2 - y1])
        den = d[:, 0] * e[1] - d[:, 1] * e[0]
        with np.errstate(divide="ignore", invalid="ignore"):
            w = np.array([x1, y1]) - o
            t = (w[0] * e[1] - w[1] * e[0]) / den
            u = (w[0] * d[:, 1] - w[1] * d[:, 0]) / den
        hit = (np.abs(den) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1)
        best = np.where(hit & (t < best), t, best)
    keep = np.isfinite(best)
    r = best[keep] + (0 if rng is None else rng.normal(scale=noise, size=keep.sum()))
    local = a[keep] - pose[2]
    return np.column_stack([r * np.cos(local), r * np.sin(local), np.zeros(keep.sum())])


ROOM = [
    ((-4, -3), (4, -3)),
    ((4, -3), (4, 3)),
    ((4, 3), (-4, 3)),
    ((-4, 3), (-4, -3)),
    ((-1, -1), (0.5, -1)),
    ((0.5, -1), (0.5, 0.2)),
    ((2, 1.5), (3, 2.5)),
]
CORRIDOR = [((-20, -1), (20, -1)), ((-20, 1), (20, 1))]


def _map_of(walls: list, pose: np.ndarray, beams: int = 360) -> LocalMap:
    local = LocalMap(planar=True)
    m = se2.to_matrix(pose)
    pts = _segments_scan(pose, walls, beams)
    local.add(pts @ m[:3, :3].T + m[:3, 3], m)
    return local


def test_match_recovers_a_known_offset_in_a_room() -> None:
    truth = np.array([0.3, -0.4, 0.2])
    local = _map_of(ROOM, np.array([0.0, 0.0, 0.0]))
    scan = _segments_scan(truth, ROOM)
    result = match(scan, local, se2.to_matrix(truth + np.array([0.15, -0.1, 0.06])))
    assert result.ok
    np.testing.assert_allclose(se2.from_matrix(result.pose), truth, atol=5e-3)
    assert result.rmse < 0.01
    assert np.all(np.sqrt(np.diag(result.covariance)) < 0.05)


def test_corridor_leaves_its_length_unconstrained() -> None:
    local = _map_of(CORRIDOR, np.zeros(3))
    truth = np.array([0.5, 0.1, 0.05])
    result = match(
        _segments_scan(truth, CORRIDOR), local, se2.to_matrix(truth + np.array([0.0, 0.08, 0.03]))
    )
    assert result.ok
    pose = se2.from_matrix(result.pose)
    assert pose[1:] == pytest.approx(
        truth[1:], abs=5e-3
    )  # across the corridor and the heading are found
    sd = np.sqrt(np.diag(result.covariance))
    assert sd[0] > 20 * sd[1]  # along the corridor: no information


def test_a_match_says_which_keyframes_it_used_and_how_much() -> None:
    # Two keyframes of the room from two poses: the match's correspondences come from both, and
    # their shares of the information add up to the Hessian behind the covariance (which is at
    # least the independent noise's part of it, a residual's 1 cm floor: the patches' shared
    # errors only add to it).
    local = LocalMap(planar=True, key_distance=0.25)
    for pose in (np.zeros(3), np.array([1.0, 0.5, 0.3])):
        m = se2.to_matrix(pose)
        key = local.add(_segments_scan(pose, ROOM) @ m[:3, :3].T + m[:3, 3], m)
        assert key == local.ids[-1]
    assert local.ids == [0, 1] and set(np.unique(local.labels).tolist()) == {0, 1}
    truth = np.array([0.5, 0.2, 0.1])
    result = match(_segments_scan(truth, ROOM), local, se2.to_matrix(truth + 0.03))
    assert result.ok and result.labels is not None and result.information is not None
    assert result.labels.tolist() == [0, 1]
    total = result.information.sum(axis=0)
    for share in result.information:
        assert np.linalg.eigvalsh(share).min() >= -1e-9  # each keyframe's share is information
    np.testing.assert_allclose(total, total.T)
    extra = result.covariance - 1e-4 * np.linalg.inv(total)
    assert np.linalg.eigvalsh(0.5 * (extra + extra.T)).min() >= -1e-12


#: A 10 cm thick wall (faces at x = -0.05 and +0.05) and a long wall at y = 3 seen from both sides
#: of it: only the thin wall constrains x.
THIN_WALL = [((-0.05, -2), (-0.05, 2)), ((0.05, -2), (0.05, 2)), ((-4, 3), (4, 3))]


def test_orient_turns_normals_towards_the_viewpoint() -> None:
    normals = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    points = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    out = orient(normals, points, np.array([1.0, 0.0, 0.0]))
    np.testing.assert_array_equal(out, [[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def test_a_thin_walls_far_face_is_not_matched_to_its_near_face() -> None:
    # The map saw the wall from the left (x = -1); the robot, truly at x = 1, sees its right face.
    # Unsigned normals pair the two faces and pull the robot 10 cm through the wall; oriented
    # ones drop those pairs, and x (constrained by nothing else) stays where it was predicted.
    local = _map_of(THIN_WALL, np.array([-1.0, 0.0, 0.0]), beams=1440)
    truth = np.array([1.0, 0.0, 0.0])
    scan = _segments_scan(truth, THIN_WALL, beams=1440)
    oriented = match(scan, local, se2.to_matrix(truth))
    assert oriented.ok
    assert se2.from_matrix(oriented.pose)[0] == pytest.approx(1.0, abs=1e-3)
    assert math.sqrt(oriented.covariance[0, 0]) > 20 * math.sqrt(oriented.covariance[1, 1])

    class Unsigned:  # the same map without the side it was seen from
        points, normals, tree, oriented = local.points, local.normals, local.tree, False

    unsigned = match(scan, Unsigned(), se2.to_matrix(truth))
    assert se2.from_matrix(unsigned.pose)[0] == pytest.approx(0.9, abs=0.01)


def test_match_reports_an_empty_map_and_bad_dof() -> None:
    result = match(np.zeros((10, 3)), LocalMap(planar=True), np.eye(4))
    assert not result.ok and result.reason == "empty map"
    with pytest.raises(LocalisationError, match=r"dof: expected 3 .* or 6, found 4"):
        match(np.zeros((10, 3)), LocalMap(planar=True), np.eye(4), dof=4)
    with pytest.raises(LocalisationError, match="keyframes >= 1"):
        LocalMap(planar=True, keyframes=0)


def test_scan_localiser_beats_biased_odometry_in_a_room() -> None:
    rng = np.random.default_rng(4)
    t = np.linspace(0, 2 * math.pi, 200)
    truth = np.column_stack([2.5 * np.cos(t), 1.8 * np.sin(t), np.zeros_like(t)])
    heading = np.arctan2(np.gradient(truth[:, 1]), np.gradient(truth[:, 0]))
    truth[:, 2] = heading
    odo = synthesise(truth, OdometryNoise(0.05, 0.05, 0.01, 0.03, 0.02), seed=1)
    loc = ScanLocaliser(planar=True)
    est = np.array(
        [
            loc.step(_segments_scan(p, ROOM, noise=0.01, rng=rng), o).pose
            for p, o in zip(truth, odo, strict=True)
        ]
    )
    err_est = np.linalg.norm(est[:, :2] - truth[:, :2], axis=1).max()
    err_odo = np.linalg.norm(odo[:, :2] - truth[:, :2], axis=1).max()
    assert err_odo > 0.3
    assert err_est < 0.1
    assert loc.ekf is not None and loc.ekf.accepted > 150


def _noisy_match(
    walls: list, beams: int, start: np.ndarray, truth: np.ndarray | None = None, **kw: object
) -> tuple[np.ndarray, np.ndarray]:
    """The pose and standard deviations (x, y, yaw) of a scan with 5 mm noise matched from
    `start` against a map of the same walls seen from the origin."""
    truth = np.zeros(3) if truth is None else truth
    local = _map_of(walls, np.zeros(3), beams=1440)
    scan = _segments_scan(truth, walls, beams, noise=0.005, rng=np.random.default_rng(3))
    result = match(scan, local, se2.to_matrix(start), **kw)  # type: ignore[arg-type]
    assert result.ok
    return se2.from_matrix(result.pose), np.sqrt(np.diag(result.covariance))


def test_a_single_wall_leaves_its_length_free_and_fixes_the_distance_to_it() -> None:
    _, sd = _noisy_match([((-10, 2), (10, 2))], 720, np.array([0.02, -0.01, 0.0]))
    assert sd[1] < 0.02  # across: a centimetre or two
    assert sd[0] > 10 * sd[1]  # along: nothing but the wall's ends far away


def test_a_corner_constrains_both_directions() -> None:
    _, sd = _noisy_match([((-0.5, 2), (6, 2)), ((-0.5, 2), (-0.5, -6))], 720, np.zeros(3))
    assert sd[0] < 0.02 and sd[1] < 0.02
    assert 1 / 3 < sd[0] / sd[1] < 3


def test_four_times_the_points_do_not_quarter_the_variance() -> None:
    # Points on the same piece of wall share its error: more of them narrow the covariance
    # far less than independent measurements would (variance / 4).
    _, few = _noisy_match(ROOM, 360, np.zeros(3))
    _, many = _noisy_match(ROOM, 1440, np.zeros(3))
    ratio = (many / few) ** 2
    assert np.all(ratio[:2] > 0.5), ratio


def test_a_second_minimum_along_a_repeating_wall_widens_the_covariance() -> None:
    # A wall with a 12 cm square-wave relief and one across it far below: started 7 cm off, the
    # match settles on the copy 12 cm away; the restarts along the wall find the true one as
    # good, and the variance along the wall covers both (without them: a millimetre).
    period, walls = 0.12, [((-5.0, -1.0), (5.0, -1.0))]
    for k in range(-30, 30):
        x0, mid = k * period, k * period + period / 2
        walls += [((x0, 1.0), (mid, 1.0)), ((mid, 1.0), (mid, 1.05))]
        walls += [((mid, 1.05), (x0 + period, 1.05)), ((x0 + period, 1.05), (x0 + period, 1.0))]
    local = LocalMap(planar=True, cell=0.01)
    local.add(_segments_scan(np.zeros(3), walls, 2880), np.eye(4))
    scan = _segments_scan(np.zeros(3), walls, 2880, noise=0.003, rng=np.random.default_rng(1))
    start = se2.to_matrix(np.array([0.072, 0.0, 0.0]))
    alone = match(scan, local, start, probe=False)
    probed = match(scan, local, start)
    assert se2.from_matrix(alone.pose)[0] == pytest.approx(period, abs=0.01)  # the wrong copy
    np.testing.assert_array_equal(probed.pose, alone.pose)  # the restarts move nothing
    assert math.sqrt(alone.covariance[0, 0]) < 0.01
    assert math.sqrt(probed.covariance[0, 0]) > period / 2
