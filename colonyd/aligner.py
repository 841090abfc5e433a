"""Aligner: runs map registration in a child process, off the daemon's interpreter lock."""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from typing import Any, TypeVar

T = TypeVar("T")


class Aligner:
    """One spawned worker process for registration (seconds of numpy and Python per attempt):
    in a thread of the daemon it would hold the interpreter lock while peers' deltas wait in the
    inbox. Spawned, never forked, so no Zenoh session is copied; started on first use."""

    def __init__(self) -> None:
        self._pool: ProcessPoolExecutor | None = None

    def run(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """`fn(*args, **kwargs)` in the worker (arguments and result are pickled)."""
        if self._pool is None:
            self._pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
        return self._pool.submit(fn, *args, **kwargs).result()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
