"""Message authentication with a colony key (HMAC-SHA256) and per-origin replay detection."""

from __future__ import annotations

import hashlib
import hmac
import threading

from protocol.errors import AuthError, ReplayError

#: Length of the authentication tag appended to an authenticated frame.
TAG_BYTES = 32
#: Shortest colony key accepted.
MIN_KEY_BYTES = 16


def check_key(key: bytes) -> bytes:
    """Return `key` if it can serve as a colony key, else raise AuthError."""
    if not isinstance(key, (bytes, bytearray)):
        msg = f"colony key must be bytes, found {type(key).__name__}"
        raise AuthError(msg)
    if len(key) < MIN_KEY_BYTES:
        msg = f"colony key must be at least {MIN_KEY_BYTES} bytes, found {len(key)}"
        raise AuthError(msg)
    return bytes(key)


def compute_tag(key: bytes, data: bytes | memoryview) -> bytes:
    """HMAC-SHA256 of `data` under `key`: the 32-byte tag of a frame."""
    return hmac.new(check_key(key), data, hashlib.sha256).digest()


def verify_tag(key: bytes, data: bytes | memoryview, tag: bytes | memoryview) -> None:
    """Raise AuthError unless `tag` is the tag of `data` under `key` (constant-time compare)."""
    expected = compute_tag(key, data)
    if len(tag) != TAG_BYTES or not hmac.compare_digest(expected, bytes(tag)):
        msg = (
            "authentication tag does not match: expected HMAC-SHA256 of the frame under the "
            f"colony key, found {bytes(tag[:8]).hex()}…"
        )
        raise AuthError(msg)


class ReplayWindow:
    """Per-origin (epoch, seq) window: accepts each (origin, epoch, seq) at most once.

    Within an epoch a message is accepted if its seq is new and not older than the newest seq
    minus `window`. A higher epoch (the origin restarted without its state) resets the window;
    a lower epoch is a replay. The number of origins tracked is bounded by `max_origins`
    (least recently updated origins are forgotten first).
    """

    def __init__(self, window: int = 4096, max_origins: int = 4096) -> None:
        if window < 1:
            msg = f"replay window must be >= 1, found {window}"
            raise ValueError(msg)
        self.window = window
        self.max_origins = max_origins
        # origin -> (epoch, highest seq, bitmask of seen seqs below highest: bit i = highest - i)
        self._state: dict[str, tuple[int, int, int]] = {}
        self._lock = threading.Lock()

    def check(self, origin: str, epoch: int, seq: int, *, late_ok: bool = False) -> None:
        """Raise ReplayError if (origin, epoch, seq) was seen or is too old; else record it.
        `late_ok`: a frame of the current epoch older than the window is let through without
        being recorded (a reply to a fresh random request id, which proves it fresh, that fell
        behind the window while its query ran).

        Thread-safe: daemons decode on several worker threads.
        """
        with self._lock:
            if late_ok and self._late(origin, epoch, seq):
                return
            state = self._next_state(origin, epoch, seq)
            self._state.pop(origin, None)
            if len(self._state) >= self.max_origins:
                self._state.pop(next(iter(self._state)))
            self._state[origin] = state

    def peek(self, origin: str, epoch: int, seq: int, *, late_ok: bool = False) -> None:
        """Raise ReplayError if `check` (with the same `late_ok`) would; never records anything
        (the window stays put)."""
        with self._lock:
            if not (late_ok and self._late(origin, epoch, seq)):
                self._next_state(origin, epoch, seq)

    def _late(self, origin: str, epoch: int, seq: int) -> bool:
        """True if (epoch, seq) is of `origin`'s current epoch and older than the window."""
        state = self._state.get(origin)
        return state is not None and epoch == state[0] and state[1] - seq >= self.window

    def _next_state(self, origin: str, epoch: int, seq: int) -> tuple[int, int, int]:
        """The origin's state after accepting (epoch, seq), or ReplayError."""
        state = self._state.get(origin)
        if state is None or epoch > state[0]:  # a higher epoch: the origin started afresh
            return (epoch, seq, 1)
        cur_epoch, top, mask = state
        if epoch < cur_epoch:
            msg = f"replay from {origin!r}: expected epoch >= {cur_epoch}, found epoch {epoch}"
            raise ReplayError(msg)
        if seq > top:
            shift = seq - top
            mask = ((mask << shift) | 1) & ((1 << self.window) - 1) if shift < self.window else 1
            return (epoch, seq, mask)
        age = top - seq
        if age >= self.window:
            msg = (
                f"replay from {origin!r}: expected seq > {top - self.window} in epoch {epoch}, "
                f"found seq {seq} (older than the replay window)"
            )
            raise ReplayError(msg)
        if mask >> age & 1:
            msg = f"replay from {origin!r}: seq {seq} of epoch {epoch} was already accepted"
            raise ReplayError(msg)
        return (cur_epoch, top, mask | (1 << age))

    def forget(self, origin: str) -> None:
        """Stop tracking `origin`."""
        with self._lock:
            self._state.pop(origin, None)
