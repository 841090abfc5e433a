"""Tests of the synthetic source: scans, rendering with the world's ray caster, pacing, spec
errors."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from plugins.errors import SourceSpecError
from plugins.observation import Observation
from plugins.source import open_source
from plugins.stream import Source
from plugins.synthetic import SyntheticSource


def test_synthetic_and_bulk_sources():
    stop = threading.Event()
    frames = list(open_source("synthetic:scans=3,rate=100,points=50", stop=stop))
    assert len(frames) == 3 and frames[0].points.shape == (50, 3)
    (bulk,) = list(open_source("bulk:voxels=1000"))
    assert len(bulk.delta) == 1000


@pytest.mark.parametrize(
    ("spec", "match"),
    [
        (
            "synthetic:bogus=1",
            (
                r"option 'bogus': expected one of \['points', 'rate', 'room', 'scans', 'seed', "
                r"'step'\], found unknown option"
            ),
        ),
        ("synthetic:rate=fast", r"option 'rate': expected float, found 'fast'"),
        ("synthetic:points", r"expected key=value, found 'points'"),
        (
            "synthetic:rate=0",
            r"synthetic: expected rate > 0, points > 0 and room > 1, found rate=0.0",
        ),
        ("bulk:voxels=-1", r"bulk: expected voxels > 0, found -1"),
    ],
)
def test_bad_specs_say_what_was_expected(spec, match):
    with pytest.raises(SourceSpecError, match=match):
        open_source(spec)


def test_a_scan_is_an_observation_from_the_scanner():
    source = SyntheticSource(scans=2, rate=100, points=90, seed=1)
    assert isinstance(source, Source) and len(source) == 2
    obs = source.scan(12.5)
    assert isinstance(obs, Observation) and obs.time == 12.5 and len(obs) == 90
    np.testing.assert_array_equal(obs.pose[:3, :3], np.eye(3))
    assert obs.origin[2] == 1.0 and 0.5 <= obs.origin[0] <= 7.5 and 0.5 <= obs.origin[1] <= 7.5
    world = obs.points_world()
    assert world[:, 2].min() >= 0.1 - 1e-12 and world[:, 2].max() < 2.0 + 1e-12
    assert source.adapter.sensor_model.kind == "sim" and source.adapter.reliability == 1.0


def test_walls_rendered_by_the_world_are_where_the_box_formula_puts_them():
    source = SyntheticSource(points=720, room=10.0, seed=4)
    for _ in range(20):
        obs = source.scan(0.0)
        o = obs.origin[:2]
        d = obs.points[:, :2] / np.linalg.norm(obs.points[:, :2], axis=1, keepdims=True)
        with np.errstate(divide="ignore"):
            tx = np.where(d[:, 0] > 0, (10.0 - o[0]) / d[:, 0], -o[0] / d[:, 0])
            ty = np.where(d[:, 1] > 0, (10.0 - o[1]) / d[:, 1], -o[1] / d[:, 1])
        r = np.minimum(np.abs(tx), np.abs(ty)) * 0.999
        np.testing.assert_allclose(np.linalg.norm(obs.points[:, :2], axis=1), r, rtol=1e-12)


def test_same_seed_same_walk():
    a = [o.points_world() for o in SyntheticSource(scans=5, rate=1000, seed=9)]
    b = [o.points_world() for o in SyntheticSource(scans=5, rate=1000, seed=9)]
    c = [o.points_world() for o in SyntheticSource(scans=5, rate=1000, seed=10)]
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a[-1], c[-1])


def test_the_seed_comes_from_the_caller_unless_the_spec_sets_one():
    def first(spec: str, seed: int) -> np.ndarray:
        return next(iter(open_source(spec, seed=seed))).origin

    np.testing.assert_array_equal(
        first("synthetic:rate=1000", 5), first("synthetic:rate=1000,seed=5", 0)
    )
    np.testing.assert_array_equal(
        first("synthetic:rate=1000,seed=none", 5), first("synthetic:rate=1000", 5)
    )
    assert not np.array_equal(first("synthetic:rate=1000", 5), first("synthetic:rate=1000", 6))


def test_stop_ends_an_endless_source_while_it_waits():
    stop = threading.Event()
    source = open_source("synthetic:rate=0.2", stop=stop)  # scans=0: endless, one scan every 5 s
    assert len(source) == 0
    frames = iter(source)
    next(frames)
    threading.Timer(0.1, stop.set).start()
    began = time.monotonic()
    assert list(frames) == []
    assert time.monotonic() - began < 2.0 and source.stats.delivered == 1


def test_rate_paces_scans_in_real_time():
    began = time.monotonic()
    assert len(list(SyntheticSource(scans=3, rate=20, points=10))) == 3
    assert time.monotonic() - began >= 2 / 20 - 0.01
    assert math.isclose(SyntheticSource(rate=4).rate, 4.0)
