"""Heap: the cyclic collector kept off the delivery path by freezing what imports allocated."""

from __future__ import annotations

import gc
import logging
import sys

from voxel import kernels

log = logging.getLogger(__name__)


def freeze() -> None:
    """Move every object alive now into the collector's permanent generation (`gc.freeze`), so
    that no later pass traverses it. O(1): no pass runs (one would be the very pause this
    avoids), so what is garbage at that moment is never collected. (`gc.get_freeze_count` is
    not: it walks the list, 20-70 ms for a daemon's 230k objects.)"""
    gc.freeze()


class Freezer:
    """Freezes the heap (`freeze`) when modules were imported, or the compiled kernels loaded,
    since it last did: a daemon's modules (zenoh, pydantic, numpy at start-up; numba and
    llvmlite with the kernels; sklearn, pandas and scipy when objects are first clustered)
    leave ~230k long-lived objects, and a full collection walks all of them with the
    interpreter lock held: 100-400 ms per pass on a shared 2-core machine, several times a
    minute, during which no thread of the daemon (Zenoh callbacks, the inbox) runs Python. Those
    passes were the largest propagation outliers (docs/RELIABILITY.md, "Busy CPU"). Imports
    happen a bounded number of times (each module once), so the garbage frozen with them is
    bounded too (a full collection after start-up found 23 unreachable objects)."""

    def __init__(self) -> None:
        self._seen: tuple[int, bool] | None = None
        #: Times it froze the heap.
        self.count = 0

    def __call__(self) -> bool:
        """Freeze if anything was imported or loaded since the last call; True if it did."""
        now = (len(sys.modules), kernels.loaded())
        if now == self._seen:
            return False
        freeze()
        self.count += 1
        self._seen = (len(sys.modules), kernels.loaded())
        log.debug("heap: %d modules; their objects frozen out of the collector's passes", now[0])
        return True
