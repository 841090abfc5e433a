"""Colony-map updates on constructed cases: a peer's map pulls a drifted estimate back, a wrong
one is gated out, a short-range robot in a corridor stays on the peer's map."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.voxel.localisation.test_scan_match import ROOM, _segments_scan
from voxel.errors import LocalisationError
from voxel.localisation import se2
from voxel.localisation.colony_map import colony_map
from voxel.localisation.drift import OffsetWalk
from voxel.localisation.ekf import MotionNoise, PlanarEkf
from voxel.localisation.localiser import ScanLocaliser, ScanParams
from voxel.localisation.odometry import OdometryNoise, synthesise


def _wall_points(walls: list, spacing: float = 0.02, height: float = 0.0) -> np.ndarray:
    """Points every `spacing` m along wall segments, at `height` (a peer's map of them)."""
    out = []
    for (x1, y1), (x2, y2) in walls:
        n = max(2, int(math.hypot(x2 - x1, y2 - y1) / spacing))
        s = np.linspace(0.0, 1.0, n)
        out.append(np.column_stack([x1 + s * (x2 - x1), y1 + s * (y2 - y1), np.full(n, height)]))
    return np.concatenate(out)


def _drifted(pose: np.ndarray, sd: float) -> ScanLocaliser:
    """A localiser whose filter believes `pose` with standard deviation `sd` (m and rad)."""
    loc = ScanLocaliser(planar=True)
    loc.ekf = PlanarEkf(pose, covariance=np.diag([sd**2, sd**2, (sd / 2) ** 2]))
    loc.last_odometry = np.zeros(3)
    return loc


def test_colony_map_pulls_a_drifted_estimate_to_the_peers_map() -> None:
    truth = np.array([0.4, -0.5, 0.3])
    peers = colony_map(_wall_points(ROOM), planar=True, height=0.0, centre=np.zeros(2), radius=10.0)
    assert len(peers) > 500 and peers.tree is not None
    loc = _drifted(truth + np.array([0.2, -0.15, 0.05]), 0.2)
    step = loc.step(_segments_scan(truth, ROOM), np.zeros(3), colony=peers)
    assert step.match is not None and not step.match.ok  # no own map yet: only the colony's
    assert step.colony_fused and loc.colony_accepted == 1
    np.testing.assert_allclose(step.pose, truth, atol=0.02)


def test_a_wrong_colony_map_is_gated_out() -> None:
    truth = np.array([0.4, -0.5, 0.3])
    shifted = _wall_points(ROOM) + np.array([0.4, 0.0, 0.0])  # a bad alignment: 40 cm off
    peers = colony_map(shifted, planar=True, height=0.0, centre=np.zeros(2), radius=10.0)
    believed = truth + np.array([0.01, 0.0, 0.0])
    loc = _drifted(believed, 0.03)
    step = loc.step(_segments_scan(truth, ROOM), np.zeros(3), colony=peers)
    assert step.colony is not None and step.colony.ok
    assert not step.colony_fused and loc.colony_rejected == 1
    np.testing.assert_allclose(step.pose, believed, atol=1e-3)  # not dragged


def test_planar_cut_keeps_the_scan_band_and_the_radius() -> None:
    wall = _wall_points([((-4, 2), (4, 2))])
    stack = np.concatenate([wall + np.array([0, 0, z]) for z in (0.05, 0.35, 0.65, 1.5)])
    peers = colony_map(stack, planar=True, height=0.3, centre=np.array([0.0, 0.0]), radius=3.0)
    assert np.all(peers.points[:, 2] == 0.3)  # the band around the scan height, on it
    assert np.all(np.abs(peers.points[:, 0]) <= math.sqrt(9 - 4) + 1e-9)
    assert len(peers) == len(np.unique(np.floor(peers.points / 0.05), axis=0))  # thinned
    assert peers.covers(np.array([0.5, 0.0]), 2.0) and not peers.covers(np.array([2.0, 0]), 2.0)
    far = colony_map(stack, planar=True, height=5.0, centre=np.zeros(2), radius=3.0)
    assert far.tree is None and len(far) == 0
    with pytest.raises(LocalisationError, match="radius, cell, band > 0"):
        colony_map(stack, planar=True, height=0.3, centre=np.zeros(2), radius=0.0)


# A 24 m corridor with door jambs every 4 m (sides alternating): a 1.5 m scanner sees one over
# about 2 of every 4 m, and nothing but two parallel walls in between;
# its own map has every jamb where its drifted estimate put it, the peer's map where it is.
CORRIDOR = [((-12, -1), (12, -1)), ((-12, 1), (12, 1)), ((-12, -1), (-12, 1)), ((12, -1), (12, 1))]
CORRIDOR += [((x, 1), (x, 0.75)) for x in (-8.0, 0.0, 8.0)]
CORRIDOR += [((x + 4, -1), (x + 4, -0.75)) for x in (-8.0, 0.0)]


def _corridor_run(with_colony: bool) -> float:
    n = 220
    truth = np.column_stack([np.linspace(-10.5, 10.5, n), np.zeros(n), np.zeros(n)])
    odo = synthesise(truth, OdometryNoise(0.02, 0.01, 0.002, 0.06, 0.0), seed=2)
    peers = colony_map(
        _wall_points(CORRIDOR), planar=True, height=0.0, centre=np.zeros(2), radius=30.0
    )
    rng = np.random.default_rng(3)
    loc = ScanLocaliser(planar=True)
    errors = []
    for p, o in zip(truth, odo, strict=True):
        scan = _segments_scan(p, CORRIDOR, noise=0.01, rng=rng)
        scan = scan[np.linalg.norm(scan[:, :2], axis=1) <= 1.5]
        pose = loc.step(scan, o, colony=peers if with_colony else None).pose
        errors.append(float(np.linalg.norm(pose[:2] - p[:2])))
    return float(np.sqrt(np.mean(np.square(errors))))


def test_a_short_range_robot_in_a_corridor_localises_better_on_the_peers_map() -> None:
    alone, together = _corridor_run(False), _corridor_run(True)
    assert alone > 0.2  # the scale error of odometry is not visible in the robot's own map
    assert together < 0.5 * alone


def test_a_fix_from_a_moment_ago_is_carried_to_the_present() -> None:
    loc = _drifted(np.array([0.0, 0.0, 0.0]), 0.3)
    loc.history.append((10.0, np.array([0.0, 0.0, 0.0])))
    loc.ekf.kf.x = np.array([[1.0], [0.0], [0.0]])  # the filter has moved 1 m along x since
    # At t = 10 the camera saw the robot 0.2 m further left than it believed: so it is now too.
    assert loc.fix(np.array([0.0, 0.2, 0.0]), np.diag([1e-4, 1e-4, 1e-4]), 10.05) is True
    # Kalman gain 0.09 / (0.09 + 0.01 + 1e-4): prior 0.3 m, the fix widened by 0.1 m/sqrt(m) x 1 m
    np.testing.assert_allclose(loc.ekf.pose, [1.0, 0.2 * 0.09 / 0.1001, 0.0], atol=1e-3)
    assert not loc.ahead(10.1)
    assert loc.ahead(12.0)  # seen after our last step: the daemon keeps it for later
    assert loc.fix(np.zeros(3), np.eye(3) * 1e-4, 12.0) is None  # no step near that time
    assert (loc.fix_accepted, loc.fix_stale) == (1, 1)


def test_a_fix_far_from_a_confident_estimate_is_refused() -> None:
    loc = _drifted(np.array([2.0, 1.0, 0.5]), 0.02)
    loc.history.append((3.0, np.array([2.0, 1.0, 0.5])))
    assert loc.fix(np.array([2.5, 1.0, 0.5]), np.diag([1e-4, 1e-4, 1e-3]), 3.0) is False
    np.testing.assert_allclose(loc.ekf.pose, [2.0, 1.0, 0.5])
    assert loc.fix_rejected == 1


def test_a_colony_map_that_keeps_disagreeing_is_dropped_until_the_alignment_changes() -> None:
    truth = np.array([0.4, -0.5, 0.3])
    shifted = _wall_points(ROOM) + np.array([0.4, 0.0, 0.0])
    wrong = colony_map(
        shifted, planar=True, height=0.0, centre=np.zeros(2), radius=10.0, alignment=b"a"
    )
    loc = _drifted(truth, 0.03)
    scan = _segments_scan(truth, ROOM)
    for _ in range(15):
        loc.step(scan, np.zeros(3), colony=wrong)
    assert loc.colony_rejected == 10 and loc.colony_suspended == 5  # tried 10 times, then not
    np.testing.assert_allclose(loc.ekf.pose[:2], truth[:2], atol=0.01)
    right = colony_map(
        _wall_points(ROOM), planar=True, height=0.0, centre=np.zeros(2), radius=10.0, alignment=b"b"
    )
    assert loc.step(scan, np.zeros(3), colony=right).colony_fused  # a new alignment: used again


def test_a_peers_free_space_orients_its_map_so_a_walls_far_face_is_not_matched() -> None:
    from tests.voxel.localisation.test_scan_match import THIN_WALL
    from voxel.localisation import se2
    from voxel.localisation.scan_match import match

    # The peer saw the thin wall from the left only: its map holds the left face, and the
    # free space it knows is left of the wall. The robot, truly at x = 1, sees the right face.
    left_face, far_wall = THIN_WALL[0], THIN_WALL[2]
    seen = _wall_points([left_face, far_wall])

    def free(points: np.ndarray) -> np.ndarray:
        return (points[:, 0] < -0.07) & (np.abs(points[:, 1]) < 2.95)

    truth = np.array([1.0, 0.0, 0.0])
    scan = _segments_scan(truth, THIN_WALL, beams=1440)
    cut = dict(planar=True, height=0.0, centre=np.zeros(2), radius=10.0)
    sided = colony_map(seen, free=free, step=0.1, **cut)
    assert sided.oriented and len(sided) > 100
    assert np.all(sided.normals[np.abs(sided.points[:, 0] + 0.05) < 0.01][:, 0] < -0.99)
    kept = match(scan, sided, se2.to_matrix(truth))
    assert kept.ok and se2.from_matrix(kept.pose)[0] == pytest.approx(1.0, abs=1e-3)
    unsigned = colony_map(seen, **cut)  # the same cut without the peer's free space
    assert not unsigned.oriented
    pulled = match(scan, unsigned, se2.to_matrix(truth))
    assert se2.from_matrix(pulled.pose)[0] == pytest.approx(0.9, abs=0.01)  # through the wall
    # A cut whose surfaces mostly have no free side keeps unsigned normals.
    blind = colony_map(seen, free=lambda p: np.zeros(len(p), bool), **cut)
    assert not blind.oriented and len(blind) == len(unsigned)


def test_a_poorly_aligned_colony_map_weighs_what_its_alignment_is_worth() -> None:
    # The peer's map is 8 cm off (its alignment, honestly, is known to 10 cm); the robot is
    # right and knows it to 2 cm, and keeps no map of its own (nothing else holds it). Scan
    # after scan matches the map 8 cm off: the alignment's error is one error, counted once.
    # (Fused as 30 independent measurements, it dragged the robot 7.5 cm.)
    truth = np.array([0.4, -0.5, 0.3])
    off = colony_map(
        _wall_points(ROOM) + np.array([0.08, 0.0, 0.0]),
        planar=True,
        height=0.0,
        centre=np.zeros(2),
        radius=10.0,
        covariance=np.diag([0.1**2, 0.1**2, math.radians(1.0) ** 2]),
        alignment=b"a",
    )
    loc = _drifted(truth, 0.02)
    loc.local.wants = lambda pose: False  # type: ignore[method-assign]
    scan = _segments_scan(truth, ROOM)
    for _ in range(30):
        loc.step(scan, np.zeros(3), colony=off)
    assert loc.colony_accepted == 30  # every match fused, none refused
    np.testing.assert_allclose(loc.ekf.pose[:2], truth[:2], atol=0.01)
    assert loc.ekf.offset is not None
    assert loc.ekf.offset.value[0] == pytest.approx(0.08, abs=0.02)  # it learnt the map's error


def test_a_2d_scanners_map_corrects_a_3d_robot_as_vertical_walls() -> None:
    # The peer is a 2D LiDAR: its map is one row of voxels per wall, at the scan height. A
    # depth robot (3D points, walls from the floor up) matches against it: without taking the
    # rows as traces of vertical walls every normal points up and the match constrains nothing.
    truth = np.array([0.4, -0.5, 0.3])
    rows = _wall_points(ROOM, spacing=0.1, height=0.3)
    peers = colony_map(rows, planar=False, height=0.3, centre=np.zeros(2), radius=10.0, cell=0.1)
    assert peers.tree is not None
    assert np.max(np.abs(peers.normals[:, 2])) < 1e-6  # horizontal, across each wall
    flat = _segments_scan(truth, ROOM)
    scan = np.concatenate([flat + np.array([0.0, 0.0, z]) for z in (0.1, 0.25, 0.35, 0.6)])
    loc = ScanLocaliser(planar=False)
    loc.ekf = PlanarEkf(truth + np.array([0.12, -0.1, 0.03]), np.diag([0.04, 0.04, 0.01]))
    loc.last_odometry = np.zeros(3)
    step = loc.step(scan, np.zeros(3), colony=peers)
    assert step.colony_fused and loc.colony_failed == 0
    np.testing.assert_allclose(step.pose, truth, atol=0.02)


def test_a_3d_peers_floor_strip_is_not_taken_for_a_wall() -> None:
    # Two peers: a 2D scanner (one row of voxels per wall, a slice) and a 3D sensor that sees
    # the floor as well (a CCTV or a depth camera; at a grazing angle its floor is mapped in
    # strips a few voxels wide). A strip two cells wide has no height, as the scanner's rows
    # have, and passes the line's flatness test (0.8). Taken for a wall it put phantom walls on
    # the floor, and the robot's own floor points beside it pulled its match 7 cm off across
    # the strip and 1.1 degrees in yaw. Only the slice's rows are traces: the match lands on the
    # truth, every wall row stays.
    truth = np.array([0.4, -0.5, 0.3])
    rows = _wall_points(ROOM, spacing=0.1, height=0.3)
    gx, gy = np.meshgrid(np.arange(-3.5, 3.5, 0.1), [-2.2, -2.1])
    strip = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    cut = {"planar": False, "height": 0.3, "centre": np.zeros(2), "radius": 10.0, "cell": 0.1}
    slices = np.concatenate([np.ones(len(rows), bool), np.zeros(len(strip), bool)])
    peers = colony_map(np.concatenate([rows, strip]), slices=slices, **cut)
    walls = np.abs(peers.normals[:, 2]) < 0.5
    assert not np.any(walls & (peers.points[:, 2] < 0.1))  # no wall on the floor
    alone = colony_map(rows, **cut)
    assert np.count_nonzero(walls & (peers.points[:, 2] > 0.2)) == len(alone)  # rows all kept
    flat = _segments_scan(truth, ROOM)
    fx, fy = np.meshgrid(np.arange(-1.5, 2.0, 0.05), np.arange(-2.05, -1.6, 0.05))
    floor = np.column_stack([fx.ravel(), fy.ravel(), np.zeros(fx.size)])  # north of the strip
    back = np.linalg.inv(se2.to_matrix(truth))
    scan = np.concatenate(
        [
            *(flat + np.array([0.0, 0.0, z]) for z in (0.1, 0.25, 0.35, 0.6)),
            floor @ back[:3, :3].T + back[:3, 3],
        ]
    )
    loc = ScanLocaliser(planar=False)
    loc.ekf = PlanarEkf(truth + np.array([0.12, -0.1, 0.03]), np.diag([0.04, 0.04, 0.01]))
    loc.last_odometry = np.zeros(3)
    step = loc.step(scan, np.zeros(3), colony=peers)
    assert step.colony is not None and step.colony_fused
    np.testing.assert_allclose(se2.from_matrix(step.colony.pose), truth, atol=0.005)
    with pytest.raises(LocalisationError, match="a slice flag per surface point"):
        colony_map(rows, slices=np.ones(3, bool), **cut)


def test_a_peer_that_gets_lost_widens_its_maps_error_without_a_new_alignment() -> None:
    # The peer's map is right and the peer sure of itself (1 cm): the robot (right, 2 cm) learns
    # that the map's error is small. Then the peer gets lost: its map near the robot is now
    # 15 cm off and it says so (20 cm), the alignment unchanged. The map's error follows what
    # the peer says (`widen_offset`): its matches are taken at that worth, neither refused for
    # disagreeing with what the filter had learnt nor dragging the robot onto the lost map.
    truth = np.array([0.4, -0.5, 0.3])
    sure = np.diag([0.01**2, 0.01**2, math.radians(0.1) ** 2])
    lost = np.diag([0.2**2, 0.2**2, math.radians(0.1) ** 2])
    cut = {"planar": True, "height": 0.0, "centre": np.zeros(2), "radius": 10.0}
    right = colony_map(_wall_points(ROOM), covariance=sure, alignment=b"a", **cut)
    off = colony_map(
        _wall_points(ROOM) + np.array([0.15, 0.0, 0.0]), covariance=lost, alignment=b"a", **cut
    )
    loc = _drifted(truth, 0.02)
    loc.local.wants = lambda pose: False  # type: ignore[method-assign]
    scan = _segments_scan(truth, ROOM)
    for _ in range(10):
        loc.step(scan, np.zeros(3), colony=right)
    assert loc.colony_accepted == 10 and loc.ekf.offset is not None
    learnt = loc.ekf.offset.covariance
    assert learnt[0, 0] < sure[0, 0]
    loc.step(scan, np.zeros(3), colony=off)
    widened = loc.ekf.offset
    assert widened is not None
    np.testing.assert_allclose(widened.accounted, lost)
    assert loc.colony_accepted == 11  # fused at its worth, not refused
    for _ in range(19):
        loc.step(scan, np.zeros(3), colony=off)
    assert (loc.colony_accepted, loc.colony_rejected, loc.colony_suspended) == (30, 0, 0)
    np.testing.assert_allclose(loc.ekf.pose[:2], truth[:2], atol=0.01)
    assert loc.ekf.offset.value[0] == pytest.approx(0.15, abs=0.03)  # it learnt the map's error


def test_a_walking_offset_follows_a_peer_maps_error_that_changes_along_the_way() -> None:
    # The peer's map is right where the robot learns its error, and 5 cm off in x 1.5 m
    # further on (its error differs place by place), the alignment and its stated covariance
    # unchanged. The robot's odometry and own map hold it to ~1 cm. Rigid (no walk): the learnt
    # offset pins pose + offset to millimetres, and the 5 cm are refused by the gate (without
    # it they would go into the pose: test_ekf.py's known answer). With the walk
    # (`OffsetWalk`: the distance driven since the last colony match widens the offset) the
    # new place's error goes into the offset and the pose stays.
    start = np.array([-1.5, 0.5, 0.0])
    there = se2.compose(start, np.array([1.5, 0.0, 0.0]))
    sure = np.diag([0.01**2, 0.01**2, math.radians(0.1) ** 2])
    cut = {"planar": True, "height": 0.0, "centre": np.zeros(2), "radius": 10.0}
    right = colony_map(_wall_points(ROOM), covariance=sure, alignment=b"a", **cut)
    off = colony_map(
        _wall_points(ROOM) + np.array([0.05, 0.0, 0.0]), covariance=sure, alignment=b"a", **cut
    )
    results = {}
    for walk in (None, OffsetWalk()):
        loc = ScanLocaliser(
            planar=True,
            params=ScanParams(colony_walk=walk),
            motion=MotionNoise(trans=0.003, rot=0.003, rot_per_m=0.003, still=1e-8),
        )
        loc.ekf = PlanarEkf(start, covariance=np.diag([0.01**2, 0.01**2, 1e-6]), motion=loc.motion)
        loc.last_odometry = np.zeros(3)
        loc.local.wants = lambda pose: False  # type: ignore[method-assign]
        for _ in range(10):
            loc.step(_segments_scan(start, ROOM), np.zeros(3), colony=right)
        assert loc.colony_accepted == 10
        for i in range(1, 16):  # 1.5 m on, no colony map in reach
            loc.step(_segments_scan(start, ROOM), np.array([0.1 * i, 0.0, 0.0]))
        for _ in range(5):
            loc.step(_segments_scan(there, ROOM), np.array([1.5, 0.0, 0.0]), colony=off)
        assert loc.ekf is not None and loc.ekf.offset is not None
        results[walk is None] = (loc.ekf.pose, loc.ekf.offset.value, loc.colony_accepted)
    pose, offset, accepted = results[False]
    assert accepted == 15
    np.testing.assert_allclose(pose[:2], there[:2], atol=0.01)
    assert offset[0] == pytest.approx(0.05, abs=0.015)
    pose, _, accepted = results[True]
    assert accepted == 10  # rigid: every match at the new place refused by the gate
