"""Thread clock: the calling thread's CPU time and run-queue wait, to tell work from waiting."""

from __future__ import annotations

import os
import threading
import time

#: Linux per-thread scheduler statistics: CPU ns, ns runnable but waiting for a core, slices.
SCHEDSTAT = "/proc/thread-self/schedstat"


class _Stat:
    """One thread's open schedstat file, closed when the thread ends (its `local` goes)."""

    def __init__(self) -> None:
        try:
            self.fd = os.open(SCHEDSTAT, os.O_RDONLY)
        except OSError:
            self.fd = -1

    def __del__(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)


_local = threading.local()


def read() -> tuple[float, float] | None:
    """(CPU seconds, run-queue seconds) this thread has spent so far, or None where the kernel
    does not say (not Linux, no schedstat). Wall time minus both is time the thread was blocked:
    the interpreter lock, another lock, I/O. One `pread` of an fd kept per thread (~1 us)."""
    stat = getattr(_local, "stat", None)
    if stat is None:
        stat = _local.stat = _Stat()
    if stat.fd < 0:
        return None
    try:
        cpu, runq, *_ = os.pread(stat.fd, 96, 0).split()
        return int(cpu) / 1e9, int(runq) / 1e9
    except (OSError, ValueError):
        return None


def stamp(marks: dict[str, float], name: str) -> None:
    """Mark a hand-off: `marks[name]` = time.monotonic() and, where known, `name.cpu` and
    `name.runq`: this thread's clocks (`read`) at that moment, so that a stage between two marks
    on one thread splits into CPU work, waiting for a core and the rest (blocked)."""
    clock = read()
    marks[name] = time.monotonic()
    if clock is not None:
        marks[f"{name}.cpu"], marks[f"{name}.runq"] = clock
