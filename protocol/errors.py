"""Errors raised by the protocol package; every one says what was expected and what was found."""

from __future__ import annotations


class ProtocolError(Exception):
    """Base class of every error raised while encoding, decoding or authenticating a message."""

    #: Short machine-readable reason, used by daemons to count rejected messages per cause.
    reason = "protocol"


class TruncatedError(ProtocolError):
    """The input ends before a field it announces."""

    reason = "truncated"


class MalformedError(ProtocolError):
    """The input is not laid out as the protocol requires (bad magic, types or structure)."""

    reason = "malformed"


class OversizedError(ProtocolError):
    """The input, or something it announces, is larger than the configured limits allow."""

    reason = "oversized"


class VersionError(ProtocolError):
    """The input is of a protocol or codec version this implementation does not speak."""

    reason = "version"


class UnknownTypeError(ProtocolError):
    """The input carries a message type, channel or field kind this implementation does not know."""

    reason = "unknown_type"


class RangeError(ProtocolError):
    """A value is outside the range the protocol allows (keys, times, counts, names)."""

    reason = "range"


class DecompressionBombError(OversizedError):
    """A compressed body would expand beyond the configured limit."""

    reason = "decompression_bomb"


class AuthError(ProtocolError):
    """A message fails authentication: missing, wrong or unexpected tag, or a replay."""

    reason = "auth"


class ReplayError(AuthError):
    """A message repeats or predates an (epoch, seq) already accepted from its origin."""

    reason = "replay"


class OwnOriginError(AuthError):
    """A received frame claims the receiver's own origin: a replay of one of its own frames, a
    forgery, or another process running under the same origin (then its epoch differs and its
    time is recent). The frame's `kind`, `epoch` and `time` say which."""

    reason = "own_origin"

    def __init__(self, message: str, *, kind: str = "", epoch: int = 0, time: float = 0.0) -> None:
        super().__init__(message)
        self.kind = kind
        self.epoch = epoch
        self.time = time


class IdentityError(AuthError):
    """A frame's signature does not verify with its origin's key, a frame that must be signed is
    not, or an agent presents another key than the one pinned for it."""

    reason = "identity"


class UnknownIdentityError(IdentityError):
    """No key is known for a signed frame's origin yet (or it is not on the trust list)."""

    reason = "unknown_identity"


class NotIntroducedError(UnknownIdentityError):
    """Trust on first use, and the origin's first Heartbeat (which introduces its key) has not
    arrived yet: a frame that overtook it, as at every join; repaired later like any loss."""


class KeyExprError(ProtocolError, ValueError):
    """A key expression or one of its names is not valid."""

    reason = "keyexpr"
