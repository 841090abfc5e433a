"""Catch-up's timeline: marks kept in the metrics and written as one log line."""

from __future__ import annotations

import threading
from collections.abc import Callable
from types import SimpleNamespace

from colonyd.catchup import timeline
from colonyd.metrics import Metrics
from tests.shared import fresh_process


def test_a_catch_up_timeline_reads_in_order_of_its_steps() -> None:
    marks = {"request": 10.0, "installed": 10.25, "first": 10.1, "decode_s": 0.05}
    assert timeline(marks) == "first +100.0 ms, installed +250.0 ms, decode_s 50.0 ms"
    assert timeline({"decode_s": 0.1}) == ""


def test_metrics_report_catch_ups_and_serves_with_their_marks() -> None:
    m = Metrics()
    marks = {"request": 1.0, "installed": 1.5}
    m.catchup("a", 10, 0.5, marks)
    marks["installed"] = 9.0  # the metrics keep their own copy
    m.served("b", {"query": 2.0, "replied": 2.1})
    out = m.snapshot()
    assert out["catchups"] == [["a", 10, 0.5, {"request": 1.0, "installed": 1.5}]]
    assert out["serves"] == [["b", {"query": 2.0, "replied": 2.1}]]


def test_a_snapshot_that_did_not_arrive_whole_is_asked_for_with_a_longer_timeout() -> None:
    from colonyd.catchup import MAX_DOUBLINGS, snapshot_timeout

    assert [snapshot_timeout(5.0, n) for n in range(4)] == [5.0, 10.0, 20.0, 40.0]
    assert snapshot_timeout(5.0, 100) == 5.0 * 2**MAX_DOUBLINGS


def _labelling_daemon(idle: Callable[[], bool]) -> SimpleNamespace:
    """What `Daemon._warm_up` reads of a daemon: one source that may label (every warm import
    applies), objects clustered, and catch-up idle when `idle()` says so."""
    return SimpleNamespace(
        stop=threading.Event(),
        warm=threading.Event(),
        _sources=[SimpleNamespace(adapter=SimpleNamespace())],
        config=SimpleNamespace(objects_s=2.0),
        gossip=SimpleNamespace(catchup=SimpleNamespace(idle=idle)),
    )


def test_compiled_kernels_load_once_catch_up_is_idle(monkeypatch) -> None:
    import sys
    import time

    from colonyd import daemon as dm

    loaded: list[float] = []
    monkeypatch.setattr(dm.kernels, "warm", lambda: loaded.append(time.monotonic()) or True)
    monkeypatch.setattr(dm, "KERNELS_SETTLE_S", 0.0)
    busy_until = time.monotonic() + 0.3
    fake = _labelling_daemon(idle=lambda: time.monotonic() >= busy_until)
    dm.Daemon._warm_up(fake)  # type: ignore[arg-type]
    assert len(loaded) == 1 and loaded[0] >= busy_until
    assert fake.warm.is_set()  # start-up over: the status says so
    for name in dm.WARM_IMPORTS:
        assert name in sys.modules
    fake.stop.set()  # a daemon stopping meanwhile loads nothing
    fake.warm.clear()
    dm.Daemon._warm_up(fake)  # type: ignore[arg-type]
    assert len(loaded) == 1 and not fake.warm.is_set()


def test_start_up_ends_when_a_warm_import_fails_in_any_way(monkeypatch) -> None:
    """An import the warm-up cannot do (missing, or the import lock's deadlock error when a job's
    thread imports a neighbouring module at the same moment) is left to the job that needs it:
    start-up still ends."""

    from colonyd import daemon as dm

    def fail(name: str) -> None:
        raise (ImportError if name.startswith("sklearn") else RuntimeError)(f"cannot {name}")

    monkeypatch.setattr(dm.importlib, "import_module", fail)
    monkeypatch.setattr(dm.kernels, "warm", lambda: True)
    monkeypatch.setattr(dm.kernels, "warm_codec", lambda: True)
    monkeypatch.setattr(dm, "KERNELS_SETTLE_S", 0.0)
    fake = _labelling_daemon(idle=lambda: True)
    dm.Daemon._warm_up(fake)  # type: ignore[arg-type]
    assert fake.warm.is_set()


def test_a_daemon_without_sources_ends_start_up_without_scipy() -> None:
    """The warm-up imports scipy (~0.6 CPU-s) only where a job of this process uses it: with
    sources (scan matching, colony maps), never registration's scipy.ndimage and scipy.fft (they
    load in the aligner's worker). A fresh process warms up a daemon without sources (warm,
    nothing imported), turns a quaternion into a matrix (numpy alone: still no scipy), then warms
    up one with a source."""

    code = (
        "import sys, threading\n"
        "from types import SimpleNamespace\n"
        "import numpy as np\n"
        "from colonyd import daemon as dm\n"
        "dm.KERNELS_SETTLE_S = 0.0\n"
        "loads = []\n"
        "dm.kernels.warm = lambda: loads.append('kernels') or True\n"
        "dm.kernels.warm_codec = lambda: loads.append('codec') or True\n"
        "SCIPY = ('scipy.spatial', 'scipy.spatial.transform', 'scipy.ndimage', 'scipy.fft',\n"
        "         'sklearn.cluster')\n"
        "def warm_up(sources):\n"
        "    fake = SimpleNamespace(stop=threading.Event(), warm=threading.Event(),\n"
        "        _sources=sources, config=SimpleNamespace(objects_s=0.0),\n"
        "        gossip=SimpleNamespace(catchup=SimpleNamespace(idle=lambda: True)))\n"
        "    dm.Daemon._warm_up(fake)\n"
        "    print(fake.warm.is_set(), loads, [m for m in SCIPY if m in sys.modules])\n"
        "warm_up([])\n"
        "from voxel.rotation import quaternion_to_matrix\n"
        "print(np.allclose(quaternion_to_matrix((0.0, 0.0, 0.0, 1.0)), np.eye(3)),\n"
        "      [m for m in SCIPY if m in sys.modules])\n"
        "warm_up([SimpleNamespace(adapter=SimpleNamespace(labels=False))])\n"
    )
    stdout = fresh_process(code)
    assert stdout.split("\n")[:3] == [
        "True [] []",
        "True []",
        "True ['kernels', 'codec'] ['scipy.spatial', 'scipy.spatial.transform']",  # (its package's)
    ], stdout
