"""rmw_zenoh's wire format: data keys, liveliness tokens, QoS text, attachments, type names, hashes.

Checked against rmw_zenoh's docs/design.md ("Topic and Service name mapping", "Graph Cache",
"Publishers", "Quality of Service"); see docs/ROS2.md.
"""

from __future__ import annotations

import hashlib
import struct
from dataclasses import dataclass
from functools import cache
from typing import Any

from plugins.errors import SensorInputError, SourceError

#: Hermetic prefix of every rmw_zenoh liveliness token.
ADMIN = "@ros2_lv"
#: The current attachment: int64 sequence number, int64 source time (ns), 0x10, 16-byte GID.
ATTACHMENT = struct.Struct("<qqB16s")
#: The labelled attachment of rmw_zenoh before mid-2025 (humble 0.1.1, jazzy 0.2.3, rolling 0.5).
_LABELS = (b"sequence_number", b"source_timestamp", b"source_gid")
LEGACY_ATTACHMENT_SIZE = sum(1 + len(label) for label in _LABELS) + 8 + 8 + 1 + 16
#: What Humble's rmw_zenoh writes where a type hash goes.
NO_HASH = "TypeHashNotSupported"
#: Entity kinds of liveliness tokens.
NODE, PUBLISHER, SUBSCRIPTION = "NN", "MP", "MS"
#: QoS enum values of `qos_to_keyexpr`.
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2


class RmwError(SensorInputError):
    """A sample, key or token that does not follow rmw_zenoh's wire format."""


@dataclass(frozen=True)
class Attachment:
    """What rmw_zenoh attaches to every sample: publisher sequence number, source time, GID."""

    seq: int
    stamp_ns: int
    gid: bytes

    def encode(self) -> bytes:
        """The 33-byte attachment of current rmw_zenoh releases."""
        return ATTACHMENT.pack(self.seq, self.stamp_ns, 16, self.gid)


def decode_attachment(data: bytes | None) -> Attachment:
    """An attachment in either format (33 bytes, or the 77-byte labelled one of older releases)."""
    if data is None:
        msg = "attachment: expected rmw_zenoh's sequence number, time and GID, found none"
        raise RmwError(msg)
    if len(data) == ATTACHMENT.size:
        seq, stamp, n, gid = ATTACHMENT.unpack(data)
        if n != 16:
            msg = f"attachment: expected a GID of 16 bytes, found length byte {n}"
            raise RmwError(msg)
        return Attachment(seq, stamp, gid)
    if len(data) == LEGACY_ATTACHMENT_SIZE:
        values: list[Any] = []
        at = 0
        for label in _LABELS:
            if data[at] != len(label) or data[at + 1 : at + 1 + len(label)] != label:
                msg = f"attachment: expected label {label.decode()!r} at byte {at}"
                raise RmwError(msg)
            at += 1 + len(label)
            if label == b"source_gid":
                if data[at] != 16:
                    msg = f"attachment: expected a GID of 16 bytes, found length byte {data[at]}"
                    raise RmwError(msg)
                values.append(bytes(data[at + 1 : at + 17]))
            else:
                values.append(struct.unpack_from("<q", data, at)[0])
                at += 8
        return Attachment(values[0], values[1], values[2])
    msg = (
        f"attachment: expected {ATTACHMENT.size} bytes (or {LEGACY_ATTACHMENT_SIZE}, the "
        f"labelled format of older releases), found {len(data)}"
    )
    raise RmwError(msg)


def dds_type(ros_type: str) -> str:
    """`pkg/msg/T` as DDS names it: `pkg::msg::dds_::T_`."""
    pkg, kind, name = _type_parts(ros_type)
    return f"{pkg}::{kind}::dds_::{name}_"


def ros_type(dds: str) -> str:
    """`pkg::msg::dds_::T_` back to `pkg/msg/T`; RmwError for anything else."""
    parts = dds.split("::")
    if len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_") or len(parts[3]) < 2:
        msg = f"type name: expected 'pkg::msg::dds_::Type_', found {dds!r}"
        raise RmwError(msg)
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


def _type_parts(ros_type: str) -> tuple[str, str, str]:
    parts = ros_type.split("/")
    if len(parts) != 3 or not all(parts):
        msg = f"type name: expected 'pkg/msg/Type', found {ros_type!r}"
        raise RmwError(msg)
    return parts[0], parts[1], parts[2]


def topic_name(topic: str) -> str:
    """A fully qualified topic name (`/scan`, `/robot1/odom`) without its outer slashes."""
    name = topic.strip("/")
    if not name or "//" in name or any(c in name for c in "*$?#@% "):
        msg = f"topic: expected a ROS 2 topic name such as /scan, found {topic!r}"
        raise RmwError(msg)
    return name


def data_key(domain: int, topic: str, ros_type: str, type_hash: str) -> str:
    """`<domain>/<topic>/<dds type>/<type hash>`: the key rmw_zenoh publishes `topic` on."""
    return f"{domain}/{topic_name(topic)}/{dds_type(ros_type)}/{type_hash}"


def any_type_key(domain: int, topic: str) -> str:
    """The key of `topic` whatever its type and hash (Humble sends no hash; types are checked on
    arrival)."""
    return f"{domain}/{topic_name(topic)}/*/*"


def type_of_key(key: str) -> tuple[str, str]:
    """(ROS type, type hash) named by the last two chunks of a data key."""
    chunks = key.split("/")
    if len(chunks) < 4:
        msg = f"key: expected '<domain>/<topic>/<type>/<hash>', found {key!r}"
        raise RmwError(msg)
    return ros_type(chunks[-2]), chunks[-1]


@cache
def type_hash(ros_type: str) -> str:
    """The RIHS01 hash (REP-2016) of a message type, as rosidl computes it (rosbags' typestore)."""
    return typestore().hash_rihs01(ros_type)  # type: ignore[no-any-return]


@cache
def typestore() -> Any:
    """rosbags' ROS 2 Jazzy typestore (CDR in both directions); SourceError without rosbags."""
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        msg = "ROS 2: expected the rosbags package (pip install 'colony[ros]'), found it missing"
        raise SourceError(msg) from None
    return get_typestore(Stores.ROS2_JAZZY)


def mangle(name: str) -> str:
    """A name as it appears in a token: every `/` becomes `%`; empty becomes `%`."""
    return name.replace("/", "%") or "%"


def qos_text(
    *, reliable: bool = True, transient_local: bool = False, depth: int = 10, keep_all: bool = False
) -> str:
    """QoS as `qos_to_keyexpr` writes it, every value explicit (defaults changed between
    releases)."""
    rel = RELIABLE if reliable else BEST_EFFORT
    dur = TRANSIENT_LOCAL if transient_local else VOLATILE
    hist = KEEP_ALL if keep_all else KEEP_LAST
    return f"{rel}:{dur}:{hist},{depth}:,:,:,,"


def node_token(domain: int, zid: str, node_id: int, namespace: str, node: str) -> str:
    """The liveliness token of a node (entity kind NN; default enclave)."""
    return f"{ADMIN}/{domain}/{zid}/{node_id}/{node_id}/{NODE}/%/{mangle(namespace)}/{node}"


def endpoint_token(
    domain: int,
    zid: str,
    node_id: int,
    entity_id: int,
    kind: str,
    namespace: str,
    node: str,
    topic: str,
    ros_type: str,
    type_hash: str,
    qos: str,
) -> str:
    """The liveliness token of a publisher (MP) or subscription (MS) of `node`."""
    return (
        f"{ADMIN}/{domain}/{zid}/{node_id}/{entity_id}/{kind}/%/{mangle(namespace)}/{node}/"
        f"{mangle('/' + topic_name(topic))}/{dds_type(ros_type)}/{type_hash}/{qos}"
    )


@dataclass(frozen=True)
class Endpoint:
    """A publisher or subscription read from a liveliness token."""

    kind: str
    node: str
    topic: str
    ros_type: str
    type_hash: str
    qos: str


def parse_endpoint(token: str) -> Endpoint:
    """The publisher or subscription a token declares; RmwError for nodes and malformed tokens."""
    parts = token.split("/")
    if len(parts) < 13 or parts[0] != ADMIN or parts[5] not in ("MP", "MS", "SS", "SC"):
        msg = f"token: expected an rmw_zenoh endpoint token (13 parts), found {token!r}"
        raise RmwError(msg)
    return Endpoint(
        parts[5],
        parts[8],
        parts[9].replace("%", "/"),
        ros_type(parts[10]),
        parts[11],
        parts[12],
    )


def gid_of(token: str) -> bytes:
    """A 16-byte GID for the entity of `token` (rmw_zenoh hashes the token too; receivers only
    compare GIDs)."""
    return hashlib.blake2b(token.encode(), digest_size=16).digest()
