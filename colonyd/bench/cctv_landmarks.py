"""depth-1 with the CCTV's fixes and its landmarks offline, deterministic: each sighting fused as
independent, or the landmark's error estimated in the filter and counted once.

`python -m colonyd.bench.cctv_landmarks --world hall|office --seed S [--duration S] [--lag S]
[--modes independent,once] [--lidar] [--json FILE]`

As `cctv_offline` (its `cctv_view` fixes, its `Cctv` fix path: sightings until depth-1's frame is
aligned with the CCTV's, then fixes fused), plus the landmarks as the daemon fuses them: cctv-1's
published markers (its images folded into `OwnObjects` as its daemon does, `cctv_markers`; the
list as it stood `--lag` s before each of depth-1's frames), once depth-1 is aligned with the
CCTV put into depth-1's frame by `colony_landmarks` (the markers' published covariance plus the
alignment's error there), and fused after each step for every marker depth-1's camera detects
in its observation (`ScanEstimator.landmarks`; its sim source with `markers=1`, as the
experiment's `agent_options`). `--modes`: `independent`, every sighting a new
measurement (`ScanParams.landmark_errors` off); `once`, each landmark's error in the filter
(on); `none`, fixes only (as `cctv_offline`). Per mode: depth-1's ATE, landmarks fused /
refused, fixes fused / refused / stale, the filter's consistency (`Run.consistency`) and its
heading's (`heading_consistency`); `--lidar`: lidar-1 then runs as `cctv_offline`'s `both`
(fixes fused, the colony map of that depth-1 run's final map and the CCTV's).

Truth renders and evaluates; no estimator reads it. Not as live: the object lists arrive
without loss at a fixed lag, and lidar-1 gets depth-1's final map (live, as it grows).
"""

from __future__ import annotations

import argparse
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from colonyd.bench.cctv_offline import (
    CCTV,
    ROBOTS,
    Cctv,
    Fix,
    alignment_truth,
    cctv_view,
)
from colonyd.bench.files import print_and_append
from colonyd.bench.options import alignment_option, names
from colonyd.bench.paper_offline import Run
from colonyd.estimator import ScanEstimator
from colonyd.landmarks import colony_landmarks
from colonyd.layers import Layer
from colonyd.objects import OwnObjects, to_wire
from plugins.observation import Observation
from plugins.sim import AGENTS, SimSource
from protocol import ObjectCentroid as WireObject
from voxel.localisation import se2

MODES = ("none", "independent", "once")


def published_markers(seed: int, duration: float, world: str) -> list[tuple[float, list[Any]]]:
    """cctv-1's object list over `duration` s of seed `seed` (its images as `cctv_view`
    renders them, the robots' boards included), folded into `OwnObjects` as its daemon does:
    (time, the list as published then) at each image where it changed."""
    frames = max(2, int(AGENTS[world][CCTV].rate * duration))
    source = SimSource(
        world=world,
        agent=CCTV,
        seed=100 * seed + 3,
        frames=frames,
        epoch=0.0,
        keep_late=True,
        robots="+".join(ROBOTS),
    )
    objects = OwnObjects(frozenset())
    layer = Layer(CCTV, 0.1)  # its own layer's map: unused (no clusters, only identified)
    lists: list[tuple[float, list[Any]]] = []
    for obs in source:
        objects.observe(obs)
        found = objects.refresh(layer)
        if found is not None:
            lists.append((obs.time, to_wire(found)))
    return lists


class Landmarks:
    """The daemon's landmark path for depth-1 (`Run.go`'s `after`): the CCTV's list as it stood
    `lag` s before the frame, in depth-1's frame once its fix path (`fixes`, a `Cctv`) aligned
    it with the CCTV, fused for every marker depth-1 detects (`ScanEstimator.landmarks`); the
    filter estimates each landmark's error with `once` (`ScanParams.landmark_errors`)."""

    def __init__(
        self, lists: list[tuple[float, list[WireObject]]], fixes: Cctv, lag: float, once: bool
    ) -> None:
        self.lists, self.fixes, self.lag, self.once = lists, fixes, lag, once
        self.fused = self.refused = 0

    def __call__(self, obs: Observation, estimator: ScanEstimator) -> None:
        loc = estimator.localiser
        if loc.params.landmark_errors != self.once:
            loc.params = replace(loc.params, landmark_errors=self.once)
        if self.fixes.edge is None or not obs.objects:
            return
        ready = [objects for t, objects in self.lists if t + self.lag <= obs.time + 1e-6]
        if not ready:
            return
        ids = {d.object_id for d in obs.objects}
        mine = [o for o in ready[-1] if o.object_id in ids]
        if not mine:
            return
        known = colony_landmarks(
            self.fixes.frame(), self.fixes.robot, {CCTV: mine}, framed=estimator.framed
        )
        before = loc.landmark_accepted, loc.landmark_rejected
        estimator.landmarks(obs, known)
        self.fused += loc.landmark_accepted - before[0]
        self.refused += loc.landmark_rejected - before[1]


def heading_consistency(run: Run) -> dict[str, float]:
    """Evaluation: depth-1's heading error in its own frame (the truth put there by the first
    frame) against the variance its filter claimed: RMS and largest error (degrees), mean NEES
    (1 when honest), share of frames above the 95 % bound (3.84)."""
    if len(run.covariances) != len(run.estimates) or not run.estimates:
        return {}
    frame = run.truths[0] @ np.linalg.inv(run.estimates[0])
    back, unmount = np.linalg.inv(frame), np.linalg.inv(run.mount)
    errors, nees = [], []
    for est, truth, cov in zip(run.estimates, run.truths, run.covariances, strict=True):
        e = se2.wrap(
            float(se2.from_matrix(back @ truth @ unmount)[2] - se2.from_matrix(est @ unmount)[2])
        )
        errors.append(e)
        nees.append(e * e / (cov[2, 2] + 1e-12))
    err, n = np.array(errors[1:] or errors), np.array(nees[1:] or nees)
    return {
        "rms_deg": round(math.degrees(float(np.sqrt(np.mean(err**2)))), 3),
        "max_deg": round(math.degrees(float(np.abs(err).max())), 3),
        "nees_mean": round(float(n.mean()), 2),
        "nees_over": round(float((n > 3.84).mean()), 3),
    }


def run_mode(
    mode: str,
    args: argparse.Namespace,
    fixes: list[Fix],
    lists: list[tuple[float, list[WireObject]]],
    cctv_grid: Any,
) -> dict[str, Any]:
    """depth-1 with the CCTV's fixes and (unless `mode` none) its landmarks, then with
    `--lidar` lidar-1 as `cctv_offline`'s `both`; the figures of both."""
    out: dict[str, Any] = {}
    depth = Run("depth-1", 100 * args.seed + 2, args.lidar_range, args.duration, world=args.world)
    depth.spec += ",markers=1"  # depth-1 reads the markers, as in the experiment
    state = args.alignment == "state"
    path = Cctv("depth-1", fixes, args.lag, state=state)
    hook = None if mode == "none" else Landmarks(lists, path, args.lag, mode == "once")
    out["depth_ate"] = round(depth.go(before=path, after=hook), 4)
    out["depth_landmarks"] = None if hook is None else [hook.fused, hook.refused]
    out["depth_fixes"] = [path.fused, path.refused, path.stale]
    out["depth_aligned_at"] = path.aligned_at
    out["depth_consistency"] = depth.consistency()
    out["depth_heading"] = heading_consistency(depth)
    out["depth_alignment"] = alignment_truth(path, depth)
    if args.lidar and path.edge is not None:
        lidar = Run(
            "lidar-1", 100 * args.seed + 1, args.lidar_range, args.duration, world=args.world
        )
        both = Cctv(
            "lidar-1",
            fixes,
            args.lag,
            cctv_grid=cctv_grid,
            peer=("depth-1", depth, path.edge, path.edge.time),
            state=state,
        )
        out["lidar_ate"] = round(lidar.go(before=both), 4)
        out["lidar_fixes"] = [both.fused, both.refused, both.stale]
    return out


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m colonyd.bench.cctv_landmarks")
    parser.add_argument("--world", choices=("office", "hall"), default="hall")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--duration", type=float, default=60.0, help="seconds of path")
    parser.add_argument("--lidar-range", type=float, default=4.0)
    parser.add_argument("--lag", type=float, default=0.5, help="s from a stamp to its use")
    parser.add_argument(
        "--modes",
        type=names(MODES),
        default="independent,once",
        help=f"comma-separated, of {MODES}",
    )
    parser.add_argument("--lidar", action="store_true", help="lidar-1 after each depth-1 run")
    alignment_option(parser, "the fixes and landmarks")
    parser.add_argument("--json", type=Path, help="append the result as one JSON line")
    args = parser.parse_args(argv)
    modes = args.modes
    fixes, cctv_grid, _ = cctv_view(args.seed, args.duration, world=args.world)
    lists = published_markers(args.seed, args.duration, args.world)
    out: dict[str, Any] = {
        "world": args.world,
        "seed": args.seed,
        "duration": args.duration,
        "lag": args.lag,
        "alignment": args.alignment,
        "published": [
            {"at_s": t, "markers": sorted(o.object_id for o in objects)} for t, objects in lists
        ][:3],
    }
    for mode in modes:
        out[mode] = run_mode(mode, args, fixes, lists, cctv_grid)
    print_and_append(out, args.json)
    return out


if __name__ == "__main__":
    main()
