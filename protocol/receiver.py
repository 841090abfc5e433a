"""Receiver: one daemon's decoding front door (key, limits, replay window, key check, counts)."""

from __future__ import annotations

import threading
from collections import Counter

from protocol.auth import ReplayWindow
from protocol.codec import decode
from protocol.errors import ProtocolError
from protocol.keyexpr import check_origin
from protocol.limits import DEFAULT_LIMITS, Limits
from protocol.messages import Message


class Receiver:
    """Decodes every frame a daemon receives and counts what it accepted and rejected, by reason.

    With a colony `key`, frames must be authenticated and each (origin, epoch, seq) is accepted
    once (replay window). Given the Zenoh key a frame arrived on, the key's origin must be the
    frame's origin.
    """

    def __init__(
        self,
        *,
        key: bytes | None = None,
        limits: Limits = DEFAULT_LIMITS,
        replay_window: int = 4096,
    ) -> None:
        self.key = key
        self.limits = limits
        self.replay = ReplayWindow(replay_window) if key is not None else None
        self.accepted: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()
        self._lock = threading.Lock()

    def decode(self, data: bytes, key_expr: str | None = None) -> Message:
        """The validated message of `data`, or a ProtocolError (counted under its `reason`)."""
        try:
            msg = decode(data, key=self.key, limits=self.limits, replay=self.replay)
            if key_expr is not None:
                check_origin(key_expr, msg.origin)
        except ProtocolError as exc:
            with self._lock:
                self.rejected[exc.reason] += 1
            raise
        with self._lock:
            self.accepted[msg.KIND] += 1
        return msg
