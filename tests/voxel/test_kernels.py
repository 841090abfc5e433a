"""The compiled kernels' loading: a daemon's callers never wait for a compilation."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from tests.voxel.test_grid_pinned import grid_digest
from voxel import kernels
from voxel.grid import VoxelGrid


@pytest.fixture
def unloaded(monkeypatch: pytest.MonkeyPatch) -> None:
    """Kernels on, none loaded yet in this process, no background mode."""
    pytest.importorskip("numba")
    monkeypatch.setattr(kernels._switch, "on", True)
    monkeypatch.setattr(kernels, "_compiled", {})
    monkeypatch.setattr(kernels, "_loading", kernels._Loading())


@pytest.mark.usefixtures("unloaded")
def test_in_background_mode_a_scan_takes_the_numpy_path_while_the_kernels_load() -> None:
    kernels.load_in_background()
    grid = VoxelGrid(0.1)
    pts = np.random.default_rng(1).uniform(-2, 2, size=(500, 3))
    done = threading.Event()

    def scan() -> None:
        grid.integrate(pts, np.zeros(3), time=0.0)
        done.set()

    # A loading in progress (as a compilation of ~11 s would be) holds the kernels' lock.
    with kernels._lock:
        worker = threading.Thread(target=scan, daemon=True)
        worker.start()
        assert done.wait(30), "the scan waited for the kernels' loading"
        assert "trace" not in kernels._compiled
        loader = kernels._loading.thread
        assert loader is not None and loader.is_alive()
    loader.join(60)
    assert kernels._compiled["trace"] is not None
    assert kernels.trace() is not None
    numpy_grid = grid  # integrated on the numpy path; the compiled path must agree
    compiled_grid = VoxelGrid(0.1)
    compiled_grid.integrate(pts, np.zeros(3), time=0.0)
    assert grid_digest(numpy_grid) == grid_digest(compiled_grid)


@pytest.mark.usefixtures("unloaded")
def test_without_background_mode_the_first_call_loads_them() -> None:
    assert kernels.trace() is not None
    assert kernels.warm()
