"""Whether a robot's scans are biased against the world: each scan matched from its TRUE pose,
the offset the matcher recovers, in the body frame (forward, left, yaw).

`python -m colonyd.bench.match_bias --seed S [--agent A] [--lidar-range R] [--duration D]
[--json FILE]`

For each robot of the paper's experiment (its spec and seed, as `match_nees`), each scan,
preprocessed as its localiser does, is matched with the localiser's parameters from the true
body pose against two targets:

- `world`: the world's exact surfaces (points every 2 cm on every box face, cylinder side and
  the floor, with their exact outward normals). Only the sensor model and the matcher's
  arithmetic are left: a mean offset beyond its standard error is a sensor-side defect (render
  against back-projection, intrinsics, mount, timing).
- `truth_map`: a `LocalMap` built from the true poses (as `match_nees`): adds the voxelised
  map's own effects (thinning, normals fitted to it).

Per target: the mean body-frame offset (mm, mm, degrees) with its standard error, the spread,
and the median claimed standard deviations. Truth builds these fixtures and evaluates; no
estimator reads it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from colonyd.bench.truthscan import add_true, agent_main, truth_map, truth_scans
from plugins.world import World, get_world
from voxel.localisation import se2
from voxel.localisation.scan_match import LocalMap

#: Spacing (m) of the exact surfaces' points.
SPACING = 0.02


@dataclass(frozen=True)
class Surfaces:
    """A `MatchTarget` of exact surfaces: points, outward normals, their tree."""

    points: np.ndarray
    normals: np.ndarray
    tree: cKDTree
    cell: float
    oriented: bool = True


def surfaces(world: World, cell: float, spacing: float = SPACING) -> Surfaces:
    """The world's boxes, cylinder sides and floor (under the boxes' extent) as points every
    `spacing` m with exact outward normals; `cell`: the map cell the matcher assumes."""
    points, normals = [], []
    for box in world.boxes:
        lo, hi = np.asarray(box.lo, np.float64), np.asarray(box.hi, np.float64)
        for axis in range(3):
            for side, sign in ((lo[axis], -1.0), (hi[axis], 1.0)):
                a, b = lo.copy(), hi.copy()
                a[axis] = b[axis] = side
                axes = [np.arange(a[i], b[i] + spacing / 2, spacing) for i in range(3)]
                grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
                normal = np.zeros(3)
                normal[axis] = sign
                points.append(grid)
                normals.append(np.tile(normal, (len(grid), 1)))
    for c in world.cylinders:
        n = max(8, int(2 * np.pi * c.radius / spacing))
        ring = np.column_stack(
            [
                np.cos(np.linspace(0, 2 * np.pi, n, endpoint=False)),
                np.sin(np.linspace(0, 2 * np.pi, n, endpoint=False)),
            ]
        )
        z = np.arange(c.z0, c.z1 + spacing / 2, spacing)
        side = np.column_stack([np.repeat(ring * c.radius + c.centre, len(z), 0), np.tile(z, n)])
        points.append(side)
        normals.append(np.column_stack([np.repeat(ring, len(z), 0), np.zeros(len(side))]))
    if world.floor is not None and world.boxes:
        lo = np.min([b.lo for b in world.boxes], axis=0)
        hi = np.max([b.hi for b in world.boxes], axis=0)
        xs, ys = np.arange(lo[0], hi[0], spacing), np.arange(lo[1], hi[1], spacing)
        grid = np.stack(np.meshgrid(xs, ys, [world.floor], indexing="ij"), axis=-1).reshape(-1, 3)
        points.append(grid)
        normals.append(np.tile([0.0, 0.0, 1.0], (len(grid), 1)))
    p = np.concatenate(points)
    return Surfaces(p, np.concatenate(normals), cKDTree(p), cell)


def summary(errors: np.ndarray, covariances: np.ndarray) -> dict[str, Any]:
    """Mean body-frame offset with its standard error, spread and median claimed sigma, in mm,
    mm, degrees."""
    if len(errors) == 0:
        return {"n": 0}
    scale = np.array([1e3, 1e3, math.degrees(1.0)])
    mean, sd = errors.mean(axis=0) * scale, errors.std(axis=0) * scale
    claimed = np.sqrt(np.median(covariances[:, [0, 1, 2], [0, 1, 2]], axis=0)) * scale
    return {
        "n": len(errors),
        "mean": np.round(mean, 3).tolist(),
        "standard_error": np.round(sd / math.sqrt(len(errors)), 3).tolist(),
        "sd": np.round(sd, 3).tolist(),
        "claimed_sd": np.round(claimed, 3).tolist(),
    }


def measure(agent: str, seed: int, lidar_range: float, duration: float) -> dict[str, Any]:
    """Both targets for one robot."""
    rng = np.random.default_rng(seed)
    exact: Surfaces | None = None
    target_map: LocalMap | None = None
    rows: dict[str, list[Any]] = {"we": [], "wc": [], "te": [], "tc": []}
    for scan in truth_scans(agent, seed, lidar_range, duration, rng):
        loc = scan.estimator.localiser
        if exact is None or target_map is None:
            exact = surfaces(get_world("office"), loc.params.map_cell)
            target_map = truth_map(scan.estimator)
        true = scan.true
        c, s = math.cos(true[2]), math.sin(true[2])
        for key, target in (("w", exact), ("t", target_map)):
            if target.tree is None:
                continue
            m = loc.match_from(scan.points, target, true)
            if not m.ok:
                continue
            e = se2.from_matrix(m.pose) - true
            rows[key + "e"].append(
                [c * e[0] + s * e[1], -s * e[0] + c * e[1], se2.wrap(float(e[2]))]
            )
            rows[key + "c"].append(m.covariance)
        add_true(target_map, scan)
    return {
        "world": summary(
            np.array(rows["we"]).reshape(-1, 3), np.array(rows["wc"]).reshape(-1, 3, 3)
        ),
        "truth_map": summary(
            np.array(rows["te"]).reshape(-1, 3), np.array(rows["tc"]).reshape(-1, 3, 3)
        ),
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    return agent_main("python -m colonyd.bench.match_bias", measure, argv)


if __name__ == "__main__":
    main()
