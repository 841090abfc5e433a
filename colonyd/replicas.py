"""Replicas: peers' deltas admitted and folded into their layers, with what it did counted."""

from __future__ import annotations

import time

import numpy as np

from colonyd.errors import WireError
from colonyd.layers import Layers
from colonyd.metrics import Metrics
from voxel.delta import Delta

#: The highest layer version a replica takes: its grid keeps versions as 32-bit integers (the
#: wire allows 63 bits; a layer publishing ten deltas a second reaches it in 13 years).
MAX_VERSION = (1 << 32) - 1
#: The furthest from the Unix epoch (seconds) a voxel's time may lie: its grid keeps times as
#: integer milliseconds in int64 arithmetic (2^53 ms, ~285,000 years); a voxel without a time
#: (the wire's NaN code) has no place there either.
MAX_ABS_TIME_S = float(1 << 53) / 1000.0


class Replicas:
    """The peer side of `Layers`: admission (headers, budgets) and ordered application."""

    def __init__(self, layers: Layers, metrics: Metrics) -> None:
        self.layers = layers
        self.metrics = metrics

    def admit(self, origin: str, epoch: int, deltas: list[Delta], replace: bool = False) -> None:
        """Raise WireError unless `deltas` (a snapshot if `replace`) may enter `origin`'s layer."""
        for d in deltas:
            prev, seq = d.from_version, d.to_version
            if not (0 <= prev < seq) or epoch <= 0:
                raise WireError("bad-header", f"delta header invalid: epoch {epoch} {prev}->{seq}")
            if seq > MAX_VERSION:
                text = (
                    f"expected layer versions up to {MAX_VERSION} (a replica's grid keeps 32-bit "
                    f"versions), found {prev}->{seq}"
                )
                raise WireError("bad-header", text)
            times = d.last_time
            if len(times) and not bool(np.all(np.abs(times) <= MAX_ABS_TIME_S)):
                bad = times[~(np.abs(times) <= MAX_ABS_TIME_S)][0]
                text = (
                    f"expected a time within {MAX_ABS_TIME_S:.3g} s of the Unix epoch for every "
                    f"voxel (a replica's grid keeps one), found {bad}"
                )
                raise WireError("bad-time", text)
        self.layers.admit(origin, deltas, replace=replace)

    def offer(
        self, origin: str, epoch: int, delta: Delta, *, admitted: bool = False, via: str = "frame"
    ) -> bool:
        """Fold a whole delta of `origin`'s layer (epoch `epoch`, covering (from, to]) into it;
        True if the layer is left with a gap to repair. `admitted`: the caller has just admitted
        this very delta (a single-part frame), so its budget is not counted twice. `via` says
        how it came ("frame" or "range": `Metrics.applied`)."""
        if not admitted:
            self.admit(origin, epoch, [delta])
        layer = self.layers.get(origin, delta.resolution)
        result = layer.offer(epoch, delta.from_version, delta.to_version, delta, delta.time)
        now = time.time()
        if result.outcome == "duplicate":
            self.metrics.add("duplicates")
        elif result.outcome == "stale-epoch":
            self.metrics.add("stale_epoch")
        for s, c in result.drained:
            self.metrics.sample(origin, s, c, now, via if s == delta.to_version else "held")
        if result.drained:
            self.metrics.add("deltas_applied", len(result.drained))
        if result.missing is not None:
            self.metrics.add("gaps")
            return True
        return False
