"""Activity log: what a daemon's threads were busy with (collector pauses, periodic jobs), timed."""

from __future__ import annotations

import gc
import threading
import time
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

#: Activities shorter than this are not kept (the log is for what can delay a delta).
FLOOR_S = 0.001


class Activity:
    """A bounded log of (name, thread, start, end) in time.monotonic() (one clock for every
    process of the machine), so that a slow delivery can be matched with what every daemon's
    threads were doing meanwhile (`colonyd bench faults --only busy`, docs/RELIABILITY.md)."""

    def __init__(self, size: int = 4000, floor_s: float = FLOOR_S) -> None:
        self._lock = threading.Lock()
        self.floor_s = floor_s
        self.entries: deque[tuple[str, str, float, float]] = deque(maxlen=size)
        self._gc_started: dict[int, float] = {}

    def record(self, name: str, start: float, end: float) -> None:
        if end - start >= self.floor_s:
            with self._lock:
                self.entries.append((name, threading.current_thread().name, start, end))

    @contextmanager
    def timed(self, name: str) -> Iterator[None]:
        start = time.monotonic()
        try:
            yield
        finally:
            self.record(name, start, time.monotonic())

    def watch_gc(self) -> None:
        """Log the cyclic collector's passes (`gc.callbacks`), named `gc<generation>`."""
        if self._on_gc not in gc.callbacks:
            gc.callbacks.append(self._on_gc)

    def unwatch_gc(self) -> None:
        if self._on_gc in gc.callbacks:
            gc.callbacks.remove(self._on_gc)

    def _on_gc(self, phase: str, info: dict[str, Any]) -> None:
        ident = threading.get_ident()
        if phase == "start":
            self._gc_started[ident] = time.monotonic()
        elif (start := self._gc_started.pop(ident, None)) is not None:
            self.record(f"gc{info.get('generation', '?')}", start, time.monotonic())

    def snapshot(self) -> list[list[Any]]:
        with self._lock:
            return [list(e) for e in self.entries]


def thread_names() -> dict[str, str]:
    """The process's Python threads by their kernel thread id (as `perf` and /proc name them)."""
    return {str(t.native_id): t.name for t in threading.enumerate() if t.native_id is not None}
