"""A member's drift from its Pose messages (`Membership.pose_drifts`): the growth of its reported
covariance per metre of its reported path, on a real (loopback, no scouting) Zenoh session."""

from __future__ import annotations

import numpy as np
import pytest

from colonyd.membership import Membership
from colonyd.runtime import open_session, zenoh_config
from protocol import Heartbeat, Pose


def _pose(x: float, variance: float) -> Pose:
    t = np.eye(4)
    t[0, 3] = x
    cov = np.zeros((6, 6))
    cov[0, 0] = cov[1, 1] = variance
    cov[5, 5] = 1e-6
    return Pose(
        origin="peer",
        epoch=1,
        seq=1,
        time=0.0,
        frame_id="peer",
        **Pose.split_matrix(t),
        covariance=[float(v) for v in cov.ravel()],
    )


def test_a_members_drift_is_its_covariance_growth_per_metre_it_reported() -> None:
    session = open_session(zenoh_config(listen=["tcp/127.0.0.1:0"]))
    try:
        members = Membership(session, "drift-test", "me", lambda agent, event: None)
        assert not members.posed("peer", _pose(0.0, 0.0))  # not a member yet: nothing kept
        members.heard(
            "peer",
            Heartbeat(origin="peer", epoch=1, seq=1, time=0.0, kind="robot", frame_id="peer"),
        )
        for s in range(6):  # 1 m a report, 1e-4 m^2 more each metre
            assert members.posed("peer", _pose(float(s), 1e-4 * s))
        walk = members.pose_drifts()["peer"]
        assert walk.trans == pytest.approx(0.01)
    finally:
        session.close()
