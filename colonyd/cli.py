"""Command line: `colonyd run|status|map|localize|align|sources|bench|demo|experiment|dump-config`;
the one place errors become exit codes."""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
from pathlib import Path
from typing import Any, NoReturn

from colonyd.config import PRECEDENCE, load_config
from colonyd.errors import ColonydError, ConfigError

log = logging.getLogger("colonyd")

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_CONFIG = 3  # configuration, including bad source specs
EXIT_DATA = 4  # voxel / protocol / plugin input errors
EXIT_INTERRUPTED = 130


#: Configuration flags: (dest, flag, argparse keywords). `_config_flags` adds all or some.
_CONFIG_FLAGS: tuple[tuple[str, str, dict[str, Any]], ...] = (
    ("config", "--config", {"type": Path, "help": "TOML config file (also COLONYD_CONFIG)"}),
    (
        "colony",
        "--colony",
        {"help": "colony name (default: default); every member must use the same"},
    ),
    ("namespace", "--namespace", {"help": "key-expression namespace (default: the colony name)"}),
    ("agent_id", "--agent-id", {"help": "this agent's unique id (default: the host name)"}),
    ("kind", "--kind", {"help": "agent kind shown in status"}),
    ("state_dir", "--state-dir", {"type": Path, "help": "state directory"}),
    ("mode", "--mode", {"choices": ["peer", "client"], "help": "Zenoh mode"}),
    (
        "listen",
        "--listen",
        {
            "action": "append",
            "metavar": "ENDPOINT",
            "help": "listen endpoint, e.g. tcp/0.0.0.0:7447 (repeatable)",
        },
    ),
    (
        "connect",
        "--connect",
        {
            "action": "append",
            "metavar": "ENDPOINT",
            "help": "a peer or router to connect to, e.g. tcp/10.0.0.2:7447 (repeatable; without "
            "one, peers are found by multicast scouting unless --no-multicast)",
        },
    ),
    (
        "multicast",
        "--no-multicast",
        {"action": "store_const", "const": False, "help": "disable multicast scouting"},
    ),
    (
        "sources",
        "--source",
        {
            "action": "append",
            "metavar": "SPEC",
            "help": "data source, repeatable (sim:..., "
            "replay:PATH, ros2:..., synthetic:..., bulk:...; see `colonyd sources`)",
        },
    ),
    ("resolution", "--resolution", {"type": float, "help": "voxel size in metres"}),
    (
        "block_shape",
        "--block-shape",
        {
            "choices": ["cube", "planar", "slab"],
            "help": "own layer's voxel blocks (planar: 2D scanners only; slab: 3D LiDAR)",
        },
    ),
    ("publish_hz", "--publish-hz", {"type": float, "help": "own-delta publish rate"}),
    ("heartbeat_s", "--heartbeat-s", {"type": float, "help": "heartbeat period"}),
    (
        "sync_before_publish",
        "--sync-before-publish",
        {
            "action": "store_const",
            "const": True,
            "help": "fsync each own delta's log record before publishing it (slower)",
        },
    ),
    (
        "lease_ms",
        "--lease-ms",
        {"type": int, "help": "Zenoh transport lease (default: Zenoh's 10 s)"},
    ),
    ("colony_key", "--colony-key", {"help": "shared secret for authentication"}),
    (
        "export_dir",
        "--export-dir",
        {"type": Path, "help": "write the fused map (.ply, .bt) here on shutdown"},
    ),
    (
        "drop_rate",
        "--drop-rate",
        {
            "type": float,
            "help": "testing: drop this share of received deltas (exercises gap repair)",
        },
    ),
    (
        "log_level",
        "--log-level",
        {"choices": ["debug", "info", "warning", "error"], "help": "log level (default info)"},
    ),
)
#: The flags of commands that only talk to a running colony.
_CLIENT_FLAGS = ("config", "colony", "namespace", "mode", "listen", "connect", "multicast")


def _config_flags(p: argparse.ArgumentParser, only: tuple[str, ...] | None = None) -> None:
    g = p.add_argument_group(f"configuration (precedence: {' > '.join(PRECEDENCE)})")
    for dest, flag, kwargs in _CONFIG_FLAGS:
        if only is None or dest in only:
            g.add_argument(flag, dest=dest, **_with_default(dest, kwargs))


def _with_default(dest: str, kwargs: dict[str, Any]) -> dict[str, Any]:
    """A config flag's help with the configuration's default (`Config`), where the help does not
    say it already: the flags' own default is None (unset: the environment, the file or the
    configuration's default applies), so --help showed none (`--resolution`: "voxel size in
    metres", not that it is 0.1)."""
    from colonyd.config import Config

    field = Config.model_fields.get(dest)
    help_text = str(kwargs.get("help", ""))
    if field is None or field.is_required() or "default" in help_text:
        return kwargs
    default = field.get_default(call_default_factory=True)
    if default in (None, [], {}):
        return kwargs
    if isinstance(default, bool) or kwargs.get("action") == "store_const":
        return kwargs  # a switch: its help says what it turns on or off
    return {**kwargs, "help": f"{help_text} (default {default})"}


_FLAG_NAMES = (
    "colony",
    "namespace",
    "agent_id",
    "kind",
    "state_dir",
    "mode",
    "listen",
    "connect",
    "multicast",
    "sources",
    "resolution",
    "block_shape",
    "publish_hz",
    "heartbeat_s",
    "sync_before_publish",
    "lease_ms",
    "colony_key",
    "export_dir",
    "drop_rate",
    "log_level",
)


def _flags(args: argparse.Namespace) -> dict[str, Any]:
    return {k: getattr(args, k, None) for k in _FLAG_NAMES if getattr(args, k, None) is not None}


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("colony")
    except PackageNotFoundError:  # running from a checkout that is not installed
        return "unknown"


def _positive_int(text: str) -> int:
    """An argparse type: a whole number >= 1 (a count of frames, runs, daemons...)."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        msg = f"expected a whole number >= 1, found {text!r}"
        raise argparse.ArgumentTypeError(msg)
    return value


def _finite_float(text: str, *, zero: bool) -> float:
    """A finite number > 0 (>= 0 when `zero`), or a usage error saying what was expected."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (value >= 0 if zero else value > 0) or value == float("inf"):
        msg = f"expected a number {'>=' if zero else '>'} 0, found {text!r}"
        raise argparse.ArgumentTypeError(msg)
    return value


def _positive_float(text: str) -> float:
    """An argparse type: a number > 0 (seconds, metres)."""
    return _finite_float(text, zero=False)


def _non_negative_float(text: str) -> float:
    """An argparse type: a number >= 0 (seconds to wait)."""
    return _finite_float(text, zero=True)


def _lidar_range(p: argparse.ArgumentParser) -> None:
    from colonyd.experimentopts import LIDAR_RANGE

    p.add_argument(
        "--lidar-range",
        type=_positive_float,
        default=LIDAR_RANGE,
        help=f"lidar-1's range in m (default {LIDAR_RANGE:g}: a short-range 2D LiDAR)",
    )


def _world(p: argparse.ArgumentParser) -> None:
    from colonyd.experimentopts import WORLDS

    p.add_argument(
        "--world",
        choices=WORLDS,
        default=WORLDS[0],
        help="the sim world (default office; hall: the paper's sparse environment, 18 x 12 m, "
        "docs/LOCALISATION.md)",
    )


def _bench_io(b: argparse.ArgumentParser, *, shared_data: bool = False) -> None:
    """The flags every benchmark takes: where its JSON goes (and where the real data is)."""
    b.add_argument("--json", type=Path, required=True, help="write the results here (JSON)")
    if shared_data:
        b.add_argument(
            "--shared-data",
            type=Path,
            default=None,
            help="the real recordings (default: ../shared/data beside the checkout)",
        )


def _map_query_flags(p: argparse.ArgumentParser) -> None:
    """The flags of the commands that fetch maps from a running colony (`export`, `changes`)."""
    _config_flags(p, _CLIENT_FLAGS)
    p.add_argument("--out", dest="export_out", type=Path, required=True, help="output directory")
    p.add_argument(
        "--layer",
        dest="export_layer",
        default=None,
        metavar="ID",
        help="only this agent's layer, in its own frame",
    )
    p.add_argument(
        "--from",
        dest="export_agent",
        default=None,
        metavar="AGENT",
        help="ask this daemon (default: the first to answer, by agent id)",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="colonyd", description="colony daemon: peer-to-peer voxel mapping over Zenoh"
    )
    parser.add_argument("--version", action="version", version=f"colonyd {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser(
        "run",
        help="run the daemon until SIGTERM",
        description="Run this agent's daemon until SIGTERM (docs/DAEMON.md). Multicast scouting "
        "is on unless --no-multicast (or multicast = false in the config).",
    )
    _config_flags(p)

    p = sub.add_parser("status", help="print the members of a running colony")
    _config_flags(p, _CLIENT_FLAGS)
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument("--digest", action="store_true", help="include layer digests")
    p.add_argument(
        "--wait",
        type=_positive_float,
        default=3.0,
        help="seconds to wait for all members (default 3)",
    )

    p = sub.add_parser("dump-config", help="print the effective configuration as TOML")
    _config_flags(p)

    p = sub.add_parser(
        "export",
        help="fetch the live fused map (colony frame) and the layers' maps "
        "from a running colony into .bt/.ply files (and a floor plan for 2D maps)",
    )
    _map_query_flags(p)
    p.add_argument(
        "--at",
        dest="export_at",
        default=None,
        metavar="T",
        help="the map as it was at time T (Unix seconds, -SECONDS before now, or ISO 8601), "
        "from the layers' history",
    )

    p = sub.add_parser(
        "forget-agent",
        help="remove an agent's layer from the whole colony and keep it removed "
        "(e.g. a robot with a broken sensor)",
    )
    _config_flags(p, (*_CLIENT_FLAGS, "colony_key"))
    p.add_argument("forget_id", metavar="ID", help="the agent whose layer to forget")
    p.add_argument(
        "--wait",
        type=float,
        default=None,
        help="seconds to keep asking until a daemon takes the request (default 15)",
    )

    p = sub.add_parser(
        "changes",
        help="what appeared and disappeared in the live fused map (or one layer) since a time: "
        "appeared.ply, disappeared.ply and the counts",
    )
    _map_query_flags(p)
    p.add_argument(
        "--since",
        dest="changes_since",
        required=True,
        metavar="T",
        help="Unix seconds, -SECONDS before now, or ISO 8601",
    )

    p = sub.add_parser(
        "identity",
        help="print this agent's public identity key (made if missing), "
        "for other agents' trusted_keys",
    )
    _config_flags(p, ("config", "agent_id", "state_dir"))

    p = sub.add_parser("map", help="map a source offline into a directory of map files")
    p.add_argument(
        "--source",
        dest="map_source",
        required=True,
        metavar="SPEC",
        help="source spec (sim:..., replay:PATH, ...; see `colonyd sources`)",
    )
    p.add_argument(
        "--resolution",
        type=_positive_float,
        default=0.1,
        help="voxel size in metres (default 0.1)",
    )
    p.add_argument("--out", type=Path, required=True, help="output directory")

    p = sub.add_parser(
        "localize",
        help="estimate one agent's poses offline (EKF with scan matching, or RGB-D "
        "visual odometry), map from them, and measure ATE against the source's reference",
    )
    p.add_argument(
        "--source",
        dest="loc_source",
        required=True,
        metavar="SPEC",
        help="source spec (sim:..., replay:CARMEN_LOG, replay:RGBD_FOLDER, replay:BAG)",
    )
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument(
        "--resolution",
        type=_positive_float,
        default=0.1,
        help="voxel size in metres (default 0.1)",
    )
    p.add_argument(
        "--odometry-noise",
        dest="odometry_noise",
        default=None,
        metavar="MODEL",
        help="synthesise wheel odometry from the reference: none, low, realistic, high or "
        "trans/rot/rot_per_m/scale_bias/yaw_bias (docs/LOCALISATION.md)",
    )
    p.add_argument("--seed", type=int, default=None, help="seed of the odometry noise")
    p.add_argument(
        "--max-frames",
        dest="max_frames",
        type=_positive_int,
        default=None,
        help="stop after this many frames (default: all)",
    )
    p.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar")

    p = sub.add_parser("align", help="align map B to map A by their geometry (offline)")
    p.add_argument(
        "map_a",
        type=Path,
        metavar="A",
        help="reference map (.bt, grid .npz from `colonyd map`, .ply)",
    )
    p.add_argument("map_b", type=Path, metavar="B", help="map to align into A's frame")
    p.add_argument(
        "--dof",
        type=int,
        choices=[3, 4, 6],
        default=4,
        help="3: x, y, yaw (planar); 4: adds z (default); 6: full",
    )
    p.add_argument(
        "--json",
        type=Path,
        required=True,
        metavar="OUT",
        help="write the result here (transform maps B's points into A's frame)",
    )

    p = sub.add_parser("sources", help="print every source kind, what it reads and its options")
    p.add_argument(
        "--markdown", action="store_true", help="print Markdown (the reference in docs/SOURCES.md)"
    )

    p = sub.add_parser("bench", help="benchmarks")
    bsub = p.add_subparsers(dest="bench", required=True)
    b = bsub.add_parser("integrate", help="voxel integration benchmark")
    _bench_io(b, shared_data=True)
    b.add_argument("--repeats", type=int, default=3, help="timed runs per scenario (default 3)")
    b.add_argument(
        "--runs",
        type=int,
        default=1,
        help="whole measurements per scenario; speedup min / median / max over them (default 1)",
    )
    b.add_argument(
        "--only",
        action="append",
        metavar="SCENARIO",
        help="run this scenario (repeatable; also opt-in ones such as lidar3d_64x1024_0.05)",
    )
    b.add_argument(
        "--surface",
        action="store_true",
        help="our grid keeps the sub-voxel surface, as daemons do (VoxelGrid surface=True)",
    )
    b = bsub.add_parser(
        "wal", help="write-ahead log bytes per record, with its history (and compressed, measured)"
    )
    _bench_io(b, shared_data=True)
    b = bsub.add_parser("wire", help="wire-format benchmark")
    _bench_io(b, shared_data=True)
    b.add_argument(
        "--scenario",
        action="append",
        help="run only this scenario (repeatable; default all): camera_path_50_0.05, "
        "lidar3d_32k_seq_0.10, redkitchen50_0.05",
    )
    b.add_argument(
        "--no-surface",
        action="store_true",
        help="grids without the sub-voxel surface channel (daemons keep it; for comparison)",
    )
    b.add_argument(
        "--dense-surface",
        action="store_true",
        help="deltas carry every voxel's surface codes (0 when not occupied) and codes follow "
        "their means whenever a voxel is sent anyway: the format before sparse codes, for "
        "comparison",
    )
    b = bsub.add_parser(
        "history",
        help="history bytes per record on the wire, replica temporal queries against the "
        "origin's, allocated bytes after forgetting",
    )
    _bench_io(b, shared_data=True)
    b = bsub.add_parser(
        "align",
        help="map alignment: real laser halves, OctoMap crops, negatives, vs map_merge's ORB",
    )
    _bench_io(b, shared_data=True)
    b.add_argument("--seeds", type=int, default=20, help="random moves of the CARMEN halves")
    b.add_argument(
        "--octomap-seeds", type=int, default=10, help="random moves of the OctoMap crops"
    )
    b.add_argument(
        "--negative-seeds", type=int, default=5, help="random moves of each negative pair"
    )
    b.add_argument("--carmen-step", type=int, default=1, help="map every step-th scan of each half")
    b.add_argument(
        "--work-dir",
        type=Path,
        default=None,
        help="keep the maps here (default: a temporary folder)",
    )
    b = bsub.add_parser(
        "align-live",
        help="live alignment: sim office agents at unknown poses, error vs truth, fused map",
    )
    b.add_argument("--json", type=Path, required=True)
    b.add_argument("--frames", type=int, default=120, help="frames each sim agent maps")
    b.add_argument(
        "--noise",
        type=float,
        nargs="+",
        default=[0.0, 0.02],
        help="sim odometry noise per run (0: drift-free; 0.02: the sim's default)",
    )
    b.add_argument("--no-realtime", action="store_true", help="map as fast as possible")
    b = bsub.add_parser(
        "paper",
        help="the paper's experiment (colonyd experiment paper) over seeds, with its claims",
    )
    _bench_io(b)
    b.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5], help="default 1-5")
    b.add_argument(
        "--duration", type=_positive_float, default=60.0, help="seconds per run (default 60)"
    )
    b.add_argument(
        "--parallel", type=_positive_int, default=2, help="runs at the same time (default 2)"
    )
    _lidar_range(b)
    _world(b)
    b.add_argument(
        "--out-dir", type=Path, default=None, help="keep each seed's outputs here (seed-N/)"
    )
    b.add_argument(
        "--timeout",
        type=_positive_float,
        default=None,
        help="per run, as for colonyd experiment paper (default 6 x duration + 120)",
    )
    b = bsub.add_parser("colony", help="N daemons on loopback: propagation, catch-up, idle cost")
    _bench_io(b)
    b.add_argument("--daemons", type=int, default=4, help="daemons on loopback (default 4)")
    b.add_argument("--duration", type=float, default=10.0, help="seconds of 2 Hz gossip")
    b.add_argument(
        "--catchup-voxels",
        type=int,
        action="append",
        help="voxels of the layer a newcomer catches up with (repeatable; default 1,000,000)",
    )
    b.add_argument(
        "--catchup-runs",
        type=int,
        default=3,
        help="newcomers, one after another, timed catching up each layer (default 3)",
    )
    b.add_argument(
        "--start-runs", type=int, default=5, help="daemons timed from spawn to READY (default 5)"
    )
    b.add_argument(
        "--phase",
        action="append",
        choices=["gossip", "catchup", "steps", "start"],
        help="run only this phase (repeatable; default all)",
    )
    b = bsub.add_parser(
        "faults",
        help="real daemons under faults: crash, partition, freeze, disk, "
        "busy CPU, flood, hostile input (scale with --only scale)",
    )
    _bench_io(b)
    b.add_argument(
        "--only",
        action="append",
        metavar="SCENARIO",
        help="run this scenario (repeatable): crash, freeze, hostile, disk, partition, "
        "busy, flood, scale",
    )
    b.add_argument("--kills", type=int, default=20, help="SIGKILLs in the crash scenario")
    b.add_argument("--duration", type=float, default=10.0, help="seconds of 2 Hz gossip (busy)")
    b.add_argument(
        "--sync-before-publish",
        action="store_true",
        help="busy: daemons fsync each delta before publishing it (the stricter mode)",
    )

    p = sub.add_parser(
        "demo",
        help="a depth-camera robot, a 2D-LiDAR robot and a CCTV map the sim office as a colony on "
        "loopback; a 3D-LiDAR robot joins halfway",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=Path("demo-out"),
        help="where maps, pictures and summary.json go (default demo-out)",
    )
    p.add_argument(
        "--duration",
        type=_positive_float,
        default=40.0,
        help="seconds of mapping, in simulated real time (default 40)",
    )
    p.add_argument(
        "--timeout",
        type=_positive_float,
        default=150.0,
        help="give up waiting for the colony after this many seconds (default 150)",
    )
    p.add_argument(
        "--align-wait",
        type=_non_negative_float,
        default=15.0,
        help="once mapping is over, wait up to this many seconds for every member to align "
        "(default 15; a loaded machine registers maps slowly)",
    )
    p = sub.add_parser("experiment", help="experiments of the paper, as real daemons on loopback")
    esub = p.add_subparsers(dest="experiment", required=True)
    e = esub.add_parser(
        "paper",
        help="sim robots localising alone and sharing (depth-alone, lidar-alone, "
        "lidar+depth, lidar+depth+cctv): pose error against the sim's truth",
    )
    e.add_argument(
        "--out",
        type=Path,
        required=True,
        help="where results.json, pose-error.png and each run's trajectories and picture go",
    )
    e.add_argument("--seed", type=int, default=1, help="seed of the agents' noise (default 1)")
    e.add_argument(
        "--duration",
        type=_positive_float,
        default=60.0,
        help="seconds of sim time each run maps, in real time (default 60)",
    )
    e.add_argument(
        "--parallel", type=_positive_int, default=2, help="runs at the same time (default 2)"
    )
    _lidar_range(e)
    _world(e)
    e.add_argument(
        "--timeout",
        type=_positive_float,
        default=None,
        help="end a run whose sources are not done after this many seconds and mark it "
        "incomplete (default 6 x duration + 120)",
    )
    e.add_argument(
        "--start-delay",
        type=_non_negative_float,
        default=15.0,
        help="seconds from starting a run's daemons to the start of its agents' paths (default "
        "15: every daemon is up by then on a loaded machine; frames a daemon is late for are "
        "mapped late, not skipped)",
    )
    _name_parsers(parser)
    return parser


def _unrecognized(parser: argparse.ArgumentParser, unknown: list[str]) -> str:
    """argparse's message, with the closest flags of that command for a mistyped one."""
    import difflib

    flags = [o for a in parser._actions for o in a.option_strings if o.startswith("--")]
    close = [
        m
        for u in unknown
        if u.startswith("--")
        for m in difflib.get_close_matches(u, flags, n=1, cutoff=0.75)
    ]
    hint = f" (expected one of its flags, such as {', '.join(close)})" if close else ""
    return f"unrecognized arguments: {' '.join(unknown)}{hint}"


def _name_parsers(parser: argparse.ArgumentParser) -> None:
    """Every parser stores itself as `parser_` (the innermost one given wins), so that an
    unknown flag is reported with the usage of the command it was given to."""
    parser.set_defaults(parser_=parser)
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                _name_parsers(sub)


def _stop_on_term() -> None:
    """SIGTERM and SIGHUP (a CI job's timeout, `kill`, a closed terminal) end the command as
    Ctrl-C does, through its `finally` clauses: the commands that start daemons (demo,
    experiment, bench) stop them there. Without this the command died at once and left its
    daemons (each in a session of its own) and replays running. A second signal during that
    clean-up is ignored (SIGKILL still ends it)."""

    def stop(signum: int, frame: object) -> None:
        for sig in (signal.SIGTERM, signal.SIGHUP):
            signal.signal(sig, signal.SIG_IGN)
        raise KeyboardInterrupt(signal.Signals(signum).name)

    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, stop)


def main(argv: list[str] | None = None) -> int:
    """Parse and dispatch; raises the package errors that `launch` maps to exit codes."""
    args, unknown = build_parser().parse_known_args(argv)
    if unknown:  # in the words of the (sub)command given, not of `colonyd` with every command
        args.parser_.error(_unrecognized(args.parser_, unknown))
    cmd = args.command
    if cmd in ("demo", "experiment", "bench") and argv is None:  # the command line, not a test
        _stop_on_term()
    if cmd in ("run", "status", "dump-config", "identity", "export", "changes", "forget-agent"):
        flags = _flags(args)
        config = load_config(args.config, **flags)
        if cmd == "forget-agent":
            from colonyd.logs import setup_logging
            from colonyd.tombstones import FORGET_WAIT_S, forget_agent

            setup_logging("warning")
            wait = FORGET_WAIT_S if args.wait is None else args.wait
            answers = forget_agent(config, args.forget_id, wait_s=wait)
            sys.stdout.write(json.dumps(answers) + "\n")
            return EXIT_OK
        if cmd == "changes":
            from colonyd.export import map_changes, parse_time
            from colonyd.logs import setup_logging

            setup_logging("warning")
            since = parse_time(args.changes_since, "--since")
            changes, files = map_changes(
                config, args.export_out, since, layer=args.export_layer, agent=args.export_agent
            )
            counts = {
                "since": changes.since,
                "frame": changes.frame,
                "appeared": len(changes.appeared),
                "disappeared": len(changes.disappeared),
                "files": [str(p) for p in files.values()],
            }
            sys.stdout.write(json.dumps(counts) + "\n")
            return EXIT_OK
        if cmd == "export":
            from colonyd.export import UNALIGNED, export_maps, parse_time
            from colonyd.logs import setup_logging

            setup_logging("warning")
            at = None if args.export_at is None else parse_time(args.export_at, "--at")
            frame, files = export_maps(
                config, args.export_out, layer=args.export_layer, agent=args.export_agent, at=at
            )
            sys.stdout.write(
                f"fused map in frame {frame}; wrote "
                + ", ".join(str(p) for p in files.values())
                + "\n"
            )
            apart = sorted({p.stem for k, p in files.items() if k.startswith(f"{UNALIGNED}/")})
            if apart:
                sys.stdout.write(
                    f"not aligned with the colony frame, so not in the fused map: "
                    f"{', '.join(apart)} (each in its own frame in {UNALIGNED}/)\n"
                )
            return EXIT_OK
        if cmd == "identity":
            from colonyd.identity import identity_path, load_signer

            signer = load_signer(identity_path(config.identity_file, config.state_dir))
            sys.stdout.write(f'"{config.agent_id}" = "{signer.public.hex()}"\n')
            return EXIT_OK
        if cmd == "dump-config":
            from colonyd.config import dump_config

            sys.stdout.write(dump_config(config))
            return EXIT_OK
        if cmd == "status":
            from colonyd.logs import setup_logging
            from colonyd.status import collect_status, format_status

            setup_logging("warning")
            reports = collect_status(config, digest=args.digest, wait_s=args.wait)
            if args.json:
                from colonyd.status import behind

                lags = behind(reports)
                for r in reports:
                    r["behind"] = lags.get(r["agent"], 0)
                sys.stdout.write(json.dumps(reports, indent=1) + "\n")
            else:
                sys.stdout.write(format_status(reports) + "\n")
            return EXIT_OK
        from colonyd.daemon import run_daemon

        code = run_daemon(config, args.config, flags)
        _leave(code)
    if cmd == "sources":
        from plugins.source import describe_sources

        sys.stdout.write(describe_sources(markdown=args.markdown))
        return EXIT_OK
    from colonyd.logs import setup_logging

    setup_logging("info")
    if cmd == "map":
        from colonyd.mapping import map_source, summary_breakdown

        summary = map_source(args.map_source, args.resolution, args.out)
        written = ", ".join(str(p) for p in getattr(summary, "files", {}).values())
        sys.stdout.write(
            f"{summary.spec}: {summary.frames} frames ({summary.skipped} skipped), "
            f"{summary.points} points -> {summary.occupied} occupied, {summary.free} free voxels "
            f"at {summary.resolution} m in {summary.seconds:.1f} s "
            f"({summary.frames_per_second:.1f} frames/s read and integrated)\nwrote {written}\n"
            f"time: {summary_breakdown(summary.breakdown, summary.seconds)}\n"
        )
        return EXIT_OK
    if cmd == "localize":
        from colonyd.localize import localize_source

        s = localize_source(
            args.loc_source,
            args.out,
            resolution=args.resolution,
            odometry_noise=args.odometry_noise,
            seed=args.seed,
            max_frames=args.max_frames,
            progress=args.progress,
        )
        odo = "no odometry" if s.ate_odometry is None else f"odometry {s.ate_odometry:.3f} m"
        if s.ate_smoothed is not None:
            odo += f", smoothed {s.ate_smoothed:.3f} m"
        if s.ate_estimate is not None:
            ate = f"ATE {s.ate_estimate:.3f} m ({odo})"
        elif s.reference_poses:
            ate = f"ATE not measured: expected at least 3 poses, found {s.reference_poses}"
        else:
            ate = "no reference: ATE not measured"
        sys.stdout.write(
            f"{s.spec}: {s.frames} frames by {s.estimator} in {s.seconds:.1f} s; {ate}\n"
            f"wrote {', '.join(str(p) for p in s.files.values())}\n"
        )
        return EXIT_OK
    if cmd == "align":
        return _align(args)
    if cmd == "bench":
        return _bench(args)
    if cmd == "experiment":
        from colonyd.experiment import run_paper

        run_paper(
            args.out,
            seed=args.seed,
            duration=args.duration,
            parallel=args.parallel,
            timeout=args.timeout,
            lidar_range=args.lidar_range,
            world=args.world,
            start_delay=args.start_delay,
        )
        sys.stdout.write(f"wrote {args.out}: results.json, pose-error.png, <run>/\n")
        return EXIT_OK
    if cmd == "demo":
        from colonyd.demo import run_demo

        return run_demo(
            args.out, duration=args.duration, timeout=args.timeout, align_wait=args.align_wait
        )
    return EXIT_USAGE


def _align(args: argparse.Namespace) -> int:
    """`colonyd align`: exit 0 whether or not the maps aligned; the JSON says which and why."""
    from voxel.registration import AlignParams, align_maps

    result = align_maps(args.map_a, args.map_b, AlignParams(dof=args.dof)).to_json()
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=1) + "\n")
    if result["aligned"]:
        sys.stdout.write(
            f"aligned (confidence {result['confidence']:.2f}): "
            f"x {result['x']:.3f} y {result['y']:.3f} z {result['z']:.3f} m, "
            f"yaw {result['yaw_deg']:.2f} deg, {result['inliers']} inliers, "
            f"RMS {result['rmse_m']} m, in {result['seconds']:.2f} s\nwrote {args.json}\n"
        )
    else:
        sys.stdout.write(f"not aligned: {result['reason']}\nwrote {args.json}\n")
    return EXIT_OK


def _bench(args: argparse.Namespace) -> int:
    result: object  # what the benchmark returns, printed as JSON
    if args.bench == "integrate":
        from colonyd.bench.integrate import run_integrate_bench

        result = run_integrate_bench(
            args.json, args.shared_data, args.repeats, args.only, args.runs, args.surface
        )
    elif args.bench == "align":
        from colonyd.bench.align import run_align_bench

        report = run_align_bench(
            args.json,
            args.shared_data,
            seeds=args.seeds,
            octomap_seeds=args.octomap_seeds,
            negative_seeds=args.negative_seeds,
            carmen_step=args.carmen_step,
            work_dir=args.work_dir,
        )
        result = {"summary": report["summary"], "json": str(args.json)}
    elif args.bench == "align-live":
        from colonyd.bench.align_live import run_align_live_bench

        live = run_align_live_bench(
            args.json,
            frames=args.frames,
            drifts=tuple(args.noise),
            realtime=not args.no_realtime,
            command=" ".join(["colonyd", *sys.argv[1:]]),
        )
        result = {"summary": live["summary"], "json": str(args.json)}
    elif args.bench == "paper":
        from colonyd.bench.paper import run_paper_bench

        paper = run_paper_bench(
            args.json,
            seeds=args.seeds,
            duration=args.duration,
            parallel=args.parallel,
            lidar_range=args.lidar_range,
            world=args.world,
            timeout=args.timeout,
            out_dir=args.out_dir,
            command=" ".join(["colonyd", *sys.argv[1:]]),
        )
        result = {"summary": paper["summary"], "json": str(args.json)}
    elif args.bench == "wal":
        from colonyd.bench.walbytes import run_wal_bench

        result = run_wal_bench(args.json, args.shared_data)
    elif args.bench == "wire":
        from colonyd.bench.wire import run_wire_bench

        result = run_wire_bench(
            args.json,
            args.shared_data,
            only=args.scenario,
            surface=not args.no_surface,
            sparse=not args.dense_surface,
        )
    elif args.bench == "history":
        from colonyd.bench.history import run_history_bench

        result = run_history_bench(args.json, args.shared_data)
    elif args.bench == "faults":
        from colonyd.bench.faults import run_faults_bench

        result = run_faults_bench(
            args.json,
            only=args.only,
            kills=args.kills,
            duration=args.duration,
            sync_first=args.sync_before_publish,
        )
    else:
        from colonyd.bench.colony import run_colony_bench

        result = run_colony_bench(
            args.json,
            daemons=args.daemons,
            duration=args.duration,
            catchup_voxels=args.catchup_voxels or [1_000_000],
            catchup_runs=args.catchup_runs,
            start_runs=args.start_runs,
            phases=args.phase,
        )
    if result is not None:
        sys.stdout.write(json.dumps(result, indent=1, default=str) + "\n")
    return EXIT_OK


def _known_errors() -> list[tuple[type[BaseException], int, str]]:
    """(error class, exit code, label) for every package that defines errors, most specific
    first."""
    known: list[tuple[type[BaseException], int, str]] = [(ConfigError, EXIT_CONFIG, "config")]
    try:
        from voxel.errors import VoxelError

        known.append((VoxelError, EXIT_DATA, "voxel"))
    except ImportError:
        pass
    try:
        from protocol.errors import ProtocolError

        known.append((ProtocolError, EXIT_DATA, "protocol"))
    except ImportError:
        pass
    try:
        from plugins.errors import PluginError, SourceSpecError

        known.append((SourceSpecError, EXIT_CONFIG, "source"))
        known.append((PluginError, EXIT_DATA, "plugin"))
    except ImportError:
        pass
    known.append((ColonydError, EXIT_FAILURE, "colonyd"))
    return known


def _leave(code: int) -> NoReturn:
    """End a daemon that stopped cleanly (session, log and files closed) without tearing the
    interpreter down: finalising numpy, scipy, OpenCV and Zenoh's modules takes a second or
    more, which every stop or restart (a unit's, a test's) would wait for."""
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def launch(argv: list[str] | None = None) -> None:
    """Console-script entry point: run `main` and map known errors to exit codes and log lines."""
    try:
        code = main(argv)
    except KeyboardInterrupt:
        code = EXIT_INTERRUPTED
    except Exception as exc:
        for cls, exit_code, label in _known_errors():
            if isinstance(exc, cls):
                if not logging.getLogger().handlers:
                    from colonyd.logs import setup_logging

                    setup_logging("info")
                log.error("%s error: %s", label, exc)
                code = exit_code
                break
        else:
            raise
    sys.exit(code)
