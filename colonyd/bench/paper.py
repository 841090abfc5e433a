"""The paper's experiment over several seeds: do the claims of issue 12 hold for each (sharing
halves the LiDAR robot's ATE, the CCTV anchor does not make it worse, no growth after contact)?"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

#: Targets: lidar+depth ATE <= RATIO x lidar-alone; after first contact the error's linear trend
#: rises by at most GROWTH_M over the rest of the run.
RATIO, GROWTH_M = 0.5, 0.05


def growth_after_contact(out: Path, run: str, agent: str, contact: float | None) -> float | None:
    """The rise (m) of the least-squares line through the agent's pose errors (after the Umeyama
    fit) from first contact to its last pose; None without contact or with < 3 poses after it."""
    from colonyd.tracks import Track, pose_errors

    if contact is None:
        return None
    track = Track("", 0.0)
    rows = []
    for name in ("estimate", "groundtruth"):
        path = out / run / f"{agent}.{name}.tum"
        rows.append(np.loadtxt(path, ndmin=2) if path.exists() else np.empty((0, 8)))
    for est, ref in zip(*rows, strict=True):
        track.times.append(float(est[0]))
        track.estimate.append(_pose(est))
        track.truth.append(_pose(ref))
    errors = pose_errors(track)
    if errors is None:
        return None
    times = np.array(track.times)
    after = times >= contact
    if after.sum() < 3:
        return None
    slope = np.polyfit(times[after], errors[after], 1)[0]
    return round(float(slope * (times[after][-1] - times[after][0])), 4)


def _load() -> list[float]:
    """The 1, 5 and 15 minute load averages."""
    import os

    return [round(x, 2) for x in os.getloadavg()]


def _pose(row: np.ndarray) -> np.ndarray:
    from voxel.rotation import quaternion_to_matrix

    pose = np.eye(4)
    pose[:3, :3] = quaternion_to_matrix(row[4:8])
    pose[:3, 3] = row[1:4]
    return pose


def claims(results: dict[str, Any], out: Path) -> dict[str, Any]:
    """The claims of one seed's results, each with the figures it rests on."""
    runs = results["runs"]

    def ate(run: str) -> float | None:
        value = runs.get(run, {}).get("lidar-1", {}).get("ate_rmse_m")
        return None if value is None else float(value)

    alone, shared, cctv = ate("lidar-alone"), ate("lidar+depth"), ate("lidar+depth+cctv")
    growth = {
        run: growth_after_contact(out, run, "lidar-1", runs[run]["lidar-1"]["first_contact_s"])
        for run in ("lidar+depth", "lidar+depth+cctv")
    }
    return {
        "lidar_ate_m": {"alone": alone, "lidar+depth": shared, "lidar+depth+cctv": cctv},
        "ratio_shared_to_alone": None
        if alone in (None, 0.0) or shared is None
        else round(shared / alone, 3),
        "shared_halves_ate": None if alone is None or shared is None else shared <= RATIO * alone,
        "cctv_no_worse": None if shared is None or cctv is None else cctv <= shared,
        "growth_after_contact_m": growth,
        "no_growth_after_contact": all(g is not None and g <= GROWTH_M for g in growth.values()),
    }


def run_paper_bench(
    out_json: Path,
    *,
    seeds: list[int],
    duration: float = 60.0,
    parallel: int = 2,
    lidar_range: float | None = None,
    world: str = "office",
    timeout: float | None = None,
    out_dir: Path | None = None,
    command: str | None = None,
) -> dict[str, Any]:
    """`run_paper` once per seed (outputs in `out_dir`/seed-N, or a temporary folder); writes every
    seed's results and claims to `out_json`."""
    from colonyd.experiment import run_paper

    per_seed = []
    with tempfile.TemporaryDirectory(prefix="bench-paper-") as tmp:
        base = Path(out_dir) if out_dir is not None else Path(tmp)
        for seed in seeds:
            out = base / f"seed-{seed}"
            before = _load()
            results = run_paper(
                out,
                seed=seed,
                duration=duration,
                parallel=parallel,
                lidar_range=lidar_range,
                world=world,
                timeout=timeout,
            )
            load = {"start": before, "end": _load()}  # the machine is shared: results' context
            per_seed.append({**results, "load_average": load, "claims": claims(results, out)})
    summary = {
        "seeds": seeds,
        "lidar_ate_m": {s["seed"]: s["claims"]["lidar_ate_m"] for s in per_seed},
        "shared_halves_ate": [s["claims"]["shared_halves_ate"] for s in per_seed],
        "cctv_no_worse": [s["claims"]["cctv_no_worse"] for s in per_seed],
        "no_growth_after_contact": [s["claims"]["no_growth_after_contact"] for s in per_seed],
        "seconds": [s["seconds"] for s in per_seed],
        "load_average": [s["load_average"] for s in per_seed],
    }
    result = {
        "command": command,
        "targets": {"ratio": RATIO, "growth_m": GROWTH_M},
        "summary": summary,
        "seeds": per_seed,
    }
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(result, indent=1) + "\n")
    return result
