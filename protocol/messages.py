"""Messages exchanged between daemons: pydantic models validated at the network boundary."""

from __future__ import annotations

import math
from typing import Annotated, Any, ClassVar

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    InstanceOf,
    StringConstraints,
    field_validator,
    model_validator,
)

from protocol.keyexpr import NAME_PATTERN
from protocol.summary import FreeSummary
from voxel.delta import Delta
from voxel.history import HistoryPage
from voxel.rotation import matrix_to_quaternion, quaternion_to_matrix
from voxel.sensor import SENSOR_KINDS, SensorModel

#: The protocol version this implementation speaks (byte 4 of every frame).
PROTOCOL_VERSION = 1

U8 = Annotated[int, Field(ge=0, le=0xFF)]
U16 = Annotated[int, Field(ge=0, le=0xFFFF)]
U32 = Annotated[int, Field(ge=0, le=0xFFFF_FFFF)]
U63 = Annotated[int, Field(ge=0, le=(1 << 63) - 1)]
Finite = Annotated[float, Field(allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0.0, allow_inf_nan=False)]
Probability = Annotated[float, Field(gt=0.0, lt=1.0)]
Name = Annotated[str, StringConstraints(pattern=f"^{NAME_PATTERN}$")]
Label = Annotated[str, StringConstraints(max_length=256)]
Vec3 = tuple[Finite, Finite, Finite]
Quat = tuple[Finite, Finite, Finite, Finite]
Cov3 = Annotated[list[Finite], Field(min_length=9, max_length=9)]
Cov6 = Annotated[list[Finite], Field(min_length=36, max_length=36)]

#: Fields every message carries in its envelope rather than in its body.
HEADER_FIELDS = ("version", "origin", "epoch", "seq", "time")


class Message(BaseModel):
    """Common part of every message: protocol version, origin, epoch, sequence number and time.

    `epoch` changes when the origin restarts without its previous state; `seq` increases by one
    per message the origin sends within an epoch; `time` is the origin's clock, seconds (Unix).
    """

    model_config = ConfigDict(
        extra="forbid", arbitrary_types_allowed=True, validate_assignment=False
    )

    TYPE: ClassVar[int] = 0
    KIND: ClassVar[str] = ""
    #: A request (query payload): read-only, so receivers that check identities accept it
    #: unsigned; every other message must carry its origin's signature there.
    REQUEST: ClassVar[bool] = False

    version: U8 = PROTOCOL_VERSION
    origin: Name
    epoch: U63 = 0
    seq: U63 = 0
    time: Finite


class SensorInfo(BaseModel):
    """One sensor of an agent and its inverse sensor model."""

    model_config = ConfigDict(extra="forbid")

    name: Name
    kind: str
    prob_hit: Probability = 0.7
    prob_miss: Probability = 0.4
    clamp_min: Probability = 0.12
    clamp_max: Probability = 0.97
    #: Maximum range in metres; None means unlimited.
    max_range: Positive | None = None

    @field_validator("kind")
    @classmethod
    def _known_kind(cls, v: str) -> str:
        if v not in SENSOR_KINDS:
            msg = f"sensor kind must be one of {sorted(SENSOR_KINDS)}, found {v!r}"
            raise ValueError(msg)
        return v

    @classmethod
    def from_model(cls, name: str, model: SensorModel) -> SensorInfo:
        """Describe a `voxel.sensor.SensorModel` under `name`."""
        return cls(
            name=name,
            kind=model.kind,
            prob_hit=model.prob_hit,
            prob_miss=model.prob_miss,
            clamp_min=model.clamp_min,
            clamp_max=model.clamp_max,
            max_range=None if math.isinf(model.max_range) else model.max_range,
        )

    def to_model(self) -> SensorModel:
        """The `voxel.sensor.SensorModel` this describes (voxel InputError if inconsistent)."""
        return SensorModel(
            prob_hit=self.prob_hit,
            prob_miss=self.prob_miss,
            clamp_min=self.clamp_min,
            clamp_max=self.clamp_max,
            max_range=math.inf if self.max_range is None else self.max_range,
            kind=self.kind,
        )


class Announce(Message):
    """Who an agent is: kind, sensors, software, protocol versions, map frame and resolution."""

    TYPE: ClassVar[int] = 1
    KIND: ClassVar[str] = "announce"

    kind: Name
    sensors: Annotated[list[SensorInfo], Field(max_length=64)] = []
    software: Label = ""
    protocols: Annotated[list[U8], Field(min_length=1, max_length=16)] = [PROTOCOL_VERSION]
    frame_id: Name
    resolution: Positive
    capabilities: Annotated[list[Name], Field(max_length=64)] = []


def _check_quaternion(q: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    norm = math.sqrt(sum(c * c for c in q))
    if abs(norm - 1.0) > 1e-3:
        msg = f"orientation must be a unit quaternion (x, y, z, w), found norm {norm:.6g}"
        raise ValueError(msg)
    return q


class _Rigid(BaseModel):
    """Mixin: a rigid transform as position + unit quaternion (x, y, z, w)."""

    position: Vec3
    orientation: Quat = (0.0, 0.0, 0.0, 1.0)

    @field_validator("orientation")
    @classmethod
    def _unit(cls, q: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
        return _check_quaternion(q)

    def matrix(self) -> np.ndarray:
        """The 4x4 homogeneous matrix of this transform."""
        t = np.eye(4)
        t[:3, :3] = quaternion_to_matrix(self.orientation)
        t[:3, 3] = self.position
        return t

    @staticmethod
    def split_matrix(matrix: np.ndarray) -> dict[str, Any]:
        """`position` and `orientation` keyword arguments of a 4x4 rigid transform."""
        m = np.asarray(matrix, dtype=np.float64)
        if m.shape != (4, 4):
            msg = f"transform must be a 4x4 matrix, found shape {m.shape}"
            raise ValueError(msg)
        return {
            "position": tuple(float(v) for v in m[:3, 3]),
            "orientation": tuple(float(c) for c in matrix_to_quaternion(m[:3, :3])),
        }


class Pose(Message, _Rigid):
    """The origin's pose in its map frame with a 6x6 covariance (x y z roll pitch yaw)."""

    TYPE: ClassVar[int] = 2
    KIND: ClassVar[str] = "pose"

    frame_id: Name
    covariance: Cov6 = [0.0] * 36


class VoxelDelta(Message):
    """Changed voxels of the origin's own layer, with absolute values (see `voxel.delta.Delta`).

    A delta too large for one message is sent as `parts` messages (`part` = 0..parts-1), each
    independently decodable and applicable. `free_summary`, when present, is a coarse,
    approximate stand-in for free space left out of `delta` to meet a byte budget.
    """

    TYPE: ClassVar[int] = 3
    KIND: ClassVar[str] = "delta"

    frame_id: Name
    part: U16 = 0
    parts: Annotated[int, Field(ge=1, le=0xFFFF)] = 1
    delta: Delta
    free_summary: FreeSummary | None = None

    @model_validator(mode="after")
    def _part_in_range(self) -> VoxelDelta:
        _check_part(self.part, self.parts)
        return self

    @property
    def exact(self) -> bool:
        """True if the message carries no approximate free-space summary."""
        return self.free_summary is None


def _check_part(part: int, parts: int) -> None:
    if part >= parts:
        msg = f"part must be below parts, found part {part} of {parts}"
        raise ValueError(msg)


class ObjectCentroid(BaseModel):
    """One object of the origin's map: centroid in the origin's frame with covariance."""

    model_config = ConfigDict(extra="forbid")

    object_id: U63
    class_id: U16
    class_name: Label = ""
    position: Vec3
    covariance: Cov3 = [0.0] * 9
    voxel_count: U32
    time: Finite


class Objects(Message):
    """The origin's current object centroids (a full list: objects not listed are gone)."""

    TYPE: ClassVar[int] = 4
    KIND: ClassVar[str] = "objects"

    frame_id: Name
    objects: Annotated[list[ObjectCentroid], Field(max_length=16_384)] = []


class AlignOffer(Message, _Rigid):
    """The origin's estimate of the transform taking `target`'s frame into its own frame."""

    TYPE: ClassVar[int] = 5
    KIND: ClassVar[str] = "align"

    target: Name
    source_frame: Name
    target_frame: Name
    covariance: Cov6 = [0.0] * 36
    matches: U32 = 0
    inliers: U32 = 0
    rmse: Annotated[float, Field(ge=0.0, allow_inf_nan=False)] = 0.0
    #: How sure the sender is, 0-1 (senders offer only transforms they accept).
    confidence: Annotated[float, Field(ge=0.0, le=1.0, allow_inf_nan=False)] = 1.0
    #: (own object id, target's object id) pairs used for the estimate.
    pairs: Annotated[list[tuple[U63, U63]], Field(max_length=4096)] = []


class PoseFix(Message, _Rigid):
    """An absolute observation of another agent's pose: the origin (a fixed camera with a surveyed
    pose) saw `target`'s marker at `stamp`; `position`/`orientation` are the target's body pose in
    `frame_id`, the origin's own frame, with a 6x6 covariance (x y z roll pitch yaw)."""

    TYPE: ClassVar[int] = 11
    KIND: ClassVar[str] = "fix"

    target: Name
    frame_id: Name
    #: When the target was seen (the observation's time on the origin's clock), seconds (Unix).
    stamp: Finite
    covariance: Cov6 = [0.0] * 36
    #: The marker seen (0: unknown).
    marker_id: U32 = 0
    confidence: Annotated[float, Field(ge=0.0, le=1.0, allow_inf_nan=False)] = 1.0

    @model_validator(mode="after")
    def _other_agent(self) -> PoseFix:
        if self.target == self.origin:
            msg = f"target must be another agent than the origin, found {self.target!r} for both"
            raise ValueError(msg)
        return self


class SnapshotRequest(Message):
    """Ask for the full content of `layer` (answered with SnapshotReply parts)."""

    TYPE: ClassVar[int] = 6
    KIND: ClassVar[str] = "snapshot_request"
    REQUEST: ClassVar[bool] = True

    layer: Name
    request_id: U63
    #: Largest reply part the requester accepts.
    max_part_bytes: Annotated[int, Field(ge=1024, le=1 << 30)] = 4 << 20
    #: How long the requester waits for replies after sending it, ms (0: not said); a server
    #: may drop the work of a request it cannot answer within that.
    timeout_ms: U32 = 0


class SnapshotReply(Message):
    """One part of the content of `layer` at version `delta.to_version` (from_version 0).

    `layer_epoch` is the epoch of the layer's origin the content belongs to: a server answering
    for another origin's layer (store and forward) says which of that origin's epochs it holds.
    """

    TYPE: ClassVar[int] = 7
    KIND: ClassVar[str] = "snapshot_reply"

    layer: Name
    request_id: U63
    frame_id: Name
    layer_epoch: U63
    part: U16 = 0
    parts: Annotated[int, Field(ge=1, le=0xFFFF)] = 1
    delta: Delta

    @model_validator(mode="after")
    def _part_in_range(self) -> SnapshotReply:
        _check_part(self.part, self.parts)
        return self


class DeltaRangeRequest(Message):
    """Ask for the changes of `layer` in versions (from_version, to_version]."""

    TYPE: ClassVar[int] = 8
    KIND: ClassVar[str] = "delta_range_request"
    REQUEST: ClassVar[bool] = True

    layer: Name
    request_id: U63
    from_version: U63
    to_version: U63
    max_part_bytes: Annotated[int, Field(ge=1024, le=1 << 30)] = 4 << 20
    #: How long the requester waits for replies after sending it, ms (0: not said); a server
    #: may drop the work of a request it cannot answer within that.
    timeout_ms: U32 = 0

    @model_validator(mode="after")
    def _ordered(self) -> DeltaRangeRequest:
        if self.to_version < self.from_version:
            msg = (
                f"to_version must be >= from_version, found {self.from_version} -> "
                f"{self.to_version}"
            )
            raise ValueError(msg)
        return self


class DeltaRangeReply(Message):
    """One part of the changes of `layer` in (from_version, to_version].

    `complete` is False if the server no longer holds that range; the requester should then ask
    for a snapshot. `delta` is None when nothing changed or nothing is available. `layer_epoch`
    is the epoch of the layer's origin the versions belong to (0: the server holds no such layer).
    """

    TYPE: ClassVar[int] = 9
    KIND: ClassVar[str] = "delta_range_reply"

    layer: Name
    request_id: U63
    frame_id: Name
    layer_epoch: U63
    complete: bool = True
    part: U16 = 0
    parts: Annotated[int, Field(ge=1, le=0xFFFF)] = 1
    delta: Delta | None = None

    @model_validator(mode="after")
    def _part_in_range(self) -> DeltaRangeReply:
        _check_part(self.part, self.parts)
        return self


class LayerVersion(BaseModel):
    """One layer a peer holds: its origin, the origin's epoch and the layer's version (seq)."""

    model_config = ConfigDict(extra="forbid")

    origin: Name
    epoch: U63
    version: U63
    #: The layer's decay half-life in seconds (None: no decay), as its origin configured it: a
    #: replica decays its copy the same way, so it computes the origin's occupancy.
    half_life: Positive | None = None


class Heartbeat(Message):
    """What a peer is and holds: kind, pose, and the (origin, epoch, version) of every layer.

    Sent periodically and on membership changes; a receiver that holds less of a layer than a
    heartbeat reports asks the sender for it (SnapshotRequest or DeltaRangeRequest). `position`
    is None when the peer does not know its pose.
    """

    TYPE: ClassVar[int] = 10
    KIND: ClassVar[str] = "heartbeat"

    kind: Name
    frame_id: Name
    position: Vec3 | None = None
    orientation: Quat = (0.0, 0.0, 0.0, 1.0)
    layers: Annotated[list[LayerVersion], Field(max_length=4096)] = []
    #: Agents whose layers were forgotten colony-wide (`colonyd forget-agent`): receivers drop
    #: them and refuse them from then on.
    forgotten: Annotated[list[Name], Field(max_length=4096)] = []
    #: The sender's Ed25519 public key (32 bytes): how peers that trust on first use learn it.
    identity: Annotated[bytes, Field(min_length=32, max_length=32)] | None = None

    @field_validator("orientation")
    @classmethod
    def _unit(cls, q: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
        return _check_quaternion(q)

    @field_validator("layers")
    @classmethod
    def _unique(cls, layers: list[LayerVersion]) -> list[LayerVersion]:
        origins = [entry.origin for entry in layers]
        if len(set(origins)) != len(origins):
            dup = next(o for o in origins if origins.count(o) > 1)
            msg = f"layers must list each origin once, found {dup!r} twice"
            raise ValueError(msg)
        return layers


class HistoryRequest(Message):
    """Ask for the history records of `layer` made at versions above `from_version` (the
    origin's grid versions, one per scan), at most about `max_records` of them."""

    TYPE: ClassVar[int] = 12
    KIND: ClassVar[str] = "history_request"
    REQUEST: ClassVar[bool] = True

    layer: Name
    request_id: U63
    from_version: U63
    max_records: Annotated[int, Field(ge=1, le=1_000_000)] = 200_000
    max_part_bytes: Annotated[int, Field(ge=1024, le=1 << 30)] = 4 << 20
    #: How long the requester waits for replies after sending it, ms (0: not said); a server
    #: may drop the work of a request it cannot answer within that.
    timeout_ms: U32 = 0


class HistoryReply(Message):
    """One part of the history records of `layer` in versions (from_version, to_version].

    The server pages in whole versions: the parts of one reply together hold every record it
    holds of those versions. `more` says records of later versions remain (ask again from
    `to_version`). `layer_epoch` is the epoch of the layer's origin the versions belong to
    (0: the server holds no such layer). `records` is None when there are none.
    """

    TYPE: ClassVar[int] = 13
    KIND: ClassVar[str] = "history_reply"

    layer: Name
    request_id: U63
    layer_epoch: U63
    from_version: U63
    to_version: U63
    more: bool = False
    part: U16 = 0
    parts: Annotated[int, Field(ge=1, le=0xFFFF)] = 1
    records: InstanceOf[HistoryPage] | None = None

    @model_validator(mode="after")
    def _checked(self) -> HistoryReply:
        _check_part(self.part, self.parts)
        if self.to_version < self.from_version:
            msg = (
                f"to_version must be >= from_version, found {self.from_version} -> "
                f"{self.to_version}"
            )
            raise ValueError(msg)
        if self.records is not None and (self.records.records.size or self.records.seen.size):
            v = np.concatenate([self.records.records["version"], self.records.seen["version"]])
            if int(v.min()) <= self.from_version or int(v.max()) > self.to_version:
                msg = (
                    f"records must have versions in ({self.from_version}, {self.to_version}], "
                    f"found {int(v.min())}..{int(v.max())}"
                )
                raise ValueError(msg)
        return self


#: Every message class by its type code (byte 5 of a frame).
MESSAGE_TYPES: dict[int, type[Message]] = {
    cls.TYPE: cls
    for cls in (
        Announce,
        Pose,
        VoxelDelta,
        Objects,
        AlignOffer,
        SnapshotRequest,
        SnapshotReply,
        DeltaRangeRequest,
        DeltaRangeReply,
        Heartbeat,
        PoseFix,
        HistoryRequest,
        HistoryReply,
    )
}
