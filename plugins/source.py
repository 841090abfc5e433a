"""Source specs (`sim:world=office,agent=lidar-1`, `replay:PATH,step=2`) and `open_source(spec)`.

Grammar: ``KIND ":" BODY`` where KIND is ``sim`` or ``replay``.

- ``sim:key=value,...``: world (room, office), agent (depth-1, lidar-1, lidar3d-1, cctv-1,
  cctv-2 in office), seed, frames, noise, drift, range_noise, start (origin, world), realtime.
- ``replay:PATH[,key=value...]``: PATH is a CARMEN log (.log, .log.gz), a 7-Scenes or TUM RGB-D
  folder, or a ROS 1/2 bag; options: format (auto, carmen, 7scenes, tum, rosbag), start, stop,
  step, strict; CARMEN: poses (reference, odometry), max_range; RGB-D: stride, max_range;
  ROS: topic, odom, info, max_range.
"""

from __future__ import annotations

import inspect
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from plugins.carmen import CarmenSource
from plugins.errors import SourceSpecError
from plugins.replay import detect_format, open_replay
from plugins.sevenscenes import RgbdSource
from plugins.sim import SimSource
from plugins.stream import Source

KINDS = ("sim", "replay")
_TRUE, _FALSE = {"1", "true", "yes", "on"}, {"0", "false", "no", "off"}


@dataclass(frozen=True)
class SourceSpec:
    """A parsed source spec: kind, path (replay only) and options as strings."""

    kind: str
    path: str | None = None
    options: dict[str, str] = field(default_factory=dict)


def parse_spec(spec: str) -> SourceSpec:
    """Parse a source spec string (see the module docstring)."""
    kind, sep, body = spec.partition(":")
    if not sep or kind not in KINDS:
        msg = f"source spec: expected 'sim:key=value,...' or 'replay:PATH', found {spec!r}"
        raise SourceSpecError(msg)
    parts = [p for p in body.split(",")] if body else []
    path = None
    if kind == "replay":
        if not parts or not parts[0] or "=" in parts[0]:
            msg = f"source spec: expected 'replay:PATH[,key=value...]', found {spec!r}"
            raise SourceSpecError(msg)
        path, parts = parts[0], parts[1:]
    options: dict[str, str] = {}
    for part in parts:
        key, eq, value = part.partition("=")
        key = key.strip()
        if not eq or not key:
            msg = f"source spec {spec!r}: expected key=value, found {part!r}"
            raise SourceSpecError(msg)
        if key in options:
            msg = f"source spec {spec!r}: expected each option once, found {key!r} twice"
            raise SourceSpecError(msg)
        options[key] = value.strip()
    return SourceSpec(kind=kind, path=path, options=options)


def _coerce(target: Any, options: dict[str, str], spec: str, exclude: tuple[str, ...] = ()) -> dict[str, Any]:
    """Options converted to the types of `target`'s keyword parameters; unknown keys rejected."""
    params = {name: p for name, p in inspect.signature(target).parameters.items()
              if p.kind is inspect.Parameter.KEYWORD_ONLY and name not in ("spec", *exclude)}
    out: dict[str, Any] = {}
    for key, text in options.items():
        if key not in params:
            msg = f"source spec {spec!r}: option {key!r}: expected one of {sorted(params)}, found unknown option"
            raise SourceSpecError(msg)
        kind = str(params[key].annotation)
        try:
            if text.lower() in ("none", "") and "None" in kind:
                out[key] = None
            elif kind.startswith("bool"):
                if text.lower() not in _TRUE | _FALSE:
                    raise ValueError
                out[key] = text.lower() in _TRUE
            elif kind.startswith("int"):
                out[key] = int(text)
            elif kind.startswith("float"):
                out[key] = float(text)
            else:
                out[key] = text
        except ValueError:
            msg = f"source spec {spec!r}: option {key!r}: expected {kind}, found {text!r}"
            raise SourceSpecError(msg) from None
    return out


def open_source(spec: str) -> Source:
    """Open the source described by `spec`."""
    parsed = parse_spec(spec)
    if parsed.kind == "sim":
        return SimSource(spec=spec, **_coerce(SimSource, parsed.options, spec))
    options = dict(parsed.options)
    fmt = options.pop("format", "auto")
    path = Path(parsed.path).expanduser()
    kind = detect_format(path) if fmt == "auto" else fmt
    if kind == "carmen":
        target: Any = CarmenSource
    elif kind in ("7scenes", "tum"):
        target = RgbdSource
    elif kind == "rosbag":
        from plugins.rosbag import RosbagSource

        target = RosbagSource
    else:
        msg = f"source spec {spec!r}: option 'format': expected auto, carmen, 7scenes, tum or rosbag, found {fmt!r}"
        raise SourceSpecError(msg)
    return open_replay(path, format=kind, spec=spec, **_coerce(target, options, spec, exclude=("layout",)))
