"""Bulk source: one ready-made layer of many occupied voxels, for benchmarks of catch-up."""

from __future__ import annotations

import math
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
from voxel.delta import Delta


class BulkOptions(Options):
    """Options of `bulk:`."""

    voxels: int = Field(1_000_000, description="occupied voxels in the layer, a cube of them (> 0)")
    seed: int | None = Field(
        None,
        description="seed of the log-odds values and of the cube's place; "
        "none: the daemon's per-agent seed (0 in `colonyd map`)",
    )


class BulkSource:
    """One observation carrying a delta of `voxels` voxels with random log-odds, on the grid's 1/32
    steps."""

    def __init__(
        self, *, voxels: int = 1_000_000, resolution: float = 0.1, seed: int = 0, spec: str = ""
    ) -> None:
        if voxels <= 0:
            msg = f"bulk: expected voxels > 0, found {voxels}"
            raise SourceSpecError(msg)
        self.voxels, self.resolution, self.seed = voxels, resolution, seed
        self.spec = spec or "bulk:"
        self.adapter: SensorAdapter = PointsAdapter("bulk")
        self.stats = StreamStats()

    def __len__(self) -> int:
        return 1

    def delta(self) -> Delta:
        """The layer as one delta from version 0 to 1, timed now."""
        side = math.ceil(self.voxels ** (1 / 3))
        idx = np.arange(self.voxels, dtype=np.int64)
        keys = np.column_stack([idx // (side * side), (idx // side) % side, idx % side])
        keys += (self.seed % 64) * 2 * side
        rng = np.random.default_rng(self.seed)
        # What a grid holds: log-odds on its 1/32 grid, times in whole milliseconds.
        lo = (rng.integers(-64, 112, size=self.voxels) / 32).astype(np.float32)
        now = round(time.time() * 1000) / 1000.0
        return Delta(self.resolution, 0, 1, keys, lo, np.full(self.voxels, now), time=now)

    def __iter__(self) -> Iterator[Observation]:
        delta = self.delta()
        obs = Observation(
            sensor=self.adapter.name,
            time=delta.time,
            points=np.empty((0, 3)),
            pose=np.eye(4),
            delta=delta,
            frame=f"{self.spec}#0",
        )
        self.stats.delivered += 1
        yield obs


def open_bulk(spec: SourceSpec, context: SourceContext) -> BulkSource:
    """The `bulk:` source of a parsed spec; the context gives the grid's resolution and the default
    seed."""
    options = parse_options(BulkOptions, spec.options, spec.text)
    seed = context.seed if options.seed is None else options.seed
    return BulkSource(
        voxels=options.voxels, resolution=context.resolution, seed=seed, spec=spec.text
    )
