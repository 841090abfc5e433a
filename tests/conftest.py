"""Session set-up for the whole suite: the compiled kernels are built once, before any test."""

from __future__ import annotations

import pytest


@pytest.hookimpl(tryfirst=True)
def pytest_sessionstart(session: pytest.Session) -> None:
    """Compile and cache the numba kernels (voxel/kernels.py) in the controlling process, before
    xdist starts its workers. On a fresh clone nothing is cached: every daemon a test starts
    would compile them itself (~44 CPU-s each with the codec's, measured), on the numpy path
    meanwhile: the first live tests ran slowly and timed out. Warm, each process loads the
    cached code in ~0.5 s."""
    if hasattr(session.config, "workerinput"):  # an xdist worker: the controller did it
        return
    from voxel import kernels

    kernels.warm()
    kernels.warm_codec()
