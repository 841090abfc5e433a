"""How honest the scan matcher's covariance is: real sim scans matched against a map, each match's
error against the covariance it claims (NEES).

`python -m colonyd.bench.match_nees --seed S [--agent A] [--lidar-range R] [--duration D]
[--json FILE]`

For each robot of the paper's experiment (its spec and seed, as `paper_offline`), two cases:

- `truth`: the scan matched against a local map built from the TRUE poses (the same `LocalMap`
  and keyframe rule as the estimator's), from the true pose perturbed by a realistic prediction
  error (3 cm, 3 cm, 1 degree, drawn with a fixed seed). Only the matcher is measured: the map
  has no drift. Truth builds this fixture and evaluates; no estimator reads it.
- `own`: the estimator's own match (against its own map, built from its drifting estimates),
  as the filter meets it; the error is against the truth in the robot's frame (put there by the
  first frame), so it includes the map's drift: what the filter is told is an absolute pose.

Per case: `nees_mean` (3 when honest), `nees_over` (share above the chi-square 95 % bound,
7.81; 0.05 when honest), the median position error and claimed position standard deviation,
the same over named places (`top_wall`: lidar-1 on the top room's 10 m wall, true y > 2.8 m;
`slide`: frames 438-458, where depth-1 of seed 2 slides along its camera's axis), and the
worst 20-frame window.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from colonyd.bench.files import print_and_append
from colonyd.estimator import ScanEstimator, get_estimator
from colonyd.simrun import sim_spec
from plugins.source import open_source
from voxel.localisation import se2
from voxel.localisation.scan_match import LocalMap, thin

#: Standard deviations of the prediction error the truth case starts each match from (x, y, yaw).
START_ERROR = (0.03, 0.03, float(np.radians(1.0)))
CHI2_95_3DOF = 7.81
WINDOW = 20


def _nees(errors: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    solved = np.linalg.solve(covariances + 1e-12 * np.eye(3), errors[:, :, None])[:, :, 0]
    out: np.ndarray = np.einsum("ni,ni->n", errors, solved)
    return out


def summary(errors: np.ndarray, covariances: np.ndarray) -> dict[str, float]:
    """NEES mean, share over the 95 % bound, median position error and claimed sigma."""
    if len(errors) == 0:
        return {}
    n = _nees(errors, covariances)
    return {
        "n": len(n),
        "nees_mean": round(float(n.mean()), 2),
        "nees_median": round(float(np.median(n)), 2),
        "nees_over": round(float((n > CHI2_95_3DOF).mean()), 3),
        "error_m": round(float(np.median(np.hypot(errors[:, 0], errors[:, 1]))), 4),
        "sigma_m": round(float(np.median(np.sqrt(covariances[:, 0, 0] + covariances[:, 1, 1]))), 4),
        "yaw_error_deg": round(float(np.degrees(np.median(np.abs(errors[:, 2])))), 3),
    }


def report(
    frames: np.ndarray, errors: np.ndarray, covs: np.ndarray, places: dict[str, np.ndarray]
) -> dict[str, Any]:
    """`summary` overall, per place (a mask over `frames`) and over the worst window."""
    out: dict[str, Any] = {"all": summary(errors, covs)}
    for name, mask in places.items():
        if mask.any():
            out[name] = summary(errors[mask], covs[mask])
    n = _nees(errors, covs)
    if len(n) >= WINDOW:
        means = np.convolve(n, np.ones(WINDOW) / WINDOW, mode="valid")
        i = int(np.argmax(means))
        out["worst_window"] = {"frames": [int(frames[i]), int(frames[i + WINDOW - 1])]} | summary(
            errors[i : i + WINDOW], covs[i : i + WINDOW]
        )
    return out


def measure(agent: str, seed: int, lidar_range: float, duration: float) -> dict[str, Any]:
    """Both cases for one robot."""
    options = f"lidar_range={lidar_range:g}" if agent == "lidar-1" else ""
    spec = sim_spec(
        agent, duration, seed, odometry_noise="realistic", realtime=False, options=options
    )
    source = open_source(spec, resolution=0.1)
    rng = np.random.default_rng(seed)
    estimator: ScanEstimator | None = None
    truth_map: LocalMap | None = None
    rows: dict[str, list[Any]] = {k: [] for k in ("tf", "te", "tc", "ty", "of", "oe", "oc")}
    frame = np.eye(4)
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
        loc = estimator.localiser
        p = loc.params
        unmount = np.linalg.inv(estimator.mount)
        body_truth = obs.truth @ unmount
        # the truth case: this scan, preprocessed as the localiser does, against the truth map
        points = obs.points if obs.no_return is None else obs.points[~obs.no_return]
        body = points @ estimator.mount[:3, :3].T + estimator.mount[:3, 3]
        pts = body[np.linalg.norm(body[:, :2], axis=1) <= p.max_range]
        pts = thin(pts, p.scan_cell)
        if len(pts) > p.max_points:
            pts = pts[rng.choice(len(pts), p.max_points, replace=False)]
        true = se2.from_matrix(body_truth)
        if truth_map is None:
            truth_map = LocalMap(
                planar=estimator.planar,
                keyframes=p.keyframes,
                cell=p.map_cell,
                key_distance=p.key_distance,
                key_angle=p.key_angle,
            )
        else:
            start = true + rng.normal(0.0, START_ERROR)
            m = loc.match_from(pts, truth_map, start)
            if m.ok:
                e = se2.from_matrix(m.pose) - true
                e[2] = se2.wrap(float(e[2]))
                rows["tf"].append(i)
                rows["te"].append(e)
                rows["tc"].append(m.covariance)
                rows["ty"].append(true[1])
        flat = se2.to_matrix(true)
        if truth_map.wants(flat):
            truth_map.add(
                pts @ flat[:3, :3].T + flat[:3, 3], flat, flat[:3, :3] @ loc.sensor + flat[:3, 3]
            )
        # the own case: the estimator's step, its own-map match against the truth in its frame
        odometry = None if obs.odometry is None else se2.from_matrix(obs.odometry)
        step = loc.step(body, odometry, colony=None, time=obs.time)
        if i == 0:
            frame = body_truth @ np.linalg.inv(se2.to_matrix(step.pose))  # robot frame in world
        if step.match is not None and step.match.ok:
            own_true = se2.from_matrix(np.linalg.inv(frame) @ body_truth)
            e = se2.from_matrix(step.match.pose) - own_true
            e[2] = se2.wrap(float(e[2]))
            rows["of"].append(i)
            rows["oe"].append(e)
            rows["oc"].append(step.match.covariance)
    tf, te, tc = np.array(rows["tf"]), np.array(rows["te"]), np.array(rows["tc"])
    of, oe, oc = np.array(rows["of"]), np.array(rows["oe"]), np.array(rows["oc"])
    places_t: dict[str, np.ndarray] = {}
    places_o: dict[str, np.ndarray] = {}
    if agent == "lidar-1":
        places_t["top_wall"] = np.array(rows["ty"]) > 2.8
    else:
        places_t["slide"] = (tf >= 438) & (tf <= 458)
        places_o["slide"] = (of >= 438) & (of <= 458)
    return {
        "truth": report(tf, te, tc, places_t),
        "own": report(of, oe, oc, places_o),
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m colonyd.bench.match_nees")
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


if __name__ == "__main__":
    main()
