"""Bridge to the plugins' data sources (`sim:`, `replay:`, ...) as daemon frame sources."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import numpy as np

from colonyd.errors import SourceError
from colonyd.source import Frame


class PluginSource:
    """Wraps a plugins source; each Observation becomes a frame in the map frame."""

    def __init__(self, spec: str, inner: Any) -> None:
        self.name = spec
        self._inner = inner

    def frames(self, stop: threading.Event) -> Iterator[Frame]:
        for obs in self._inner:
            if stop.is_set():
                return
            pts = np.asarray(obs.points_world(), dtype=np.float64)
            origin = np.asarray(obs.origin, dtype=np.float64)
            yield Frame(pts, origin, float(getattr(obs, "time", 0.0)),
                        tuple(float(x) for x in origin[:3]), extra={"observation": obs})


def plugin_source(spec: str, resolution: float) -> PluginSource:
    """A plugins source from its spec, or SourceError naming what is available."""
    try:
        from plugins import sources  # type: ignore[attr-defined]
    except ImportError:
        msg = (f"source {spec!r}: plugin sources are not available in this build; "
               "expected one of 'synthetic:...', 'bulk:...'")
        raise SourceError(msg) from None
    try:
        inner = sources.open_source(spec)
    except Exception as exc:
        raise SourceError(f"source {spec!r}: {exc}") from None
    return PluginSource(spec, inner)


def sim_spec(agent_index: int) -> str | None:
    """A short `sim:` spec for demo agent `agent_index` when the plugins provide sim sources."""
    try:
        from plugins import sources  # type: ignore[attr-defined]  # noqa: F401
    except ImportError:
        return None
    return None
