"""Truth scans: a paper robot's scans, preprocessed as its localiser does, with its true pose."""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from colonyd.bench.files import print_and_append
from colonyd.estimator import ScanEstimator, get_estimator
from colonyd.simrun import sim_spec
from plugins.observation import Observation
from plugins.source import open_source
from voxel.localisation import se2
from voxel.localisation.scan_match import LocalMap, thin


@dataclass
class TruthScan:
    """One scan of a robot: its index, its observation, its estimator (made from its first
    observation), all its points in the body frame (`body`: what the estimator's step takes),
    the matcher's thinned and subsampled set (`points`), and the true body pose (4x4 `truth`,
    and x, y, yaw `true`; evaluation only)."""

    index: int
    observation: Observation
    estimator: ScanEstimator
    body: np.ndarray
    points: np.ndarray
    truth: np.ndarray
    true: np.ndarray


def truth_scans(
    agent: str, seed: int, lidar_range: float, duration: float, rng: np.random.Generator
) -> Iterator[TruthScan]:
    """The paper experiment's robot `agent` (its sim spec and seed), scan by scan. `rng` draws
    the matcher's subsample, as the localiser's own does."""
    options = f"lidar_range={lidar_range:g}" if agent == "lidar-1" else ""
    spec = sim_spec(
        agent, duration, seed, odometry_noise="realistic", realtime=False, options=options
    )
    source = open_source(spec, resolution=0.1)
    estimator: ScanEstimator | None = None
    for i, obs in enumerate(source):
        if obs.truth is None:
            msg = f"{spec}: expected the simulator's truth to evaluate, found none"
            raise ValueError(msg)
        if estimator is None:
            made = get_estimator(source.adapter, obs)
            if not isinstance(made, ScanEstimator):
                msg = f"{agent}: expected a scan estimator, found {made.name}"
                raise ValueError(msg)
            estimator = made
        p = estimator.localiser.params
        points = obs.points if obs.no_return is None else obs.points[~obs.no_return]
        body = points @ estimator.mount[:3, :3].T + estimator.mount[:3, 3]
        pts = thin(body[np.linalg.norm(body[:, :2], axis=1) <= p.max_range], p.scan_cell)
        if len(pts) > p.max_points:
            pts = pts[rng.choice(len(pts), p.max_points, replace=False)]
        truth = obs.truth @ np.linalg.inv(estimator.mount)
        yield TruthScan(i, obs, estimator, body, pts, truth, se2.from_matrix(truth))


def truth_map(estimator: ScanEstimator) -> LocalMap:
    """An empty local map with the localiser's parameters, to build from true poses."""
    p = estimator.localiser.params
    return LocalMap(
        planar=estimator.planar,
        keyframes=p.keyframes,
        cell=p.map_cell,
        key_distance=p.key_distance,
        key_angle=p.key_angle,
    )


def add_true(target: LocalMap, scan: TruthScan) -> None:
    """Add `scan` to `target` at its true pose, where the map wants a keyframe there."""
    flat = se2.to_matrix(scan.true)
    if target.wants(flat):
        sensor = scan.estimator.localiser.sensor
        target.add(
            scan.points @ flat[:3, :3].T + flat[:3, 3], flat, flat[:3, :3] @ sensor + flat[:3, 3]
        )


def agent_main(
    prog: str,
    measure: Callable[[str, int, float, float], dict[str, Any]],
    argv: list[str] | None = None,
) -> dict[str, Any]:
    """A truth-scan bench's command line: `measure(agent, seed, lidar_range, duration)` per robot,
    printed and appended as one JSON line."""
    parser = argparse.ArgumentParser(prog=prog)
    parser.add_argument("--seed", type=int, default=2)
    parser.add_argument("--agent", choices=("lidar-1", "depth-1", "both"), default="both")
    parser.add_argument("--lidar-range", type=float, default=3.0)
    parser.add_argument("--duration", type=float, default=60.0, help="seconds of path")
    parser.add_argument("--json", type=Path, help="append the result as one JSON line")
    args = parser.parse_args(argv)
    out: dict[str, Any] = {"seed": args.seed, "lidar_range": args.lidar_range}
    agents = ("lidar-1", "depth-1") if args.agent == "both" else (args.agent,)
    for agent in agents:
        seed = 100 * args.seed + (1 if agent == "lidar-1" else 2)
        out[agent] = measure(agent, seed, args.lidar_range, args.duration)
    print_and_append(out, args.json)
    return out
