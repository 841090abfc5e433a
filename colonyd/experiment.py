"""The paper's experiment: sim robots localising alone and sharing, as real daemons on
loopback; their pose error against the sim's truth (read here only, to evaluate)."""

from __future__ import annotations

import json
import logging
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from colonyd.demo import stdout_console
from colonyd.errors import ConfigError, StatusError
from colonyd.experimentopts import LIDAR_RANGE, WORLDS
from colonyd.outdir import output_dir
from colonyd.plots import Panel, Series, draw_colony, draw_errors
from colonyd.simrun import SimRun
from colonyd.tracks import Track, pose_errors, write_tum
from voxel import kernels

#: The runs: name -> the agents of its colony. Every agent starts at an unknown pose (its own
#: frame) with realistic wheel odometry; cctv-1 is fixed with a surveyed pose (the anchor).
log = logging.getLogger(__name__)

RUNS: dict[str, tuple[str, ...]] = {
    "depth-alone": ("depth-1",),
    "lidar-alone": ("lidar-1",),
    "lidar+depth": ("lidar-1", "depth-1"),
    "lidar+depth+cctv": ("lidar-1", "depth-1", "cctv-1"),
}
#: The robots whose pose is estimated (one panel each in pose-error.png), and the anchor.
ROBOTS = ("lidar-1", "depth-1")
ANCHOR = "cctv-1"
#: Robots whose camera reads the tagged landmarks' ArUco markers (landmark updates, paper
#: Alg. 3: the positions the surveyed CCTV publishes for them).
MARKER_READERS = ("depth-1",)
#: One seed per agent, the same in every run: an agent sees the same odometry noise alone and in
#: a colony, so the runs differ only in what is shared.
AGENT_SEED = {"lidar-1": 1, "depth-1": 2, "cctv-1": 3}
ODOMETRY_NOISE = "realistic"
#: Seconds from starting a run's daemons to its shared clock's zero (`epoch=`): every agent's path
#: starts then, so a daemon slow to start does not skip the first frames.
EPOCH_DELAY_S = 15.0
#: Seconds to wait for the fused map of a finished run (a loaded machine answers late).
MAP_WAIT_S = 30.0
#: Colour index of each run in the pictures.
RUN_COLOUR = {name: i for i, name in enumerate(RUNS)}
AGENT_COLOUR = {"lidar-1": 0, "depth-1": 1, "cctv-1": 2}


@dataclass
class RunResult:
    """One finished run: its tracks, and its figures per agent."""

    name: str
    tracks: dict[str, Track]
    metrics: dict[str, dict[str, float | None]]
    seconds: float
    complete: bool  # every source done before the timeout
    updates: dict[str, dict[str, int]]  # per agent, its estimator's update counts at the end


def agent_metrics(track: Track) -> dict[str, float | None]:
    """ATE RMSE, the last pose's error, the largest error after first contact (None without
    contact), the first contact (seconds from the run's start; None without)."""
    errors = pose_errors(track)
    contact = track.aligned_at
    after = None
    if errors is not None and contact is not None:
        later = errors[np.array(track.times) >= contact]
        after = float(later.max()) if len(later) else None
    return {
        "ate_rmse_m": None if errors is None else _round(float(np.sqrt(np.mean(errors**2)))),
        "final_error_m": None if errors is None else _round(float(errors[-1])),
        "max_error_after_contact_m": _round(after),
        "first_contact_s": _round(contact, 2),
    }


def _round(x: float | None, digits: int = 4) -> float | None:
    return None if x is None else round(x, digits)


def _start(
    base: Path,
    name: str,
    seed: int,
    duration: float,
    lidar_range: float,
    world: str,
    start_delay: float = EPOCH_DELAY_S,
) -> SimRun:
    agents = RUNS[name]
    env = {"COLONYD_ANCHOR": ANCHOR} if ANCHOR in agents else {}
    run = SimRun(base / name, name, env=env, odometry_noise=ODOMETRY_NOISE, world=world)
    epoch = time.time() + start_delay
    try:
        for agent in agents:
            run.add(
                agent,
                duration,
                seed * 100 + AGENT_SEED[agent],
                agent_options(agents, agent, epoch, lidar_range),
            )
    except BaseException:  # interrupted (Ctrl-C, SIGTERM) or failed half-way: stop the started
        run.close()
        raise
    return run


def agent_options(
    agents: tuple[str, ...], agent: str, epoch: float, lidar_range: float = LIDAR_RANGE
) -> str:
    """The `sim:` options of `agent` in a run of `agents`: the run's shared clock (frames a
    daemon is late for are mapped late, not skipped: on a loaded machine a run takes longer, but
    every agent maps every frame, so a run's figures do not depend on the load), lidar-1's short
    range, depth-1 reading the landmarks' markers, and the CCTV told which robots' markers it
    can see (so that it sends them fixes)."""
    options = [f"epoch={epoch:.3f}", "keep_late=1"]
    if agent == "lidar-1":
        options.append(f"lidar_range={lidar_range:g}")
    if agent in MARKER_READERS:
        options.append("markers=1")
    if agent == ANCHOR:
        robots = [a for a in ROBOTS if a in agents]
        if robots:
            options.append("robots=" + "+".join(robots))
    return ",".join(options)


def _finish(run: SimRun, out: Path, complete: bool) -> RunResult:
    """Write the run's trajectories and top-down picture; its figures."""
    directory = out / run.name
    directory.mkdir(parents=True, exist_ok=True)
    for agent, track in run.tracks.items():
        write_tum(track, directory, agent)
    viewer = next(a for a in ROBOTS if a in run.tracks)  # whose fused map is drawn
    try:
        fused, _ = run.maps(viewer, wait_s=MAP_WAIT_S)
    except StatusError as exc:  # a daemon too busy to answer: the figures still count
        log.warning("run %s: no top-down picture: %s", run.name, exc)
        fused = None
    report = run.report(viewer)
    frame = report.get("colony_frame", {"agents": {}})
    if fused is not None:
        draw_colony(
            directory / "topdown.png",
            fused,
            run.tracks,
            {a: np.array(t) for a, t in frame.get("agents", {}).items()},
            report.get("peer_objects", {}),
            report.get("objects", []),
            title=f"{run.name} (map of {viewer})",
            colours=AGENT_COLOUR,
        )
    metrics = {agent: agent_metrics(track) for agent, track in run.tracks.items()}
    updates = {agent: update_counts(run.report(agent)) for agent in run.tracks}
    return RunResult(run.name, run.tracks, metrics, run.now(), complete, updates)


def update_counts(report: dict[str, Any]) -> dict[str, int]:
    """What an agent's estimator fused and refused, by kind (own map, colony map, fixes), and the
    fixes its daemon received, from its last status."""
    out: dict[str, int] = {}
    for entry in (report.get("localisation") or {}).values():
        if isinstance(entry, dict):
            out.update({k: int(v) for k, v in entry.items() if isinstance(v, int)})
    counts = report.get("metrics", {}).get("counts", {})
    out.update({k: int(v) for k, v in counts.items() if k.startswith("fix")})
    return out


def _say(what: str, began: float) -> None:
    """A progress line for a log (stdout is not a terminal: the live table shows nothing)."""
    sys.stdout.write(f"experiment 'paper' at {time.monotonic() - began:5.0f} s: {what}\n")
    sys.stdout.flush()


def _progress(active: dict[str, SimRun], done: dict[str, RunResult], began: float) -> Any:
    """The live table: one row per run."""
    from rich.table import Table

    table = Table(title=f"experiment 'paper' at {time.monotonic() - began:5.0f} s")
    for column in ("run", "state", "seconds", "frames", "aligned"):
        table.add_column(column)
    for name in RUNS:
        if name in done:
            r = done[name]
            table.add_row(name, "done" if r.complete else "timed out", f"{r.seconds:.0f}", "", "")
        elif name in active:
            run = active[name]
            frames = ", ".join(
                f"{r['agent']} {r['metrics']['counts'].get('frames', 0)}" for r in run.reports
            )
            aligned = ", ".join(a for a, t in run.tracks.items() if t.aligned_at is not None)
            table.add_row(name, "mapping", f"{run.now():.0f}", frames, aligned or "-")
        else:
            table.add_row(name, "waiting", "", "", "")
    return table


def run_paper(
    out: Path,
    *,
    seed: int = 1,
    duration: float = 60.0,
    parallel: int = 2,
    timeout: float | None = None,
    progress: bool = True,
    lidar_range: float | None = None,
    world: str = "office",
    start_delay: float = EPOCH_DELAY_S,
) -> dict[str, Any]:
    """Run every run of `RUNS` in the sim `world` (at most `parallel` at a time), each for
    `duration` seconds of sim time from `start_delay` seconds after its daemons' start (a run
    whose sources are not done after `timeout` seconds, default 6 x duration + 120, is evaluated
    as far as it got and marked incomplete); write trajectories, pictures and results.json into
    `out`; return the results."""
    from rich.live import Live

    if world not in WORLDS:
        msg = f"world: expected one of {', '.join(WORLDS)}, found {world!r}"
        raise ConfigError(msg)
    out = Path(out)
    output_dir(out, "--out")
    timeout = timeout if timeout is not None else 6 * duration + 120
    lidar_range = LIDAR_RANGE if lidar_range is None else lidar_range
    console = stdout_console()
    # Compile the kernels here once (a fresh install has none cached): otherwise every daemon
    # compiles them at once, answering no status meanwhile (docs/VOXEL.md).
    kernels.warm()
    work = Path(tempfile.mkdtemp(prefix="colonyd-paper-"))
    began = time.monotonic()
    pending = list(RUNS)
    active: dict[str, SimRun] = {}
    done: dict[str, RunResult] = {}
    try:
        with Live(console=console, refresh_per_second=1, transient=True) as live:
            while pending or active:
                while pending and len(active) < max(1, parallel):
                    name = pending.pop(0)
                    active[name] = _start(
                        work, name, seed, duration, lidar_range, world, start_delay
                    )
                    active[name].watch()
                    if progress and not console.is_terminal:  # a log: no live table there
                        _say(f"{name}: started", began)
                for name, run in list(active.items()):
                    over = run.now() > timeout
                    if run.mapping_done() or over:
                        run.unwatch()
                        run.poll_all()  # the last poses, and every member's last report
                        done[name] = _finish(run, out, complete=not over)
                        run.close()
                        del active[name]
                        if progress and not console.is_terminal:
                            _say(f"{name}: {'done' if not over else 'timed out'}", began)
                if progress:
                    live.update(_progress(active, done, began))
                time.sleep(0.25)
    finally:
        for run in active.values():
            run.close()
        shutil.rmtree(work, ignore_errors=True)
    results = {
        "seed": seed,
        "world": world,
        "duration_s": duration,
        "lidar_range_m": lidar_range,
        "odometry_noise": ODOMETRY_NOISE,
        "start_delay_s": start_delay,
        "seconds": round(time.monotonic() - began, 1),
        "runs": {name: done[name].metrics for name in RUNS},
        "complete": {name: done[name].complete for name in RUNS},
        "run_seconds": {name: round(done[name].seconds, 1) for name in RUNS},
        "updates": {name: done[name].updates for name in RUNS},
    }
    (out / "results.json").write_text(json.dumps(results, indent=1) + "\n")
    draw_errors(
        out / "pose-error.png", _panels(done, world), note="vertical: first contact", axis="sim"
    )
    if progress:
        console.print(results_table(results))
    return results


def _panels(done: dict[str, RunResult], world: str) -> list[Panel]:
    """One panel per robot, one line per run it took part in, over the robot's sim time (frames
    mapped / frame rate: the same axis however fast a loaded machine ran each daemon)."""
    from plugins.sim import AGENTS

    panels = []
    for robot in ROBOTS:
        rate = AGENTS[world][robot].rate
        series = []
        for name, result in done.items():
            track = result.tracks.get(robot)
            errors = None if track is None else pose_errors(track)
            if track is None or errors is None:
                continue
            sim = [f / rate for f in track.frames]
            contact = None if track.aligned_frame is None else track.aligned_frame / rate
            series.append(
                Series(
                    name, list(zip(sim, errors.tolist(), strict=True)), contact, RUN_COLOUR[name]
                )
            )
        panels.append(Panel(f"{robot} (APE after Umeyama)", series))
    return panels


def results_table(results: dict[str, Any]) -> Any:
    """The results as a rich Table: one row per run and agent."""
    from rich.table import Table

    table = Table(
        title=f"paper experiment, sim {results.get('world', 'office')}, seed {results['seed']}, "
        f"{results['duration_s']:.0f} s "
        f"per run, {results['odometry_noise']} odometry ({results['seconds']:.0f} s in all)",
        caption="pose error after the Umeyama fit (m): ATE RMSE, at the last pose, largest "
        "after first contact; first contact with a peer (s from the run's start)",
    )
    for column in ("run", "agent", "ATE", "final", "max after", "contact at"):
        table.add_column(
            column, justify="left" if column in ("run", "agent") else "right", no_wrap=True
        )

    def cell(x: float | None, fmt: str = ".3f") -> str:
        return "-" if x is None else format(x, fmt)

    for name, agents in results["runs"].items():
        for agent, m in agents.items():
            table.add_row(
                name,
                agent,
                cell(m["ate_rmse_m"]),
                cell(m["final_error_m"]),
                cell(m["max_error_after_contact_m"]),
                cell(m["first_contact_s"], ".1f"),
            )
    return table
