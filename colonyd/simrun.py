"""A sim colony run: real daemons on loopback mapping sim agents from unknown start poses,
watched through their status (the demo and the paper's experiment both are such runs)."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from colonyd.bench.launcher import LocalColony
from colonyd.export import MapReply, fetch_maps
from colonyd.priority import as_us, below_us
from colonyd.tracks import Track, record

log = logging.getLogger(__name__)

#: What each sim office agent carries (for tables and legends).
CARRIES = {
    "depth-1": "depth camera",
    "lidar-1": "2D LiDAR",
    "lidar3d-1": "3D LiDAR",
    "cctv-1": "CCTV",
    "cctv-2": "CCTV",
}

#: Daemon settings of a short run: alignment attempts every 2 s, objects every 1 s.
RUN_ENV = {"COLONYD_ALIGN_S": "2", "COLONYD_OBJECTS_S": "1"}


def sim_spec(
    agent: str,
    duration: float,
    seed: int,
    *,
    world: str = "office",
    odometry_noise: str | None = None,
    realtime: bool = True,
    options: str = "",
) -> str:
    """One sim agent for `duration` seconds of its own frame rate, starting at an unknown pose (its
    own frame), paced in real time; `odometry_noise` a wheel noise model (docs/LOCALISATION.md)
    instead of the sim's default odometer; `options`: more comma-separated `name=value` options
    of `sim:` (docs/SOURCES.md)."""
    from plugins.sim import AGENTS

    frames = max(2, int(AGENTS[world][agent].rate * duration))
    spec = f"sim:world={world},agent={agent},frames={frames},seed={seed}"
    if odometry_noise:
        spec += f",odometry_noise={odometry_noise}"
    if realtime:
        spec += ",realtime=1"
    if options:
        spec += f",{options}"
    return spec


class SimRun:
    """Daemons of one run in a fresh namespace; `poll` records every member's track."""

    def __init__(
        self,
        base: Path,
        name: str,
        *,
        env: dict[str, str] | None = None,
        odometry_noise: str | None = None,
        world: str = "office",
    ) -> None:
        self.name = name
        self.world = world
        self.colony = LocalColony(base, colony="sim", heartbeat_s=0.5)
        self.env = {**RUN_ENV, **(env or {})}
        self.odometry_noise = odometry_noise
        self.tracks: dict[str, Track] = {}
        self.reports: list[dict[str, Any]] = []
        self.began = time.monotonic()
        self._watcher: threading.Thread | None = None
        self._stop_watch = threading.Event()

    def now(self) -> float:
        """Seconds since the run began."""
        return time.monotonic() - self.began

    def add(self, agent: str, duration: float, seed: int, options: str = "") -> None:
        """Start `agent`'s daemon mapping its sim source for `duration` seconds (`options`: more
        options of its `sim:` spec)."""
        spec = sim_spec(
            agent,
            duration,
            seed,
            world=self.world,
            odometry_noise=self.odometry_noise,
            options=options,
        )
        d = self.colony.add(agent, [spec], start=False)
        d.env = dict(self.env)
        d.start()
        self.tracks[agent] = Track(CARRIES.get(agent, "?"), self.now())

    def poll(self, timeout: float = 3.0) -> list[dict[str, Any]]:
        """One status round, recorded into the tracks (a round ends once every daemon answered:
        the timeout only bounds a slow one, which a loaded machine has; with 1 s, rounds missed
        a busy robot so often that a 5 s run recorded fewer than 3 of its poses)."""
        self.reports = self.colony.status(timeout=timeout)
        record(self.reports, self.tracks, self.now())
        return self.reports

    def poll_all(self, within: float = 15.0) -> list[dict[str, Any]]:
        """Status rounds until every member answered one (or `within` seconds passed): the last
        round, recorded (a loaded daemon can miss a round's timeout; its report would be {})."""
        deadline = time.monotonic() + within
        while True:
            reports = self.poll()
            if {r["agent"] for r in reports} >= set(self.tracks) or time.monotonic() > deadline:
                return reports
            time.sleep(0.2)

    def watch(self, interval: float = 0.25) -> None:
        """Poll in a thread of its own every `interval` seconds until `unwatch` (runs watched
        side by side each keep their pace, however slowly another answers)."""
        self._stop_watch = threading.Event()

        def loop() -> None:
            while not self._stop_watch.is_set():
                try:
                    self.poll()
                except Exception:  # one failed round (a session closing, a bad reply)
                    log.exception("run %s: a status round failed", self.name)
                self._stop_watch.wait(interval)

        self._watcher = threading.Thread(target=loop, name=f"watch-{self.name}", daemon=True)
        self._watcher.start()

    def unwatch(self) -> None:
        """Stop the watching thread after its current poll."""
        if self._watcher is not None:
            self._stop_watch.set()
            self._watcher.join()
            self._watcher = None

    def mapping_done(self) -> bool:
        """True when every member answered in the last round and its sources are done."""
        answered = {r["agent"]: r for r in self.reports}
        return set(answered) >= set(self.tracks) and all(
            answered[a].get("sources_done") for a in self.tracks
        )

    def report(self, agent: str) -> dict[str, Any]:
        """`agent`'s last status report ({} when it did not answer)."""
        return next((r for r in self.reports if r["agent"] == agent), {})

    def maps(self, agent: str, wait_s: float = 5.0) -> tuple[MapReply, dict[str, MapReply]]:
        """`agent`'s fused map (in its colony frame) and its layers' maps (waiting up to `wait_s`
        seconds for an answer)."""
        return fetch_maps(self.colony.session(), self.colony.namespace, agent=agent, wait_s=wait_s)

    def close(self) -> None:
        self.unwatch()
        self.colony.close()


class AloneReplay:
    """One agent's sim source (same spec and seed as in a run, not paced) through its estimator
    with nobody to share with: `colonyd localize` in a process of low priority, so that it takes
    what the run's daemons leave of the CPU. Its ATE is what the agent achieves alone."""

    def __init__(
        self, out: Path, agent: str, duration: float, seed: int, odometry_noise: str | None
    ) -> None:
        self.agent, self.out = agent, Path(out)
        spec = sim_spec(agent, duration, seed, odometry_noise=odometry_noise, realtime=False)
        self.out.parent.mkdir(parents=True, exist_ok=True)
        command = ["localize", "--source", spec, "--out", str(self.out), "--no-progress"]
        with open(self.out.parent / f"{self.out.name}.log", "ab") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "colonyd", *command],
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=log,
            )
        below_us(self.proc.pid)

    def hurry(self) -> None:
        """Back to our priority (the run it gave way to is over)."""
        as_us(self.proc.pid)

    def result(self, wait_s: float) -> dict[str, float | None]:
        """ATE RMSE (m) of the estimate and of dead reckoning alone, waiting up to `wait_s`
        seconds for the replay to finish; None for both if it did not (it is then stopped)."""
        try:
            self.proc.wait(max(0.0, wait_s))
        except subprocess.TimeoutExpired:
            self.close()
            return {"estimate": None, "odometry": None}
        try:
            ate = json.loads((self.out / "results.json").read_text())["ate_rmse_m"]
        except (OSError, ValueError, KeyError):
            return {"estimate": None, "odometry": None}
        return {"estimate": ate.get("estimate"), "odometry": ate.get("odometry")}

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)
