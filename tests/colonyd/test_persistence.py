"""State directory: write-ahead log, snapshots, torn tails, ownership and locking."""

from __future__ import annotations

import numpy as np
import pytest

from colonyd.errors import PersistenceError
from colonyd.grid import new_grid
from colonyd.persistence import WAL, StateStore


def scan(grid, seed: int) -> None:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-2, 2, (200, 3))
    grid.integrate(pts, np.zeros(3), time=float(seed))


@pytest.mark.parametrize("shape", ["cube", "planar"])
def test_wal_and_snapshot_recover_everything_logged(tmp_path, shape):
    store = StateStore(tmp_path, "a", 0.1, shape)
    rec = store.recover()
    assert rec.fresh and rec.seq == 0
    grid, published = rec.grid, 0
    for seq in range(1, 4):
        scan(grid, seq)
        store.append(seq, grid.delta_since(published))
        published = grid.version
        if seq == 2:
            store.snapshot(grid, seq)
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
    with pytest.raises(PersistenceError, match="in use by another colonyd"):
        StateStore(tmp_path, "a", 0.1)
    store.close()
    for agent, res, match in (("b", 0.1, "belongs to agent 'a', expected 'b'"),
                              ("a", 0.2, "resolution 0.1, expected 0.2")):
        other = StateStore(tmp_path, agent, res)
        try:
            with pytest.raises(PersistenceError, match=match):
                other.recover()
        finally:
            other.close()
    (tmp_path / "file").write_text("x")
    with pytest.raises(PersistenceError, match="not writable"):
        StateStore(tmp_path / "file" / "sub", "a", 0.1)


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
