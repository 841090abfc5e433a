"""Forgetting an agent colony-wide: the tombstone, its checks, and a live colony that keeps it."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time

import numpy as np
import pytest

from colonyd.bench.launcher import free_port
from colonyd.errors import WireError
from colonyd.layers import Layers
from colonyd.tombstones import forget_params, forget_tag, load_tombstones, save_tombstones
from voxel.delta import Delta


def test_a_forgotten_layer_is_dropped_and_refused_from_then_on(tmp_path) -> None:
    layers = Layers("me", 0.1)
    delta = Delta(0.1, 0, 1, np.zeros((1, 3)), np.ones(1), np.zeros(1))
    layers.admit("bad", [delta])
    layers.get("bad")
    saved: list[str] = []
    layers.on_forget = saved.append
    assert layers.forget_agent("bad") and layers.find("bad") is None and saved == ["bad"]
    assert not layers.forget_agent("bad") and not layers.forget_agent("me")
    with pytest.raises(WireError, match="expected a layer not forgotten, found 'bad'"):
        layers.admit("bad", [delta])
    save_tombstones(tmp_path, layers.forgotten)
    assert load_tombstones(tmp_path) == {"bad"}
    (tmp_path / "forgotten.json").write_text('{"not": "a list"}')
    assert load_tombstones(tmp_path) == set() == load_tombstones(tmp_path / "nowhere")


def test_concurrent_forgets_take_one_tombstone_each_and_stay_bounded(tmp_path) -> None:
    """The inbox (tombstones in heartbeats) and the forget server forget agents on their own
    threads. The checks (forgotten already, at most `max_layers` tombstones) ran before
    `apply_lock` was taken: threads waiting for it (a delta being applied holds it) had all
    passed them, so each said the same agent was new (each saved it, logged it) and together
    they took the tombstones past their bound."""
    import threading

    layers = Layers("me", 0.1, max_layers=4)
    saved: list[str] = []
    layers.on_forget = lambda origin: (
        saved.append(origin),
        save_tombstones(tmp_path, layers.forgotten),  # as the daemon persists them
    )
    names = ["same"] * 8 + [f"x{i}" for i in range(8)]
    new: list[tuple[str, bool]] = []
    threads = [
        threading.Thread(target=lambda n=n: new.append((n, layers.forget_agent(n)))) for n in names
    ]
    with layers.apply_lock:  # a delta between its admission and its application
        for t in threads:
            t.start()
        time.sleep(0.3)  # every thread at the lock (a slow start only hides the race)
    for t in threads:
        t.join(10.0)
    assert not any(t.is_alive() for t in threads)
    assert len(new) == len(names)
    taken = [n for n, ok in new if ok]
    assert len(taken) == len(set(taken)) == len(layers.forgotten) <= layers.max_layers, taken
    assert sorted(saved) == sorted(taken) and set(taken) == layers.forgotten
    assert load_tombstones(tmp_path) == layers.forgotten


def test_a_tombstone_known_already_waits_for_no_delta() -> None:
    """Every member's heartbeat carries the colony's tombstones, and the inbox forgets each on
    its one thread: one known already (or past the bound) is nothing new, and is answered
    without `apply_lock`. Taking the lock first, every heartbeat waited for a range or a
    snapshot being applied on the catch-up thread (seconds for a big layer) behind it."""
    import threading

    layers = Layers("me", 0.1, max_layers=1)
    assert layers.forget_agent("gone")
    answers: list[bool] = []
    heartbeat = threading.Thread(
        target=lambda: answers.extend(layers.forget_agent(o) for o in ("gone", "another"))
    )
    holder_in, release = threading.Event(), threading.Event()

    def catch_up() -> None:
        with layers.apply_lock:  # a range being applied
            holder_in.set()
            release.wait(30.0)

    holder = threading.Thread(target=catch_up)
    holder.start()
    holder_in.wait(10.0)
    try:
        heartbeat.start()
        heartbeat.join(10.0)  # a bound far past any run's, not a speed: on the lock, it waits
        assert not heartbeat.is_alive() and answers == [False, False]
    finally:
        release.set()
        holder.join(10.0)
        heartbeat.join(10.0)
    assert layers.forgotten == {"gone"}


def test_forget_requests_are_checked_against_the_colony_key() -> None:
    assert forget_params({"agent": "r1"}, None, 0.0) == "r1"
    with pytest.raises(ValueError, match="expected agent=NAME"):
        forget_params({"agent": "r 1"}, None, 0.0)
    key = b"k" * 32
    good = {"agent": "r1", "t": "100.0", "auth": forget_tag(key, "r1", 100.0)}
    assert forget_params(good, key, 130.0) == "r1"
    with pytest.raises(ValueError, match="within 60 s"):
        forget_params(good, key, 200.0)
    with pytest.raises(ValueError, match="bad tag"):
        forget_params({**good, "auth": forget_tag(b"x" * 32, "r1", 100.0)}, key, 100.0)
    with pytest.raises(ValueError, match="within 60 s"):
        forget_params({"agent": "r1"}, key, 100.0)


def test_forget_agent_removes_a_layer_from_the_colony_and_repair_respects_it(make_colony):
    colony = make_colony("tomb", extra=["--colony-key", "s3cret"])
    colony.add("a", ["synthetic:scans=0,rate=2,points=120,seed=1"])
    colony.add("b")
    c = colony.add("c")
    deadline = time.monotonic() + 40
    while time.monotonic() < deadline:
        report = {r["agent"]: r for r in colony.status()}
        if all("a" in report.get(x, {}).get("layers", {}) for x in ("b", "c")):
            break
        time.sleep(0.5)
    base = [
        sys.executable, "-m", "colonyd", "forget-agent", "--colony", "tomb",
        "--namespace", colony.namespace, "--no-multicast", "--connect", c.endpoint,
    ]  # fmt: skip
    wrong = subprocess.run(
        [*base, "a", "--colony-key", "wrong"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert wrong.returncode == 1 and "to forget 'a'" in wrong.stderr
    run = subprocess.run(
        [*base, "a", "--colony-key", "s3cret"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert run.returncode == 0, run.stderr
    answers = json.loads(run.stdout)
    assert "c" in {x["agent"] for x in answers if x.get("forgotten") == "a"}
    # a daemon the request did not reach learns the tombstone from heartbeats
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        report = colony.reports(["b", "c"])
        if all("a" not in report[x]["layers"] for x in ("b", "c")):
            break
        time.sleep(0.5)
    time.sleep(3.0)  # a keeps mapping and publishing; heartbeats keep listing its layer

    def refused(reports: list[dict]) -> bool:  # a's deltas since came and were refused
        return all(
            r["metrics"]["rejected"].get("forgotten", 0) > 0 for r in reports if r["agent"] != "a"
        )

    report = {r["agent"]: r for r in colony.wait_status(refused, agents=("a", "b", "c"))}
    assert report["a"]["layers"]["a"]["seq"] > 0
    for x in ("b", "c"):
        assert "a" not in report[x]["layers"], x
        assert report[x]["metrics"]["rejected"].get("forgotten", 0) > 0, x


def _forget_cli(namespace: str, endpoint: str, *extra: str) -> list[str]:
    return [
        sys.executable, "-m", "colonyd", "forget-agent", "--colony", "tomb",
        "--namespace", namespace, "--no-multicast", "--connect", endpoint, *extra,
    ]  # fmt: skip


def test_forget_agent_asks_again_until_a_daemon_that_came_up_late_takes_it(make_colony):
    """The request goes out before the daemon it connects to is up (a single query then found
    nobody and gave up): it is asked again until the daemon answers."""
    colony = make_colony("tomb")
    x = colony.add("x", start=False)
    proc = subprocess.Popen(
        [*_forget_cli(colony.namespace, x.endpoint, "ghost")],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        time.sleep(1.0)
        x.start()
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
    assert proc.returncode == 0, err
    assert [(a["agent"], a["forgotten"]) for a in json.loads(out)] == [("x", "ghost")]


def test_forget_agent_gives_up_after_its_wait_and_says_so(tmp_path):
    """Nobody to ask: it gives up after --wait seconds, saying where it looked and how long."""
    nobody = f"tcp/127.0.0.1:{free_port()}"
    run = subprocess.run(
        [*_forget_cli("nowhere", nobody, "ghost", "--wait", "1.5")],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert run.returncode == 1, run.stderr
    assert f"found no answer from a daemon reached through {nobody} in " in run.stderr
    assert re.search(r"rounds over 1\.[5-9] s", run.stderr), run.stderr
    bad = subprocess.run(
        [*_forget_cli("nowhere", nobody, "ghost", "--wait", "0")],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert bad.returncode == 1 and "--wait: expected seconds > 0, found 0.0" in bad.stderr


def test_what_the_answers_said_when_nobody_took_the_request():
    """A one-daemon colony asked to forget that daemon: "found 1 answers: own layer" said
    neither who answered nor why."""
    from colonyd.tombstones import OWN_LAYER, answers_found

    assert answers_found({"a": {"agent": "a", "error": OWN_LAYER}}) == (
        "1 answer: a: its own layer (a daemon never forgets its own: its peers do)"
    )
    answers = {
        "b": {"agent": "b", "error": "bad-forget"},
        "c": {"agent": "c", "error": "bad-forget"},
        "d": {"agent": "d"},
    }
    assert answers_found(answers) == "3 answers: b, c: bad-forget"
