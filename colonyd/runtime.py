"""Zenoh runtime: builds the session config from ours and opens the one session of a process."""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import zenoh

from colonyd.config import Config
from colonyd.errors import RuntimeSetupError, StatusError

log = logging.getLogger(__name__)

MULTICAST_ADDRESS = "224.0.0.224"


def zenoh_config(
    *,
    mode: str = "peer",
    listen: list[str] | None = None,
    connect: list[str] | None = None,
    multicast: bool = False,
    multicast_port: int = 7446,
    multicast_interface: str = "auto",
    gossip: bool = True,
    shared_memory: bool = False,
    lease_ms: int | None = None,
    extra_file: Path | None = None,
) -> zenoh.Config:
    """A Zenoh config; multicast scouting stays off unless asked for explicitly."""
    if extra_file is not None:
        try:
            conf = zenoh.Config.from_file(str(extra_file))
        except zenoh.ZError as exc:
            msg = f"zenoh config {extra_file} is invalid: {exc}"
            raise RuntimeSetupError(msg) from None
    else:
        conf = zenoh.Config()
    entries: dict[str, object] = {
        "mode": mode,
        "scouting/multicast/enabled": multicast,
        "scouting/gossip/enabled": gossip,
        "transport/shared_memory/enabled": shared_memory,
    }
    if multicast:
        entries["scouting/multicast/address"] = f"{MULTICAST_ADDRESS}:{multicast_port}"
        entries["scouting/multicast/interface"] = multicast_interface
    if listen:
        entries["listen/endpoints"] = list(listen)
    elif mode == "client":
        entries["listen/endpoints"] = []
    if connect:
        entries["connect/endpoints"] = list(connect)
    if lease_ms is not None:
        entries["transport/link/tx/lease"] = int(lease_ms)
        entries["transport/link/tx/keep_alive"] = 4
    for key, value in entries.items():
        try:
            conf.insert_json5(key, json.dumps(value))
        except zenoh.ZError as exc:
            msg = f"zenoh rejected {key}={value!r}: {exc}"
            raise RuntimeSetupError(msg) from None
    return conf


def get_zenoh_config(config: Config) -> zenoh.Config:
    """The Zenoh config of a daemon config."""
    return zenoh_config(
        mode=config.mode,
        listen=config.listen,
        connect=config.connect,
        multicast=config.multicast,
        multicast_port=config.multicast_port,
        multicast_interface=config.multicast_interface,
        gossip=config.gossip_scouting,
        shared_memory=config.shared_memory,
        lease_ms=config.lease_ms,
        extra_file=config.zenoh_config,
    )


#: " at /path/to/file.rs:61." that Zenoh appends to its errors (where in its Rust source).
_RUST_PLACE = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")
#: Zenoh's error for a listen endpoint whose address is taken.
_IN_USE = re.compile(r"listener bound to (\S+?):\s*\[.*Address already in use", re.DOTALL)


def session_error_text(error: str) -> str:
    """What a Zenoh error says, for people: a listen address in use is named with what to do;
    otherwise the text without the Rust source places."""
    in_use = _IN_USE.search(error)
    if in_use:
        return (
            f"cannot listen on {in_use.group(1)}: the address is already in use (another colonyd "
            "or another program listens there); expected a free address: stop that program or "
            "choose another --listen endpoint"
        )
    return "cannot open the Zenoh session: " + _RUST_PLACE.sub("", error).strip()


def open_session(conf: zenoh.Config) -> zenoh.Session:
    """Open a session; the caller closes it in `finally`."""
    try:
        return zenoh.open(conf)
    except zenoh.ZError as exc:
        raise RuntimeSetupError(session_error_text(str(exc))) from None


def get_session(config: Config) -> zenoh.Session:
    """Open the daemon's session from its config."""
    session = open_session(get_zenoh_config(config))
    log.info(
        "zenoh %s session %s (listen %s, connect %s, multicast %s)",
        config.mode,
        session.zid(),
        config.listen or "default",
        config.connect or "none",
        f"{MULTICAST_ADDRESS}:{config.multicast_port}" if config.multicast else "off",
    )
    return session


def get_client_session(config: Config, command: str) -> zenoh.Session:
    """A short-lived peer session for a command that talks to a running colony (`status`,
    `export`): StatusError unless it has a daemon to connect to or multicast to find one."""
    if not config.connect and not config.multicast:
        msg = f"{command} needs --connect ENDPOINT (a daemon's listen endpoint) or multicast"
        raise StatusError(msg)
    return open_session(
        zenoh_config(
            mode="peer",
            listen=config.listen or ["tcp/127.0.0.1:0"],
            connect=config.connect,
            multicast=config.multicast,
            multicast_port=config.multicast_port,
            multicast_interface=config.multicast_interface,
            gossip=True,
        )
    )


def undeclare(*entities: object) -> None:
    """Undeclare Zenoh publishers, subscribers, queryables or tokens; quietly for any the
    session has already closed."""
    for entity in entities:
        try:
            entity.undeclare()  # type: ignore[attr-defined]
        except Exception as exc:  # noqa: BLE001 - shutting down: whatever it was, go on
            log.debug("undeclare: %s", exc)
