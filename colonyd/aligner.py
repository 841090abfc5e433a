"""Aligner: runs map registration in a child process, off the daemon's interpreter lock."""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

from colonyd.errors import StoppedError

if TYPE_CHECKING:
    import multiprocessing.pool

T = TypeVar("T")

#: Niceness added to the registration process: seconds of background CPU that must not take a
#: core from the daemon's mapping and replication threads on a machine with few cores.
NICE = 10


#: Niceness of the registration process's own session where the kernel shares the CPU by
#: session (autogroup): its session weighs ~10 % of an ordinary one (weight 110 of 1024). At 19
#: (~1.5 %) an attempt of ~0.1 s of CPU took 9-45 s under load and the paper experiment's two
#: robots aligned after its run; the daemons' propagation tail was the same within the noise at
#: 10 and at 19, and worse with no session of its own (docs/RELIABILITY.md, "Busy CPU").
AUTOGROUP_NICE = 10
#: Linux's per-session CPU weight of the calling process (sched_autogroup_enabled).
AUTOGROUP = "/proc/self/autogroup"


def background(session_nice: int | None = AUTOGROUP_NICE) -> None:
    """Make the calling process background work (the worker's initializer): `NICE`; on Linux
    the SCHED_IDLE policy (a thread that wakes on its core takes it at once), and a session of
    its own at autogroup niceness `session_nice` (None: no session of its own). Niceness alone
    did not keep registration off the daemons' cores: where the kernel shares the CPU between
    sessions (autogroup) first, the worker weighed as much as its daemon's whole session, and
    with SCHED_IDLE alone it still took cores that woken Zenoh and inbox threads waited for.
    Registration runs for seconds every `align_s`; it was the largest part of the propagation
    tail left once the collector's pauses were gone (docs/RELIABILITY.md, "Busy CPU")."""
    os.nice(NICE)
    with contextlib.suppress(AttributeError, OSError):  # not Linux: niceness only
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    if session_nice is None:
        return
    try:
        os.setsid()
    except (AttributeError, OSError):
        return
    for _ in range(20):  # unprivileged writes are rate-limited machine-wide (EAGAIN)
        try:
            with open(AUTOGROUP, "w") as f:
                f.write(str(session_nice))
            return
        except BlockingIOError:
            time.sleep(0.1)
        except OSError:  # no autogroup here: the session alone changes nothing
            return


class Aligner:
    """One spawned worker process for registration (seconds of numpy and Python per attempt):
    in a thread of the daemon it would hold the interpreter lock while peers' deltas wait in the
    inbox. Spawned, never forked, so no Zenoh session is copied; started on first use, as
    background work (`background`); `close` ends it at once, even in the middle of an attempt."""

    def __init__(self, session_nice: int | None = AUTOGROUP_NICE) -> None:
        self.session_nice = session_nice
        self._pool: multiprocessing.pool.Pool | None = None
        self._closed = threading.Event()

    def run(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """`fn(*args, **kwargs)` in the worker (arguments and result are pickled); StoppedError
        if the aligner is closed before it returns."""
        if self._closed.is_set():
            raise StoppedError("the aligner is closed: no registration is started")
        import multiprocessing  # loads with the worker, not at start-up

        if self._pool is None:
            self._pool = multiprocessing.get_context("spawn").Pool(
                1, initializer=background, initargs=(self.session_nice,)
            )
        pending = self._pool.apply_async(fn, args, kwargs)
        while True:
            try:
                result: T = pending.get(timeout=0.2)
                return result
            except multiprocessing.TimeoutError:
                if self._closed.is_set():
                    raise StoppedError("the aligner was closed during a registration") from None

    def close(self) -> None:
        self._closed.set()
        if self._pool is not None:
            self._pool.terminate()
            self._pool.join()
            self._pool = None
