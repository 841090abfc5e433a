"""Hostile peers against real daemons: forged origins and replays change nothing they should not."""

from __future__ import annotations

import json
import threading

from colonyd.frames import Sender, colony_key
from protocol import Heartbeat, VoxelDelta
from protocol.keyexpr import topic_key
from voxel.delta import Delta

SECRET = "correct horse battery staple"


def test_forged_frames_neither_freeze_replication_nor_impersonate(make_colony):
    colony = make_colony("hostile", extra=["--colony-key", SECRET])
    colony.add("a", ["synthetic:scans=16,rate=4,points=200,seed=1"])
    colony.add("b")
    colony.wait_members(2)
    s = colony.session()
    ns = colony.namespace
    a_epoch = colony.reports(["a"])["a"]["epoch"]
    # A key holder forges a frame of a's origin, far ahead in a's sequence, on b's key: it
    # is refused (keyexpr) and must not move b's replay window for a.
    forger = Sender("a", a_epoch, key=colony_key(SECRET), first_seq=10**9)
    forged = forger.encode(
        VoxelDelta(
            **forger.header(), frame_id="map", delta=Delta(0.1, 0, 1, [[0, 0, 0]], [0.5], [1.0])
        )
    )
    s.put(topic_key(ns, "b", "delta"), forged)
    # A replay of a's own heartbeat, sent back to it, must not make a list itself.
    heard: list[bytes] = []
    got = threading.Event()

    def keep(sample) -> None:
        heard.append(sample.payload.to_bytes())
        got.set()

    sub = s.declare_subscriber(topic_key(ns, "a", "heartbeat"), keep)
    assert got.wait(30.0), "no heartbeat of a heard"
    sub.undeclare()
    s.put(topic_key(ns, "a", "heartbeat"), heard[0])
    colony.wait_converged(30)
    reports = colony.reports(["a", "b"])
    b_rejected = reports["b"]["metrics"]["rejected"]
    assert b_rejected.get("keyexpr", 0) >= 1, b_rejected
    assert b_rejected.get("replay", 0) <= 1, b_rejected  # the replayed heartbeat, no more
    a_rejected = reports["a"]["metrics"]["rejected"]
    assert a_rejected.get("own_origin", 0) >= 1, a_rejected
    assert "a" not in {m["agent"] for m in reports["a"]["members"]}


def test_a_second_daemon_with_a_taken_agent_id_refuses_to_start(make_colony):
    colony = make_colony("dup")
    colony.add("a", ["synthetic:scans=4,rate=4,points=100,seed=1"])
    colony.add("b")
    colony.wait_converged(30)
    twin = colony.add("twin", ["synthetic:scans=4,rate=4,points=100,seed=2"], start=False)
    twin.args[twin.args.index("twin")] = "a"  # its own state dir, the first one's agent id
    twin.start()
    assert twin.proc is not None and twin.proc.wait(30) == 3  # a configuration error
    text = twin.log_path.read_text()
    assert "agent id 'a' is already in use in colony 'dup'" in text, text
    assert "expected every daemon to have its own agent_id" in text
    reports = colony.reports(["a", "b"])
    assert set(reports) == {"a", "b"}  # the first 'a' carries on, unharmed
    assert reports["b"]["layers"]["a"]["epoch"] == reports["a"]["epoch"]
    colony.wait_converged(30, ["a", "b"])


def test_a_young_daemon_gives_way_to_a_live_twin_it_hears_later(make_colony):
    """Two daemons started at once both pass the start-up check; the younger then gives way."""
    colony = make_colony("twins")
    a = colony.add("a", ["synthetic:scans=40,rate=4,points=100,seed=1"])
    colony.wait_members(1)
    s = colony.session()
    twin = Sender("a", 12345)  # another process running as 'a', in its own epoch
    s.put(
        topic_key(colony.namespace, "a", "heartbeat"),
        twin.encode(Heartbeat(**twin.header(), kind="robot", frame_id="map")),
    )
    assert a.proc is not None and a.proc.wait(60) == 3
    assert "heard a heartbeat of epoch 12345" in a.log_path.read_text()


def test_a_key_holder_cannot_forge_another_agents_layer(make_colony):
    """Identities: with the colony key but not a's identity key, c cannot write a's layer."""
    from protocol.identity import Signer

    colony = make_colony("ident", extra=["--colony-key", SECRET])
    a = colony.add("a", ["synthetic:scans=4,rate=8,points=200,seed=1"])
    colony.add("b")
    colony.wait_converged(30)
    a_public = Signer.from_bytes((a.state_dir / "identity.key").read_bytes()).public
    pins = json.loads((colony.daemons["b"].state_dir / "known_agents.json").read_text())
    assert pins["a"] == a_public.hex()  # b pinned a's key on first use
    before = colony.reports(["a", "b"], digest=True)
    layer = before["b"]["layers"]["a"]
    s = colony.session()
    mallory = Sender(
        "a", before["a"]["epoch"], key=colony_key(SECRET), signer=Signer.generate(), first_seq=10**9
    )
    delta = Delta(0.1, layer["seq"], layer["seq"] + 1, [[7, 7, 7]], [3.0], [1.0])
    s.put(
        topic_key(colony.namespace, "a", "delta"),
        mallory.encode(VoxelDelta(**mallory.header(), frame_id="map", delta=delta)),
    )
    s.put(
        topic_key(colony.namespace, "a", "heartbeat"),
        mallory.encode(
            Heartbeat(**mallory.header(), kind="robot", frame_id="map", identity=mallory.identity)
        ),
    )

    def refused(reports: list[dict]) -> bool:
        b = next(r for r in reports if r["agent"] == "b")
        return b["metrics"]["rejected"].get("identity", 0) >= 2

    reports = colony.wait_status(refused, 30, agents=("b",), digest=True)
    b = next(r for r in reports if r["agent"] == "b")
    assert b["metrics"]["rejected"].get("identity", 0) >= 2, b["metrics"]["rejected"]
    assert b["layers"]["a"]["digest"] == layer["digest"]  # nothing of mallory's applied
    # a restarts with its identity: b still accepts it, no new identity rejection
    a.stop()
    a.start()
    colony.wait_converged(30)
    b2 = colony.reports(["b"])["b"]
    assert b2["metrics"]["rejected"].get("identity", 0) == b["metrics"]["rejected"]["identity"]


def test_liveliness_churn_of_a_stranger_does_not_multiply_heartbeats(make_colony):
    """Liveliness tokens are not authenticated (no colony key covers them): a stranger that
    declares and undeclares tokens as fast as it can made a daemon send a heartbeat (and a pose)
    for every join, up to one every 10 ms, to the whole colony. Early heartbeats after a join
    are now at most one every `MIN_EARLY_HEARTBEAT_S`."""
    import time

    from colonyd.daemon import MIN_EARLY_HEARTBEAT_S
    from protocol.keyexpr import alive_key

    colony = make_colony("churn", extra=["--colony-key", SECRET], heartbeat_s=60.0)
    colony.add("a")
    colony.wait_members(1)
    s = colony.session()
    beats: list[float] = []
    sub = s.declare_subscriber(
        topic_key(colony.namespace, "a", "heartbeat"), lambda _: beats.append(time.monotonic())
    )
    start = time.monotonic()
    for i in range(300):
        s.liveliness().declare_token(alive_key(colony.namespace, f"x{i}")).undeclare()
        time.sleep(0.005)
    time.sleep(0.5)  # the last joins handled
    sub.undeclare()
    elapsed = time.monotonic() - start
    during = [t for t in beats if t >= start]
    assert len(during) <= elapsed / MIN_EARLY_HEARTBEAT_S + 2, (len(during), elapsed)
    assert colony.reports(["a"])["a"]["metrics"]["counts"].get("joins", 0) >= 100
