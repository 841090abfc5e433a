"""Hostile peers against real daemons: forged origins and replays change nothing they should not."""

from __future__ import annotations

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
    a_epoch = next(r for r in colony.status() if r["agent"] == "a")["epoch"]
    # A key holder forges a frame of a's origin, far ahead in a's sequence, on b's key: it
    # is refused (keyexpr) and must not move b's replay window for a.
    forger = Sender("a", a_epoch, key=colony_key(SECRET), first_seq=10**9)
    forged = forger.encode(VoxelDelta(**forger.header(), frame_id="map",
                                      delta=Delta(0.1, 0, 1, [[0, 0, 0]], [0.5], [1.0])))
    s.put(topic_key(ns, "b", "delta"), forged)
    # A replay of a's own heartbeat, sent back to it, must not make a list itself.
    heard: list[bytes] = []
    got = threading.Event()

    def keep(sample) -> None:
        heard.append(sample.payload.to_bytes())
        got.set()

    sub = s.declare_subscriber(topic_key(ns, "a", "heartbeat"), keep)
    assert got.wait(5.0), "no heartbeat of a heard"
    sub.undeclare()
    s.put(topic_key(ns, "a", "heartbeat"), heard[0])
    colony.wait_converged(30)
    reports = {r["agent"]: r for r in colony.status()}
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
    reports = {r["agent"]: r for r in colony.status()}
    assert set(reports) == {"a", "b"}  # the first 'a' carries on, unharmed
    assert reports["b"]["layers"]["a"]["epoch"] == reports["a"]["epoch"]
    colony.wait_converged(10, ["a", "b"])


def test_a_young_daemon_gives_way_to_a_live_twin_it_hears_later(make_colony):
    """Two daemons started at once both pass the start-up check; the younger then gives way."""
    colony = make_colony("twins")
    a = colony.add("a", ["synthetic:scans=40,rate=4,points=100,seed=1"])
    colony.wait_members(1)
    s = colony.session()
    twin = Sender("a", 12345)  # another process running as 'a', in its own epoch
    s.put(topic_key(colony.namespace, "a", "heartbeat"),
          twin.encode(Heartbeat(**twin.header(), kind="robot", frame_id="map")))
    assert a.proc is not None and a.proc.wait(20) == 3
    assert "heard a heartbeat of epoch 12345" in a.log_path.read_text()
