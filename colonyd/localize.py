"""Offline localisation: run one agent's estimator over a source, build the map from its poses,
write trajectories, map and ATE."""

from __future__ import annotations

import json
import time as clock
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from colonyd.estimator import Estimator, ScanEstimator, get_estimator
from colonyd.mapping import get_progress, integrate_observation, no_frames, tum_line, write_map
from colonyd.outdir import run_output
from plugins.carmen import CarmenSource
from plugins.observation import Observation
from plugins.sevenscenes import RgbdSource
from plugins.source import open_source
from voxel.grid import VoxelGrid
from voxel.localisation import se2
from voxel.localisation.metrics import absolute_trajectory_error

#: Poses an ATE needs (the rigid fit of the path onto the reference takes three).
MIN_ATE_POSES = 3


@dataclass(frozen=True)
class LocalizeSummary:
    """What `localize_source` measured and wrote."""

    spec: str
    estimator: str
    frames: int
    seconds: float
    ate_estimate: float | None
    ate_odometry: float | None
    ate_smoothed: float | None
    recording_seconds: float
    files: dict[str, Path]
    #: Poses with a reference (simulator truth, a recording's reference): 0 without one.
    reference_poses: int = 0


def _reference(source: object, obs: Observation) -> np.ndarray | None:
    """The reference sensor pose of an observation, for evaluation only: simulator truth or a
    recording's reference."""
    if obs.truth is not None:
        return obs.truth
    if isinstance(source, RgbdSource) or (
        isinstance(source, CarmenSource) and source.poses == "reference"
    ):
        return obs.pose
    return None


def localize_source(
    spec: str,
    out_dir: Path,
    *,
    resolution: float = 0.1,
    odometry_noise: str | None = None,
    seed: int | None = None,
    max_frames: int | None = None,
    progress: bool = True,
) -> LocalizeSummary:
    """Estimate the poses of the agent of `spec` and write estimate.tum (the filter's online
    estimate, each pose as it was known then), smoothed.tum (a scan estimator's: every pose
    re-solved with everything the filter fused, `PoseGraph`), odometry.tum, groundtruth.tum, the
    map from the estimated poses (grid.npz, map.bt, map.ply) and results.json into `out_dir`."""
    began = clock.monotonic()
    if odometry_noise is not None:
        spec += f",odometry_noise={odometry_noise}"
    if seed is not None:
        spec += f",seed={seed}"
    source = open_source(spec, resolution=resolution)
    adapter = source.adapter
    grid = VoxelGrid(resolution, block_shape="planar" if adapter.kind == "lidar2d" else "cube")
    out_dir = Path(out_dir)
    total = len(source) if max_frames is None else min(len(source), max_frames)
    estimator: Estimator | None = None
    times: list[float] = []
    est: list[np.ndarray] = []
    odo: list[np.ndarray] = []
    ref: list[np.ndarray] = []
    with run_output(out_dir, "--out"):  # no result, no folder left behind
        bar = get_progress(progress)
        try:
            for obs in source:
                if max_frames is not None and len(times) >= max_frames:
                    break
                if estimator is None:
                    estimator = get_estimator(adapter, obs)
                    if isinstance(estimator, ScanEstimator):
                        estimator.localiser.record = True
                pose = estimator(obs)
                integrate_observation(
                    grid,
                    replace(obs, pose=pose),
                    sensor=adapter.sensor_model,
                    reliability=adapter.reliability,
                )
                times.append(obs.time)
                est.append(pose)
                if obs.odometry is not None:
                    odo.append(obs.odometry @ getattr(adapter, "mount", np.eye(4)))
                reference = _reference(source, obs)
                if reference is not None:
                    ref.append(reference)
                bar.update(len(times), total)
        finally:
            bar.close()
        if not times:
            raise no_frames(spec, source.stats, "nothing written")
    files = write_map(grid, out_dir, [tum_line(t, p) for t, p in zip(times, est, strict=True)])
    files["estimate"] = _write_tum(out_dir / "estimate.tum", times, est)
    smoothed: list[np.ndarray] = []
    smoothing = 0.0
    graph = estimator.localiser.graph if isinstance(estimator, ScanEstimator) else None
    if graph is not None and isinstance(estimator, ScanEstimator) and graph.nodes == len(times):
        began_smoothing = clock.process_time()
        mount = estimator.mount
        smoothed = [se2.to_matrix(p) @ mount for p in graph.solve().poses]
        smoothing = clock.process_time() - began_smoothing
        files["smoothed"] = _write_tum(out_dir / "smoothed.tum", times, smoothed)
    ate_est = ate_odo = ate_smooth = None
    if len(odo) == len(times) and odo:
        files["odometry"] = _write_tum(out_dir / "odometry.tum", times, odo)
    if len(ref) == len(times):
        files["groundtruth"] = _write_tum(out_dir / "groundtruth.tum", times, ref)
    if len(ref) == len(times) and len(ref) >= MIN_ATE_POSES:
        ate_est = absolute_trajectory_error(np.array(ref), np.array(est)).rmse
        if smoothed:
            ate_smooth = absolute_trajectory_error(np.array(ref), np.array(smoothed)).rmse
        if "odometry" in files:
            ate_odo = absolute_trajectory_error(np.array(ref), np.array(odo)).rmse
    seconds = clock.monotonic() - began
    recording = float(times[-1] - times[0]) if times else 0.0
    summary = LocalizeSummary(
        spec=spec,
        estimator=estimator.name if estimator else "none",
        frames=len(times),
        seconds=seconds,
        ate_estimate=ate_est,
        ate_odometry=ate_odo,
        ate_smoothed=ate_smooth,
        recording_seconds=recording,
        files=files,
        reference_poses=len(ref) if len(ref) == len(times) else 0,
    )
    files["results"] = out_dir / "results.json"
    files["results"].write_text(
        json.dumps(
            {
                "spec": spec,
                "estimator": summary.estimator,
                "ate_rmse_m": {"estimate": ate_est, "odometry": ate_odo, "smoothed": ate_smooth},
                "smoothing_cpu_seconds": round(smoothing, 3) if smoothed else None,
                "frames": len(times),
                "seconds": round(seconds, 3),
                "frames_per_second": round(len(times) / max(seconds, 1e-9), 2),
                "recording_seconds": round(recording, 3),
                "faster_than_real_time": round(recording / max(seconds, 1e-9), 2)
                if recording
                else None,
                "skipped": source.stats.skipped,
            },
            indent=1,
        )
        + "\n",
        encoding="ascii",
    )
    return summary


def _write_tum(path: Path, times: list[float], poses: list[np.ndarray]) -> Path:
    lines = "".join(tum_line(t, p) + "\n" for t, p in zip(times, poses, strict=True))
    path.write_text(lines, encoding="ascii")
    return path
