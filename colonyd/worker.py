"""Worker: a named daemon thread that hands each item of a bounded queue to a handler."""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Generic, TypeVar

from colonyd.activity import Activity
from colonyd.errors import ColonydError, WireError
from colonyd.metrics import Metrics
from protocol import ProtocolError
from protocol.errors import NotIntroducedError

log = logging.getLogger(__name__)

T = TypeVar("T")

#: How often an idle worker looks at its stop event (seconds).
POLL_S = 0.2
#: Seconds between two log lines of one worker about refusals of one reason (or failures of one
#: exception type): a flood of hostile input is counted, and logged a line per reason at most
#: this often, saying how many it left out.
LOG_EVERY_S = 10.0


class Throttle:
    """Whether a line of one kind may be logged now: the first, then one per `every_s`; it
    counts the lines it held back (kinds: refusal reasons and exception types, a bounded set)."""

    def __init__(self, every_s: float = LOG_EVERY_S) -> None:
        self.every_s = every_s
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}
        self._lock = threading.Lock()

    def allow(self, kind: str) -> int | None:
        """None: hold this line back; else log it, with the count of lines of `kind` held back
        since the last one."""
        now = time.monotonic()
        with self._lock:
            last = self._last.get(kind)
            if last is not None and now - last < self.every_s:
                self._held[kind] = self._held.get(kind, 0) + 1
                return None
            self._last[kind] = now
            return self._held.pop(kind, 0)


def held_text(held: int) -> str:
    """What a throttled line adds about the lines held back before it."""
    return f" (and {held} more like it since the last such line)" if held else ""


class Bounded(Generic[T]):
    """A queue bounded in count and, with `weigh`, in bytes: `put` refuses rather than grows."""

    def __init__(
        self, size: int, max_bytes: int = 0, weigh: Callable[[T], int] | None = None
    ) -> None:
        self._q: queue.Queue[T] = queue.Queue(maxsize=size)
        self._weigh = weigh
        self._max = max_bytes
        self._bytes = 0
        self._lock = threading.Lock()

    def put(self, item: T) -> bool:
        """Enqueue `item` without waiting; False (nothing kept) when it does not fit."""
        n = self._weigh(item) if self._weigh is not None else 0
        with self._lock:
            if self._weigh is not None and self._bytes + n > self._max:
                return False
            self._bytes += n
        try:
            self._q.put_nowait(item)
        except queue.Full:
            with self._lock:
                self._bytes -= n
            return False
        return True

    def get(self, timeout: float) -> T | None:
        """The oldest item, or None after `timeout` seconds without one."""
        try:
            item = self._q.get(timeout=timeout)
        except queue.Empty:
            return None
        if self._weigh is not None:
            n = self._weigh(item)
            with self._lock:
                self._bytes -= n
        return item


class Worker(Generic[T]):
    """A named daemon thread calling `handle(item)` for each item `put` on its bounded queue.

    No exception ends the thread. With `metrics`, a refusal (`ProtocolError`, `WireError`) is
    counted by its reason and logged as a warning; with `hostile` (items straight from the
    network) any other `ColonydError` or `ValueError` counts as `invalid` and anything else as
    `internal`. Every other exception is logged with its stack. Lines are throttled: one per
    reason or exception type at most every `LOG_EVERY_S` (`Throttle`). `done(item)` runs once
    per item, handled or refused by `put` (a query is dropped there); a refused `put` counts
    `drops`. `idle()` runs on the thread each time it is about to wait for the next item. Each
    item's handling goes to `activity` (by default the metrics'), named `label(item)` or the
    worker's name.
    """

    def __init__(
        self,
        name: str,
        handle: Callable[[T], None],
        items: Bounded[T],
        *,
        metrics: Metrics | None = None,
        hostile: bool = False,
        drops: str | None = None,
        describe: Callable[[T], str] = str,
        done: Callable[[T], None] | None = None,
        idle: Callable[[], None] | None = None,
        stop: threading.Event | None = None,
        activity: Activity | None = None,
        label: Callable[[T], str] | None = None,
    ) -> None:
        self.name = name
        self._activity = activity if activity is not None or metrics is None else metrics.activity
        self._label = label
        self._handle = handle
        self._items = items
        self._metrics = metrics
        self._hostile = hostile
        self._drops = drops
        self._describe = describe
        self._done = done
        self._idle = idle
        self.stop = stop if stop is not None else threading.Event()
        self._throttle = Throttle()
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)

    def put(self, item: T) -> bool:
        """Enqueue `item` for the thread; False if the queue is full (dropped and counted)."""
        if self._items.put(item):
            return True
        if self._metrics is not None and self._drops:
            self._metrics.add(self._drops)
        if self._done is not None:
            self._done(item)
        return False

    def start(self) -> None:
        self._thread.start()

    def close(self, timeout: float = 2.0) -> None:
        """Stop the thread (after the item in hand) and wait up to `timeout` seconds for it."""
        self.stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=timeout)

    def is_alive(self) -> bool:
        return self._thread.is_alive()

    def _loop(self) -> None:
        while not self.stop.is_set():
            if self._idle is not None:
                self._idle()
            item = self._items.get(timeout=POLL_S)
            if item is None:
                continue
            start = time.monotonic()
            try:
                self._handle(item)
            except Exception as exc:  # noqa: BLE001 - one item never kills the worker
                self._failed(item, exc)
            finally:
                if self._done is not None:
                    self._done(item)
                if self._activity is not None:
                    name = self._label(item) if self._label is not None else self.name
                    self._activity.record(name, start, time.monotonic())

    def _failed(self, item: T, exc: Exception) -> None:
        """Count a refusal or failure; log it, a line per reason or exception type at most every
        `LOG_EVERY_S` (`Throttle`: a flood of hostile input must not flood the log)."""
        metrics = self._metrics
        if metrics is not None and isinstance(exc, (ProtocolError, WireError)):
            metrics.reject(exc.reason)
            # a peer's frame that overtook its first heartbeat (every join, trust on first use)
            # is counted like the rest but is no cause for alarm: info, not a warning, and
            # throttled apart (it held back the warnings of its reason: a trust list's refusals)
            benign = isinstance(exc, NotIntroducedError)
            held = self._throttle.allow(f"{exc.reason}:info" if benign else exc.reason)
            if held is not None:
                level = logging.INFO if benign else logging.WARNING
                log.log(level, "rejected %s: %s%s", self._describe(item), exc, held_text(held))
        elif metrics is not None and self._hostile and isinstance(exc, (ColonydError, ValueError)):
            metrics.reject("invalid")
            held = self._throttle.allow(f"invalid:{type(exc).__name__}")
            if held is not None:
                log.warning("rejected %s: %s%s", self._describe(item), exc, held_text(held))
        else:
            if metrics is not None and self._hostile:
                metrics.reject("internal")
            held = self._throttle.allow(f"failed:{type(exc).__name__}")
            if held is not None:
                log.exception(
                    "%s: failed to handle %s%s", self.name, self._describe(item), held_text(held)
                )
