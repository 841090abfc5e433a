"""The paper experiment's two robots offline, deterministic: one robot alone and with the other's
map, for A/B of estimator changes without the live runs' timing chaos.

`python -m colonyd.bench.paper_offline --seed S [--lidar-range R] [--rng N] [--duration S]
[--no-peer-covariance] [--json FILE]`

Each robot's sim source (the experiment's spec and seed, not paced) runs through its estimator
and maps from the estimate, as `colonyd localize` does. The peer's map (its estimated-pose voxel
grid at the end of its path) is put into the robot's frame by a fixture alignment, the true
transform between the two frames with a fixed error (3 cm, -5 cm, 0.5 degrees about the
robot's origin; its opposite for lidar-1) and the honest-error covariance measured live (6 cm,
12 cm, 1.2 degrees, docs/LOCALISATION.md), and given to the estimator from the middle of the
path (live first contact came at ~31 s of 60). As the daemon does (`colonyd.colonymap`), the
cut's covariance also holds the peer's own pose uncertainty: its filter's covariance at the
frame nearest in time to the robot's contact (when the cut is made), as an error of its map
about the cut's centre, moved into the robot's frame (`--no-peer-covariance`: the alignment's
alone, as before). The simulator's truth builds that fixture and
evaluates; no estimator reads it (as the "perfect peer map" diagnosis in docs/LOCALISATION.md).
`--rng` draws the scans' subsample with another seed: how far a run moves when nothing but
that changes (the noise to compare against).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from colonyd.colonymap import peer_map_error
from colonyd.estimator import ScanEstimator, get_estimator
from colonyd.mapping import integrate_observation
from colonyd.simrun import sim_spec
from plugins.source import open_source
from voxel import keys as vk
from voxel.grid import VoxelGrid
from voxel.localisation import se2
from voxel.localisation.colony_map import ColonyMap, colony_map
from voxel.localisation.metrics import absolute_trajectory_error
from voxel.occupancy import FREE_STATE, OCCUPIED

#: The fixture alignment's error (x, y, yaw about the robot's origin) and its covariance.
ALIGNMENT_ERROR = (0.03, -0.05, float(np.radians(0.5)))
ALIGNMENT_COVARIANCE = np.diag([0.06**2, 0.12**2, float(np.radians(1.2)) ** 2])
DURATION_S = 60.0


class Run:
    """One robot's path through its estimator: estimated and true sensor poses, its map."""

    def __init__(
        self, agent: str, seed: int, lidar_range: float, duration: float = DURATION_S
    ) -> None:
        options = f"lidar_range={lidar_range:g}" if agent == "lidar-1" else ""
        self.spec = sim_spec(
            agent, duration, seed, odometry_noise="realistic", realtime=False, options=options
        )
        self.estimates: list[np.ndarray] = []
        self.truths: list[np.ndarray] = []
        self.counts: dict[str, int] = {}
        self.covariances: list[np.ndarray] = []  # the filter's (x, y, yaw) covariance per frame
        self.times: list[float] = []  # the time of each frame with a covariance
        self.mount = np.eye(4)
        self.grid: VoxelGrid | None = None

    def go(
        self,
        peer: Run | None = None,
        rng: int = 0,
        sign: float = 1.0,
        peer_covariance: bool = True,
    ) -> float:
        """Run the path (with `peer`'s map from the middle on, its alignment off by `sign`
        times `ALIGNMENT_ERROR`, its pose covariance in the cut's if `peer_covariance`); the
        ATE."""
        source = open_source(self.spec, resolution=0.1)
        adapter = source.adapter
        grid = VoxelGrid(0.1, block_shape="planar" if adapter.kind == "lidar2d" else "cube")
        estimator: Any = None
        cut: ColonyMap | None = None
        frames = len(source)
        self.estimates, self.truths, self.covariances, self.times = [], [], [], []
        for i, obs in enumerate(source):
            if estimator is None:
                estimator = get_estimator(adapter, obs)
                estimator.localiser.rng = np.random.default_rng(rng)
            if peer is not None and i >= frames // 2 and self.estimates:
                pose = self.estimates[-1]
                if cut is None or not cut.covers(pose[:2, 3], cut.radius - 2.0):
                    at = obs.time if peer_covariance else None
                    cut = peer.cut_for(self, pose, estimator, sign, at)
                estimator.colony = cut
            pose = estimator(obs)
            integrate_observation(
                grid,
                replace(obs, pose=pose),
                sensor=adapter.sensor_model,
                reliability=adapter.reliability,
            )
            if obs.truth is None:
                msg = f"{self.spec}: expected the simulator's truth to evaluate, found none"
                raise ValueError(msg)
            self.estimates.append(pose)
            self.truths.append(obs.truth)
            if isinstance(estimator, ScanEstimator) and estimator.localiser.ekf is not None:
                self.covariances.append(estimator.localiser.ekf.covariance)
                self.times.append(obs.time)
        self.grid = grid
        if isinstance(estimator, ScanEstimator):
            self.mount = estimator.mount
            self.counts = {k: v for k, v in estimator.counts().items() if k.startswith("colony")}
        return absolute_trajectory_error(np.array(self.truths), np.array(self.estimates)).rmse

    def consistency(self) -> dict[str, float]:
        """How honest the filter's covariance was: the body pose error in the robot's own frame
        (truth put there by the first frame, evaluation only) against the covariance the filter
        claimed at each frame. `nees_mean`: mean normalised estimation error squared (3 when
        the covariance is honest, far above when overconfident); `nees_over`: share of frames
        above the 95 % chi-square bound (7.81; 0.05 when honest); `error_m` / `sigma_m`: median
        position error and claimed position standard deviation."""
        if len(self.covariances) != len(self.estimates) or not self.estimates:
            return {}
        frame = self.truths[0] @ np.linalg.inv(self.estimates[0])  # the robot's frame, world
        back, unmount = np.linalg.inv(frame), np.linalg.inv(self.mount)
        nees, errors, sigmas = [], [], []
        for est, truth, cov in zip(self.estimates, self.truths, self.covariances, strict=True):
            e = se2.from_matrix(back @ truth @ unmount) - se2.from_matrix(est @ unmount)
            e[2] = se2.wrap(float(e[2]))
            nees.append(float(e @ np.linalg.solve(cov + 1e-12 * np.eye(3), e)))
            errors.append(float(np.hypot(e[0], e[1])))
            sigmas.append(float(np.sqrt(cov[0, 0] + cov[1, 1])))
        n = np.array(nees[1:] or nees)
        return {
            "nees_mean": round(float(n.mean()), 2),
            "nees_over": round(float((n > 7.81).mean()), 3),
            "error_m": round(float(np.median(errors)), 4),
            "sigma_m": round(float(np.median(sigmas)), 4),
        }

    def cut_for(
        self,
        robot: Run,
        pose: np.ndarray,
        estimator: ScanEstimator,
        sign: float,
        at: float | None = None,
    ) -> ColonyMap:
        """This run's map near `robot`'s pose, in its frame through the fixture alignment; its
        covariance the alignment's, plus (at time `at`) this run's pose covariance then, as the
        error of its map about the cut's centre (`colonymap.peer_map_error`)."""
        assert self.grid is not None, "run the peer first"
        grid = self.grid
        ours = self.truths[0] @ np.linalg.inv(self.estimates[0])  # our frame in the world
        theirs = robot.truths[0] @ np.linalg.inv(robot.estimates[0])
        m = se2.to_matrix(sign * np.array(ALIGNMENT_ERROR)) @ np.linalg.inv(theirs) @ ours
        back = np.linalg.inv(m)
        centres = vk.keys_to_centers(grid.occupied_keys(), grid.resolution)

        def free(points: np.ndarray) -> np.ndarray:
            state = grid.state(points @ back[:3, :3].T + back[:3, 3])
            out: np.ndarray = (state == FREE_STATE) & (state != OCCUPIED)
            return out

        covariance = ALIGNMENT_COVARIANCE
        if at is not None and self.covariances:
            i = int(np.argmin(np.abs(np.array(self.times) - at)))
            covariance = covariance + peer_map_error(self.covariances[i], m, pose[:2, 3])
        planar = estimator.planar
        return colony_map(
            centres @ m[:3, :3].T + m[:3, 3],
            cell=0.05 if planar else 0.1,
            max_points=50_000 if planar else 20_000,
            planar=planar,
            height=estimator.height,
            centre=pose[:2, 3],
            radius=min(estimator.sensor_range, 30.0) + 2.0,
            sources=("peer",),
            covariance=covariance,
            alignment=b"fixture",
            free=free,
            step=grid.resolution,
        )


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m colonyd.bench.paper_offline")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--lidar-range", type=float, default=4.0)
    parser.add_argument("--rng", type=int, default=0, help="seed of the scans' subsample")
    parser.add_argument("--duration", type=float, default=DURATION_S, help="seconds of path")
    parser.add_argument(
        "--peer-covariance",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="add the peer's pose covariance to its map's (as the daemon does; default on)",
    )
    parser.add_argument("--json", type=Path, help="append the result as one JSON line")
    args = parser.parse_args(argv)

    def robot(agent: str) -> Run:
        seed = 100 * args.seed + (1 if agent == "lidar-1" else 2)
        return Run(agent, seed, args.lidar_range, args.duration)

    lidar, depth = robot("lidar-1"), robot("depth-1")
    out: dict[str, Any] = {"seed": args.seed, "lidar_range": args.lidar_range, "rng": args.rng}
    out["peer_covariance"] = args.peer_covariance
    out["lidar_alone"] = round(lidar.go(rng=args.rng), 4)
    out["lidar_alone_consistency"] = lidar.consistency()
    out["depth_alone"] = round(depth.go(rng=args.rng), 4)
    out["depth_alone_consistency"] = depth.consistency()
    with_lidar = robot("depth-1")
    out["depth_with_lidar"] = round(
        with_lidar.go(lidar, rng=args.rng, peer_covariance=args.peer_covariance), 4
    )
    out["depth_counts"] = with_lidar.counts
    out["depth_with_lidar_consistency"] = with_lidar.consistency()
    with_depth = robot("lidar-1")
    out["lidar_with_depth"] = round(
        with_depth.go(depth, rng=args.rng, sign=-1.0, peer_covariance=args.peer_covariance), 4
    )
    out["lidar_counts"] = with_depth.counts
    out["lidar_with_depth_consistency"] = with_depth.consistency()
    print(json.dumps(out))
    if args.json is not None:
        with args.json.open("a", encoding="ascii") as f:
            f.write(json.dumps(out) + "\n")
    return out


if __name__ == "__main__":
    main()
