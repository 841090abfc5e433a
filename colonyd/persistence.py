"""State directory: write-ahead log of own deltas plus periodic snapshots, replaced atomically."""

from __future__ import annotations

import fcntl
import json
import logging
import math
import os
import struct
import time
import zlib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar, cast

import msgpack
import numpy as np

from colonyd.errors import PersistenceError
from colonyd.grid import VoxelGrid, load_grid, new_grid
from voxel.delta import Delta, channel_spec
from voxel.history import HistoryPage
from voxel.record import RECORD_DTYPE, SEEN_DTYPE

log = logging.getLogger(__name__)

T = TypeVar("T")

_HEAD = struct.Struct("<II")  # length, crc32
META = "meta.json"
SNAPSHOT = "snapshot.json"
WAL = "wal.log"
FRAMES = "frames.json"
BOOT_ID = Path("/proc/sys/kernel/random/boot_id")
#: `unsynced_boot` after a failed flush: matches no boot, so the next recovery takes a new epoch.
SYNC_FAILED = "sync-failed"


def current_boot_id() -> str:
    """This boot of the machine (Linux's random boot id), "" where the system has none."""
    try:
        return BOOT_ID.read_text().strip()
    except OSError:
        return ""


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
    #: The sources' positions stored with the recovered grid version (`colonyd.resume`'s record,
    #: not yet validated); None when none was stored (a fresh directory, an older colonyd).
    sources: Any = None
    #: The log's records replayed, (seq, delta in grid versions, its publication time), for the
    #: own layer's ring (so a peer that missed the last deltas before a crash repairs with a
    #: range, not a snapshot); none when recovery took a new epoch.
    records: list[tuple[int, Delta, float]] = field(default_factory=list)


def atomic_write(path: Path, data: bytes, mode: int = 0o644) -> None:
    """Replace `path` by `data` durably: a temporary file (created with `mode`), fsync, rename."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
        with open(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except OSError:
        tmp.unlink(missing_ok=True)  # a full disk keeps no half-written temporary file
        raise
    _fsync_dir(path.parent)


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class StateStore:
    """Own layer on disk: `meta.json`, `snapshot.json` + grid file, and `wal.log`.

    Two ways to log an own delta: `append` (written and fsync'ed before the caller publishes
    it) and `write` + `sync` (published once written, before the fsync: a killed daemon loses
    nothing, as written bytes survive the process in the page cache, but a machine that loses
    power may lose the last records a peer has seen). The second is only safe with a boot id:
    while records may be published unsynced, `meta.json` names the boot they were written in
    (`unsynced_boot`), and a recovery in another boot continues in a new epoch, so peers replace
    what they hold instead of silently keeping versions the origin lost. `close` clears the mark
    once everything is on disk (a clean shutdown keeps the epoch across a reboot).
    """

    def __init__(
        self,
        state_dir: Path,
        agent_id: str,
        resolution: float,
        block_shape: str = "cube",
        *,
        boot_id: str | None = None,
    ) -> None:
        self.dir = Path(state_dir)
        self.agent_id = agent_id
        self.resolution = resolution
        self.block_shape = block_shape
        self.boot_id = current_boot_id() if boot_id is None else boot_id
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
            self._lock_fd = os.open(self.dir / "lock", os.O_RDWR | os.O_CREAT, 0o600)
        except OSError as exc:
            found = "a file" if self.dir.is_file() else f"not writable: {exc.strerror}"
            msg = (
                f"state directory {self.dir} is {found}; expected a "
                "directory this user may create and write (--state-dir DIR, or state_dir in the "
                "config; the default /var/lib/colonyd is the systemd unit's)"
            )
            raise PersistenceError(msg) from None
        try:
            fcntl.flock(self._lock_fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(self._lock_fd)
            msg = (
                f"state directory {self.dir} is in use by another colonyd (it holds "
                f"{self.dir / 'lock'}); expected a directory no running daemon holds: stop that "
                "daemon, or give this one a --state-dir of its own"
            )
            raise PersistenceError(msg) from None
        self._wal: Any = None
        self.wal_bytes = 0
        #: Why appends are refused (a failed append could not be cut back off the log); "" if not.
        self.broken = ""
        self._flusher: ThreadPoolExecutor | None = None  # fsyncs while the caller works on
        self.epoch = 0  # set by `recover`
        self._unsynced = False  # records written (and maybe published) but not yet fsync'ed
        self._marked = False  # meta.json names this boot as one with unsynced records

    # -- recovery -------------------------------------------------------------------------
    def recover(self) -> Recovered:
        """Load the last snapshot and replay the log after it; start a new epoch if empty.

        Layer versions and frame numbers are never reused within an epoch: when the files show
        that logged records or frame reservations may be missing (the log or `frames.json` gone,
        a log that does not continue the snapshot, a gap in its sequence), the daemon keeps what
        it recovered but continues in a new epoch, snapshotted at once. A log record that passes
        its CRC but cannot be decoded, or damage before the log's end, stops recovery with a
        PersistenceError; the files are left as they were.
        """
        meta_path = self.dir / META
        fresh = not meta_path.exists()
        meta: dict[str, Any] = {}
        if fresh:
            epoch = _new_epoch(0)
            self._write_meta(epoch)
            self.reserve_frames(0)
            atomic_write(self.dir / WAL, _wal_header(0, epoch))
        else:
            meta = self._read_json(meta_path)
            epoch = self._check_meta(meta)
        grid, seq, published = new_grid(self.resolution, self.block_shape), 0, 0
        sources: Any = None
        snap_path = self.dir / SNAPSHOT
        if snap_path.exists():
            snap = self._read_json(snap_path)
            try:
                grid = load_grid(self.dir / snap["file"])
            except Exception as exc:  # noqa: BLE001 - any unreadable snapshot becomes PersistenceError
                msg = f"snapshot {snap['file']} in {self.dir} cannot be loaded: {exc}"
                raise PersistenceError(msg) from None
            seq = int(snap["seq"])
            published = int(snap.get("published", grid.version))
            sources = snap.get("sources")
        header, records = self._read_wal()
        lost = self._lost(header, seq, epoch) or self._rebooted(meta)
        applied: list[tuple[int, Delta, float]] = []
        for rec in records:
            if rec["seq"] <= seq:
                continue
            if rec["seq"] != seq + 1:
                lost = lost or f"{WAL} skips from seq {seq} to seq {rec['seq']}"
                break  # later records cannot apply in order
            before = grid.version
            grid.apply(rec["delta"])
            if rec.get("hist") is not None:  # absent in an older colonyd's records
                grid.history.replay(rec["hist"], before)
            sources = rec.get("src")  # the positions stored with this grid version
            seq = rec["seq"]
            published = max(published, int(rec["delta"].to_version))
            applied.append((seq, rec["delta"], float(rec.get("tc", rec["delta"].time))))
        frames_path = self.dir / FRAMES
        frames = self._read_json(frames_path) if frames_path.exists() else {}
        frame_seq = int(frames.get("next", 0))
        if lost:
            old, epoch = epoch, _new_epoch(epoch)
            log.warning(
                "state %s: %s; continuing with what was recovered (seq %d) in a new "
                "epoch %d (was %d), so no layer version or frame number is reused",
                self.dir,
                lost,
                seq,
                epoch,
                old,
            )
            self._write_meta(epoch)
            self.reserve_frames(0)
            frame_seq = 0
        else:
            self._marked = bool(meta.get("unsynced_boot"))  # this boot's mark: it stays
        self.epoch = epoch
        self._open_wal()
        if lost:
            self.snapshot(grid, seq, published, sources)
        return Recovered(
            epoch,
            seq,
            grid,
            len(applied),
            fresh,
            published,
            frame_seq,
            sources,
            [] if lost else applied,
        )

    def _check_meta(self, meta: dict[str, Any]) -> int:
        """The epoch of a state directory's meta.json, after checking it is ours."""
        if meta.get("agent_id") != self.agent_id:
            msg = (
                f"state directory {self.dir} belongs to agent {meta.get('agent_id')!r}, "
                f"expected {self.agent_id!r}: every agent keeps its own state directory (give "
                f"--agent-id {meta.get('agent_id')} to run that agent, or another --state-dir)"
            )
            raise PersistenceError(msg)
        if abs(float(meta.get("resolution", 0)) - self.resolution) > 1e-12:
            msg = (
                f"state directory {self.dir} holds a map at resolution "
                f"{meta.get('resolution')}, expected {self.resolution}"
            )
            raise PersistenceError(msg)
        return int(meta["epoch"])

    def _write_meta(self, epoch: int, unsynced_boot: str = "") -> None:
        meta: dict[str, Any] = {
            "agent_id": self.agent_id,
            "epoch": epoch,
            "resolution": self.resolution,
        }
        if unsynced_boot:
            meta["unsynced_boot"] = unsynced_boot
        atomic_write(self.dir / META, json.dumps(meta).encode())
        self._marked = bool(unsynced_boot)

    def _rebooted(self, meta: dict[str, Any]) -> str:
        """Why published records may be missing from the log after a reboot ("" if not)."""
        marked = str(meta.get("unsynced_boot", ""))
        if not marked or (marked == self.boot_id and self.boot_id):
            return ""
        if marked == SYNC_FAILED:
            return "a flush of the log failed after its record was published"
        return (
            "the machine restarted (boot id changed) while records were published before "
            "reaching the disk: the last ones a peer saw may be missing"
        )

    @property
    def early_publish(self) -> bool:
        """True if records may be published before their fsync (a boot id tells a reboot)."""
        return bool(self.boot_id)

    def _lost(self, header: dict[str, Any] | None, seq: int, epoch: int) -> str:
        """Why logged records or frame reservations may be missing ("" if nothing shows it),
        for a snapshot at `seq` in `epoch`."""
        if not (self.dir / FRAMES).exists():
            return f"{FRAMES} is missing"
        if header is None:
            return f"{WAL} is missing or has no header (emptied or replaced)"
        if header["epoch"] != epoch:
            return f"{WAL} belongs to epoch {header['epoch']}, expected {epoch}"
        if header["base"] > seq:
            return f"{WAL} continues seq {header['base']} but the snapshot is at seq {seq}"
        return ""

    def reserve_frames(self, up_to: int) -> None:
        """Durably record that frame numbers below `up_to` may be in use (a restart skips them)."""
        try:
            atomic_write(self.dir / FRAMES, json.dumps({"next": int(up_to)}).encode())
        except OSError as exc:
            msg = f"cannot reserve frame numbers in {self.dir}: {exc.strerror}"
            raise PersistenceError(msg) from None

    def _read_json(self, path: Path) -> dict[str, Any]:
        try:
            data: dict[str, Any] = json.loads(path.read_text())
            return data
        except (OSError, ValueError) as exc:
            msg = f"{path} is unreadable or not JSON: {exc}"
            raise PersistenceError(msg) from None

    def logged(self) -> list[tuple[int, Delta]]:
        """The (seq, delta) records of the log as it is on disk (for checks; changes nothing
        but a torn tail, as recovery would)."""
        return [(rec["seq"], rec["delta"]) for rec in self._read_wal()[1]]

    def _read_wal(self) -> tuple[dict[str, Any] | None, list[dict[str, Any]]]:
        """The log's header record (None if absent) and its delta records.

        Only a torn *tail* is dropped (cut from the file): a last record that is incomplete or
        fails its CRC with nothing after it, as a crash during an append leaves. A record that
        fails its CRC with more records after it, or passes its CRC but cannot be decoded (a
        newer build's record, say), raises PersistenceError naming the file, offset and seq; the
        file is left as it was.
        """
        path = self.dir / WAL
        if not path.exists():
            return None, []
        data = path.read_bytes()
        header: dict[str, Any] | None = None
        out: list[dict[str, Any]] = []
        pos = 0
        while pos + _HEAD.size <= len(data):
            length, crc = _HEAD.unpack_from(data, pos)
            end = pos + _HEAD.size + length
            body = data[pos + _HEAD.size : end]
            if end > len(data) or (zlib.crc32(body) != crc and end == len(data)):
                break  # a torn write at the tail: everything before it was acknowledged
            if zlib.crc32(body) != crc:
                msg = (
                    f"write-ahead log {path}: the record at offset {pos} fails its CRC and "
                    f"{len(data) - end} bytes follow it: expected damage only at the end "
                    "(a torn append), found it inside the log; the file is left as it was"
                )
                raise PersistenceError(msg)
            rec = _decode_wal_record(body, path, pos)
            if "base" in rec:
                if pos != 0:
                    msg = (
                        f"write-ahead log {path}: expected its header only at offset 0, "
                        f"found another at offset {pos}; the file is left as it was"
                    )
                    raise PersistenceError(msg)
                header = rec
            else:
                out.append(rec)
            pos = end
        if pos != len(data):
            log.warning(
                "write-ahead log %s: dropped a torn tail of %d bytes", path, len(data) - pos
            )
            with open(path, "r+b") as fh:
                fh.truncate(pos)
                os.fsync(fh.fileno())
        return header, out

    # -- writing --------------------------------------------------------------------------
    def _open_wal(self) -> None:
        if self._wal is not None:
            self._wal.close()
            self._wal = None
        # Unbuffered: a failed write leaves nothing in a buffer that a later write would flush.
        self._wal = open(self.dir / WAL, "ab", buffering=0)  # noqa: SIM115 - kept open for appends
        self.wal_bytes = self._wal.seek(0, os.SEEK_END)

    def write(
        self,
        seq: int,
        delta: Delta,
        sources: Any = None,
        history: HistoryPage | None = None,
        created: float | None = None,
    ) -> None:
        """Write an own delta's record without waiting for the disk: once this returns it may
        be published (a killed process loses nothing written); `sync` makes it durable.

        All or nothing, as `append` (`sources`, `history` and `created` as there). Needs
        `early_publish`: the first write of a run marks this boot in `meta.json` (see the class)."""
        if not self.early_publish:
            msg = "publishing before the log is flushed needs a boot id, and this system has none"
            raise PersistenceError(msg)
        if self.broken:
            raise PersistenceError(self.broken)
        if not self._marked:
            try:
                self._write_meta(self.epoch, self.boot_id)
            except OSError as exc:
                msg = f"cannot mark {META} in {self.dir} before logging seq {seq}: {exc.strerror}"
                raise PersistenceError(msg) from None
        record = _delta_record(seq, delta, sources, history, created)
        try:
            if self._wal is None:
                self._open_wal()
            start = self.wal_bytes
            view = memoryview(record)
            while view:
                view = view[self._wal.write(view) :]
        except OSError as exc:
            msg = f"cannot append seq {seq} to the write-ahead log in {self.dir}: {exc.strerror}"
            self._rewind(msg)
            raise PersistenceError(msg) from None
        self.wal_bytes = start + len(record)
        self._unsynced = True

    def sync(self) -> None:
        """fsync what `write` wrote. A failure cannot take back what was published: appends
        stop until restart, and `meta.json` is marked so that recovery starts a new epoch."""
        if not self._unsynced or self._wal is None:
            return
        try:
            os.fsync(self._wal.fileno())
        except OSError as exc:
            self.broken = (
                f"cannot flush the write-ahead log in {self.dir} ({exc.strerror}) after its "
                "last record was published: nothing more is logged or published until colonyd "
                "restarts, in a new epoch"
            )
            log.error("%s", self.broken)
            try:
                self._write_meta(self.epoch, SYNC_FAILED)
            except OSError as again:
                log.error("cannot mark %s in %s either: %s", META, self.dir, again.strerror)
            raise PersistenceError(self.broken) from None
        self._unsynced = False

    def append(
        self,
        seq: int,
        delta: Delta,
        meanwhile: Callable[[], T] | None = None,
        sources: Any = None,
        history: HistoryPage | None = None,
        created: float | None = None,
    ) -> T | None:
        """Log an own delta (grid versions) durably before it is published, with `sources`
        (plain values: the sources' positions at the delta's last version, `colonyd.resume`),
        which recovery hands back with the grid it rebuilds up to this record, `history`
        (the grid's history records and seen entries of the delta's versions, `History.since`),
        which recovery takes back into the grid's history after the delta (`History.replay`),
        and `created`, the time its frames say it was published (a range served after a restart
        says it again).

        `meanwhile()` (encoding the frames, say) runs while the disk flushes, and its result is
        returned once the record is durable: the flush and the work overlap, nothing is sent
        earlier. If `meanwhile` raises, the record is still logged, then the error propagates.

        All or nothing: when the write or fsync fails (disk full, I/O error) the bytes written
        are cut off again, so the seq can be logged later with other content and a restart
        never finds a record that was not acknowledged. If they cannot be cut off, the store
        refuses every later append (`broken`): the daemon keeps running but publishes nothing
        of its own until restarted, and recovery then takes the record as the last one.
        """
        if self.broken:
            raise PersistenceError(self.broken)
        record = _delta_record(seq, delta, sources, history, created)
        try:
            if self._wal is None:  # closed by a snapshot that failed half-way
                self._open_wal()
            start = self.wal_bytes
            view = memoryview(record)
            while view:
                view = view[self._wal.write(view) :]
            result, failure = self._flush(self._wal.fileno(), meanwhile)
        except OSError as exc:
            msg = f"cannot append seq {seq} to the write-ahead log in {self.dir}: {exc.strerror}"
            self._rewind(msg)
            raise PersistenceError(msg) from None
        self.wal_bytes = start + len(record)
        if failure is not None:
            raise failure
        return result

    def _flush(self, fd: int, work: Callable[[], T] | None) -> tuple[T | None, Exception | None]:
        """fsync(fd) here, with `work()` running meanwhile on a helper thread (fsync releases
        the GIL); the work's result or error. Raises OSError if the flush failed.

        The caller flushes itself, so it resumes straight from the system call when the disk is
        done; the work (shorter than a flush) is normally finished by then.
        """
        if work is None:
            os.fsync(fd)
            return None, None
        if self._flusher is None:
            self._flusher = ThreadPoolExecutor(max_workers=1, thread_name_prefix="wal-overlap")
        done = self._flusher.submit(work)
        result: T | None
        failure: Exception | None
        try:
            os.fsync(fd)
        finally:
            try:
                result, failure = done.result(), None
            except Exception as exc:  # noqa: BLE001 - handed back: the record is logged all the same
                result, failure = None, exc
        return result, failure

    def _rewind(self, why: str) -> None:
        """Cut the log back to its last acknowledged record after a failed append."""
        if self._wal is None:
            return
        try:
            os.ftruncate(self._wal.fileno(), self.wal_bytes)
            os.fsync(self._wal.fileno())
        except OSError as exc:
            self.broken = (
                f"{why}; the partial record could not be removed ({exc.strerror}), "
                "so nothing more is logged or published until colonyd restarts"
            )
            log.error("%s", self.broken)

    def snapshot(
        self, grid: VoxelGrid, seq: int, published: int | None = None, sources: Any = None
    ) -> None:
        """Save the grid at `seq`, point snapshot.json at it, then start an empty log after it.

        `sources`: the sources' positions at the grid's version (kept in snapshot.json).

        `published` is the grid version up to which changes went into deltas; later changes in
        the saved grid are sent after a restart. The new log's header names `seq` and the epoch,
        so a log emptied or replaced later is noticed at recovery.

        A snapshot that fails (disk full, read-only) leaves the previous one and the log in
        use, removes its partial files and raises PersistenceError; appends go on.
        """
        published = int(grid.version if published is None else published)
        name = f"own-{seq}.grid"
        tmp = self.dir / (name + ".tmp")
        pointed = False
        try:
            previous = json.loads((self.dir / SNAPSHOT).read_text()).get("file")
        except (OSError, ValueError):
            previous = None
        try:
            grid.save(tmp)
            with open(tmp, "rb") as fh:
                os.fsync(fh.fileno())
            os.replace(tmp, self.dir / name)
            pointer = {"seq": int(seq), "file": name, "published": published}
            if sources is not None:
                pointer["sources"] = sources
            atomic_write(self.dir / SNAPSHOT, json.dumps(pointer).encode())
            pointed = True
            # The old log stays in use until the new one is in place (its records up to `seq`
            # are skipped at recovery, as they are in the snapshot).
            atomic_write(self.dir / WAL, _wal_header(seq, self.epoch))
            self._open_wal()
            self.broken = ""  # the new log holds only whole records
            self._unsynced = False  # and the snapshot holds every record before it, on disk
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            if not pointed and name != previous:  # the previous snapshot stays the one in use
                (self.dir / name).unlink(missing_ok=True)
            msg = f"cannot write a snapshot in {self.dir}: {exc.strerror}"
            raise PersistenceError(msg) from None
        for old in self.dir.glob("own-*.grid"):
            if old.name != name:
                old.unlink(missing_ok=True)

    def close(self) -> None:
        """Flush and close; a store that published unsynced records and now has them all on
        disk drops its boot mark (a later reboot then keeps the epoch)."""
        if self._flusher is not None:
            self._flusher.shutdown(wait=True)
            self._flusher = None
        if self._wal is not None:
            try:
                self.sync()
                if self._marked and not self.broken:
                    self._write_meta(self.epoch)
            except (OSError, PersistenceError) as exc:
                log.error(
                    "state %s: closing with records that may not be on disk: %s", self.dir, exc
                )
            self._wal.close()
            self._wal = None
        os.close(self._lock_fd)


# ------------------------------------------------------------------ log records (local, exact)


def _new_epoch(previous: int) -> int:
    """A fresh epoch: microseconds since 1970, and always above `previous`."""
    return max(time.time_ns() // 1000, previous + 1)


def _record(fields: dict[str, Any]) -> bytes:
    """One framed log record: length, CRC32, msgpack body."""
    body: bytes = msgpack.packb(fields, use_bin_type=True)
    return _HEAD.pack(len(body), zlib.crc32(body)) + body


def _delta_record(
    seq: int,
    delta: Delta,
    sources: Any,
    history: HistoryPage | None = None,
    created: float | None = None,
) -> bytes:
    """The log record of an own delta, with the sources' positions, the history of its versions
    and its publication time when given."""
    fields: dict[str, Any] = {"seq": int(seq), "delta": _pack_wal_delta(delta)}
    if sources is not None:
        fields["src"] = sources
    if history is not None:
        fields["hist"] = _pack_wal_history(history)
    if created is not None:
        fields["tc"] = float(created)
    return _record(fields)


def _pack_wal_history(page: HistoryPage) -> dict[str, Any]:
    """History records and seen entries as a log record: byte for byte (RECORD_DTYPE and
    SEEN_DTYPE are little-endian), with the agent table their codes index."""
    return {
        "a": list(page.agents),
        "n": int(page.records.size),
        "r": np.ascontiguousarray(page.records, dtype=RECORD_DTYPE).tobytes(),
        "ns": int(page.seen.size),
        "s": np.ascontiguousarray(page.seen, dtype=SEEN_DTYPE).tobytes(),
    }


def _unpack_wal_history(h: dict[str, Any]) -> HistoryPage:
    agents = h["a"]
    if not isinstance(agents, list) or not all(isinstance(a, str) for a in agents):
        msg = f"log record field hist.a: expected a list of agent names, found {agents!r:.80}"
        raise PersistenceError(msg)
    records = _wal_array(h["r"], RECORD_DTYPE, (int(h["n"]),), "hist.r")
    seen = _wal_array(h["s"], SEEN_DTYPE, (int(h["ns"]),), "hist.s")
    return HistoryPage(records, list(agents), seen)


def _wal_header(base: int, epoch: int) -> bytes:
    """The first record of a log started after a snapshot at seq `base` in `epoch`."""
    return _record({"base": int(base), "epoch": int(epoch)})


def _decode_wal_record(body: bytes, path: Path, offset: int) -> dict[str, Any]:
    """A log record (header or delta) of a CRC-checked body, or PersistenceError."""
    seq: Any = "unknown"
    try:
        rec = msgpack.unpackb(body, raw=False)
        if isinstance(rec, dict):
            seq = rec.get("seq", seq)
            if "base" in rec:
                return {"base": int(rec["base"]), "epoch": int(rec["epoch"])}
        rec["seq"] = int(rec["seq"])
        rec["delta"] = _unpack_wal_delta(rec["delta"])
        if rec.get("hist") is not None:
            rec["hist"] = _unpack_wal_history(rec["hist"])
        return cast("dict[str, Any]", rec)  # indexed by name above: a map
    except Exception as exc:  # noqa: BLE001 - a record that fails to decode in any way
        msg = (
            f"write-ahead log {path}: the record at offset {offset} (seq {seq}) passes its "
            f"CRC but cannot be decoded ({type(exc).__name__}: {exc}); expected a record of "
            "this colonyd version (a newer one may have written it); the file is left as it was"
        )
        raise PersistenceError(msg) from None


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
        **({} if delta.surface_mask is None else {"sm": np.packbits(delta.surface_mask).tobytes()}),
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
        float(d["r"]),
        int(d["f"]),
        int(d["v"]),
        _wal_array(d["k"], np.dtype(np.int64), (n, 3), "keys"),
        _wal_array(d["l"], np.dtype(np.float32), (n,), "logodds"),
        _wal_array(d["lt"], np.dtype(np.float64), (n,), "last_time"),
        channels,
        float(d["tm"]),
        surface_mask=None
        if d.get("sm") is None
        else np.unpackbits(
            _wal_array(d["sm"], np.dtype(np.uint8), ((n + 7) // 8,), "surface_mask"), count=n
        ).astype(bool),
    )
