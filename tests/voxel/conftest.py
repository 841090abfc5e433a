"""Fixtures of the voxel tests: the traversal's two paths (compiled kernel and pure numpy)."""

from __future__ import annotations

import pytest

from voxel import kernels


@pytest.fixture(params=["numpy", "compiled"])
def kernel_path(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Runs a test once on the pure-numpy path and once on the compiled one (skipped without
    numba, the optional `fast` extra)."""
    if request.param == "numpy":
        monkeypatch.setattr(kernels._switch, "on", False)
        assert kernels.trace() is None
    else:
        pytest.importorskip("numba")
        monkeypatch.setattr(kernels._switch, "on", True)
        assert kernels.warm()
    return str(request.param)
