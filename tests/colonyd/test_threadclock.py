"""Thread clock: a thread's CPU time and run-queue wait, and the marks stamped with them."""

from __future__ import annotations

import threading
import time

import pytest

from colonyd import threadclock


def _clock() -> tuple[float, float]:
    clock = threadclock.read()
    if clock is None:
        pytest.skip("no per-thread schedstat on this kernel")
    return clock


def test_cpu_grows_while_working_and_not_while_sleeping() -> None:
    cpu0, runq0 = _clock()
    start = time.monotonic()
    cpu1, runq1 = cpu0, runq0
    while cpu1 - cpu0 < 0.02 and time.monotonic() - start < 10.0:  # work until 20 ms of CPU
        cpu1, runq1 = _clock()
    end = time.monotonic()
    # a loaded machine may take the core away for a while (CI has), never for 10 s
    assert cpu1 - cpu0 >= 0.02
    assert cpu1 - cpu0 <= end - start + 0.005  # one thread is never on a core longer than wall time
    assert runq1 >= runq0
    time.sleep(0.1)
    cpu2, runq2 = _clock()
    assert cpu2 - cpu1 < 0.05  # asleep: neither on a core nor waiting for one
    assert (time.monotonic() - end) - (cpu2 - cpu1) - (runq2 - runq1) > 0.05  # blocked


def test_each_thread_reads_its_own_clock() -> None:
    _clock()
    seen: list[tuple[float, float] | None] = []
    t = threading.Thread(target=lambda: seen.append(threadclock.read()))
    t.start()
    t.join()
    mine = _clock()
    other = seen[0]
    assert other is not None
    assert other[0] < mine[0]  # a fresh thread has used less CPU than this one


def test_stamp_marks_the_time_and_the_clocks() -> None:
    _clock()
    marks: dict[str, float] = {}
    before = time.monotonic()
    threadclock.stamp(marks, "decoded")
    assert before <= marks["decoded"] <= time.monotonic()
    assert marks["decoded.cpu"] > 0
    assert marks["decoded.runq"] >= 0
