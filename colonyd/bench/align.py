"""Alignment benchmark: real laser halves, OctoMap crops, negatives, and map_merge's ORB method side
by side."""

from __future__ import annotations

import json
import logging
import math
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from colonyd.bench.files import shared_data_dir
from colonyd.bench.mapmerge import estimate as baseline_estimate
from colonyd.errors import ConfigError
from voxel import keys as vk
from voxel.octomap_io import BtMap, read_bt, write_bt
from voxel.registration import Alignment, AlignParams, MapCloud, align_clouds, load_map
from voxel.registration.transform import apply, rigid

log = logging.getLogger("colonyd.bench")

CARMEN_LOG = "carmen/freiburg-079-corrected.log.gz"
OCTOMAP = "octomap/fr_079.bt"
CARMEN_SCANS = 4791
RESOLUTION_2D = 0.05
MAX_RANGE_2D = 40.0
#: Targets of issue 11.
RMS_2D_M, YAW_DEG = 0.10, 1.0
VOXELS_3D = 1.5


def run_align_bench(
    out_json: Path,
    shared_data: Path | None = None,
    *,
    seeds: int = 20,
    octomap_seeds: int = 10,
    negative_seeds: int = 5,
    carmen_step: int = 1,
    octomap: str = OCTOMAP,
    work_dir: Path | None = None,
    command: str | None = None,
) -> dict[str, Any]:
    """Run every case, write the JSON result (with its command) to `out_json` and return it."""
    data = shared_data_dir(shared_data)
    if data is None or not (data / CARMEN_LOG).is_file() or not (data / octomap).is_file():
        msg = (
            f"align benchmark: expected the shared recordings ({CARMEN_LOG}, {octomap}) under "
            f"../shared/data or --shared-data, found {data}"
        )
        raise ConfigError(msg)
    work = (
        Path(work_dir) if work_dir is not None else Path(tempfile.mkdtemp(prefix="colony-align-"))
    )
    began = time.perf_counter()
    try:
        rows: list[dict[str, Any]] = []
        halves = CarmenHalves(data / CARMEN_LOG, work, carmen_step)
        rows += carmen_cases(halves, seeds)
        rows += octomap_cases(data / octomap, work, octomap_seeds)
        rows += negative_cases(halves, data / octomap, work, negative_seeds)
    finally:
        if work_dir is None:
            shutil.rmtree(work, ignore_errors=True)
    result = {
        "command": command or "colonyd bench align " + " ".join(sys.argv[3:]),
        "params": {
            "seeds": seeds,
            "octomap_seeds": octomap_seeds,
            "negative_seeds": negative_seeds,
            "carmen_step": carmen_step,
            "octomap": octomap,
            "resolution_2d": RESOLUTION_2D,
            "max_range_2d": MAX_RANGE_2D,
        },
        "summary": summarise(rows),
        "cases": rows,
        "seconds": round(time.perf_counter() - began, 1),
    }
    out_json = Path(out_json)
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(result, indent=1) + "\n")
    return result


class CarmenHalves:
    """The Freiburg 079 log split into its first and last 60 % of scans, mapped with `colonyd map`'s
    mapper; the second half's poses moved by a rigid transform per seed."""

    def __init__(self, log_path: Path, work: Path, step: int) -> None:
        self.log, self.work, self.step = log_path, work, step
        self.split_a = int(0.6 * CARMEN_SCANS)
        self.split_b = CARMEN_SCANS - int(0.6 * CARMEN_SCANS)

    def first(self) -> tuple[MapCloud, float]:
        """Map A (first 60 %), and the seconds it took to load."""
        return self._map("a", f"stop={self.split_a}")

    def second(self, move: tuple[float, float, float]) -> tuple[MapCloud, float, np.ndarray]:
        """Map B (last 60 %) with poses moved by (x, y, yaw degrees); load seconds; trajectory (N,
        3)."""
        x, y, yaw = move
        name = f"b_{x:.3f}_{y:.3f}_{yaw:.3f}"
        cloud, load_s = self._map(
            name, f"start={self.split_b},move_x={x!r},move_y={y!r},move_yaw={yaw!r}"
        )
        trajectory = np.loadtxt(self.work / name / "trajectory.tum", ndmin=2)[:, 1:4]
        return cloud, load_s, trajectory

    def _map(self, name: str, options: str) -> tuple[MapCloud, float]:
        from colonyd.mapping import map_source

        out = self.work / name
        if not (out / "grid.npz").is_file():
            spec = f"replay:{self.log},{options},step={self.step},max_range={MAX_RANGE_2D}"
            map_source(spec, RESOLUTION_2D, out, progress=False)
        began = time.perf_counter()
        cloud = load_map(out / "grid.npz")
        return cloud, time.perf_counter() - began


def random_move_2d(seed: int) -> tuple[float, float, float]:
    """x, y in [-20, 20] m and any yaw (degrees), from the seed."""
    rng = np.random.default_rng(seed)
    return float(rng.uniform(-20, 20)), float(rng.uniform(-20, 20)), float(rng.uniform(-180, 180))


def carmen_cases(halves: CarmenHalves, seeds: int) -> list[dict[str, Any]]:
    """Real laser data: both halves aligned, ours and the baseline, error over B's trajectory."""
    a, _ = halves.first()
    rows = []
    for seed in range(seeds):
        move = random_move_2d(seed)
        b, load_s, trajectory = halves.second(move)
        truth = np.linalg.inv(rigid(move[0], move[1], yaw=math.radians(move[2])))
        row = {
            "case": "carmen079_halves",
            "seed": seed,
            "expect": "aligned",
            "move": [round(v, 4) for v in move],
            "occupied_a": len(a.occupied),
            "occupied_b": len(b.occupied),
            "load_seconds": round(load_s, 3),
        }
        row.update(_ours(align_clouds(a, b, AlignParams(dof=3)), truth, trajectory, RMS_2D_M))
        row.update(_baseline(a, b, truth, trajectory, RMS_2D_M, seed))
        log.info(
            "carmen seed %d: ours %s %.3f m, baseline %s",
            seed,
            row["aligned"],
            row["rms_m"],
            row["baseline_merged"],
        )
        rows.append(row)
    return rows


def octomap_cases(path: Path, work: Path, seeds: int) -> list[dict[str, Any]]:
    """Two crops of an OctoMap map overlapping by 20 % of its extent, B moved in x, y, z and yaw,
    both written as .bt and aligned from the files (reading included in `seconds_with_io`)."""
    bt = read_bt(path)
    rows = []
    for seed in range(seeds):
        rng = np.random.default_rng(1000 + seed)
        move = rigid(
            rng.uniform(-20, 20),
            rng.uniform(-20, 20),
            rng.uniform(-2, 2),
            yaw=math.radians(rng.uniform(-180, 180)),
        )
        a_path, b_path = work / f"oct_a_{seed}.bt", work / f"oct_b_{seed}.bt"
        _write_crop(a_path, bt, 0.0, 0.6, None)
        _write_crop(b_path, bt, 0.4, 1.0, move)
        began = time.perf_counter()
        a, b = load_map(a_path), load_map(b_path)
        result = align_clouds(a, b, AlignParams(dof=4))
        with_io = time.perf_counter() - began
        row = {
            "case": "octomap_crops_20pct",
            "seed": seed,
            "expect": "aligned",
            "resolution": bt.resolution,
            "occupied_a": len(a.occupied),
            "occupied_b": len(b.occupied),
            "seconds_with_io": round(with_io, 3),
        }
        row.update(_ours(result, np.linalg.inv(move), b.occupied, VOXELS_3D * bt.resolution))
        log.info("octomap seed %d: %s %.3f m", seed, row["aligned"], row["rms_m"])
        rows.append(row)
    return rows


def _write_crop(
    path: Path, bt: BtMap, lo_frac: float, hi_frac: float, move: np.ndarray | None
) -> None:
    keys, occupied = crop_keys(bt.keys, bt.occupied, bt.resolution, lo_frac, hi_frac, move)
    write_bt(path, bt.resolution, keys, occupied)


def crop_keys(
    keys: np.ndarray,
    occupied: np.ndarray,
    resolution: float,
    lo_frac: float,
    hi_frac: float,
    move: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Voxels whose x lies in [lo_frac, hi_frac) of the occupied extent, optionally moved by a
    rigid transform and voxelised again (occupied wins where two land in one voxel)."""
    occ_x = keys[occupied, 0]
    x0, ext = int(occ_x.min()), int(occ_x.max() - occ_x.min()) + 1
    sel = (keys[:, 0] >= x0 + lo_frac * ext) & (keys[:, 0] < x0 + hi_frac * ext)
    keys, occupied = keys[sel], occupied[sel]
    if move is None:
        return keys, occupied
    moved = vk.points_to_keys(apply(move, vk.keys_to_centers(keys, resolution)), resolution)
    uniq, inv = np.unique(vk.pack(moved), return_inverse=True)
    return vk.unpack(uniq), np.bincount(inv, weights=occupied, minlength=len(uniq)) > 0


def negative_cases(
    halves: CarmenHalves, octomap: Path, work: Path, seeds: int
) -> list[dict[str, Any]]:
    """Pairs that must never align: a building against simulated other buildings, and halves of one
    map that do not overlap (2D and 3D); the baseline runs on the 2D ones."""
    from colonyd.mapping import map_source

    a, _ = halves.first()
    others = {}
    for world in ("office", "room"):
        out = work / f"sim_{world}"
        if not (out / "grid.npz").is_file():
            map_source(
                f"sim:world={world},agent=lidar-1,frames=300", RESOLUTION_2D, out, progress=False
            )
        others[world] = load_map(out / "grid.npz")
    assert a.known is not None  # a simulated grid knows its free voxels
    known_keys = vk.unpack(a.known)
    bt = read_bt(octomap)
    rows = []
    for seed in range(seeds):
        x, y, yaw = random_move_2d(100 + seed)
        move = rigid(x, y, yaw=math.radians(yaw))
        pairs: list[tuple[str, MapCloud, MapCloud, int, bool]] = [
            (f"079_vs_sim_{w}", a, _moved_cloud(others[w], move), 3, True) for w in others
        ]
        pairs.append(
            (
                "079_halves_no_overlap",
                _crop_cloud(a, known_keys, 0.0, 0.4, None),
                _crop_cloud(a, known_keys, 0.6, 1.0, move),
                3,
                True,
            )
        )
        pairs.append(
            (
                "octomap_crops_no_overlap",
                _bt_cloud(bt, 0.0, 0.35, None),
                _bt_cloud(bt, 0.65, 1.0, move),
                4,
                False,
            )
        )
        for name, first, second, dof, planar in pairs:
            result = align_clouds(first, second, AlignParams(dof=dof))
            row = {
                "case": f"negative_{name}",
                "seed": seed,
                "expect": "not aligned",
                "aligned": result.aligned,
                "confidence": round(result.confidence, 4),
                "reason": result.reason,
                "failed_checks": list(result.failed_checks),
                "ambiguity": round(result.ambiguity, 4),
                "inlier_ratio": round(result.inlier_ratio, 4),
                "conflict": round(result.conflict, 4),
                "agreement": round(result.agreement, 4),
                "seconds": round(result.seconds, 3),
            }
            if planar:
                base = baseline_estimate(first, second, seed)
                row.update(
                    {
                        "baseline_merged": base.merged,
                        "baseline_confidence": round(base.confidence, 3),
                        "baseline_seconds": round(base.seconds, 3),
                    }
                )
            log.info("negative %s seed %d: aligned %s", name, seed, result.aligned)
            rows.append(row)
    return rows


def _moved_cloud(cloud: MapCloud, move: np.ndarray) -> MapCloud:
    assert cloud.known is not None and cloud.known_occupied is not None  # a grid or .bt map
    keys = vk.unpack(cloud.known)
    return _from_keys(keys, cloud.known_occupied, cloud.resolution, move)


def _crop_cloud(
    cloud: MapCloud, keys: np.ndarray, lo: float, hi: float, move: np.ndarray | None
) -> MapCloud:
    assert cloud.known_occupied is not None  # a grid or .bt map
    k, o = crop_keys(keys, cloud.known_occupied, cloud.resolution, lo, hi, None)
    return _from_keys(k, o, cloud.resolution, move)


def _bt_cloud(bt: BtMap, lo: float, hi: float, move: np.ndarray | None) -> MapCloud:
    k, o = crop_keys(bt.keys, bt.occupied, bt.resolution, lo, hi, move)
    return MapCloud.from_keys(bt.resolution, k, o)


def _from_keys(
    keys: np.ndarray, occupied: np.ndarray, resolution: float, move: np.ndarray | None
) -> MapCloud:
    if move is not None:
        moved = vk.points_to_keys(apply(move, vk.keys_to_centers(keys, resolution)), resolution)
        uniq, inv = np.unique(vk.pack(moved), return_inverse=True)
        keys, occupied = (
            vk.unpack(uniq),
            np.bincount(inv, weights=occupied, minlength=len(uniq)) > 0,
        )
    return MapCloud.from_keys(resolution, keys, occupied)


def _errors(t: np.ndarray, truth: np.ndarray, points: np.ndarray) -> tuple[float, float]:
    rms = float(np.sqrt(np.mean(np.sum((apply(t, points) - apply(truth, points)) ** 2, axis=1))))
    rel = t[:3, :3] @ truth[:3, :3].T
    return rms, abs(math.degrees(math.atan2(rel[1, 0], rel[0, 0])))


def _ours(result: Alignment, truth: np.ndarray, points: np.ndarray, tol_m: float) -> dict[str, Any]:
    rms, yaw = _errors(result.transform, truth, points)
    within = rms <= tol_m and yaw <= YAW_DEG
    return {
        "aligned": result.aligned,
        "within_target": within,
        "confident_wrong": result.aligned and not within,
        "rms_m": round(rms, 4),
        "yaw_err_deg": round(yaw, 4),
        "confidence": round(result.confidence, 4),
        "inliers": result.inliers,
        "rmse_m": round(result.rmse_m, 4) if math.isfinite(result.rmse_m) else None,
        "overlap": round(result.overlap, 4),
        "ambiguity": round(result.ambiguity, 4),
        "conflict": round(result.conflict, 4),
        "conflict_extent_m": round(result.conflict_extent_m, 2),
        "reason": result.reason,
        "failed_checks": list(result.failed_checks),
        "seconds": round(result.seconds, 3),
    }


def _baseline(
    a: MapCloud, b: MapCloud, truth: np.ndarray, points: np.ndarray, tol_m: float, seed: int
) -> dict[str, Any]:
    base = baseline_estimate(a, b, seed)
    rms, yaw = _errors(base.transform, truth, points)
    within = rms <= tol_m and yaw <= YAW_DEG
    return {
        "baseline_merged": base.merged,
        "baseline_within_target": within,
        "baseline_confident_wrong": base.merged and not within,
        "baseline_rms_m": round(rms, 4),
        "baseline_yaw_err_deg": round(yaw, 4),
        "baseline_confidence": round(base.confidence, 3),
        "baseline_matches": base.matches,
        "baseline_inliers": base.inliers,
        "baseline_seconds": round(base.seconds, 3),
    }


def summarise(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One line per case: success rates, confident wrong answers, errors and times, ours and
    baseline."""
    out = []
    for case in dict.fromkeys(r["case"] for r in rows):
        rs = [r for r in rows if r["case"] == case]
        positive = rs[0]["expect"] == "aligned"
        line = {"case": case, "trials": len(rs)}
        if positive:
            ok = [r for r in rs if r["aligned"] and r["within_target"]]
            line.update(
                {
                    "ours_success": len(ok),
                    "ours_not_aligned": sum(not r["aligned"] for r in rs),
                    "ours_confident_wrong": sum(r["confident_wrong"] for r in rs),
                    "ours_rms_m_median": _median([r["rms_m"] for r in ok]),
                    "ours_rms_m_max": _max([r["rms_m"] for r in ok]),
                    "ours_yaw_err_deg_max": _max([r["yaw_err_deg"] for r in ok]),
                    "ours_seconds_median": _median([r["seconds"] for r in rs]),
                    "ours_seconds_max": _max([r["seconds"] for r in rs]),
                }
            )
            if "seconds_with_io" in rs[0]:
                line["ours_seconds_with_io_max"] = _max([r["seconds_with_io"] for r in rs])
            if "baseline_merged" in rs[0]:
                bok = [r for r in rs if r["baseline_merged"] and r["baseline_within_target"]]
                line.update(
                    {
                        "baseline_success": len(bok),
                        "baseline_not_merged": sum(not r["baseline_merged"] for r in rs),
                        "baseline_confident_wrong": sum(r["baseline_confident_wrong"] for r in rs),
                        "baseline_estimate_within_target": sum(
                            r["baseline_within_target"] for r in rs
                        ),
                        "baseline_rms_m_median": _median([r["baseline_rms_m"] for r in rs]),
                        "baseline_seconds_median": _median([r["baseline_seconds"] for r in rs]),
                    }
                )
        else:
            line.update(
                {
                    "ours_correctly_refused": sum(not r["aligned"] for r in rs),
                    "ours_confident_wrong": sum(r["aligned"] for r in rs),
                    "ours_fewest_failed_checks": min(len(r["failed_checks"]) for r in rs),
                    "ours_failed_checks": sorted({c for r in rs for c in r["failed_checks"]}),
                    "ours_seconds_max": _max([r["seconds"] for r in rs]),
                }
            )
            if "baseline_merged" in rs[0]:
                line.update(
                    {
                        "baseline_correctly_refused": sum(not r["baseline_merged"] for r in rs),
                        "baseline_confident_wrong": sum(r["baseline_merged"] for r in rs),
                    }
                )
        out.append(line)
    return out


def _median(v: list[float]) -> float | None:
    return round(float(np.median(v)), 4) if v else None


def _max(v: list[float]) -> float | None:
    return round(float(np.max(v)), 4) if v else None
