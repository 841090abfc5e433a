"""Wire protocol: messages, frames, voxel-delta codec, key expressions, authentication, errors."""

from protocol.auth import ReplayWindow
from protocol.codec import FrameInfo, decode, delta_messages, encode, peek
from protocol.deltacodec import decode_delta, encode_delta, fit_delta, split_delta
from protocol.errors import (
    AuthError,
    DecompressionBombError,
    KeyExprError,
    MalformedError,
    OversizedError,
    ProtocolError,
    RangeError,
    ReplayError,
    TruncatedError,
    UnknownTypeError,
    VersionError,
)
from protocol.limits import Limits
from protocol.messages import (
    PROTOCOL_VERSION,
    AlignOffer,
    Announce,
    DeltaRangeReply,
    DeltaRangeRequest,
    Message,
    ObjectCentroid,
    Objects,
    Pose,
    SensorInfo,
    SnapshotReply,
    SnapshotRequest,
    VoxelDelta,
)
from protocol.receiver import Receiver
from protocol.summary import FreeSummary

__all__ = [
    "PROTOCOL_VERSION",
    "AlignOffer",
    "Announce",
    "AuthError",
    "DecompressionBombError",
    "DeltaRangeReply",
    "DeltaRangeRequest",
    "FrameInfo",
    "FreeSummary",
    "KeyExprError",
    "Limits",
    "MalformedError",
    "Message",
    "ObjectCentroid",
    "Objects",
    "OversizedError",
    "Pose",
    "ProtocolError",
    "RangeError",
    "Receiver",
    "ReplayError",
    "ReplayWindow",
    "SensorInfo",
    "SnapshotReply",
    "SnapshotRequest",
    "TruncatedError",
    "UnknownTypeError",
    "VersionError",
    "VoxelDelta",
    "decode",
    "decode_delta",
    "delta_messages",
    "encode",
    "encode_delta",
    "fit_delta",
    "peek",
    "split_delta",
]
