"""Replay of real recordings: picks the reader (CARMEN log, 7-Scenes/TUM RGB-D folder, ROS bag) for a path."""

from __future__ import annotations

import gzip
from pathlib import Path
from typing import Any

from plugins.carmen import CarmenSource
from plugins.errors import SourceError, SourceSpecError
from plugins.sevenscenes import RgbdSource
from plugins.stream import Source

FORMATS = ("carmen", "7scenes", "tum", "rosbag")


def detect_format(path: Path) -> str:
    """The recording format of `path`: carmen, 7scenes, tum or rosbag."""
    if path.is_dir():
        if (path / "metadata.yaml").is_file() or any(path.glob("*.db3")) or any(path.glob("*.mcap")):
            return "rosbag"
        if (path / "depth.txt").is_file():
            return "tum"
        if any(path.glob("frame-*.depth.png")) or any((path / "frames").glob("frame-*.depth.png")):
            return "7scenes"
        msg = f"{path}: expected a 7-Scenes folder (frame-*.depth.png), a TUM folder (depth.txt) or a ROS 2 bag (metadata.yaml), found none of them"
        raise SourceError(msg)
    if not path.is_file():
        msg = f"replay: expected a recording file or folder, found nothing at {path}"
        raise SourceError(msg)
    if path.suffix in (".bag", ".db3", ".mcap"):
        return "rosbag"
    opener = gzip.open if path.suffix == ".gz" else open
    try:
        with opener(path, "rt", encoding="ascii", errors="replace") as f:
            head = [f.readline() for _ in range(2000)]
    except (OSError, EOFError) as exc:
        msg = f"{path}: cannot read the start of the file: {exc}"
        raise SourceError(msg) from None
    if any(line.startswith(("FLASER", "ROBOTLASER1", "ODOM", "PARAM")) for line in head):
        return "carmen"
    msg = f"{path}: expected a CARMEN log (FLASER lines) or a ROS bag (.bag, .db3, .mcap), found neither"
    raise SourceError(msg)


def open_replay(path: str | Path, *, format: str = "auto", spec: str = "", **options: Any) -> Source:  # noqa: A002
    """A replay source for `path` with reader options (see each reader's parameters)."""
    path = Path(path)
    kind = detect_format(path) if format == "auto" else format
    if kind == "carmen":
        return CarmenSource(path, spec=spec, **options)
    if kind in ("7scenes", "tum"):
        return RgbdSource(path, layout=kind, spec=spec, **options)
    if kind == "rosbag":
        from plugins.rosbag import RosbagSource

        return RosbagSource(path, spec=spec, **options)
    msg = f"format: expected 'auto' or one of {list(FORMATS)}, found {format!r}"
    raise SourceSpecError(msg)
