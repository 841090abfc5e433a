"""Wheel odometry model: exact without noise, biased as documented, seeded, variance linear in
distance."""

from __future__ import annotations

import math

import numpy as np
import pytest

from voxel.errors import LocalisationError
from voxel.localisation import se2
from voxel.localisation.odometry import (
    PRESETS,
    OdometryNoise,
    WheelOdometer,
    parse_noise,
    synthesise,
)


def _straight(n: int, step: float) -> np.ndarray:
    return np.column_stack([np.arange(n) * step, np.zeros(n), np.zeros(n)])


def test_no_noise_reproduces_the_reference() -> None:
    t = np.linspace(0, 2 * math.pi, 100)
    ref = np.column_stack([np.cos(t), np.sin(t), se2.wrap(t + math.pi / 2)])
    np.testing.assert_allclose(synthesise(ref, PRESETS["none"]), ref, atol=1e-9)


def test_biases_only_give_the_documented_scale_and_heading_drift() -> None:
    noise = OdometryNoise(0.0, 0.0, 0.0, scale_bias=0.01, yaw_bias=0.002)
    odo = synthesise(_straight(101, 0.1), noise)  # 10 m straight
    assert odo[-1, 2] == pytest.approx(0.002 * 10.0, rel=1e-6)
    assert math.hypot(*odo[-1, :2]) == pytest.approx(10.1, rel=1e-3)


def test_random_walk_does_not_depend_on_the_sampling_rate() -> None:
    noise = OdometryNoise(0.05, 0.0, 0.0, 0.0, 0.0)
    finals = {}
    for step in (0.05, 0.5):
        n = round(10.0 / step) + 1
        ends = [synthesise(_straight(n, step), noise, seed)[-1, 1] for seed in range(300)]
        finals[step] = float(np.std(ends))
    # lateral sd after 10 m is trans * sqrt(10) = 0.158 m at either rate
    assert finals[0.05] == pytest.approx(0.05 * math.sqrt(10), rel=0.15)
    assert finals[0.5] == pytest.approx(0.05 * math.sqrt(10), rel=0.15)


def test_seeded() -> None:
    ref = _straight(50, 0.2)
    np.testing.assert_array_equal(
        synthesise(ref, PRESETS["realistic"], 7), synthesise(ref, PRESETS["realistic"], 7)
    )
    assert not np.array_equal(
        synthesise(ref, PRESETS["realistic"], 7), synthesise(ref, PRESETS["realistic"], 8)
    )
    odometer = WheelOdometer(np.zeros(3), PRESETS["none"])
    np.testing.assert_allclose(odometer.step(np.array([1.0, 0.0, 0.5])), [1.0, 0.0, 0.5])


def test_parse_noise() -> None:
    assert parse_noise("realistic") == OdometryNoise()
    assert parse_noise("0.1/0.2/0.03/0/0.001") == OdometryNoise(0.1, 0.2, 0.03, 0.0, 0.001)
    assert parse_noise(OdometryNoise().text) == OdometryNoise()
    with pytest.raises(
        LocalisationError, match=r"expected one of .* or five numbers .* found 'loud'"
    ):
        parse_noise("loud")
    with pytest.raises(LocalisationError, match=r"trans: expected a finite number \(>= 0"):
        parse_noise("-1/0/0/0/0")
    with pytest.raises(LocalisationError, match=r"planar poses \(N, 3\)"):
        synthesise(np.zeros((3, 4)), OdometryNoise())
