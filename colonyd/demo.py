"""`colonyd demo`: robots and a CCTV camera map the sim office as a colony, with a live table."""

from __future__ import annotations

import json
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from colonyd.bench.launcher import LocalColony
from colonyd.demoplot import draw_colony, draw_errors
from colonyd.export import MapReply, fetch_maps, write_maps
from colonyd.mapping import tum_line
from colonyd.outdir import output_dir

#: The colony: (agent, what it carries, frames per second of simulated time). The 3D LiDAR robot
#: joins halfway and catches up.
MEMBERS = (
    ("depth-1", "depth camera", 10.0),
    ("lidar-1", "2D LiDAR", 10.0),
    ("cctv-1", "CCTV", 1.0),
)
LATE = ("lidar3d-1", "3D LiDAR", 10.0)


def member_spec(agent: str, rate: float, duration: float, seed: int) -> str:
    """One sim office agent at an unknown start pose (its own frame), paced in real time."""
    frames = max(2, int(rate * duration))
    return f"sim:world=office,agent={agent},frames={frames},seed={seed},realtime=1"


@dataclass
class Track:
    """What the demo saw of one member over time (from its status; truth for evaluation)."""

    carries: str
    joined: float
    times: list[float] = field(default_factory=list)
    estimate: list[np.ndarray] = field(default_factory=list)  # sensor pose, own frame
    truth: list[np.ndarray] = field(default_factory=list)  # sensor pose, world (evaluation)
    errors: list[tuple[float, float]] = field(default_factory=list)  # (t, pose error m)
    aligned_at: float | None = None
    caught_up_at: float | None = None
    sent: int = 0
    received: int = 0


def _table(reports: list[dict[str, Any]], tracks: dict[str, Track], now: float) -> Any:
    """The live table: one row per member (a rich Table)."""
    from rich.table import Table

    table = Table(title=f"colony 'demo' at {now:5.1f} s", expand=False)
    for name in (
        "member",
        "carries",
        "aligned",
        "pose error",
        "own seq",
        "replicas",
        "sent",
        "received",
    ):
        table.add_column(name, justify="right" if name in ("sent", "received") else "left")
    for r in reports:
        agent = r["agent"]
        track = tracks.get(agent)
        frame = r.get("colony_frame", {})
        aligned = agent in frame.get("agents", {})
        root = frame.get("root", "?")
        err = r.get("pose_error_m")
        layers = r.get("layers", {})
        own = layers.get(agent, {}).get("seq", 0)
        replicas = sum(1 for o, v in layers.items() if o != agent and v.get("seq"))
        counts = r["metrics"]["counts"]
        table.add_row(
            agent,
            track.carries if track else "?",
            ("root" if agent == root else "yes") if aligned else "no",
            "-" if err is None else f"{err:.3f} m",
            str(own),
            str(replicas),
            f"{counts.get('bytes_published', 0) / 1024:.0f} KiB",
            f"{counts.get('bytes_received', 0) / 1024:.0f} KiB",
        )
    return table


def _record(reports: list[dict[str, Any]], tracks: dict[str, Track], now: float) -> None:
    for r in reports:
        track = tracks.get(r["agent"])
        if track is None:
            continue
        counts = r["metrics"]["counts"]
        track.sent = int(counts.get("bytes_published", 0)) + int(counts.get("bytes_served", 0))
        track.received = int(counts.get("bytes_received", 0))
        posed = r.get("pose_matrix") is not None and r.get("truth_matrix") is not None
        if posed and (not track.times or now - track.times[-1] >= 0.2):
            track.times.append(now)
            track.estimate.append(np.array(r["pose_matrix"]))
            track.truth.append(np.array(r["truth_matrix"]))
        if r.get("pose_error_m") is not None:
            track.errors.append((now, float(r["pose_error_m"])))
        frame = r.get("colony_frame", {})
        if (
            track.aligned_at is None
            and r["agent"] in frame.get("agents", {})
            and len(frame.get("agents", {})) > 1
        ):
            track.aligned_at = now


def _caught_up(reports: list[dict[str, Any]], agent: str) -> bool:
    """True when `agent` holds every other member's layer at the version its origin reports."""
    mine = next((r for r in reports if r["agent"] == agent), None)
    if mine is None:
        return False
    for r in reports:
        own = r.get("layers", {}).get(r["agent"])
        if r["agent"] == agent or not own or not own.get("seq"):
            continue
        have = mine.get("layers", {}).get(r["agent"])
        if have is None or have["seq"] < own["seq"]:
            return False
    return True


def _ate(truth: list[np.ndarray], estimate: list[np.ndarray]) -> float | None:
    if len(truth) < 3:
        return None
    from voxel.localisation.metrics import absolute_trajectory_error

    return float(absolute_trajectory_error(np.array(truth), np.array(estimate)).rmse)


def run_demo(out: Path, *, duration: float = 40.0, timeout: float = 120.0) -> int:
    """Run the demo for `duration` seconds of mapping; write maps, pictures and a summary."""
    from rich.console import Console
    from rich.live import Live

    out = Path(out)
    output_dir(out, "--out")
    console = Console(file=sys.stdout)
    work = Path(tempfile.mkdtemp(prefix="colonyd-demo-"))
    colony = LocalColony(work, colony="demo", heartbeat_s=0.5)
    env = {"COLONYD_ALIGN_S": "2", "COLONYD_OBJECTS_S": "1"}
    tracks: dict[str, Track] = {}
    t0 = time.monotonic()
    try:
        for i, (agent, carries, rate) in enumerate(MEMBERS):
            d = colony.add(agent, [member_spec(agent, rate, duration, i + 1)], start=False)
            d.env = env
            d.start()
            tracks[agent] = Track(carries, time.monotonic() - t0)
        colony.wait_members(len(MEMBERS), timeout=30)
        late_started = False
        reports: list[dict[str, Any]] = []
        with Live(console=console, refresh_per_second=2, transient=False) as live:
            while time.monotonic() - t0 < timeout:
                now = time.monotonic() - t0
                if not late_started and now >= duration / 2:
                    agent, carries, rate = LATE
                    d = colony.add(agent, [member_spec(agent, rate, duration / 2, 9)], start=False)
                    d.env = env
                    d.start()
                    tracks[agent] = Track(carries, now)
                    late_started = True
                reports = colony.status(timeout=1.0)
                _record(reports, tracks, now)
                late = tracks.get(LATE[0])
                if late and late.caught_up_at is None and _caught_up(reports, LATE[0]):
                    late.caught_up_at = now
                live.update(_table(reports, tracks, now))
                if (
                    late_started
                    and colony.converged()[0]
                    and all(t.aligned_at is not None for t in tracks.values())
                ):
                    break
                if late_started and now > duration + 15 and colony.converged()[0]:
                    break  # mapping is over; alignment did not complete: say so below
                time.sleep(0.5)
        fused, layers = fetch_maps(colony.session(), colony.namespace, agent=MEMBERS[0][0])
        summary = _write_outputs(out, fused, layers, reports, tracks, time.monotonic() - t0)
        console.print(_summary_text(summary, out))
        return 0
    finally:
        colony.close()
        shutil.rmtree(work, ignore_errors=True)


def _write_outputs(
    out: Path,
    fused: MapReply,
    layers: dict[str, MapReply],
    reports: list[dict[str, Any]],
    tracks: dict[str, Track],
    seconds: float,
) -> dict[str, Any]:
    files = write_maps(fused, out, "map")
    for name, reply in layers.items():
        files.update(write_maps(reply, out / "layers", name))
    report = next((r for r in reports if r["agent"] == fused.agent), {})
    frame = report.get("colony_frame", {"root": "?", "agents": {}})
    colony_tf = {a: np.array(t) for a, t in frame.get("agents", {}).items()}
    trajectories = out / "trajectories"
    trajectories.mkdir(exist_ok=True)
    per_robot: dict[str, Any] = {}
    for agent, track in tracks.items():
        if track.estimate:
            (trajectories / f"{agent}.estimate.tum").write_text(
                "".join(
                    tum_line(t, p) + "\n" for t, p in zip(track.times, track.estimate, strict=True)
                )
            )
            (trajectories / f"{agent}.groundtruth.tum").write_text(
                "".join(
                    tum_line(t, p) + "\n" for t, p in zip(track.times, track.truth, strict=True)
                )
            )
        alive = max(seconds - track.joined, 1e-9)
        per_robot[agent] = {
            "carries": track.carries,
            "ate_m": _ate(track.truth, track.estimate),
            "final_pose_error_m": track.errors[-1][1] if track.errors else None,
            "aligned": agent in colony_tf,
            "time_to_align_s": None
            if track.aligned_at is None
            else round(track.aligned_at - track.joined, 2),
            "bytes_sent_per_s": round(track.sent / alive, 1),
            "bytes_received_per_s": round(track.received / alive, 1),
        }
    late = tracks.get(LATE[0])
    summary = {
        "seconds": round(seconds, 1),
        "colony_frame": frame.get("root"),
        "robots": per_robot,
        "late_joiner": LATE[0],
        "late_joiner_catch_up_s": None
        if late is None or late.caught_up_at is None
        else round(late.caught_up_at - late.joined, 2),
        "map": {
            "frame": fused.frame,
            "voxels": len(fused.keys),
            "occupied": int((fused.logodds >= 0).sum()),
            "layers_fused": fused.layers,
        },
        "files": sorted(str(p.relative_to(out)) for p in files.values()),
    }
    draw_colony(
        out / "colony.png",
        fused,
        tracks,
        colony_tf,
        report.get("peer_objects", {}),
        report.get("objects", []),
    )
    draw_errors(out / "pose-error.png", tracks)
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    return summary


def _summary_text(summary: dict[str, Any], out: Path) -> str:
    lines = [
        f"colony 'demo': {len(summary['robots'])} members, {summary['seconds']} s; "
        f"colony frame: {summary['colony_frame']}"
    ]
    for agent, r in summary["robots"].items():
        ate = "-" if r["ate_m"] is None else f"{r['ate_m']:.3f} m"
        align = (
            f"aligned after {r['time_to_align_s']} s"
            if r["aligned"] and r["time_to_align_s"] is not None
            else "not aligned"
        )
        lines.append(
            f"  {agent:<10} {r['carries']:<13} ATE {ate:>9}  {align:<22} "
            f"sent {r['bytes_sent_per_s'] / 1024:.1f} KiB/s"
        )
    catch = summary["late_joiner_catch_up_s"]
    lines.append(
        f"  {summary['late_joiner']} joined halfway and caught up in "
        f"{'-' if catch is None else f'{catch} s'}"
    )
    m = summary["map"]
    lines.append(
        f"  fused map ({m['frame']}, layers {', '.join(m['layers_fused'])}): "
        f"{m['occupied']} occupied of {m['voxels']} voxels"
    )
    lines.append(
        f"  wrote {out}: map.bt, map.ply, colony.png, pose-error.png, summary.json, "
        "trajectories/, layers/"
    )
    return "\n".join(lines)
