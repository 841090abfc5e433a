"""The observer-to-agent transform from sightings, on constructed cases with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from voxel.errors import LocalisationError
from voxel.localisation import se2
from voxel.localisation.sightings import frame_from_sightings


def _believed(seen: np.ndarray, frame: np.ndarray) -> np.ndarray:
    return np.array([se2.compose(frame, p) for p in seen])


SEEN = np.array([[1.0, 2.0, 0.1], [3.0, 2.5, 0.5], [2.0, 4.0, -1.0], [0.5, 3.5, 2.0]])


def test_the_frame_is_found_from_four_sightings() -> None:
    frame = np.array([0.7, -1.2, 0.4])  # the observer's frame in the agent's
    rng = np.random.default_rng(1)
    noisy = _believed(SEEN, frame) + rng.normal(scale=[0.02, 0.02, 0.01], size=SEEN.shape)
    fit = frame_from_sightings(SEEN, noisy)
    assert fit.ok, fit.reason
    np.testing.assert_allclose(se2.from_matrix(fit.transform), frame, atol=0.03)
    assert fit.rmse < 0.04 and fit.spread > 2.0


def test_too_few_close_or_inconsistent_sightings_give_no_frame() -> None:
    frame = np.array([0.7, -1.2, 0.4])
    assert "4 sightings" in frame_from_sightings(SEEN[:3], _believed(SEEN[:3], frame)).reason
    close = SEEN * [0.1, 0.1, 1.0]
    assert "1.0 m apart" in frame_from_sightings(close, _believed(close, frame)).reason
    flipped = _believed(SEEN, frame)
    flipped[2, 2] += math.pi / 2  # one heading seen a quarter turn off
    assert not frame_from_sightings(SEEN, flipped).ok
    moved = _believed(SEEN, frame)
    moved[1, :2] += 0.6  # one position far off
    assert "rmse" in frame_from_sightings(SEEN, moved).reason
    with pytest.raises(LocalisationError, match=r"two \(N, 3\) arrays"):
        frame_from_sightings(SEEN, SEEN[:, :2])
