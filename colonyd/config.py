"""Daemon configuration: one pydantic-settings model from TOML, `COLONYD_` environment and flags."""

from __future__ import annotations

import difflib
import json
import os
import re
import socket
import tomllib
import zlib
from contextvars import ContextVar
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, ValidationError, field_validator, model_validator
from pydantic.fields import FieldInfo
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict
from pydantic_settings.exceptions import SettingsError

from colonyd.aligner import AUTOGROUP_NICE
from colonyd.errors import ConfigError
from voxel.rotation import pose_from_degrees

#: Precedence, highest first: command-line flags, `COLONYD_*` environment variables, the TOML
#: file given with `--config` (or `COLONYD_CONFIG`), built-in defaults.
PRECEDENCE = ("flags", "environment (COLONYD_*)", "TOML file (--config)", "defaults")

try:  # names must also be valid key-expression chunks of the protocol
    from protocol.keyexpr import NAME_PATTERN
except ImportError:  # pragma: no cover - protocol package without keyexpr
    NAME_PATTERN = r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}"
_NAME = re.compile(f"^{NAME_PATTERN}$")
_ENDPOINT = re.compile(r"^(tcp|udp|tls|quic|ws|unixsock-stream)/.+$")
SECRETS = ("colony_key",)
_TOML_PATH: ContextVar[Path | None] = ContextVar("colonyd_toml_path", default=None)


def _default_agent_id() -> str:
    name = re.sub(r"[^A-Za-z0-9_.-]", "-", socket.gethostname())[:64]
    return name or "agent"


def multicast_port(colony: str) -> int:
    """The colony-specific multicast scouting port: 17000 + a stable hash of the colony name."""
    return 17000 + zlib.crc32(colony.encode()) % 20000


class _TomlSource(PydanticBaseSettingsSource):
    """Settings from the TOML file named in the current load (lowest precedence above defaults)."""

    def __init__(self, settings_cls: type[BaseSettings]) -> None:
        super().__init__(settings_cls)
        self._data = _read_toml(_TOML_PATH.get())

    def get_field_value(self, field: FieldInfo, field_name: str) -> tuple[Any, str, bool]:
        return self._data.get(field_name), field_name, False

    def __call__(self) -> dict[str, Any]:
        return dict(self._data)


def _read_toml(path: Path | None) -> dict[str, Any]:
    if path is None:
        return {}
    try:
        with Path(path).open("rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        msg = f"config file {path} does not exist"
        raise ConfigError(msg) from None
    except tomllib.TOMLDecodeError as exc:
        msg = f"config file {path} is not valid TOML: {exc}"
        raise ConfigError(msg) from None
    # Accept either a flat file or one with a [colonyd] table.
    if isinstance(data.get("colonyd"), dict):
        data = {**{k: v for k, v in data.items() if k != "colonyd"}, **data["colonyd"]}
    return {k.replace("-", "_"): v for k, v in data.items()}


class Config(BaseSettings):
    """Everything a daemon needs; see docs/DAEMON.md for each field."""

    model_config = SettingsConfigDict(
        env_prefix="COLONYD_", extra="forbid", validate_default=True, populate_by_name=True
    )

    colony: str = Field("default", description="colony name; peers of one colony share it")
    namespace: str | None = Field(None, description="key-expression namespace (default: colony)")
    agent_id: str = Field(default_factory=_default_agent_id, description="this agent's unique id")
    kind: str = Field("robot", description="agent kind shown in status (robot, cctv, ...)")
    state_dir: Path = Field(Path("/var/lib/colonyd"), description="WAL and snapshots")
    mode: Literal["peer", "client"] = Field("peer", description="Zenoh mode; client for routers")
    listen: list[str] = Field(default_factory=list, description="Zenoh listen endpoints")
    connect: list[str] = Field(default_factory=list, description="Zenoh connect endpoints")
    multicast: bool = Field(True, description="multicast scouting on the colony's port")
    multicast_interface: str = Field("auto", description="interface for multicast scouting")
    gossip_scouting: bool = Field(True, description="Zenoh gossip scouting (keeps a full mesh)")
    shared_memory: bool = Field(False, description="Zenoh shared memory on one host")
    lease_ms: int | None = Field(None, ge=100, description="transport lease (freeze detection)")
    zenoh_config: Path | None = Field(None, description="extra Zenoh JSON5 file, merged first")
    sources: list[str] = Field(default_factory=list, description="source specs")
    resolution: float = Field(0.1, gt=0, le=10, description="voxel size in metres")
    block_shape: Literal["cube", "planar", "slab"] = Field(
        "cube",
        description="own layer's voxel blocks: planar (8x8x1) when mapping with 2D scanners only, "
        "slab (4x4x1) with a 3D LiDAR",
    )
    surface: bool = Field(
        True,
        description="own layer keeps each hit voxel's mean hit position (sub-voxel surface, "
        "sent to peers; their colony maps match scans against it, not voxel centres)",
    )
    publish_hz: float = Field(2.0, gt=0, le=100, description="own-delta publish rate")
    heartbeat_s: float = Field(1.0, gt=0, le=60, description="status heartbeat period")
    snapshot_s: float = Field(30.0, gt=0, description="own-layer snapshot period")
    sync_before_publish: bool = Field(
        False,
        description="fsync each own delta's log record before publishing it (slower; a power "
        "loss then never loses a delta a peer saw; otherwise it starts a new epoch)",
    )
    inbox_size: int = Field(256, ge=8, description="bounded queue of received messages")
    inbox_mb: float = Field(128.0, gt=0, description="bytes the received-message queue may hold")
    max_layers: int = Field(
        256,
        ge=1,
        description="most peer layers held (hostile origins), and layers a member's heartbeat "
        "is remembered to hold (beyond its own)",
    )
    max_members: int = Field(
        1024,
        ge=1,
        description="most members whose heartbeats are kept, with a layer or without (cameras, "
        "command-line clients), most kept from their liveliness token alone, and peers whose "
        "object lists are kept",
    )
    max_peer_blocks: int = Field(
        100_000, ge=1, description="voxel blocks (64 voxels each) in peer layers"
    )
    localise: bool = Field(
        True,
        description="estimate the pose of sources with odometry (EKF + scan matching), map from it",
    )
    colony_map_s: float = Field(
        1.0,
        ge=0,
        description="seconds between refreshes of the aligned peers' map a localising LiDAR "
        "robot also matches its scans against (0: its own map only)",
    )
    colony_peer_pose: bool = Field(
        True,
        description="add each peer's reported pose covariance (its Pose messages) to the error "
        "of its map in the colony map (false: the alignments' error alone; docs/BENCHMARKS.md)",
    )
    align_s: float = Field(
        5.0, ge=0, description="seconds between alignment attempts with peers (0: none)"
    )
    align_session_nice: int = Field(
        AUTOGROUP_NICE,
        ge=-1,
        le=19,
        description="autogroup niceness of the registration worker's own session (Linux; 10: "
        "~10 % of a busy session's CPU, 19: ~1.5 %; -1: no session of its own; docs/DAEMON.md)",
    )
    align_dof: Literal[3, 4, 6] = Field(
        4, description="alignment degrees of freedom: 3 planar, 4 + z, 6 full"
    )
    anchor: str | None = Field(
        None, description="agent whose frame is the site frame (a surveyed CCTV)"
    )
    site_pose: list[float] | None = Field(
        None,
        description=(
            "this agent's frame in the anchor's (site) frame, when known (a survey, a start "
            "mark): x, y, z (m), yaw (deg)[, pitch, roll (deg)]; offered as a sure alignment"
        ),
    )
    layer_weights: dict[str, float] = Field(
        default_factory=dict,
        description="reliability weight in the fused map per agent id or agent kind (default 1.0)",
    )
    objects_s: float = Field(
        2.0,
        ge=0,
        description="seconds between object-list refreshes (0: no objects); peers take 16,384 "
        "listed objects a second, shared by the members sending lists, at most 8192 each "
        "(docs/DAEMON.md)",
    )
    structure_classes: list[int] = Field(
        [1, 2], description="class ids that are structure (walls, floors), never objects; the sim's"
    )
    ring_size: int = Field(64, ge=1, description="recent deltas kept per layer for gap repair")
    max_message_mb: float = Field(64.0, gt=0, description="largest accepted decoded message")
    query_timeout_s: float = Field(
        5.0, gt=0, allow_inf_nan=False, description="range/snapshot query timeout"
    )
    snapshot_chunk_voxels: int = Field(250_000, ge=1000, description="voxels per snapshot reply")
    half_life_s: float | None = Field(
        None,
        gt=0,
        description="own layer's evidence decays toward unknown with this half-life, seconds "
        "(none: no decay); peers decay their copy the same way (heartbeats carry it)",
    )
    forget_after_s: float | None = Field(
        None,
        gt=0,
        description="own layer's voxels nobody observed for this long become unknown (none: never)",
    )
    forget_s: float = Field(
        10.0, gt=0, description="seconds between forgetting passes over the own layer"
    )
    history_sync_s: float = Field(
        5.0,
        ge=0,
        description="seconds between pulls of peer layers' history records, so temporal "
        "queries on replicas answer as the origin (0: replicas keep none)",
    )
    history_push: bool = Field(
        False,
        description="opt-in: publish the own layer's new history records with each delta "
        "(<own>/history) and take peers' as they come; the pull fills any gap",
    )
    peer_history_entries: int = Field(
        2_000_000,
        ge=10_000,
        description="history entries (records; seen-log entries alike) all peer layers keep "
        "together, split evenly, each its newest (~53 B a record, 20 B a seen entry)",
    )
    colony_key: str | None = Field(None, description="shared secret; unauthenticated dropped")
    trust: Literal["off", "tofu", "list"] = Field(
        "tofu", description="peers' identities: off, pinned on first use, or trusted_keys only"
    )
    trusted_keys: dict[str, str] = Field(
        default_factory=dict,
        description="agent id -> Ed25519 public key (64 hex digits) pinned in advance",
    )
    identity_file: Path | None = Field(
        None,
        description=(
            "this agent's Ed25519 key (default <state_dir>/identity.key, made on first start)"
        ),
    )
    export_dir: Path | None = Field(None, description="write the fused map here on shutdown")
    drop_rate: float = Field(
        0.0, ge=0, lt=1, description="testing: drop this share of received deltas"
    )
    ros2_publish: bool = Field(
        False, description="publish the fused map, objects and frame to ROS 2 (rmw_zenoh)"
    )
    ros2_domain: int = Field(0, ge=0, le=232, description="ROS_DOMAIN_ID of the ROS 2 outputs")
    ros2_node: str = Field("colonyd", description="ROS 2 node name of the outputs")
    ros2_map_topic: str = Field("/colony/map", description="nav_msgs/OccupancyGrid topic")
    ros2_cloud_topic: str = Field("/colony/cloud", description="sensor_msgs/PointCloud2 topic")
    ros2_objects_topic: str = Field(
        "/colony/objects", description="visualization_msgs/MarkerArray topic"
    )
    ros2_frame: str = Field("colony", description="frame id of the published map")
    ros2_robot_frame: str = Field(
        "map", description="the robot's frame its own layer is built in (/tf child of ros2_frame)"
    )
    ros2_period_s: float = Field(
        2.0, gt=0, description="seconds between publications of the map (when it changed)"
    )
    ros2_grid_z: tuple[float, float] = Field(
        (-0.5, 2.0), description="heights (m) of voxels projected into the OccupancyGrid"
    )
    ros2_max_points: int = Field(
        2_000_000, ge=1, description="most points in the published cloud (thinned beyond)"
    )
    ros2_type_hashes: bool = Field(
        True,
        description="type hashes in keys (Jazzy and later); false for Humble's rmw_zenoh",
    )
    log_level: Literal["debug", "info", "warning", "error"] = "info"

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        return (init_settings, env_settings, _TomlSource(settings_cls))

    @field_validator("colony", "agent_id", "kind")
    @classmethod
    def _name(cls, value: str) -> str:
        if not _NAME.match(value):
            msg = (
                "expected 1-64 characters of [A-Za-z0-9_.-] starting with a letter or digit, "
                f"found {value!r}"
            )
            raise ValueError(msg)
        return value

    @field_validator("agent_id")
    @classmethod
    def _not_reserved(cls, value: str) -> str:
        if value in ("alive", "colony"):
            msg = (
                "expected an agent id other than the reserved words 'alive' and 'colony', "
                f"found {value!r}"
            )
            raise ValueError(msg)
        return value

    @field_validator("ros2_map_topic", "ros2_cloud_topic", "ros2_objects_topic")
    @classmethod
    def _topic(cls, value: str) -> str:
        from plugins.rmw import topic_name

        topic_name(value)  # RmwError (a ValueError) says what was expected
        return value

    @field_validator("ros2_publish")
    @classmethod
    def _rosbags(cls, value: bool) -> bool:
        if value:
            try:
                import rosbags  # noqa: F401
            except ImportError:
                msg = "expected the rosbags package (pip install 'colony[ros]'), found it missing"
                raise ValueError(msg) from None
        return value

    @field_validator("ros2_node", "ros2_frame", "ros2_robot_frame")
    @classmethod
    def _ros_name(cls, value: str) -> str:
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]{0,63}", value):
            msg = f"expected a ROS 2 name ([A-Za-z_][A-Za-z0-9_]*), found {value!r}"
            raise ValueError(msg)
        return value

    @field_validator("namespace")
    @classmethod
    def _namespace(cls, value: str | None) -> str | None:
        if value is not None and not _NAME.match(value):
            msg = (
                "expected 1-64 characters of [A-Za-z0-9_.-] starting with a letter or digit, "
                f"found {value!r}"
            )
            raise ValueError(msg)
        return value

    @field_validator("trusted_keys")
    @classmethod
    def _trusted(cls, value: dict[str, str]) -> dict[str, str]:
        for agent, key in value.items():
            if not _NAME.match(agent):
                msg = f"expected agent ids of 1-64 characters of [A-Za-z0-9_.-], found {agent!r}"
                raise ValueError(msg)
            if not re.fullmatch(r"[0-9a-fA-F]{64}", key):
                msg = f"expected {agent!r}'s Ed25519 public key as 64 hex digits, found {key!r}"
                raise ValueError(msg)
        return value

    @field_validator("sources")
    @classmethod
    def _recordings_once(cls, value: list[str]) -> list[str]:
        from colonyd.resume import resumes  # (plugins: not needed for the other checks)

        twice = sorted({s for s in value if value.count(s) > 1 and resumes(s)})
        if twice:
            msg = (
                f"expected each recording once (its position after a restart is kept by its "
                f"spec, so two readings of it could not be told apart), found {twice[0]!r} twice"
            )
            raise ValueError(msg)
        return value

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints(cls, value: list[str]) -> list[str]:
        for ep in value:
            if not _ENDPOINT.match(ep):
                msg = f"expected a Zenoh endpoint like 'tcp/127.0.0.1:7447', found {ep!r}"
                raise ValueError(msg)
            if not ep.startswith("unixsock-stream/"):
                address = ep.split("/", 1)[1].split("#")[0].split("?")[0]
                host, _, port = address.rpartition(":")
                if not host or not port.isdigit() or int(port) > 65535:
                    msg = (
                        "expected a Zenoh endpoint with host and port 0-65535 like "
                        f"'tcp/127.0.0.1:7447', found {ep!r}"
                    )
                    raise ValueError(msg)
        return value

    @model_validator(mode="after")
    def _consistent(self) -> Config:
        if self.mode == "client" and not self.connect and not self.multicast:
            msg = "client mode needs --connect ENDPOINT (a router) or multicast scouting"
            raise ValueError(msg)
        if self.site_pose is not None:
            if len(self.site_pose) not in (4, 6):
                msg = (
                    "site_pose: expected 4 numbers (x, y, z, yaw_deg) or 6 (x, y, z, yaw_deg, "
                    f"pitch_deg, roll_deg), found {len(self.site_pose)}"
                )
                raise ValueError(msg)
            if self.anchor is None:
                msg = (
                    "site_pose: expected `anchor` (the agent whose frame is the site frame) to be "
                    "set as well, found no anchor"
                )
                raise ValueError(msg)
            if self.anchor == self.agent_id:
                msg = (
                    f"site_pose: expected no site pose on the anchor {self.anchor!r} itself (its "
                    "frame is the site frame), found one"
                )
                raise ValueError(msg)
        return self

    def site_matrix(self) -> np.ndarray | None:
        """`site_pose` as a 4x4 transform taking this agent's frame into the site frame."""
        if self.site_pose is None:
            return None
        return pose_from_degrees(self.site_pose)

    @property
    def key_namespace(self) -> str:
        """The key-expression namespace: `namespace` if set, else the colony name."""
        return self.namespace or self.colony

    @property
    def multicast_port(self) -> int:
        return multicast_port(self.colony)


def load_config(path: Path | str | None = None, **flags: Any) -> Config:
    """Config from defaults < TOML file < `COLONYD_*` environment < flags (None flags ignored)."""
    if path is None and os.environ.get("COLONYD_CONFIG"):
        path = os.environ["COLONYD_CONFIG"]
    _check_environment()
    token = _TOML_PATH.set(Path(path) if path is not None else None)
    try:
        return Config(**{k: v for k, v in flags.items() if v is not None})
    except ValidationError as exc:
        raise ConfigError(_explain(exc)) from None
    except SettingsError as exc:  # an environment variable that is not the JSON a list needs
        field = str(exc).split('"')[1] if '"' in str(exc) else "?"
        name = f"COLONYD_{field.upper()}"
        msg = (
            f"environment variable {name}: expected JSON for a list or table (e.g. "
            f"{name}='[\"tcp/10.0.0.1:7447\"]'), found {os.environ.get(name, '')!r}"
        )
        raise ConfigError(msg) from None
    finally:
        _TOML_PATH.reset(token)


def _check_environment() -> None:
    """A `COLONYD_*` variable that names no field is a typo, not a setting to ignore silently."""
    for name in sorted(os.environ):
        upper = name.upper()
        if not upper.startswith("COLONYD_") or upper == "COLONYD_CONFIG":
            continue
        field = upper.removeprefix("COLONYD_").lower()
        if field not in Config.model_fields:
            msg = f"environment variable {name}: {_unknown_field(field)}, found unknown field"
            raise ConfigError(msg)


def _explain(exc: ValidationError) -> str:
    lines = ["invalid configuration:"]
    for err in exc.errors():
        where = ".".join(str(p) for p in err["loc"])
        text = str(err.get("input"))
        if len(text) > 80:
            text = text[:77] + "..."
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "extra_forbidden":
            lines.append(f"  {where}: {_unknown_field(where)}, found unknown field {where!r}")
        elif not where:  # a check across fields: its message says what it found
            lines.append(f"  {msg}")
        elif "found" in msg:  # the validator's own message says what it found
            lines.append(f"  {where}: {msg}")
        else:
            lines.append(f"  {where}: {msg} (found {text!r})")
    return "\n".join(lines)


def _unknown_field(name: str) -> str:
    """What an unknown field should have been: the closest known ones, or where they are listed."""
    close = difflib.get_close_matches(name, list(Config.model_fields), n=3, cutoff=0.6)
    if close:
        return "expected a known field such as " + " or ".join(repr(c) for c in close)
    return "expected one of the fields `colonyd dump-config` prints (docs/DAEMON.md)"


def dump_config(config: Config) -> str:
    """The effective configuration as TOML text (what `colonyd dump-config` prints)."""
    lines = [f"# precedence: {' > '.join(PRECEDENCE)}"]
    for name, value in config.model_dump(mode="json").items():
        if name in SECRETS and value is not None:
            lines.append(f'{name} = "********"  # set; not shown')
            continue
        if value is None:
            lines.append(f"# {name} = (unset)")
            continue
        lines.append(f"{name} = {_toml_value(value)}")
    return "\n".join(lines) + "\n"


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return (
            "{" + ", ".join(f"{json.dumps(k)} = {_toml_value(v)}" for k, v in value.items()) + "}"
        )
    return json.dumps(str(value))
