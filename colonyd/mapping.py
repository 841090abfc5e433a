"""Offline mapping: integrate every observation of one source into a VoxelGrid and write the map
files."""

from __future__ import annotations

import logging
import sys
import threading
import time as clock
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, TextIO

import numpy as np

from colonyd.outdir import run_output
from plugins.errors import SourceError
from plugins.observation import Observation
from plugins.source import open_source
from plugins.stream import StreamStats
from voxel import kernels
from voxel import keys as vk
from voxel.blocks import shape_for
from voxel.delta import Delta
from voxel.errors import InputError
from voxel.grid import VoxelGrid
from voxel.octomap_io import write_bt
from voxel.ply import write_ply
from voxel.rotation import matrix_to_quaternion
from voxel.sensor import SensorModel

#: Floor-plan grey levels (map_server convention): occupied, free, unknown.
OCCUPIED_GREY, FREE_GREY, UNKNOWN_GREY = 0, 254, 205


@dataclass(frozen=True)
class MapSummary:
    """What `map_source` did and wrote."""

    spec: str
    resolution: float
    frames: int
    skipped: int
    points: int
    occupied: int
    free: int
    seconds: float
    files: dict[str, Path] = field(default_factory=dict)
    skip_reasons: dict[str, int] = field(default_factory=dict)
    #: Seconds spent reading and decoding frames, integrating them, and writing the map files.
    breakdown: dict[str, float] = field(default_factory=dict)

    @property
    def frames_per_second(self) -> float:
        """Frames mapped per second of reading and integrating them (files not counted)."""
        busy = self.breakdown.get("decode", 0.0) + self.breakdown.get("integrate", 0.0)
        return self.frames / busy if busy > 0 else 0.0


class Progress(Protocol):
    """Progress display: told the total once, then every finished frame."""

    def update(self, done: int, total: int | None) -> None: ...

    def close(self) -> None: ...


class NullProgress:
    """Progress display that shows nothing."""

    def update(self, done: int, total: int | None) -> None:
        """Do nothing."""

    def close(self) -> None:
        """Do nothing."""


class BarProgress:
    """A one-line progress bar on a text stream (stderr), redrawn at most every 0.1 s. While it is
    shown, log records that go to the same stream clear the bar's line, print, and redraw it, so
    warnings never run into the bar. On a stream that is not a terminal (a log file, CI) it writes
    a line of its own every `LOG_EVERY_S` and at the end instead (no carriage returns)."""

    #: Seconds between progress lines when the stream is not a terminal.
    LOG_EVERY_S = 10.0

    def __init__(
        self, stream: TextIO | None = None, width: int = 30, terminal: bool | None = None
    ) -> None:
        self.stream, self.width = sys.stderr if stream is None else stream, width
        self.terminal = self.stream.isatty() if terminal is None else terminal
        self.began = clock.monotonic()
        self.drawn = 0.0
        self.line = ""  # the bar as last drawn ("" before the first draw and after close)
        self._handlers: list[logging.StreamHandler[Any]] = []
        for handler in logging.getLogger().handlers if self.terminal else ():
            if isinstance(handler, logging.StreamHandler) and handler.stream is self.stream:
                handler.setStream(_AroundBar(self))
                self._handlers.append(handler)

    def update(self, done: int, total: int | None) -> None:
        """Redraw the bar after `done` of `total` frames."""
        now = clock.monotonic()
        if now - self.drawn < (0.1 if self.terminal else self.LOG_EVERY_S) and done != total:
            return
        self.drawn = now
        rate = done / max(now - self.began, 1e-9)
        if total:
            filled = int(self.width * min(done / total, 1.0))
            bar = "#" * filled + "." * (self.width - filled)
            line = f"\r[{bar}] {done}/{total} frames {rate:.1f} fps"
        else:
            line = f"\r{done} frames {rate:.1f} fps"
        if not self.terminal:  # a line of its own in a log
            self.stream.write(line[1:] + "\n")
            self.stream.flush()
            return
        self.line = line
        self.stream.write(line)
        self.stream.flush()

    def clear(self) -> None:
        """Blank the bar's line and return to its start (before a log line is written)."""
        if self.line:
            self.stream.write("\r" + " " * (len(self.line) - 1) + "\r")

    def close(self) -> None:
        """End the bar's line; log records go straight to the stream again."""
        for handler in self._handlers:
            handler.setStream(self.stream)
        self._handlers = []
        self.line = ""
        if self.terminal:
            self.stream.write("\n")
            self.stream.flush()


class _AroundBar:
    """The stream a log handler writes to while a bar is shown: each record clears the bar's line
    first and redraws the bar after its newline."""

    def __init__(self, bar: BarProgress) -> None:
        self.bar = bar

    def write(self, text: str) -> int:
        self.bar.clear()
        n = self.bar.stream.write(text)
        if text.endswith("\n") and self.bar.line:
            self.bar.stream.write(self.bar.line)
        return n

    def flush(self) -> None:
        self.bar.stream.flush()


def get_progress(enabled: bool) -> Progress:
    """A stderr progress bar when enabled, else a do-nothing one."""
    return BarProgress() if enabled else NullProgress()


def integrate_observation(
    grid: VoxelGrid,
    obs: Observation,
    *,
    sensor: SensorModel,
    reliability: float,
    agent: str = "self",
    error: float = 0.0,
    agent_reliability: float = 1.0,
    bias: float = 0.0,
) -> None:
    """Integrate one observation, with its pose guess, into `grid`; a ready-made delta is applied as
    the grid's next version. `error`, `agent_reliability` and `bias` go into its history records
    (VOXEL.md, "Provenance")."""
    if obs.delta is not None:
        v, d = int(grid.version), obs.delta
        grid.apply(
            Delta(
                d.resolution,
                v,
                v + 1,
                d.keys,
                d.logodds,
                d.last_time,
                d.channels,
                d.time,
                surface_mask=d.surface_mask,
            )
        )
        return
    if len(obs) == 0:
        return
    grid.integrate(
        obs.points_world(),
        obs.origin,
        time=obs.time,
        sensor=sensor,
        agent=agent,
        reliability=reliability,
        error=error,
        agent_reliability=agent_reliability,
        bias=bias,
        colours=obs.colours,
        normals=obs.normals_world(),
        class_ids=obs.class_ids,
        class_probs=obs.class_probs,
        scalars=obs.scalars or None,
        no_return=obs.no_return,
    )


def tum_line(time: float, pose: np.ndarray) -> str:
    """One TUM trajectory line: timestamp tx ty tz qx qy qz qw."""
    q = matrix_to_quaternion(pose[:3, :3])
    t = pose[:3, 3]
    return (
        f"{time:.6f} {t[0]:.6f} {t[1]:.6f} {t[2]:.6f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}"
    )


def floor_plan(
    occupied: np.ndarray, free: np.ndarray, layer: int, margin: int | None = 20
) -> tuple[np.ndarray, np.ndarray]:
    """Grey image of the voxel layer z = `layer` (+x right, +y up) and the key of its lower-left
    pixel.

    occupied, free: voxel keys (N, 3). Occupied 0, free 254, unknown 205. With a margin (cells),
    the image is cropped to the occupied cells' extent plus the margin, so free space cleared by
    long no-return beams does not swamp the plan.
    """
    occ = occupied[occupied[:, 2] == layer, :2]
    fre = free[free[:, 2] == layer, :2]
    both = np.concatenate([occ, fre])
    if both.size == 0:
        return np.full((1, 1), UNKNOWN_GREY, np.uint8), np.zeros(2, np.int64)
    lo, hi = both.min(axis=0), both.max(axis=0)
    if margin is not None and len(occ):
        lo = np.maximum(lo, occ.min(axis=0) - margin)
        hi = np.minimum(hi, occ.max(axis=0) + margin)
        fre = fre[np.all((fre >= lo) & (fre <= hi), axis=1)]
    w, h = (hi - lo + 1).tolist()
    image = np.full((h, w), UNKNOWN_GREY, np.uint8)
    image[h - 1 - (fre[:, 1] - lo[1]), fre[:, 0] - lo[0]] = FREE_GREY
    image[h - 1 - (occ[:, 1] - lo[1]), occ[:, 0] - lo[0]] = OCCUPIED_GREY
    return image, lo


def write_floor_plan(
    out_dir: Path, occupied: np.ndarray, free: np.ndarray, layer: int, resolution: float
) -> dict[str, Path]:
    """`floorplan.png` of voxel layer z = `layer` and its ROS map_server `floorplan.yaml`."""
    image, lo = floor_plan(occupied, free, layer)
    files = {"floorplan": out_dir / "floorplan.png", "floorplan_yaml": out_dir / "floorplan.yaml"}
    import cv2  # loads where a floor plan is written, not at start-up

    if not cv2.imwrite(str(files["floorplan"]), image):
        msg = f"{files['floorplan']}: cannot write the floor plan PNG"
        raise OSError(msg)
    files["floorplan_yaml"].write_text(
        f"image: floorplan.png\nresolution: {resolution}\n"
        # rounded: -41 * 0.1 is -4.1000000000000005 in binary floating point
        f"origin: [{round(lo[0] * resolution, 9)}, {round(lo[1] * resolution, 9)}, 0.0]\n"
        f"layer: {layer}\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n",
        encoding="ascii",
    )
    return files


def no_frames(spec: str, stats: StreamStats, written: str) -> SourceError:
    """The error of a run whose source `spec` yielded no frame (an empty map or trajectory is no
    result): how many it skipped and why, and what was `written` (nothing)."""
    reasons = "; ".join(f"{n} x {r}" for r, n in stats.reasons.items()) or "none given"
    msg = (
        f"{spec}: expected at least one readable frame, found none "
        f"({stats.skipped} skipped: {reasons}); {written}"
    )
    return SourceError(msg)


def map_source(
    spec: str,
    resolution: float,
    out_dir: Path,
    *,
    max_frames: int | None = None,
    progress: bool = True,
) -> MapSummary:
    """Map the source `spec` at `resolution` metres and write grid.npz, map.bt, map.ply,
    trajectory.tum (and floorplan.png for 2D scanners) into `out_dir`."""
    began = clock.monotonic()
    warming = threading.Thread(target=kernels.warm, name="kernels", daemon=True)
    warming.start()  # compiled kernels load while the source opens and decodes
    source = open_source(spec, resolution=resolution)
    adapter = source.adapter
    # the surface (mean hit positions) for what reads grid.npz: `colonyd align`'s registration
    grid = VoxelGrid(resolution, block_shape=shape_for(adapter.kind), surface=True)
    out_dir = Path(out_dir)
    total = len(source) if max_frames is None else min(len(source), max_frames)
    trajectory: list[str] = []
    heights: list[float] = []
    frames = points = 0
    spent = {"decode": 0.0, "integrate": 0.0, "write": 0.0}
    frames_in = iter(source)
    with run_output(out_dir, "--out"):  # no map, no folder left behind
        bar = get_progress(progress)
        try:
            while max_frames is None or frames < max_frames:
                t0 = clock.perf_counter()
                obs = next(frames_in, None)
                t1 = clock.perf_counter()
                spent["decode"] += t1 - t0
                if obs is None:
                    break
                integrate_observation(
                    grid, obs, sensor=adapter.sensor_model, reliability=adapter.reliability
                )
                spent["integrate"] += clock.perf_counter() - t1
                trajectory.append(tum_line(obs.time, obs.pose))
                heights.append(float(obs.pose[2, 3]))
                frames += 1
                points += len(obs)
                bar.update(frames, total)
        finally:
            bar.close()
        if frames == 0:
            raise no_frames(spec, source.stats, "no map written")
    t0 = clock.perf_counter()
    files = write_map(grid, out_dir, trajectory)
    if adapter.kind == "lidar2d" and heights:
        layer = int(vk.points_to_keys(np.array([[0.0, 0.0, np.median(heights)]]), resolution)[0, 2])
        files.update(
            write_floor_plan(out_dir, grid.occupied_keys(), grid.free_keys(), layer, resolution)
        )
    spent["write"] = clock.perf_counter() - t0
    return MapSummary(
        spec=spec,
        resolution=resolution,
        frames=frames,
        skipped=source.stats.skipped,
        points=points,
        occupied=len(grid.occupied_keys()),
        free=len(grid.free_keys()),
        seconds=clock.monotonic() - began,
        files=files,
        skip_reasons=dict(source.stats.reasons),
        breakdown=spent,
    )


def summary_breakdown(spent: dict[str, float], total: float) -> str:
    """One line of where a mapping run's time went, e.g. 'decode 1.2 s (40 %), ...'."""
    parts = [
        f"{name} {sec:.2f} s ({100 * sec / max(total, 1e-9):.0f} %)" for name, sec in spent.items()
    ]
    other = total - sum(spent.values())
    parts.append(f"other {max(other, 0.0):.2f} s")
    return ", ".join(parts)


def write_map(grid: VoxelGrid, out_dir: Path, trajectory: list[str]) -> dict[str, Path]:
    """Snapshot, OctoMap .bt, PLY of the occupied voxels' surface points (their mean hit positions,
    with colour) and TUM trajectory."""
    files = {
        "snapshot": out_dir / "grid.npz",
        "bt": out_dir / "map.bt",
        "ply": out_dir / "map.ply",
        "trajectory": out_dir / "trajectory.tum",
    }
    grid.save(files["snapshot"])
    occupied, free = grid.occupied_keys(), grid.free_keys()
    keys = np.concatenate([occupied, free]).astype(np.int64)
    mask = np.zeros(len(keys), bool)
    mask[: len(occupied)] = True
    write_bt(files["bt"], grid.resolution, keys, mask)
    try:
        colours = grid.channel_at_keys("colour", occupied) if len(occupied) else None
    except InputError:  # no colour was ever integrated
        colours = None
    write_ply(files["ply"], grid.surface_points(occupied), colours)  # mean hit positions
    files["trajectory"].write_text("".join(line + "\n" for line in trajectory), encoding="ascii")
    return files
