"""The time base of a grid: stored times are uint32 milliseconds since a base that moves."""

from __future__ import annotations

import numpy as np

from voxel.blocks import BlockStore

#: Stored times span at most this many ms from the grid's time base (uint32).
TIME_SPAN_MS = 2**32 - 1
#: A new base lies on a whole hour (when it moves back, or is first set).
BASE_STEP_MS = 3_600_000


def quantise_time(t: float) -> float:
    """Time rounded to whole milliseconds, as k / 1000.0."""
    return round(float(t) * 1000.0) / 1000.0


class TimeBase:
    """Converts seconds to the stored form (uint32 ms since `base_ms`) and back.

    The base is set by the first time stamped and moves when a time falls outside the 49-day
    window; then the stored times of `store` are shifted, and voxels older than the moved base
    are kept at the base (their age is then only known to be at least ~24 days).
    """

    def __init__(self, store: BlockStore, base_ms: int | None = None) -> None:
        self.store = store
        self.base_ms = base_ms

    def stamp(self, t: float | np.ndarray) -> np.ndarray:
        """Stored form (uint32 ms since the base) of times in seconds; moves the base if needed."""
        if isinstance(t, float):  # one time (a scan's): the same arithmetic on Python integers
            one = round(t * 1000.0)  # rounds half to even, as np.rint
            base = self._base_for(one, one)
            return np.array(min(max(one - base, 0), TIME_SPAN_MS), dtype=np.uint32)
        ms = np.rint(np.asarray(t, dtype=np.float64) * 1000.0).astype(np.int64)
        if ms.size == 0:
            return ms.astype(np.uint32)
        base = self._base_for(int(ms.min()), int(ms.max()))
        return (ms - base).clip(0, TIME_SPAN_MS).astype(np.uint32)

    def _base_for(self, lo: int, hi: int) -> int:
        """The base (ms) that stores times lo..hi (ms), moved (stored times shifted) if needed."""
        base = lo - lo % BASE_STEP_MS if self.base_ms is None else self.base_ms
        if lo < base or hi - base > TIME_SPAN_MS:
            new_base = lo - lo % BASE_STEP_MS if lo < base else hi - TIME_SPAN_MS // 2
            self._shift_stored(new_base - base)
            base = new_base
        self.base_ms = base
        return base

    def seconds(self, stored: np.ndarray) -> np.ndarray:
        """Seconds (float64, exactly k / 1000) of stored times."""
        base = self.base_ms or 0
        return (np.asarray(stored).astype(np.int64) + base) / 1000.0

    def _shift_stored(self, moved_ms: int) -> None:
        """Re-express the store's times after the base moved forward by `moved_ms` (or back)."""
        last = self.store.channels["last_time"]
        slots = self.store.used_slots()
        rel = last[slots].astype(np.int64) - moved_ms
        last[slots] = rel.clip(0, TIME_SPAN_MS).astype(np.uint32)
