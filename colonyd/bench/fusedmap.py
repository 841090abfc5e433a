"""The fused map's cost as a daemon's export and ROS 2 outputs pay it, on a real grid.

`python -m colonyd.bench.fusedmap --grid DIR/grid.npz [--yaw DEG] [--labelled F] [--repeats N]
[--json FILE]`: two layers hold the grid (a `colonyd map` output, e.g. of the 7-Scenes kitchen),
as gossip delivers it: "own" in the colony frame, "peer" turned by `--yaw` degrees about z and
moved by (0.37, -0.21, 0.05) m; with `--labelled`, that fraction of the voxels holds three
random classes (seeded), as a segmenting camera's map would. One live fused map (the daemon's
`fused_map`) gives its outputs three times: cold (a new map), again with nothing changed, and
after the own layer grew by 5,000 voxels (a delta of its own voxels, as a scan brings); once as
the ROS 2 loop asks (the view and the occupied voxels' surface points) and once, on new layers
and a new map, as an export reply does (with each voxel's class: `Daemon.fused_reply`). CPU
seconds of this process per output and round (`time.process_time`: on a shared machine,
others' load lengthens the wall time, not these), the median over `--repeats`.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from colonyd.layers import FusedMap, Layer
from voxel.delta import Delta
from voxel.grid import VoxelGrid

ROUNDS = ("cold", "again", "own grew")
OUTPUTS = ("ros", "reply")


def _turn(yaw_deg: float) -> np.ndarray:
    t = np.eye(4)
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    t[:2, :2] = [[c, -s], [s, c]]
    t[:3, 3] = [0.37, -0.21, 0.05]
    return t


def labelled(full: Delta, fraction: float, seed: int = 0, k: int = 3) -> Delta:
    """`full` with `fraction` of its voxels holding `k` random classes (0..19; a grid keeps
    three) and their probabilities, the others none (-1)."""
    if fraction <= 0:
        return full
    rng = np.random.default_rng(seed)
    n = len(full)
    ids = rng.integers(0, 20, (n, k)).astype(np.int16)
    ids[rng.random(n) >= fraction] = -1
    probs = np.where(ids >= 0, rng.random((n, k)), 0.0).astype(np.float32)
    channels = {**full.channels, "class_ids": ids, "class_probs": probs}
    return replace(full, channels=channels)


def outputs(
    live: FusedMap, layers: list[Layer], res: float, transforms: dict[str, np.ndarray], ask: str
) -> float:
    """CPU seconds of one round's outputs: the ROS 2 loop's ("ros") or a reply's ("reply")."""
    t0 = time.process_time()
    live.outputs(layers, res, transforms, classes=ask == "reply")
    return time.process_time() - t0


def run(
    grid: VoxelGrid, yaw: float = 30.0, repeats: int = 3, fraction: float = 0.0
) -> dict[str, object]:
    """Median CPU seconds per round and output over `repeats` (see the module's docstring)."""
    res = grid.resolution
    full = labelled(grid.delta_since(0), fraction)
    transforms = {"own": np.eye(4), "peer": _turn(yaw)}
    times: dict[str, dict[str, list[float]]] = {r: {o: [] for o in OUTPUTS} for r in ROUNDS}
    voxels = 0
    for _ in range(repeats):
        for ask in OUTPUTS:
            own, peer = Layer("own", res), Layer("peer", res)
            own.offer(1, 0, 1, full)
            peer.offer(1, 0, 1, full)
            live = FusedMap()
            for name in ROUNDS:
                if name == "own grew":
                    own.offer(1, 1, 2, full.select(slice(0, 5000)))
                times[name][ask].append(outputs(live, [own, peer], res, transforms, ask))
            voxels = len(live.view([own, peer], res, transforms)[0])
    return {
        "resolution": res,
        "layer_voxels": len(full),
        "labelled": fraction,
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
    p.add_argument("--labelled", type=float, default=0.0, help="fraction of voxels with classes")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--json", type=Path)
    args = p.parse_args()
    result = run(VoxelGrid.load(args.grid), args.yaw, args.repeats, args.labelled)
    print(json.dumps(result))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
