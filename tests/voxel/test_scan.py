"""Tests of scan input: validation messages, and beams sorted into hits, clearing, invalid,
dropped."""

from __future__ import annotations

import numpy as np
import pytest

from voxel.errors import InputError
from voxel.scan import Scan, as_points, sort_beams
from voxel.sensor import SensorModel


def test_errors_say_what_was_expected_and_what_was_found() -> None:
    pts = np.ones((2, 3))
    with pytest.raises(InputError, match="points must be numeric, found dtype <U1"):
        as_points(np.array([["a", "b", "c"]]))
    with pytest.raises(InputError, match=r"time must be a finite number of seconds, found nan"):
        Scan.of(pts, np.zeros(3), time=float("nan"), reliability=1.0)
    with pytest.raises(InputError, match=r"reliability must be in \(0, 1\], found 1.5"):
        Scan.of(pts, np.zeros(3), time=0.0, reliability=1.5)
    with pytest.raises(
        InputError, match=r"no_return must have shape \(2,\) \(one row per point\), found \(3,\)"
    ):
        Scan.of(pts, np.zeros(3), time=0.0, reliability=1.0, no_return=np.zeros(3, dtype=bool))
    with pytest.raises(InputError, match=r"scalars\['t'\] must have shape \(2,\) .*found \(\)"):
        Scan.of(pts, np.zeros(3), time=0.0, reliability=1.0, scalars={"t": None})  # type: ignore[dict-item]


def test_beams_are_sorted_by_what_they_do() -> None:
    origin = np.array([0.01, 0.02, 0.03])
    pts = np.array(
        [[1.0, 0, 0], [5.0, 0, 0], [0, 1.0, 0], [np.nan, 0, 0], [0.01, 0.02, 0.03], [1e9, 0, 0]]
    )
    no_return = np.array([False, False, True, False, False, False])
    scan = Scan.of(
        pts,
        origin,
        time=0.0,
        reliability=1.0,
        no_return=no_return,
        colours=np.arange(18).reshape(6, 3),
    )
    beams = sort_beams(scan, SensorModel(max_range=2.0), 0.1)
    assert (beams.hits, beams.cleared, beams.invalid, beams.dropped) == (1, 3, 2, 0)
    assert beams.hit_mask.tolist() == [True, False, False, False, False, False]
    assert beams.hit_keys.T.tolist() == [[10.0, 0.0, 0.0]]
    assert np.allclose(np.linalg.norm(beams.clear_ends - origin, axis=1), 2.0)
    assert scan.channels.select(np.flatnonzero(beams.hit_mask)).colours.tolist() == [[0, 1, 2]]  # type: ignore[union-attr]
    # Without a finite max range, no-return and far beams cannot clear: dropped.
    beams = sort_beams(scan, SensorModel(), 0.1)
    assert (beams.hits, beams.cleared, beams.invalid, beams.dropped) == (
        2,
        0,
        3,
        1,
    )  # 1e9 m: off the key space


def test_beams_without_a_return_clear_only_up_to_the_free_range() -> None:
    """OctoMap's maxrange for beams that saw nothing: a no-return beam clears up to free_range,
    a point beyond max range still clears up to max range."""
    origin = np.zeros(3)
    pts = np.array([[0, 7.0, 0], [9.0, 0, 0], [0, 0, 1.0]])
    scan = Scan.of(pts, origin, time=0.0, reliability=1.0, no_return=np.array([True, False, False]))
    beams = sort_beams(scan, SensorModel(max_range=5.0, free_range=1.5), 0.1)
    assert (beams.hits, beams.cleared, beams.dropped) == (1, 2, 0)
    reach = sorted(np.linalg.norm(beams.clear_ends - origin, axis=1).round(6).tolist())
    assert reach == [1.5, 5.0]
    # Without a max range, a free range alone lets no-return beams clear.
    beams = sort_beams(scan, SensorModel(free_range=2.0), 0.1)
    assert (beams.hits, beams.cleared, beams.dropped) == (2, 1, 0)
    assert np.allclose(np.linalg.norm(beams.clear_ends, axis=1), 2.0)
    with pytest.raises(InputError, match="free_range must be positive, found 0"):
        SensorModel(free_range=0.0)
