"""RGB-D folders: Microsoft 7-Scenes (frame-NNNNNN.depth.png + pose.txt) and TUM RGB-D
(depth.txt + groundtruth.txt)."""

from __future__ import annotations

import bisect
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from pydantic import Field

from plugins.adapter import SensorAdapter, load_adapter
from plugins.checks import quaternion_to_matrix
from plugins.depth import DepthFrame
from plugins.errors import ParseError, SensorInputError, SourceError, SourceSpecError
from plugins.observation import Observation
from plugins.spec import Options
from plugins.stream import StreamStats

#: 7-Scenes' Kinect intrinsics, used when camera-intrinsics.txt is absent.
SEVEN_SCENES_K = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])
#: TUM RGB-D default intrinsics (ROS default) and depth scale (5000 units per metre).
TUM_K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class RgbdFrame:
    """One depth frame on disk with its reference pose (camera-to-world)."""

    depth: Path
    pose: np.ndarray | Path  # (4, 4) or a 7-Scenes pose file, read lazily
    time: float
    colour: Path | None = None


def read_matrix(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """A whitespace-separated numeric matrix file of `shape`; ParseError names the file and line."""
    try:
        text = path.read_text(encoding="ascii", errors="replace")
    except OSError as exc:
        msg = f"{path}: cannot read: {exc.strerror}"
        raise ParseError(msg) from None
    rows = [line.split() for line in text.splitlines() if line.strip()]
    if len(rows) != shape[0]:
        msg = f"{path}: expected {shape[0]} rows of {shape[1]} numbers, found {len(rows)} rows"
        raise ParseError(msg)
    for i, row in enumerate(rows, start=1):
        if len(row) != shape[1]:
            msg = f"{path}:{i}: expected {shape[1]} numbers, found {len(row)}"
            raise ParseError(msg)
        for j, token in enumerate(row, start=1):
            try:
                value = float(token)
            except ValueError:
                msg = f"{path}:{i}: field {j}: expected a number, found {token!r}"
                raise ParseError(msg) from None
            if not np.isfinite(value):
                msg = f"{path}:{i}: field {j}: expected a finite number, found {token!r}"
                raise ParseError(msg)
    return np.array(rows, dtype=np.float64)


def read_depth_png(path: Path) -> np.ndarray:
    """A 16-bit single-channel depth PNG; ParseError names the file when it is missing, truncated or
    not 16-bit."""
    if not path.is_file():
        msg = f"{path}: expected a depth image, found no file"
        raise ParseError(msg)
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        msg = f"{path}: expected a readable 16-bit PNG, found an unreadable or truncated file"
        raise ParseError(msg)
    if image.dtype != np.uint16 or image.ndim != 2:
        msg = (
            f"{path}: expected a single-channel uint16 depth image, "
            f"found {image.dtype} with shape {image.shape}"
        )
        raise ParseError(msg)
    return image


def read_colour(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """An RGB colour image (PNG or JPEG) of the depth image's size; ParseError names the file
    otherwise."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        msg = f"{path}: expected a readable colour image, found an unreadable or truncated file"
        raise ParseError(msg)
    if image.shape[:2] != tuple(shape):
        msg = (
            f"{path}: expected a colour image of the depth image's size {shape[1]}x{shape[0]}, "
            f"found {image.shape[1]}x{image.shape[0]}"
        )
        raise ParseError(msg)
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def seven_scenes_frames(root: Path) -> list[RgbdFrame]:
    """Frames of a 7-Scenes sequence folder (frames/ or the folder itself), in index order,
    30 Hz."""
    folder = root / "frames" if (root / "frames").is_dir() else root
    depths = sorted(folder.glob("frame-*.depth.png"))
    frames: list[RgbdFrame] = []
    for depth in depths:
        stem = depth.name[: -len(".depth.png")]
        try:
            index = int(stem.split("-", 1)[1])
        except ValueError:
            index = len(frames)
        colour = folder / f"{stem}.color.png"
        if not colour.is_file():
            colour = folder / f"{stem}.color.jpg"
        frames.append(
            RgbdFrame(
                depth=depth,
                pose=folder / f"{stem}.pose.txt",
                time=index / 30.0,
                colour=colour if colour.is_file() else None,
            )
        )
    return frames


def read_tum_list(path: Path) -> list[tuple[float, list[str]]]:
    """Rows (timestamp, other fields) of a TUM list file (# comments); ParseError names the line."""
    rows = []
    try:
        lines = path.read_text(encoding="ascii", errors="replace").splitlines()
    except OSError as exc:
        msg = f"{path}: cannot read: {exc.strerror}"
        raise ParseError(msg) from None
    for i, line in enumerate(lines, start=1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        try:
            stamp = float(fields[0])
        except ValueError:
            msg = f"{path}:{i}: field 1 (timestamp): expected a number, found {fields[0]!r}"
            raise ParseError(msg) from None
        rows.append((stamp, fields[1:]))
    return rows


def tum_frames(root: Path, max_dt: float = 0.02) -> list[RgbdFrame]:
    """Frames of a TUM RGB-D folder: depth.txt associated with groundtruth.txt by nearest
    timestamp."""
    depth_rows = read_tum_list(root / "depth.txt")
    truth = []
    for stamp, fields in read_tum_list(root / "groundtruth.txt"):
        if len(fields) != 7:
            msg = (
                f"{root / 'groundtruth.txt'}: at time {stamp}: "
                f"expected 'timestamp tx ty tz qx qy qz qw', found {len(fields) + 1} fields"
            )
            raise ParseError(msg)
        try:
            tx, ty, tz, qx, qy, qz, qw = (float(v) for v in fields)
        except ValueError:
            msg = f"{root / 'groundtruth.txt'}: at time {stamp}: expected numbers, found {fields}"
            raise ParseError(msg) from None
        pose = np.eye(4)
        pose[:3, :3] = quaternion_to_matrix(qx, qy, qz, qw)
        pose[:3, 3] = (tx, ty, tz)
        truth.append((stamp, pose))
    truth.sort(key=lambda row: row[0])
    stamps = [s for s, _ in truth]
    frames = []
    for stamp, fields in depth_rows:
        if not fields:
            msg = (
                f"{root / 'depth.txt'}: at time {stamp}: expected 'timestamp filename', "
                "found no filename"
            )
            raise ParseError(msg)
        i = bisect.bisect_left(stamps, stamp)
        best = min(
            (j for j in (i - 1, i) if 0 <= j < len(stamps)),
            key=lambda j: abs(stamps[j] - stamp),
            default=None,
        )
        if best is None or abs(stamps[best] - stamp) > max_dt:
            continue  # no reference pose close enough
        frames.append(RgbdFrame(depth=root / fields[0], pose=truth[best][1], time=stamp))
    return frames


class RgbdOptions(Options):
    """Options of `replay:` for a 7-Scenes or TUM RGB-D folder."""

    start: int = Field(0, description="first frame (index in time order)")
    stop: int | None = Field(None, description="frame index to stop before; none: the end")
    step: int = Field(1, description="take every step-th frame (>= 1)")
    stride: int = Field(1, description="take every stride-th pixel on each image axis")
    max_range: float = Field(10.0, description="depth range, metres; farther readings are dropped")
    strict: bool = Field(
        False, description="fail on the first bad frame instead of skipping and counting it"
    )


class RgbdSource:
    """Depth frames of a 7-Scenes or TUM RGB-D folder with their reference poses."""

    def __init__(
        self,
        root: str | Path,
        *,
        layout: str = "auto",
        start: int = 0,
        stop: int | None = None,
        step: int = 1,
        stride: int = 1,
        max_range: float = 10.0,
        strict: bool = False,
        spec: str = "",
    ) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            msg = f"rgb-d folder: expected a directory, found nothing at {self.root}"
            raise SourceError(msg)
        if layout == "auto":
            layout = "tum" if (self.root / "depth.txt").is_file() else "7scenes"
        if layout == "7scenes":
            frames = seven_scenes_frames(self.root)
            k_file = self.root / "camera-intrinsics.txt"
            K = read_matrix(k_file, (3, 3)) if k_file.is_file() else SEVEN_SCENES_K
            scale = 0.001
        elif layout == "tum":
            frames = tum_frames(self.root)
            K, scale = TUM_K, 1.0 / 5000.0
        else:
            msg = f"layout: expected 'auto', '7scenes' or 'tum', found {layout!r}"
            raise SourceSpecError(msg)
        if not frames:
            msg = f"{self.root}: expected depth frames ({layout} layout), found none"
            raise SourceError(msg)
        if step < 1 or start < 0:
            msg = f"start/step: expected start >= 0 and step >= 1, found {start}, {step}"
            raise SourceSpecError(msg)
        self.layout = layout
        self.frames = frames[start:stop:step]
        if not self.frames:  # an empty map, written as if it were one
            msg = (
                f"start/stop/step: expected a selection of at least one of the {len(frames)} "
                f"frames, found none (start {start}, stop {stop}, step {step})"
            )
            raise SourceSpecError(msg)
        self.strict = strict
        self.spec = spec or f"replay:{self.root}"
        self.adapter: SensorAdapter = load_adapter(
            "depth", K=K, depth_scale=scale, invalid=(0, 65535), max_range=max_range, stride=stride
        )
        self.stats = StreamStats()

    def __len__(self) -> int:
        return len(self.frames)

    def __iter__(self) -> Iterator[Observation]:
        for frame in self.frames:
            try:
                pose = (
                    read_matrix(frame.pose, (4, 4)) if isinstance(frame.pose, Path) else frame.pose
                )
                depth = read_depth_png(frame.depth)
                colour = (
                    read_colour(frame.colour, depth.shape) if frame.colour is not None else None
                )
                obs = self.adapter.observe(
                    DepthFrame(depth=depth, colour=colour),
                    pose=pose,
                    time=frame.time,
                    frame=str(frame.depth),
                )
            except (ParseError, SensorInputError) as exc:
                if self.strict:
                    raise
                self.stats.skip(str(frame.depth), exc)
                continue
            self.stats.delivered += 1
            yield obs
