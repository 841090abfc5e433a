"""Agent identities: Ed25519 keys that sign an agent's frames, and the pins that say whose is
whose."""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping
from typing import Literal

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from protocol.errors import IdentityError, NotIntroducedError, UnknownIdentityError

#: Bytes of an Ed25519 signature (it follows a signed frame's envelope) and of a public key.
SIG_BYTES = 64
PUBLIC_BYTES = 32
#: What a receiver does with identities: "off" checks no signature; "tofu" pins the key an
#: agent first introduces itself with (its Heartbeat's `identity`) and refuses any other after;
#: "list" accepts only the agents and keys it was given.
TrustMode = Literal["off", "tofu", "list"]
TRUST_MODES: tuple[TrustMode, ...] = ("off", "tofu", "list")
#: Most agents a receiver pins on first use: past them a new agent's key is refused (a stranger
#: inventing agent ids must not grow the pins, which a daemon keeps on disk, without end; a pin is
#: never dropped to make room, or its agent could be impersonated after).
MAX_PINS = 4096


class Signer:
    """An agent's private identity key: signs its frames; `public` is what peers pin."""

    def __init__(self, private: Ed25519PrivateKey) -> None:
        self._key = private
        self.public = private.public_key().public_bytes_raw()

    @classmethod
    def generate(cls) -> Signer:
        return cls(Ed25519PrivateKey.generate())

    @classmethod
    def from_bytes(cls, raw: bytes) -> Signer:
        """A signer of a 32-byte raw Ed25519 private key."""
        if len(raw) != 32:
            msg = f"identity key: expected 32 raw Ed25519 private key bytes, found {len(raw)}"
            raise IdentityError(msg)
        return cls(Ed25519PrivateKey.from_private_bytes(raw))

    def private_bytes(self) -> bytes:
        return self._key.private_bytes_raw()

    def sign(self, data: bytes) -> bytes:
        return self._key.sign(data)


def verify_signature(
    public: bytes, data: bytes | memoryview, signature: bytes | memoryview, origin: str
) -> None:
    """Raise IdentityError unless `signature` is `public`'s Ed25519 signature of `data`."""
    try:
        Ed25519PublicKey.from_public_bytes(bytes(public)).verify(bytes(signature), bytes(data))
    except (InvalidSignature, ValueError):
        msg = (
            f"signature: expected {origin!r}'s Ed25519 signature by key "
            f"{bytes(public).hex()[:16]}…, found one that does not verify"
        )
        raise IdentityError(msg) from None


def parse_public(text: str, what: str) -> bytes:
    """A 32-byte public key written as 64 hex digits."""
    try:
        raw = bytes.fromhex(text)
    except ValueError:
        raw = b""
    if len(raw) != PUBLIC_BYTES:
        msg = f"{what}: expected an Ed25519 public key as 64 hex digits, found {text!r}"
        raise IdentityError(msg)
    return raw


class Trust:
    """Which public key each agent signs with, as this receiver knows it.

    `pins` are known keys (from a trust list or earlier first uses). In "tofu" mode an agent not
    pinned yet may introduce its key in a Heartbeat (self-signed); `pin` then records it (called
    only once the frame is accepted), and `on_pin(agent, key)` may persist it. A different key
    for a pinned agent is refused: that is how impersonation by another key holder shows. At most
    `max_pins` agents are pinned on first use (a new one past them is refused).
    """

    def __init__(
        self,
        mode: TrustMode = "tofu",
        pins: Mapping[str, bytes] | None = None,
        on_pin: Callable[[str, bytes], None] | None = None,
        max_pins: int = MAX_PINS,
    ) -> None:
        if mode not in TRUST_MODES:
            msg = f"trust mode must be one of {TRUST_MODES}, found {mode!r}"
            raise IdentityError(msg)
        self.mode: TrustMode = mode
        self.max_pins = max_pins
        self._pins = dict(pins or {})
        self._on_pin = on_pin
        self._lock = threading.Lock()

    @property
    def checks(self) -> bool:
        return self.mode != "off"

    def pins(self) -> dict[str, bytes]:
        with self._lock:
            return dict(self._pins)

    def pinned(self, origin: str) -> bytes | None:
        """`origin`'s pinned key, if any."""
        with self._lock:
            return self._pins.get(origin)

    def key_for(self, origin: str, offered: bytes | None) -> bytes:
        """The key `origin`'s frame must verify with (`offered`: the key its heartbeat carries)."""
        with self._lock:
            pinned = self._pins.get(origin)
        if pinned is not None:
            if offered is not None and offered != pinned:
                msg = (
                    f"identity of {origin!r}: expected its pinned key {pinned.hex()[:16]}…, "
                    f"found {offered.hex()[:16]}… (another key holder impersonating it, or "
                    "a reinstalled agent whose pin must be removed)"
                )
                raise IdentityError(msg)
            return pinned
        if self.mode == "tofu" and offered is not None:
            with self._lock:
                full = len(self._pins) >= self.max_pins
            if full:
                msg = (
                    f"identity of {origin!r}: expected one of the {self.max_pins} agents pinned "
                    "(the most pinned on first use), found a new agent"
                )
                raise UnknownIdentityError(msg)
            return offered
        if self.mode == "list":
            msg = f"identity of {origin!r}: expected a pinned key (trust list), found no key for it"
            raise UnknownIdentityError(msg)
        msg = f"identity of {origin!r}: expected its heartbeat first, found no key for it"
        raise NotIntroducedError(msg)

    def pin(self, origin: str, key: bytes) -> None:
        """Record `origin`'s key on first use (tofu); a known pin stays as it is."""
        with self._lock:
            if origin in self._pins or self.mode != "tofu" or len(self._pins) >= self.max_pins:
                return
            self._pins[origin] = key
        if self._on_pin is not None:
            self._on_pin(origin, key)
