"""The sim CCTV's ArUco corners against the true projected corners, renderer and detector apart.

`python -m colonyd.bench.marker_corners [--distances M ...] [--yaws RAD ...]`

A 0.3 m landmark marker on a pillar is seen by the sim CCTV's camera (640 x 480, 75 degrees)
from each distance and yaw (0.3 m to its side, 0.2 m above it). Each view is drawn twice: by the
sim's renderer (`plugins.sim.render`) and area-sampled (the same renderer at 8 x 8 samples per
pixel around the marker, averaged: an exact pixel-area image); on each, the corners of OpenCV's
detector (`cornerSubPix`, as `CctvCamera` sets it) and the same refined by `refine_corners` (as
`CctvCamera.detect`) are compared with the true projected corners: their mean displacement into
the square (px, each axis) and the range PnP solves from them (% of the true range)
(docs/BENCHMARKS.md "The CCTV's marker corners"). The truth only evaluates.
"""

from __future__ import annotations

import argparse
import math

import cv2
import numpy as np

from plugins.cctv import CctvCamera, CctvFrame, marker_corners, refine_corners
from plugins.checks import pose_matrix
from plugins.sim import OPTICAL, Rig, make_rig, render
from plugins.world import CLASSES, Box, Marker, World
from voxel.depth import pixel_rays

LENGTH = 0.3  # the worlds' landmark markers (m)
SAMPLES = 8  # per pixel and axis, for the area-sampled image


def pillar() -> World:
    """A pillar whose -x face is the plane x = 2, a 0.3 m marker centred at (2, 0, 1) on it."""
    box = Box((2.0, -0.5, 0.0), (2.4, 0.5, 2.0), CLASSES["landmark"], 42)
    return World("pillar", boxes=[box], markers=[Marker(7, (2.0, 0.0, 1.0), (-1, 0, 0), LENGTH)])


def colour(world: World, rig: Rig, pose: np.ndarray) -> np.ndarray:
    """The sim camera `rig`'s colour image (BGR) of `world` from `pose`."""
    frame = render(world, "cctv", rig, pose, np.random.default_rng(0), 0.0)
    assert isinstance(frame, CctvFrame)  # a camera rig renders a CCTV frame
    return frame.image


def area_sampled(world: World, rig: Rig, pose: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """The rig's image with the box around the corners `uv` (+ 20 px) drawn at SAMPLES x SAMPLES
    rays per pixel and averaged (pixel i spans i +- 0.5: the fine pixel j is at (j + 0.5) / s -
    0.5)."""
    assert rig.K is not None
    out = colour(world, rig, pose)
    h, w = rig.shape
    lo = np.maximum(np.floor(uv.min(axis=0)).astype(int) - 20, 0)
    hi = np.minimum(np.ceil(uv.max(axis=0)).astype(int) + 20, [w, h])
    s = SAMPLES
    K = rig.K.copy()
    K[:2, :2] *= s
    K[:2, 2] = s * (rig.K[:2, 2] - lo + 0.5) - 0.5
    size = hi - lo
    fine = Rig(pixel_rays(K, size[0] * s, size[1] * s), OPTICAL, (size[1] * s, size[0] * s), K)
    big = colour(world, fine, pose)
    small = cv2.resize(big, (int(size[0]), int(size[1])), interpolation=cv2.INTER_AREA)
    out[lo[1] : hi[1], lo[0] : hi[0]] = small
    return out


def corner_errors(
    camera: CctvCamera, image: np.ndarray, uv: np.ndarray, truth_range: float
) -> dict[str, tuple[float, float]]:
    """Per corner method (subpix, edges): the mean displacement of the detected corners into the
    square (px, each axis) and the PnP range's error (% of `truth_range`); empty if not found."""
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    corners, ids, _ = camera.detector.detectMarkers(grey)
    if ids is None:
        return {}
    found = corners[0].reshape(4, 2).astype(np.float64)
    out = {}
    centre = uv.mean(axis=0)
    outward = (uv - centre) / np.linalg.norm(uv - centre, axis=1)[:, None]
    for name, quad in (("subpix", found), ("edges", refine_corners(grey, found, camera.cells))):
        inward = -float(np.einsum("ij,ij->i", quad - uv, outward).mean()) / math.sqrt(2.0)
        _, _, tvec = cv2.solvePnP(
            marker_corners(LENGTH), quad, camera.K, None, flags=cv2.SOLVEPNP_IPPE
        )
        out[name] = (inward, 100.0 * (float(np.linalg.norm(tvec)) / truth_range - 1.0))
    return out


def views(distances: list[float], yaws: list[float]) -> list[dict[str, float]]:
    """Per distance and yaw, per image (sim, area) and corner method: the mean inward corner
    displacement (px) and the range error (%), with the marker's mean side (px)."""
    world = pillar()
    rig, _ = make_rig("cctv")
    assert rig.K is not None
    rows = []
    for distance in distances:
        for yaw in yaws:
            pose = pose_matrix(2.0 - distance, 0.3, 1.2, yaw) @ OPTICAL
            camera = CctvCamera(pose=pose, K=rig.K, marker_length=LENGTH)
            truth = np.linalg.inv(pose) @ world.markers[0].frame()
            cam = marker_corners(LENGTH) @ truth[:3, :3].T + truth[:3, 3]
            uv = cam[:, :2] / cam[:, 2:] * np.diag(rig.K)[:2] + rig.K[:2, 2]
            row = {
                "distance_m": distance,
                "yaw": yaw,
                "side_px": float(np.linalg.norm(np.roll(uv, 1, axis=0) - uv, axis=1).mean()),
            }
            sim = colour(world, rig, pose)
            r = float(np.linalg.norm(truth[:3, 3]))
            for image, name in ((sim, "sim"), (area_sampled(world, rig, pose, uv), "area")):
                for method, (inward, error) in corner_errors(camera, image, uv, r).items():
                    row[f"{name}_{method}_inward_px"] = inward
                    row[f"{name}_{method}_range_pct"] = error
            rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> list[dict[str, float]]:
    parser = argparse.ArgumentParser(prog="python -m colonyd.bench.marker_corners")
    parser.add_argument("--distances", type=float, nargs="+", default=[3.0, 5.0, 7.0, 10.0, 15.0])
    parser.add_argument("--yaws", type=float, nargs="+", default=[-0.3, 0.0, 0.3])
    args = parser.parse_args(argv)
    rows = views(args.distances, args.yaws)
    keys = [f"{i}_{m}" for i in ("sim", "area") for m in ("subpix", "edges")]
    print("dist m   yaw  side px  " + "  ".join(f"{k:>20s}" for k in keys))
    print(" " * 24 + "  ".join(f"{'inward px, range %':>20s}" for _ in keys))
    for row in rows:
        cells = [
            f"{row[k + '_inward_px']:+8.2f} {row[k + '_range_pct']:+10.2f}"
            if k + "_inward_px" in row
            else f"{'not found':>20s}"
            for k in keys
        ]
        print(
            f"{row['distance_m']:6.1f} {row['yaw']:+5.2f} {row['side_px']:8.1f}  "
            + "  ".join(f"{c:>20s}" for c in cells)
        )
    for k in keys:
        found = [row[k + "_range_pct"] for row in rows if k + "_range_pct" in row]
        inward = [row[k + "_inward_px"] for row in rows if k + "_inward_px" in row]
        if found:
            print(
                f"{k}: {len(found)} of {len(rows)} found, inward px mean {np.mean(inward):+.3f}, "
                f"range % mean {np.mean(found):+.2f}, |range %| max {np.max(np.abs(found)):.2f}"
            )
    return rows


if __name__ == "__main__":
    main()
