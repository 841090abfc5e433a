"""Daemon sources: synthetic and bulk specs, plugin specs, and their errors."""

from __future__ import annotations

import threading

import pytest

from colonyd.errors import ConfigError, SourceError
from colonyd.source import get_source
from plugins.errors import PluginError


def test_synthetic_and_bulk_sources():
    stop = threading.Event()
    frames = list(get_source("synthetic:scans=3,rate=100,points=50", 0.1).frames(stop))
    assert len(frames) == 3 and frames[0].points.shape == (50, 3)
    (bulk,) = list(get_source("bulk:voxels=1000", 0.1).frames(stop))
    assert len(bulk.delta) == 1000


@pytest.mark.parametrize(
    ("spec", "match"),
    [
        ("synthetic:bogus=1", r"unknown parameters \['bogus'\]"),
        ("synthetic:rate=fast", r"could not convert string to float: 'fast'"),
        ("synthetic:points", r"expected key=value in source parameters, found 'points'"),
        ("synthetic:rate=0", r"synthetic source needs rate>0"),
        ("bulk:voxels=-1", r"bulk source needs voxels>0"),
    ],
)
def test_bad_specs_say_what_was_expected(spec, match):
    with pytest.raises(SourceError, match=match) as info:
        get_source(spec, 0.1)
    assert isinstance(info.value, ConfigError)


def test_plugin_specs_go_to_the_plugins():
    stop = threading.Event()
    source = get_source("sim:world=office,agent=lidar-1,frames=2", 0.1)
    frames = list(source.frames(stop))
    assert len(frames) == 2 and "observation" in frames[0].extra
    with pytest.raises(PluginError, match="expected 'sim:key=value"):
        get_source("nope:x", 0.1)
