"""Receiver: one daemon's decoding front door (key, limits, replay window, key check, counts)."""

from __future__ import annotations

import threading
from collections import Counter

from protocol.auth import ReplayWindow
from protocol.codec import decode
from protocol.errors import OwnOriginError, ProtocolError
from protocol.identity import Trust
from protocol.keyexpr import check_origin
from protocol.limits import DEFAULT_LIMITS, Limits
from protocol.messages import Message


class Receiver:
    """Decodes every frame a daemon receives and counts what it accepted and rejected, by reason.

    With a colony `key`, frames must be authenticated and each (origin, epoch, seq) is accepted
    once (replay window; also without a key, requests apart, when `trust` checks identities).
    Given the Zenoh key a frame arrived on, the key's origin must be the frame's origin. Frames
    claiming the receiver's `own` origin are forgeries or echoes of its own frames and are
    rejected. With a `trust` that checks identities, every frame but a request must carry its
    origin's Ed25519 signature (an agent's first Heartbeat introduces its key when the trust is
    on first use; `accept` pins it).

    Receiving is two steps so that a rejected frame has no side effect: `decode` validates and
    records nothing but a rejection; the caller then checks what only it can check (message type,
    layer, budgets) and calls `accept`, which moves the replay window and counts the frame.
    """

    def __init__(
        self,
        *,
        key: bytes | None = None,
        limits: Limits = DEFAULT_LIMITS,
        replay_window: int = 4096,
        own: str | None = None,
        trust: Trust | None = None,
    ) -> None:
        self.key = key
        self.trust = trust
        self.limits = limits
        self.own = own
        # signatures prove who sent a frame, not when: with identities checked, a window keeps
        # strangers from replaying a pinned agent's old frames even without a colony key
        checks = key is not None or (trust is not None and trust.checks)
        self.replay = ReplayWindow(replay_window) if checks else None
        # requests (unsigned: anyone may send them under any origin) in a window of their own, so
        # that made-up requesters cannot push a signed agent's state out of `replay`; and only
        # with a key: without one anybody can make a fresh request, a replayed one is no worse
        self.request_replay = ReplayWindow(replay_window) if key is not None else None
        self.accepted: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()
        self._lock = threading.Lock()

    def decode(self, data: bytes, key_expr: str | None = None, *, answer: bool = False) -> Message:
        """The validated message of `data`, or a ProtocolError (counted under its `reason`).

        A replay is rejected here, but nothing is recorded for a frame that passes: the replay
        window moves only in `accept`. `answer`: a reply to one of our queries, which the caller
        matches to its fresh random request id, passes though older than the window (its holder
        encoded it, then sent more than the window's frames before it arrived), as in `accept`.
        The key's origin, our own origin, the replay window and (but for a Heartbeat, whose body
        carries its key) the signature are checked before the body is parsed: a stranger's frame
        costs no body parse.
        """

        def before_body(cls: type[Message], origin: str, epoch: int, seq: int, time: float) -> None:
            if key_expr is not None:
                check_origin(key_expr, origin)
            if origin == self.own:
                text = f"frame: expected another agent's origin, found our own {origin!r}"
                raise OwnOriginError(text, kind=cls.KIND, epoch=epoch, time=time)
            window = self.request_replay if cls.REQUEST else self.replay
            if window is not None:
                window.peek(origin, epoch, seq, late_ok=answer)

        try:
            msg = decode(
                data, key=self.key, limits=self.limits, trust=self.trust, before_body=before_body
            )
        except ProtocolError as exc:
            self.count_rejected(exc.reason)
            raise
        return msg

    def accept(self, msg: Message, *, answer: bool = False) -> None:
        """Take a decoded message: record its (origin, epoch, seq) and count it as accepted.
        `answer`: a reply that matched our fresh random request id, taken once every reply of
        its query passed; one that fell behind the replay window meanwhile (its holder sent
        more than the window's frames while the query ran) is taken without being recorded.

        Raises ReplayError (counted) if the same frame was accepted meanwhile on another thread.
        """
        window = self._window(msg)
        if window is not None:
            try:
                window.check(msg.origin, msg.epoch, msg.seq, late_ok=answer)
            except ProtocolError as exc:
                self.count_rejected(exc.reason)
                raise
        identity = getattr(msg, "identity", None)
        if self.trust is not None and self.trust.checks and identity is not None:
            self.trust.pin(msg.origin, identity)  # first use: verified with this very key
        with self._lock:
            self.accepted[msg.KIND] += 1

    def _window(self, msg: Message) -> ReplayWindow | None:
        """The replay window of `msg`: requests have their own."""
        return self.request_replay if msg.REQUEST else self.replay

    def receive(self, data: bytes, key_expr: str | None = None) -> Message:
        """`decode` then `accept`: for a caller with nothing of its own to check."""
        msg = self.decode(data, key_expr)
        self.accept(msg)
        return msg

    def count_rejected(self, reason: str) -> None:
        """Count a rejected frame under `reason`."""
        with self._lock:
            self.rejected[reason] += 1
