"""History sync's memory of pushed pages dropped before the replica held their layer."""

from __future__ import annotations

import threading

import numpy as np

from colonyd import historysync
from colonyd.historysync import HistorySync
from colonyd.layers import Layers
from colonyd.metrics import Metrics
from voxel.delta import Delta


def _sync(layers: Layers) -> HistorySync:
    # no catch-up: `dropped` and `_arrived` never ask anyone
    return HistorySync(layers, None, Metrics(), period_s=0, stop=threading.Event())  # type: ignore[arg-type]


def _hold(layers: Layers, origin: str, epoch: int = 1) -> None:
    delta = Delta(0.1, 0, 1, np.zeros((1, 3)), np.ones(1), np.zeros(1))
    layers.get(origin).offer(epoch, 0, 1, delta)


def test_a_dropped_page_is_pulled_once_its_layer_arrives_at_that_epoch():
    layers = Layers("me", 0.1)
    sync = _sync(layers)
    sync.dropped("a", 2)
    sync.dropped("b", 1)
    assert sync._arrived() == []  # neither held yet
    _hold(layers, "a", epoch=1)  # an older epoch than the page's: not yet
    _hold(layers, "b", epoch=1)
    assert [x.origin for x in sync._arrived()] == ["b"]
    assert sync._arrived() == []  # pulled once: forgotten
    _hold(layers, "a", epoch=2)
    assert [x.origin for x in sync._arrived()] == ["a"]
    assert sync.metrics.counts["history_dropped"] == 2


def test_dropped_pages_are_bounded_and_forgotten_origins_let_go(monkeypatch):
    monkeypatch.setattr(historysync, "MAX_DROPPED", 3)
    layers = Layers("me", 0.1)
    sync = _sync(layers)
    for origin in ("a", "b", "c", "d", "e"):  # a hostile peer inventing origins
        sync.dropped(origin, 1)
    assert sorted(sync._dropped) == ["a", "b", "c"]
    sync.dropped("a", 3)  # one already remembered takes the later epoch
    assert sync._dropped["a"] == 3
    layers.forget_agent("b")
    assert sync._arrived() == [] and sorted(sync._dropped) == ["a", "c"]
