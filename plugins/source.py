"""Source kinds (`sim:`, `replay:`, `ros2:`, `synthetic:`, `bulk:`): their registry,
`open_source(spec)` and reference."""

from __future__ import annotations

import importlib
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, cast

from plugins.errors import SourceError
from plugins.spec import OptionDoc, Options, SourceSpec, option_docs, split_spec
from plugins.stream import Source, SourceContext


def _load(name: str) -> Any:
    """The object a "module:attribute" name names, its module imported now (a plugin that cannot
    load is a SourceError naming it, as a bad spec is)."""
    module, attribute = name.split(":")
    try:
        return getattr(importlib.import_module(module), attribute)
    except (ImportError, AttributeError) as exc:
        raise SourceError(f"expected the source plugin {name} to load, found: {exc}") from exc


@dataclass(frozen=True)
class SourceKind:
    """A kind of source: how its spec looks, what it reads, its options models and how to open it.

    `models` lists (heading, "module:Model"): the kind's own options under heading "", then options
    that depend on what is read (replay: per recording format); `opener` names its open function.
    Both are named, not imported: a kind's plugin modules load when a spec of that kind is opened
    (or the options are listed), so a daemon or command imports only the plugins it uses.
    """

    name: str
    usage: str
    reads: str
    models: tuple[tuple[str, str], ...]
    opener: str
    takes_path: bool = False

    @property
    def options(self) -> tuple[tuple[str, type[Options]], ...]:
        """(heading, model) of every options model (imports the kind's plugin modules)."""
        return tuple((heading, cast(type[Options], _load(name))) for heading, name in self.models)

    @property
    def open(self) -> Callable[[SourceSpec, SourceContext], Source]:
        """The kind's open function (imports its plugin module)."""
        return cast(Callable[[SourceSpec, SourceContext], Source], _load(self.opener))


SOURCE_KINDS: dict[str, SourceKind] = {
    kind.name: kind
    for kind in (
        SourceKind(
            "sim",
            "sim:key=value,...",
            "an agent of a simulated world: a depth camera, 2D or 3D LiDAR or CCTV camera "
            "rendered by ray casting along the agent's path, pose guesses from noisy odometry, "
            "ground truth kept; deterministic for a seed",
            (("", "plugins.sim:SimOptions"),),
            "plugins.sim:open_sim",
        ),
        SourceKind(
            "replay",
            "replay:PATH[,key=value...]",
            "a real recording at PATH: a CARMEN laser log (.log, .log.gz), a 7-Scenes or TUM "
            "RGB-D folder, or a ROS 1/2 bag (.bag, .db3, .mcap, or a folder with metadata.yaml; "
            "needs the [ros] extra); bad frames are skipped and counted unless strict; a "
            "CARMEN log's lines are read at most 1 MiB each (a file without line breaks is "
            "refused at that length, never read whole into memory)",
            (
                ("", "plugins.replay:ReplayOptions"),
                ("carmen", "plugins.carmen:CarmenOptions"),
                ("7scenes, tum", "plugins.sevenscenes:RgbdOptions"),
                ("rosbag", "plugins.rosbag:RosbagOptions"),
            ),
            "plugins.replay:open_replay",
            takes_path=True,
        ),
        SourceKind(
            "ros2",
            "ros2:key=value,...",
            "a live ROS 2 robot on rmw_zenoh (no ROS install): one LaserScan, PointCloud2 or "
            "depth Image topic, its sensor pose from Odometry and /tf, /tf_static at each "
            "reading's time (docs/ROS2.md; needs the [ros] extra); runs until stopped or frames",
            (("", "plugins.ros2:Ros2Options"),),
            "plugins.ros2:open_ros2",
        ),
        SourceKind(
            "synthetic",
            "synthetic:key=value,...",
            "nothing: a 2.5D scanner walking an empty square room, horizontal beams to the walls "
            "with returns at random heights, paced in real time (daemon tests and benchmarks)",
            (("", "plugins.synthetic:SyntheticOptions"),),
            "plugins.synthetic:open_synthetic",
        ),
        SourceKind(
            "bulk",
            "bulk:key=value,...",
            "nothing: one ready-made layer of occupied voxels with random log-odds, at the grid's "
            "resolution, integrated at once (benchmarks of catch-up)",
            (("", "plugins.bulk:BulkOptions"),),
            "plugins.bulk:open_bulk",
        ),
    )
}


def parse_spec(spec: str) -> SourceSpec:
    """Split a spec of any registered kind into kind, path and options (values still text)."""
    usages = {name: kind.usage for name, kind in SOURCE_KINDS.items()}
    with_path = frozenset(name for name, kind in SOURCE_KINDS.items() if kind.takes_path)
    return split_spec(spec, usages, with_path)


def open_source(
    spec: str,
    *,
    resolution: float = 0.1,
    seed: int = 0,
    stop: threading.Event | None = None,
    session: Callable[[], Any] | None = None,
) -> Source:
    """Open the source described by `spec` (`colonyd sources` lists them).

    `resolution` is the voxel size of the grid it feeds, `seed` the seed of sources whose spec
    sets none, `stop` ends paced or endless sources between frames, `session` gives the caller's
    Zenoh session to network sources (`ros2:`).
    """
    parsed = parse_spec(spec)
    context = SourceContext(
        resolution=resolution,
        seed=seed,
        stop=stop if stop is not None else threading.Event(),
        session=session,
    )
    return SOURCE_KINDS[parsed.kind].open(parsed, context)


def describe_sources(*, markdown: bool = False) -> str:
    """Every source kind: its spec, what it reads and its options with type, default and help."""
    return "\n".join(_markdown(kind) if markdown else _text(kind) for kind in SOURCE_KINDS.values())


def _sections(kind: SourceKind) -> list[tuple[str, list[OptionDoc]]]:
    """(heading, option docs) of a kind; later sections leave out the options of the first."""
    own = tuple(kind.options[0][1].model_fields)
    return [
        (heading, option_docs(model, exclude=own if i else ()))
        for i, (heading, model) in enumerate(kind.options)
    ]


def _text(kind: SourceKind) -> str:
    lines = [kind.usage, f"  reads: {kind.reads}"]
    for heading, docs in _sections(kind):
        lines.append(f"  options{f' for {heading}' if heading else ''}:")
        width = max((len(d.name) for d in docs), default=0)
        tw = max((len(d.type) for d in docs), default=0)
        dw = max((len(d.default) for d in docs), default=0)
        lines += [
            f"    {d.name:<{width}}  {d.type:<{tw}}  {d.default:<{dw}}  {d.help}" for d in docs
        ]
    return "\n".join(lines) + "\n"


def _markdown(kind: SourceKind) -> str:
    lines = [f"### `{kind.usage}`", "", f"Reads {kind.reads}.", ""]
    for heading, docs in _sections(kind):
        if heading:
            lines += [f"Options for {heading}:", ""]
        lines += ["| option | type | default | meaning |", "|---|---|---|---|"]
        lines += [f"| `{d.name}` | {d.type} | `{d.default}` | {d.help} |" for d in docs]
        lines.append("")
    return "\n".join(lines)
