"""`colonyd demo`: robots and a CCTV camera map the sim office as a colony, with a live table."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from colonyd.errors import StatusError
from colonyd.export import MapReply, fetch_maps, write_maps
from colonyd.outdir import output_dir
from colonyd.plots import Panel, draw_colony, draw_errors, track_series
from colonyd.simrun import AloneReplay, SimRun
from colonyd.tracks import Track, ate, caught_up, write_tum
from voxel import kernels

#: The colony: (agent, seed of its sim source). The 3D LiDAR robot joins halfway and catches up.
MEMBERS = (("depth-1", 1), ("lidar-1", 2), ("cctv-1", 3))
LATE = ("lidar3d-1", 9)
#: Wheel odometry of the robots (docs/LOCALISATION.md), as in the paper's experiment.
ODOMETRY_NOISE = "realistic"
#: Seconds between progress lines when stdout is not a terminal (no live table there).
PROGRESS_S = 10.0
#: Seconds to wait, once mapping is over and the colony converged, for every member to align.
ALIGN_WAIT_S = 15.0
#: Seconds to wait for each robot's replay alone after the colony stopped (about 30 s on the
#: idle 2-core machine; 70 s for depth-1 at load 11-15).
REPLAY_WAIT_S = 180.0


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


def stdout_console() -> Any:
    """A rich Console on stdout; where stdout is no terminal (a log), 120 columns wide: the
    table printed there once at the end wrapped at rich's default 80 ("lidar3…", "replic…")."""
    from rich.console import Console

    console = Console(file=sys.stdout)
    return console if console.is_terminal else Console(file=sys.stdout, width=120)


def _progress_line(reports: list[dict[str, Any]], now: float) -> str:
    """One line of the colony's state, for a log (the live table needs a terminal)."""
    frame: dict[str, Any] = next((r["colony_frame"] for r in reports if "colony_frame" in r), {})
    aligned = sorted(frame.get("agents", {}))
    return (
        f"demo at {now:5.1f} s: {len(reports)} members answered; "
        f"aligned with the colony frame ({frame.get('root', '?')}): "
        f"{', '.join(aligned) if aligned else 'none yet'}"
    )


def run_demo(
    out: Path, *, duration: float = 40.0, timeout: float = 120.0, align_wait: float = ALIGN_WAIT_S
) -> int:
    """Run the demo for `duration` seconds of mapping, then wait up to `align_wait` seconds for
    every member to align; write maps, pictures and a summary."""
    from rich.live import Live

    out = Path(out)
    output_dir(out, "--out")
    console = stdout_console()
    # Compile the kernels here once (a fresh install has none cached): otherwise every daemon
    # compiles them at once, answering no status meanwhile (docs/VOXEL.md).
    kernels.warm()
    work = Path(tempfile.mkdtemp(prefix="colonyd-demo-"))
    run = SimRun(work / "colony", "demo", odometry_noise=ODOMETRY_NOISE)
    replays: dict[str, AloneReplay] = {}
    try:
        for agent, seed in MEMBERS:
            run.add(agent, duration, seed)
        run.colony.wait_members(len(MEMBERS), timeout=60)  # (a loaded machine starts slowly)
        late_started = False
        reports: list[dict[str, Any]] = []
        said = -PROGRESS_S  # not a terminal (a log, CI): a line every PROGRESS_S instead
        with Live(console=console, refresh_per_second=2, transient=False) as live:
            while run.now() < timeout:
                now = run.now()
                if not late_started and now >= duration / 2:
                    run.add(LATE[0], duration / 2, LATE[1])
                    late_started = True
                reports = run.poll()
                late = run.tracks.get(LATE[0])
                if late and late.caught_up_at is None and caught_up(reports, LATE[0]):
                    late.caught_up_at = now
                live.update(_table(reports, run.tracks, now))
                if not console.is_terminal and now - said >= PROGRESS_S:
                    sys.stdout.write(_progress_line(reports, now) + "\n")
                    sys.stdout.flush()
                    said = now
                converged = late_started and run.colony.converged()[0]
                if converged and late and late.caught_up_at is None:  # a round that missed it
                    late.caught_up_at = now  # converged: it holds every layer as its origin
                if converged and all(t.aligned_at is not None for t in run.tracks.values()):
                    break
                if converged and now > duration + align_wait:
                    break  # mapping is over; alignment did not complete: say so below
                time.sleep(0.5)
            reports = run.poll_all()  # every member's last report (the summary reads them)
        fused, layers = run.maps(MEMBERS[0][0], wait_s=30.0)  # a loaded daemon answers late
        layers.update(_unfused_layers(run, fused, reports))
        seconds = run.now()
        load = os.getloadavg()  # of the colony's run (the summary says why it did not align)
        run.close()
        # What each robot achieves alone, replayed only now: beside the colony these replays
        # (~45 s of CPU) took the idle CPU its map registration runs on (SCHED_IDLE).
        sys.stdout.write(_replay_line(seconds, [a for a, _, _ in _robots(duration)]) + "\n")
        sys.stdout.flush()
        for agent, seed, mapped in _robots(duration):
            replays[agent] = AloneReplay(
                work / f"alone-{agent}", agent, mapped, seed, ODOMETRY_NOISE
            )
            replays[agent].hurry()  # nothing to give way to any more (where permitted)
        alone = {a: r.result(REPLAY_WAIT_S) for a, r in replays.items()}
        summary = _write_outputs(out, fused, layers, reports, run.tracks, seconds, alone, load)
        sys.stdout.write("\n" + _summary_text(summary, out) + "\n")  # plain: no wrapping
        return 0
    finally:
        for replay in replays.values():
            replay.close()
        run.close()
        shutil.rmtree(work, ignore_errors=True)


def _replay_line(seconds: float, robots: list[str]) -> str:
    """What the demo does once the colony stopped (a minute or more of nothing printed else)."""
    return (
        f"colony stopped at {seconds:.1f} s; replaying {', '.join(robots)} alone "
        "(`colonyd localize`, the same frames and odometry noise) for the 'alone' figures "
        f"(up to {REPLAY_WAIT_S:.0f} s)"
    )


def _unfused_layers(
    run: SimRun, fused: MapReply, reports: list[dict[str, Any]]
) -> dict[str, MapReply]:
    """The maps of the members' layers that `fused` does not hold aligned (so not in the fused
    map), each in its own frame: a robot that did not align still leaves its map. Each is asked
    of `fused`'s daemon, else of its origin (a late joiner's layer may not have reached it)."""
    mapped = {
        r["agent"]
        for r in reports
        if r.get("layers", {}).get(r["agent"], {}).get("seq")  # its origin has published it
    }
    maps: dict[str, MapReply] = {}
    for name in sorted(mapped - set(fused.layers)):
        for holder in (fused.agent, name):
            with contextlib.suppress(StatusError):  # not held there (or dropped): try its origin
                _, one = fetch_maps(
                    run.colony.session(), run.colony.namespace, layer=name, agent=holder
                )
                maps.update(one)
                break
    return maps


def _robots(duration: float) -> list[tuple[str, int, float]]:
    """(agent, seed, seconds mapped) of every member that moves (the CCTV does not)."""
    moving = [(a, seed, duration) for a, seed in MEMBERS if not a.startswith("cctv")]
    return [*moving, (LATE[0], LATE[1], duration / 2)]


def _write_outputs(
    out: Path,
    fused: MapReply,
    layers: dict[str, MapReply],
    reports: list[dict[str, Any]],
    tracks: dict[str, Track],
    seconds: float,
    alone: dict[str, dict[str, float | None]],
    load: tuple[float, float, float],
) -> dict[str, Any]:
    files = write_maps(fused, out, "map")
    for name, reply in layers.items():
        files.update(write_maps(reply, out / "layers", name))
    report = next((r for r in reports if r["agent"] == fused.agent), {})
    frame = report.get("colony_frame", {"root": "?", "agents": {}})
    colony_tf = {a: np.array(t) for a, t in frame.get("agents", {}).items()}
    per_robot: dict[str, Any] = {}
    for agent, track in tracks.items():
        write_tum(track, out / "trajectories", agent)
        alive = max(seconds - track.joined, 1e-9)
        per_robot[agent] = {
            "carries": track.carries,
            "ate_m": ate(track),
            "ate_alone_m": _rounded(alone.get(agent, {}).get("estimate")),
            "ate_odometry_m": _rounded(alone.get(agent, {}).get("odometry")),
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
        # Registration runs at a low CPU share (docs/DAEMON.md): the load says why it may not have.
        "load_average": [round(x, 2) for x in load],
        "cpus": os.cpu_count(),
    }
    draw_colony(
        out / "colony.png",
        fused,
        tracks,
        colony_tf,
        report.get("peer_objects", {}),
        report.get("objects", []),
    )
    draw_errors(out / "pose-error.png", [Panel("pose error", track_series(tracks))])
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    return summary


def _rounded(x: float | None) -> float | None:
    return None if x is None else round(x, 4)


def _summary_text(summary: dict[str, Any], out: Path) -> str:
    lines = [
        f"colony 'demo': {len(summary['robots'])} members, {summary['seconds']} s; "
        f"colony frame: {summary['colony_frame']}"
    ]
    root = summary["colony_frame"]
    for agent, r in summary["robots"].items():
        ate = "-" if r["ate_m"] is None else f"{r['ate_m']:.3f} m"
        if not r["aligned"]:
            align = "not aligned"
        elif agent == root:
            align = "colony frame's root"
        elif r["time_to_align_s"] is not None:
            align = f"aligned after {r['time_to_align_s']} s"
        else:
            align = "aligned"
        lines.append(
            f"  {agent:<10} {r['carries']:<13} ATE {ate:>9}  {align:<22} "
            f"sent {r['bytes_sent_per_s'] / 1024:.1f} KiB/s"
        )
    for agent, r in summary["robots"].items():
        if r["ate_m"] is None or r["ate_alone_m"] is None:
            continue
        lines.append(
            f"  {r['carries']} robot ({agent}): ATE {r['ate_alone_m']:.3f} m alone -> "
            f"{r['ate_m']:.3f} m in the colony"
            + ("" if r["ate_odometry_m"] is None else f" (odometry {r['ate_odometry_m']:.3f} m)")
        )
    apart = [a for a, r in summary["robots"].items() if not r["aligned"]]
    if apart:
        load = summary.get("load_average") or ["?"]
        lines.append(
            f"  not aligned within the run: {', '.join(apart)}. Map registration runs at a low "
            "CPU share (a session of its own at autogroup niceness align_session_nice, "
            f"docs/DAEMON.md), and the load average was {load[0]} on "
            f"{summary.get('cpus', '?')} cores (the demo's daemons included) at the colony's "
            "end. Their maps are in layers/ in their own frames, not in the fused map"
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
