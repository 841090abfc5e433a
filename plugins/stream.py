"""Source protocol, per-stream counters and what a caller gives every source: resolution, seed,
stop."""

from __future__ import annotations

import logging
import threading
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

from plugins.adapter import SensorAdapter
from plugins.observation import Observation

log = logging.getLogger(__name__)


@dataclass
class StreamStats:
    """Frames delivered and frames skipped (by reason) by one source."""

    delivered: int = 0
    skipped: int = 0
    reasons: Counter[str] = field(default_factory=Counter)
    first_errors: list[str] = field(default_factory=list)

    def skip(self, where: str, error: Exception) -> None:
        """Count a bad frame at `where`; log the first few in full."""
        self.skipped += 1
        self.reasons[type(error).__name__] += 1
        if len(self.first_errors) < 10:
            self.first_errors.append(f"{where}: {error}")
            log.warning("skipped bad frame %s: %s", where, error)


@dataclass(frozen=True)
class SourceContext:
    """What the caller of a source knows and a spec does not say.

    `resolution`: voxel size of the grid fed (sources of ready-made voxels need it); `seed`: the
    seed of sources whose spec sets none (the daemon derives one per agent); `stop`: set to end
    a paced or endless source between frames; `session`: gives the caller's Zenoh session (the
    daemon's), for sources that read from the network (`ros2:`), once it is open.
    """

    resolution: float = 0.1
    seed: int = 0
    stop: threading.Event = field(default_factory=threading.Event)
    session: Callable[[], Any] | None = None


@runtime_checkable
class Source(Protocol):
    """A stream of Observations from one sensor of one agent."""

    spec: str
    adapter: SensorAdapter
    stats: StreamStats

    def __iter__(self) -> Iterator[Observation]: ...

    def __len__(self) -> int:
        """Number of frames the source expects to deliver (an estimate for progress bars)."""
        ...
