"""The colony map a daemon cuts for its estimator: peers' occupied voxels in our frame, made
again only when an alignment changes or the robot's scans would reach past the cut."""

from __future__ import annotations

import numpy as np
import pytest

from colonyd.alignment import ColonyFrame
from colonyd.colonymap import ColonyMaps, PeerError, cut_error, peer_map_error, peer_surfaces
from colonyd.inbox import check_pose_covariance
from colonyd.layers import Layers
from voxel.delta import Delta
from voxel.errors import LocalisationError
from voxel.localisation import frame_error
from voxel.localisation.ekf import PlanarEkf


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


def _turn(dx: float, yaw_deg: float) -> np.ndarray:
    t = np.eye(4)
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    t[:2, :2] = [[c, -s], [s, c]]
    t[0, 3] = dx
    return t


POSE = np.diag([0.01, 0.04, 1e-4])  # a peer's x, y, yaw covariance, its frame


def test_a_peers_pose_error_about_the_cut_is_its_covariance_moved_into_our_frame() -> None:
    # the cut at our origin, the peer's frame 1.03 m along x: its error about the cut is itself
    np.testing.assert_allclose(peer_map_error(POSE, _turn(1.03, 0), np.zeros(2)), POSE, atol=1e-15)
    # about a cut 2 m along x: a yaw error about it moves our origin sideways by 2 m x the angle
    want = np.array([[0.01, 0.0, 0.0], [0.0, 0.04 + 4e-4, -2e-4], [0.0, -2e-4, 1e-4]])
    np.testing.assert_allclose(peer_map_error(POSE, _turn(1.03, 0), np.array([2.0, 0.0])), want)
    # a peer frame turned 90 degrees: its x error is our y error
    turned = peer_map_error(POSE, _turn(0.0, 90), np.zeros(2))
    np.testing.assert_allclose(turned, np.diag([0.04, 0.01, 1e-4]), atol=1e-15)


def test_the_cuts_error_is_the_worst_peers_alignment_plus_pose_floored() -> None:
    small, big, zero = np.diag([1e-4, 1e-4, 1e-6]), np.diag([0.01, 0.02, 1e-4]), np.zeros((3, 3))
    errors = {
        "a": PeerError(small, big, None),  # the largest: its alignment plus its pose
        "b": PeerError(big, zero, None),
        "c": PeerError(small, small, None),
    }
    np.testing.assert_allclose(cut_error(errors), small + big)
    # a peer claiming certainty, aligned perfectly: no better than the floor
    np.testing.assert_allclose(cut_error({"d": PeerError(zero, zero, zero)}), frame_error.FLOOR)


def test_a_pose_covariance_checked_to_a_tolerance_gives_the_filter_a_covariance() -> None:
    # A Pose whose z variance (1e4) dwarfs the rest passes the check with its x, y, yaw block
    # indefinite (eigenvalue -0.004, within 1e-6 of 1e4): the cut's error is still a covariance,
    # which the estimator's filter takes; unprojected, the filter refuses it.
    planar = np.array([[0.01, 0.014, 0.0], [0.014, 0.01, 0.0], [0.0, 0.0, 1e-4]])
    cov = np.zeros((6, 6))
    cov[2, 2] = 1e4
    cov[np.ix_([0, 1, 5], [0, 1, 5])] = planar
    reported = frame_error.planar(check_pose_covariance(cov.ravel()))
    pose = peer_map_error(reported, _turn(1.03, 0), np.array([1.0, 2.0]))
    assert np.linalg.eigvalsh(pose).min() < -1e-3
    error = cut_error({"peer": PeerError(frame_error.FLOOR, pose, reported)})
    assert np.linalg.eigvalsh(error).min() > 0
    f = PlanarEkf(np.zeros(3))
    f.reset_offset(error)
    f.widen_offset(error * 2)
    with pytest.raises(LocalisationError, match="semi-definite"):
        f.widen_offset(frame_error.FLOOR + pose)


def test_the_cut_carries_the_peers_reported_pose_covariance_and_follows_it() -> None:
    layers = _layers()
    frame = ColonyFrame(
        "me", {"me": np.eye(4), "peer": _turn(1.03, 0)}, {"me": np.zeros((3, 3)), "peer": POSE / 4}
    )
    maps = ColonyMaps("me", planar=True, height=0.3, sensor_range=2.0)
    alone = maps.refresh(layers, frame, np.eye(4))  # the peer sent no Pose: its alignment's
    assert alone is not None
    np.testing.assert_allclose(alone.covariance, POSE / 4, atol=1e-12)
    cut = maps.refresh(layers, frame, np.eye(4), {"peer": POSE})
    assert cut is not None and cut.points is alone.points  # the same surfaces, kept
    np.testing.assert_allclose(cut.covariance, POSE / 4 + POSE, atol=1e-12)
    assert maps.refresh(layers, frame, np.eye(4), {"peer": POSE}) is cut  # nothing changed
    report = maps.report()
    assert report is not None
    np.testing.assert_allclose(report["covariance"], POSE * 1.25, atol=1e-12)
    part = report["peers"]["peer"]
    np.testing.assert_allclose(part["alignment_covariance"], POSE / 4, atol=1e-12)
    np.testing.assert_allclose(part["pose_covariance"], POSE, atol=1e-12)
    np.testing.assert_allclose(part["reported_pose_covariance"], POSE, atol=1e-12)
    lost = maps.refresh(layers, frame, np.eye(4), {"peer": POSE * 100, "stranger": POSE})
    assert lost is not None and lost.points is alone.points
    np.testing.assert_allclose(lost.covariance, POSE / 4 + POSE * 100, atol=1e-12)


def test_the_cut_walks_by_its_peers_drift_and_follows_it() -> None:
    from voxel.localisation.drift import OffsetWalk

    layers = _layers()
    maps = ColonyMaps("me", planar=True, height=0.3, sensor_range=2.0)
    frame = _frame(1.03)
    cut = maps.refresh(layers, frame, np.eye(4))
    assert cut is not None and cut.walk is None  # no drift known: none
    slow, fast = OffsetWalk(0.01, 0.002), OffsetWalk(0.04, 0.01)
    walking = maps.refresh(layers, frame, np.eye(4), walks={"peer": slow, "stranger": fast})
    assert walking is not None and walking.walk == slow  # a stranger's drift is not this cut's
    assert walking.points is cut.points  # the same surfaces
    later = maps.refresh(layers, frame, np.eye(4), walks={"peer": fast})
    assert later is not None and later.walk == fast
    report = maps.report()
    assert report is not None and report["walk"] == {"trans": 0.04, "yaw": 0.01}


def test_the_cut_holds_a_replicas_surface_points_not_its_voxel_centres() -> None:
    from protocol.deltacodec import decode_delta, encode_delta
    from voxel.grid import VoxelGrid

    # the peer's own grid: a wall at y = 2.013, its voxels' centres at 2.05
    origin = VoxelGrid(0.1, surface=True)
    x = np.linspace(-1.5, 1.5, 601)
    rng = np.random.default_rng(0)
    for t in range(5):
        wall = np.column_stack([x, 2.013 + rng.normal(0, 0.003, x.size), np.full(x.size, 0.3)])
        origin.integrate(wall, np.array([0.0, 0.0, 0.3]), time=float(t))
    layers = Layers("me", 0.1)
    sent = decode_delta(encode_delta(origin.delta_since(0)))  # the wire, as gossip carries it
    applied = layers.get("peer").offer(1, 0, 1, sent)
    assert applied.outcome == "applied"
    keys = origin.occupied_keys()
    replica = layers.get("peer").grid
    assert np.array_equal(replica.surface_points(keys), origin.surface_points(keys))
    assert replica.content_equal(origin)  # bit for bit, the surface codes included
    cut = ColonyMaps("me", planar=True, height=0.3, sensor_range=2.0).refresh(
        layers, _frame(0.0), np.eye(4)
    )
    assert cut is not None and len(cut) > 20
    assert np.abs(cut.points[:, 1] - 2.013).max() < 0.002  # centres would be 37 mm off


def test_a_peer_map_of_one_height_is_a_slice_and_a_3d_one_is_not() -> None:
    layers = _layers()  # a wall at one height: a 2D scanner's map
    seen = layers.get("seen")  # a floor and a wall 1 m high: a 3D sensor's
    x = np.arange(-30, 30)
    floor = np.column_stack([x, np.full(len(x), 10), np.zeros(len(x), int)])
    wall = np.column_stack([np.zeros(10, int), np.full(10, 15), np.arange(10)])
    keys = np.concatenate([floor, wall])
    seen.grid.apply(Delta(0.1, 0, 1, keys, np.full(len(keys), 2.0), np.ones(len(keys))))
    peers = [(layers.get("peer"), np.eye(4)), (seen, np.eye(4))]
    points, slices = peer_surfaces(peers)
    assert len(points) == len(slices) == 60 + 70
    assert slices[:60].all() and not slices[60:].any()


def test_a_3d_peer_map_still_one_flat_band_is_not_a_slice() -> None:
    """Early on, a 3D sensor's map can be one band (its first hits on the floor): too few
    surfaces to tell it from a 2D scanner's, so it is not called a slice (its band raised into
    walls across every height would be phantom walls)."""
    layers = Layers("me", 0.1)
    early = layers.get("early")
    x = np.arange(-15, 15)
    floor = np.column_stack([x, np.full(len(x), 10), np.zeros(len(x), int)])  # 30 floor hits
    early.grid.apply(Delta(0.1, 0, 1, floor, np.full(len(x), 2.0), np.ones(len(x))))
    points, slices = peer_surfaces([(early, np.eye(4))])
    assert len(points) == 30 and not slices.any()


def test_a_2d_peer_map_with_one_off_height_hit_is_still_a_slice() -> None:
    """One hit off the scan plane (a tilt, a reflection) does not make a 2D scanner's map 3D:
    its span leaves the outermost heights out."""
    layers = _layers()  # a wall of 60 voxels at one height
    peer = layers.get("peer")
    stray = np.array([[5, 20, 9]])  # 0.6 m above the scan plane
    peer.grid.apply(Delta(0.1, 1, 2, stray, np.full(1, 2.0), np.ones(1)))
    points, slices = peer_surfaces([(peer, np.eye(4))])
    assert len(points) == 61 and slices.all()
    assert np.ptp(points[:, 2]) > 0.5  # the whole map's span is 3D, its trimmed one is not
