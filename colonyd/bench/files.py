"""Where benchmarks find the shared recordings and how they write their JSON results."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np


def shared_data_dir(given: Path | None) -> Path | None:
    """`given`, else the checkout's sibling `../shared/data` when it exists, else None."""
    if given is not None:
        return Path(given)
    candidate = Path(__file__).resolve().parents[3] / "shared" / "data"
    return candidate if candidate.is_dir() else None


def room_and_carmen(
    shared_data: Path | None, sim_frames: int, carmen: tuple[str, str]
) -> list[tuple[str, str, float, str]]:
    """The history benches' scenarios (name, source spec, resolution, block shape): the sim
    room's depth camera for `sim_frames` frames, and the Freiburg 079 log as `carmen` (its
    scenario name, the replay options) when the shared data holds it."""
    scenarios = [
        ("sim-depth-room", f"sim:world=room,agent=depth-1,frames={sim_frames}", 0.1, "cube")
    ]
    data = shared_data_dir(shared_data)
    log = None if data is None else data / "carmen" / "freiburg-079-corrected.log.gz"
    if log is not None and log.is_file():
        scenarios.append((carmen[0], f"replay:{log},{carmen[1]}", 0.05, "planar"))
    return scenarios


def print_and_append(out: dict[str, Any], path: Path | None) -> None:
    """Print one result as a JSON line, and append it to `path` (when given): a harness's runs,
    one line each."""
    print(json.dumps(out))
    if path is not None:
        with path.open("a", encoding="ascii") as f:
            f.write(json.dumps(out) + "\n")


def write_results(out_json: Path, results: list[dict[str, Any]]) -> None:
    """Write a benchmark's result list as indented JSON, creating the folder."""
    out_json = Path(out_json)
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(results, indent=2) + "\n")


def redkitchen_depths(shared_data: Path) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The 7-Scenes redkitchen-50 frames of `shared_data`, in order: (depth in metres, 0 where
    the sensor gave none, intrinsics K (3, 3), reference pose camera-to-world (4, 4)).
    plugins.errors.ParseError names a file that is unreadable or not a 16-bit depth PNG."""
    from plugins.sevenscenes import (
        SEVEN_SCENES_K,
        read_depth_png,
        read_matrix,
        seven_scenes_frames,
    )

    for frame in seven_scenes_frames(shared_data / "redkitchen-50"):
        raw = read_depth_png(frame.depth).astype(np.float64)
        raw[(raw == 0) | (raw == 65535)] = 0
        pose = frame.pose if isinstance(frame.pose, np.ndarray) else read_matrix(frame.pose, (4, 4))
        yield raw / 1000.0, SEVEN_SCENES_K, pose
