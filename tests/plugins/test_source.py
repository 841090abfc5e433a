"""Tests of the source registry: spec parsing, open_source for every kind, the reference text."""

from __future__ import annotations

import inspect
from pathlib import Path

import pytest

from plugins.bulk import BulkOptions, BulkSource
from plugins.carmen import CarmenOptions, CarmenSource
from plugins.errors import SourceSpecError
from plugins.rosbag import RosbagOptions, RosbagSource
from plugins.sevenscenes import RgbdOptions, RgbdSource
from plugins.sim import SimOptions, SimSource
from plugins.source import SOURCE_KINDS, describe_sources, open_source, parse_spec
from plugins.stream import Source
from plugins.synthetic import SyntheticOptions, SyntheticSource
from tests.shared import SHARED_DATA, fresh_process

DATA = SHARED_DATA


def test_parse_spec() -> None:
    spec = parse_spec("sim:world=office,agent=lidar-1")
    assert (spec.kind, spec.path, spec.options) == (
        "sim",
        None,
        {"world": "office", "agent": "lidar-1"},
    )
    spec = parse_spec("replay:../data/log.gz,step=2,poses=odometry")
    assert (spec.kind, spec.path, spec.options) == (
        "replay",
        "../data/log.gz",
        {"step": "2", "poses": "odometry"},
    )
    assert parse_spec("sim:").options == {}


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        (
            "office",
            (
                r"expected 'sim:key=value,...', 'replay:PATH\[,key=value...\]', "
                r"'ros2:key=value,...', 'synthetic:key=value,...' or 'bulk:key=value,...', "
                r"found 'office'"
            ),
        ),
        (
            "lidar:x",
            r"expected 'sim:key=value,...', 'replay:PATH\[,key=value...\]', .* found 'lidar:x'",
        ),
        ("replay:", r"expected 'replay:PATH\[,key=value...\]', found 'replay:'"),
        ("sim:world", r"expected key=value, found 'world'"),
        ("sim:seed=1,seed=2", r"expected each option once, found 'seed' twice"),
    ],
)
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
    with pytest.raises(
        SourceSpecError,
        match=r"option 'sede': expected one of \[.*'seed'.*\], found unknown option",
    ):
        open_source("sim:sede=1")
    with pytest.raises(SourceSpecError, match=r"option 'frames': expected int, found 'many'"):
        open_source("sim:frames=many")
    with pytest.raises(SourceSpecError, match=r"option 'realtime': expected bool, found 'maybe'"):
        open_source("sim:realtime=maybe")


@pytest.mark.skipif(not DATA.is_dir(), reason=f"real data not found at {DATA}")
def test_open_replays() -> None:
    carmen = open_source(
        f"replay:{DATA}/carmen/freiburg-079-corrected.log.gz,step=1000,max_range=40"
    )
    assert isinstance(carmen, CarmenSource) and len(carmen) == 5
    assert carmen.adapter.sensor_model.max_range == 40.0
    kitchen = open_source(f"replay:{DATA}/redkitchen-50,start=10,stop=20,stride=2")
    assert isinstance(kitchen, RgbdSource) and len(kitchen) == 10
    with pytest.raises(SourceSpecError, match=r"option 'poses': expected one of"):
        open_source(f"replay:{DATA}/redkitchen-50,poses=odometry")
    with pytest.raises(
        SourceSpecError,
        match=(
            r"option 'format': expected 'auto', 'carmen', '7scenes', 'tum' or 'rosbag', "
            r"found 'pcd'"
        ),
    ):
        open_source(f"replay:{DATA}/redkitchen-50,format=pcd")


def test_every_kind_opens_from_its_spec() -> None:
    assert set(SOURCE_KINDS) == {"sim", "replay", "ros2", "synthetic", "bulk"}
    assert isinstance(open_source("synthetic:scans=1"), SyntheticSource)
    assert isinstance(open_source("bulk:voxels=8"), BulkSource)
    for source in (
        open_source("synthetic:scans=1"),
        open_source("bulk:voxels=8"),
        open_source("sim:frames=1"),
        open_source("ros2:scan=/scan,frame=map"),
    ):
        assert isinstance(source, Source)
        assert source.adapter.sensor_model is not None and 0 < source.adapter.reliability <= 1


def test_replay_options_depend_on_the_format(tmp_path: Path) -> None:
    log = tmp_path / "run.log"
    log.write_text("PARAM robot_name test\n")
    source = open_source(f"replay:{log},format=carmen,stop=none,poses=odometry")
    assert isinstance(source, CarmenSource) and source.stop is None and source.poses == "odometry"
    with pytest.raises(
        SourceSpecError,
        match=(
            r"option 'stride': expected one of \['format', 'free_range', 'max_range', 'move_x', "
            r"'move_y', 'move_yaw', 'odometry_noise', 'poses', 'seed', 'start', 'step', 'stop', "
            r"'strict'\], found unknown option"
        ),
    ):
        open_source(f"replay:{log},stride=2")
    with pytest.raises(SourceSpecError, match=r"option 'stop': expected int or None, found 'end'"):
        open_source(f"replay:{log},stop=end")


def test_model_defaults_are_the_sources_defaults() -> None:
    """What `colonyd sources` prints as a default is what a source gets when the option is left
    out."""
    pairs = [
        (SimOptions, SimSource),
        (CarmenOptions, CarmenSource),
        (RgbdOptions, RgbdSource),
        (RosbagOptions, RosbagSource),
        (SyntheticOptions, SyntheticSource),
        (BulkOptions, BulkSource),
    ]
    for model, source in pairs:
        params = {
            name: p.default
            for name, p in inspect.signature(source).parameters.items()
            if p.kind is inspect.Parameter.KEYWORD_ONLY
        }
        for name, info in model.model_fields.items():
            assert name in params, (model.__name__, name)
            if info.default is not None or params[name] is None:  # none: the caller's value (seed)
                assert info.default == params[name], (model.__name__, name)


def test_describe_sources_lists_every_option_of_every_kind() -> None:
    text = describe_sources()
    for kind in SOURCE_KINDS.values():
        assert kind.usage in text and kind.reads in text
        for _, model in kind.options:
            for name, info in model.model_fields.items():
                assert name in text and str(info.description) in text
    assert "int or None" in text and "80.0" in text
    markdown = describe_sources(markdown=True)
    assert (
        "### `replay:PATH[,key=value...]`" in markdown
        and "| `max_range` | float | `10.0` |" in markdown
    )


def test_a_kind_s_plugin_modules_load_when_a_spec_of_that_kind_is_opened() -> None:
    """A daemon or command imports only the plugins of the kinds it opens (every plugin at import
    was ~14 % of an idle daemon's start-up): a fresh process imports the daemon and the command
    line without any, opens a synthetic source (its module and the world it walks, not the other
    kinds'), then lists every kind's options (every plugin)."""

    code = (
        "import sys\n"
        "import colonyd.daemon, colonyd.cli\n"
        "KINDS = ('plugins.sim', 'plugins.world', 'plugins.replay', 'plugins.carmen',\n"
        "         'plugins.rosbag', 'plugins.sevenscenes', 'plugins.ros2', 'plugins.synthetic',\n"
        "         'plugins.bulk', 'plugins.cctv')\n"
        "def loaded():\n"
        "    return sorted(m for m in KINDS if m in sys.modules)\n"
        "print(loaded())\n"
        "from plugins.source import describe_sources, open_source\n"
        "source = open_source('synthetic:scans=1')\n"
        "print(len(list(source)), [m for m in loaded() if m != 'plugins.world'])\n"
        "text = describe_sources()\n"
        "print(len(loaded()), 'max_range' in text)\n"
    )
    stdout = fresh_process(code)
    assert stdout.split("\n")[:3] == [
        "[]",
        "1 ['plugins.synthetic']",
        "10 True",
    ], stdout


def test_a_plugin_that_cannot_load_is_a_source_error_naming_it() -> None:
    from plugins.errors import SourceError
    from plugins.source import _load

    assert callable(_load("plugins.sim:open_sim"))
    for name, found in (
        ("plugins.nosuch:open", "No module named"),
        ("plugins.sim:nosuch", "nosuch"),
    ):
        with pytest.raises(SourceError, match=f"expected the source plugin {name} to load") as e:
            _load(name)
        assert found in str(e.value)
