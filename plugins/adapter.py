"""Sensor adapter protocol and the registry of adapters found through `colony.sensors` entry
points."""

from __future__ import annotations

from importlib.metadata import EntryPoint, entry_points
from typing import Any, Protocol, runtime_checkable

import numpy as np

from plugins.errors import AdapterNotFoundError, PluginError
from plugins.observation import Observation
from voxel.sensor import SensorModel

#: Entry-point group under which every adapter (built-in or third-party) is registered.
GROUP = "colony.sensors"


@runtime_checkable
class SensorAdapter(Protocol):
    """Turns raw readings of one sensor into Observations and declares how far to trust them."""

    name: str
    kind: str  # a voxel.sensor.SENSOR_KINDS key
    sensor_model: SensorModel  # hit/miss probabilities, clamping, max range
    noise: float  # range noise, standard deviation in metres
    reliability: float  # default trust in (0, 1]

    def observe(
        self,
        reading: Any,
        *,
        pose: np.ndarray | None = None,
        time: float = 0.0,
        odometry: np.ndarray | None = None,
        frame: str = "",
    ) -> Observation:
        """Observation of `reading`; `pose` is the agent body's pose guess (world frame)."""
        ...


def adapter_entry_points() -> dict[str, EntryPoint]:
    """Every registered adapter entry point, by name."""
    return {ep.name: ep for ep in entry_points(group=GROUP)}


def available_adapters() -> list[str]:
    """Names of the registered adapters, sorted."""
    return sorted(adapter_entry_points())


def load_adapter(name: str, **params: Any) -> SensorAdapter:
    """Instantiate the adapter registered as `name` with keyword parameters."""
    points = adapter_entry_points()
    if name not in points:
        msg = f"sensor adapter: expected one of {sorted(points)}, found {name!r}"
        raise AdapterNotFoundError(msg)
    try:
        factory = points[name].load()
    except Exception as exc:  # a broken third-party distribution must not take the daemon down
        msg = f"sensor adapter {name!r}: cannot load {points[name].value}: {exc}"
        raise PluginError(msg) from exc
    try:
        adapter = factory(**params)
    except TypeError as exc:
        msg = f"sensor adapter {name!r}: bad parameters {sorted(params)}: {exc}"
        raise PluginError(msg) from None
    if not isinstance(adapter, SensorAdapter):
        msg = (
            f"sensor adapter {name!r}: expected an object with name, kind, sensor_model, noise, "
            f"reliability and observe(), found {type(adapter).__name__}"
        )
        raise PluginError(msg)
    return adapter
