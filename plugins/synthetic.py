"""Synthetic source: a 2.5D scanner walking an empty square room, paced in real time until
stopped."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator

import numpy as np
from pydantic import Field

from plugins.adapter import SensorAdapter
from plugins.errors import SourceSpecError
from plugins.observation import Observation
from plugins.points import PointsAdapter
from plugins.spec import Options, SourceSpec, parse_options
from plugins.stream import SourceContext, StreamStats
from plugins.world import box_room

#: Height of the scanner above the floor, metres.
HEIGHT = 1.0


class SyntheticOptions(Options):
    """Options of `synthetic:`."""

    scans: int = Field(0, description="scans to take; 0 (or less) scans until the daemon stops")
    rate: float = Field(2.0, description="scans per second, paced in real time (> 0)")
    points: int = Field(360, description="beams per scan, evenly spread over a full turn (> 0)")
    seed: int | None = Field(
        None,
        description="seed of the walk and the return heights; none: the "
        "daemon's per-agent seed (0 in `colonyd map`)",
    )
    room: float = Field(8.0, description="side of the square room, metres (> 1)")
    step: float = Field(
        0.3, description="distance walked in a random direction between scans, metres"
    )


class SyntheticSource:
    """Horizontal beams from 1 m above the floor to the walls of a square room; each return lands at
    a random height in [0.1, 2.0) m. Scan times are wall-clock times."""

    def __init__(
        self,
        *,
        scans: int = 0,
        rate: float = 2.0,
        points: int = 360,
        seed: int = 0,
        room: float = 8.0,
        step: float = 0.3,
        spec: str = "",
        stop: threading.Event | None = None,
    ) -> None:
        if rate <= 0 or points <= 0 or room <= 1:
            msg = (
                "synthetic: expected rate > 0, points > 0 and room > 1, "
                f"found rate={rate}, points={points}, room={room}"
            )
            raise SourceSpecError(msg)
        self.scans, self.rate, self.points = scans, rate, points
        self.room, self.step = room, step
        self.spec = spec or "synthetic:"
        self.stop = stop if stop is not None else threading.Event()
        self.world = box_room(room)
        self.adapter: SensorAdapter = PointsAdapter("synthetic")
        self.stats = StreamStats()
        self.rng = np.random.default_rng(seed)
        self.pos = self.rng.uniform(1.0, room - 1.0, size=2)

    def __len__(self) -> int:
        return max(self.scans, 0)

    def scan(self, t: float) -> Observation:
        """Walk one step, then scan at time `t`."""
        angle = self.rng.uniform(0, 2 * math.pi)
        self.pos = np.clip(
            self.pos + self.step * np.array([math.cos(angle), math.sin(angle)]),
            0.5,
            self.room - 0.5,
        )
        a = np.linspace(0, 2 * math.pi, self.points, endpoint=False) + self.rng.uniform(0, 0.01)
        d = np.stack([np.cos(a), np.sin(a)], axis=1)
        origin = np.array([self.pos[0], self.pos[1], HEIGHT])
        r = self.world.cast(origin, np.column_stack([d, np.zeros(self.points)])).t * 0.999
        z = self.rng.uniform(0.1, 2.0, size=self.points)
        pose = np.eye(4)
        pose[:3, 3] = origin
        return self.adapter.observe(
            np.column_stack([d * r[:, None], z - HEIGHT]),
            pose=pose,
            time=t,
            frame=f"{self.spec}#{self.stats.delivered}",
        )

    def __iter__(self) -> Iterator[Observation]:
        n = 0
        period = 1.0 / self.rate
        next_t = time.monotonic()
        while not self.stop.is_set() and (self.scans <= 0 or n < self.scans):
            obs = self.scan(time.time())
            self.stats.delivered += 1
            yield obs
            n += 1
            next_t += period
            self.stop.wait(max(0.0, next_t - time.monotonic()))


def open_synthetic(spec: SourceSpec, context: SourceContext) -> SyntheticSource:
    """The `synthetic:` source of a parsed spec; the context gives the default seed and the stop
    event."""
    options = parse_options(SyntheticOptions, spec.options, spec.text)
    seed = context.seed if options.seed is None else options.seed
    return SyntheticSource(
        **options.model_dump(exclude={"seed"}), seed=seed, spec=spec.text, stop=context.stop
    )
