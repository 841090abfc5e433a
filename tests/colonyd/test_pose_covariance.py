"""A peer's Pose covariance is hostile input: checked (finite, symmetric, positive semi-definite,
bounded) before a daemon keeps it for its colony map; a bad one is refused and counted, with no
side effect (unit tests of the check, then against a real daemon)."""

from __future__ import annotations

import numpy as np
import pytest

from colonyd.alignment import Edge, offer_of
from colonyd.errors import WireError
from colonyd.frames import Sender, colony_key, frame_of
from colonyd.inbox import check_pose_covariance
from protocol import Heartbeat, Pose, VoxelDelta
from protocol.identity import Signer
from protocol.keyexpr import topic_key
from voxel.delta import Delta
from voxel.localisation import frame_error

SECRET = "correct horse battery staple"


def _cov(planar: np.ndarray) -> list[float]:
    cov = np.zeros((6, 6))
    cov[np.ix_([0, 1, 5], [0, 1, 5])] = planar
    return [float(v) for v in cov.ravel()]


GOOD = np.array([[0.04, 0.01, 0.0], [0.01, 0.09, 0.001], [0.0, 0.001, 0.0004]])
ASYMMETRIC = GOOD + np.array([[0, 0.02, 0], [0, 0, 0], [0, 0, 0]])
INDEFINITE = np.array([[0.04, 0.1, 0.0], [0.1, 0.04, 0.0], [0.0, 0.0, 0.0004]])  # eigen -0.06
HUGE = np.diag([1e9, 0.01, 0.0004])
NEGATIVE = np.diag([-0.01, 0.01, 0.0004])


def test_a_pose_covariance_is_kept_only_when_it_is_one() -> None:
    np.testing.assert_array_equal(check_pose_covariance(_cov(GOOD)).reshape(36), _cov(GOOD))
    assert not check_pose_covariance([0.0] * 36).any()  # a sender without one
    rounded = GOOD.copy()
    rounded[0, 1] += 1e-12  # its filter's rounding, not an asymmetry
    check_pose_covariance(_cov(rounded))
    for bad, says in (
        (ASYMMETRIC, "symmetric"),
        (INDEFINITE, "semi-definite"),
        (HUGE, "variances"),
        (NEGATIVE, "variances"),
    ):
        with pytest.raises(WireError, match=says) as caught:
            check_pose_covariance(_cov(bad))
        assert caught.value.reason == "bad-pose-covariance"
    with pytest.raises(WireError, match="36 finite"):
        check_pose_covariance([float("nan")] + [0.0] * 35)
    with pytest.raises(WireError, match="36 finite"):
        check_pose_covariance([0.0] * 35)


def _pose(sender: Sender, x: float, planar: np.ndarray) -> bytes:
    t = np.eye(4)
    t[0, 3] = x
    return sender.encode(
        Pose(
            **sender.header(),
            frame_id=frame_of(sender.origin),
            **Pose.split_matrix(t),
            covariance=_cov(planar),
        )
    )


def _forged_member(colony):
    """A session on `colony` and a signed peer "peer" it announced, once b lists it."""
    colony.wait_members(1)
    s, ns, key = colony.session(), colony.namespace, colony_key(SECRET)
    peer = Sender("peer", 1, key=key, signer=Signer.generate())
    s.put(
        topic_key(ns, "peer", "heartbeat"),
        peer.encode(
            Heartbeat(
                **peer.header(), kind="robot", frame_id=frame_of("peer"), identity=peer.identity
            )
        ),
    )
    colony.wait_status(
        lambda rs: any(m["agent"] == "peer" for r in rs for m in r["members"]), agents=("b",)
    )
    return s, ns, peer


def test_a_hostile_pose_covariance_is_refused_counted_and_changes_nothing(make_colony):
    colony = make_colony("posecov", extra=["--colony-key", SECRET])
    colony.add("b")
    s, ns, peer = _forged_member(colony)
    pose_key = topic_key(ns, "peer", "pose")
    s.put(pose_key, _pose(peer, 1.0, GOOD))
    for x, bad in ((2.0, ASYMMETRIC), (3.0, INDEFINITE), (4.0, HUGE)):
        s.put(pose_key, _pose(peer, x, bad))

    def settled(reports: list[dict]) -> bool:
        return reports[0]["metrics"]["rejected"].get("bad-pose-covariance", 0) >= 3

    (b,) = colony.wait_status(settled, 30, agents=("b",))
    assert b["metrics"]["rejected"]["bad-pose-covariance"] == 3, b["metrics"]["rejected"]
    seen = next(m for m in b["members"] if m["agent"] == "peer")
    assert seen["pose"][0] == 1.0, seen  # the good Pose's, not a refused one's
    assert seen["pose_std_m"] == pytest.approx(np.sqrt(0.04 + 0.09)), seen


@pytest.mark.parametrize("peer_pose", [True, False])
def test_a_colony_map_holds_its_peers_reported_pose_covariance(make_colony, peer_pose):
    """A localising lidar robot aligned (by the peer's offer) with a peer that reports a known
    pose covariance: its status shows the colony map's covariance with the peer's in it (not
    with `colony_peer_pose` off)."""
    colony = make_colony("peercov", extra=["--colony-key", SECRET])
    spec = "sim:world=office,agent=lidar-1,frames=200,seed=1,odometry_noise=realistic"
    d = colony.add("b", [spec], start=False)
    d.env = {"COLONYD_COLONY_MAP_S": "0.3", "COLONYD_COLONY_PEER_POSE": str(peer_pose).lower()}
    d.start()
    s, ns, peer = _forged_member(colony)
    x = np.arange(-30, 30)  # a wall at y = 1.05 m, at the scan's height, in the peer's frame
    keys = np.column_stack([x, np.full(len(x), 10), np.full(len(x), 3)])
    wall = Delta(0.1, 0, 1, keys, np.full(len(x), 2.0), np.ones(len(x)))
    s.put(
        topic_key(ns, "peer", "delta"),
        peer.encode(VoxelDelta(**peer.header(), frame_id=frame_of("peer"), delta=wall)),
    )
    offered = np.diag([0.02**2, 0.03**2, 0.0, 0.0, 0.0, np.radians(0.5) ** 2])
    edge = Edge("peer", "b", np.eye(4), 1.0, 100, 0.02, offered, 0.0)
    s.put(topic_key(ns, "peer", "align"), peer.encode(offer_of(edge, peer.header())))
    s.put(topic_key(ns, "peer", "pose"), _pose(peer, 1.0, GOOD))

    def cut(reports: list[dict]) -> dict | None:
        entries = [v for k, v in reports[0]["localisation"].items() if k.startswith("sim:")]
        made = entries[0].get("colony_map") if entries else None
        part = (made or {}).get("peers", {}).get("peer")
        posed = any(m["agent"] == "peer" and m["pose_std_m"] for m in reports[0]["members"])
        if not part or not posed or (peer_pose and part["reported_pose_covariance"] is None):
            return None
        return made

    (b,) = colony.wait_status(lambda rs: cut(rs) is not None, 30, agents=("b",))
    made = cut([b])
    assert made is not None and made["sources"] == ["peer"] and made["points"] > 0, made
    part = made["peers"]["peer"]
    if not peer_pose:  # the Pose arrived (members), the colony map left it out
        assert part["reported_pose_covariance"] is None, part
        total = frame_error.floored(np.array(part["alignment_covariance"]))
        np.testing.assert_allclose(made["covariance"], total, atol=1e-9)
        return
    np.testing.assert_allclose(part["reported_pose_covariance"], GOOD, atol=1e-9)
    # its pose error about the cut's centre (identity alignment: our frame is the peer's)
    pose = frame_error.about(GOOD, np.array(made["centre"]))
    np.testing.assert_allclose(part["pose_covariance"], pose, atol=1e-6)
    total = frame_error.floored(np.array(part["alignment_covariance"]) + pose)
    np.testing.assert_allclose(made["covariance"], total, atol=1e-6)
    assert np.trace(np.array(made["covariance"])[:2, :2]) > 0.04 + 0.09, made  # more than GOOD
