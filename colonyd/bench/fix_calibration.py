"""The sim CCTV's fixes and published markers: their errors against the covariances they claim.

`python -m colonyd.bench.fix_calibration [--worlds office,hall] [--samples N] [--seed S]
[--experiment S] [--json FILE]`

cctv-1 (its image has no noise) renders `--samples` images per world (`SAMPLES`), each with one
robot's boards where a robot of the world could be (a uniform point of lidar-1's or depth-1's path,
up to 0.2 m off it, any heading: `sample_bodies`), and solves them as its daemon does
(`CctvCamera.detect`); every board it would send (confidence >= `MIN_FIX_CONFIDENCE`) is a fix. Per
fix, its error against the true body pose along and across the horizontal ray from the camera, in
yaw, and the standard deviations `fix_covariance` claims (`--model`, default its fitted one); per
board, its range solved by PnP (before the board's known height moves it: what a landmark marker's
range is) against the truth, in pixels of its side (`marker_covariance`'s model). With
`--experiment S`, also the paper experiment's own fixes over S seconds (`cctv_offline.cctv_view`:
the robots' scripted paths, one image a second). The landmark markers are solved from one image
(the camera and they are fixed, the image has no noise: every frame repeats it). Tables per range
bin: mean (a bias the bin's fixes share) and RMS error, RMS over claimed sd, mean NEES; the same
per band of the board's incidence (`ANGLE_BINS`, `CctvCamera.board_incidence`), and the "angle"
model's growth fitted (`fit_angle`). The truth only evaluates.
"""

from __future__ import annotations

import argparse
import itertools
import math
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np
from scipy import optimize

from colonyd.bench.files import print_and_append
from colonyd.bench.options import names
from colonyd.fixes import (
    FIX_ACROSS_M,
    FIX_ALONG_M,
    FIX_MODELS,
    FIX_YAW_RAD,
    MAX_INCIDENCE,
    fix_covariance,
    fix_sd,
)
from plugins.cctv import CORNER_PX, CctvCamera, marker_corners
from plugins.checks import pose_matrix
from plugins.observation import AGENT_LABEL
from plugins.sim import AGENTS, BOARD_LENGTH, SimSource, boards_at, robot_markers
from plugins.world import Hits
from voxel.localisation import frame_error, se2

CCTV = "cctv-1"
ROBOTS = ("lidar-1", "depth-1")
#: The daemon's `MIN_FIX_CONFIDENCE` (colonyd.daemon; not imported: it pulls in Zenoh).
MIN_FIX_CONFIDENCE = 0.15
#: Range bins (m, camera to the robot's body at the floor) of the tables.
BINS = (3.0, 4.5, 6.0, 7.5, 9.0, 10.5, 12.0, 14.0, 18.0)
#: Images per world (the hall's camera sees a board in fewer of them): the samples
#: `colonyd.fixes`' model was fitted to.
SAMPLES = {"office": 300, "hall": 400}
#: Bins of a marker's apparent side (px) for its PnP range's error.
SIDE_BINS = (8.0, 12.0, 15.0, 18.0, 22.0, 26.0, 40.0)
#: Bins of a board's incidence (degrees: its solved normal against the camera's ray).
ANGLE_BINS = (0.0, 30.0, 45.0, 60.0, 70.0, 90.0)
#: How far (m) a sampled body may be off its robot's path, either side.
OFF_PATH_M = 0.2


def camera(world: str) -> tuple[SimSource, CctvCamera, Hits]:
    """cctv-1 of `world` told both robots' boards, its camera and its static scene's hits."""
    source = SimSource(
        world=world,
        agent=CCTV,
        seed=0,
        frames=1,
        epoch=0.0,
        keep_late=True,
        robots="+".join(ROBOTS),
    )
    cam = cast(CctvCamera, source.adapter)
    rays = source.rig.directions @ cam.pose[:3, :3].T
    return source, cam, source.world.cast(cam.pose[:3, 3], rays)


def _size(source: SimSource) -> tuple[int, int]:
    """The camera image's (height, width)."""
    h, w = source.rig.shape[:2]
    return int(h), int(w)


def sample_bodies(world: str, n: int, rng: np.random.Generator) -> list[tuple[str, np.ndarray]]:
    """`n` robot body poses (x, y, yaw) where the world's robots drive: a uniform point of a
    robot's closed waypoint path (lidar-1's and depth-1's in turn), up to `OFF_PATH_M` across it,
    any heading."""
    out = []
    for i in range(n):
        robot = ROBOTS[i % len(ROBOTS)]
        pts = np.asarray(AGENTS[world][robot].waypoints, np.float64)
        ends = np.roll(pts, -1, axis=0)
        lengths = np.linalg.norm(ends - pts, axis=1)
        k = int(rng.choice(len(pts), p=lengths / lengths.sum()))
        d = (ends[k] - pts[k]) / lengths[k]
        xy = pts[k] + rng.uniform(0, lengths[k]) * d
        xy = xy + rng.uniform(-OFF_PATH_M, OFF_PATH_M) * np.array([-d[1], d[0]])
        out.append((robot, np.array([xy[0], xy[1], rng.uniform(-math.pi, math.pi)])))
    return out


def _pnp_range(cam: CctvCamera, quad: np.ndarray, length: float) -> float:
    """The range of a square marker of side `length` solved by PnP from its image corners, as
    `CctvCamera.detect` solves it (before a board's known height moves it)."""
    model = marker_corners(length)
    ok, _, tvec = cv2.solvePnP(model, quad, cam.K, cam.distortion, flags=cv2.SOLVEPNP_IPPE_SQUARE)
    if not (ok and np.isfinite(tvec).all()):
        ok, _, tvec = cv2.solvePnP(model, quad, cam.K, cam.distortion, flags=cv2.SOLVEPNP_IPPE)
    return float(np.linalg.norm(tvec)) if ok and np.isfinite(tvec).all() else math.nan


def fix_row(
    cam: CctvCamera, body: np.ndarray, covariance: np.ndarray, truth: np.ndarray, range_m: float
) -> dict[str, Any]:
    """A fix's error (its body pose `body`, 4x4, camera's site frame, claiming `covariance`)
    against the true body pose `truth` (x, y, yaw): along and across the horizontal ray from the
    camera to the fix, in yaw, and the standard deviations claimed along those."""
    got = se2.from_matrix(body)
    e = got - truth
    e[2] = se2.wrap(float(e[2]))
    ray = got[:2] - cam.pose[:2, 3]
    norm = float(np.linalg.norm(ray))
    ray = ray / norm if norm > 1e-9 else np.array([1.0, 0.0])  # right below: any direction
    across = np.array([-ray[1], ray[0]])
    cov = frame_error.planar(covariance)
    return {
        "range_m": range_m,
        "along_m": float(e[:2] @ ray),
        "across_m": float(e[:2] @ across),
        "yaw_rad": float(e[2]),
        "sd_along_m": math.sqrt(float(ray @ cov[:2, :2] @ ray)),
        "sd_across_m": math.sqrt(float(across @ cov[:2, :2] @ across)),
        "sd_yaw_rad": math.sqrt(float(cov[2, 2])),
        "nees_xy": float(e[:2] @ np.linalg.solve(cov[:2, :2], e[:2])),
        "nees": float(e @ np.linalg.solve(cov, e)),
    }


def board_rows(world: str, samples: int, seed: int, model: str = "fitted") -> list[dict[str, Any]]:
    """Per board cctv-1 would send as a fix, over `samples` images of one sampled robot each:
    `fix_row` (the claim by `fix_covariance`'s `model`), the image index, the board's mean side
    (px), and its PnP range's error against the truth in pixels of that side (range error /
    range x side: `marker_covariance`'s CORNER_PX is its claimed standard deviation)."""
    source, cam, scene = camera(world)
    rays = source.rig.directions @ cam.pose[:3, :3].T
    to_cam = np.linalg.inv(cam.pose)
    rng = np.random.default_rng(seed)
    rows: list[dict[str, Any]] = []
    for i, (robot, truth) in enumerate(sample_bodies(world, samples, rng)):
        spec = AGENTS[world][robot]
        body = pose_matrix(truth[0], truth[1], 0.0, truth[2])
        image = source.world.render_colour(
            cam.K, cam.pose, _size(source), rays, scene, boards_at(spec, body)
        )
        mounts = robot_markers(spec)
        for det in cam.detect(image):
            if not det.label.startswith(AGENT_LABEL) or det.probability < MIN_FIX_CONFIDENCE:
                continue
            assert det.corners is not None
            range_m = float(np.linalg.norm(det.pose[:3, 3]))
            seen = cam.pose @ det.pose
            ray = seen[:2, 3] - cam.pose[:2, 3]  # as the daemon's `_send_fixes`
            incidence = cam.board_incidence(det)
            cov = fix_covariance(range_m, ray=ray, model=model, incidence=incidence)
            row = fix_row(cam, seen, cov, truth, range_m)
            row["incidence_deg"] = math.degrees(incidence)
            board = to_cam @ body @ mounts[det.object_id]
            true_range = float(np.linalg.norm(board[:3, 3]))
            side = float(
                np.linalg.norm(np.roll(det.corners, 1, axis=0) - det.corners, axis=1).mean()
            )
            solved = _pnp_range(cam, det.corners, BOARD_LENGTH)
            row.update(
                image=i,
                robot=robot,
                marker=det.object_id,
                side_px=side,
                range_px=(solved - true_range) / true_range * side,
            )
            rows.append(row)
    return rows


def experiment_rows(world: str, duration: float, model: str = "fitted") -> list[dict[str, Any]]:
    """`fix_row` of each fix of the paper experiment's first `duration` s (its scripted paths,
    `cctv_offline.cctv_view`), with its stamp, robot and board."""
    from colonyd.bench.cctv_offline import cctv_view  # its renders of the experiment

    _, cam, _ = camera(world)
    fixes, _, _ = cctv_view(1, duration, world, model=model)
    rows: list[dict[str, Any]] = []
    for f in fixes:
        row = fix_row(cam, f.body, f.covariance, f.truth, f.range_m)
        row.update(image=f.stamp, robot=f.target, marker=f.marker)
        row["incidence_deg"] = math.degrees(f.incidence)
        rows.append(row)
    return rows


def marker_rows(world: str) -> list[dict[str, float]]:
    """Per landmark marker cctv-1 solves in its (every frame identical) image: its range, side
    (px), the solved centre's error along and across the ray and the sd `marker_covariance`
    claims along it, and the range's error in pixels of the side."""
    source, cam, scene = camera(world)
    rays = source.rig.directions @ cam.pose[:3, :3].T
    image = source.world.render_colour(cam.K, cam.pose, _size(source), rays, scene)
    truth = {m.marker_id: np.asarray(m.centre, np.float64) for m in source.world.markers}
    rows = []
    for det in cam.detect(image):
        if det.label.startswith(AGENT_LABEL) or det.object_id not in truth:
            continue
        assert det.corners is not None and det.covariance is not None
        centre = cam.pose[:3, :3] @ det.pose[:3, 3] + cam.pose[:3, 3]
        ray = truth[det.object_id] - cam.pose[:3, 3]
        r = float(np.linalg.norm(ray))
        ray /= r
        e = centre - truth[det.object_id]
        side = float(np.linalg.norm(np.roll(det.corners, 1, axis=0) - det.corners, axis=1).mean())
        cov = cam.pose[:3, :3] @ det.covariance @ cam.pose[:3, :3].T
        rows.append(
            {
                "marker": det.object_id,
                "range_m": r,
                "side_px": side,
                "along_m": float(e @ ray),
                "across_m": float(np.linalg.norm(e - (e @ ray) * ray)),
                "sd_along_m": math.sqrt(float(ray @ cov @ ray)),
                "range_px": float(e @ ray) / r * side,
            }
        )
    return rows


def by_range(
    rows: list[dict[str, Any]], bins: tuple[float, ...] = BINS, key: str = "range_m"
) -> list[dict[str, Any]]:
    """Per range bin of fixes (or bin of another of the rows' `key`, e.g. "incidence_deg"):
    count, images, mean (shared) and RMS error along, across and in yaw, RMS over the claimed
    sd (1 when honest) and the mean and median NEES (2 in x-y, 3 in all)."""
    out = []
    r = np.array([row[key] for row in rows])
    for lo, hi in itertools.pairwise(bins):
        sel = [row for row, x in zip(rows, r, strict=True) if lo <= x < hi]
        if not sel:
            continue
        s: dict[str, Any] = {key: f"{lo:g}-{hi:g}", "n": len(sel)}
        s["images"] = len({(row["image"], row.get("robot")) for row in sel})
        for axis, unit in (("along", "m"), ("across", "m"), ("yaw", "rad")):
            e = np.array([row[f"{axis}_{unit}"] for row in sel])
            sd = np.array([row[f"sd_{axis}_{unit}"] for row in sel])
            scale = math.degrees(1.0) if unit == "rad" else 100.0  # degrees, cm
            s[f"{axis}_mean"] = round(float(e.mean()) * scale, 2)
            s[f"{axis}_rms"] = round(float(np.sqrt(np.mean(e**2))) * scale, 2)
            s[f"{axis}_claimed"] = round(float(np.sqrt(np.mean(sd**2))) * scale, 2)
            s[f"{axis}_ratio"] = round(float(np.sqrt(np.mean((e / sd) ** 2))), 2)
        s["nees_xy"] = round(float(np.mean([row["nees_xy"] for row in sel])), 2)
        s["nees"] = round(float(np.mean([row["nees"] for row in sel])), 2)
        s["nees_median"] = round(float(np.median([row["nees"] for row in sel])), 2)
        out.append(s)
    return out


def fit_angle(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Per axis (along, across, yaw), the k of a standard deviation `fix_sd`(range) x (1 + k
    tan^2(incidence)) (the fitted model over range kept, the incidence capped at
    `MAX_INCIDENCE`) that makes the fixes' errors likeliest as zero-mean Gaussian (k >= 0):
    `colonyd.fixes.FIX_ANGLE_K`'s fit."""
    r = np.array([row["range_m"] for row in rows])
    grow = np.tan(np.minimum(np.radians([row["incidence_deg"] for row in rows]), MAX_INCIDENCE))
    grow = grow**2
    out = {}
    for axis, model in (
        ("along_m", FIX_ALONG_M),
        ("across_m", FIX_ACROSS_M),
        ("yaw_rad", FIX_YAW_RAD),
    ):
        e2 = np.array([row[axis] for row in rows]) ** 2
        base = np.array([fix_sd(model, x) for x in r])

        def nll(k: float, e2: np.ndarray = e2, base: np.ndarray = base) -> float:
            sd = base * (1.0 + k * grow)
            return float(np.sum(np.log(sd) + e2 / (2.0 * sd**2)))

        best = optimize.minimize_scalar(nll, bounds=(0.0, 10.0), method="bounded")
        out[axis] = round(float(best.x), 4)
    return out


def fit_sd(ranges: np.ndarray, errors: np.ndarray, power: int) -> tuple[float, float, float]:
    """The (floor, per) of a standard deviation floor + per x range**power that makes `errors`
    at `ranges` likeliest as zero-mean Gaussian, and that negative log-likelihood."""
    r = np.asarray(ranges, np.float64) ** power
    e2 = np.asarray(errors, np.float64) ** 2

    def nll(q: np.ndarray) -> float:
        sd = np.exp(q[0]) + np.exp(q[1]) * r
        return float(np.sum(np.log(sd) + e2 / (2.0 * sd**2)))

    rms = math.sqrt(float(e2.mean()))
    start = np.log([rms / 3.0, rms / float(r.mean())])
    best = optimize.minimize(
        nll, start, method="Nelder-Mead", options={"xatol": 1e-7, "fatol": 1e-9, "maxiter": 8000}
    )
    return float(np.exp(best.x[0])), float(np.exp(best.x[1])), float(best.fun)


def fits(rows: list[dict[str, Any]], powers: tuple[int, ...] = (1, 2, 3, 4)) -> dict[str, Any]:
    """`fit_sd` of the fixes' errors along, across and in yaw at each of `powers`."""
    r = np.array([row["range_m"] for row in rows])
    out: dict[str, Any] = {}
    for axis in ("along_m", "across_m", "yaw_rad"):
        e = np.array([row[axis] for row in rows])
        out[axis] = [
            {"power": p, "floor": f"{a:.3g}", "per": f"{b:.3g}", "nll": round(n, 1)}
            for p in powers
            for a, b, n in [fit_sd(r, e, p)]
        ]
    return out


def sides(rows: list[dict[str, Any]], edges: tuple[float, ...] = SIDE_BINS) -> list[dict[str, Any]]:
    """Per bin of apparent side (px): count, mean and RMS of the PnP range's error in pixels of
    the side, and the mean of its square over `CORNER_PX`'s (1 when honest)."""
    side = np.array([row["side_px"] for row in rows])
    px = np.array([row["range_px"] for row in rows])
    out = []
    for lo, hi in itertools.pairwise(edges):
        sel = (side >= lo) & (side < hi) & np.isfinite(px)
        if sel.any():
            out.append(
                {
                    "side_px": f"{lo:g}-{hi:g}",
                    "n": int(sel.sum()),
                    "mean_px": round(float(px[sel].mean()), 3),
                    "rms_px": round(float(np.sqrt(np.mean(px[sel] ** 2))), 3),
                    "nees": round(float(np.mean((px[sel] / CORNER_PX) ** 2)), 2),
                }
            )
    return out


def serial(rows: list[dict[str, Any]]) -> dict[str, float]:
    """The correlation of consecutive fixes' errors (the same robot and board, one image apart)
    along, across and in yaw: how much of the experiment's error its fixes share."""
    by: dict[tuple[Any, Any], list[dict[str, Any]]] = {}
    for row in rows:
        by.setdefault((row["robot"], row["marker"]), []).append(row)
    out = {}
    for axis in ("along_m", "across_m", "yaw_rad"):
        a, b = [], []
        for found in by.values():
            ordered = sorted(found, key=lambda x: x["image"])
            for x, y in itertools.pairwise(ordered):
                if y["image"] - x["image"] <= 1.0 + 1e-6:
                    a.append(x[axis] / x[f"sd_{axis}"])
                    b.append(y[axis] / y[f"sd_{axis}"])
        out[axis] = round(float(np.corrcoef(a, b)[0, 1]), 2) if len(a) > 2 else math.nan
    out["pairs"] = len(a)
    return out


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m colonyd.bench.fix_calibration")
    parser.add_argument(
        "--worlds",
        type=names(("office", "hall")),
        default="office,hall",
        help="comma-separated sim worlds (office, hall)",
    )
    parser.add_argument(
        "--samples", type=int, default=0, help=f"images per world (default {SAMPLES})"
    )
    parser.add_argument("--seed", type=int, default=1, help="of the sampled robots' poses")
    parser.add_argument(
        "--experiment", type=float, default=0.0, help="also the experiment's fixes over S s"
    )
    parser.add_argument(
        "--model",
        choices=FIX_MODELS,
        default="fitted",
        help="the fix model whose claims are judged",
    )
    parser.add_argument("--json", type=Path, help="append the result as one JSON line")
    args = parser.parse_args(argv)
    worlds = args.worlds
    if args.samples < 0:
        parser.error(f"--samples: expected a whole number >= 0 (0: SAMPLES), found {args.samples}")
    out: dict[str, Any] = {"worlds": worlds, "samples": args.samples, "seed": args.seed}
    out["model"] = args.model
    pooled: list[dict[str, Any]] = []
    markers: list[dict[str, Any]] = []
    for world in worlds:
        boards = board_rows(world, args.samples or SAMPLES[world], args.seed, args.model)
        pooled += boards
        out[f"fixes_{world}"] = by_range(boards)
        if args.experiment > 0:
            seen = experiment_rows(world, args.experiment, args.model)
            out[f"experiment_{world}"] = by_range(seen)
            out[f"experiment_{world}_angles"] = by_range(seen, ANGLE_BINS, "incidence_deg")
            out[f"experiment_{world}_serial"] = serial(seen)
        found = marker_rows(world)
        markers += found
        out[f"markers_{world}"] = [{k: round(v, 4) for k, v in row.items()} for row in found]
    out["fixes"] = by_range(pooled)
    out["angles"] = by_range(pooled, ANGLE_BINS, "incidence_deg")
    out["fits"] = fits(pooled)
    out["angle_fit"] = fit_angle(pooled)
    out["sides"] = sides(pooled)
    out["markers_nees"] = round(
        float(np.mean([(row["along_m"] / row["sd_along_m"]) ** 2 for row in markers])), 2
    )
    print_and_append(out, args.json)
    return out


if __name__ == "__main__":
    main()
