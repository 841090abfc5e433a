"""State directory: write-ahead log, snapshots, torn tails, ownership and locking."""

from __future__ import annotations

import errno
import fcntl
import json
import os
from pathlib import Path

import numpy as np
import pytest

from colonyd.errors import PersistenceError
from colonyd.grid import new_grid
from colonyd.mapping import integrate_observation
from colonyd.persistence import WAL, StateStore


def scan(grid, seed: int) -> None:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-2, 2, (200, 3))
    grid.integrate(pts, np.zeros(3), time=float(seed))


def log_three(store: StateStore, grid) -> None:
    """Integrate and log scans 1-3, snapshotting after the second."""
    published = 0
    for seq in range(1, 4):
        scan(grid, seq)
        store.append(seq, grid.delta_since(published))
        published = grid.version
        if seq == 2:
            store.snapshot(grid, seq)


@pytest.mark.parametrize("shape", ["cube", "planar"])
def test_wal_and_snapshot_recover_everything_logged(tmp_path, shape):
    store = StateStore(tmp_path, "a", 0.1, shape)
    rec = store.recover()
    assert rec.fresh and rec.seq == 0
    grid = rec.grid
    log_three(store, grid)
    scan(grid, 99)  # integrated but never logged: allowed to be lost
    store.close()

    store = StateStore(tmp_path, "a", 0.1)
    again = store.recover()
    assert not again.fresh and again.epoch == rec.epoch and again.seq == 3
    assert again.wal_records == 1
    assert again.grid.store.shifts == rec.grid.store.shifts  # the snapshot keeps its block shape
    expected = new_grid(0.1)
    for seq in range(1, 4):
        scan(expected, seq)
    assert again.grid.content_equal(expected)
    store.close()


def test_the_surface_survives_the_log_and_the_snapshot(tmp_path):
    store = StateStore(tmp_path, "a", 0.1)
    grid = store.recover().grid
    grid.surface = True  # as the daemon sets it (Config.surface)
    log_three(store, grid)
    store.close()
    again = StateStore(tmp_path, "a", 0.1).recover()
    keys = grid.occupied_keys()
    off = grid.surface_points(keys) - again.grid.surface_points(keys)
    assert again.grid.content_equal(grid) and "surface" in grid.delta_since(0).channels
    assert np.abs(off).max() <= 0.1 / 254 / 2 + 1e-12  # the log holds the wire's codes
    assert np.abs(grid.surface_points(keys) - new_grid(0.1).surface_points(keys)).max() > 0.01
    again.grid.surface = True
    scan(again.grid, 4)  # integrating on after recovery keeps the channel going
    assert "surface" in again.grid.delta_since(again.grid.version - 1).channels


def test_torn_wal_tail_is_dropped(tmp_path):
    store = StateStore(tmp_path, "a", 0.1)
    grid = store.recover().grid
    scan(grid, 1)
    store.append(1, grid.delta_since(0))
    v = grid.version
    scan(grid, 2)
    store.append(2, grid.delta_since(v))
    store.close()
    data = (tmp_path / WAL).read_bytes()
    (tmp_path / WAL).write_bytes(data[:-7])  # a crash in the middle of the second record
    store = StateStore(tmp_path, "a", 0.1)
    rec = store.recover()
    assert rec.seq == 1 and rec.wal_records == 1
    store.close()


def test_state_dir_guards(tmp_path):
    store = StateStore(tmp_path, "a", 0.1)
    store.recover()
    with pytest.raises(
        PersistenceError,
        match=r"in use by another colonyd \(it holds .*/lock\); expected a directory no running "
        "daemon holds: stop that daemon, or give this one a --state-dir of its own",
    ):
        StateStore(tmp_path, "a", 0.1)
    store.close()
    for agent, res, match in (
        ("b", 0.1, "belongs to agent 'a', expected 'b': every agent keeps its own state"),
        ("a", 0.2, "resolution 0.1, expected 0.2"),
    ):
        other = StateStore(tmp_path, agent, res)
        try:
            with pytest.raises(PersistenceError, match=match):
                other.recover()
        finally:
            other.close()
    (tmp_path / "file").write_text("x")
    with pytest.raises(PersistenceError, match="not writable"):
        StateStore(tmp_path / "file" / "sub", "a", 0.1)
    # --state-dir naming a file: was "not writable: File exists"
    with pytest.raises(PersistenceError, match=r"/file is a file; expected a directory"):
        StateStore(tmp_path / "file", "a", 0.1)


def test_changes_after_the_last_publish_are_sent_after_a_restart(tmp_path):
    store = StateStore(tmp_path, "a", 0.1)
    grid = store.recover().grid
    scan(grid, 1)
    store.append(1, grid.delta_since(0))
    published = grid.version
    scan(grid, 2)  # integrated, then snapshotted before it was published
    store.snapshot(grid, 1, published)
    store.close()
    store = StateStore(tmp_path, "a", 0.1)
    rec = store.recover()
    assert rec.seq == 1 and rec.published == published < rec.grid.version
    assert len(rec.grid.delta_since(rec.published)) > 0
    store.close()


def test_frame_numbers_reserved_survive_a_restart(tmp_path):
    from colonyd.frames import SEQ_BLOCK, Sender

    store = StateStore(tmp_path, "a", 0.1)
    rec = store.recover()
    assert rec.frame_seq == 0
    sender = Sender("a", rec.epoch, first_seq=rec.frame_seq, reserve=store.reserve_frames)
    used = [sender.take() for _ in range(5)]
    store.close()  # as after SIGKILL: nothing else written

    store = StateStore(tmp_path, "a", 0.1)
    again = store.recover()
    assert again.epoch == rec.epoch and again.frame_seq == 1 + SEQ_BLOCK > max(used)
    store.close()


def _logged(tmp_path, n: int = 3, snapshot_at: int | None = None):
    """A state directory with `n` logged deltas (and a snapshot after `snapshot_at` of them)."""
    store = StateStore(tmp_path, "a", 0.1)
    rec = store.recover()
    grid, published = rec.grid, 0
    for seq in range(1, n + 1):
        scan(grid, seq)
        store.append(seq, grid.delta_since(published))
        published = grid.version
        if seq == snapshot_at:
            store.snapshot(grid, seq)
    store.close()
    return rec.epoch, grid


def _offsets(data: bytes) -> list[int]:
    import struct

    out, pos = [], 0
    while pos < len(data):
        out.append(pos)
        pos += 8 + struct.unpack_from("<I", data, pos)[0]
    return out


def test_undecodable_record_stops_recovery_and_leaves_the_log_as_it_was(tmp_path):
    import struct
    import zlib

    import msgpack

    _logged(tmp_path, 3)
    wal = tmp_path / WAL
    data = wal.read_bytes()
    first = _offsets(data)[1]  # the first delta record, after the header
    # a record of a newer build: a valid CRC, a body this build cannot decode
    body = msgpack.packb({"seq": 1, "delta": {"format": 9}}, use_bin_type=True)
    alien = struct.pack("<II", len(body), zlib.crc32(body)) + body
    damaged = data[:first] + alien + data[first:]
    wal.write_bytes(damaged)
    store = StateStore(tmp_path, "a", 0.1)
    try:
        with pytest.raises(
            PersistenceError,
            match=rf"wal.log: the record at offset {first} "
            r"\(seq 1\) passes its CRC but cannot be decoded",
        ):
            store.recover()
    finally:
        store.close()
    assert wal.read_bytes() == damaged  # nothing acknowledged was cut


def test_crc_damage_inside_the_log_is_not_a_torn_tail(tmp_path):
    _logged(tmp_path, 3)
    wal = tmp_path / WAL
    data = bytearray(wal.read_bytes())
    second = _offsets(bytes(data))[2]
    data[second + 20] ^= 0xFF
    wal.write_bytes(bytes(data))
    store = StateStore(tmp_path, "a", 0.1)
    try:
        with pytest.raises(
            PersistenceError,
            match=rf"offset {second} fails its CRC and \d+ bytes "
            "follow it",
        ):
            store.recover()
    finally:
        store.close()
    assert wal.read_bytes() == bytes(data)


def test_zero_filled_last_record_is_a_torn_tail(tmp_path):
    _logged(tmp_path, 3)
    wal = tmp_path / WAL
    data = wal.read_bytes()
    last = _offsets(data)[-1]
    wal.write_bytes(data[: last + 8] + b"\0" * (len(data) - last - 8))  # as a crash may leave it
    store = StateStore(tmp_path, "a", 0.1)
    rec = store.recover()
    assert rec.seq == 2 and wal.stat().st_size == last
    store.close()


@pytest.mark.parametrize(
    "damage", ["wal-deleted", "wal-emptied", "gap", "frames-deleted", "old-snapshot"]
)
def test_lost_records_start_a_new_epoch_never_a_reused_version(tmp_path, damage):
    epoch, grid = _logged(tmp_path, 4, snapshot_at=2)
    wal = tmp_path / WAL
    if damage == "wal-deleted":
        wal.unlink()
    elif damage == "wal-emptied":
        wal.write_bytes(b"")
    elif damage == "gap":  # the record of seq 3 vanished
        data = wal.read_bytes()
        offsets = _offsets(data)
        wal.write_bytes(data[: offsets[1]] + data[offsets[2] :])
    elif damage == "frames-deleted":
        (tmp_path / "frames.json").unlink()
    elif damage == "old-snapshot":  # snapshot.json replaced by an older copy
        (tmp_path / "snapshot.json").write_text('{"seq": 1, "file": "own-2.grid", "published": 1}')
    store = StateStore(tmp_path, "a", 0.1)
    rec = store.recover()
    store.close()
    want = {"wal-deleted": 2, "wal-emptied": 2, "gap": 2, "frames-deleted": 4, "old-snapshot": 1}
    assert rec.seq == want[damage]
    assert rec.epoch > epoch and rec.frame_seq == 0  # versions above seq may exist in the old one
    if damage == "frames-deleted":
        assert rec.grid.content_equal(grid)  # what was recovered is kept
    store = StateStore(tmp_path, "a", 0.1)  # the new epoch is consistent: a restart keeps it
    again = store.recover()
    store.close()
    assert (again.epoch, again.seq) == (rec.epoch, rec.seq) and again.grid.content_equal(rec.grid)


def _published_unsynced(tmp_path, boot: str):
    """Two records written for early publishing (the second never fsync'ed), the process gone
    without closing; the epoch and grid it had."""
    store = StateStore(tmp_path, "a", 0.1, boot_id=boot)
    rec = store.recover()
    grid = rec.grid
    scan(grid, 1)
    store.write(1, grid.delta_since(0))
    store.sync()
    v = grid.version
    scan(grid, 2)
    store.write(2, grid.delta_since(v))  # published now, before any fsync
    fcntl.flock(store._lock_fd, fcntl.LOCK_UN)  # as a killed process leaves it (no close)
    store._wal.close()
    os.close(store._lock_fd)
    return rec.epoch, grid


def test_early_published_records_survive_a_crash_in_the_same_boot(tmp_path):
    epoch, grid = _published_unsynced(tmp_path, "boot-1")
    assert json.loads((tmp_path / "meta.json").read_text())["unsynced_boot"] == "boot-1"
    store = StateStore(tmp_path, "a", 0.1, boot_id="boot-1")
    rec = store.recover()  # the page cache kept both records: same epoch, nothing lost
    assert rec.epoch == epoch and rec.seq == 2 and rec.grid.content_equal(grid)
    store.close()  # everything on disk: a clean close drops the mark
    assert "unsynced_boot" not in json.loads((tmp_path / "meta.json").read_text())
    store = StateStore(tmp_path, "a", 0.1, boot_id="boot-2")  # so a reboot keeps the epoch
    assert store.recover().epoch == epoch
    store.close()


def test_a_reboot_after_early_publishing_starts_a_new_epoch(tmp_path):
    """Power lost before the fsync: the last record a peer saw is gone from the log. The origin
    must not log seq 2 again with other content in the same epoch."""
    epoch, _ = _published_unsynced(tmp_path, "boot-1")
    data = (tmp_path / WAL).read_bytes()
    records = _record_offsets(data)
    (tmp_path / WAL).write_bytes(data[: records[-1]])  # the page cache never reached the disk
    store = StateStore(tmp_path, "a", 0.1, boot_id="boot-2")
    rec = store.recover()
    assert rec.seq == 1 and rec.epoch > epoch  # what survived, in a new epoch
    store.close()
    # same files in the boot that wrote them would have kept the epoch (nothing could be lost)
    meta = json.loads((tmp_path / "meta.json").read_text())
    assert meta["epoch"] == rec.epoch and "unsynced_boot" not in meta


def test_a_failed_flush_after_publishing_stops_appends_and_forces_a_new_epoch(
    tmp_path, monkeypatch
):
    store = StateStore(tmp_path, "a", 0.1, boot_id="boot-1")
    rec = store.recover()
    scan(rec.grid, 1)
    store.write(1, rec.grid.delta_since(0))

    real, calls = os.fsync, []

    def eio(fd: int) -> None:  # the log's flush fails; the disk takes the mark after it
        calls.append(fd)
        if len(calls) == 1:
            raise OSError(errno.EIO, "Input/output error")
        real(fd)

    monkeypatch.setattr(os, "fsync", eio)
    with pytest.raises(PersistenceError, match=r"cannot flush .*Input/output error.*new epoch"):
        store.sync()
    monkeypatch.setattr(os, "fsync", real)
    v = rec.grid.version
    scan(rec.grid, 2)
    with pytest.raises(PersistenceError, match="cannot flush"):
        store.write(2, rec.grid.delta_since(v))
    store.close()
    store = StateStore(tmp_path, "a", 0.1, boot_id="boot-1")  # same boot, all the same
    again = store.recover()
    assert again.epoch > rec.epoch and again.seq == 1
    store.close()


def test_early_publishing_needs_a_boot_id(tmp_path):
    store = StateStore(tmp_path, "a", 0.1, boot_id="")
    rec = store.recover()
    assert not store.early_publish
    scan(rec.grid, 1)
    with pytest.raises(PersistenceError, match="needs a boot id"):
        store.write(1, rec.grid.delta_since(0))
    store.append(1, rec.grid.delta_since(0))  # the fsync-first path works everywhere
    store.close()


def _record_offsets(data: bytes) -> list[int]:
    """Start offsets of the log's records."""
    out, pos = [], 0
    while pos + 8 <= len(data):
        length = int.from_bytes(data[pos : pos + 4], "little")
        out.append(pos)
        pos += 8 + length
    return out


def test_a_state_directory_that_cannot_be_made_says_what_to_give(tmp_path):
    """A new user's first `colonyd run` without --state-dir meets /var/lib/colonyd: the error
    names the flag (here: a path under a file, unwritable even for root)."""
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(
        PersistenceError,
        match=r"state directory .*/file/state is not writable: Not a directory; expected a "
        r"directory this user may create and write \(--state-dir DIR",
    ):
        StateStore(blocker / "state", "a", 0.1)


CARMEN = Path("/work/shared/data/carmen/freiburg-079-corrected.log.gz")


@pytest.mark.skipif(not CARMEN.exists(), reason=f"needs the CARMEN log {CARMEN}")
@pytest.mark.parametrize("early", [False, True], ids=["append", "write-sync"])
def test_the_history_of_every_logged_delta_is_recovered_exactly(tmp_path, early):
    """30 real CARMEN scans, a delta logged every 3 with its versions' history (both write
    paths), a snapshot after the 15th and a forget before the 7th delta, then the process
    gone without a snapshot (as a SIGKILL leaves it): the recovered history is the one that
    wrote the log, record for record, seen entry for entry, agent table and all."""
    from plugins.source import open_source

    store = StateStore(tmp_path, "a", 0.05, "planar", boot_id="boot-1")
    grid = store.recover().grid
    source = open_source(f"replay:{CARMEN},stop=30", resolution=0.05)
    seq = published = 0
    start = None
    for i, obs in enumerate(source):
        agent = "a" if i % 5 else "helper"  # two agents in the table
        integrate_observation(
            grid, obs, sensor=source.adapter.sensor_model, reliability=1.0, agent=agent
        )
        start = grid.now if start is None else start
        if i % 3 != 2:
            continue
        if i == 20:  # as the daemon forgets: just before the delta, under the same hold
            held = grid.history.size
            grid.forget(after=(grid.now - start) * 0.5)
            assert grid.history.size < held
        seq += 1
        delta, page = grid.delta_since(published), grid.history.since(published, grid.version)
        assert page.records.size and page.seen.size
        if early:
            store.write(seq, delta, None, page)
            store.sync()
        else:
            store.append(seq, delta, history=page)
        published = grid.version
        if i == 14:
            store.snapshot(grid, seq, published)
    want = grid.history
    assert want.agents == ["helper", "a"]
    store.close()
    store = StateStore(tmp_path, "a", 0.05)
    rec = store.recover()
    store.close()
    assert rec.seq == 10 and rec.wal_records == 5
    got = rec.grid.history
    assert np.array_equal(got.view(), want.view())
    assert np.array_equal(got.seen(), want.seen())
    assert got.agents == want.agents
    assert rec.grid.content_equal(grid)


def test_a_record_without_history_recovers_as_before(tmp_path):
    """A log written before records carried history (or with none given): the grid is
    recovered, its history holds what the snapshot held and nothing of the log."""
    store = StateStore(tmp_path, "a", 0.1)
    grid = store.recover().grid
    scan(grid, 1)
    store.append(1, grid.delta_since(0))
    store.snapshot(grid, 1)
    v = grid.version
    scan(grid, 2)
    store.append(2, grid.delta_since(v))  # no history: an older colonyd's record
    held = grid.history.since(0, v)
    store.close()
    store = StateStore(tmp_path, "a", 0.1)
    rec = store.recover()
    store.close()
    assert rec.seq == 2 and rec.grid.content_equal(grid)
    assert np.array_equal(rec.grid.history.view(), held.records)
    assert np.array_equal(rec.grid.history.seen(), held.seen)


def test_work_beside_an_append_hands_back_its_result_or_its_error_after_the_record(tmp_path):
    """`meanwhile` (the daemon encodes the delta's frames with it) runs while the record is
    flushed: its result comes back once the record is durable; its error propagates, and the
    record is logged all the same (its seq taken)."""
    store = StateStore(tmp_path, "a", 0.1)
    grid = store.recover().grid
    log = store.append
    scan(grid, 1)
    assert log(1, grid.delta_since(0), meanwhile=lambda: "frames") == "frames"
    v = grid.version
    scan(grid, 2)

    def fails() -> None:
        raise RuntimeError("encoding failed")

    with pytest.raises(RuntimeError, match="encoding failed"):
        log(2, grid.delta_since(v), meanwhile=fails)
    assert log(3, grid.delta_since(grid.version), meanwhile=None) is None
    store.close()
    store = StateStore(tmp_path, "a", 0.1)
    rec = store.recover()
    store.close()
    assert rec.seq == 3 and rec.grid.content_equal(grid)


def test_a_record_with_a_damaged_history_stops_recovery(tmp_path):
    """A record whose history field does not decode (its bytes cut short) is damage, not a
    torn tail: recovery stops with an error naming the field and leaves the log as it was."""
    import zlib

    import msgpack

    from colonyd.persistence import _HEAD, _delta_record

    store = StateStore(tmp_path, "a", 0.1)
    grid = store.recover().grid
    scan(grid, 1)
    record = _delta_record(1, grid.delta_since(0), None, grid.history.since(0, grid.version))
    body = msgpack.unpackb(record[_HEAD.size :], raw=False)
    body["hist"]["r"] = body["hist"]["r"][:-1]
    store.close()
    bad = msgpack.packb(body, use_bin_type=True)
    with open(tmp_path / WAL, "ab") as fh:
        fh.write(_HEAD.pack(len(bad), zlib.crc32(bad)) + bad)
    size = (tmp_path / WAL).stat().st_size
    store = StateStore(tmp_path, "a", 0.1)
    with pytest.raises(PersistenceError, match=r"seq 1.*hist\.r: expected \d+ bytes"):
        store.recover()
    store.close()
    assert (tmp_path / WAL).stat().st_size == size


def test_recovery_hands_back_the_logged_deltas_for_the_rings_ranges(tmp_path):
    """A restarted origin's ring was empty: a peer that missed its last delta before a SIGKILL
    (logged, not yet sent) could only take a whole snapshot (the SIGKILL test's flake:
    snapshots_installed 2 > 1). Recovery hands back the records after the snapshot, with the
    time each was published; none when it takes a new epoch (peers replace the layer)."""
    store = StateStore(tmp_path, "a", 0.1)
    grid = store.recover().grid
    published, sent = 0, {}
    for seq in range(1, 5):
        scan(grid, seq)
        delta = grid.delta_since(published)
        sent[seq] = delta
        if seq % 2:
            store.append(seq, delta, created=1000.0 + seq)
        else:
            store.write(seq, delta, None, created=1000.0 + seq)
        published = grid.version
        if seq == 2:
            store.snapshot(grid, seq)
    store.close()
    store = StateStore(tmp_path, "a", 0.1)
    again = store.recover()
    assert [(s, t) for s, _d, t in again.records] == [(3, 1003.0), (4, 1004.0)]
    for s, d, _t in again.records:
        assert np.array_equal(d.keys, sent[s].keys) and np.array_equal(d.logodds, sent[s].logodds)
        assert (d.from_version, d.to_version) == (sent[s].from_version, sent[s].to_version)
    store.close()
    (tmp_path / "frames.json").unlink()  # recovery takes a new epoch: no range of the old one
    store = StateStore(tmp_path, "a", 0.1)
    assert store.recover().records == []
    store.close()
