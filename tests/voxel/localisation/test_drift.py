"""A peer's drift from its reports (known answers): the growth of its reported variances per
metre of its path, floored and capped; and the localiser walking a cut by it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.voxel.localisation.test_colony_map import _wall_points
from tests.voxel.localisation.test_scan_match import ROOM, _segments_scan
from voxel.errors import LocalisationError
from voxel.localisation import se2
from voxel.localisation.colony_map import colony_map
from voxel.localisation.drift import CAP, FLOOR, OffsetWalk, PeerDrift, widest
from voxel.localisation.ekf import MotionNoise, PlanarEkf
from voxel.localisation.localiser import ScanLocaliser, ScanParams


def _straight(q_trans: float, q_yaw: float, metres: int = 10) -> PeerDrift:
    """A peer driving straight along x, reporting every metre a covariance grown by `q_trans`
    (m^2) and `q_yaw` (rad^2) per metre."""
    drift = PeerDrift()
    for s in range(metres + 1):
        drift.add(np.array([float(s), 0.0, 0.0]), np.diag([q_trans * s, q_trans * s, q_yaw * s]))
    return drift


def test_the_walk_is_the_square_root_of_the_variance_growth_per_metre() -> None:
    walk = _straight(0.02**2, 0.004**2).walk()
    assert walk is not None
    assert (walk.trans, walk.yaw) == (pytest.approx(0.02), pytest.approx(0.004))


def test_a_turn_counts_as_lever_metres_per_radian() -> None:
    drift = PeerDrift(lever=1.0)
    for i in range(5):  # turning on the spot, half a radian a report: 2 m of path in all
        drift.add(np.array([0.0, 0.0, 0.5 * i]), np.diag([1e-4 * i, 1e-4 * i, 1e-6 * i]))
    assert drift.path == pytest.approx(2.0)
    walk = drift.walk()
    assert walk is not None and walk.trans == pytest.approx(math.sqrt(1e-4 / 0.5))


def test_a_sawtooth_of_growth_and_matches_gives_its_trend() -> None:
    # Each metre's odometry adds 4e-4 m^2 and a match takes back 3e-4: the trend is 1e-4 per
    # metre, whatever the sawtooth.
    drift, v = PeerDrift(), 0.0
    for s in range(21):
        for half, dv in ((0.0, 4e-4), (0.5, -3e-4)):
            v += dv
            drift.add(np.array([s + half, 0.0, 0.0]), np.diag([v, v, 1e-6]))
    walk = drift.walk()
    assert walk is not None and walk.trans == pytest.approx(0.01, rel=0.05)


def test_a_peer_sure_of_itself_walks_at_the_floor_and_a_lost_one_at_the_cap() -> None:
    steady = _straight(0.0, 0.0).walk()
    assert steady is not None and (steady.trans, steady.yaw) == (FLOOR.trans, FLOOR.yaw)
    shrinking = PeerDrift()  # a peer that got surer as it drove (fixes): no evidence of drift
    for s in range(5):
        shrinking.add(np.array([float(s), 0.0, 0.0]), np.eye(3) * (0.1 - 0.01 * s))
    assert shrinking.walk() == OffsetWalk(FLOOR.trans, FLOOR.yaw)
    lost = _straight(1.0, 1.0).walk()
    assert lost is not None and (lost.trans, lost.yaw) == (CAP.trans, CAP.yaw)


def test_too_little_path_or_too_few_reports_tell_nothing() -> None:
    assert _straight(1e-4, 1e-6, metres=1).walk() is None  # 1 m of path
    drift = PeerDrift()
    drift.add(np.zeros(3), np.eye(3) * 1e-4)
    drift.add(np.array([5.0, 0.0, 0.0]), np.eye(3) * 2e-4)
    assert drift.walk() is None  # two reports


def test_a_bad_report_is_refused_and_changes_nothing() -> None:
    drift = _straight(1e-4, 1e-6)
    before = drift.walk()
    with pytest.raises(LocalisationError, match="finite pose"):
        drift.add(np.array([np.nan, 0.0, 0.0]), np.eye(3))
    with pytest.raises(LocalisationError, match="covariance"):
        drift.add(np.zeros(3), np.eye(2))
    assert drift.walk() == before


def test_a_cut_of_several_peers_walks_by_the_fastest() -> None:
    slow, fast = OffsetWalk(0.01, 0.01), OffsetWalk(0.05, 0.001)
    assert widest([slow, fast]) == fast and widest([]) is None


def test_the_localiser_walks_a_cut_by_its_peers_drift_when_asked() -> None:
    # As test_colony_map's walking offset: a peer map right where the robot learns its error
    # and 5 cm off 1.5 m on. A cut carrying a fast peer's drift (the constant walk's density)
    # follows it when `colony_peer_walk`; the same cut with the switch off is rigid (refused);
    # a cut of a peer that drifts at the floor is near rigid (refused too).
    start = np.array([-1.5, 0.5, 0.0])
    there = se2.compose(start, np.array([1.5, 0.0, 0.0]))
    sure = np.diag([0.01**2, 0.01**2, math.radians(0.1) ** 2])
    cut = {"planar": True, "height": 0.0, "centre": np.zeros(2), "radius": 10.0}
    accepted = {}
    for name, walk, on in (
        ("fast", OffsetWalk(), True),
        ("off", OffsetWalk(), False),
        ("floor", FLOOR, True),
    ):
        right = colony_map(_wall_points(ROOM), covariance=sure, alignment=b"a", walk=walk, **cut)
        off = colony_map(
            _wall_points(ROOM) + np.array([0.05, 0.0, 0.0]),
            covariance=sure,
            alignment=b"a",
            walk=walk,
            **cut,
        )
        loc = ScanLocaliser(
            planar=True,
            params=ScanParams(colony_peer_walk=on),
            motion=MotionNoise(trans=0.003, rot=0.003, rot_per_m=0.003, still=1e-8),
        )
        assert loc.walk_of(right) == (walk if on else None)
        loc.ekf = PlanarEkf(start, covariance=np.diag([0.01**2, 0.01**2, 1e-6]), motion=loc.motion)
        loc.last_odometry = np.zeros(3)
        loc.local.wants = lambda pose: False  # type: ignore[method-assign]
        for _ in range(10):
            loc.step(_segments_scan(start, ROOM), np.zeros(3), colony=right)
        for i in range(1, 16):
            loc.step(_segments_scan(start, ROOM), np.array([0.1 * i, 0.0, 0.0]))
        for _ in range(5):
            loc.step(_segments_scan(there, ROOM), np.array([1.5, 0.0, 0.0]), colony=off)
        accepted[name] = loc.colony_accepted
        if name == "fast":
            np.testing.assert_allclose(loc.ekf.pose[:2], there[:2], atol=0.01)
    assert accepted == {"fast": 15, "off": 10, "floor": 10}


def test_without_a_peer_drift_the_constant_walk_stands_in() -> None:
    cut = colony_map(_wall_points(ROOM), planar=True, height=0.0, centre=np.zeros(2), radius=10.0)
    loc = ScanLocaliser(planar=True, params=ScanParams(colony_peer_walk=True))
    assert loc.walk_of(cut) is None
    loc.params = ScanParams(colony_peer_walk=True, colony_walk=OffsetWalk())
    assert loc.walk_of(cut) == OffsetWalk()


def test_own_aliasing_widens_what_each_own_map_match_claims() -> None:
    # The same path through the room, with and without a 4 cm standard deviation of aliasing on
    # each own-map match: the filter's position variance is larger with it, and the estimate
    # stays on the truth (the scans are exact).
    variances = {}
    for aliasing in (0.0, 0.04**2):
        loc = ScanLocaliser(planar=True, params=ScanParams(own_aliasing=aliasing))
        for i in range(30):
            pose = np.array([-1.5 + 0.1 * i, 0.5, 0.0])
            loc.step(_segments_scan(pose, ROOM), pose)
        assert loc.ekf is not None
        np.testing.assert_allclose(loc.ekf.pose[:2], [1.4, 0.5], atol=0.02)
        variances[aliasing] = float(loc.ekf.covariance[0, 0])
    assert variances[0.04**2] > 2 * variances[0.0]
