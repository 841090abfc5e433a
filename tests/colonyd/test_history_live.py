"""History across the colony: a replica pages an origin's history and answers temporal queries
(`export --at`, `changes --since`) exactly as the origin does."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np

from colonyd.bench.launcher import free_port
from colonyd.export import query_maps
from colonyd.frames import Sender
from colonyd.runtime import open_session, undeclare, zenoh_config
from protocol import Heartbeat, HistoryReply
from protocol.identity import Signer
from protocol.keyexpr import topic_key
from voxel import keys as vk
from voxel.history import History


def _layer_at(colony, daemon: str, t: float):
    replies = query_maps(colony.session(), colony.namespace, f"layer=a;at={float(t)!r}", 20.0)
    reply = next(r for r in replies if r.agent == daemon)
    order = np.argsort(vk.pack(reply.keys))
    return vk.pack(reply.keys)[order], reply.logodds[order]


def test_a_replica_answers_temporal_queries_as_the_origin(make_colony, tmp_path):
    colony = make_colony("history")
    t_start = time.time()
    colony.add("a", ["synthetic:scans=8,rate=2,points=240,seed=1"])
    b = colony.add("b", start=False)
    b.env["COLONYD_HISTORY_SYNC_S"] = "0.5"
    b.start()
    colony.wait_converged(40)
    t_end = time.time()
    samples = np.linspace(t_start, t_end, 16)
    deadline = time.monotonic() + 20
    while True:
        pairs = [(_layer_at(colony, "a", t), _layer_at(colony, "b", t)) for t in samples]
        same = [np.array_equal(ka, kb) and np.array_equal(la, lb) for (ka, la), (kb, lb) in pairs]
        if all(same) or time.monotonic() > deadline:
            break
        time.sleep(0.5)
    assert all(same), f"replica differs from the origin at {same.count(False)} of {len(same)} times"
    known = [len(ka) for (ka, _), _ in pairs]
    assert known[0] == 0 and known[-1] > 200 and len(set(known)) > 3  # the map grew over time
    # every (voxel, t) pair of the final map's voxels, over all sampled times: 100 % equal
    voxels = sum(len(ka) for (ka, _), _ in pairs)
    assert voxels > 1000

    base = [
        sys.executable, "-m", "colonyd", "changes", "--colony", "history",
        "--namespace", colony.namespace, "--no-multicast", "--connect", b.endpoint,
    ]  # fmt: skip
    mid = samples[len(samples) // 2]
    out = tmp_path / "changes"
    run = subprocess.run(
        [*base, "--since", repr(float(mid)), "--out", str(out), "--from", "b", "--layer", "a"],
        capture_output=True, check=False, text=True, timeout=60,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    counts = json.loads(run.stdout)
    (ka, la), _ = pairs[len(samples) // 2]
    (kz, lz), _ = pairs[-1]
    appeared = np.setdiff1d(kz[lz >= 0], ka[la >= 0])
    assert counts["appeared"] == appeared.size > 0
    assert (out / "appeared.ply").stat().st_size > 0 and (out / "disappeared.ply").exists()
    bad = subprocess.run(
        [*base, "--since", "yesterday", "--out", str(out)],
        capture_output=True, check=False, text=True, timeout=60,
    )  # fmt: skip
    assert bad.returncode == 1 and "--since: expected seconds" in bad.stderr


def test_forgetting_replicates_with_the_origins_decay(make_colony):
    """An origin that forgets what nobody observed for a second: its replica drops the same
    voxels (digests equal) and decays its copy with the origin's half-life."""
    colony = make_colony("forget")
    a = colony.add("a", ["synthetic:scans=12,rate=4,points=240,seed=2,step=1.0"], start=False)
    a.env.update(
        {"COLONYD_HALF_LIFE_S": "20", "COLONYD_FORGET_AFTER_S": "1.0", "COLONYD_FORGET_S": "0.3"}
    )
    a.start()
    colony.add("b")
    colony.wait_converged(40)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        report = colony.reports(["a", "b"], digest=True)
        la, lb = report["a"]["layers"]["a"], report["b"]["layers"].get("a", {})
        if la["digest"] == lb.get("digest") and lb.get("half_life") == 20.0:
            break
        time.sleep(0.5)
    assert la["digest"] == lb["digest"] and lb["half_life"] == 20.0 and la["half_life"] == 20.0
    assert report["a"]["metrics"]["counts"].get("blocks_forgotten", 0) > 0


def test_replicas_equal_the_origin_in_every_channel_and_the_history(make_colony):
    """A simulated depth camera maps colour, classes and normals: the replica's layer equals
    the origin's in every channel (digests cover them all) and holds the same history (history
    sync is on by default); a replica with a small peer history budget keeps within it."""
    colony = make_colony("channels")
    a = colony.add("a", ["sim:world=room,agent=depth-1,frames=4"], start=False)
    a.env["COLONYD_HISTORY_SYNC_S"] = "0.5"
    a.start()
    colony.add("b")  # the default history_sync_s
    c = colony.add("c", start=False)
    c.env.update({"COLONYD_HISTORY_SYNC_S": "0.5", "COLONYD_PEER_HISTORY_ENTRIES": "10000"})
    c.start()
    colony.wait_converged(60)
    deadline = time.monotonic() + 40
    while time.monotonic() < deadline:
        report = {r["agent"]: r for r in colony.status(digest=True)}
        if set(report) == {"a", "b", "c"}:  # a round every daemon answered
            la, lb = (report[x]["layers"].get("a", {}) for x in "ab")
            lc = report["c"]["layers"].get("a", {})
            same = la["digest"] == lb.get("digest") and la["history"] == lb.get("history")
            if same and lc.get("history", 0) > 0:
                break
        time.sleep(0.5)
    assert la["digest"] == lb["digest"] and la["history"] == lb["history"] > 10_000
    assert la["digest"] == lc["digest"] and 0 < lc["history"] <= 10_000  # its budget
    for channels in (la["channels"], lb["channels"]):
        assert {"colour", "normal", "class_ids", "class_probs"} <= set(channels)
    ka, va = _layer_at(colony, "a", time.time())
    kb, vb = _layer_at(colony, "b", time.time())
    assert np.array_equal(ka, kb) and np.array_equal(va, vb) and len(ka) > 1000


def _history_of_a_alike(colony, within: float = 30.0):
    """Reports of a and b once both hold as many of a's history records (or after `within`
    seconds), and those two counts."""
    deadline = time.monotonic() + within
    while True:
        report = colony.reports(["a", "b"])
        held = tuple(
            report[x]["layers"].get("a", {}).get("history", -1) for x in "ab"
        )  # -1: that daemon does not hold a's layer yet (a late joiner catches up first)
        if held[0] == held[1] or time.monotonic() > deadline:
            return report, held
        time.sleep(0.5)


def test_history_pushed_with_the_deltas_reaches_a_replica_that_never_pulls(make_colony):
    """History push (opt-in): the origin publishes its new records with each delta and a
    replica whose pull is off holds the origin's history, answering temporal queries alike."""
    colony = make_colony("push")
    b = colony.add("b", start=False)  # listening first: a is connected before it maps
    b.env.update({"COLONYD_HISTORY_PUSH": "true", "COLONYD_HISTORY_SYNC_S": "0"})
    b.start()
    a = colony.add("a", ["synthetic:scans=8,rate=4,points=240,seed=3"], start=False)
    a.env["COLONYD_HISTORY_PUSH"] = "true"
    t_start = time.time()
    a.start()
    colony.wait_converged(40)
    report, held = _history_of_a_alike(colony)
    assert held[0] == held[1] > 100, held
    counts = {x: report[x]["metrics"]["counts"] for x in "ab"}
    assert counts["a"].get("history_pushed", 0) >= held[0]
    assert counts["b"].get("history_records", 0) >= held[1]
    # nobody pulled, unless a pushed page arrived before b held a's layer (a loaded machine):
    # the next page then left a gap, which b filled with a pull at once
    assert counts["a"].get("histories_served", 0) == 0 or counts["b"].get("history_repairs")
    for t in np.linspace(t_start, time.time(), 6):
        (ka, la), (kb, lb) = _layer_at(colony, "a", t), _layer_at(colony, "b", t)
        assert np.array_equal(ka, kb) and np.array_equal(la, lb)
    # a peer pushing records of another's layer is refused, counted, and changes nothing
    evil = Sender("evil", 1, signer=Signer.generate())
    page = History()
    code = page.agent_code("evil")
    page.append(np.arange(5, dtype=np.int64), time=1.0, version=10**6, agent=code)
    forged = HistoryReply(
        **evil.header(), layer="a", request_id=0, layer_epoch=1, from_version=0,
        to_version=10**6, records=page.page(0, 10)[0],
    )  # fmt: skip
    hello = Heartbeat(**evil.header(), kind="robot", frame_id="evil.odom", identity=evil.identity)
    s = colony.session()
    s.put(topic_key(colony.namespace, "evil", "heartbeat"), evil.encode(hello))  # pinned (TOFU)
    colony.wait_status(  # b has heard it (and pinned evil's key) before the history comes
        lambda rs: any(m["agent"] == "evil" for r in rs if r["agent"] == "b" for m in r["members"]),
        agents=("b",),
    )
    s.put(topic_key(colony.namespace, "evil", "history"), evil.encode(forged))
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        b_report = next((r for r in colony.status() if r["agent"] == "b"), None)
        if b_report and b_report["metrics"]["rejected"].get("bad-history", 0) >= 1:
            break
        time.sleep(0.3)
    assert b_report["metrics"]["rejected"].get("bad-history", 0) >= 1, b_report["metrics"]
    assert b_report["layers"]["a"]["history"] == held[1]


def test_a_push_only_replica_that_joined_late_pulls_the_history_it_missed(make_colony):
    """A replica with pulls off that joins while the origin maps: the pushed pages after its
    catch-up leave a gap (the history before it), which it fills with a pull at once."""
    colony = make_colony("late")
    # 15 s of mapping: a still pushes after b's catch-up (with 6 s, a loaded machine started b
    # after a had stopped, and no pushed page showed b the gap: seen once under load 12)
    a = colony.add("a", ["synthetic:scans=60,rate=4,points=240,seed=3"], start=False)
    a.env["COLONYD_HISTORY_PUSH"] = "true"
    a.start()
    colony.wait_status(
        lambda rs: rs[0]["layers"]["a"]["history"] > 0, within=30, agents=("a",)
    )  # a has mapped and pushed before b exists
    b = colony.add("b", start=False)
    b.env.update({"COLONYD_HISTORY_PUSH": "true", "COLONYD_HISTORY_SYNC_S": "0"})
    b.start()
    colony.wait_converged(40)
    report, held = _history_of_a_alike(colony)
    assert held[0] == held[1] > 100, held
    assert report["b"]["metrics"]["counts"].get("history_repairs", 0) >= 1
    assert report["a"]["metrics"]["counts"].get("histories_served", 0) >= 1


def test_a_pushed_page_that_came_before_the_layer_is_pulled_once_the_layer_arrives(make_colony):
    """A push-only replica (pulls off) hears an origin's pushed page before it holds the
    origin's layer and drops it; no push follows (the origin has stopped mapping): once the
    layer arrives the replica pulls its history. The page is a's own frame, recorded while a
    mapped and put again (with a's heartbeat, which pins a's key) while a is down."""
    colony = make_colony("early")
    ns, port = colony.namespace, free_port()
    observer = open_session(zenoh_config(listen=[f"tcp/127.0.0.1:{port}"], gossip=False))
    frames: dict[str, list[bytes]] = {"heartbeat": [], "history": []}
    subs = [
        observer.declare_subscriber(
            topic_key(ns, "a", kind), lambda s, kind=kind: frames[kind].append(s.payload.to_bytes())
        )
        for kind in frames
    ]
    try:
        a = colony.add(
            "a",
            ["synthetic:scans=8,rate=4,points=240,seed=3"],
            start=False,
            extra=["--connect", f"tcp/127.0.0.1:{port}"],
        )
        a.env["COLONYD_HISTORY_PUSH"] = "true"
        a.start()
        colony.wait_converged(40)
        held = colony.reports(["a"])["a"]["layers"]["a"]["history"]
        assert held > 100 and frames["history"] and frames["heartbeat"], (held, len(frames))
        a.stop()  # its final snapshot keeps the history
        at = a.args.index("--source")
        del a.args[at : at + 2]
        b = colony.add("b", start=False, extra=["--connect", f"tcp/127.0.0.1:{port}"])
        b.env.update({"COLONYD_HISTORY_PUSH": "true", "COLONYD_HISTORY_SYNC_S": "0"})
        b.start()
        b.wait_listening()
        deadline = time.monotonic() + 30
        while True:  # a's frames put again until b has heard one (its subscriptions are up)
            observer.put(topic_key(ns, "a", "heartbeat"), frames["heartbeat"][-1])
            observer.put(topic_key(ns, "a", "history"), frames["history"][-1])
            counts = colony.reports(["b"])["b"]["metrics"]["counts"]
            if counts.get("history_dropped", 0) >= 1 or time.monotonic() > deadline:
                break
            time.sleep(0.5)
        assert counts.get("history_dropped", 0) >= 1, counts
        a.start()  # without its source: nothing new is mapped, so nothing more is pushed
        report, held_now = _history_of_a_alike(colony)
        assert held_now == (held, held), held_now
        assert report["b"]["metrics"]["counts"].get("history_repairs", 0) >= 1
        assert report["a"]["metrics"]["counts"].get("history_pushed", 0) == 0
    finally:
        undeclare(*subs)
        observer.close()
