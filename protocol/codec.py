"""Frames: encode a message into bytes for Zenoh, decode hostile bytes into a validated message.

A frame is an 8-byte prefix (magic, version, type, flags), a msgpack envelope
[origin, epoch, seq, time, body] with the body zstd-compressed, the origin's 64-byte Ed25519
signature when it signs, and, with a colony key, a 32-byte HMAC-SHA256 tag over everything
before it. See docs/PROTOCOL.md.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, Literal, cast

import numpy as np
from pydantic import ValidationError

from protocol import fields
from protocol.auth import TAG_BYTES, ReplayWindow, compute_tag, verify_tag
from protocol.deltacodec import (
    decode_delta_with_summary,
    encode_delta,
    encoded_size,
    fit_delta,
    split_delta,
)
from protocol.errors import (
    AuthError,
    IdentityError,
    MalformedError,
    OversizedError,
    ProtocolError,
    RangeError,
    TruncatedError,
    UnknownTypeError,
    VersionError,
)
from protocol.historycodec import decode_history, encode_history
from protocol.identity import SIG_BYTES, Signer, Trust, verify_signature
from protocol.keyexpr import NAME_PATTERN
from protocol.limits import DEFAULT_LIMITS, Limits
from protocol.messages import HEADER_FIELDS, MESSAGE_TYPES, PROTOCOL_VERSION, Message, VoxelDelta
from protocol.summary import FreeSummary
from voxel.delta import Delta

MAGIC = b"CLNY"
PREFIX = struct.Struct("<4sBBBB")  # magic, version, type, flags, reserved
PREFIX_BYTES = PREFIX.size
FLAG_AUTH = 0x01
COMPRESSION_SHIFT = 1
COMPRESSION_MASK = 0x06
COMPRESSION_NONE = 0
COMPRESSION_ZSTD = 1
FLAG_SIGNED = 0x08
FLAGS_RESERVED = 0xF0
#: Bodies shorter than this are sent uncompressed (zstd would not make them smaller).
MIN_COMPRESS_BYTES = 64
#: Bytes a frame adds around a delta body (prefix, envelope, body fields, signature, tag), upper
#: bound.
FRAME_OVERHEAD = 320

_NAME_RE = __import__("re").compile(NAME_PATTERN)
_DELTA_FIELDS = ("delta", "free_summary", "records")


@dataclass(frozen=True)
class FrameInfo:
    """What a frame says about itself before its body is decoded or its tag checked."""

    version: int
    type: int
    kind: str
    origin: str
    epoch: int
    seq: int
    time: float
    authenticated: bool
    compression: int
    size: int


# --------------------------------------------------------------------------- encoding


def _body(msg: Message) -> dict[str, Any]:
    skip = set(HEADER_FIELDS) | set(_DELTA_FIELDS)
    body = msg.model_dump(mode="python", exclude=skip)
    if "delta" in type(msg).model_fields:
        delta = cast("Delta | None", msg.__dict__["delta"])  # the field a message type declares
        summary = getattr(msg, "free_summary", None)
        body["delta"] = None if delta is None else encode_delta(delta, summary=summary)
    if "records" in type(msg).model_fields:
        page = msg.__dict__["records"]
        body["records"] = None if page is None else encode_history(page)
    return body


def encode(
    msg: Message,
    *,
    key: bytes | None = None,
    compression: Literal["zstd", "none"] = "zstd",
    level: int = fields.DEFAULT_LEVEL,
    signer: Signer | None = None,
) -> bytes:
    """Frame bytes of `msg`; signed by the origin's identity `signer` (Ed25519) when given, and
    authenticated with HMAC-SHA256 when a colony `key` is given."""
    if msg.version != PROTOCOL_VERSION:
        msg_ = (
            f"can only encode protocol version {PROTOCOL_VERSION}, found message version "
            f"{msg.version}"
        )
        raise VersionError(msg_)
    if type(msg).TYPE not in MESSAGE_TYPES:
        msg_ = (
            "expected one of the message classes "
            f"{sorted(c.__name__ for c in MESSAGE_TYPES.values())}, found {type(msg).__name__}"
        )
        raise UnknownTypeError(msg_)
    body = fields.pack(_body(msg))
    code = COMPRESSION_NONE
    if compression == "zstd" and len(body) >= MIN_COMPRESS_BYTES:
        body = fields.compress(body, level)
        code = COMPRESSION_ZSTD
    elif compression not in ("zstd", "none"):
        msg_ = f"compression must be 'zstd' or 'none', found {compression!r}"
        raise ValueError(msg_)
    flags = (code << COMPRESSION_SHIFT) | (FLAG_AUTH if key is not None else 0)
    flags |= FLAG_SIGNED if signer is not None else 0
    envelope = fields.pack([msg.origin, msg.epoch, msg.seq, float(msg.time), body])
    frame = PREFIX.pack(MAGIC, PROTOCOL_VERSION, type(msg).TYPE, flags, 0) + envelope
    if signer is not None:
        frame += signer.sign(frame)
    if key is not None:
        frame += compute_tag(key, frame)
    return frame


# --------------------------------------------------------------------------- decoding


def _prefix(data: bytes, limits: Limits) -> tuple[int, int, int]:
    if not isinstance(data, (bytes, bytearray, memoryview)):
        msg = f"frame must be bytes, found {type(data).__name__}"
        raise MalformedError(msg)
    if len(data) > limits.max_message_bytes:
        msg = f"frame: expected at most {limits.max_message_bytes} bytes, found {len(data)}"
        raise OversizedError(msg)
    if len(data) < PREFIX_BYTES:
        msg = f"frame: expected at least {PREFIX_BYTES} bytes of prefix, found {len(data)}"
        raise TruncatedError(msg)
    magic, version, mtype, flags, reserved = PREFIX.unpack_from(data)
    if magic != MAGIC:
        msg = f"frame: expected magic {MAGIC!r}, found {bytes(magic)!r}"
        raise MalformedError(msg)
    if version != PROTOCOL_VERSION:
        msg = f"frame: expected protocol version {PROTOCOL_VERSION}, found {version}"
        raise VersionError(msg)
    if mtype not in MESSAGE_TYPES:
        msg = f"frame: expected a message type in {sorted(MESSAGE_TYPES)}, found {mtype}"
        raise UnknownTypeError(msg)
    if flags & FLAGS_RESERVED or reserved:
        msg = (
            f"frame: expected reserved flag bits and byte 7 to be 0, found flags 0x{flags:02x}, "
            f"byte 7 0x{reserved:02x}"
        )
        raise MalformedError(msg)
    compression = (flags & COMPRESSION_MASK) >> COMPRESSION_SHIFT
    if compression not in (COMPRESSION_NONE, COMPRESSION_ZSTD):
        msg = f"frame: expected compression 0 (none) or 1 (zstd), found {compression}"
        raise UnknownTypeError(msg)
    return mtype, flags, compression


def _envelope(data: bytes, end: int, limits: Limits) -> tuple[str, int, int, float, bytes]:
    env = fields.unpack(bytes(data[PREFIX_BYTES:end]), "envelope", limits)
    if not isinstance(env, list) or len(env) != 5:
        found = f"{len(env)} items" if isinstance(env, list) else type(env).__name__
        msg = f"envelope: expected [origin, epoch, seq, time, body], found {found}"
        raise MalformedError(msg)
    origin, epoch, seq, time, body = env
    if not isinstance(origin, str) or not _NAME_RE.fullmatch(origin):
        msg = f"envelope: expected origin matching {NAME_PATTERN}, found {str(origin)[:80]!r}"
        raise RangeError(msg)
    for name, value, hi in (("epoch", epoch, (1 << 63) - 1), ("seq", seq, (1 << 63) - 1)):
        if isinstance(value, bool) or not isinstance(value, int):
            msg = f"envelope: expected integer {name}, found {type(value).__name__}"
            raise MalformedError(msg)
        if not 0 <= value <= hi:
            msg = f"envelope: expected {name} in [0, {hi}], found {value}"
            raise RangeError(msg)
    if not isinstance(time, float):
        msg = f"envelope: expected float time, found {type(time).__name__}"
        raise MalformedError(msg)
    if not math.isfinite(time):
        msg = f"envelope: expected a finite time, found {time}"
        raise RangeError(msg)
    if not isinstance(body, bytes):
        msg = f"envelope: expected binary body, found {type(body).__name__}"
        raise MalformedError(msg)
    return origin, epoch, seq, time, body


def _envelope_end(data: bytes | memoryview, flags: int) -> int:
    """Where the envelope ends: before the signature and the tag the flags announce."""
    tail = (TAG_BYTES if flags & FLAG_AUTH else 0) + (SIG_BYTES if flags & FLAG_SIGNED else 0)
    end = len(data) - tail
    if end <= PREFIX_BYTES:
        what = " and ".join(
            w
            for w, f in (("a 64-byte signature", FLAG_SIGNED), ("a 32-byte tag", FLAG_AUTH))
            if flags & f
        )
        msg = (
            f"frame: expected an envelope{' and ' + what if what else ''} after the prefix, "
            f"found {len(data) - PREFIX_BYTES} bytes"
        )
        raise TruncatedError(msg)
    return end


def peek(data: bytes, limits: Limits = DEFAULT_LIMITS) -> FrameInfo:
    """Prefix and envelope of a frame without decoding its body or checking its tag."""
    mtype, flags, compression = _prefix(data, limits)
    auth = bool(flags & FLAG_AUTH)
    end = _envelope_end(data, flags)
    origin, epoch, seq, time, _ = _envelope(data, end, limits)
    cls = MESSAGE_TYPES[mtype]
    return FrameInfo(
        PROTOCOL_VERSION, mtype, cls.KIND, origin, epoch, seq, time, auth, compression, len(data)
    )


_RANGE_ERRORS = {
    "greater_than",
    "greater_than_equal",
    "less_than",
    "less_than_equal",
    "finite_number",
    "string_pattern_mismatch",
    "value_error",
    "literal_error",
    "enum",
    "too_short",
}


def _validation_error(cls: type[Message], exc: ValidationError) -> ProtocolError:
    err = exc.errors(include_url=False)[0]
    loc = ".".join(str(p) for p in err["loc"]) or "(body)"
    value = err.get("input")
    scalar = isinstance(value, (int, float, str, bytes, bool, type(None)))
    found = repr(value)[:80] if scalar else f"a {type(value).__name__}"
    text = f"{cls.KIND} message field {loc}: {err['msg']}, found {found}"
    if err["type"] == "too_long":
        return OversizedError(text)
    if err["type"] in _RANGE_ERRORS:
        return RangeError(text)
    return MalformedError(text)


def decode(
    data: bytes,
    *,
    key: bytes | None = None,
    limits: Limits = DEFAULT_LIMITS,
    replay: ReplayWindow | None = None,
    trust: Trust | None = None,
    before_body: Callable[[type[Message], str, int, int, float], None] | None = None,
) -> Message:
    """Validated message of hostile frame bytes, or a ProtocolError subclass saying why not.

    With a colony `key`, frames without a valid tag are rejected (AuthError); without one,
    authenticated frames are rejected too (the colony is closed to us). With a `trust` that
    checks identities, every message but a request must carry its origin's valid signature
    (IdentityError). With a `replay` window, a frame whose (origin, epoch, seq) was already
    accepted raises ReplayError.

    The cheap checks come before the body is decompressed and parsed (which costs up to ~0.5 s
    for the largest bodies): the tag, the envelope, `before_body(class, origin, epoch, seq,
    time)` (the caller's own checks; it raises to refuse), and the signature: with the key the
    `trust` knows for the origin; only a Heartbeat of an origin not pinned yet (trust on first
    use) offers it in its body, and then its body, at most `limits.max_heartbeat_bytes`, is
    decompressed and its `identity` alone read (the rest skipped undecoded) to check it.
    """
    mtype, flags, compression = _prefix(data, limits)
    cls = MESSAGE_TYPES[mtype]
    keyed = "identity" in cls.model_fields  # a Heartbeat: its body carries its key
    max_body = min(limits.max_body_bytes, limits.max_heartbeat_bytes) if keyed else None
    if max_body is not None and len(data) > max_body + FRAME_OVERHEAD:
        msg = (
            f"frame: expected a {cls.KIND} frame of at most {max_body + FRAME_OVERHEAD} bytes, "
            f"found {len(data)}"
        )
        raise OversizedError(msg)
    auth = bool(flags & FLAG_AUTH)
    view = memoryview(data)
    if key is not None:
        if not auth:
            msg = "frame: expected an authenticated frame (colony key configured), found no tag"
            raise AuthError(msg)
        if len(data) - TAG_BYTES <= PREFIX_BYTES:
            msg = (
                f"frame: expected an envelope and a {TAG_BYTES}-byte tag after the prefix, found "
                f"{len(data) - PREFIX_BYTES} bytes"
            )
            raise TruncatedError(msg)
        verify_tag(key, view[: len(data) - TAG_BYTES], view[len(data) - TAG_BYTES :])
    elif auth:
        msg = "frame: expected an unauthenticated frame (no colony key configured), found a tag"
        raise AuthError(msg)
    end = _envelope_end(data, flags)
    origin, epoch, seq, time, body = _envelope(data, end, limits)
    if before_body is not None:
        before_body(cls, origin, epoch, seq, time)
    # the signature before the body, with the key the receiver knows (for a Heartbeat, the
    # pinned or listed one): a stranger's frame costs no body parse
    early = trust is not None and (
        not keyed or not trust.checks or trust.mode == "list" or trust.pinned(origin) is not None
    )
    if trust is not None and early:
        _verify(data, cls, origin, None, trust)
    if max_body is not None:
        limits = replace(limits, max_body_bytes=max_body)
    if compression == COMPRESSION_ZSTD:
        body = fields.decompress(body, limits, "body")
    elif len(body) > limits.max_body_bytes:
        msg = f"body: expected at most {limits.max_body_bytes} bytes, found {len(body)}"
        raise OversizedError(msg)
    offered: bytes | None = None
    if trust is not None and not early:
        # a stranger's Heartbeat (trust on first use): the key it offers, read alone (the rest
        # skipped undecoded), checks its signature before the body is scanned and validated
        offered = fields.map_bin(body, "identity", f"{cls.KIND} body", limits)
        _verify(data, cls, origin, offered, trust)
    content = fields.as_map(fields.unpack(body, f"{cls.KIND} body", limits), f"{cls.KIND} body")
    known = {k: v for k, v in content.items() if k in cls.model_fields and k not in HEADER_FIELDS}
    if "delta" in cls.model_fields:
        raw = known.get("delta")
        if raw is None and cls.model_fields["delta"].is_required():
            msg = f"{cls.KIND} body: expected field 'delta' with a delta body, found none"
            raise MalformedError(msg)
        if raw is not None:
            if not isinstance(raw, bytes):
                msg = f"{cls.KIND} body: expected binary 'delta', found {type(raw).__name__}"
                raise MalformedError(msg)
            delta, summary = decode_delta_with_summary(raw, limits)
            known["delta"] = delta
            if summary is not None:
                if "free_summary" not in cls.model_fields:
                    msg = f"{cls.KIND} body: expected an exact delta, found a free-space summary"
                    raise MalformedError(msg)
                known["free_summary"] = summary
    if "records" in cls.model_fields and known.get("records") is not None:
        raw = known["records"]
        if not isinstance(raw, bytes):
            msg = f"{cls.KIND} body: expected binary 'records', found {type(raw).__name__}"
            raise MalformedError(msg)
        known["records"] = decode_history(raw, limits)
    try:
        message = cls.model_validate(
            {
                **known,
                "version": PROTOCOL_VERSION,
                "origin": origin,
                "epoch": epoch,
                "seq": seq,
                "time": time,
            }
        )
    except ValidationError as exc:
        raise _validation_error(cls, exc) from None
    identity = getattr(message, "identity", None)
    if trust is not None and trust.checks and keyed and identity != offered:
        if not early:  # (a key the walk above did not see as one: no bin)
            msg = f"identity of {origin!r}: expected the key its signature was checked with"
            raise IdentityError(msg)
        trust.key_for(origin, identity)  # the key it offers is the pinned one, if it offers one
    if replay is not None:
        replay.check(origin, epoch, seq)
    return message


def verify_identity(data: bytes, message: Message, trust: Trust) -> None:
    """Raise IdentityError unless frame `data` of the decoded `message` carries its origin's
    valid signature (requests and a `trust` that checks nothing pass)."""
    _verify(data, type(message), message.origin, getattr(message, "identity", None), trust)


def _verify(
    data: bytes, cls: type[Message], origin: str, identity: bytes | None, trust: Trust
) -> None:
    """`verify_identity` of a frame of `cls` from `origin` whose body offers key `identity`."""
    if not trust.checks or cls.REQUEST:
        return
    _, flags, _ = _prefix(data, DEFAULT_LIMITS)
    if not flags & FLAG_SIGNED:
        msg = f"frame: expected {origin!r}'s signature on a {cls.KIND} frame, found none"
        raise IdentityError(msg)
    end = _envelope_end(data, flags)
    public = trust.key_for(origin, identity)
    view = memoryview(data)
    try:
        verify_signature(public, view[:end], view[end : end + SIG_BYTES], origin)
    except IdentityError as exc:
        if identity is None and "identity" in cls.model_fields:  # a Heartbeat, the pinned key
            msg = (
                f"{exc} (a Heartbeat checked with its pinned or listed key before its body is "
                "read: signed by another key holder impersonating it, or by a reinstalled agent "
                "whose pin must be removed)"
            )
            raise IdentityError(msg) from None
        raise


# --------------------------------------------------------------------------- delta helpers


def delta_messages(
    *,
    origin: str,
    epoch: int,
    seq: int,
    time: float,
    frame_id: str,
    delta: Delta,
    max_bytes: int = 1 << 20,
    budget: int | None = None,
    prev_logodds: np.ndarray | None = None,
) -> list[VoxelDelta]:
    """VoxelDelta messages (seq, seq+1, …) carrying `delta`, each frame at most `max_bytes`.

    With a `budget` (compressed bytes for the whole delta), free space is summarised first
    (`fit_delta`); the result is then split (`split_delta`) into independently decodable parts,
    surfaces first.
    """
    summary = None
    if budget is not None:
        delta, summary = fit_delta(delta, budget, prev_logodds=prev_logodds)
        prev_logodds = None
    limit = max_bytes - FRAME_OVERHEAD - len(frame_id) - len(origin)
    parts: list[tuple[Delta, FreeSummary | None]] = [
        (part, None) for part in split_delta(delta, limit, prev_logodds=prev_logodds)
    ]
    if summary is not None and len(summary):
        last = parts[-1][0]
        if encoded_size(last, summary=summary) <= limit:
            parts[-1] = (last, summary)
        else:  # the summary travels in a part of its own, with no exact voxels
            empty = last.select(np.zeros(len(last), dtype=bool))
            parts.append((empty, summary))
    return [
        VoxelDelta(
            origin=origin,
            epoch=epoch,
            seq=seq + i,
            time=time,
            frame_id=frame_id,
            part=i,
            parts=len(parts),
            delta=part,
            free_summary=part_summary,
        )
        for i, (part, part_summary) in enumerate(parts)
    ]
