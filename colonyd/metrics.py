"""Counters and bounded samples a daemon reports in its status (rejections, bytes, latency)."""

from __future__ import annotations

import threading
from collections import Counter, deque

from colonyd.activity import Activity, thread_names


class Metrics:
    """Thread-safe counters plus the most recent propagation samples."""

    def __init__(self, samples: int = 4000) -> None:
        self._lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()
        #: Applied peer deltas: (origin, seq, created, applied, via) in epoch seconds; `via` is
        #: "frame" (the frame just received), "held" (buffered until a gap before it was filled)
        #: or "range" (fetched by a repair).
        self.applied: deque[tuple[str, int, float, float, str]] = deque(maxlen=samples)
        #: Installed snapshots: (origin, voxels, seconds from request to installed, marks); marks:
        #: step name -> time.monotonic() ("asked", "request", "first", "received", "admitted",
        #: "installed") plus "decode_s", "cpu_s" (the repair thread's CPU over the catch-up) and
        #: "process_cpu_s" (every thread's).
        self.catchups: deque[tuple[str, int, float, dict[str, float]]] = deque(maxlen=64)
        #: Snapshots served: (layer, marks); marks: "query", "snapshot", "encoded", "replied"
        #: (time.monotonic(), one clock for every process of the machine).
        self.serves: deque[tuple[str, dict[str, float]]] = deque(maxlen=64)
        #: Where a delta's time goes: ("out", own, seq, marks) at its origin and ("in", origin,
        #: seq, marks) at a replica; marks: hand-off name -> time.monotonic() (one clock for
        #: every process of the machine), in the order of the path (docs/RELIABILITY.md).
        self.stages: deque[tuple[str, str, int, dict[str, float]]] = deque(maxlen=samples)
        #: What the threads were busy with: collector passes and timed jobs (`Activity`).
        self.activity = Activity()

    def add(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.counts[name] += n

    def reject(self, reason: str) -> None:
        with self._lock:
            self.rejected[reason] += 1
            self.counts["rejected"] += 1

    def sample(
        self, origin: str, seq: int, created: float, applied: float, via: str = "frame"
    ) -> None:
        with self._lock:
            self.applied.append((origin, seq, created, applied, via))

    def stage(self, side: str, origin: str, seq: int, marks: dict[str, float]) -> None:
        with self._lock:
            self.stages.append((side, origin, seq, marks))

    def catchup(
        self, origin: str, voxels: int, seconds: float, marks: dict[str, float] | None = None
    ) -> None:
        with self._lock:
            self.catchups.append((origin, voxels, seconds, dict(marks or {})))

    def served(self, layer: str, marks: dict[str, float]) -> None:
        with self._lock:
            self.serves.append((layer, dict(marks)))

    def snapshot(self, *, samples: bool = False) -> dict[str, object]:
        with self._lock:
            out: dict[str, object] = {
                "counts": dict(self.counts),
                "rejected": dict(self.rejected),
                "catchups": [list(c) for c in self.catchups],
                "serves": [list(c) for c in self.serves],
            }
            if samples:
                out["samples"] = [list(s) for s in self.applied]
                out["stages"] = [list(s) for s in self.stages]
        if samples:
            out["activity"] = self.activity.snapshot()
            out["threads"] = thread_names()
        return out
