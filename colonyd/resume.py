"""Where each recording source stopped, kept with the own layer's state so a restart resumes it."""

from __future__ import annotations

import errno
import hashlib
import logging
import math
import os
import stat
import threading
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from plugins.errors import SourceSpecError
from plugins.observation import Observation
from plugins.source import parse_spec
from plugins.stream import Source

log = logging.getLogger(__name__)

#: Version of the record (`encode`); another one is refused (its sources start afresh).
RECORD_VERSION = 1
#: The source kinds that resume: recordings. Live and time-driven kinds start anew.
RESUMED_KINDS = frozenset({"replay"})


@dataclass(frozen=True)
class EstimatorState:
    """What a scan estimator needs to continue in the same frame: its pose (x, y, yaw), that
    pose's 3x3 covariance, and the last odometry reading it predicted from (None: none)."""

    pose: np.ndarray
    covariance: np.ndarray
    odometry: np.ndarray | None


@dataclass(frozen=True)
class SourcePosition:
    """One recording's position: `frames` observations of it were integrated (or refused as bad
    frames) into the layer version this record is stored with, the last one named `frame`;
    `recording` identifies the file or folder read (`fingerprint`); `done`: it was read to its
    end."""

    spec: str
    recording: dict[str, int]
    frames: int
    frame: str
    done: bool
    estimator: EstimatorState | None = None


@dataclass(frozen=True)
class Decision:
    """How a source starts: after `frames` observations (0: afresh), or not at all (`done`),
    with the estimator state to restore and what to log (`message`, at `level`)."""

    frames: int
    done: bool
    estimator: EstimatorState | None
    message: str
    level: str  # "info", "warning" or "error"


def resumes(spec: str) -> bool:
    """Whether a source of this spec resumes after a restart (a recording: `replay:`)."""
    try:
        return parse_spec(spec).kind in RESUMED_KINDS
    except SourceSpecError:
        return False


#: The `fingerprint` key holding the hash of the recording's content. A stored fingerprint
#: without it was written by an older colonyd, by size and modification time (`stat_fingerprint`).
CONTENT = "sha256"


def fingerprint(spec: str) -> dict[str, int]:
    """What identifies the recording a `replay:` spec reads, by content: its size and the first
    64 bits of the SHA-256 of its bytes (a folder's: its files' count and total size, and the
    SHA-256 over every file below it in the order of their relative names, of each name, size
    and bytes' SHA-256; a file it may not read is left out, see `_files_below` for the rest);
    {} when it cannot be read. Times are left out: a recording touched, or copied without
    keeping them, is the same recording."""
    path = parse_spec(spec).path
    if path is None:
        return {}
    p = Path(path).expanduser()
    try:
        if not p.is_dir():
            size, digest = _hash_file(p)
            return {"size": size, CONTENT: _as_int(digest)}
        folder = hashlib.sha256()
        count = total = 0
        for name, f in sorted(_files_below(p)):
            try:
                size, digest = _hash_file(f)
            except (FileNotFoundError, PermissionError):  # removed since it was listed, or
                continue  # not ours to read (nor the reader's): not part of what is replayed
            folder.update(b"%d:%s:%d:%s" % (len(name), name, size, digest))
            count, total = count + 1, total + size
    except OSError:
        return {}
    return {"files": count, "size": total, CONTENT: _as_int(folder.digest())}


def _files_below(root: Path) -> list[tuple[bytes, str]]:
    """Every regular file below the folder `root` (symbolic links followed), by its relative
    name as the system keeps it (bytes: any name, UTF-8 or not). A link to a folder that holds
    it (`latest -> .`) is not walked again: followed, it made the walk endless. What is not a
    regular file (a dangling link, a named pipe, a device) holds no bytes of the recording and
    is left out: a pipe's reading waits for a writer for good. A folder that cannot be listed
    below `root` is left out, as `os.walk` left it; OSError when `root` cannot be listed."""
    top = os.stat(root)
    found: list[tuple[bytes, str]] = []
    stack = [(os.fspath(root), b"", frozenset({(top.st_dev, top.st_ino)}))]
    while stack:
        folder, prefix, above = stack.pop()
        try:
            with os.scandir(folder) as listing:
                entries = list(listing)
        except OSError:
            if folder == os.fspath(root):
                raise
            continue
        for entry in entries:
            try:
                st = entry.stat()  # through links
            except OSError as exc:
                if exc.errno in (errno.ENOENT, errno.ELOOP):  # dangling, or removed meanwhile
                    continue
                raise
            name = prefix + os.fsencode(entry.name)
            if stat.S_ISDIR(st.st_mode):
                key = (st.st_dev, st.st_ino)
                if key not in above:  # else a link back up: walked already
                    stack.append((entry.path, name + b"/", above | {key}))
            elif stat.S_ISREG(st.st_mode):
                found.append((name, entry.path))
    return found


def _hash_file(path: str | Path) -> tuple[int, bytes]:
    """A file's size (the bytes read) and their SHA-256."""
    digest = hashlib.sha256()
    size = 0
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            digest.update(chunk)
            size += len(chunk)
    return size, digest.digest()


def _as_int(digest: bytes) -> int:
    return int.from_bytes(digest[:8], "big")


def stored_by_older(recording: Mapping[str, int]) -> bool:
    """A stored fingerprint written by an older colonyd (by size and time, no `CONTENT`); {}
    is not one: the recording could not be read when it was stored."""
    return bool(recording) and CONTENT not in recording


def stat_fingerprint(spec: str) -> dict[str, int]:
    """The fingerprint an older colonyd stored, by size and modification time (a folder's: its
    top-level entries' count, summed size and latest time); {} when it cannot be read. Only
    compared with a stored fingerprint that has no `CONTENT`."""
    path = parse_spec(spec).path
    if path is None:
        return {}
    p = Path(path).expanduser()
    try:
        if p.is_dir():
            stats = [entry.stat() for entry in os.scandir(p)]
            return {
                "files": len(stats),
                "size": sum(s.st_size for s in stats),
                "mtime_ns": max((s.st_mtime_ns for s in stats), default=0),
            }
        s = p.stat()
    except OSError:
        return {}
    return {"size": s.st_size, "mtime_ns": s.st_mtime_ns}


# -------------------------------------------------------------------------- the stored record


def encode(positions: Mapping[str, SourcePosition]) -> dict[str, Any]:
    """The record of every source's position (plain values: JSON and msgpack both carry it)."""
    return {
        "v": RECORD_VERSION,
        "sources": {spec: _encode_one(p) for spec, p in positions.items()},
    }


def _encode_one(p: SourcePosition) -> dict[str, Any]:
    out: dict[str, Any] = {
        "recording": dict(p.recording),
        "frames": int(p.frames),
        "frame": p.frame,
        "done": bool(p.done),
        "estimator": None,
    }
    if p.estimator is not None:
        e = p.estimator
        out["estimator"] = {
            "pose": [float(x) for x in e.pose],
            "covariance": [[float(x) for x in row] for row in e.covariance],
            "odometry": None if e.odometry is None else [float(x) for x in e.odometry],
        }
    return out


def decode(raw: Any) -> tuple[dict[str, SourcePosition], dict[str, str]]:
    """The positions of a stored record, and per spec why its entry was refused ("*": the
    whole record). None (nothing stored) is no position and no error."""
    if raw is None:
        return {}, {}
    if not isinstance(raw, dict):
        return {}, {"*": f"expected a map of source positions, found {type(raw).__name__}"}
    if raw.get("v") != RECORD_VERSION:
        return {}, {"*": f"expected record version {RECORD_VERSION}, found {raw.get('v')!r}"}
    sources = raw.get("sources")
    if not isinstance(sources, dict):
        found = type(sources).__name__
        return {}, {"*": f"expected 'sources' to be a map of spec to position, found {found}"}
    good: dict[str, SourcePosition] = {}
    bad: dict[str, str] = {}
    for spec, entry in sources.items():
        try:
            good[str(spec)] = _decode_one(str(spec), entry)
        except ValueError as exc:
            bad[str(spec)] = str(exc)
    return good, bad


def _decode_one(spec: str, entry: Any) -> SourcePosition:
    if not isinstance(entry, dict):
        raise ValueError(f"expected a map, found {type(entry).__name__}")
    recording = entry.get("recording")
    if not isinstance(recording, dict) or not all(
        isinstance(k, str) and _is_int(v) and v >= 0 for k, v in recording.items()
    ):
        raise ValueError(f"'recording': expected a map of name to count >= 0, found {recording!r}")
    frames: Any = entry.get("frames")
    if not _is_int(frames) or frames < 0:
        raise ValueError(f"'frames': expected a whole number >= 0, found {frames!r}")
    frame = entry.get("frame")
    if not isinstance(frame, str):
        raise ValueError(f"'frame': expected the last frame's name (text), found {frame!r}")
    done = entry.get("done")
    if not isinstance(done, bool):
        raise ValueError(f"'done': expected true or false, found {done!r}")
    raw = entry.get("estimator")
    estimator = None if raw is None else _decode_estimator(raw)
    return SourcePosition(spec, dict(recording), int(frames), frame, done, estimator)


def _decode_estimator(raw: Any) -> EstimatorState:
    if not isinstance(raw, dict):
        raise ValueError(f"'estimator': expected a map or null, found {type(raw).__name__}")
    pose = _finite(raw.get("pose"), (3,), "estimator pose (x, y, yaw)")
    cov = _finite(raw.get("covariance"), (3, 3), "estimator covariance (3x3)")
    if not np.allclose(cov, cov.T, atol=1e-9 * max(1.0, float(np.abs(cov).max()))) or np.any(
        np.linalg.eigvalsh((cov + cov.T) / 2) < -1e-12
    ):
        raise ValueError(f"estimator covariance: expected symmetric and >= 0, found {cov.tolist()}")
    odo = raw.get("odometry")
    odometry = None if odo is None else _finite(odo, (3,), "estimator odometry (x, y, yaw)")
    return EstimatorState(pose, cov, odometry)


def _finite(value: Any, shape: tuple[int, ...], what: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        arr = None
    if arr is None or arr.shape != shape or not np.all(np.isfinite(arr)):
        raise ValueError(f"{what}: expected {math.prod(shape)} finite numbers, found {value!r}")
    return arr


def _path_of(spec: str) -> str | None:
    try:
        return parse_spec(spec).path
    except SourceSpecError:
        return None


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


# -------------------------------------------------------------------------- the decision


def decide(
    spec: str,
    recording: dict[str, int],
    stored: Mapping[str, SourcePosition],
    refused: Mapping[str, str],
) -> Decision:
    """How the source `spec` (reading `recording`, its `fingerprint` now, or its
    `stat_fingerprint` when the stored one has no `CONTENT`) starts, given the positions
    recovered with the layer (`stored`) and the entries refused (`refused`, by spec; "*": the
    whole record)."""
    why = refused.get(spec) or refused.get("*")
    if why:
        return Decision(
            0,
            False,
            None,
            f"source {spec}: its stored position is unusable ({why}); it starts afresh from "
            "its first frame (its evidence already in the layer is kept, and counted again)",
            "error",
        )
    mine = stored.get(spec)
    if mine is None:
        path = _path_of(spec)
        others = [s for s in stored if s != spec and _path_of(s) == path]
        if others:
            return Decision(
                0,
                False,
                None,
                f"source {spec}: the spec changed (the layer holds {others[0]}'s frames); "
                "a changed spec is another recording: it starts afresh from its first frame",
                "warning",
            )
        return Decision(0, False, None, f"source {spec}: starts from its first frame", "info")
    if mine.recording != recording:
        older = (
            " (a position stored by an older colonyd, which knew a recording by its size "
            "and modification time)"
            if stored_by_older(mine.recording)
            else " (it could not be read when the position was stored)"
            if not mine.recording
            else ""
        )
        return Decision(
            0,
            False,
            None,
            f"source {spec}: the recording changed since its position was stored (expected "
            f"{mine.recording}, found {recording}){older}; it starts afresh from its first frame",
            "warning",
        )
    if mine.done:
        return Decision(
            mine.frames,
            True,
            None,
            f"source {spec}: already read to its end ({mine.frames} frames in the layer); "
            "not read again",
            "info",
        )
    if mine.frames == 0:
        return Decision(0, False, None, f"source {spec}: starts from its first frame", "info")
    return Decision(
        mine.frames,
        False,
        mine.estimator,
        f"source {spec}: resumes after frame {mine.frames} ({mine.frame}), the last whose "
        f"evidence is in the layer: frames 1 to {mine.frames} are passed over, not integrated",
        "info",
    )


# -------------------------------------------------------------------------- the daemon's tracker


class Positions:
    """The daemon's record of its recordings' positions, as of the own grid's version.

    `advance` is called with the layer's lock held, right after a frame's evidence went into the
    grid, and `record` with it held, where the grid's version is read for a delta or a snapshot:
    the record stored with a grid version names exactly the frames whose evidence that version
    holds. Positions recovered for configured sources are carried until each source starts.
    """

    def __init__(self, raw: Any, specs: list[str]) -> None:
        self.stored, self.refused = decode(raw)
        for spec, why in sorted(self.refused.items()):
            where = "the whole record" if spec == "*" else f"source {spec}"
            log.error(
                "stored source positions: %s refused: %s; the sources concerned start afresh",
                where,
                why,
            )
        self._lock = threading.Lock()
        self._specs = frozenset(specs)
        self._now = {s: p for s, p in self.stored.items() if s in specs and resumes(s)}
        self._restore: dict[str, EstimatorState] = {}
        self._recording: dict[str, dict[str, int]] = {}  # per started recording: `fingerprint`
        #: Per spec: frames passed over at start (already in the layer), for the status report.
        self.resumed: dict[str, int] = {}

    def start(
        self,
        source: Source,
        stop: threading.Event,
        pass_over: Callable[[Observation], None] | None = None,
    ) -> Iterator[Observation] | None:
        """The source's frames from where the layer's evidence of it ends (None: nothing to
        read, a recording already read to its end); each frame passed over on the way is given
        to `pass_over` (the estimator steps through it again). A source that does not resume is
        iterated from its start; one whose stored position does not match the recording (the
        frame named is not there) is logged and read afresh."""
        spec = source.spec
        if not resumes(spec):
            return iter(source)
        recording = self._recording[spec] = fingerprint(spec)
        # another configured source's position is its own, not an older spec of this one
        candidates = {s: p for s, p in self.stored.items() if s == spec or s not in self._specs}
        mine = candidates.get(spec)
        old = mine is not None and stored_by_older(mine.recording)
        decision = decide(
            spec, stat_fingerprint(spec) if old else recording, candidates, self.refused
        )
        getattr(log, decision.level)("%s", decision.message)
        stored = self.stored.get(spec)
        if stored is not None:  # kept from now on with the recording's fingerprint by content
            stored = replace(stored, recording=recording)
        if decision.done and stored is not None:
            self.resumed[spec] = stored.frames
            with self._lock:
                self._now[spec] = stored
            return None
        frames = iter(source)
        if decision.frames == 0 or stored is None:
            self.advance(spec, 0, "", None)
            return frames
        passed, last = 0, ""
        for obs in frames:
            passed, last = passed + 1, obs.frame
            if pass_over is not None:
                pass_over(obs)
            if passed == decision.frames or stop.is_set():
                break
        if stop.is_set():
            return None
        if passed != decision.frames or last != stored.frame:
            found = (
                f"frame {passed} is {last!r}"
                if passed == decision.frames
                else (f"the recording ends after {passed} frames")
            )
            log.error(
                "source %s: its stored position does not match the recording (expected frame "
                "%d to be %r, found %s); it starts afresh from its first frame (its evidence "
                "already in the layer is kept, and counted again)",
                spec,
                decision.frames,
                stored.frame,
                found,
            )
            self.advance(spec, 0, "", None)
            return iter(source)
        if decision.estimator is not None:
            self._restore[spec] = decision.estimator
        self.resumed[spec] = passed
        with self._lock:
            self._now[spec] = stored
        return frames

    def restored(self, spec: str) -> EstimatorState | None:
        """The estimator state stored with a resumed source's position (once)."""
        return self._restore.pop(spec, None)

    def position(self, spec: str) -> SourcePosition | None:
        """The source's current position (None: not a recording, or not started)."""
        with self._lock:
            return self._now.get(spec)

    def tracks(self, spec: str) -> bool:
        """Whether the source `spec` is a started recording whose position is kept."""
        return spec in self._recording

    def advance(self, spec: str, frames: int, frame: str, estimator: EstimatorState | None) -> None:
        """Set a started recording's position: `frames` observations of it are in the grid,
        the last named `frame` (call with the layer's lock held, right after its evidence went
        in); other sources are not tracked."""
        recording = self._recording.get(spec)
        if recording is None:
            return
        with self._lock:
            self._now[spec] = SourcePosition(spec, recording, frames, frame, False, estimator)

    def finished(self, spec: str) -> None:
        """The source was read to its end: not read again after a restart."""
        with self._lock:
            p = self._now.get(spec)
            if p is not None:
                self._now[spec] = replace(p, done=True)

    def record(self) -> dict[str, Any]:
        """The record to store with the grid's current version (call with the layer's lock
        held)."""
        with self._lock:
            return encode(self._now)


def agrees(
    a: EstimatorState, b: EstimatorState, metres: float = 1e-3, radians: float = 1e-3
) -> bool:
    """Whether two estimator states put the sensor at the same pose (within `metres` and
    `radians`)."""
    d = a.pose - b.pose
    yaw = math.atan2(math.sin(float(d[2])), math.cos(float(d[2])))
    return bool(math.hypot(float(d[0]), float(d[1])) <= metres and abs(yaw) <= radians)
