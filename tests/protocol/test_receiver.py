"""Tests of protocol.receiver: counting, replay, key/origin check."""

from __future__ import annotations

import pytest

from protocol.codec import encode
from protocol.errors import AuthError, KeyExprError, ReplayError, TruncatedError
from protocol.messages import Pose
from protocol.receiver import Receiver
from tests.protocol.helpers import KEY


def _pose(seq: int, origin: str = "r1") -> Pose:
    return Pose(origin=origin, epoch=1, seq=seq, time=1.0, frame_id="map", position=(0.0, 0.0, 0.0))


def test_receiver_counts_accepted_and_rejected() -> None:
    rx = Receiver(key=KEY)
    frame = encode(_pose(1), key=KEY)
    assert isinstance(rx.decode(frame, "colony/c/r1/pose"), Pose)
    with pytest.raises(ReplayError):
        rx.decode(frame)
    with pytest.raises(AuthError):
        rx.decode(encode(_pose(2)))
    with pytest.raises(TruncatedError):
        rx.decode(b"CL")
    with pytest.raises(KeyExprError, match="belongs to origin 'r2'"):
        rx.decode(encode(_pose(3), key=KEY), "colony/c/r2/pose")
    assert rx.accepted == {"pose": 1}
    assert rx.rejected == {"replay": 1, "auth": 1, "truncated": 1, "keyexpr": 1}


def test_open_colony_receiver_has_no_replay_window() -> None:
    rx = Receiver()
    frame = encode(_pose(1))
    rx.decode(frame)
    rx.decode(frame)
    assert rx.accepted == {"pose": 2} and rx.replay is None
