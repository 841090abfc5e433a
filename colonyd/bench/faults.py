"""`colonyd bench faults`: real daemons under crashes, partitions, freezes, full disks, load,
floods, hostile input."""

from __future__ import annotations

import json
import logging
import os
import random
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from functools import partial
from itertools import pairwise
from pathlib import Path
from typing import Any, cast

import numpy as np
import zenoh

from colonyd.bench.faultlab import (
    DeltaWatch,
    NetLab,
    Spinner,
    Tmpfs,
    delta_digest,
    need_root,
    peak_rss_mb,
)
from colonyd.bench.launcher import LocalColony, LocalDaemon, free_port
from colonyd.runtime import open_session, zenoh_config
from voxel import kernels

log = logging.getLogger(__name__)

#: Scenarios run by default (a few minutes in all), and those run only when named with --only.
SCENARIOS = ("crash", "freeze", "hostile", "disk", "partition", "busy", "flood")
OPT_IN = ("scale",)

SCANS = "synthetic:scans={n},rate={rate},points={points},seed={seed},room=6"


def src(seed: int, n: int, rate: float = 4, points: int = 200) -> list[str]:
    return [SCANS.format(n=n, rate=rate, points=points, seed=seed)]


def run_faults_bench(
    out_json: Path | str,
    *,
    only: list[str] | None = None,
    kills: int = 20,
    duration: float = 10.0,
    scale_sizes: tuple[int, ...] = (4, 8, 16),
    sync_first: bool = False,
) -> dict[str, Any]:
    """Run the scenarios (all default ones, or `only`) and write one JSON object of figures."""
    names = list(only or SCENARIOS)
    unknown = [n for n in names if n not in SCENARIOS + OPT_IN]
    if unknown:
        msg = f"unknown scenario {unknown}: expected some of {', '.join(SCENARIOS + OPT_IN)}"
        raise ValueError(msg)
    work = Path(tempfile.mkdtemp(prefix="colonyd-faults-"))
    result: dict[str, Any] = {"scenarios": names, "skipped": {}, "errors": {}}
    runs: dict[str, Callable[[Path], dict[str, Any]]] = {
        "crash": lambda b: crash(b, kills=kills),
        "freeze": freeze,
        "hostile": hostile,
        "disk": disk,
        "partition": partition,
        "busy": lambda b: busy(b, duration=duration, sync_first=sync_first),
        "flood": flood,
        "scale": lambda b: scale(b, sizes=scale_sizes),
    }
    try:
        for name in names:
            t0 = time.monotonic()
            log.info("faults: %s", name)
            try:
                figures = runs[name](work / name)
            except Skip as exc:
                result["skipped"][name] = str(exc)
                log.warning("faults: %s skipped: %s", name, exc)
                continue
            except Exception as exc:  # one failing scenario is reported, not fatal
                log.exception("faults: %s failed", name)
                result["errors"][name] = f"{type(exc).__name__}: {exc}"
                continue
            figures[f"{name}_wall_s"] = round(time.monotonic() - t0, 1)
            result.update(figures)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    out = Path(out_json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1, sort_keys=True) + "\n")
    return result


class Skip(Exception):
    """A scenario that cannot run here (with the reason)."""


# ----------------------------------------------------------------------------------- helpers


def by_agent(colony: LocalColony, **kw: Any) -> dict[str, dict[str, Any]]:
    return {r["agent"]: r for r in colony.status(**kw)}


def reports_of(
    colony: LocalColony,
    agents: list[str],
    *,
    within: float = 10.0,
    timeout: float = 1.0,
    digest: bool = False,
) -> dict[str, dict[str, Any]]:
    """`LocalColony.reports` with the scenarios' short rounds (1 s): a daemon that misses a
    round's timeout on a loaded machine would otherwise read as holding nothing (seq 0)."""
    return colony.reports(agents, within=within, timeout=timeout, digest=digest)


def seq_of(reports: dict[str, dict[str, Any]], holder: str, origin: str) -> int:
    return int(reports.get(holder, {}).get("layers", {}).get(origin, {}).get("seq", 0))


def _saw_any(watch: DeltaWatch, epoch: int) -> bool:
    return bool(watch.seqs(epoch))


def wait_for(what: str, check: Callable[[], bool], timeout: float, every: float = 0.1) -> float:
    """Seconds until `check()` holds; TimeoutError naming `what` otherwise."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if check():
            return time.monotonic() - t0
        time.sleep(every)
    raise TimeoutError(f"{what}: not within {timeout:.0f} s")


def wait_holding(
    colony: LocalColony,
    want: dict[str, int],
    holders: list[str],
    timeout: float,
    status_timeout: float = 1.0,
) -> float:
    """Seconds until every holder has every origin of `want` at least at its seq."""

    def ok() -> bool:
        reports = by_agent(colony, timeout=status_timeout)
        return all(seq_of(reports, h, o) >= s for h in holders for o, s in want.items() if o != h)

    return wait_for(f"{holders} holding {want}", ok, timeout, every=0.2)


def _more_ready(d: LocalDaemon, before: int) -> Callable[[], bool]:
    """A check that `d` has logged more ready lines than `before`."""
    return lambda: _ready_count(d) > before


def _ready_count(d: LocalDaemon) -> int:
    return (
        d.log_path.read_text(errors="replace").count("daemon: ready:") if d.log_path.exists() else 0
    )


def _digest_lines(d: LocalDaemon) -> list[str]:
    text = d.log_path.read_text(errors="replace") if d.log_path.exists() else ""
    return re.findall(r"layer digest ([0-9a-f]+)", text)


def layer_digest(grid: Any) -> str:
    from colonyd.layers import Layer

    layer = Layer("x", grid.resolution)
    layer.grid = grid
    return layer.digest()


def rejected_total(reports: dict[str, dict[str, Any]]) -> Counter[str]:
    total: Counter[str] = Counter()
    for r in reports.values():
        total.update(r["metrics"]["rejected"])
    return total


def percentile(values: list[float], q: float) -> float | None:
    return round(float(np.percentile(values, q)), 2) if values else None


# ------------------------------------------------------------------------------------- crash


def crash(base: Path, *, kills: int = 20, seed: int = 7) -> dict[str, Any]:
    """SIGKILL a mapping daemon `kills` times at random moments. After each kill, a copy of its
    state directory is recovered offline: every seq a peer saw must be in it (`records_lost`),
    every logged record must have the content the peer saw for its seq and no (epoch, seq) may
    be seen with two contents (`seq_reused`); the restarted daemon's layer must equal the
    recovered one (`restart_mismatch`); at the end the peer's replica equals the layer."""
    from colonyd.persistence import StateStore

    rng = random.Random(seed)
    colony = LocalColony(base, colony="crash", heartbeat_s=0.5)
    b = colony.add("b")  # the hub: a restarts against it
    time.sleep(0.3)
    mapping = [*src(1, 0, rate=8, points=200), "--publish-hz", "8"]
    a = colony.add("a", start=False, extra=["--source", mapping[0], *mapping[1:]])
    watch_session = open_session(
        zenoh_config(
            mode="peer",
            listen=["tcp/127.0.0.1:0"],
            connect=[b.endpoint],
            multicast=False,
            gossip=True,
        )
    )
    figures: dict[str, Any] = {}
    try:
        watch = DeltaWatch(watch_session, colony.namespace, "a")
        time.sleep(0.3)
        lost = mismatched = restart_mismatch = new_epochs = 0
        logged_seen = 0
        kill_ms: list[float] = []
        for i in range(kills):
            if not a.alive():
                before = _ready_count(a)
                a.start()
                wait_for("a ready", _more_ready(a, before), 30, 0.02)
            if i == 0:
                # Kill during mapping: a loaded machine can take over a second from ready to
                # the source's first scan, and a layer never written has nothing to lose.
                first = int(json.loads((a.state_dir / "meta.json").read_text())["epoch"])
                wait_for("a's first delta", partial(_saw_any, watch, first), 30, 0.02)
            delay = rng.uniform(0.15, 1.2)
            kill_ms.append(round(delay * 1000))
            time.sleep(delay)
            meta = json.loads((a.state_dir / "meta.json").read_text())
            a.kill()
            time.sleep(0.25)  # frames already on the wire reach the watcher
            copy = base / f"copy-{i}"
            shutil.copytree(a.state_dir, copy, ignore=shutil.ignore_patterns("lock"))
            store = StateStore(copy, "a", 0.1)
            try:
                records = store.logged()
                rec = store.recover()
            finally:
                store.close()
            epoch = int(meta["epoch"])
            if rec.epoch != epoch:
                new_epochs += 1
            seen = watch.seqs(epoch)
            lost += sum(1 for s in seen if s > rec.seq)
            for s, delta in records:
                saw = watch.digest(epoch, s)
                if saw:
                    logged_seen += 1
                    if saw != {delta_digest(delta)}:
                        mismatched += 1
            want = layer_digest(rec.grid)
            shutil.rmtree(copy, ignore_errors=True)
            # Restart (the last time without its source, so the colony can settle) and compare
            # the layer it recovered with the offline recovery of the same files.
            if i == kills - 1:
                a.args = [x for x in a.args if x != mapping[0] and x != "--source"]
            before = _ready_count(a)
            a.start()
            wait_for("a ready", _more_ready(a, before), 30, 0.02)
            got = _digest_lines(a)[-1]
            if got != want:
                restart_mismatch += 1
                log.error("restart %d: layer digest %s, recovered offline %s", i, got, want)
        converge = colony.wait_converged(60, ["a", "b"])
        reports = reports_of(colony, ["a", "b"], digest=True)
        figures = {
            "kills": kills,
            "kill_after_ms": kill_ms,
            "records_lost": lost,
            "seq_reused": watch.reused() + mismatched,
            "logged_records_checked": logged_seen,
            "restart_mismatch": restart_mismatch,
            "crash_new_epochs": new_epochs,
            "crash_final_seq": seq_of(reports, "a", "a"),
            "crash_converge_s": round(converge, 2),
            "crash_peer_equal": reports["a"]["layers"]["a"]["digest"]
            == reports["b"]["layers"]["a"]["digest"],
        }
        watch.close()
    except Exception:
        log.error("crash scenario failed; daemon logs:\n%s", colony.logs())
        raise
    finally:
        watch_session.close()
        colony.close()
    return figures


# ------------------------------------------------------------------------------------ freeze


def freeze(
    base: Path, *, lease_ms: int = 1000, frozen_s: float = 3.0, scans: int = 40
) -> dict[str, Any]:
    """SIGSTOP one of three mapping daemons past the lease: the others map and converge between
    themselves; after SIGCONT it catches up (`freeze_catchup_s`: to the others' seqs at SIGCONT)."""
    colony = LocalColony(base, colony="freeze", lease_ms=lease_ms, heartbeat_s=0.5)
    a = colony.add("a", src(1, scans))
    time.sleep(0.3)
    colony.add("b", src(2, scans))
    c = colony.add("c", src(3, scans))
    try:
        colony.wait_members(3, timeout=30)
        time.sleep(1.0)
        c.signal(19)  # SIGSTOP
        stopped = reports_of(colony, ["a", "b"], timeout=0.5)
        t0 = time.monotonic()
        time.sleep(frozen_s)
        during = reports_of(colony, ["a", "b"], timeout=0.5)
        a_progress = seq_of(during, "a", "a") - seq_of(stopped, "a", "a")
        # b's replica read after a's own seq: in one round a loaded b may answer before a, and
        # a's deltas since then read as lag
        b_after = reports_of(colony, ["b"], timeout=0.5)
        b_lag = max(0, seq_of(during, "a", "a") - seq_of(b_after, "b", "a"))
        c.signal(18)  # SIGCONT
        frozen = time.monotonic() - t0
        want = {o: seq_of(during, o, o) for o in ("a", "b")}
        catchup = wait_holding(colony, want, ["c"], 30)
        converge = colony.wait_converged(60)
        return {
            "freeze_s": round(frozen, 2),
            "freeze_lease_ms": lease_ms,
            "freeze_others_progress": a_progress,
            "freeze_peer_lag_while_frozen": b_lag,
            "freeze_catchup_s": round(catchup, 2),
            "freeze_converge_s": round(converge, 2),
            "freeze_alive": a.alive() and c.alive(),
        }
    except Exception:
        log.error("freeze scenario failed; daemon logs:\n%s", colony.logs())
        raise
    finally:
        c.signal(18)
        colony.close()


# ----------------------------------------------------------------------------------- hostile


def hostile_frames(target: str, other: str, seed: int = 3) -> list[tuple[str, bytes]]:
    """(topic, frame) pairs a hostile peer puts on `<origin>/<topic>` keys: random bytes, bad
    prefixes and versions, truncation, decompression and object bombs, bad fields, huge."""
    import msgpack
    import zstandard

    from colonyd.frames import Sender
    from protocol import Heartbeat, VoxelDelta
    from protocol.codec import MAGIC, PREFIX
    from voxel.delta import Delta

    rng = np.random.default_rng(seed)
    forger = Sender("evil", 1)
    ok_delta = Delta(0.1, 0, 1, np.array([[0, 0, 0]]), np.array([0.5]), np.array([1.0]))
    delta = forger.encode(VoxelDelta(**forger.header(), frame_id="map", delta=ok_delta))
    hb = forger.encode(Heartbeat(**forger.header(), kind="robot", frame_id="map"))

    def frame(mtype: int, envelope: object, flags: int = 0, version: int = 1) -> bytes:
        body: bytes = msgpack.packb(envelope, use_bin_type=True)
        return PREFIX.pack(MAGIC, version, mtype, flags, 0) + body

    bomb = zstandard.ZstdCompressor(level=19).compress(b"\0" * (200 << 20))
    out: list[tuple[str, bytes]] = []
    for topic, good, mtype in (
        ("delta", delta, VoxelDelta.TYPE),
        ("heartbeat", hb, Heartbeat.TYPE),
    ):
        out += [
            (topic, b""),
            (topic, b"\x00"),
            (topic, rng.bytes(7)),
            (topic, rng.bytes(4096)),
            (topic, good[:8] + rng.bytes(200)),  # a valid prefix, garbage after it
            (topic, good[: len(good) // 2]),  # truncated
            (topic, good[:4] + b"\x09" + good[5:]),  # a future protocol version
            (topic, good[:5] + b"\x77" + good[6:]),  # an unknown message type
            # a decompression bomb behind a fresh envelope (the receiver checks the envelope,
            # and a frame's signature where its key is not in its body, before decompressing:
            # the heartbeat's bomb reaches the decompression, the delta's is refused unsigned)
            (topic, frame(mtype, [*forger.header().values(), bomb], flags=1 << 1)),
            (
                topic,
                frame(
                    mtype,
                    [
                        "evil",
                        1,
                        2,
                        3.0,
                        msgpack.packb(
                            [[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[0]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]
                        ),
                    ],
                ),
            ),
            (topic, frame(mtype, ["evil", -1, -2, float("nan"), b""])),  # bad envelope fields
            (
                topic,
                frame(mtype, ["evil", 1, 2, 3.0, msgpack.packb({"frame_id": 7, "layers": "x"})]),
            ),
        ]
    bad_fields = [
        # another resolution
        Delta(0.37, 0, 1, np.array([[0, 0, 0]]), np.array([0.5]), np.array([1.0])),
        # a key out of range
        Delta(0.1, 0, 1, np.array([[2**40, 0, 0]]), np.array([0.5]), np.array([1.0])),
        # log-odds not finite
        Delta(0.1, 0, 1, np.array([[0, 0, 0]]), np.array([np.inf]), np.array([1.0])),
    ]
    for d in bad_fields:
        try:
            out.append(
                ("delta", forger.encode(VoxelDelta(**forger.header(), frame_id="map", delta=d)))
            )
        except Exception as exc:  # noqa: BLE001 - the encoder itself refuses it: nothing to send
            log.debug("hostile frame not encodable: %s", exc)
    zero = Sender("evil", 0)  # epoch 0 is not a layer epoch
    out.append(("delta", zero.encode(VoxelDelta(**zero.header(), frame_id="map", delta=ok_delta))))
    # Another agent's origin on evil's key, and the target's own origin sent to it.
    mimic = Sender(other, 1)
    out.append(
        ("delta", mimic.encode(VoxelDelta(**mimic.header(), frame_id="map", delta=ok_delta)))
    )
    # (An hour old: a fresh one of another epoch would be a live twin, which a young daemon
    # gives way to, by design; see DAEMON.md.)
    own = Sender(target, 1)
    stale = own.header()
    stale["time"] = time.time() - 3600
    out.append(("heartbeat:own", own.encode(Heartbeat(**stale, kind="robot", frame_id="map"))))
    out.append(("delta", delta[:8] + rng.bytes(70 << 20)))  # huge: above max_message_mb
    return out


def hostile(base: Path) -> dict[str, Any]:
    """Every kind of hostile input on every key two daemons listen to, in an open colony and in
    a closed one (colony key): all rejected and counted; with a key, no layer changes."""
    figures: dict[str, Any] = {}
    for closed in (False, True):
        figures.update(_hostile_round(base / ("closed" if closed else "open"), closed))
    figures["rejected"] = dict(
        Counter(figures.pop("rejected_open")) + Counter(figures.pop("rejected_closed"))
    )
    return figures


def _hostile_round(base: Path, closed: bool) -> dict[str, Any]:
    from colonyd.frames import Sender
    from protocol import DeltaRangeRequest, SnapshotRequest
    from protocol.keyexpr import Topic, query_key, topic_key

    secret = "correct horse battery staple"
    label = "closed" if closed else "open"
    colony = LocalColony(
        base,
        colony=f"hostile-{label}",
        heartbeat_s=0.5,
        extra=["--colony-key", secret] if closed else [],
    )
    colony.add("a", src(1, 6))
    time.sleep(0.3)
    colony.add("b", src(2, 6))
    try:
        colony.wait_converged(40)
        before = reports_of(colony, ["a", "b"], digest=True)
        s = colony.session()
        ns = colony.namespace
        sent = 0
        frames = hostile_frames("a", "b")
        # Replays: real frames of a and b captured on the wire and put again.
        captured: list[tuple[str, bytes]] = []

        def keep(sample: Any) -> None:
            if len(captured) < 20:
                captured.append((str(sample.key_expr), sample.payload.to_bytes()))

        sub = s.declare_subscriber(f"colony/{ns}/*/heartbeat", keep)
        wait_for("heartbeats to replay", lambda: len(captured) >= 4, 30)
        sub.undeclare()
        for key, raw in captured[:4]:
            s.put(key, raw)
            sent += 1
        for topic, raw in frames:
            if topic == "heartbeat:own":  # the target's own origin, to the target
                s.put(topic_key(ns, "a", "heartbeat"), raw)
            else:  # (blocking: a huge frame is not dropped on the way by congestion control)
                s.put(
                    topic_key(ns, "evil", cast(Topic, topic)),  # "delta" or "heartbeat"
                    raw,
                    congestion_control=zenoh.CongestionControl.BLOCK,
                )
            sent += 1
            time.sleep(0.01)
        # Queries: hostile request payloads on every queryable of both daemons.
        queries = 0
        junk = [b"", b"\x00", os.urandom(300)]
        forger = Sender("evil", 1)
        # Valid requests that do not match the key they are sent on (another layer), and a
        # message of another type as a request.
        junk.append(forger.encode(SnapshotRequest(**forger.header(), layer="b", request_id=1)))
        junk.append(
            forger.encode(
                DeltaRangeRequest(
                    **forger.header(), layer="zz", request_id=2, from_version=1, to_version=5
                )
            )
        )
        junk.append(frames[-3][1])  # a VoxelDelta of b as a request
        for server in ("a", "b"):
            for q in ("snapshot", "deltas"):
                for payload in junk:
                    for reply in s.get(query_key(ns, server, q, "a"), payload=payload, timeout=2.0):
                        del reply
                    queries += 1
        # Every hostile frame reaches both daemons, every query one: each must be counted (the
        # replays of real heartbeats are harmless repeats in an open colony, so not required).
        expected = len(frames) + queries // 2

        def count(after: dict[str, dict[str, Any]]) -> dict[str, int]:
            per_daemon = {}
            for agent in ("a", "b"):
                c0, c1 = before[agent]["metrics"]["counts"], after[agent]["metrics"]["counts"]
                per_daemon[agent] = sum(
                    c1.get(k, 0) - c0.get(k, 0) for k in ("rejected", "inbox_dropped", "duplicates")
                )
            return per_daemon

        # A loaded daemon may take seconds over the bombs and the huge frame: read the counts
        # once every frame is counted, or after 30 s (the figures then say what was not).
        deadline = time.monotonic() + 30
        while True:
            time.sleep(0.5)
            after = reports_of(colony, ["a", "b"], digest=True)
            per_daemon = count(after)
            if all(v >= expected for v in per_daemon.values()) or time.monotonic() > deadline:
                break
        rejected = rejected_total(after)
        for r in before.values():
            rejected.subtract(r["metrics"]["rejected"])
        unchanged = all(
            after[h]["layers"][o]["digest"] == before[h]["layers"][o]["digest"]
            for h in ("a", "b")
            for o in ("a", "b")
        )
        foreign = sorted({o for r in after.values() for o in r["layers"]} - {"a", "b"})
        alive = all(d.alive() for d in colony.daemons.values())
        return {
            f"hostile_{label}_sent": sent,
            f"hostile_{label}_all_counted": all(v >= expected for v in per_daemon.values()),
            f"hostile_{label}_queries": queries,
            f"hostile_{label}_counted": per_daemon,
            f"hostile_{label}_layers_unchanged": unchanged,
            f"hostile_{label}_foreign_layers": foreign,
            f"hostile_{label}_alive": alive,
            f"rejected_{label}": {k: v for k, v in rejected.items() if v},
        }
    except Exception:
        log.error("hostile scenario failed; daemon logs:\n%s", colony.logs())
        raise
    finally:
        colony.close()


# -------------------------------------------------------------------------------------- disk


def disk(base: Path, *, size_mb: float = 6.0) -> dict[str, Any]:
    """A mapping daemon's state directory on a small tmpfs that fills up mid-run: a clear error,
    mapping and the colony go on, the last good snapshot stays intact; freed, it catches up."""
    from colonyd.grid import load_grid

    reason = need_root("the disk scenario (a tmpfs mount)")
    if reason:
        raise Skip(reason)
    colony = LocalColony(base / "colony", colony="disk", heartbeat_s=0.5)
    # b maps until the end (scans=0): with 60 scans (15 s) a loaded start had it done before
    # the disk filled, and its progress while a's disk is full read 0.
    colony.add("b", src(2, 0))
    time.sleep(0.3)
    mount = Tmpfs(base / "colony" / "a", size_mb)
    with mount:
        a = colony.add("a", src(1, 0, rate=4), extra=["--publish-hz", "4"], start=False)
        a.env["COLONYD_SNAPSHOT_S"] = "1"
        a.start()
        try:
            wait_for("a snapshots", (a.state_dir / "snapshot.json").exists, 30)
            wait_for("b holds a", lambda: seq_of(by_agent(colony), "b", "a") >= 3, 30)
            mount.fill()
            t_full = time.monotonic()
            error = ""

            def noticed() -> bool:
                nonlocal error
                error = by_agent(colony).get("a", {}).get("state_error", "")
                return bool(error)

            notice_s = wait_for("a reports the full disk", noticed, 20)
            r0 = reports_of(colony, ["a", "b"])
            time.sleep(3.0)  # several publish and snapshot attempts fail meanwhile
            r1 = reports_of(colony, ["a", "b"])
            # b's progress meanwhile: on a loaded machine (the suite's other worker) b once
            # published nothing in those 3 s; it is given up to 20 s more, a's disk still full.
            deadline = time.monotonic() + 20
            while seq_of(r1, "b", "b") <= seq_of(r0, "b", "b") and time.monotonic() < deadline:
                time.sleep(0.5)
                r1 = reports_of(colony, ["a", "b"])
            frames = r1["a"]["metrics"]["counts"].get("frames", 0) - r0["a"]["metrics"][
                "counts"
            ].get("frames", 0)
            snap = json.loads((a.state_dir / "snapshot.json").read_text())
            grid = load_grid(a.state_dir / snap["file"])
            intact = grid is not None and int(snap["seq"]) >= 1
            b_progress = seq_of(r1, "b", "b") - seq_of(r0, "b", "b")
            a_seq_full = seq_of(r1, "a", "a")
            mount.free()
            t_free = time.monotonic()
            wait_for(
                "a publishes again", lambda: seq_of(by_agent(colony), "b", "a") > a_seq_full, 30
            )
            resume = time.monotonic() - t_free
            cleared = not reports_of(colony, ["a"])["a"].get("state_error")
            return {
                "disk_full_error": error,
                "disk_noticed_s": round(notice_s, 2),
                "disk_frames_mapped_while_full": frames,
                "disk_seq_held_while_full": seq_of(r1, "a", "a") - seq_of(r0, "a", "a") == 0,
                "disk_peer_progress_while_full": b_progress,
                "disk_snapshot_intact": intact,
                "disk_full_s": round(t_free - t_full, 1),
                "disk_resume_s": round(resume, 2),
                "disk_error_cleared": cleared,
                "disk_alive": a.alive(),
            }
        except Exception:
            log.error("disk scenario failed; daemon logs:\n%s", colony.logs())
            raise
        finally:
            colony.close()


# --------------------------------------------------------------------------------- partition


def partition(
    base: Path, *, lease_ms: int = 1500, cut_s: float = 4.0, scans: int = 80
) -> dict[str, Any]:
    """Three daemons in their own network namespaces on a bridge; c's link is cut during
    mapping and restored: both sides keep mapping, every replica converges after the heal.
    `scans` (at 4 a second) must outlast the start: a starts mapping when it is ready, and on a
    loaded machine b and c took 6-10 s more to start, so 48 scans were over before the cut."""
    reason = need_root("the partition scenario (network namespaces)")
    if reason:
        raise Skip(reason)
    names = ["a", "b", "c"]
    with NetLab(names) as lab:
        colony = LocalColony(base, colony="partition", lease_ms=lease_ms, heartbeat_s=0.5)
        try:
            for i, name in enumerate(names):
                colony.add(name, src(i + 1, scans), host=lab.hosts[name], prefix=lab.prefix(name))
                if i == 0:
                    time.sleep(0.5)
            colony.wait_members(3, timeout=30)
            time.sleep(1.0)
            # (The observer reaches the daemons through the same switch: while c's link is cut
            # it sees a and b only; c's side is read right after the heal.)
            r0 = reports_of(colony, names)
            lab.cut("c")
            t_cut = time.monotonic()
            time.sleep(1.0)
            # a's answer is what the progress needs; b's is used when it came (b may not answer
            # for seconds during a cut, RELIABILITY.md: waiting would let a finish mapping)
            r_cut = reports_of(colony, ["a"], timeout=0.5)
            time.sleep(cut_s - 1.0)
            r1 = reports_of(colony, ["a", "b"])
            a_side = seq_of(r1, "a", "a") - seq_of(r_cut, "a", "a")
            b_lag = seq_of(r1, "a", "a") - seq_of(r1, "b", "a")
            saw_c = max(
                seq_of(r1, h, "c") - seq_of(r_cut, h, "c") for h in ("a", "b") if h in r_cut
            )
            log.info(
                "partition: during the cut %s",
                {h: {o: seq_of(r1, h, o) for o in names} for h in r1},
            )
            lab.heal("c")
            cut = time.monotonic() - t_cut
            t_heal = time.monotonic()
            wait_for("c answers after the heal", lambda: "c" in by_agent(colony, timeout=0.5), 30)
            rc = reports_of(colony, names)
            c_side = seq_of(rc, "c", "c") - seq_of(r0, "c", "c")
            c_saw_a = seq_of(rc, "c", "a")  # before any repair: what leaked across the cut
            want = {"a": seq_of(r1, "a", "a"), "b": seq_of(r1, "b", "b"), "c": seq_of(rc, "c", "c")}
            wait_holding(colony, want, names, 60)
            heal = time.monotonic() - t_heal
            converge = colony.wait_converged(90)
            return {
                "partition_cut_s": round(cut, 2),
                "partition_lease_ms": lease_ms,
                "partition_majority_progress": a_side,
                "partition_minority_progress": c_side,
                "partition_majority_lag": b_lag,
                "partition_minority_held_a": c_saw_a,
                "partition_majority_saw_c": saw_c,
                "partition_majority_a_seq_at_heal": want["a"],
                "partition_heal_s": round(heal, 2),
                "partition_converge_s": round(converge, 2),
            }
        except Exception:
            log.error("partition scenario failed; daemon logs:\n%s", colony.logs())
            raise
        finally:
            colony.close()


# -------------------------------------------------------------------------------------- busy


#: A delta's hand-offs in the order of its path (`Metrics.stages`): at the origin, then at each
#: replica. A stage is named by the hand-off that ends it and runs from the one before.
OUT_MARKS = ("created", "logged", "numbered", "encoded", "put", "sent")
IN_MARKS = ("entered", "queued", "dequeued", "decoded", "admitted", "applied")
#: Stage names (the mark ending each): what each one is, in docs/RELIABILITY.md.
STAGES = {
    "logged": "log",
    "numbered": "number",
    "encoded": "encode",
    "put": "remember",
    "sent": "put",
    "entered": "transport",
    "queued": "copy",
    "dequeued": "queue",
    "decoded": "decode",
    "admitted": "admit",
    "applied": "apply",
}


def _stats(values: list[float]) -> dict[str, float | None]:
    return {
        "p50": percentile(values, 50),
        "p99": percentile(values, 99),
        "mean": round(float(np.mean(values)), 2) if values else None,
    }


#: Stages that cross threads: the receiving thread's clocks are split from its own earlier
#: stamp (the Zenoh callback thread's last return; the inbox thread's end of its last item).
SPLIT_FROM = {"entered": "idle", "dequeued": "waited"}
#: How a stage's wall time splits (`threadclock`): on a core (`cpu`), runnable but waiting for
#: one (`runq`), the receiving thread still busy with earlier items (`behind`), and the rest
#: (`blocked`: the interpreter lock, other locks, I/O; in `transport` also the network and
#: Zenoh's own threads).
SPLITS = ("cpu", "runq", "behind", "blocked")


def _split(times: dict[str, float], before: str, after: str) -> dict[str, float] | None:
    """The stage (before, after) split into `SPLITS`, ms, from one thread's stamps; None
    without them (a daemon on another OS, or marks of another build)."""
    start = SPLIT_FROM.get(after, before)
    keys = (f"{start}.cpu", f"{start}.runq", f"{after}.cpu", f"{after}.runq")
    if start not in times or not all(k in times for k in keys):
        return None
    cpu = (times[f"{after}.cpu"] - times[f"{start}.cpu"]) * 1000
    runq = (times[f"{after}.runq"] - times[f"{start}.runq"]) * 1000
    behind = max(0.0, times[start] - times[before]) * 1000
    wall = (times[after] - times[before]) * 1000
    return {"cpu": cpu, "runq": runq, "behind": behind, "blocked": wall - cpu - runq - behind}


def stage_breakdown(reports: list[dict[str, Any]], since: float = 0.0) -> dict[str, dict[str, Any]]:
    """Where a delta's time goes, ms, per delivery (one delta at one replica, joined by origin
    and seq): p50 / p99 / mean of every stage between two hand-offs (`STAGES`), of their sum
    (`total`, creation to application at that replica) and of `unmeasured` (the replica's own
    propagation sample, wall clock, minus `total`: time outside the marks); `tail_mean`: the mean
    over the slowest 10 % of deliveries; `split` / `split_tail`: each stage's mean over all /
    over the slowest 10 % split into `SPLITS` (where the daemons stamp thread clocks), and the
    same summed over the stages in `total`. Only deltas created at `since` (monotonic) or
    later."""
    out_side: dict[tuple[str, int], dict[str, float]] = {}
    for r in reports:
        for side, origin, seq, marks in r["metrics"].get("stages", []):
            if side == "out" and marks["created"] >= since:
                out_side[(origin, int(seq))] = marks
    wall: dict[tuple[str, str, int], float] = {}
    for r in reports:
        for origin, seq, created, at, *_ in r["metrics"].get("samples", []):
            wall[(r["agent"], origin, int(seq))] = (float(at) - float(created)) * 1000
    names = [*STAGES.values(), "total", "unmeasured"]
    parts: dict[str, list[float]] = {k: [] for k in names}
    splits: dict[str, list[dict[str, float] | None]] = {k: [] for k in STAGES.values()}
    for r in reports:
        for side, origin, seq, marks in r["metrics"].get("stages", []):
            sent = out_side.get((origin, int(seq)))
            if side != "in" or sent is None:
                continue
            times = {**sent, **marks}
            path = [m for m in OUT_MARKS + IN_MARKS if m in times]
            for before, after in pairwise(path):
                parts[STAGES[after]].append((times[after] - times[before]) * 1000)
                splits[STAGES[after]].append(_split(times, before, after))
            total = (times["applied"] - times["created"]) * 1000
            parts["total"].append(total)
            measured = wall.get((r["agent"], origin, int(seq)))
            if measured is not None:
                parts["unmeasured"].append(measured - total)
    out: dict[str, dict[str, Any]] = {k: dict(_stats(v)) for k, v in parts.items()}
    total = np.asarray(parts["total"])
    if not len(total):
        return out
    # The tail: what each stage contributes, on average, to the slowest 10 % of deliveries
    # (every delivery has every stage but `unmeasured`, which is left out here).
    slow = total >= np.percentile(total, 90)
    sums = {"split": np.zeros(len(SPLITS)), "split_tail": np.zeros(len(SPLITS))}
    for k in STAGES.values():
        if len(parts[k]) != len(total):
            continue
        out[k]["tail_mean"] = round(float(np.asarray(parts[k])[slow].mean()), 2)
        nan = [float("nan")] * len(SPLITS)
        table = np.asarray([nan if x is None else [x[n] for n in SPLITS] for x in splits[k]])
        stamped = ~np.isnan(table[:, 0])
        for name, rows in (("split", table[stamped]), ("split_tail", table[slow & stamped])):
            if not len(rows):
                continue
            means = rows.mean(axis=0)
            out[k][name] = {n: round(float(v), 2) for n, v in zip(SPLITS, means, strict=True)}
            sums[name] += means
    out["total"]["tail_mean"] = round(float(total[slow].mean()), 2)
    for name, v in sums.items():
        out["total"][name] = {n: round(float(x), 2) for n, x in zip(SPLITS, v, strict=True)}
    return out


def tail_activity(reports: list[dict[str, Any]], since: float = 0.0) -> dict[str, dict[str, float]]:
    """What the daemons were busy with while the slowest deliveries travelled: per activity
    (`Metrics.activity`: collector passes `gc0`-`gc2`, periodic jobs, worker items) and role
    (at the delta's `origin`, at the `replica` applying it, at an `other` daemon), the share of
    the slowest 10 % of deliveries whose path (creation to application) it overlapped, and the
    same share over all deliveries: an activity behind the tail has a much larger `tail` share
    than `all`. Only deltas created at `since` (monotonic) or later."""
    acts = {r["agent"]: r["metrics"].get("activity", []) for r in reports}
    created: dict[tuple[str, int], float] = {}
    for r in reports:
        for side, origin, seq, marks in r["metrics"].get("stages", []):
            if side == "out" and marks["created"] >= since:
                created[(origin, int(seq))] = marks["created"]
    paths: list[tuple[float, float, str, str]] = []  # (created, applied, origin, replica)
    for r in reports:
        for side, origin, seq, marks in r["metrics"].get("stages", []):
            t0 = created.get((origin, int(seq)))
            if side == "in" and t0 is not None and "applied" in marks:
                paths.append((t0, marks["applied"], origin, r["agent"]))
    if not paths:
        return {}
    took = np.asarray([t1 - t0 for t0, t1, _, _ in paths])
    slow = took >= np.percentile(took, 90)
    hits: dict[str, np.ndarray] = {}
    for i, (t0, t1, origin, replica) in enumerate(paths):
        for agent, entries in acts.items():
            role = "origin" if agent == origin else "replica" if agent == replica else "other"
            for name, _thread, start, end in entries:
                if start < t1 and end > t0 and not (role == "replica" and name == "inbox-delta"):
                    hits.setdefault(f"{name}@{role}", np.zeros(len(paths), bool))[i] = True
    out = {
        k: {"tail": round(float(v[slow].mean()), 3), "all": round(float(v.mean()), 3)}
        for k, v in hits.items()
    }
    return dict(sorted(out.items(), key=lambda kv: -kv[1]["tail"]))


def propagation_ms(
    reports: list[dict[str, Any]], agents: list[str], since: float = 0.0
) -> list[float]:
    """Per (origin, seq) delta created at `since` (epoch s) or later: ms from creation to its
    application on the last other peer (as `bench colony` computes it)."""
    return [ms for ms, _ in _slowest(reports, agents, since).values()]


def _slowest(
    reports: list[dict[str, Any]], agents: list[str], since: float = 0.0
) -> dict[tuple[str, int], tuple[float, str]]:
    """Per delta held by every other peer: (ms to the last of them, how that one got it)."""
    applied: dict[tuple[str, int], list[tuple[float, str]]] = {}
    for r in reports:
        for origin, seq, created, at, *via in r["metrics"].get("samples", []):
            if origin != r["agent"] and float(created) >= since:
                ms = (float(at) - float(created)) * 1000
                applied.setdefault((origin, int(seq)), []).append((ms, via[0] if via else "?"))
    return {k: max(v) for k, v in applied.items() if len(v) >= len(agents) - 1}


def delivery_paths(
    reports: list[dict[str, Any]], agents: list[str], since: float = 0.0
) -> dict[str, Any]:
    """How the last peer got each delta ("frame": as it arrived; "held": buffered behind a gap;
    "range": by a repair) and the propagation p99 over deltas that every peer applied as they
    arrived, with the per-delivery p99 (one replica, not the slowest of them)."""
    slowest = _slowest(reports, agents, since)
    framed = [ms for ms, via in slowest.values() if via == "frame"]
    deliveries = [
        (float(at) - float(created)) * 1000
        for r in reports
        for origin, _seq, created, at, *_ in r["metrics"].get("samples", [])
        if origin != r["agent"] and float(created) >= since
    ]
    return {
        "via": dict(Counter(via for _, via in slowest.values())),
        "p99_frame_only_ms": percentile(framed, 99),
        "delivery_p50_ms": percentile(deliveries, 50),
        "delivery_p99_ms": percentile(deliveries, 99),
    }


#: Seconds a propagation run maps beyond `duration`: the daemons start mapping at once, and
#: only the deltas created once all of them are members count.
JOIN_S = 10.0

#: Counters (summed over the daemons) a propagation run reports.
PROPAGATION_COUNTS = ("deltas_published", "deltas_applied", "gaps", "inbox_dropped", "duplicates")


def propagation(
    base: Path, *, daemons: int = 4, duration: float = 10.0, extra: list[str] | None = None
) -> dict[str, Any]:
    """N daemons mapping at 2 deltas/s: propagation (creation to application on the last other
    peer) p50 / p99, and the stage breakdown, over the deltas created once every daemon is a
    member (those before cannot reach a late starter as frames) and warm (start-up over)."""
    scans = max(2, int((duration + JOIN_S) * 2))
    colony = LocalColony(base, colony="prop", heartbeat_s=1.0, extra=extra)
    agents = [f"d{i}" for i in range(daemons)]
    load = [round(os.getloadavg()[0], 1)]
    t0 = time.monotonic()
    try:
        for i, agent in enumerate(agents):
            colony.add(agent, [f"synthetic:scans={scans},rate=2,points=120,seed={i + 1}"])
            if i == 0:
                time.sleep(0.3)
        colony.wait_members(daemons, timeout=90)  # a loaded machine starts slowly
        # and every daemon's start-up is over (kernels loaded, first-use imports done: `warm`)
        colony.wait_status(lambda reps: all(r.get("warm") for r in reps), 60, agents)
        since, since_mono = time.time(), time.monotonic()
        joined_s = round(since_mono - t0, 1)
        colony.wait_converged(duration + 60, agents)
        load.append(round(os.getloadavg()[0], 1))
        reports = colony.status(samples=True)
        lat = propagation_ms(reports, agents, since)
        counts: Counter[str] = Counter()
        for r in reports:
            c = r["metrics"]["counts"]
            counts.update({k: c.get(k, 0) for k in PROPAGATION_COUNTS})
        return {
            "p50_ms": percentile(lat, 50),
            "p99_ms": percentile(lat, 99),
            "samples": len(lat),
            "joined_s": joined_s,
            "load": load,
            "counts": dict(counts),
            "paths": delivery_paths(reports, agents, since),
            "stages_ms": stage_breakdown(reports, since_mono),
            "tail_activity": tail_activity(reports, since_mono),
        }
    except Exception:
        log.error("propagation run failed; daemon logs:\n%s", colony.logs())
        raise
    finally:
        colony.close()


def busy(base: Path, *, duration: float = 10.0, sync_first: bool = False) -> dict[str, Any]:
    """Propagation with 4 daemons, quiet and while another process keeps one core busy
    (`sync_first`: each delta fsync'ed before it is published). The compiled kernels are
    compiled into their cache first: with none (a fresh checkout, an edited kernels module)
    every daemon would compile them in the measured window, ~11 s of CPU each."""
    kernels.warm()
    extra = ["--sync-before-publish"] if sync_first else None
    quiet = propagation(base / "quiet", duration=duration, extra=extra)
    with Spinner():
        loaded = propagation(base / "busy", duration=duration, extra=extra)
    return {
        "busy_sync_before_publish": sync_first,
        "quiet_p50_ms": quiet["p50_ms"],
        "quiet_p99_ms": quiet["p99_ms"],
        "busy_p50_ms": loaded["p50_ms"],
        "busy_p99_ms": loaded["p99_ms"],
        "busy_samples": loaded["samples"],
        "quiet_samples": quiet["samples"],
        "quiet_stages_ms": quiet["stages_ms"],
        "busy_stages_ms": loaded["stages_ms"],
        "quiet_tail_activity": quiet["tail_activity"],
        "busy_tail_activity": loaded["tail_activity"],
        "quiet_paths": quiet["paths"],
        "busy_paths": loaded["paths"],
        "quiet_run": {k: quiet[k] for k in ("joined_s", "load", "counts")},
        "busy_run": {k: loaded[k] for k in ("joined_s", "load", "counts")},
    }


# ------------------------------------------------------------------------------------- flood


def flood(
    base: Path, *, flooders: int = 3, rate_x: int = 10, seconds: float = 8.0
) -> dict[str, Any]:
    """Several peers at `rate_x` times the normal delta rate (2/s) into one mapping daemon:
    its peak RSS, its own mapping rate, the deltas/s it applies; nothing crashes."""
    hz = 2 * rate_x
    colony = LocalColony(base, colony="flood", heartbeat_s=1.0, extra=["--log-level", "warning"])
    target = colony.add("t", src(9, int(seconds * 2) + 6, rate=2, points=200))
    time.sleep(0.3)
    try:
        colony.wait_members(1, timeout=20)
        for i in range(flooders):
            colony.add(
                f"f{i}",
                src(10 + i, int(seconds * hz), rate=hz, points=400),
                extra=["--publish-hz", str(hz)],
            )
        colony.wait_members(1 + flooders, timeout=30)
        assert target.proc is not None
        rss_start = peak_rss_mb(target.proc.pid)
        r0 = reports_of(colony, ["t"])
        t0 = time.monotonic()
        time.sleep(seconds)
        r1 = reports_of(colony, ["t"])
        dt = time.monotonic() - t0
        c0, c1 = r0["t"]["metrics"]["counts"], r1["t"]["metrics"]["counts"]
        applied = (c1.get("deltas_applied", 0) - c0.get("deltas_applied", 0)) / dt
        offered = (
            sum(
                seq_of(r1, f"f{i}", f"f{i}") - seq_of(r0, f"f{i}", f"f{i}") for i in range(flooders)
            )
            / dt
        )
        own_rate = (c1.get("frames", 0) - c0.get("frames", 0)) / dt
        peak = peak_rss_mb(target.proc.pid)
        converge = colony.wait_converged(90)
        most = saturate(colony, target)
        return {
            **most,
            "flood_peers": flooders,
            "flood_rate_x": rate_x,
            "flood_offered_deltas_per_s": round(offered, 1),
            "flood_deltas_per_s": round(applied, 1),
            "flood_own_frames_per_s": round(own_rate, 2),
            "flood_peak_rss_mb": round(peak, 1),
            "flood_rss_at_start_mb": round(rss_start, 1),
            "flood_inbox_dropped": c1.get("inbox_dropped", 0) - c0.get("inbox_dropped", 0),
            "flood_converge_s": round(converge, 2),
            "flood_alive": all(d.alive() for d in colony.daemons.values()),
        }
    except Exception:
        log.error("flood scenario failed; daemon logs:\n%s", colony.logs())
        raise
    finally:
        colony.close()


def saturate(
    colony: LocalColony,
    target: LocalDaemon,
    *,
    origins: int = 4,
    frames: int = 250,
    rate: float = 400.0,
) -> dict[str, Any]:
    """The delta rate one daemon sustains: `origins` signed peers put real-sized deltas (a
    synthetic scan's, ~4.5k voxels) at `rate` deltas/s in all, more than it can take; the
    deltas it applied per second until its inbox was worked through, its drops, peak RSS."""
    import threading

    from colonyd.frames import Sender
    from colonyd.grid import new_grid
    from colonyd.layers import relabel
    from colonyd.mapping import integrate_observation
    from plugins.source import open_source
    from protocol import Heartbeat, VoxelDelta
    from protocol.identity import Signer
    from protocol.keyexpr import topic_key

    scan = open_source(
        "synthetic:scans=1,points=120,seed=5,room=6", resolution=0.1, seed=5, stop=threading.Event()
    )
    grid = new_grid(0.1)
    for obs in scan:
        integrate_observation(
            grid, obs, sensor=scan.adapter.sensor_model, reliability=1.0, agent="s"
        )
    delta = grid.delta_since(0)
    s = colony.session()
    epoch = 1
    streams = []
    for i in range(origins):
        snd = Sender(f"sat{i}", epoch, signer=Signer.generate())
        hb = snd.encode(
            Heartbeat(**snd.header(), kind="robot", frame_id="map", identity=snd.identity)
        )
        msgs = [
            snd.encode(
                VoxelDelta(
                    **snd.header(), frame_id="map", delta=relabel(delta, k, k + 1, time=time.time())
                )
            )
            for k in range(frames)
        ]
        streams.append((f"sat{i}", hb, msgs))
    for name, hb, _ in streams:
        s.put(topic_key(colony.namespace, name, "heartbeat"), hb)
    time.sleep(1.0)
    assert target.proc is not None
    r0 = reports_of(colony, [target.agent])
    count0 = r0[target.agent]["metrics"]["counts"].get("deltas_applied", 0)
    t0 = time.monotonic()
    sent = 0
    for k in range(frames):  # paced at `rate` deltas/s in all
        for name, _, msgs in streams:
            s.put(topic_key(colony.namespace, name, "delta"), msgs[k])
            sent += 1
        time.sleep(max(0.0, t0 + sent / rate - time.monotonic()))
    put_s = time.monotonic() - t0
    # Then until the target has worked through its inbox (its count stops moving).
    last, t_last = count0, t0
    while time.monotonic() - t_last < 1.0:
        time.sleep(0.3)
        counts = reports_of(colony, [target.agent])[target.agent]["metrics"]["counts"]
        now = counts.get("deltas_applied", 0)
        if now != last:
            last, t_last = now, time.monotonic()
    r1 = reports_of(colony, [target.agent])
    c0, c1 = r0[target.agent]["metrics"]["counts"], r1[target.agent]["metrics"]["counts"]
    applied = c1.get("deltas_applied", 0) - count0
    return {
        "saturate_offered_deltas_per_s": round(sent / put_s, 1),
        "saturate_deltas_per_s": round(applied / max(t_last - t0, put_s), 1),
        "saturate_voxels_per_delta": len(delta),
        "saturate_inbox_dropped": c1.get("inbox_dropped", 0) - c0.get("inbox_dropped", 0),
        "saturate_peak_rss_mb": round(peak_rss_mb(target.proc.pid), 1),
        "saturate_alive": target.alive(),
    }


# ------------------------------------------------------------------------------------- scale

ROUTER = """
import signal, sys, threading, zenoh
conf = zenoh.Config()
for k, v in (("mode", '"router"'), ("scouting/multicast/enabled", "false"),
             ("listen/endpoints", '["tcp/127.0.0.1:%d"]' % int(sys.argv[1]))):
    conf.insert_json5(k, v)
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *_: stop.set())
s = zenoh.open(conf)
try:
    print("router up", flush=True)
    stop.wait()
finally:
    s.close()
"""


def _colony_run(base: Path, n: int, *, router: str | None, seconds: float) -> dict[str, Any]:
    """n daemons (peers, or clients of `router`) mapping 4 scans each; convergence time and
    traffic per daemon (all bytes and heartbeat bytes per second)."""
    colony = LocalColony(
        base, colony=f"scale{n}", heartbeat_s=1.0, extra=["--log-level", "warning"]
    )
    agents = [f"r{i:02d}" for i in range(n)]
    try:
        t0 = time.monotonic()
        for i, agent in enumerate(agents):
            d = colony.add(agent, src(i + 1, 4, rate=2, points=120), start=False)
            if router is not None:
                d.args = [x for x in d.args]
                cut = d.args.index("--listen")
                del d.args[cut : cut + 2]
                if "--connect" in d.args:
                    j = d.args.index("--connect")
                    del d.args[j : j + 2]
                d.args += ["--mode", "client", "--connect", router]
            d.start()
            if i == 0 and router is None:
                time.sleep(0.3)
        if router is not None:
            colony._session = open_session(
                zenoh_config(mode="client", connect=[router], multicast=False)
            )
            colony._session_endpoints = [d.endpoint for d in colony.daemons.values() if d.alive()]
        colony.wait_members(n, timeout=60)
        converge = colony.wait_converged(120, agents)
        start_to_converged = time.monotonic() - t0
        r0 = reports_of(colony, list(agents), timeout=3.0)
        time.sleep(seconds)  # idle: heartbeats only
        r1 = reports_of(colony, list(agents), timeout=3.0)
        hb = [
            (
                r1[a]["metrics"]["counts"].get("bytes_heartbeat", 0)
                - r0[a]["metrics"]["counts"].get("bytes_heartbeat", 0)
            )
            / seconds
            for a in agents
        ]
        rx = [
            (
                r1[a]["metrics"]["counts"].get("bytes_received", 0)
                - r0[a]["metrics"]["counts"].get("bytes_received", 0)
            )
            / seconds
            for a in agents
        ]
        total = [r1[a]["metrics"]["counts"].get("bytes_published", 0) for a in agents]
        return {
            "converge_s": round(converge, 2),
            "start_to_converged_s": round(start_to_converged, 2),
            "heartbeat_bytes_per_s_per_daemon": round(float(np.mean(hb)), 1),
            "received_bytes_per_s_per_daemon_idle": round(float(np.mean(rx)), 1),
            "published_bytes_per_daemon": int(np.mean(total)),
        }
    except Exception:
        log.error("scale run failed; daemon logs:\n%s", colony.logs(tail=800))
        raise
    finally:
        colony.close()


def scale(
    base: Path, *, sizes: tuple[int, ...] = (4, 8, 16), seconds: float = 5.0
) -> dict[str, Any]:
    """Colonies of each size in peer mode, and the largest as clients of a Zenoh router."""
    out: dict[str, Any] = {"scale_peer": {}, "scale_client": {}}
    for n in sizes:
        out["scale_peer"][str(n)] = _colony_run(base / f"peer{n}", n, router=None, seconds=seconds)
    port = free_port()
    router = subprocess.Popen(
        [sys.executable, "-c", ROUTER, str(port)],
        stdout=subprocess.PIPE,
        stdin=subprocess.DEVNULL,
        text=True,
    )
    try:
        assert router.stdout is not None
        router.stdout.readline()
        n = max(sizes)
        out["scale_client"][str(n)] = _colony_run(
            base / f"client{n}", n, router=f"tcp/127.0.0.1:{port}", seconds=seconds
        )
    finally:
        router.terminate()
        try:
            router.wait(10)
        except subprocess.TimeoutExpired:
            router.kill()
    return out
