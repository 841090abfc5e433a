"""The sim CCTV's landmark markers as its daemon publishes them, against the world's truth.

`python -m colonyd.bench.cctv_markers [--world office|hall] [--frames N]`

cctv-1 renders `--frames` images (its image has no noise: every seed is the same), each marker it
solves is folded into `OwnObjects` as its daemon does, and per marker the published mean's error
along and across the camera's ray and the standard deviation its published covariance claims
along the ray are printed (docs/BENCHMARKS.md "depth-1 with the CCTV in the hall"). The truth
only evaluates.
"""

from __future__ import annotations

import argparse

import numpy as np

from colonyd.layers import Layer
from colonyd.objects import OwnObjects
from plugins.sim import SimSource
from plugins.world import hall_world, office_world


def marker_errors(world: str, frames: int) -> list[dict[str, float]]:
    """Per marker cctv-1 saw: its range, the published mean's error along and across the ray
    (m) and the standard deviation its published covariance claims along the ray (m)."""
    truth = {
        m.marker_id: np.array(m.centre)
        for m in (hall_world() if world == "hall" else office_world()).markers
    }
    source = SimSource(
        world=world, agent="cctv-1", seed=103, frames=frames, epoch=0.0, keep_late=True
    )
    objects = OwnObjects(frozenset())
    camera = np.zeros(3)
    for obs in source:
        objects.observe(obs)
        camera = obs.pose[:3, 3]
    rows = []
    for found in objects.refresh(Layer("cctv-1", 0.1)) or []:  # its own layer's map: unused
        centre = truth[found.object_id]
        ray = (centre - camera) / np.linalg.norm(centre - camera)
        error = found.position - centre
        along = float(error @ ray)
        rows.append(
            {
                "marker": found.object_id,
                "range_m": float(np.linalg.norm(centre - camera)),
                "along_m": along,
                "across_m": float(np.linalg.norm(error - along * ray)),
                "claimed_along_m": float(np.sqrt(ray @ found.covariance @ ray)),
            }
        )
    return rows


def main(argv: list[str] | None = None) -> list[dict[str, float]]:
    parser = argparse.ArgumentParser(prog="python -m colonyd.bench.cctv_markers")
    parser.add_argument("--world", choices=("office", "hall"), default="hall")
    parser.add_argument("--frames", type=int, default=60, help="cctv-1's images (1 per second)")
    args = parser.parse_args(argv)
    rows = marker_errors(args.world, args.frames)
    print("marker  range m  along m  across m  claimed along m")
    for r in rows:
        print(
            f"{r['marker']:6d}  {r['range_m']:7.1f}  {r['along_m']:+7.3f}  {r['across_m']:8.3f}"
            f"  {r['claimed_along_m']:15.3f}"
        )
    return rows


if __name__ == "__main__":
    main()
