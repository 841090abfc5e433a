"""Sources of observations for the own layer: a synthetic scanner, a bulk filler, plugin sources."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from colonyd.errors import SourceError
from voxel.delta import Delta


@dataclass
class Frame:
    """One observation in the agent's map frame, or a ready-made delta (bulk)."""

    points: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    time: float = 0.0
    pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    delta: Delta | None = None
    extra: dict[str, Any] = field(default_factory=dict)


class Source(Protocol):
    """Yields frames until exhausted or `stop` is set."""

    name: str

    def frames(self, stop: threading.Event) -> Iterator[Frame]: ...


def _params(text: str) -> dict[str, str]:
    out: dict[str, str] = {}
    for part in filter(None, text.split(",")):
        if "=" not in part:
            msg = f"expected key=value in source parameters, found {part!r}"
            raise SourceError(msg)
        k, v = part.split("=", 1)
        out[k.strip()] = v.strip()
    return out


class SyntheticSource:
    """A 2.5D scanner walking a box room: scans of wall and floor points at a fixed rate."""

    name = "synthetic"

    def __init__(self, *, scans: int = 0, rate: float = 2.0, points: int = 360, seed: int = 0,
                 room: float = 8.0, step: float = 0.3) -> None:
        if rate <= 0 or points <= 0 or room <= 1:
            msg = f"synthetic source needs rate>0, points>0, room>1; found {rate}, {points}, {room}"
            raise SourceError(msg)
        self.scans, self.rate, self.points = scans, rate, points
        self.room, self.step = room, step
        self.rng = np.random.default_rng(seed)
        self.pos = self.rng.uniform(1.0, room - 1.0, size=2)

    def scan(self, t: float) -> Frame:
        angle = self.rng.uniform(0, 2 * math.pi)
        self.pos = np.clip(self.pos + self.step * np.array([math.cos(angle), math.sin(angle)]),
                           0.5, self.room - 0.5)
        a = np.linspace(0, 2 * math.pi, self.points, endpoint=False) + self.rng.uniform(0, 0.01)
        d = np.stack([np.cos(a), np.sin(a)], axis=1)
        with np.errstate(divide="ignore"):
            tx = np.where(d[:, 0] > 0, (self.room - self.pos[0]) / d[:, 0], -self.pos[0] / d[:, 0])
            ty = np.where(d[:, 1] > 0, (self.room - self.pos[1]) / d[:, 1], -self.pos[1] / d[:, 1])
        r = np.minimum(np.abs(tx), np.abs(ty)) * 0.999
        z = self.rng.uniform(0.1, 2.0, size=self.points)
        pts = np.column_stack([self.pos + d * r[:, None], z])
        origin = np.array([self.pos[0], self.pos[1], 1.0])
        return Frame(pts, origin, t, (float(self.pos[0]), float(self.pos[1]), 1.0))

    def frames(self, stop: threading.Event) -> Iterator[Frame]:
        n = 0
        period = 1.0 / self.rate
        next_t = time.monotonic()
        while not stop.is_set() and (self.scans <= 0 or n < self.scans):
            yield self.scan(time.time())
            n += 1
            next_t += period
            stop.wait(max(0.0, next_t - time.monotonic()))


class BulkSource:
    """One ready-made delta of `voxels` occupied voxels (benchmarks of catch-up)."""

    name = "bulk"

    def __init__(self, *, voxels: int = 1_000_000, resolution: float = 0.1, seed: int = 0) -> None:
        if voxels <= 0:
            msg = f"bulk source needs voxels>0, found {voxels}"
            raise SourceError(msg)
        self.voxels, self.resolution, self.seed = voxels, resolution, seed

    def frames(self, stop: threading.Event) -> Iterator[Frame]:
        side = int(math.ceil(self.voxels ** (1 / 3)))
        idx = np.arange(self.voxels, dtype=np.int64)
        keys = np.column_stack([idx // (side * side), (idx // side) % side, idx % side])
        keys += (self.seed % 64) * 2 * side
        rng = np.random.default_rng(self.seed)
        # What a grid holds: log-odds on its 1/32 grid, times in whole milliseconds.
        lo = (rng.integers(-64, 112, size=self.voxels) / 32).astype(np.float32)
        now = round(time.time() * 1000) / 1000.0
        delta = Delta(self.resolution, 0, 1, keys, lo, np.full(self.voxels, now), time=now)
        yield Frame(time=now, delta=delta)


def get_source(spec: str, resolution: float, seed: int = 0) -> Source:
    """A source from a spec `NAME:key=value,...`: synthetic:, bulk:, or a plugin's sim:/replay:."""
    name, _, rest = spec.partition(":")
    if name in ("synthetic", "bulk"):
        p = _params(rest)
        try:
            if name == "synthetic":
                src: Source = SyntheticSource(
                    scans=int(p.pop("scans", 0)), rate=float(p.pop("rate", 2.0)),
                    points=int(p.pop("points", 360)), seed=int(p.pop("seed", seed)),
                    room=float(p.pop("room", 8.0)), step=float(p.pop("step", 0.3)),
                )
            else:
                src = BulkSource(voxels=int(p.pop("voxels", 1_000_000)), resolution=resolution,
                                 seed=int(p.pop("seed", seed)))
        except ValueError as exc:
            raise SourceError(f"source {spec!r}: {exc}") from None
        if p:
            raise SourceError(f"source {spec!r}: unknown parameters {sorted(p)}")
        return src
    from colonyd.plugin_source import plugin_source

    return plugin_source(spec, resolution)
