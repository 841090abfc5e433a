"""Tombstones: agents whose layers the colony forgot, on disk and in `colonyd forget-agent`."""

from __future__ import annotations

import hashlib
import hmac
import json
import os
import re
import time
from pathlib import Path
from typing import Any

from colonyd.config import Config
from colonyd.errors import StatusError
from colonyd.frames import colony_key
from colonyd.runtime import get_client_session
from colonyd.status import json_replies
from protocol.keyexpr import FORGET, NAME_PATTERN, status_selector

FILE = "forgotten.json"
#: How far a forget request's time may be from the daemon's clock, seconds.
FRESH_S = 60.0


def load_tombstones(state_dir: Path) -> set[str]:
    """The forgotten agents saved in `state_dir` (none when the file is missing or unreadable)."""
    try:
        names = json.loads((Path(state_dir) / FILE).read_text())
    except (OSError, ValueError):
        return set()
    if not isinstance(names, list):
        return set()
    return {n for n in names if isinstance(n, str) and re.fullmatch(NAME_PATTERN, n)}


def save_tombstones(state_dir: Path, names: set[str]) -> None:
    """Write the forgotten agents atomically (a restart keeps them forgotten)."""
    path = Path(state_dir) / FILE
    tmp = path.with_name(FILE + ".tmp")
    tmp.write_text(json.dumps(sorted(names)))
    os.replace(tmp, path)


def forget_tag(key: bytes, agent: str, t: float) -> str:
    """HMAC-SHA256 (hex) of a forget request with the colony key."""
    return hmac.new(key, f"forget:{agent}:{t!r}".encode(), hashlib.sha256).hexdigest()


def forget_params(params: dict[str, str], key: bytes | None, now: float) -> str:
    """The agent a forget query asks to forget; ValueError unless it names one and, with a
    colony key, carries a fresh time `t` and its tag `auth`."""
    agent = params.get("agent", "")
    if not re.fullmatch(NAME_PATTERN, agent):
        msg = f"expected agent=NAME matching {NAME_PATTERN}, found {agent[:80]!r}"
        raise ValueError(msg)
    if key is None:
        return agent
    try:
        t = float(params.get("t", "nan"))
    except ValueError:
        t = float("nan")
    if not abs(t - now) <= FRESH_S:
        msg = f"expected a request time within {FRESH_S:.0f} s of ours, found {params.get('t')!r}"
        raise ValueError(msg)
    if not hmac.compare_digest(forget_tag(key, agent, t), params.get("auth", "")):
        msg = "expected a request authenticated with the colony key, found a bad tag"
        raise ValueError(msg)
    return agent


def forget_agent(config: Config, agent: str, wait_s: float = 5.0) -> list[dict[str, Any]]:
    """Ask every reachable daemon to forget `agent`'s layer (each then tells the rest in its
    heartbeats); their answers, sorted by agent. StatusError when no daemon took it."""
    if not re.fullmatch(NAME_PATTERN, agent):
        msg = f"agent: expected a name matching {NAME_PATTERN}, found {agent!r}"
        raise StatusError(msg)
    session = get_client_session(config, "forget-agent")
    try:
        t = time.time()
        params = f"agent={agent}"
        key = colony_key(config.colony_key)
        if key is not None:
            params += f";t={t!r};auth={forget_tag(key, agent, t)}"
        selector = status_selector(config.key_namespace, FORGET) + "?" + params
        answers = json_replies(session, selector, wait_s)
    finally:
        session.close()
    if not any(a.get("forgotten") == agent for a in answers):
        errors = sorted({str(a.get("error")) for a in answers if a.get("error")})
        msg = (
            f"expected a daemon of namespace {config.key_namespace!r} to forget {agent!r}, "
            f"found {len(answers)} answers{': ' + '; '.join(errors) if errors else ''}"
        )
        raise StatusError(msg)
    return sorted(answers, key=lambda a: str(a.get("agent")))
