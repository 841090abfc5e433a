"""Bridge to the plugins' data sources (`sim:`, `replay:`) as daemon frame sources."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

from colonyd.errors import SourceError
from colonyd.source import Frame

#: Demo agents in the plugins' office world: cheap sensors, a few seconds of mapping each.
DEMO_AGENTS = (("lidar-1", 40), ("lidar3d-1", 40), ("depth-1", 25), ("lidar-1", 40))


class PluginSource:
    """Wraps a plugins source; each Observation becomes a frame integrated with its adapter."""

    def __init__(self, spec: str, inner: Any) -> None:
        self.name = spec
        self._inner = inner
        adapter = getattr(inner, "adapter", None)
        self.sensor = getattr(adapter, "sensor_model", None)
        self.reliability = float(getattr(adapter, "reliability", 1.0))

    def frames(self, stop: threading.Event) -> Iterator[Frame]:
        for obs in self._inner:
            if stop.is_set():
                return
            origin = obs.origin
            yield Frame(time=float(obs.time), origin=origin,
                        pose=(float(origin[0]), float(origin[1]), float(origin[2])),
                        extra={"observation": obs, "sensor": self.sensor,
                               "reliability": self.reliability})


def plugin_source(spec: str, resolution: float) -> PluginSource:
    """A plugins source from its spec, or SourceError saying what was expected."""
    try:
        from plugins.source import open_source
    except ImportError:
        msg = (f"source {spec!r}: plugin sources are not available in this build; "
               "expected one of 'synthetic:...', 'bulk:...'")
        raise SourceError(msg) from None
    return PluginSource(spec, open_source(spec))  # plugin errors propagate to launch()


def sim_spec(agent_index: int) -> str | None:
    """A short `sim:` spec for demo agent `agent_index` when the plugins provide sim sources."""
    try:
        import plugins.source  # noqa: F401
    except ImportError:
        return None
    agent, frames = DEMO_AGENTS[agent_index % len(DEMO_AGENTS)]
    return f"sim:world=office,agent={agent},frames={frames},seed={agent_index + 1},realtime=1"
