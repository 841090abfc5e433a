"""Tests of offline mapping: real RGB-D and laser recordings against OctoMap, and a simulated
run."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from colonyd.mapping import (
    FREE_GREY,
    OCCUPIED_GREY,
    UNKNOWN_GREY,
    floor_plan,
    integrate_observation,
    map_source,
    tum_line,
)
from plugins.source import open_source
from tests.shared import SHARED_DATA
from voxel import keys as vk
from voxel.grid import VoxelGrid
from voxel.octomap_io import read_bt
from voxel.sensor import SensorModel

DATA = SHARED_DATA
KITCHEN = DATA / "redkitchen-50"
LOG = DATA / "carmen" / "freiburg-079-corrected.log.gz"


def octomap_occupied(
    spec: str, resolution: float, tmp: Path, *, max_range: float | None = None
) -> np.ndarray:
    """Occupied voxel keys of OctoMap (pyoctomap) fed the same scans and poses as map_source."""
    pyoctomap = pytest.importorskip("pyoctomap")
    tree = pyoctomap.OcTree(resolution)
    source = open_source(spec)
    for obs in source:
        points = obs.points.copy()
        if obs.no_return is not None and max_range is not None:
            points[obs.no_return] *= (
                max_range + 1.0
            ) / max_range  # beyond max range: cleared, not hit
        world = points @ obs.pose[:3, :3].T + obs.pose[:3, 3]
        tree.insertPointCloud(
            world, obs.origin, max_range=-1.0 if max_range is None else max_range, discretize=True
        )
    path = tmp / "octomap.bt"
    tree.writeBinary(str(path))
    bt = read_bt(path)
    return bt.keys[bt.occupied]


def iou(a: np.ndarray, b: np.ndarray) -> float:
    sa, sb = set(vk.pack(a).tolist()), set(vk.pack(b).tolist())
    return len(sa & sb) / max(len(sa | sb), 1)


@pytest.mark.skipif(not KITCHEN.is_dir(), reason=f"real 7-Scenes frames not found at {KITCHEN}")
def test_redkitchen_occupied_set_agrees_with_octomap(tmp_path: Path) -> None:
    spec = f"replay:{KITCHEN}"
    summary = map_source(spec, 0.05, tmp_path / "map", progress=False)
    assert summary.frames == 50 and summary.skipped == 0
    for name in ("grid.npz", "map.bt", "map.ply", "trajectory.tum"):
        assert (tmp_path / "map" / name).stat().st_size > 0
    ours = VoxelGrid.load(tmp_path / "map" / "grid.npz").occupied_keys()
    assert len(ours) == summary.occupied > 5000
    reference = octomap_occupied(spec, 0.05, tmp_path)
    agreement = iou(ours, reference)
    assert agreement >= 0.95, agreement
    # the .bt we wrote holds the same occupied set
    bt = read_bt(tmp_path / "map" / "map.bt")
    assert iou(bt.keys[bt.occupied], ours) == 1.0
    # trajectory: one TUM line per frame, first one the first frame's pose
    lines = (tmp_path / "map" / "trajectory.tum").read_text().splitlines()
    assert len(lines) == 50
    np.testing.assert_allclose(
        [float(v) for v in lines[0].split()[1:4]], [-0.91287065, -0.34388667, 0.75986093], atol=1e-6
    )


@pytest.mark.skipif(not LOG.is_file(), reason=f"real CARMEN log not found at {LOG}")
def test_carmen_floor_plan_is_sharp_and_matches_octomap(tmp_path: Path) -> None:
    spec = f"replay:{LOG},step=60,max_range=40"
    summary = map_source(spec, 0.05, tmp_path / "map", progress=False)
    assert summary.frames == 80
    image = cv2.imread(str(tmp_path / "map" / "floorplan.png"), cv2.IMREAD_GRAYSCALE)
    assert image is not None and set(np.unique(image)) <= {OCCUPIED_GREY, FREE_GREY, UNKNOWN_GREY}
    meta = dict(
        line.split(": ", 1)
        for line in (tmp_path / "map" / "floorplan.yaml").read_text().splitlines()
    )
    ox, oy, _ = (float(v) for v in meta["origin"].strip("[]").split(","))
    rows, cols = np.nonzero(image == OCCUPIED_GREY)
    ours = np.column_stack(
        [cols + round(ox / 0.05), image.shape[0] - 1 - rows + round(oy / 0.05), np.zeros_like(rows)]
    )
    reference = octomap_occupied(spec, 0.05, tmp_path, max_range=40.0)
    reference = reference[reference[:, 2] == 0]
    agreement = iou(ours, reference)
    assert agreement >= 0.95, agreement
    # sharp: walls are thin lines, so occupied cells are few compared with the free space they bound
    free = int((image == FREE_GREY).sum())
    assert len(ours) < 0.15 * free


def test_sim_run_writes_every_file(tmp_path: Path) -> None:
    summary = map_source(
        "sim:world=room,agent=lidar-1,frames=20,start=world", 0.1, tmp_path, progress=False
    )
    assert summary.frames == 20 and summary.occupied > 50
    for name in (
        "grid.npz",
        "map.bt",
        "map.ply",
        "trajectory.tum",
        "floorplan.png",
        "floorplan.yaml",
    ):
        assert (tmp_path / name).is_file(), name
    ply = (tmp_path / "map.ply").read_bytes()
    assert ply.startswith(b"ply")
    image = cv2.imread(str(tmp_path / "floorplan.png"), cv2.IMREAD_GRAYSCALE)
    assert (image == OCCUPIED_GREY).sum() > 50  # the room's walls


def test_max_frames_and_progress_bar(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    summary = map_source("sim:world=room,agent=depth-1,frames=50", 0.1, tmp_path, max_frames=3)
    assert summary.frames == 3
    assert "3/3 frames" in capsys.readouterr().err


def test_floor_plan_image_orientation() -> None:
    occupied = np.array([[0, 0, 0], [2, 1, 0], [5, 5, 1]])
    free = np.array([[1, 0, 0], [1, 1, 0]])
    image, lo = floor_plan(occupied, free, layer=0)
    assert image.shape == (2, 3) and lo.tolist() == [0, 0]
    assert image[1, 0] == OCCUPIED_GREY and image[0, 2] == OCCUPIED_GREY  # +y is up
    assert image[1, 1] == FREE_GREY and image[0, 0] == UNKNOWN_GREY
    # free space far from any wall is cropped away
    far = np.concatenate([free, [[500, 500, 0], [-400, 0, 0]]])
    cropped, lo = floor_plan(occupied, far, layer=0, margin=2)
    assert cropped.shape == (4, 7) and lo.tolist() == [-2, 0]  # clipped to the known cells, too
    assert floor_plan(occupied, far, layer=0, margin=None)[0].shape == (501, 901)


def test_tum_line() -> None:
    pose = np.eye(4)
    pose[:3, 3] = [1, 2, 3]
    assert (
        tum_line(1.5, pose)
        == "1.500000 1.000000 2.000000 3.000000 0.000000000 0.000000000 0.000000000 1.000000000"
    )


def test_a_bulk_observation_is_applied_as_the_next_version() -> None:
    grid = VoxelGrid(0.1)
    grid.integrate(np.array([[3.0, 0.0, 0.0]]), np.zeros(3), time=1.0)
    before = int(grid.version)
    (obs,) = list(open_source("bulk:voxels=27", resolution=0.1))
    integrate_observation(grid, obs, sensor=SensorModel(), reliability=1.0)
    assert (
        int(grid.version) == before + 1 and len(grid.occupied_keys()) + len(grid.free_keys()) >= 27
    )
    np.testing.assert_array_equal(
        grid.channel_at_keys("logodds", obs.delta.keys), obs.delta.logodds
    )


def test_colonyd_map_maps_a_synthetic_source(tmp_path: Path) -> None:
    summary = map_source("synthetic:scans=3,rate=1000,points=90", 0.1, tmp_path, progress=False)
    assert summary.frames == 3 and summary.points == 270 and summary.occupied > 0


def _rendered(text: str) -> list[str]:
    """The lines a terminal shows for `text`: a carriage return starts its line over."""
    return [line.split("\r")[-1] for line in text.split("\n")]


def test_log_lines_do_not_run_into_the_progress_bar() -> None:
    """A warning logged while the bar is shown gets a line of its own; the bar is drawn again
    after it, and logging writes straight to the stream once the bar is closed."""
    import io
    import logging

    from colonyd.mapping import BarProgress

    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(logging.Formatter("%(levelname)s %(message)s"))
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        bar = BarProgress(stream, terminal=True)
        bar.update(3, 10)
        logging.getLogger("plugins.stream").warning("skipped bad frame 4: truncated")
        bar.drawn = 0.0
        bar.update(10, 10)
        bar.close()
        logging.getLogger("plugins.stream").warning("after the bar")
    finally:
        root.removeHandler(handler)
    lines = _rendered(stream.getvalue())
    assert "WARNING skipped bad frame 4: truncated" in lines, lines
    assert lines[-2] == "WARNING after the bar" and lines[-1] == ""
    assert any(line.startswith("[###") and "10/10 frames" in line for line in lines), lines
    assert handler.stream is stream


def test_progress_in_a_log_is_whole_lines_every_ten_seconds() -> None:
    """Not a terminal (a log file, CI): no carriage returns, a line every 10 s and at the end."""
    import io

    from colonyd.mapping import BarProgress

    stream = io.StringIO()
    bar = BarProgress(stream)  # StringIO is no terminal
    for done in range(1, 11):
        bar.update(done, 10)  # within 10 s: the first and the last frame only
    bar.close()
    text = stream.getvalue()
    assert "\r" not in text
    lines = text.splitlines()
    assert len(lines) == 2 and lines[0].startswith("[###...") and "10/10 frames" in lines[1], lines


def test_colonyd_map_reports_frames_per_second_and_where_time_went(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from colonyd.cli import main

    code = main(
        ["map", "--source", "synthetic:scans=4,rate=1000,points=90", "--out", str(tmp_path)]
    )
    out = capsys.readouterr().out
    assert code == 0
    # the rate counts reading and integrating only (files, start-up not): the line says so, as
    # "1198 frames ... in 20.8 s (81.0 frames/s)" read as a sum that did not add up
    assert re.search(r"4 frames .* \(\d+\.\d frames/s read and integrated\)", out)
    line = next(x for x in out.splitlines() if x.startswith("time: "))
    for part in ("decode", "integrate", "write", "other"):
        assert re.search(rf"{part} \d+\.\d\d s", line), line
    summary = map_source("synthetic:scans=3,rate=1000,points=90", 0.1, tmp_path, progress=False)
    assert set(summary.breakdown) == {"decode", "integrate", "write"}
    assert all(sec > 0 for sec in summary.breakdown.values())
    assert summary.frames_per_second > 0
    assert sum(summary.breakdown.values()) <= summary.seconds


def test_floor_plan_yaml_origin_is_written_as_the_metres_it_means(tmp_path: Path) -> None:
    """map_server reads the origin in metres: -41 cells of 0.1 m: -4.1, not -4.1000000000000005."""
    from colonyd.mapping import write_floor_plan

    occupied = np.array([[-11, -41, 0], [5, 3, 0]])
    write_floor_plan(tmp_path, occupied, np.empty((0, 3), np.int64), 0, 0.1)
    text = (tmp_path / "floorplan.yaml").read_text()
    assert "origin: [-1.1, -4.1, 0.0]\n" in text, text
