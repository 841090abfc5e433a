"""PoseFix against a real daemon: malformed, forged and inconsistent fixes are refused and counted,
with no side effect; a valid one for the daemon is received, one for another agent is ignored."""

from __future__ import annotations

import numpy as np

from colonyd.frames import Sender, colony_key, frame_of
from protocol import Heartbeat, PoseFix
from protocol.identity import Signer
from protocol.keyexpr import topic_key

SECRET = "correct horse battery staple"


def _fix(
    sender: Sender,
    target: str,
    *,
    frame: str | None = None,
    var: float = 0.01,
    xy: float = 0.0,
) -> bytes:
    covariance = np.eye(6) * var
    covariance[0, 1] = covariance[1, 0] = xy  # x-y correlation
    return sender.encode(
        PoseFix(
            **sender.header(),
            target=target,
            frame_id=frame or frame_of(sender.origin),
            stamp=1.0,
            **PoseFix.split_matrix(np.eye(4)),
            covariance=covariance.ravel().tolist(),
        )
    )


def test_hostile_and_valid_fixes_reach_a_daemon_as_counted(make_colony):
    colony = make_colony("fix", extra=["--colony-key", SECRET])
    colony.add("b")
    colony.wait_members(1)
    s, ns, key = colony.session(), colony.namespace, colony_key(SECRET)
    cam = Sender("cam", 1, key=key, signer=Signer.generate())
    s.put(
        topic_key(ns, "cam", "heartbeat"),
        cam.encode(
            Heartbeat(**cam.header(), kind="cctv", frame_id=frame_of("cam"), identity=cam.identity)
        ),
    )
    colony.wait_status(
        lambda rs: any(m["agent"] == "cam" for r in rs for m in r["members"]), agents=("b",)
    )
    mallory = Sender("cam", 1, key=key, signer=Signer.generate(), first_seq=500)
    fix_key = topic_key(ns, "cam", "fix")
    s.put(fix_key, _fix(cam, "b", var=0.0))  # claims certainty
    s.put(fix_key, _fix(cam, "b", frame="b.odom"))  # not in the sender's frame
    s.put(fix_key, _fix(cam, "b", xy=0.1))  # not a covariance: variance -0.09 along x = -y
    s.put(fix_key, _fix(cam, "b")[:-40])  # truncated
    s.put(fix_key, _fix(mallory, "b"))  # not cam's identity
    s.put(topic_key(ns, "b", "fix"), _fix(cam, "b"))  # on another origin's key
    s.put(fix_key, _fix(cam, "other"))  # valid, for someone else
    s.put(fix_key, _fix(cam, "b"))  # valid, for b

    def settled(reports: list[dict]) -> bool:
        counts = reports[0]["metrics"]["counts"]
        return counts.get("fix_received", 0) >= 1 and counts.get("fix_for_others", 0) >= 1

    (b,) = colony.wait_status(settled, 30, agents=("b",))
    counts, rejected = b["metrics"]["counts"], b["metrics"]["rejected"]
    assert counts.get("fix_received") == 1 and counts.get("fix_for_others") == 1, counts
    assert rejected.get("bad-fix") == 3, rejected
    assert rejected.get("identity", 0) >= 1, rejected
    assert rejected.get("keyexpr", 0) >= 1, rejected
    assert (
        rejected.get("truncated", 0) + rejected.get("malformed", 0) + rejected.get("auth", 0) >= 1
    ), rejected
