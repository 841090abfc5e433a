"""The sim CCTV's ArUco corners against the true projected corners, renderer and detector apart.

`python -m colonyd.bench.marker_corners [--distances M ...] [--yaws RAD ...] [--clutter]`

A 0.3 m landmark marker on a pillar is seen by the sim CCTV's camera (640 x 480, 75 degrees)
from each distance and yaw (0.3 m to its side, 0.2 m above it). Each view is drawn twice: by the
sim's renderer (`plugins.sim.render`) and area-sampled (the same renderer at 8 x 8 samples per
pixel around the marker, averaged: an exact pixel-area image); on each, the corners of OpenCV's
detector (`cornerSubPix`, as `CctvCamera` sets it) and the same refined by `refine_corners` (as
`CctvCamera.detect`) are compared with the true projected corners: their mean displacement into
the square (px, each axis) and the range PnP solves from them (% of the true range)
(docs/BENCHMARKS.md "The CCTV's marker corners"). The truth only evaluates.

With `--clutter`, instead: each distance's sim render (yaw 0) with dark bands `CLUTTER_OUT` px
out of the marker's top and left sides (from the clean image's corners), `CLUTTER_WIDTH` px wide,
clutter the detector ignores; per band, the error of the position `CctvCamera.detect` solves
along the ray against the standard deviation its covariance claims there, and whether its
corners fell back to the detector's (docs/BENCHMARKS.md "Clutter beside a marker").
"""

from __future__ import annotations

import argparse
import math

import cv2
import numpy as np

from plugins.cctv import CORNER_PX, CctvCamera, CctvFrame, marker_corners, refine_corners
from plugins.checks import pose_matrix
from plugins.sim import OPTICAL, Rig, make_rig, render
from plugins.world import CLASSES, Box, Marker, World
from voxel.depth import pixel_rays

LENGTH = 0.3  # the worlds' landmark markers (m)
SAMPLES = 8  # per pixel and axis, for the area-sampled image
#: `--clutter`: where a dark band starts outside a side (px) and how wide it is (px).
CLUTTER_OUT = (1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 4.5, 5.0)
CLUTTER_WIDTH = (1.0, 2.0, 3.0, 5.0)


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
    for name, quad in (("subpix", found), ("edges", refine_corners(grey, found, camera.cells)[0])):
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


def with_bands(image: np.ndarray, quad: np.ndarray, out: float, width: float) -> np.ndarray:
    """`image` with a black band `out` to `out + width` px outside the sides of `quad` (4, 2)
    from corner 0 to 1 and from corner 3 to 0."""
    image = image.copy()
    for i in (0, 3):
        a, b = quad[i], quad[(i + 1) % 4]
        inward = quad.mean(axis=0) - (a + b) / 2
        inward /= np.linalg.norm(inward)
        far = out + width
        band = np.array([a - out * inward, b - out * inward, b - far * inward, a - far * inward])
        cv2.fillPoly(image, [np.round(band).astype(np.int32)], (0, 0, 0))
    return image


def clutter(distances: list[float]) -> list[dict[str, float]]:
    """Per distance (yaw 0) and band (`CLUTTER_OUT`, `CLUTTER_WIDTH`) whose marker is still
    detected: the solved position's error along the ray (m), the sd its covariance claims there
    (m), and whether its corners are the detector's (fallen back: 1)."""
    world = pillar()
    rig, _ = make_rig("cctv")
    assert rig.K is not None
    rows = []
    for distance in distances:
        pose = pose_matrix(2.0 - distance, 0.3, 1.2, 0.0) @ OPTICAL
        camera = CctvCamera(pose=pose, K=rig.K, marker_length=LENGTH)
        truth = (np.linalg.inv(pose) @ world.markers[0].frame())[:3, 3]
        ray = truth / np.linalg.norm(truth)
        image = colour(world, rig, pose)
        clean = camera.detect(image)
        if not clean or clean[0].corners is None:
            continue
        for out in CLUTTER_OUT:
            for width in CLUTTER_WIDTH:
                banded = with_bands(image, clean[0].corners, out, width)
                found = camera.detect(banded)
                if not found or found[0].covariance is None:
                    continue
                grey = cv2.cvtColor(banded, cv2.COLOR_BGR2GRAY)
                detected = camera.detector.detectMarkers(grey)[0][0].reshape(4, 2)
                claim = refine_corners(grey, detected, camera.cells)[1]
                error = float((found[0].position - truth) @ ray)
                sd = float(np.sqrt(ray @ found[0].covariance @ ray))
                rows.append(
                    {
                        "distance_m": distance,
                        "out_px": out,
                        "width_px": width,
                        "along_m": error,
                        "claimed_m": sd,
                        "sigmas": abs(error) / sd,
                        "fallback": float(claim != CORNER_PX),
                    }
                )
    return rows


def main_clutter(distances: list[float]) -> list[dict[str, float]]:
    """`clutter`'s rows printed, with the worst error in claimed sds and the mean NEES."""
    rows = clutter(distances)
    print("dist m  out px  width px  along m  claimed m  sigmas  fallback")
    for r in rows:
        print(
            f"{r['distance_m']:6.1f}  {r['out_px']:6.1f}  {r['width_px']:8.1f}  "
            f"{r['along_m']:+7.3f}  {r['claimed_m']:9.3f}  {r['sigmas']:6.1f}  "
            f"{int(r['fallback']):8d}"
        )
    if rows:
        s = np.array([r["sigmas"] for r in rows])
        e = np.array([r["along_m"] for r in rows])
        print(
            f"{len(rows)} detected: along RMS {np.sqrt(np.mean(e**2)):.3f} m, worst "
            f"{np.abs(e).max():.3f} m, worst {s.max():.1f} sd, mean NEES {np.mean(s**2):.2f}, "
            f"fallen back {int(sum(r['fallback'] for r in rows))}"
        )
    return rows


def main(argv: list[str] | None = None) -> list[dict[str, float]]:
    parser = argparse.ArgumentParser(prog="python -m colonyd.bench.marker_corners")
    parser.add_argument("--distances", type=float, nargs="+", default=[3.0, 5.0, 7.0, 10.0, 15.0])
    parser.add_argument("--yaws", type=float, nargs="+", default=[-0.3, 0.0, 0.3])
    parser.add_argument(
        "--clutter", action="store_true", help="dark bands beside the marker (yaw 0) instead"
    )
    args = parser.parse_args(argv)
    if args.clutter:
        return main_clutter(args.distances)
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
