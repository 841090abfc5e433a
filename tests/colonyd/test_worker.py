"""The queue worker every daemon loop runs on: bounded, counted, never killed by one item."""

from __future__ import annotations

import threading
import time

from colonyd.errors import WireError
from colonyd.metrics import Metrics
from colonyd.worker import Bounded, Worker
from protocol import TruncatedError
from protocol.errors import NotIntroducedError, UnknownIdentityError


def wait_for(cond, seconds: float = 5.0) -> bool:
    deadline = time.monotonic() + seconds
    while not cond():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def test_bounded_refuses_over_count_and_bytes_and_frees_on_get() -> None:
    q: Bounded[bytes] = Bounded(3, max_bytes=10, weigh=len)
    assert q.put(b"123456") and q.put(b"1234")
    assert not q.put(b"1")  # 11 bytes would be over the budget
    assert q.get(timeout=0.01) == b"123456"
    assert q.put(b"1") and q.put(b"2")
    assert not q.put(b"3")  # 3 items: over the count
    assert [q.get(timeout=0.01) for _ in range(3)] == [b"1234", b"1", b"2"]
    assert q.get(timeout=0.01) is None
    assert q.put(b"0123456789")  # the budget is whole again


def test_a_full_queue_drops_counts_and_finishes_the_item() -> None:
    metrics = Metrics()
    done: list[int] = []
    w: Worker[int] = Worker(
        "t", lambda _: None, Bounded(1), metrics=metrics, drops="t_dropped", done=done.append
    )
    assert w.put(1)
    assert not w.put(2)  # not started: the queue holds one
    assert metrics.counts["t_dropped"] == 1 and done == [2]
    w.start()
    assert wait_for(lambda: done == [2, 1])
    w.close()
    assert not w.is_alive()


def test_refusals_are_counted_by_reason_and_the_worker_survives() -> None:
    metrics = Metrics()
    handled: list[str] = []

    def handle(item: str) -> None:
        if item == "wire":
            raise WireError("bad-query", "expected a query")
        if item == "protocol":
            raise TruncatedError("truncated frame")
        if item == "value":
            raise ValueError("bad value")
        if item == "bug":
            raise RuntimeError("a bug")
        handled.append(item)

    hostile: Worker[str] = Worker("h", handle, Bounded(8), metrics=metrics, hostile=True)
    hostile.start()
    for item in ("wire", "protocol", "value", "bug", "fine"):
        hostile.put(item)
    assert wait_for(lambda: handled == ["fine"])
    hostile.close()
    assert metrics.rejected == {"bad-query": 1, "truncated": 1, "invalid": 1, "internal": 1}

    calm = Metrics()
    handled.clear()
    w: Worker[str] = Worker(
        "c", handle, Bounded(8), metrics=calm
    )  # not hostile: bugs are logged only
    w.start()
    for item in ("wire", "value", "bug", "fine"):
        w.put(item)
    assert wait_for(lambda: handled == ["fine"])
    w.close()
    assert calm.rejected == {"bad-query": 1}


def test_workers_sharing_a_stop_event_stop_together() -> None:
    stop = threading.Event()
    workers = [Worker(f"w{i}", lambda _: None, Bounded(1), stop=stop) for i in range(3)]
    for w in workers:
        w.start()
    stop.set()
    assert wait_for(lambda: not any(w.is_alive() for w in workers))


def test_idle_runs_on_the_thread_before_each_wait() -> None:
    events: list[tuple[str, object]] = []
    w: Worker[int] = Worker(
        "t",
        lambda item: events.append(("item", item)),
        Bounded(4),
        idle=lambda: events.append(("idle", threading.current_thread().name)),
    )
    w.start()
    assert wait_for(lambda: len(events) >= 1)
    assert w.put(7)
    assert wait_for(lambda: ("item", 7) in events and events[-1][0] == "idle")
    w.close()
    at = events.index(("item", 7))
    assert events[at - 1] == ("idle", "t")  # it was waiting (stamped) when 7 came
    assert events[at + 1] == ("idle", "t")  # and waits again after it


def test_a_frame_ahead_of_its_origins_first_heartbeat_is_logged_as_info(caplog) -> None:
    """Every join logged "WARNING ... rejected pose ...: expected its heartbeat first" (a pose
    that overtook the newcomer's first heartbeat): counted as before, logged as info."""
    metrics = Metrics()
    seen: list[str] = []

    def handle(item: str) -> None:
        seen.append(item)
        if item == "early":
            raise NotIntroducedError("identity of 'a': expected its heartbeat first")
        raise UnknownIdentityError("identity of 'a': expected a pinned key (trust list)")

    w: Worker[str] = Worker("h", handle, Bounded(8), metrics=metrics, hostile=True)
    with caplog.at_level("INFO", logger="colonyd.worker"):
        w.start()
        w.put("early")
        w.put("listed")
        assert wait_for(lambda: metrics.rejected.get("unknown_identity") == 2)
        w.close()
    levels = {r.getMessage().split(": ", 1)[0]: r.levelname for r in caplog.records}
    assert levels == {"rejected early": "INFO", "rejected listed": "WARNING"}
