"""The daemon's publish step in process: a real state directory, layers and Zenoh session."""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from colonyd.config import Config
from colonyd.daemon import Daemon, get_store
from colonyd.errors import PersistenceError
from colonyd.persistence import StateStore
from colonyd.runtime import get_session
from tests.shared import ask_snapshot


@pytest.fixture
def daemon(tmp_path: Path) -> Iterator[Daemon]:
    cfg = Config(
        agent_id="a",
        colony="publish-once",
        state_dir=tmp_path / "state",
        listen=["tcp/127.0.0.1:0"],
        multicast=False,
        sync_before_publish=True,
        snapshot_s=3600.0,
    )
    d = Daemon(cfg)
    d.store = get_store(cfg)
    d._recover()
    d.session = get_session(cfg)
    d._declare()
    try:
        yield d
    finally:
        d.gossip.close()
        d.membership.close()
        for server in (d.status_server, d.export_server, d.forget_server):
            server.close()
        d.session.close()
        d.store.close()


def _scan(d: Daemon, t: float, seed: int) -> None:
    own = d.layers.own
    rng = np.random.default_rng(seed)
    with own.lock:
        own.grid.integrate(rng.uniform(-2, 2, (200, 3)), np.zeros(3), time=t)


def test_a_failed_log_write_ends_a_waiting_own_snapshot_at_once(daemon, monkeypatch):
    """The state directory refuses the delta's record: a snapshot waiting for it gives up at
    that failure (it held the layer server's single worker for the whole wait)."""
    from colonyd import layers as layers_mod

    monkeypatch.setattr(layers_mod, "UNLOGGED_WAIT_S", 1e6)  # only the failure ends the wait
    own = daemon.layers.own
    _scan(daemon, 1.0, 1)
    daemon._publish_once()
    assert own.seq == 1
    _scan(daemon, 2.0, 2)  # not logged
    waiting, errors = ask_snapshot(own)
    assert own.nudge.wait(5.0)

    def full(fd: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(PersistenceError):
        daemon._publish_once()
    waiting.join(10.0)
    assert not waiting.is_alive() and errors and "No space left" in str(errors[0])


def test_a_delta_logged_while_its_encoding_failed_keeps_its_seq(daemon, monkeypatch):
    """With `sync_before_publish` the frames are encoded while the record flushes; when the
    encoding fails the record is logged all the same (`StateStore.append`). Its seq is taken:
    the next delta must not be logged under it again (recovery applies the first record of a
    seq and skips the second, losing what only the second held)."""
    own = daemon.layers.own
    encode = daemon.gossip.encode_own
    calls = {"n": 0}

    def flaky(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 1:
            raise ValueError("an encoding fault")
        return encode(*args, **kwargs)

    monkeypatch.setattr(daemon.gossip, "encode_own", flaky)
    _scan(daemon, 1.0, 1)
    with contextlib.suppress(ValueError):  # (the publish loop logs what propagates)
        daemon._publish_once()  # logged: published with its frames made again
    _scan(daemon, 2.0, 2)
    daemon._publish_once()
    seqs = [seq for seq, _delta in daemon.store.logged()]
    assert seqs == [1, 2] and own.seq == 2
    with own.lock:
        live = own.grid.delta_since(0)
    daemon.store.close()
    store = StateStore(daemon.config.state_dir, "a", daemon.config.resolution)
    again = store.recover()
    store.close()
    daemon.store = get_store(daemon.config)  # (the fixture closes it)
    assert again.grid.version == own.grid.version
    from colonyd.grid import new_grid

    expected = new_grid(daemon.config.resolution)
    expected.apply(live)
    assert again.grid.content_equal(expected)


def test_the_final_publish_waits_for_a_publish_under_way(daemon, monkeypatch):
    """At shutdown the publisher thread is waited for 3 s, then the final publish runs: a
    publish still under way (a slow flush) and the final one took the same seq, and the log held
    two records of it (recovery keeps the first, and loses what only the second held)."""
    flush = os.fsync
    entered, release = threading.Event(), threading.Event()

    def slow(fd: int) -> None:
        if not entered.is_set():
            entered.set()
            release.wait(10.0)
        flush(fd)

    monkeypatch.setattr(os, "fsync", slow)
    _scan(daemon, 1.0, 1)
    first = threading.Thread(target=daemon._publish_once, daemon=True)
    first.start()
    assert entered.wait(10.0)  # its record written, its flush under way
    _scan(daemon, 2.0, 2)
    final = threading.Thread(target=lambda: daemon._publish_once(final=True), daemon=True)
    final.start()
    final.join(1.0)  # (room for a final publish that does not wait to go wrong)
    release.set()
    first.join(10.0)
    final.join(10.0)
    assert not first.is_alive() and not final.is_alive()
    assert [seq for seq, _delta in daemon.store.logged()] == [1, 2]
