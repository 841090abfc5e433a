"""CARMEN laser logs: FLASER lines (360 beams over 180 degrees) with reference and odometry
poses."""

from __future__ import annotations

import gzip
import math
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import Field

from plugins.adapter import SensorAdapter, load_adapter
from plugins.checks import pose_matrix
from plugins.errors import ParseError, SourceError, SourceSpecError
from plugins.lidar import Scan
from plugins.observation import Observation
from plugins.odometry import odometry_noise_of
from plugins.spec import Options
from plugins.stream import StreamStats
from voxel.localisation.odometry import WheelOdometer

#: Readings at or beyond this range are "no return" in CARMEN logs.
NO_RETURN = 80.0


@dataclass(frozen=True)
class FlaserRecord:
    """One FLASER line."""

    ranges: np.ndarray  # (n,)
    pose: tuple[float, float, float]  # laser pose x, y, theta (reference)
    odometry: tuple[float, float, float]
    time: float  # ipc timestamp, seconds
    line: int


def parse_flaser(text: str, path: str | Path, line: int) -> FlaserRecord:
    """Parse one FLASER line; ParseError names the file, line and field on failure."""
    fields = text.split()
    where = f"{path}:{line}"
    if not fields or fields[0] != "FLASER":
        msg = (
            f"{where}: expected a FLASER record, found {fields[0] if fields else 'an empty line'!r}"
        )
        raise ParseError(msg)
    try:
        n = int(fields[1])
    except (IndexError, ValueError):
        msg = (
            f"{where}: field 2 (beam count): expected an integer, found "
            f"{fields[1] if len(fields) > 1 else 'end of line'!r}"
        )
        raise ParseError(msg) from None
    if n <= 0 or n > 100000:
        msg = f"{where}: field 2 (beam count): expected 1..100000 beams, found {n}"
        raise ParseError(msg)
    want = 2 + n + 6 + 3
    if len(fields) < want:
        msg = (
            f"{where}: expected {want} fields for {n} beams (ranges, x y theta, odom x y theta, "
            f"ipc_timestamp hostname logger_timestamp), found {len(fields)}"
        )
        raise ParseError(msg)
    try:
        values = np.array(fields[2 : 2 + n + 7], dtype=np.float64)
    except ValueError:
        for i, token in enumerate(fields[2 : 2 + n + 7]):
            try:
                float(token)
            except ValueError:
                name = (
                    f"range {i + 1}"
                    if i < n
                    else ["x", "y", "theta", "odom_x", "odom_y", "odom_theta", "ipc_timestamp"][
                        i - n
                    ]
                )
                msg = f"{where}: field {i + 3} ({name}): expected a number, found {token!r}"
                raise ParseError(msg) from None
        raise
    if not np.all(np.isfinite(values)):
        i = int(np.flatnonzero(~np.isfinite(values))[0])
        name = (
            f"range {i + 1}"
            if i < n
            else ["x", "y", "theta", "odom_x", "odom_y", "odom_theta", "ipc_timestamp"][i - n]
        )
        msg = f"{where}: field {i + 3} ({name}): expected a finite number, found {fields[2 + i]!r}"
        raise ParseError(msg)
    ranges = values[:n]
    if np.any(ranges < 0):
        i = int(np.flatnonzero(ranges < 0)[0])
        msg = (
            f"{where}: field {i + 3} (range {i + 1}): expected a non-negative range, "
            f"found {fields[2 + i]!r}"
        )
        raise ParseError(msg)
    x, y, th, ox, oy, oth, stamp = values[n:]
    return FlaserRecord(
        ranges=ranges, pose=(x, y, th), odometry=(ox, oy, oth), time=float(stamp), line=line
    )


#: The longest line a CARMEN log may have (a FLASER line of 1081 beams is ~10 KB): a file without
#: line breaks is refused at this length, not read whole into memory.
MAX_LINE = 1 << 20


def read_lines(path: Path) -> Iterator[tuple[int, str]]:
    """(line number, text) of a plain or gzipped text file; a truncated gzip raises SourceError at
    the end, a line longer than `MAX_LINE` characters where it is found."""
    opener = gzip.open if path.suffix == ".gz" else open
    lineno = 0
    try:
        with opener(path, "rt", encoding="ascii", errors="replace") as f:
            while text := f.readline(MAX_LINE + 1):
                lineno += 1
                if len(text) > MAX_LINE:
                    msg = (
                        f"{path}: line {lineno}: expected a line of at most {MAX_LINE} "
                        "characters (a CARMEN record), found a longer one: not a CARMEN log?"
                    )
                    raise SourceError(msg)
                yield lineno, text
    except (EOFError, zlib.error, gzip.BadGzipFile) as exc:
        msg = (
            f"{path}: truncated or corrupt after line {lineno}: expected a complete gzip stream, "
            f"found {exc}"
        )
        raise SourceError(msg) from None


class CarmenOptions(Options):
    """Options of `replay:` for a CARMEN log."""

    poses: str = Field(
        "reference", description="pose of each scan: reference (the corrected pose) or odometry"
    )
    max_range: float = Field(
        NO_RETURN, description="sensor range, metres; readings at 80 m or more are no-return beams"
    )
    free_range: float = Field(
        0.0,
        description="how far a beam without a return clears free space, metres "
        "(0: the lidar2d default, 10 m)",
    )
    start: int = Field(0, description="first scan (index among FLASER lines)")
    stop: int | None = Field(None, description="scan index to stop before; none: the end")
    step: int = Field(1, description="take every step-th scan (>= 1)")
    strict: bool = Field(
        False, description="fail on the first bad line instead of skipping and counting it"
    )
    odometry_noise: str | None = Field(
        None,
        description="replace the log's odometry by odometry synthesised "
        "from the reference poses with this wheel noise model: none, low, "
        "realistic, high or trans/rot/rot_per_m/scale_bias/yaw_bias "
        "(docs/LOCALISATION.md); default: the log's own odometry",
    )
    seed: int = Field(0, description="seed of the synthesised odometry noise")
    move_x: float = Field(
        0.0,
        description="moves every scan pose and the odometry: x shift, metres (after the "
        "rotation move_yaw)",
    )
    move_y: float = Field(
        0.0, description="moves every scan pose and the odometry: y shift, metres"
    )
    move_yaw: float = Field(
        0.0,
        description="moves every scan pose and the odometry: rotation about z through the "
        "origin, degrees (then the shift)",
    )


class CarmenSource:
    """Scans of a CARMEN log as 2D LiDAR observations (sensor plane at z = 0).

    poses: "reference" (the corrected x y theta) or "odometry"; bad lines are skipped and counted
    unless strict; start/stop/step select scans by index; move_x/move_y/move_yaw (degrees) move
    every delivered pose and odometry reading by one rigid transform, as if the robot had started
    elsewhere (an estimator starts from the first odometry reading: moving the poses alone left a
    localised agent's map where it was).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        poses: str = "reference",
        max_range: float = NO_RETURN,
        free_range: float = 0.0,
        start: int = 0,
        stop: int | None = None,
        step: int = 1,
        strict: bool = False,
        move_x: float = 0.0,
        move_y: float = 0.0,
        move_yaw: float = 0.0,
        odometry_noise: str | None = None,
        seed: int = 0,
        spec: str = "",
    ) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            msg = f"carmen log: expected a file, found nothing at {self.path}"
            raise SourceError(msg)
        if poses not in ("reference", "odometry"):
            msg = f"poses: expected 'reference' or 'odometry', found {poses!r}"
            raise SourceSpecError(msg)
        if step < 1 or start < 0:
            msg = f"start/step: expected start >= 0 and step >= 1, found {start}, {step}"
            raise SourceSpecError(msg)
        if stop is not None and stop <= start:  # no scan at all: an empty map
            msg = f"start/stop: expected stop > start, found start {start}, stop {stop}"
            raise SourceSpecError(msg)
        self.poses, self.start, self.stop, self.step, self.strict = poses, start, stop, step, strict
        for name, value in (("move_x", move_x), ("move_y", move_y), ("move_yaw", move_yaw)):
            if not math.isfinite(value):
                msg = f"{name}: expected a finite number, found {value!r}"
                raise SourceSpecError(msg)
        self.move = pose_matrix(move_x, move_y, 0.0, math.radians(move_yaw))
        self.noise = odometry_noise_of(odometry_noise)
        self.seed = seed
        self.spec = spec or f"replay:{self.path}"
        self.adapter: SensorAdapter = load_adapter(
            "lidar2d",
            beams=None,
            angle_min=-math.pi / 2,
            angle_increment=math.pi / 360,
            range_max=max_range,
            no_return_range=NO_RETURN,
            free_range=free_range,
        )
        self.stats = StreamStats()
        self._count: int | None = None

    def __len__(self) -> int:
        if self._count is None:
            total = 0
            try:
                for _, text in read_lines(self.path):
                    total += text.startswith("FLASER")
            except SourceError:
                pass  # counted when the scans are read
            self._count = len(
                range(self.start, total if self.stop is None else min(self.stop, total), self.step)
            )
        return self._count

    def records(self) -> Iterator[FlaserRecord]:
        """Selected FLASER records; bad lines skipped and counted (raised when strict)."""
        index = -1
        try:
            for lineno, text in read_lines(self.path):
                if not text.startswith("FLASER"):
                    continue
                index += 1
                if self.stop is not None and index >= self.stop:
                    return
                if index < self.start or (index - self.start) % self.step:
                    continue
                try:
                    yield parse_flaser(text, self.path, lineno)
                except ParseError as exc:
                    if self.strict:
                        raise
                    self.stats.skip(f"{self.path}:{lineno}", exc)
        except SourceError as exc:
            if self.strict:
                raise
            self.stats.skip(str(self.path), exc)

    def __iter__(self) -> Iterator[Observation]:
        odometer = None
        for record in self.records():
            x, y, th = record.pose if self.poses == "reference" else record.odometry
            ox, oy, oth = record.odometry
            if self.noise is not None:
                odometer = odometer or WheelOdometer(np.array(record.pose), self.noise, self.seed)
                ox, oy, oth = odometer.step(np.array(record.pose))
            obs = self.adapter.observe(
                Scan(
                    ranges=record.ranges,
                    angle_min=-math.pi / 2,
                    angle_increment=math.pi / len(record.ranges),
                ),
                pose=self.move @ pose_matrix(x, y, 0.0, th),
                time=record.time,
                odometry=self.move @ pose_matrix(ox, oy, 0.0, oth),
                frame=f"{self.path}:{record.line}",
            )
            self.stats.delivered += 1
            yield obs
