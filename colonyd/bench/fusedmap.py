"""The fused map's cost as a daemon's export and ROS 2 outputs pay it, on a real grid.

`python -m colonyd.bench.fusedmap --grid DIR/grid.npz [--yaw DEG] [--repeats N] [--json FILE]`:
two layers hold the grid (a `colonyd map` output, e.g. of the 7-Scenes kitchen), as gossip
delivers it: "own" in the colony frame, "peer" turned by `--yaw` degrees about z and moved by
(0.37, -0.21, 0.05) m. One live fused map (the daemon's `fused_map`) gives a reply's outputs
(the view, each voxel's class, the occupied voxels' surface points, as `Daemon.fused_reply`)
three times: cold (a new map), again with nothing changed, and after the own layer grew by
5,000 voxels (a delta of its own voxels, as a scan brings). CPU seconds of this process per
output and round (`time.process_time`: on a shared machine, others' load lengthens the wall
time, not these), the median over `--repeats` (each a new pair of layers).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

from colonyd.layers import FusedMap, Layer
from voxel.grid import VoxelGrid

ROUNDS = ("cold", "again", "own grew")
OUTPUTS = ("view", "classes", "surface")


def _turn(yaw_deg: float) -> np.ndarray:
    t = np.eye(4)
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    t[:2, :2] = [[c, -s], [s, c]]
    t[:3, 3] = [0.37, -0.21, 0.05]
    return t


def reply(
    live: FusedMap, layers: list[Layer], res: float, transforms: dict[str, np.ndarray]
) -> dict[str, float]:
    """CPU seconds of each output of one fused reply."""
    t0 = time.process_time()
    keys, lo = live.view(layers, res, transforms)
    t1 = time.process_time()
    live.classes(layers, res, keys, transforms)
    t2 = time.process_time()
    live.surface(layers, res, keys[lo >= 0], transforms)
    t3 = time.process_time()
    return {"view": t1 - t0, "classes": t2 - t1, "surface": t3 - t2}


def run(grid: VoxelGrid, yaw: float = 30.0, repeats: int = 3) -> dict[str, object]:
    """Median CPU seconds per round and output over `repeats` (see the module's docstring)."""
    res = grid.resolution
    full = grid.delta_since(0)
    transforms = {"own": np.eye(4), "peer": _turn(yaw)}
    times: dict[str, dict[str, list[float]]] = {r: {o: [] for o in OUTPUTS} for r in ROUNDS}
    voxels = 0
    for _ in range(repeats):
        own, peer = Layer("own", res), Layer("peer", res)
        own.offer(1, 0, 1, full)
        peer.offer(1, 0, 1, full)
        live = FusedMap()
        for name in ROUNDS:
            if name == "own grew":
                own.offer(1, 1, 2, full.select(slice(0, 5000)))
            for out, s in reply(live, [own, peer], res, transforms).items():
                times[name][out].append(s)
        voxels = len(live.view([own, peer], res, transforms)[0])
    return {
        "resolution": res,
        "layer_voxels": len(full),
        "fused_voxels": voxels,
        "yaw_deg": yaw,
        "repeats": repeats,
        "cpu_seconds": {
            r: {o: round(float(np.median(v)), 3) for o, v in outs.items()}
            for r, outs in times.items()
        },
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--grid", type=Path, required=True, help="a grid.npz (`colonyd map --out`)")
    p.add_argument("--yaw", type=float, default=30.0, help="the peer layer's turn (degrees)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--json", type=Path)
    args = p.parse_args()
    result = run(VoxelGrid.load(args.grid), args.yaw, args.repeats)
    print(json.dumps(result))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
