"""Tests of protocol.receiver: counting, replay, key/origin check, no side effect on rejection."""

from __future__ import annotations

import pytest

from protocol.codec import encode
from protocol.errors import AuthError, KeyExprError, OwnOriginError, ReplayError, TruncatedError
from protocol.messages import Pose
from protocol.receiver import Receiver
from tests.protocol.helpers import KEY


def _pose(seq: int, origin: str = "r1", epoch: int = 1) -> Pose:
    return Pose(
        origin=origin, epoch=epoch, seq=seq, time=1.0, frame_id="map", position=(0.0, 0.0, 0.0)
    )


def test_receiver_counts_accepted_and_rejected() -> None:
    rx = Receiver(key=KEY)
    frame = encode(_pose(1), key=KEY)
    assert isinstance(rx.receive(frame, "colony/c/r1/pose"), Pose)
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


def test_frame_on_another_origins_key_moves_no_replay_window() -> None:
    """A forged frame (origin r1, far-ahead seq) on r2's key must not freeze r1's replication."""
    rx = Receiver(key=KEY)
    rx.receive(encode(_pose(1), key=KEY), "colony/c/r1/pose")
    forged = encode(_pose(100_001), key=KEY)
    with pytest.raises(KeyExprError):
        rx.decode(forged, "colony/c/r2/pose")
    for seq in range(2, 6):  # r1's real frames still pass
        rx.receive(encode(_pose(seq), key=KEY), "colony/c/r1/pose")
    assert rx.accepted == {"pose": 5} and rx.rejected == {"keyexpr": 1}


def test_decoded_but_not_accepted_frame_moves_no_window() -> None:
    rx = Receiver(key=KEY)
    rx.decode(encode(_pose(100_000), key=KEY))  # the caller refused it afterwards
    rx.decode(encode(_pose(9, epoch=9), key=KEY))  # nor does a refused higher epoch
    rx.receive(encode(_pose(1), key=KEY))
    assert rx.accepted == {"pose": 1} and not rx.rejected


def test_accept_refuses_a_frame_accepted_meanwhile() -> None:
    rx = Receiver(key=KEY)
    frame = encode(_pose(1), key=KEY)
    a, b = rx.decode(frame), rx.decode(frame)  # two threads got the same frame
    rx.accept(a)
    with pytest.raises(ReplayError, match="already accepted"):
        rx.accept(b)
    assert rx.accepted == {"pose": 1} and rx.rejected == {"replay": 1}


def test_frames_claiming_our_own_origin_are_rejected() -> None:
    rx = Receiver(own="r1")
    with pytest.raises(OwnOriginError, match="found our own 'r1'") as info:
        rx.decode(encode(_pose(1)), "colony/c/r1/pose")
    assert info.value.reason == "own_origin" and rx.rejected == {"own_origin": 1}
    rx.receive(encode(_pose(1, origin="r2")))


def test_open_colony_receiver_has_no_replay_window() -> None:
    rx = Receiver()
    frame = encode(_pose(1))
    rx.receive(frame)
    rx.receive(frame)
    assert rx.accepted == {"pose": 2} and rx.replay is None


def test_requests_of_made_up_origins_cannot_push_a_signed_agent_out_of_the_replay_window() -> None:
    """Requests need no signature, so anyone may send them under any origin, each moving the
    replay window of its origin. The window keeps 4096 origins (least recently updated
    forgotten first): 4096 requests of made-up origins used to push a signed agent's state out,
    after which its old frames could be replayed. Requests have a window of their own."""
    from protocol.identity import Signer, Trust
    from protocol.messages import DeltaRangeRequest, Heartbeat

    a = Signer.generate()
    rx = Receiver(key=KEY, trust=Trust("tofu"))
    hb = Heartbeat(
        origin="a", epoch=1, seq=1, time=1.0, kind="robot", frame_id="a.odom", identity=a.public
    )
    rx.receive(encode(hb, key=KEY, signer=a))
    old = encode(_pose(2, origin="a"), key=KEY, signer=a)
    rx.receive(old)
    for i in range(4096):
        request = DeltaRangeRequest(
            origin=f"x{i}", epoch=1, seq=1, time=1.0, layer="a", request_id=i,
            from_version=0, to_version=1,
        )  # fmt: skip
        rx.receive(encode(request, key=KEY))
    with pytest.raises(ReplayError):
        rx.decode(old)
