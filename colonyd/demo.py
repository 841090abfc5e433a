"""`colonyd demo`: a 3-daemon colony on loopback mapping simulated worlds until it converges."""

from __future__ import annotations

import logging
import shutil
import tempfile
import time
from pathlib import Path

from colonyd.bench.launcher import LocalColony

log = logging.getLogger(__name__)

#: Demo agents in the plugins' office world: cheap sensors, a few seconds of mapping each.
DEMO_AGENTS = (("lidar-1", 40), ("lidar3d-1", 40), ("depth-1", 25), ("lidar-1", 40))


def demo_sources(agent_index: int) -> list[str]:
    """A short simulated run per agent: one agent of the `sim:` office world, paced in real time."""
    agent, frames = DEMO_AGENTS[agent_index % len(DEMO_AGENTS)]
    return [f"sim:world=office,agent={agent},frames={frames},seed={agent_index + 1},realtime=1"]


def run_demo(out: Path, *, daemons: int = 3, timeout: float = 45.0) -> int:
    """Run the demo; writes each daemon's fused map as .ply and .bt into `out`."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="colonyd-demo-"))
    t0 = time.monotonic()
    colony = LocalColony(work, colony="demo", heartbeat_s=0.5)
    try:
        agents = [f"robot-{i + 1}" for i in range(daemons)]
        for i, agent in enumerate(agents):
            colony.add(
                agent, demo_sources(i), extra=["--export-dir", str(out)]
            )  # waits for the hub
        colony.wait_members(daemons, timeout=20)
        started = time.monotonic()
        colony.wait_converged(timeout, agents)
        converged_s = time.monotonic() - started
        reports = colony.status(digest=True)
        lines = [
            (
                f"colony 'demo' (namespace {colony.namespace}): {len(reports)} members, "
                f"converged {converged_s:.1f} s after all joined"
            )
        ]
        total_bytes = 0
        for r in reports:
            counts = r["metrics"]["counts"]
            sent = int(counts.get("bytes_published", 0)) + int(counts.get("bytes_served", 0))
            total_bytes += sent
            layers = ", ".join(
                f"{o}: {v['voxels']} voxels @ seq {v['seq']}"
                for o, v in sorted(r["layers"].items())
            )
            lines.append(f"  {r['agent']:<9} sent {sent / 1024:8.1f} KiB  layers {layers}")
        lines.append(
            f"  gossiped {total_bytes / 1024:.1f} KiB in total; every replica equals its "
            "origin (digests match)"
        )
        colony.close()  # each daemon writes its fused view into `out` as it stops
        written = sorted(p.name for p in out.iterdir() if p.suffix in (".ply", ".bt"))
        lines.append(f"  maps written to {out}: {', '.join(written)}")
        lines.append(f"  total {time.monotonic() - t0:.1f} s")
        print("\n".join(lines))  # the demo's report is its output
        return 0
    finally:
        colony.close()
        shutil.rmtree(work, ignore_errors=True)
