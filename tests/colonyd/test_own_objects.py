"""The own object list reads the layer's grid under the layer's lock, whatever replaces it."""

from __future__ import annotations

import threading
import time

import numpy as np

from colonyd.layers import Layer
from colonyd.objects import OwnObjects

RESOLUTION = 0.05


def _labelled_grid(layer: Layer, centre: np.ndarray, class_id: int):
    """A new grid for `layer` holding one labelled box (its surface) around `centre`."""
    grid = layer._new_grid()
    u = np.linspace(-0.2, 0.2, 30)
    a, b = (x.ravel() for x in np.meshgrid(u, u))
    h = np.full_like(a, 0.2)
    faces = [(h, a, b), (-h, a, b), (a, h, b), (a, -h, b), (a, b, h), (a, b, -h)]
    pts = np.concatenate([np.stack(f, 1) for f in faces]) + centre
    for origin in (np.array([0.01, 0.02, 0.03]), centre + np.array([0.0, 0.0, 1.5])):
        grid.integrate(
            pts,
            origin,
            time=1.0,
            class_ids=np.full(len(pts), class_id),
            class_probs=np.full(len(pts), 0.9),
        )
    return grid


def test_refresh_reads_a_grid_replaced_while_it_waited_for_the_lock():
    """A grid replaced (a snapshot install) while the refresh waits for the layer's lock: the
    refresh clusters the new grid, not the one the layer held when it was called."""
    layer = Layer("me", RESOLUTION)
    objects = OwnObjects(frozenset())
    assert objects.refresh(layer) is None  # empty layer: nothing
    centre = np.array([1.013, 0.507, 0.311])
    replacement = _labelled_grid(layer, centre, 3)
    got: list[object] = []
    with layer.lock:
        worker = threading.Thread(target=lambda: got.append(objects.refresh(layer)))
        worker.start()
        time.sleep(0.3)  # the refresh is waiting for the lock
        assert worker.is_alive()
        layer.grid = replacement  # as `install_snapshot` does, under the lock
    worker.join(30)
    (found,) = got
    assert found is not None and [o.class_id for o in found] == [3]
    assert np.linalg.norm(found[0].position - centre) < 0.03


def test_a_new_grid_at_the_old_version_is_clustered_afresh():
    """A grid that replaced the layer's at the same version (a restore) is not taken for the
    grid already clustered: its objects replace the old ones."""
    layer = Layer("me", RESOLUTION)
    objects = OwnObjects(frozenset())
    first = np.array([1.013, 0.507, 0.311])
    layer.grid = _labelled_grid(layer, first, 3)
    found = objects.refresh(layer)
    assert found is not None and [o.class_id for o in found] == [3]
    assert objects.refresh(layer) is None  # unchanged
    second = np.array([-1.487, 1.209, 0.411])
    other = _labelled_grid(layer, second, 9)
    assert int(other.version) == int(layer.grid.version)  # same version, another grid
    with layer.lock:
        layer.grid = other
    found = objects.refresh(layer)
    assert found is not None and [o.class_id for o in found] == [9]
    assert np.linalg.norm(found[0].position - second) < 0.03
