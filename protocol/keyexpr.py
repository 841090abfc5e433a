"""Zenoh key expressions of a colony: one module builds and parses every key the daemons use.

Layout (every NAME matches `NAME_PATTERN`):

    colony/<colony>/<origin>/announce|pose|delta|objects|align|heartbeat|fix|history  publications
    colony/<colony>/alive/<origin>                                  liveliness tokens
    colony/<colony>/<origin>/snapshot/<layer>                       queryable: snapshot of a layer
    colony/<colony>/<origin>/deltas/<layer>                         queryable: range of deltas
    colony/<colony>/<origin>/history/<layer>                        queryable: history records
    colony/<colony>/<origin>/status                                 queryable: JSON status report
    colony/<colony>/<origin>/export                                 queryable: the daemon's map
    colony/<colony>/<origin>/forget                                 queryable: forget an agent
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

from protocol.errors import KeyExprError

ROOT = "colony"
#: A name (colony, origin, layer): 1-64 characters, letters, digits, `_`, `-`, `.`; starts with a
#: letter or digit. This excludes every Zenoh special character (`/ * $ # ? @` and spaces).
NAME_PATTERN = r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}"
_NAME = re.compile(NAME_PATTERN)
#: Topics an origin publishes on.
TOPICS = ("announce", "pose", "delta", "objects", "align", "heartbeat", "fix", "history")
#: Queryables an origin serves, each for one layer.
QUERIES = ("snapshot", "deltas", "history")
ALIVE = "alive"
#: An origin's status queryable (a daemon's JSON report, not a protocol frame).
STATUS = "status"
#: An origin's map export queryable (a daemon's fused or per-layer map, not a protocol frame).
EXPORT = "export"
#: An origin's queryable that forgets an agent's layer colony-wide (tooling, not a frame).
FORGET = "forget"
#: Queryables of a daemon's own that are not protocol frames (tooling).
REPORTS = (STATUS, EXPORT, FORGET)

Topic = Literal["announce", "pose", "delta", "objects", "align", "heartbeat", "fix", "history"]
Query = Literal["snapshot", "deltas", "history"]


def validate_name(name: str, what: str = "name") -> str:
    """Return `name` if it is a valid colony/origin/layer name, else raise KeyExprError."""
    if not isinstance(name, str):
        msg = f"{what} must be a string matching {NAME_PATTERN}, found {type(name).__name__}"
        raise KeyExprError(msg)
    if not _NAME.fullmatch(name):
        msg = f"{what} must match {NAME_PATTERN} (letters, digits, '_', '-', '.'), found {name!r}"
        raise KeyExprError(msg)
    if name in (ALIVE, ROOT) and what == "origin":
        msg = f"origin must not be the reserved word {name!r}"
        raise KeyExprError(msg)
    return name


def topic_key(colony: str, origin: str, topic: Topic) -> str:
    """Key an origin publishes `topic` messages on."""
    if topic not in TOPICS:
        msg = f"topic must be one of {TOPICS}, found {topic!r}"
        raise KeyExprError(msg)
    return f"{ROOT}/{validate_name(colony, 'colony')}/{validate_name(origin, 'origin')}/{topic}"


def topic_subscription(colony: str, topic: Topic | None = None) -> str:
    """Key expression matching `topic` (or every topic) of every origin of a colony."""
    if topic is not None and topic not in TOPICS:
        msg = f"topic must be one of {TOPICS} or None, found {topic!r}"
        raise KeyExprError(msg)
    return f"{ROOT}/{validate_name(colony, 'colony')}/*/{topic if topic else '*'}"


def alive_key(colony: str, origin: str) -> str:
    """Liveliness token key of an origin."""
    return f"{ROOT}/{validate_name(colony, 'colony')}/{ALIVE}/{validate_name(origin, 'origin')}"


def alive_subscription(colony: str) -> str:
    """Key expression matching the liveliness tokens of every origin of a colony."""
    return f"{ROOT}/{validate_name(colony, 'colony')}/{ALIVE}/*"


def _check_query(query: str) -> None:
    if query not in QUERIES:
        msg = f"query must be one of {QUERIES}, found {query!r}"
        raise KeyExprError(msg)


def query_key(colony: str, origin: str, query: Query, layer: str) -> str:
    """Key of the `query` queryable that `origin` serves for `layer`."""
    _check_query(query)
    return (
        f"{ROOT}/{validate_name(colony, 'colony')}/{validate_name(origin, 'origin')}"
        f"/{query}/{validate_name(layer, 'layer')}"
    )


def query_declaration(colony: str, origin: str, query: Query) -> str:
    """Key expression an origin declares its `query` queryable on (every layer it holds)."""
    _check_query(query)
    return f"{ROOT}/{validate_name(colony, 'colony')}/{validate_name(origin, 'origin')}/{query}/*"


def status_key(colony: str, origin: str, report: str = STATUS) -> str:
    """Key of `origin`'s status (JSON) or export (map) queryable: tooling, not frames."""
    if report not in REPORTS:
        msg = f"report must be one of {REPORTS}, found {report!r}"
        raise KeyExprError(msg)
    return f"{ROOT}/{validate_name(colony, 'colony')}/{validate_name(origin, 'origin')}/{report}"


def status_selector(colony: str, report: str = STATUS) -> str:
    """Key expression matching the status (or export) queryables of every origin of a colony."""
    if report not in REPORTS:
        msg = f"report must be one of {REPORTS}, found {report!r}"
        raise KeyExprError(msg)
    return f"{ROOT}/{validate_name(colony, 'colony')}/*/{report}"


@dataclass(frozen=True)
class ParsedKey:
    """A parsed colony key: `kind` is a topic, a query name or "alive"."""

    colony: str
    origin: str
    kind: str
    layer: str | None = None


def parse_key(key: str) -> ParsedKey:
    """Parse a concrete colony key (no wildcards) into its parts; raise KeyExprError otherwise."""
    if not isinstance(key, str):
        msg = f"key must be a string, found {type(key).__name__}"
        raise KeyExprError(msg)
    parts = key.split("/")
    if len(parts) < 4 or parts[0] != ROOT:
        msg = f"key must look like '{ROOT}/<colony>/<origin>/<topic>', found {key!r}"
        raise KeyExprError(msg)
    colony = validate_name(parts[1], "colony")
    if parts[2] == ALIVE:
        if len(parts) != 4:
            msg = f"liveliness key must be '{ROOT}/<colony>/{ALIVE}/<origin>', found {key!r}"
            raise KeyExprError(msg)
        return ParsedKey(colony, validate_name(parts[3], "origin"), ALIVE)
    origin = validate_name(parts[2], "origin")
    kind = parts[3]
    if len(parts) == 4 and (kind in TOPICS or kind in REPORTS):
        return ParsedKey(colony, origin, kind)
    if len(parts) == 5 and kind in QUERIES:
        return ParsedKey(colony, origin, kind, validate_name(parts[4], "layer"))
    msg = (
        f"key must end in one of {(*TOPICS, *REPORTS)} or '<{'|'.join(QUERIES)}>/<layer>', "
        f"found {'/'.join(parts[3:])!r} in {key!r}"
    )
    raise KeyExprError(msg)


def check_origin(key: str, origin: str) -> ParsedKey:
    """Parse `key` and check that it belongs to `origin` (the origin in the frame's envelope)."""
    parsed = parse_key(key)
    if parsed.origin != origin:
        msg = (
            f"key {key!r} belongs to origin {parsed.origin!r}, found a frame from origin {origin!r}"
        )
        raise KeyExprError(msg)
    return parsed
