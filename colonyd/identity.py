"""Identity files: this agent's Ed25519 signing key and the keys pinned for its peers."""

from __future__ import annotations

import json
import logging
import threading
from pathlib import Path

from colonyd.errors import ConfigError, PersistenceError
from colonyd.persistence import atomic_write
from protocol.errors import IdentityError
from protocol.identity import Signer, Trust, TrustMode, parse_public

log = logging.getLogger(__name__)

#: File names in the state directory.
IDENTITY = "identity.key"
PINS = "known_agents.json"


def load_signer(path: Path) -> Signer:
    """The private key in `path` (32 raw bytes, mode 0600), created on first use."""
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        signer = Signer.generate()
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write(path, signer.private_bytes(), mode=0o600)
        except OSError as exc:
            msg = f"cannot create the identity key {path}: {exc.strerror}"
            raise PersistenceError(msg) from None
        log.info("created identity %s (public key %s)", path, signer.public.hex())
        return signer
    except OSError as exc:
        msg = f"cannot read the identity key {path}: {exc.strerror}"
        raise PersistenceError(msg) from None
    try:
        return Signer.from_bytes(raw)
    except IdentityError as exc:
        msg = f"identity key {path}: {exc}"
        raise PersistenceError(msg) from None


class Pins:
    """Peers' public keys pinned on first use, kept in `known_agents.json` (agent -> hex)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._lock = threading.Lock()

    def load(self) -> dict[str, bytes]:
        if not self.path.exists():
            return {}
        try:
            data = json.loads(self.path.read_text())
            return {
                str(a): parse_public(str(k), f"{self.path} entry {a!r}") for a, k in data.items()
            }
        except (OSError, ValueError, AttributeError, IdentityError) as exc:
            msg = f"{self.path}: expected a JSON object of agent -> hex public key, found: {exc}"
            raise PersistenceError(msg) from None

    def add(self, agent: str, key: bytes) -> None:
        """Pin `agent`'s key durably (called once per new agent)."""
        with self._lock:
            pins = {a: k.hex() for a, k in self.load().items()}
            pins[agent] = key.hex()
            try:
                atomic_write(self.path, json.dumps(pins, indent=1, sort_keys=True).encode())
            except OSError as exc:
                log.error("cannot pin %s's key in %s: %s", agent, self.path, exc.strerror)
                return
        log.warning(
            "pinned the identity of %s on first use: %s (a different key for it is "
            "refused from now on)",
            agent,
            key.hex(),
        )


def get_trust(mode: TrustMode, trusted_keys: dict[str, str], state_dir: Path) -> Trust:
    """The receiver's trust: keys from the configuration, then pins of earlier first uses."""
    try:
        listed = {a: parse_public(k, f"trusted_keys[{a!r}]") for a, k in trusted_keys.items()}
    except IdentityError as exc:
        raise ConfigError(str(exc)) from None
    if mode != "tofu":
        return Trust(mode, listed)
    pins = Pins(state_dir / PINS)
    return Trust(mode, {**pins.load(), **listed}, on_pin=pins.add)


def identity_path(identity_file: Path | None, state_dir: Path) -> Path:
    """Where this agent's private key lives: `identity_file`, else the state directory's."""
    return identity_file if identity_file is not None else state_dir / IDENTITY
