"""Tests of the bulk source: one ready-made layer as an observation carrying a delta."""

from __future__ import annotations

import numpy as np
import pytest

from plugins.bulk import BulkSource
from plugins.errors import SourceSpecError
from plugins.source import open_source
from plugins.stream import Source


def test_one_observation_with_a_delta_of_every_voxel() -> None:
    source = open_source("bulk:voxels=1000", resolution=0.05, seed=3)
    assert isinstance(source, BulkSource) and isinstance(source, Source) and len(source) == 1
    (obs,) = list(source)
    assert len(obs) == 0 and obs.delta is not None and len(obs.delta) == 1000
    assert obs.delta.resolution == 0.05 and (obs.delta.from_version, obs.delta.to_version) == (0, 1)
    assert len(np.unique(obs.delta.keys, axis=0)) == 1000
    np.testing.assert_array_equal(obs.delta.logodds * 32, np.round(obs.delta.logodds * 32))
    assert source.stats.delivered == 1


def test_seed_moves_the_cube_and_changes_the_values() -> None:
    (a,) = list(BulkSource(voxels=64, seed=1))
    (b,) = list(open_source("bulk:voxels=64", seed=1))
    (c,) = list(open_source("bulk:voxels=64,seed=2", seed=1))
    np.testing.assert_array_equal(a.delta.keys, b.delta.keys)
    np.testing.assert_array_equal(a.delta.logodds, b.delta.logodds)
    assert not np.array_equal(a.delta.keys, c.delta.keys)


@pytest.mark.parametrize(
    ("spec", "match"),
    [
        ("bulk:voxels=0", r"bulk: expected voxels > 0, found 0"),
        ("bulk:voxels=many", r"option 'voxels': expected int, found 'many'"),
        (
            "bulk:resolution=0.1",
            r"option 'resolution': expected one of \['seed', 'voxels'\], found unknown option",
        ),
    ],
)
def test_bad_specs(spec: str, match: str) -> None:
    with pytest.raises(SourceSpecError, match=match):
        open_source(spec)
