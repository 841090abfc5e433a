"""Tests of the daemon's sources: opened from the config, seeded per agent, stopped with the
daemon."""

from __future__ import annotations

import threading
import zlib

import numpy as np
import pytest

from colonyd.config import load_config
from colonyd.daemon import get_sources
from plugins.bulk import BulkSource
from plugins.errors import PluginError, SourceSpecError
from plugins.observation import Observation
from plugins.sim import SimSource
from plugins.source import open_source
from plugins.synthetic import SyntheticSource


def test_plugin_specs_go_to_the_plugins():
    stop = threading.Event()
    config = load_config(
        None, agent_id="robot-1", sources=["sim:world=office,agent=lidar-1,frames=2"]
    )
    (source,) = get_sources(config, stop)
    frames = list(source)
    assert isinstance(source, SimSource) and len(frames) == 2 and isinstance(frames[0], Observation)
    with pytest.raises(PluginError, match="expected 'sim:key=value"):
        get_sources(load_config(None, sources=["nope:x"]), stop)


def test_sources_take_the_agents_seed_the_resolution_and_the_stop_event():
    stop = threading.Event()
    config = load_config(
        None,
        agent_id="robot-7",
        resolution=0.05,
        sources=["synthetic:scans=1,rate=1000", "bulk:voxels=64", "synthetic:seed=3,scans=1"],
    )
    synthetic, bulk, seeded = get_sources(config, stop)
    assert isinstance(synthetic, SyntheticSource) and isinstance(bulk, BulkSource)
    seed = zlib.crc32(b"robot-7") % (1 << 16)
    expected = next(iter(open_source("synthetic:scans=1,rate=1000", seed=seed)))
    np.testing.assert_array_equal(next(iter(synthetic)).points, expected.points)
    assert bulk.seed == seed + 1 and bulk.resolution == 0.05
    assert seeded.stop is stop and synthetic.stop is stop
    np.testing.assert_array_equal(
        next(iter(seeded)).origin, next(iter(open_source("synthetic:scans=1", seed=3))).origin
    )


def test_a_bad_spec_fails_before_anything_runs():
    config = load_config(None, sources=["synthetic:scans=1", "sim:frames=many"])
    with pytest.raises(SourceSpecError, match=r"option 'frames': expected int, found 'many'"):
        get_sources(config, threading.Event())


def test_only_sources_that_may_label_have_the_daemon_import_the_clustering():
    """A daemon imports scikit-learn (~1 s of CPU) at start-up only for sources whose adapter may
    label points: LiDARs and synthetic points say they do not, and do not; a depth camera and a
    CCTV do; an adapter that says nothing may."""
    from colonyd.daemon import may_label

    said = {}
    for spec in (
        "synthetic:scans=1,rate=100,points=50",
        "sim:world=office,agent=lidar-1,frames=2",
        "sim:world=office,agent=lidar3d-1,frames=2",
        "sim:world=office,agent=depth-1,frames=2",
    ):
        source = open_source(spec)
        said[spec] = may_label(source)
        if not said[spec]:  # what it says is true of what it delivers
            assert all(obs.class_ids is None for obs in source), spec
    assert list(said.values()) == [False, False, False, True], said
    assert may_label(open_source("sim:world=office,agent=cctv-1,frames=1"))
    source = open_source("synthetic:scans=1")
    source.adapter = type("ThirdParty", (), {"kind": "sim"})()  # says nothing: it may
    assert may_label(source)
