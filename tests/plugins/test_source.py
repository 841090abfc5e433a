"""Tests of source spec parsing and open_source."""

from __future__ import annotations

from pathlib import Path

import pytest

from plugins.carmen import CarmenSource
from plugins.errors import SourceSpecError
from plugins.sevenscenes import RgbdSource
from plugins.sim import SimSource
from plugins.source import open_source, parse_spec
from plugins.stream import Source

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"


def test_parse_spec() -> None:
    spec = parse_spec("sim:world=office,agent=lidar-1")
    assert (spec.kind, spec.path, spec.options) == ("sim", None, {"world": "office", "agent": "lidar-1"})
    spec = parse_spec("replay:../data/log.gz,step=2,poses=odometry")
    assert (spec.kind, spec.path, spec.options) == ("replay", "../data/log.gz", {"step": "2", "poses": "odometry"})
    assert parse_spec("sim:").options == {}


@pytest.mark.parametrize(("spec", "message"), [
    ("office", r"expected 'sim:key=value,...' or 'replay:PATH', found 'office'"),
    ("lidar:x", r"expected 'sim:key=value,...' or 'replay:PATH', found 'lidar:x'"),
    ("replay:", r"expected 'replay:PATH\[,key=value...\]', found 'replay:'"),
    ("sim:world", r"expected key=value, found 'world'"),
    ("sim:seed=1,seed=2", r"expected each option once, found 'seed' twice"),
])
def test_bad_specs(spec: str, message: str) -> None:
    with pytest.raises(SourceSpecError, match=message):
        parse_spec(spec)


def test_open_sim_with_typed_options() -> None:
    source = open_source("sim:world=room,agent=lidar3d-1,frames=3,seed=7,noise=0.1,realtime=no")
    assert isinstance(source, SimSource) and isinstance(source, Source)
    assert (source.frames, source.seed, source.noise, source.realtime) == (3, 7, 0.1, False)
    assert len(list(source)) == 3
    assert source.spec == "sim:world=room,agent=lidar3d-1,frames=3,seed=7,noise=0.1,realtime=no"


def test_unknown_and_mistyped_options() -> None:
    with pytest.raises(SourceSpecError, match=r"option 'sede': expected one of \[.*'seed'.*\], found unknown option"):
        open_source("sim:sede=1")
    with pytest.raises(SourceSpecError, match=r"option 'frames': expected int, found 'many'"):
        open_source("sim:frames=many")
    with pytest.raises(SourceSpecError, match=r"option 'realtime': expected bool, found 'maybe'"):
        open_source("sim:realtime=maybe")


@pytest.mark.skipif(not DATA.is_dir(), reason=f"real data not found at {DATA}")
def test_open_replays() -> None:
    carmen = open_source(f"replay:{DATA}/carmen/freiburg-079-corrected.log.gz,step=1000,max_range=40")
    assert isinstance(carmen, CarmenSource) and len(carmen) == 5
    assert carmen.adapter.sensor_model.max_range == 40.0
    kitchen = open_source(f"replay:{DATA}/redkitchen-50,start=10,stop=20,stride=2")
    assert isinstance(kitchen, RgbdSource) and len(kitchen) == 10
    with pytest.raises(SourceSpecError, match=r"option 'poses': expected one of"):
        open_source(f"replay:{DATA}/redkitchen-50,poses=odometry")
    with pytest.raises(SourceSpecError, match=r"option 'format': expected auto, carmen, 7scenes, tum or rosbag, found 'pcd'"):
        open_source(f"replay:{DATA}/redkitchen-50,format=pcd")
