"""Multi-process tests: real daemons, real Zenoh, loopback only, multicast off."""

from __future__ import annotations

import signal
import time

import pytest

from colonyd.wire import Codec

from .conftest import logs

SCANS = "synthetic:scans={n},rate=4,points=240,seed={seed},room=6"


def src(seed: int, n: int = 6) -> list[str]:
    return [SCANS.format(n=n, seed=seed)]


def test_three_converge_late_joiner_and_garbage(make_colony):
    colony = make_colony("conv")
    for i, agent in enumerate(["a", "b", "c"]):
        colony.add(agent, src(i + 1))
        if i == 0:
            time.sleep(0.3)
    try:
        colony.wait_members(3)
        colony.wait_converged(30)
        # A peer sending garbage is ignored and counted.
        s = colony.session()
        bad = [b"", b"garbage", b"CLD\x01\x00" + b"\x28\xb5\x2f\xfd" + b"\x00" * 20,
               b"CLD\x09\x00xx", Codec().encode({"t": "delta", "o": "evil", "e": 1, "s": 1})]
        for payload in bad:
            s.put(f"colony/{colony.namespace}/delta/evil", payload or b"\x00")
            s.put(f"colony/{colony.namespace}/hb/evil", payload or b"\x00")
        time.sleep(1.0)
        reports = colony.status()
        for r in reports:
            assert r["metrics"]["counts"].get("rejected", 0) >= len(bad), r["metrics"]
            assert "evil" not in r["layers"]
        # A late joiner catches up with every layer.
        colony.add("d")
        colony.wait_converged(20)
        d = next(r for r in colony.status() if r["agent"] == "d")
        assert {"a", "b", "c"} <= set(d["layers"])
        assert d["metrics"]["counts"].get("snapshots_installed", 0) >= 3
    except Exception:
        print(logs(colony))
        raise


def test_sigkill_restart_loses_nothing_logged(make_colony):
    colony = make_colony("kill")
    a = colony.add("a", src(1, 8))
    time.sleep(0.3)
    colony.add("b")
    try:
        colony.wait_converged(30)
        before = {r["agent"]: r for r in colony.status(digest=True)}
        seq, digest, epoch = before["a"]["layers"]["a"]["seq"], before["a"]["layers"]["a"]["digest"], before["a"]["epoch"]
        assert before["b"]["layers"]["a"]["digest"] == digest
        a.kill()  # SIGKILL: no flush, no snapshot; only the write-ahead log survives
        a.args = [x for x in a.args if not x.startswith("synthetic:")]
        a.args = [x for i, x in enumerate(a.args) if not (x == "--source")]
        a.start()
        colony.wait_members(2)
        after = {r["agent"]: r for r in colony.status(digest=True)}
        assert after["a"]["epoch"] == epoch
        assert after["a"]["layers"]["a"]["seq"] == seq
        assert after["a"]["layers"]["a"]["digest"] == digest
        # It continues its sequence: more mapping, new numbers, and b follows without a reset.
        a.stop()
        a.args += ["--source", SCANS.format(n=3, seed=9)]
        a.start()
        colony.wait_converged(30)
        final = {r["agent"]: r for r in colony.status(digest=True)}
        assert final["a"]["epoch"] == epoch
        assert final["a"]["layers"]["a"]["seq"] > seq
        assert final["b"]["layers"]["a"]["digest"] == final["a"]["layers"]["a"]["digest"]
    except Exception:
        print(logs(colony))
        raise


def test_frozen_daemon_does_not_stall_others(make_colony):
    colony = make_colony("freeze", lease_ms=1000)
    a = colony.add("a", src(1, 28))
    time.sleep(0.3)
    colony.add("b", src(2, 28))
    c = colony.add("c", src(3, 3))
    try:
        colony.wait_members(3)
        time.sleep(1.0)
        c.signal(signal.SIGSTOP)
        frozen_at = {r["agent"]: r["layers"]["a"]["seq"] for r in colony.status(timeout=1.0)
                     if "a" in r["layers"]}
        # a and b keep mapping and gossiping while c is frozen, and converge between themselves.
        colony.wait_converged(40, ["a", "b"])
        seq_a = next(r for r in colony.status(timeout=1.0) if r["agent"] == "a")["layers"]["a"]["seq"]
        assert seq_a > frozen_at.get("a", 0)
        c.signal(signal.SIGCONT)
        colony.wait_converged(40)
    except Exception:
        print(logs(colony))
        raise
    finally:
        c.signal(signal.SIGCONT)


def test_two_colonies_do_not_see_each_other(make_colony):
    x = make_colony("x")
    y = make_colony("y")
    x.add("x1", src(1, 2))
    y.add("y1", src(2, 2))
    time.sleep(0.3)
    x.add("x2")
    y.add("y2")
    try:
        x.wait_converged(30)
        y.wait_converged(30)
        rx, ry = x.status(), y.status()
        assert {r["agent"] for r in rx} == {"x1", "x2"}
        assert {r["agent"] for r in ry} == {"y1", "y2"}
        for r in rx:
            assert set(r["layers"]) <= {"x1", "x2"}
            assert {m["agent"] for m in r["members"]} <= {"x1", "x2"}
    except Exception:
        print(logs(x), logs(y))
        raise
