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


@pytest.mark.parametrize("free_range", [4.0, float("inf")])
def test_compiled_beams_are_the_numpy_beams(monkeypatch, free_range) -> None:
    # The compiled sorting (voxel/kernels.py) gives bit-identical beams: the same hits, the same
    # one beam chosen per fine cell (many beams share cells here), the same counts.
    pytest.importorskip("numba")
    from voxel import kernels

    rng = np.random.default_rng(7)
    origin = np.array([0.013, -0.021, 0.3])
    d = rng.normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts = origin + d * rng.uniform(0.0, 12.0, (3000, 1))
    pts[::97] = np.nan
    pts[5::101] = origin  # zero-length
    pts[7::103, 0] = 1e9  # key outside the key space
    pts[::5] = origin + d[::5] * 50.0  # beyond max range: clear up to it, many in one cell
    nr = rng.random(3000) < 0.2
    without_range = SensorModel(free_range=free_range)
    for sensor in (SensorModel(max_range=8.0, free_range=free_range), without_range):
        scan = Scan.of(pts, origin, time=0.0, reliability=1.0, no_return=nr)
        out = []
        for flag in ("0", "1"):
            monkeypatch.setattr(kernels._switch, "on", flag == "1")
            out.append(sort_beams(scan, sensor, 0.05))
        assert kernels.beams() is not None
        numpy_b, compiled_b = out
        assert compiled_b.clear_ends.shape[0] > 0 or not np.isfinite(sensor.no_return_range)
        for name in ("hit_keys", "hit_mask", "clear_ends"):
            np.testing.assert_array_equal(getattr(compiled_b, name), getattr(numpy_b, name))
        for name in ("cleared", "invalid", "dropped"):
            assert getattr(compiled_b, name) == getattr(numpy_b, name), name
        # The bounds the traversal's box is built from: every hit key and clear end's key.
        keys = np.concatenate(
            [numpy_b.hit_keys.T, np.floor(numpy_b.clear_ends * (1.0 / 0.05))]
        ).astype(np.int64)
        assert compiled_b.bounds is not None
        np.testing.assert_array_equal(compiled_b.bounds, [keys.min(axis=0), keys.max(axis=0)])


def test_compiled_distinct_hits_leave_repeats_out(monkeypatch) -> None:
    # A scan without channels needs no row per hit point: the compiled sorting then leaves
    # repeated hit keys out (pixels of a depth image share voxels), keeping every distinct key,
    # the order, the counts and the bounds; the grid built from it is the same.
    pytest.importorskip("numba")
    from voxel import kernels

    rng = np.random.default_rng(11)
    origin = np.array([0.02, -0.01, 0.4])
    pts = origin + 1.0 + rng.uniform(-0.2, 0.2, (20000, 3))  # ~40 points per 5 cm voxel
    pts[::7] = pts[::7][::-1]  # not only neighbours repeat
    sensor = SensorModel(max_range=3.0)
    scan = Scan.of(pts, origin, time=0.0, reliability=1.0)
    monkeypatch.setattr(kernels._switch, "on", False)
    every = sort_beams(scan, sensor, 0.05)
    monkeypatch.setattr(kernels._switch, "on", True)
    assert kernels.warm()
    few = sort_beams(scan, sensor, 0.05, distinct=True)
    assert few.hit_keys.shape[1] < every.hit_keys.shape[1] // 4
    assert (few.hits, few.cleared, few.invalid) == (every.hits, every.cleared, every.invalid)
    np.testing.assert_array_equal(few.hit_mask, every.hit_mask)
    np.testing.assert_array_equal(
        np.unique(few.hit_keys, axis=1), np.unique(every.hit_keys, axis=1)
    )
    # A subsequence of every hit key, in order: each kept key is the next of its kind.
    keep = [tuple(k) for k in few.hit_keys.T]
    j = 0
    for key in map(tuple, every.hit_keys.T):
        if j < len(keep) and key == keep[j]:
            j += 1
    assert j == len(keep)


@pytest.mark.parametrize("max_range", [3.0, 40.0])
def test_compiled_sorting_checks_hit_keys_only_where_the_ball_leaves_the_key_space(
    monkeypatch, max_range
) -> None:
    # The compiled sorting leaves out the key-space test of a hit when the sensor's ball lies
    # inside the key space; near its edge (here 40 m reaches beyond it) each hit is tested, and
    # hits past the edge are invalid, as on the numpy path.
    pytest.importorskip("numba")
    from voxel import kernels
    from voxel import keys as vk

    res = 0.05
    origin = np.array([vk.KEY_MAX * res - 20.0, 0.1, -0.2])
    rng = np.random.default_rng(3)
    d = rng.normal(size=(4000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts = origin + d * rng.uniform(0.5, 60.0, (4000, 1))
    scan = Scan.of(pts, origin, time=0.0, reliability=1.0)
    sensor = SensorModel(max_range=max_range)
    out = []
    for on in (False, True):
        monkeypatch.setattr(kernels._switch, "on", on)
        out.append(sort_beams(scan, sensor, res))
    assert kernels.beams() is not None
    numpy_b, compiled_b = out
    assert numpy_b.invalid > 0 if max_range > 20.0 else numpy_b.invalid == 0
    for name in ("hit_keys", "hit_mask", "clear_ends"):
        np.testing.assert_array_equal(getattr(compiled_b, name), getattr(numpy_b, name))
    assert (compiled_b.hits, compiled_b.cleared, compiled_b.invalid) == (
        numpy_b.hits,
        numpy_b.cleared,
        numpy_b.invalid,
    )
