"""The paper experiment's `lidar+depth` run alone, watched for alignment: every attempt of each
daemon (verdict, reason, ambiguity, seconds) and its registration worker's CPU, until first
contact and the run's end.

`python -m colonyd.bench.paper_align --seed S [--world W] [--duration D] [--session-nice N]
[--json FILE]`

The run is the experiment's (`colonyd.experiment`: the same specs, seeds, shared clock and
daemon settings); `--session-nice` sets the daemons' `align_session_nice` (the registration
worker's autogroup niceness; -1: no session of its own). Each attempt is recorded from the
daemons' status (polled every 0.25 s: one attempt per `align_s` = 2 s, so none is missed), with
the sim time it ended at (seconds since the shared clock's zero) and the frames its daemon had
mapped by then (`frames_mapped`: a loaded daemon maps its frames late, so an attempt at sim
time 100 s may see maps of 40 s of poses). The worker's CPU is read from
/proc (user + system, the pool process the daemon spawned). The sim's start poses are read only
to evaluate: an accepted attempt's error against the true transform between the two frames.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from colonyd.experiment import AGENT_SEED, EPOCH_DELAY_S, RUNS, agent_options
from colonyd.experiment import ODOMETRY_NOISE as NOISE
from colonyd.objects import CLUSTER_IDS
from colonyd.simrun import SimRun
from voxel import kernels


def worker_cpu(pid: int) -> float:
    """CPU seconds (user + system) of the registration workers `pid` spawned (0 without one)."""
    total = 0.0
    tick = os.sysconf("SC_CLK_TCK")
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmd = (entry / "cmdline").read_bytes()
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[1].split()
        if int(fields[1]) == pid and b"spawn_main" in cmd:
            total += (int(fields[11]) + int(fields[12])) / tick
    return total


def true_transform(world: str, own: str, peer: str) -> np.ndarray:
    """The true planar transform (x, y, yaw) taking `peer`'s frame into `own`'s (evaluation only:
    each agent's frame is its true start pose)."""
    from plugins.sim import AGENTS
    from plugins.sim import Path as SimPath

    def start(agent: str) -> np.ndarray:
        spec = AGENTS[world][agent]
        x, y, yaw = SimPath(spec.waypoints, spec.speed, spec.turn_rate)(0.0)
        c, s = math.cos(yaw), math.sin(yaw)
        return np.array([[c, -s, x], [s, c, y], [0, 0, 1.0]])

    out: np.ndarray = np.linalg.inv(start(own)) @ start(peer)
    return out


def error_of(record: dict[str, Any], truth: np.ndarray) -> tuple[float, float]:
    """Position (m) and heading (deg) error of an attempt's transform against `truth`."""
    t = np.asarray(record["transform"], float)
    planar = np.array([[t[0, 0], t[0, 1], t[0, 3]], [t[1, 0], t[1, 1], t[1, 3]], [0, 0, 1.0]])
    d = np.linalg.inv(truth) @ planar
    return float(np.hypot(d[0, 2], d[1, 2])), abs(math.degrees(math.atan2(d[1, 0], d[0, 0])))


def run(
    seed: int,
    *,
    world: str = "office",
    duration: float = 60.0,
    session_nice: int | None = None,
    timeout: float = 400.0,
    name: str = "lidar+depth",
) -> dict[str, Any]:
    """One watched run; its attempts, worker CPU and first contacts."""
    kernels.warm()
    agents = RUNS[name]
    env = {} if session_nice is None else {"COLONYD_ALIGN_SESSION_NICE": str(session_nice)}
    base = Path(tempfile.mkdtemp(prefix="colonyd-paper-align-"))
    sim = SimRun(base / name, name, env=env, odometry_noise=NOISE, world=world)
    epoch = time.time() + EPOCH_DELAY_S
    for agent in agents:
        sim.add(
            agent, duration, seed * 100 + AGENT_SEED[agent], agent_options(agents, agent, epoch)
        )
    attempts: dict[str, list[dict[str, Any]]] = {a: [] for a in agents}
    seen: set[tuple[str, float]] = set()
    cpu: dict[str, float] = {}
    identified: dict[str, float | None] = {a: None for a in agents}
    loads: list[float] = []
    began = time.monotonic()
    sim.watch()
    try:
        while time.monotonic() - began < timeout:
            loads.append(os.getloadavg()[0])
            for report in list(sim.reports):
                agent = str(report.get("agent"))
                if agent not in attempts:
                    continue
                proc = sim.colony.daemons[agent].proc
                if proc is not None:
                    cpu[agent] = max(cpu.get(agent, 0.0), worker_cpu(proc.pid))
                if identified[agent] is None and any(
                    o["id"] < CLUSTER_IDS for o in report.get("objects", [])
                ):
                    identified[agent] = round(time.time() - epoch, 1)
                for peer, rec in (report.get("alignments") or {}).items():
                    when = rec.get("time")
                    if when is None or (agent, when) in seen:
                        continue
                    seen.add((agent, when))
                    entry = {
                        "peer": peer,
                        "sim_s": round(when - epoch, 1),
                        "frames_mapped": sum(
                            int(s.get("delivered", 0)) for s in report.get("sources", [])
                        ),
                        "worker_cpu_s": round(cpu.get(agent, 0.0), 2),
                        **{
                            k: rec.get(k)
                            for k in (
                                "aligned",
                                "provisional",
                                "reason",
                                "failed_checks",
                                "method",
                                "confidence",
                                "overlap",
                                "ambiguity",
                                "geometric_ambiguity",
                                "inliers",
                                "seconds",
                                "objects",
                                "objects_used",
                            )
                            if k in rec
                        },
                    }
                    if "transform" in rec:
                        pos, yaw = error_of(rec, true_transform(world, agent, peer))
                        entry["error_m"], entry["error_deg"] = round(pos, 3), round(yaw, 2)
                    attempts[agent].append(entry)
            if sim.mapping_done():
                break
            time.sleep(0.25)
        sim.unwatch()
        sim.poll_all()
        contact = {
            a: (None if t.aligned_at is None else round(t.aligned_at - EPOCH_DELAY_S, 1))
            for a, t in sim.tracks.items()
        }
    finally:
        sim.close()
    return {
        "seed": seed,
        "world": world,
        "run": name,
        "session_nice": session_nice,
        "seconds": round(time.monotonic() - began, 1),
        "load": [round(min(loads), 2), round(max(loads), 2)] if loads else None,
        "first_contact_sim_s": contact,
        "first_identified_object_sim_s": identified,
        "worker_cpu_s": {a: round(c, 2) for a, c in cpu.items()},
        "attempts": attempts,
    }


def summary(result: dict[str, Any]) -> str:
    """A few lines: per agent its attempts' verdicts and first contact."""
    lines = [
        f"seed {result['seed']} session_nice {result['session_nice']} load {result['load']} "
        f"({result['seconds']} s): first contact (sim s) {result['first_contact_sim_s']}, "
        f"first identified object {result['first_identified_object_sim_s']}, "
        f"worker CPU {result['worker_cpu_s']}"
    ]
    for agent, items in result["attempts"].items():
        for a in items:
            verdict = "ok" if a.get("aligned") else (a.get("reason") or "?")[:70]
            err = f" err {a['error_m']} m {a['error_deg']} deg" if "error_m" in a else ""
            lines.append(
                f"  {agent} t={a['sim_s']:6.1f} f={a.get('frames_mapped', '?')} "
                f"{a.get('seconds', 0) or 0:6.2f} s "
                f"cpu {a['worker_cpu_s']:6.2f} amb {a.get('ambiguity')} "
                f"geo {a.get('geometric_ambiguity')} ov {a.get('overlap')}{err}: {verdict}"
            )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--world", default="office")
    parser.add_argument("--duration", type=float, default=60.0)
    parser.add_argument("--session-nice", type=int, default=None)
    parser.add_argument("--timeout", type=float, default=400.0)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    result = run(
        args.seed,
        world=args.world,
        duration=args.duration,
        session_nice=args.session_nice,
        timeout=args.timeout,
    )
    print(summary(result))
    if args.json is not None:
        with args.json.open("a", encoding="ascii") as f:
            f.write(json.dumps(result) + "\n")


if __name__ == "__main__":
    main()
