"""Frames: this daemon's side of the colony protocol (`protocol/`): sender, receiver, key, parts.

Every byte the daemon puts on the network is a `protocol` frame (docs/PROTOCOL.md) and every
byte it receives goes through one `protocol.Receiver` (validation, colony key, replays, origin of
the key). This module adds what a daemon needs around them: the colony key derived from the
configured secret, one frame counter for all frames of this origin (continued across restarts),
and the reassembly of deltas sent in several parts.
"""

from __future__ import annotations

import hashlib
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, TypedDict

import numpy as np

from colonyd.errors import WireError
from colonyd.metrics import Metrics
from protocol import Limits, Message, Receiver, encode
from protocol.identity import Signer, Trust
from voxel.delta import Delta

#: Suffix of an agent's own map frame: its layer lives in `<agent>.odom`, where it started.
FRAME_SUFFIX = ".odom"
#: Frame numbers reserved on disk at a time (see `Sender`).
SEQ_BLOCK = 1 << 20


class Header(TypedDict):
    """The envelope fields every message takes from its sender."""

    origin: str
    epoch: int
    seq: int
    time: float


def frame_of(agent: str) -> str:
    """The frame an agent's layer and objects are expressed in: `<agent>.odom` (a protocol
    name, so at most 64 characters: a longer agent id is cut before the suffix)."""
    return agent[: 64 - len(FRAME_SUFFIX)] + FRAME_SUFFIX


def colony_key(secret: str | None) -> bytes | None:
    """The protocol colony key of a configured secret: sha256(UTF-8 secret), 32 bytes, or None.

    `protocol.auth` wants at least 16 key bytes; hashing lets the configuration hold any string
    (a passphrase) while every daemon of the colony derives the same key.
    """
    if not secret:
        return None
    return hashlib.sha256(secret.encode()).digest()


def get_limits(max_message_mb: float) -> Limits:
    """Decoder limits of a daemon: frames and decoded bodies up to `max_message_mb` MiB."""
    size = int(max_message_mb * (1 << 20))
    return Limits(max_message_bytes=size, max_body_bytes=size)


def get_receiver(
    secret: str | None, max_message_mb: float, own: str, trust: Trust | None = None
) -> Receiver:
    """The daemon's one decoding front door (key, limits, replay window, key-vs-origin check,
    frames claiming our own origin `own` refused, peers' signatures checked by `trust`)."""
    return Receiver(key=colony_key(secret), limits=get_limits(max_message_mb), own=own, trust=trust)


def expect(msg: Message, cls: type[Message], what: str) -> Any:
    """`msg` if it is a `cls`, else WireError("unexpected-type")."""
    if not isinstance(msg, cls):
        text = f"expected a {cls.KIND} message {what}, found {msg.KIND}"
        raise WireError("unexpected-type", text)
    return msg


def accept(receiver: Receiver, metrics: Metrics, msg: Message, raw: bytes) -> None:
    """Take a frame that passed every check: its replay window moves, its bytes count."""
    receiver.accept(msg)
    metrics.add("bytes_received", len(raw))


class Sender:
    """Encodes this origin's frames: one (epoch, seq) counter shared by every frame it sends.

    The protocol wants seq to grow within an epoch even across restarts (receivers with a colony
    key reject repeated seqs as replays), while the daemon keeps its epoch when it restarts with
    its state. So frame numbers are reserved on disk `SEQ_BLOCK` at a time through `reserve(up_to)`
    (durable before any of them is used); a restart continues from the last reservation.
    """

    def __init__(
        self,
        origin: str,
        epoch: int,
        *,
        key: bytes | None = None,
        signer: Signer | None = None,
        first_seq: int = 0,
        reserve: Callable[[int], None] | None = None,
    ) -> None:
        self.origin = origin
        self.epoch = epoch
        self._key = key
        self._signer = signer
        #: The public key this origin signs with (None: frames are not signed).
        self.identity = signer.public if signer is not None else None
        self._next = first_seq
        self._reserved = first_seq
        self._reserve = reserve
        self._lock = threading.Lock()

    def take(self, n: int = 1) -> int:
        """The first of `n` consecutive frame numbers, reserved for the caller."""
        with self._lock:
            first = self._next
            self._next += n
            if self._reserve is None:
                self._reserved = self._next
            elif self._next > self._reserved:
                try:  # durable first: a failed reservation hands out no number
                    self._reserve(self._next + SEQ_BLOCK)
                except Exception:
                    self._next = first
                    raise
                self._reserved = self._next + SEQ_BLOCK
            return first

    def header(self) -> Header:
        """Envelope fields of one new frame: origin, epoch, a fresh seq, the time now."""
        return {"origin": self.origin, "epoch": self.epoch, "seq": self.take(), "time": time.time()}

    def encode(self, msg: Message) -> bytes:
        """Frame bytes of `msg`: signed with our identity, authenticated with the colony key."""
        return encode(msg, key=self._key, signer=self._signer)

    def encode_all(
        self, msgs: Sequence[Message], before: Callable[[int], None] | None = None
    ) -> list[bytes]:
        """Frames of `msgs` as this origin's, with consecutive fresh seqs (parts of one reply);
        `before(i)` is called before encoding the i-th (it may raise to stop)."""
        first = self.take(len(msgs))
        head = {"origin": self.origin, "epoch": self.epoch}
        out: list[bytes] = []
        for i, m in enumerate(msgs):
            if before is not None:
                before(i)
            out.append(self.encode(m.model_copy(update={**head, "seq": first + i})))
        return out


def concat(parts: list[Delta]) -> Delta:
    """One delta of the voxels of several parts of one delta (same versions, disjoint voxels)."""
    if len(parts) == 1:
        return parts[0]
    first = parts[0]
    names = set(first.channels)
    for p in parts[1:]:
        if (p.from_version, p.to_version) != (first.from_version, first.to_version):
            raise WireError("bad-parts", "expected parts of one delta to share their versions")
        if abs(p.resolution - first.resolution) > 1e-12 or set(p.channels) != names:
            msg = "expected parts of one delta to share resolution and channels"
            raise WireError("bad-parts", msg)
    try:
        return Delta(
            resolution=first.resolution,
            from_version=first.from_version,
            to_version=first.to_version,
            keys=np.concatenate([p.keys for p in parts]),
            logodds=np.concatenate([p.logodds for p in parts]),
            last_time=np.concatenate([p.last_time for p in parts]),
            channels={n: np.concatenate([p.channels[n] for p in parts]) for n in sorted(names)},
            time=first.time,
            surface_mask=None
            if all(p.surface_mask is None for p in parts)
            else np.concatenate(
                [
                    np.ones(len(p), dtype=bool) if p.surface_mask is None else p.surface_mask
                    for p in parts
                ]
            ),
        )
    except ValueError as exc:
        raise WireError("bad-parts", f"parts of one delta do not fit together: {exc}") from None


@dataclass
class _Partial:
    parts: int
    got: dict[int, Delta] = field(default_factory=dict)
    voxels: int = 0  # of the parts in `got`, kept as they come (a sum over 65535 parts each
    # time one arrives would be quadratic)


class Assembler:
    """Collects the parts of deltas sent in several messages; bounded in open deltas and in the
    voxels their parts hold together (the delta least recently added to dropped first).

    `max_voxels` is the most a whole delta may hold (a peer layer's budget: one larger could
    never be admitted), so the parts of one delta beyond it are refused (`check`) rather than
    kept: a few bytes of zstd decode to millions of voxels, and 65535 parts of each must not
    pile up unapplied.
    """

    def __init__(self, max_open: int = 128, max_voxels: int = 1 << 62) -> None:
        self._open: OrderedDict[tuple[object, ...], _Partial] = OrderedDict()
        self._max = max_open
        self._max_voxels = max_voxels
        self._voxels = 0
        self._lock = threading.Lock()

    @property
    def voxels(self) -> int:
        """Voxels the parts of open deltas hold."""
        with self._lock:
            return self._voxels

    def check(self, key: tuple[object, ...], part: int, parts: int, delta: Delta) -> None:
        """Raise WireError unless part `part` of `parts` of delta `key` may be added: the number
        of parts of the delta's other parts, and the voxels of its parts together within
        `max_voxels`. Changes nothing."""
        if parts == 1:
            return
        with self._lock:
            entry = self._open.get(key)
            if entry is None:
                held = 0
            elif entry.parts != parts:
                msg = f"expected {entry.parts} parts, found a part of {parts}"
                raise WireError("bad-parts", msg)
            else:
                held = entry.voxels - len(entry.got.get(part, ()))
        if held + len(delta) > self._max_voxels:
            msg = (
                f"expected a delta of at most {self._max_voxels} voxels in its parts, found "
                f"{held} held + {len(delta)} in part {part} of {parts}"
            )
            raise WireError("over-budget", msg)

    def add(self, key: tuple[object, ...], part: int, parts: int, delta: Delta) -> Delta | None:
        """The whole delta once every part of `key` arrived, else None (`check` first)."""
        self.check(key, part, parts, delta)
        if parts == 1:
            return delta
        with self._lock:
            entry = self._open.get(key)
            if entry is None:
                entry = self._open[key] = _Partial(parts)
            old = entry.got.get(part)
            grown = len(delta) - (len(old) if old is not None else 0)
            entry.voxels += grown
            self._voxels += grown
            entry.got[part] = delta
            self._open.move_to_end(key)  # the least recently added to goes first
            while len(self._open) > 1 and (
                len(self._open) > self._max or self._voxels > self._max_voxels
            ):
                self._voxels -= self._open.popitem(last=False)[1].voxels
            if len(entry.got) < parts:
                return None
            del self._open[key]
            self._voxels -= entry.voxels
        return concat([entry.got[i] for i in range(parts)])
