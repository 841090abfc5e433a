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
#: What a daemon answers when asked to forget its own layer (not a refusal of the request).
OWN_LAYER = "own layer"
#: Seconds `forget-agent` keeps asking until a daemon takes the request, and the most one round
#: waits for answers (a session just opened may not reach any queryable in its first round).
FORGET_WAIT_S = 15.0
FORGET_ROUND_S = 3.0


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


def forget_selector(config: Config, agent: str, timeout: float) -> str:
    """The forget query for `agent`, with a fresh time and its tag when a colony key is
    configured, and `timeout_ms` (a daemon drops it unanswered once its requester has gone)."""
    t = time.time()
    params = f"agent={agent};timeout_ms={int(timeout * 1000)}"
    key = colony_key(config.colony_key)
    if key is not None:
        params += f";t={t!r};auth={forget_tag(key, agent, t)}"
    return status_selector(config.key_namespace, FORGET) + "?" + params


def forget_agent(
    config: Config,
    agent: str,
    wait_s: float = FORGET_WAIT_S,
    round_s: float = FORGET_ROUND_S,
) -> list[dict[str, Any]]:
    """Ask every reachable daemon to forget `agent`'s layer (each then tells the rest in its
    heartbeats); their answers, sorted by agent. Asked again, in rounds of at most `round_s`,
    until a daemon took it, one refused it (a bad colony key: asking again changes nothing) or
    `wait_s` passed; StatusError then, saying what came back in how many rounds."""
    if not re.fullmatch(NAME_PATTERN, agent):
        msg = f"agent: expected a name matching {NAME_PATTERN}, found {agent!r}"
        raise StatusError(msg)
    if not wait_s > 0:
        raise StatusError(f"--wait: expected seconds > 0, found {wait_s!r}")
    session = get_client_session(config, "forget-agent")
    answers: dict[str, dict[str, Any]] = {}
    rounds = 0
    start = time.monotonic()
    try:
        while True:
            rounds += 1
            timeout = max(0.5, min(round_s, start + wait_s - time.monotonic()))
            for answer in json_replies(session, forget_selector(config, agent, timeout), timeout):
                answers[str(answer.get("agent"))] = answer
            took = any(a.get("forgotten") == agent for a in answers.values())
            refused = any(a.get("error") not in (None, OWN_LAYER) for a in answers.values())
            if took or refused or time.monotonic() - start >= wait_s:
                break
            time.sleep(0.2)
    finally:
        session.close()
    if not took:
        found = answers_found(answers)
        if not answers:
            where = ", ".join(config.connect) if config.connect else "multicast"
            found = f"no answer from a daemon reached through {where}"
        msg = (
            f"expected a daemon of namespace {config.key_namespace!r} to forget {agent!r}, "
            f"found {found} in {rounds} round{'s' if rounds > 1 else ''} over "
            f"{time.monotonic() - start:.1f} s"
        )
        raise StatusError(msg)
    return sorted(answers.values(), key=lambda a: str(a.get("agent")))


def answers_found(answers: dict[str, dict[str, Any]]) -> str:
    """What the daemons' answers to a forget request said, when none took it: each error once,
    with the daemons that gave it (a daemon never forgets its own layer: only its peers can)."""
    by_error: dict[str, list[str]] = {}
    for agent, answer in sorted(answers.items()):
        if answer.get("error"):
            by_error.setdefault(str(answer["error"]), []).append(agent)
    parts = []
    own = "its own layer (a daemon never forgets its own: its peers do)"
    for error, agents in sorted(by_error.items()):
        parts.append(f"{', '.join(agents)}: {own if error == OWN_LAYER else error}")
    n = len(answers)
    return f"{n} answer{'' if n == 1 else 's'}" + (": " + "; ".join(parts) if parts else "")
