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

from typing import Any

import numpy as np

from colonyd.bench.truthscan import add_true, agent_main, truth_map, truth_scans
from voxel.localisation import se2
from voxel.localisation.scan_match import LocalMap

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
    rng = np.random.default_rng(seed)
    target_map: LocalMap | None = None
    rows: dict[str, list[Any]] = {k: [] for k in ("tf", "te", "tc", "ty", "of", "oe", "oc")}
    frame = np.eye(4)
    for scan in truth_scans(agent, seed, lidar_range, duration, rng):
        i, obs, loc, true = scan.index, scan.observation, scan.estimator.localiser, scan.true
        # the truth case: this scan, preprocessed as the localiser does, against the truth map
        if target_map is None:
            target_map = truth_map(scan.estimator)
        else:
            start = true + rng.normal(0.0, START_ERROR)
            m = loc.match_from(scan.points, target_map, start)
            if m.ok:
                e = se2.from_matrix(m.pose) - true
                e[2] = se2.wrap(float(e[2]))
                rows["tf"].append(i)
                rows["te"].append(e)
                rows["tc"].append(m.covariance)
                rows["ty"].append(true[1])
        add_true(target_map, scan)
        # the own case: the estimator's step, its own-map match against the truth in its frame
        odometry = None if obs.odometry is None else se2.from_matrix(obs.odometry)
        step = loc.step(scan.body, odometry, colony=None, time=obs.time)
        if i == 0:
            frame = scan.truth @ np.linalg.inv(se2.to_matrix(step.pose))  # robot frame in world
        if step.match is not None and step.match.ok:
            own_true = se2.from_matrix(np.linalg.inv(frame) @ scan.truth)
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
    return agent_main("python -m colonyd.bench.match_nees", measure, argv)


if __name__ == "__main__":
    main()
