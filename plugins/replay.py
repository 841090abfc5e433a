"""Replay of real recordings: picks the reader (CARMEN log, 7-Scenes/TUM RGB-D folder, ROS bag) for
a path."""

from __future__ import annotations

import gzip
from pathlib import Path
from typing import Literal

from pydantic import Field

from plugins.carmen import MAX_LINE, CarmenOptions, CarmenSource
from plugins.errors import SourceError
from plugins.rosbag import RosbagOptions, RosbagSource
from plugins.sevenscenes import RgbdOptions, RgbdSource
from plugins.spec import Options, SourceSpec, parse_options
from plugins.stream import Source, SourceContext

#: Names of recordings that are one file (CARMEN logs, ROS 1 and ROS 2 bag files).
RECORDING_FILES = (".log", ".log.gz", ".clf", ".bag", ".db3", ".mcap")


def detect_format(path: Path) -> str:
    """The recording format of `path`: carmen, 7scenes, tum or rosbag."""
    if path.is_dir():
        if (
            (path / "metadata.yaml").is_file()
            or any(path.glob("*.db3"))
            or any(path.glob("*.mcap"))
        ):
            return "rosbag"
        if (path / "depth.txt").is_file():
            return "tum"
        if any(path.glob("frame-*.depth.png")) or any((path / "frames").glob("frame-*.depth.png")):
            return "7scenes"
        msg = (
            f"{path}: expected a 7-Scenes folder (frame-*.depth.png), a TUM folder (depth.txt) or "
            "a ROS 2 bag (metadata.yaml), found none of them"
        )
        inside = sorted(
            q.name for q in path.iterdir() if q.is_file() and q.name.endswith(RECORDING_FILES)
        )
        if inside:  # a log or bag file in the folder: replay takes the file itself
            first = path / inside[0]
            msg += f"; it holds {', '.join(inside[:3])}: give the file's path (replay:{first})"
        raise SourceError(msg)
    if not path.is_file():
        msg = f"replay: expected a recording file or folder, found nothing at {path}"
        raise SourceError(msg)
    if path.suffix in (".bag", ".db3", ".mcap"):
        return "rosbag"
    opener = gzip.open if path.suffix == ".gz" else open
    try:
        with opener(path, "rt", encoding="ascii", errors="replace") as f:
            for _ in range(2000):  # its first lines, each at most MAX_LINE characters
                line = f.readline(MAX_LINE + 1)
                if not line or len(line) > MAX_LINE:
                    break
                if line.startswith(("FLASER", "ROBOTLASER1", "ODOM", "PARAM")):
                    return "carmen"
    except (OSError, EOFError) as exc:
        msg = f"{path}: cannot read the start of the file: {exc}"
        raise SourceError(msg) from None
    msg = (
        f"{path}: expected a CARMEN log (FLASER lines) or a ROS bag (.bag, .db3, .mcap), "
        "found neither"
    )
    raise SourceError(msg)


class ReplayOptions(Options):
    """Options of `replay:` whatever the recording."""

    format: Literal["auto", "carmen", "7scenes", "tum", "rosbag"] = Field(
        "auto",
        description=(
            "recording format; auto: from the path (folder contents, file suffix, first lines)"
        ),
    )


class CarmenReplay(ReplayOptions, CarmenOptions):
    """Options of `replay:` for a CARMEN log, format included."""


class RgbdReplay(ReplayOptions, RgbdOptions):
    """Options of `replay:` for a 7-Scenes or TUM RGB-D folder, format included."""


class RosbagReplay(ReplayOptions, RosbagOptions):
    """Options of `replay:` for a ROS bag, format included."""


def open_replay(spec: SourceSpec, context: SourceContext) -> Source:
    """The replay source of a parsed `replay:PATH,...` spec: the reader of the path's format."""
    chosen = {k: v for k, v in spec.options.items() if k == "format"}
    fmt = parse_options(ReplayOptions, chosen, spec.text).format
    path = Path(str(spec.path)).expanduser()
    kind = detect_format(path) if fmt == "auto" else fmt
    if kind == "carmen":
        carmen = parse_options(CarmenReplay, spec.options, spec.text)
        return CarmenSource(path, spec=spec.text, **carmen.model_dump(exclude={"format"}))
    if kind in ("7scenes", "tum"):
        rgbd = parse_options(RgbdReplay, spec.options, spec.text)
        return RgbdSource(path, layout=kind, spec=spec.text, **rgbd.model_dump(exclude={"format"}))
    bag = parse_options(RosbagReplay, spec.options, spec.text)
    return RosbagSource(path, spec=spec.text, **bag.model_dump(exclude={"format"}))
