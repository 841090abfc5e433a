"""Wheel odometry noise model: random-walk errors growing with distance and turn, plus scale and
heading bias.

An increment of true motion (dx, dy, dyaw) in the body frame, over distance d = |(dx, dy)|, is
read as

    dx' = (1 + scale_bias) dx + trans * sqrt(d) * n1
    dy' = (1 + scale_bias) dy + trans * sqrt(d) * n2
    dyaw' = dyaw + yaw_bias * d + sqrt(rot^2 |dyaw| + rot_per_m^2 d) * n3

with n1, n2, n3 independent standard normal draws from a seeded generator. The variances grow
linearly with distance and turn (a random walk), so the error of a path does not depend on how
often odometry is sampled; the biases are systematic (a wheel radius off by `scale_bias`,
unequal wheels turning the robot by `yaw_bias` radians per metre).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import numpy.typing as npt

from voxel.errors import LocalisationError
from voxel.localisation import se2


@dataclass(frozen=True)
class OdometryNoise:
    """Parameters of the wheel odometry noise model (see the module docstring)."""

    trans: float = 0.05  # m per sqrt(m): standard deviation of forward and lateral error
    rot: float = 0.05  # rad per sqrt(rad) turned
    rot_per_m: float = 0.01  # rad per sqrt(m) driven
    scale_bias: float = 0.01  # distances read 1 % long
    yaw_bias: float = 0.002  # rad per metre of systematic heading drift (0.11 degrees per metre)

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            if not math.isfinite(value) or (name in ("trans", "rot", "rot_per_m") and value < 0):
                msg = (
                    f"odometry noise {name}: expected a finite number (>= 0 for noise), "
                    f"found {value!r}"
                )
                raise LocalisationError(msg)

    @property
    def text(self) -> str:
        """The spec text of these parameters (trans/rot/rot_per_m/scale_bias/yaw_bias)."""
        return "/".join(f"{v:g}" for v in asdict(self).values())


#: Named noise levels; "realistic" is the documented default for benchmarks.
PRESETS: dict[str, OdometryNoise] = {
    "none": OdometryNoise(0.0, 0.0, 0.0, 0.0, 0.0),
    "low": OdometryNoise(0.02, 0.02, 0.005, 0.005, 0.001),
    "realistic": OdometryNoise(),
    "high": OdometryNoise(0.1, 0.1, 0.02, 0.02, 0.005),
}


def parse_noise(text: str) -> OdometryNoise:
    """A preset name (none, low, realistic, high) or five numbers
    trans/rot/rot_per_m/scale_bias/yaw_bias."""
    text = text.strip()
    if text in PRESETS:
        return PRESETS[text]
    parts = text.split("/")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 5:
        msg = (
            f"odometry noise: expected one of {sorted(PRESETS)} or five numbers "
            f"trans/rot/rot_per_m/scale_bias/yaw_bias, found {text!r}"
        )
        raise LocalisationError(msg)
    return OdometryNoise(*values)


class WheelOdometer:
    """Dead reckoning of a ground robot from noisy readings of its true planar motion (seeded)."""

    def __init__(
        self, start: np.ndarray, noise: OdometryNoise, seed: int | np.random.Generator = 0
    ) -> None:
        self.truth = np.asarray(start, np.float64)[:3].copy()
        self.pose = self.truth.copy()
        self.noise = noise
        self.rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)

    def read(self, increment: np.ndarray) -> np.ndarray:
        """The noisy reading (dx', dy', dyaw') of a true body-frame increment (dx, dy, dyaw)."""
        dx, dy, da = increment
        d = math.hypot(dx, dy)
        m = self.noise
        n = self.rng.normal(size=3)
        sd_t = m.trans * math.sqrt(d)
        sd_a = math.sqrt(m.rot**2 * abs(da) + m.rot_per_m**2 * d)
        return np.array(
            [
                (1 + m.scale_bias) * dx + sd_t * n[0],
                (1 + m.scale_bias) * dy + sd_t * n[1],
                da + m.yaw_bias * d + sd_a * n[2],
            ]
        )

    def step(self, truth: npt.ArrayLike) -> np.ndarray:
        """Advance to the true pose `truth` (x, y, yaw); returns the odometry pose (x, y, yaw)."""
        true_pose = np.asarray(truth, np.float64)[:3]
        self.pose = se2.compose(self.pose, self.read(se2.relative(self.truth, true_pose)))
        self.truth = true_pose.copy()
        return self.pose.copy()


def synthesise(reference: np.ndarray, noise: OdometryNoise, seed: int = 0) -> np.ndarray:
    """Odometry poses (N, 3) of a robot that followed the planar `reference` poses (N, 3), starting
    at the first."""
    ref = np.asarray(reference, np.float64)
    if ref.ndim != 2 or ref.shape[1] != 3:
        msg = f"reference: expected planar poses (N, 3), found shape {ref.shape}"
        raise LocalisationError(msg)
    if len(ref) == 0:
        return ref.copy()
    odometer = WheelOdometer(ref[0], noise, seed)
    return np.array([ref[0]] + [odometer.step(p) for p in ref[1:]])
