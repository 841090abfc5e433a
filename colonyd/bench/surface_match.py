"""Scan matching against a peer's 10 cm map as voxel centres and as surface points (sim office).

`python -m colonyd.bench.surface_match [--seed S] [--poses N] [--range R] [--yaw DEG]
[--shift M] [--sparse-surface] [--json FILE]`: a peer's planar grid is built from 2D scans of
the sim office at known poses (range noise 1 cm); then 2D scans at other poses are matched
(`scan_match.match`, dof 3) against its colony-map cut made from the occupied voxels' centres
and from their surface points (`occupied_surface`), from the true pose moved by `--offset` in x
and -y (default 5 cm) and 20 x that in radians (1.15 degrees). The office's walls lie on voxel
faces; `--yaw` and `--shift` turn the peer's map frame by DEG about z and move it by (M, 0.7 M),
so that they do not. Truth is for this evaluation only.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from plugins.world import World, office_world
from voxel import keys as vk
from voxel.grid import VoxelGrid
from voxel.localisation.colony_map import colony_map
from voxel.localisation.scan_match import match
from voxel.sensor import SensorModel

HEIGHT = 0.3


def _pose(x: float, y: float, yaw: float) -> np.ndarray:
    t = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    t[:2, :2] = [[c, -s], [s, c]]
    t[:3, 3] = [x, y, HEIGHT]
    return t


def _scan(world: World, pose: np.ndarray, rng: np.random.Generator, reach: float) -> np.ndarray:
    """Body-frame points of a 360-beam scan at `pose`, range noise 1 cm, within `reach`."""
    a = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    body = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)
    hits = world.cast(pose[:3, 3], body @ pose[:3, :3].T)
    r = hits.t + rng.normal(0.0, 0.01, len(a))
    keep = np.isfinite(r) & (r < reach) & (r > 0.1)
    out: np.ndarray = body[keep] * r[keep, None]
    return out


def _free_poses(world: World, rng: np.random.Generator, n: int) -> list[np.ndarray]:
    """Poses in the office at least 0.4 m from anything (free floor)."""
    out: list[np.ndarray] = []
    while len(out) < n:
        x, y = rng.uniform(-5.5, 5.5), rng.uniform(-3.5, 3.5)
        pose = _pose(x, y, rng.uniform(-math.pi, math.pi))
        a = np.linspace(-math.pi, math.pi, 36, endpoint=False)
        d = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)
        t = world.cast(pose[:3, 3], d).t
        if np.min(t) > 0.4:
            out.append(pose)
    return out


def run(
    seed: int = 1,
    poses: int = 40,
    reach: float = 4.0,
    offset: float = 0.05,
    yaw: float = 0.0,
    shift: float = 0.0,
    sparse: bool = False,
) -> dict[str, object]:
    """Match errors of `poses` scans; the peer's map frame is the world turned by `yaw` degrees
    about z and moved by (`shift`, 0.7 `shift`, 0) m. `sparse`: the peer publishes its codes as
    with sparse surface codes (a code moves only at a voxel's first hit and a step away)."""
    rng = np.random.default_rng(seed)
    world = office_world()
    frame = _pose(shift, 0.7 * shift, math.radians(yaw))  # world -> the peer's map frame
    frame[2, 3] = 0.0
    rot, move = frame[:3, :3], frame[:3, 3]
    grid = VoxelGrid(0.1, block_shape="planar", surface=True)
    grid.sparse_surface = sparse
    for i, pose in enumerate(_free_poses(world, rng, 150)):  # the peer's mapping run
        pts = _scan(world, pose, rng, 8.0)
        grid.integrate(
            (pts @ pose[:3, :3].T + pose[:3, 3]) @ rot.T + move,
            rot @ pose[:3, 3] + move,
            time=float(i),
            sensor=SensorModel(max_range=8.0),
        )
    keys = grid.occupied_keys()
    targets = {  # back in the world frame, where the scans are matched
        "centres": (vk.keys_to_centers(keys, grid.resolution) - move) @ rot,
        "surface": (grid.surface_points(keys) - move) @ rot,
    }
    errors: dict[str, list[float]] = {name: [] for name in targets}
    for pose in _free_poses(world, rng, poses):
        pts = _scan(world, pose, rng, reach)
        init = pose @ _pose(offset, -offset, math.radians(20 * offset))
        init[2, 3] = HEIGHT
        for name, points in targets.items():
            cut = colony_map(
                points, planar=True, height=HEIGHT, centre=pose[:2, 3], radius=reach + 2.0
            )
            got = match(pts, cut, init, dof=3)
            err = float(np.linalg.norm(got.pose[:2, 3] - pose[:2, 3])) if got.ok else math.nan
            errors[name].append(err)
    out: dict[str, object] = {
        "seed": seed,
        "poses": poses,
        "range_m": reach,
        "offset_m": offset,
        "yaw_deg": yaw,
        "shift_m": shift,
        "sparse_surface": sparse,
    }
    for name, e in errors.items():
        arr = np.asarray(e)
        ok = arr[np.isfinite(arr)]
        out[f"{name}_median_m"] = round(float(np.median(ok)), 4) if ok.size else None
        out[f"{name}_p90_m"] = round(float(np.percentile(ok, 90)), 4) if ok.size else None
        out[f"{name}_failed"] = int(np.count_nonzero(~np.isfinite(arr)))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--poses", type=int, default=40)
    p.add_argument("--range", type=float, default=4.0, dest="reach")
    p.add_argument("--offset", type=float, default=0.05, help="start x, -y off (m); yaw 20x rad")
    p.add_argument("--yaw", type=float, default=0.0, help="peer's map frame turned (degrees)")
    p.add_argument("--shift", type=float, default=0.0, help="and moved by (M, 0.7 M) metres")
    p.add_argument(
        "--sparse-surface",
        action="store_true",
        help="the peer's codes as with sparse surface codes in deltas (voxel.surface.SPARSE)",
    )
    p.add_argument("--json", type=Path)
    args = p.parse_args()
    result = run(
        args.seed, args.poses, args.reach, args.offset, args.yaw, args.shift, args.sparse_surface
    )
    print(json.dumps(result))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
