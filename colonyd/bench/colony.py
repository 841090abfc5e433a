"""`colonyd bench colony`: N daemons on loopback; propagation, catch-up (daemons, and step by step
in one process), idle cost, start to ready."""

from __future__ import annotations

import json
import logging
import os
import shutil
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from colonyd.bench.catchup import catchup_steps, start_to_ready
from colonyd.bench.launcher import LocalColony

log = logging.getLogger(__name__)

_TICKS = os.sysconf("SC_CLK_TCK")


def _cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / _TICKS  # utime + stime


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def propagation_ms(reports: list[dict[str, Any]], agents: list[str]) -> list[float]:
    """Per (origin, seq) delta: ms from creation to its application on the last other peer."""
    applied: dict[tuple[str, int], list[float]] = {}
    for r in reports:
        for origin, seq, created, at, *_ in r["metrics"].get("samples", []):
            if origin != r["agent"]:
                applied.setdefault((origin, int(seq)), []).append(float(at) - float(created))
    need = len(agents) - 1
    return [max(v) * 1000 for v in applied.values() if len(v) >= need]


#: Phases of the benchmark, in the order they run.
PHASES = ("gossip", "catchup", "steps", "start")


def run_colony_bench(
    out_json: Path | str,
    *,
    daemons: int = 4,
    duration: float = 10.0,
    catchup_voxels: int | list[int] = 1_000_000,
    catchup_runs: int = 3,
    start_runs: int = 5,
    phases: list[str] | None = None,
) -> dict[str, Any]:
    """Run the phases (all of PHASES unless named) and write the result JSON; returns it.

    gossip: propagation and idle cost of `daemons` daemons; catchup: a newcomer daemon's
    snapshot of a `bulk:` layer of each size in `catchup_voxels`, `catchup_runs` newcomers each
    (the first size's figures also under the keys of one size); steps: the same catch-up step
    by step in this process (CPU); start: `start_runs` daemons from spawn to READY.
    """
    sizes = [catchup_voxels] if isinstance(catchup_voxels, int) else list(catchup_voxels)
    wanted = set(phases or PHASES)
    work = Path(tempfile.mkdtemp(prefix="colonyd-bench-"))
    result: dict[str, Any] = {"daemons": daemons}
    try:
        if "gossip" in wanted:
            result.update(_propagation_and_idle(work / "gossip", daemons, duration))
        if "catchup" in wanted:
            runs = [_catchup(work / f"catchup{n}", n, catchup_runs) for n in sizes]
            result.update(runs[0])
            result["catchups"] = runs
        if "steps" in wanted:
            result["catchup_steps"] = [catchup_steps(n) for n in sizes]
        if "start" in wanted:
            result.update(start_to_ready(work / "start", start_runs))
        result["load_average"] = [round(x, 2) for x in os.getloadavg()]
    finally:
        shutil.rmtree(work, ignore_errors=True)
    out = Path(out_json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")
    return result


def _propagation_and_idle(base: Path, daemons: int, duration: float) -> dict[str, Any]:
    scans = max(2, int(duration * 2))
    colony = LocalColony(base, colony="bench", heartbeat_s=1.0)
    try:
        agents = [f"d{i}" for i in range(daemons)]
        for i, agent in enumerate(agents):
            colony.add(
                agent, [f"synthetic:scans={scans},rate=2,points=120,seed={i + 1}"], start=False
            )
        # The hub first, so the others have someone to connect to.
        for i, agent in enumerate(agents):
            colony.daemons[agent].start()
            if i == 0:
                colony.daemons[agent].wait_listening()
        colony.wait_members(daemons, timeout=30)
        colony.wait_converged(duration + 60, agents)
        reports = colony.status(samples=True)
        lat = propagation_ms(reports, agents)
        # Idle: sources are done; measure CPU over a quiet window.
        pids = [d.proc.pid for d in colony.daemons.values() if d.proc is not None]
        c0 = {p: _cpu_seconds(p) for p in pids}
        t0 = time.monotonic()
        time.sleep(5.0)
        dt = time.monotonic() - t0
        cpu = [100 * (_cpu_seconds(p) - c0[p]) / dt for p in pids]
        rss = [_rss_mb(p) for p in pids]
        bytes_out = sum(int(r["metrics"]["counts"].get("bytes_published", 0)) for r in reports)
    except Exception:
        log.error("colony benchmark failed; daemon logs:\n%s", colony.logs())
        raise
    else:
        return {
            "propagation_p50_ms": round(float(np.percentile(lat, 50)), 2) if lat else None,
            "propagation_p99_ms": round(float(np.percentile(lat, 99)), 2) if lat else None,
            "propagation_samples": len(lat),
            "deltas_per_s_per_daemon": 2.0,
            "idle_cpu_percent": round(max(cpu), 2),
            "idle_cpu_percent_mean": round(float(np.mean(cpu)), 2),
            "rss_mb": round(max(rss), 1),
            "bytes_published": bytes_out,
        }
    finally:
        colony.close()


def _catchup(base: Path, voxels: int, runs: int = 1) -> dict[str, Any]:
    """`runs` newcomers, one after another, each catching up the `bulk:` layer of `voxels`
    voxels from the same holder: seconds from the snapshot request to the installed layer
    (min, median, each run) and each run's timeline (ms after the request, both daemons)."""
    colony = LocalColony(base, colony="catchup", heartbeat_s=1.0)
    try:
        colony.add("big", [f"bulk:voxels={voxels}"])
        deadline = time.monotonic() + 120 + voxels / 50_000
        while time.monotonic() < deadline:
            reports = colony.status(timeout=1.0)
            big = next((r for r in reports if r["agent"] == "big"), None)
            if big and big["layers"].get("big", {}).get("seq", 0) >= 1 and not big["unpublished"]:
                break
            time.sleep(0.3)
        else:
            raise TimeoutError("the bulk daemon did not publish its layer")
        done = [_newcomer(colony, f"newcomer{i}", voxels) for i in range(runs)]
        seconds = [d["catchup_s"] for d in done]
        walls = [d["catchup_wall_s_incl_process_start"] for d in done]
        return {
            "catchup_voxels": done[0]["catchup_voxels"],
            "catchup_s": round(min(seconds), 3),
            "catchup_s_median": round(statistics.median(seconds), 3),
            "catchup_s_max": round(max(seconds), 3),
            "catchup_s_first": seconds[0],  # the holder's first serve of the layer
            "catchup_s_each": seconds,
            "catchup_wall_s_incl_process_start": round(min(walls), 2),
            "catchup_runs": done,
        }
    except Exception:
        log.error("catch-up benchmark failed; daemon logs:\n%s", colony.logs())
        raise
    finally:
        colony.close()


def _wait_caught_up(colony: LocalColony, agent: str, timeout: float) -> None:
    """Until `agent` reports a snapshot of the bulk layer installed, asking for status without
    digests: a digest costs each daemon a pass over its layers (and the layer's lock) and would
    slow down the catch-up it watches; `wait_converged` checks the content afterwards."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for r in colony.status(timeout=1.0):
            if r["agent"] == agent and any(c[0] == "big" for c in r["metrics"]["catchups"]):
                return
        time.sleep(0.2)
    raise TimeoutError(f"{agent} did not catch up the bulk layer in {timeout:.0f} s")


def _newcomer(colony: LocalColony, agent: str, voxels: int) -> dict[str, Any]:
    """Start `agent`, wait for it to hold the bulk layer, stop it; its catch-up figures."""
    t0 = time.monotonic()
    newcomer = colony.add(agent, start=False)
    # Room for the layer: the default peer budget (100,000 blocks) refuses 10 M voxels.
    newcomer.env["COLONYD_MAX_PEER_BLOCKS"] = str(max(100_000, voxels // 16))
    newcomer.start()
    try:
        _wait_caught_up(colony, agent, 120 + voxels / 50_000)
        # a digest of 10 M voxels takes seconds, more on a busy machine
        colony.wait_converged(120 + voxels / 50_000, ["big", agent], 2.0 + voxels / 500_000)
        wall = time.monotonic() - t0
        reports = {r["agent"]: r for r in colony.status()}
    finally:
        newcomer.stop()
    catchups = [c for c in reports[agent]["metrics"]["catchups"] if c[0] == "big"]
    if not catchups:
        raise RuntimeError(f"{agent} holds the layer without a snapshot catch-up")
    _, got, seconds, marks = catchups[-1]
    serves = reports["big"]["metrics"].get("serves", [])
    # The serve of this request: the last one that began after it was sent.
    served = [m for _, m in serves if m["query"] >= marks["request"]]
    if served:
        marks = {**served[-1], **marks}
    request = marks["request"]
    return {
        "catchup_voxels": int(got),
        "catchup_s": round(float(seconds), 3),
        "catchup_wall_s_incl_process_start": round(wall, 2),
        "timeline_ms": {
            k: round((v - request) * 1000, 1)
            for k, v in sorted(marks.items(), key=lambda kv: kv[1])
            if not k.endswith("_s")
        },
        "decode_ms": round(marks.get("decode_s", 0.0) * 1000, 1),
        "newcomer_cpu_ms": round(marks.get("cpu_s", 0.0) * 1000, 1),
        "newcomer_process_cpu_ms": round(marks.get("process_cpu_s", 0.0) * 1000, 1),
        "server_cpu_ms": round(marks.get("serve_cpu_s", 0.0) * 1000, 1),
        "server_process_cpu_ms": round(marks.get("serve_process_cpu_s", 0.0) * 1000, 1),
    }
