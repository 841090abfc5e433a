"""State directory: write-ahead log of own deltas plus periodic snapshots, replaced atomically."""

from __future__ import annotations

import fcntl
import json
import logging
import os
import struct
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import math

import msgpack
import numpy as np

from colonyd.errors import PersistenceError
from colonyd.grid import VoxelGrid, load_grid, new_grid
from voxel.delta import Delta, channel_spec

log = logging.getLogger(__name__)

_HEAD = struct.Struct("<II")  # length, crc32
META = "meta.json"
SNAPSHOT = "snapshot.json"
WAL = "wal.log"
FRAMES = "frames.json"


@dataclass
class Recovered:
    """What a daemon restarts from."""

    epoch: int
    seq: int
    grid: VoxelGrid
    wal_records: int
    fresh: bool
    published: int  # grid version up to which changes were logged (and so may have been sent)
    frame_seq: int = 0  # first protocol frame number this run may use (reserved by the last run)


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    _fsync_dir(path.parent)


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class StateStore:
    """Own layer on disk: `meta.json`, `snapshot.json` + grid file, and `wal.log`."""

    def __init__(self, state_dir: Path, agent_id: str, resolution: float, block_shape: str = "cube") -> None:
        self.dir = Path(state_dir)
        self.agent_id = agent_id
        self.resolution = resolution
        self.block_shape = block_shape
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
            self._lock_fd = os.open(self.dir / "lock", os.O_RDWR | os.O_CREAT, 0o600)
        except OSError as exc:
            msg = f"state directory {self.dir} is not writable: {exc.strerror}"
            raise PersistenceError(msg) from None
        try:
            fcntl.flock(self._lock_fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(self._lock_fd)
            msg = f"state directory {self.dir} is in use by another colonyd"
            raise PersistenceError(msg) from None
        self._wal: Any = None
        self.wal_bytes = 0

    # -- recovery -------------------------------------------------------------------------
    def recover(self) -> Recovered:
        """Load the last snapshot and replay the log after it; start a new epoch if empty."""
        meta_path = self.dir / META
        fresh = not meta_path.exists()
        if fresh:
            epoch = time.time_ns() // 1000
            meta = {"agent_id": self.agent_id, "epoch": epoch, "resolution": self.resolution}
            _atomic_write(meta_path, json.dumps(meta).encode())
        else:
            meta = self._read_json(meta_path)
            if meta.get("agent_id") != self.agent_id:
                msg = (f"state directory {self.dir} belongs to agent {meta.get('agent_id')!r}, "
                       f"expected {self.agent_id!r}")
                raise PersistenceError(msg)
            if abs(float(meta.get("resolution", 0)) - self.resolution) > 1e-12:
                msg = (f"state directory {self.dir} holds a map at resolution "
                       f"{meta.get('resolution')}, expected {self.resolution}")
                raise PersistenceError(msg)
            epoch = int(meta["epoch"])
        grid, seq, published = new_grid(self.resolution, self.block_shape), 0, 0
        snap_path = self.dir / SNAPSHOT
        if snap_path.exists():
            snap = self._read_json(snap_path)
            try:
                grid = load_grid(self.dir / snap["file"])
            except Exception as exc:
                msg = f"snapshot {snap['file']} in {self.dir} cannot be loaded: {exc}"
                raise PersistenceError(msg) from None
            seq = int(snap["seq"])
            published = int(snap.get("published", grid.version))
        records = 0
        for rec in self._read_wal():
            if rec["seq"] <= seq:
                continue
            grid.apply(rec["delta"])
            seq = rec["seq"]
            published = max(published, int(rec["delta"].to_version))
            records += 1
        self._open_wal()
        frames = self._read_json(self.dir / FRAMES) if (self.dir / FRAMES).exists() else {}
        return Recovered(epoch, seq, grid, records, fresh, published, int(frames.get("next", 0)))

    def reserve_frames(self, up_to: int) -> None:
        """Durably record that frame numbers below `up_to` may be in use (a restart skips them)."""
        try:
            _atomic_write(self.dir / FRAMES, json.dumps({"next": int(up_to)}).encode())
        except OSError as exc:
            msg = f"cannot reserve frame numbers in {self.dir}: {exc.strerror}"
            raise PersistenceError(msg) from None

    def _read_json(self, path: Path) -> dict[str, Any]:
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            msg = f"{path} is unreadable or not JSON: {exc}"
            raise PersistenceError(msg) from None

    def _read_wal(self) -> list[dict[str, Any]]:
        path = self.dir / WAL
        if not path.exists():
            return []
        data = path.read_bytes()
        out, pos = [], 0
        while pos + _HEAD.size <= len(data):
            length, crc = _HEAD.unpack_from(data, pos)
            body = data[pos + _HEAD.size : pos + _HEAD.size + length]
            if len(body) != length or zlib.crc32(body) != crc:
                break  # a torn write at the tail: everything before it was acknowledged
            try:
                rec = msgpack.unpackb(body, raw=False)
                rec["delta"] = _unpack_wal_delta(rec["delta"])
            except Exception:
                break
            out.append(rec)
            pos += _HEAD.size + length
        if pos != len(data):
            log.warning("write-ahead log %s: dropped a torn tail of %d bytes", path, len(data) - pos)
            with open(path, "r+b") as fh:
                fh.truncate(pos)
        return out

    # -- writing --------------------------------------------------------------------------
    def _open_wal(self) -> None:
        if self._wal is not None:
            self._wal.close()
        self._wal = open(self.dir / WAL, "ab")  # noqa: SIM115 - kept open for appends
        self.wal_bytes = self._wal.tell()

    def append(self, seq: int, delta: Delta) -> None:
        """Log an own delta (grid versions) durably before it is published."""
        body = msgpack.packb({"seq": int(seq), "delta": _pack_wal_delta(delta)}, use_bin_type=True)
        try:
            self._wal.write(_HEAD.pack(len(body), zlib.crc32(body)) + body)
            self._wal.flush()
            os.fsync(self._wal.fileno())
        except OSError as exc:
            msg = f"cannot append to the write-ahead log in {self.dir}: {exc.strerror}"
            raise PersistenceError(msg) from None
        self.wal_bytes += _HEAD.size + len(body)

    def snapshot(self, grid: VoxelGrid, seq: int, published: int | None = None) -> None:
        """Save the grid at `seq`, point snapshot.json at it, then empty the log.

        `published` is the grid version up to which changes went into deltas; later changes in
        the saved grid are sent after a restart.
        """
        published = int(grid.version if published is None else published)
        name = f"own-{seq}.grid"
        tmp = self.dir / (name + ".tmp")
        try:
            grid.save(tmp)
            with open(tmp, "rb") as fh:
                os.fsync(fh.fileno())
            os.replace(tmp, self.dir / name)
            _atomic_write(self.dir / SNAPSHOT, json.dumps({"seq": int(seq), "file": name, "published": published}).encode())
            self._wal.close()
            _atomic_write(self.dir / WAL, b"")
            self._open_wal()
        except OSError as exc:
            msg = f"cannot write a snapshot in {self.dir}: {exc.strerror}"
            raise PersistenceError(msg) from None
        for old in self.dir.glob("own-*.grid"):
            if old.name != name:
                old.unlink(missing_ok=True)

    def close(self) -> None:
        if self._wal is not None:
            self._wal.close()
            self._wal = None
        os.close(self._lock_fd)


# ------------------------------------------------------------------ log records (local, exact)


def _pack_wal_delta(delta: Delta) -> dict[str, Any]:
    """A delta as a log record: every array byte for byte (the log is local, never sent)."""
    return {
        "r": float(delta.resolution),
        "f": int(delta.from_version),
        "v": int(delta.to_version),
        "tm": float(delta.time),
        "n": len(delta),
        "k": np.ascontiguousarray(delta.keys, dtype="<i8").tobytes(),
        "l": np.ascontiguousarray(delta.logodds, dtype="<f4").tobytes(),
        "lt": np.ascontiguousarray(delta.last_time, dtype="<f8").tobytes(),
        "c": {
            name: [list(arr.shape[1:]), np.ascontiguousarray(arr).tobytes()]
            for name, arr in delta.channels.items()
        },
    }


def _wal_array(raw: Any, dtype: np.dtype, shape: tuple[int, ...], what: str) -> np.ndarray:
    want = dtype.itemsize * math.prod(shape)
    if not isinstance(raw, bytes) or len(raw) != want:
        msg = f"log record field {what}: expected {want} bytes"
        raise PersistenceError(msg)
    return np.frombuffer(raw, dtype=dtype.newbyteorder("<")).reshape(shape).astype(dtype)


def _unpack_wal_delta(d: dict[str, Any]) -> Delta:
    n = int(d["n"])
    channels = {}
    for name, (tail, raw) in d.get("c", {}).items():
        dtype, _ = channel_spec(str(name))
        channels[str(name)] = _wal_array(raw, dtype, (n, *(int(x) for x in tail)), name)
    return Delta(
        float(d["r"]), int(d["f"]), int(d["v"]),
        _wal_array(d["k"], np.dtype(np.int64), (n, 3), "keys"),
        _wal_array(d["l"], np.dtype(np.float32), (n,), "logodds"),
        _wal_array(d["lt"], np.dtype(np.float64), (n,), "last_time"),
        channels, float(d["tm"]),
    )
