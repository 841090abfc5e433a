"""Sensor models: hit/miss probabilities, clamping and range, in log-odds."""

from __future__ import annotations

import math
from dataclasses import dataclass

from voxel.errors import InputError

#: Sensor kinds known to the history record (uint8 codes).
SENSOR_KINDS = {"unknown": 0, "depth": 1, "lidar2d": 2, "lidar3d": 3, "cctv": 4, "sim": 5}


def logodds(p: float) -> float:
    """Log-odds of probability p."""
    return math.log(p / (1.0 - p))


def probability(log_odds: float) -> float:
    """Probability of a log-odds value."""
    return 1.0 / (1.0 + math.exp(-log_odds))


@dataclass(frozen=True)
class SensorModel:
    """Inverse sensor model of one sensor; OctoMap's defaults.

    Points beyond `max_range` clear free space up to it and hit nothing (OctoMap's `maxrange`).
    A beam without a return clears only up to `free_range` (at most `max_range`): nothing came
    back, so how far the space is free is a guess, and clearing a scanner's whole range around
    every doorway and window fills the map with free space no wall bounds.
    """

    prob_hit: float = 0.7
    prob_miss: float = 0.4
    clamp_min: float = 0.12
    clamp_max: float = 0.97
    max_range: float = math.inf
    kind: str = "unknown"
    free_range: float = math.inf

    def __post_init__(self) -> None:
        for name in ("prob_hit", "prob_miss", "clamp_min", "clamp_max"):
            value = getattr(self, name)
            if not 0.0 < value < 1.0:
                msg = f"SensorModel.{name} must be a probability in (0, 1), found {value!r}"
                raise InputError(msg)
        if self.prob_hit <= 0.5:
            msg = f"SensorModel.prob_hit must be above 0.5, found {self.prob_hit!r}"
            raise InputError(msg)
        if self.prob_miss >= 0.5:
            msg = f"SensorModel.prob_miss must be below 0.5, found {self.prob_miss!r}"
            raise InputError(msg)
        if not self.clamp_min < 0.5 < self.clamp_max:
            msg = (
                "SensorModel clamping must satisfy clamp_min < 0.5 < clamp_max, found "
                f"{self.clamp_min!r}, {self.clamp_max!r}"
            )
            raise InputError(msg)
        if not self.max_range > 0:
            msg = f"SensorModel.max_range must be positive, found {self.max_range!r}"
            raise InputError(msg)
        if not self.free_range > 0:
            msg = f"SensorModel.free_range must be positive, found {self.free_range!r}"
            raise InputError(msg)
        if self.kind not in SENSOR_KINDS:
            msg = f"SensorModel.kind must be one of {sorted(SENSOR_KINDS)}, found {self.kind!r}"
            raise InputError(msg)

    @property
    def log_hit(self) -> float:
        return logodds(self.prob_hit)

    @property
    def log_miss(self) -> float:
        return logodds(self.prob_miss)

    @property
    def log_min(self) -> float:
        return logodds(self.clamp_min)

    @property
    def log_max(self) -> float:
        return logodds(self.clamp_max)

    @property
    def no_return_range(self) -> float:
        """How far a beam without a return clears: min(free_range, max_range)."""
        return min(self.free_range, self.max_range)

    @property
    def kind_code(self) -> int:
        return SENSOR_KINDS[self.kind]
