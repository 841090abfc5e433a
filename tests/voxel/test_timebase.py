"""Tests of the time base: stored milliseconds, a base on whole hours, moves keep times exact."""

from __future__ import annotations

import numpy as np

from voxel.blocks import BlockStore
from voxel.timebase import TIME_SPAN_MS, TimeBase, quantise_time


def test_first_time_sets_the_base_on_a_whole_hour_and_round_trips() -> None:
    times = TimeBase(BlockStore())
    stored = times.stamp(np.array([7_200_123.4567, 7_200_124.0]))
    assert times.base_ms == 7_200_000_000
    assert stored.dtype == np.uint32 and stored.tolist() == [123_457, 124_000]
    np.testing.assert_array_equal(times.seconds(stored), [7_200_123.457, 7_200_124.0])
    assert quantise_time(7_200_123.4567) == 7_200_123.457


def test_base_moves_and_stored_times_follow() -> None:
    store = BlockStore()
    times = TimeBase(store)
    slot = store.ensure(np.array([5], dtype=np.int64))
    store.channels["last_time"][slot, 0] = times.stamp(1000.0)
    later = 1000.0 + 60 * 86400  # beyond the 49-day window
    times.stamp(later)
    assert times.base_ms is not None and later * 1000 - times.base_ms == TIME_SPAN_MS // 2
    # the older voxel is clamped to the moved base
    assert times.seconds(store.channels["last_time"][slot, 0])[0] == times.base_ms / 1000.0
    times.stamp(500.0)  # earlier than the base: it moves back to a whole hour
    assert times.base_ms == 0
    assert (
        times.seconds(store.channels["last_time"][slot, 0])[0] == later - TIME_SPAN_MS // 2 / 1000.0
    )


def test_seconds_without_a_base_count_from_zero() -> None:
    assert TimeBase(BlockStore()).seconds(np.array([1500], dtype=np.uint32)).tolist() == [1.5]
