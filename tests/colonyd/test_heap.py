"""The collector's passes kept off the delivery path: the heap frozen after imports, and the
activity log that showed the passes (and what else a daemon's threads were busy with)."""

from __future__ import annotations

import gc
import sys
import threading
import time
import types

from colonyd.activity import Activity, thread_names
from colonyd.heap import Freezer
from colonyd.metrics import Metrics
from colonyd.worker import Bounded, Worker


def test_the_heap_is_frozen_after_start_up_and_again_after_an_import() -> None:
    freeze = Freezer()
    try:
        assert freeze()  # start-up: everything alive now leaves the collector's passes
        frozen = gc.get_freeze_count()
        assert frozen > 1000
        assert not freeze()  # nothing imported since: nothing to do
        # a module imported later (a job's first use of sklearn, say) is frozen in turn
        module = types.ModuleType("colony_test_late_import")
        module.table = [[i] for i in range(5000)]  # type: ignore[attr-defined]
        sys.modules[module.__name__] = module
        try:
            assert freeze()
            assert gc.get_freeze_count() >= frozen + 5000
            # no pass walks them any more: they are in no generation
            table = {id(x) for x in module.table}  # type: ignore[attr-defined]
            assert not table & {id(x) for x in gc.get_objects()}
        finally:
            del sys.modules[module.__name__]
    finally:
        gc.unfreeze()


def test_collector_passes_and_worker_items_are_logged_with_their_thread() -> None:
    activity = Activity(floor_s=0.0)
    activity.watch_gc()
    try:
        gc.collect()
    finally:
        activity.unwatch_gc()
    names = [e[0] for e in activity.snapshot()]
    assert "gc2" in names
    gc.collect()  # no longer watched: nothing more logged
    assert [e[0] for e in activity.snapshot()] == names
    name, thread, start, end = activity.snapshot()[-1]
    assert thread == threading.current_thread().name and start <= end

    metrics = Metrics()
    metrics.activity.floor_s = 0.0
    done = threading.Event()
    worker: Worker[str] = Worker(
        "w",
        lambda item: (time.sleep(0.01), done.set()),
        Bounded(4),
        metrics=metrics,
        label=lambda item: f"w-{item}",
    )
    worker.start()
    try:
        worker.put("job")
        assert done.wait(5)
        deadline = time.monotonic() + 5
        while not metrics.activity.snapshot() and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        worker.close()
    (name, thread, start, end), *_ = metrics.activity.snapshot()
    assert (name, thread) == ("w-job", "w") and end - start >= 0.01
    report = metrics.snapshot(samples=True)
    assert report["activity"] and str(threading.main_thread().native_id) in thread_names()
    assert "activity" not in metrics.snapshot()  # only with the samples
