"""Tests of protocol.keyexpr: building, parsing and validating colony key expressions."""

from __future__ import annotations

import pytest

from protocol.errors import KeyExprError
from protocol.keyexpr import (
    ParsedKey,
    alive_key,
    alive_subscription,
    parse_key,
    query_declaration,
    query_key,
    status_key,
    status_selector,
    topic_key,
    topic_subscription,
    validate_name,
)


def test_keys_build_and_parse_back() -> None:
    for topic in ("announce", "pose", "delta", "objects", "align", "heartbeat"):
        key = topic_key("site-a", "robot-1", topic)  # type: ignore[arg-type]
        assert key == f"colony/site-a/robot-1/{topic}"
        assert parse_key(key) == ParsedKey("site-a", "robot-1", topic)
    assert parse_key(alive_key("c", "r.2")) == ParsedKey("c", "r.2", "alive")
    assert parse_key(query_key("c", "r1", "snapshot", "r2")) == ParsedKey(
        "c", "r1", "snapshot", "r2"
    )
    assert parse_key(query_key("c", "r1", "deltas", "r1")) == ParsedKey("c", "r1", "deltas", "r1")


def test_wildcard_expressions() -> None:
    assert topic_subscription("c") == "colony/c/*/*"
    assert topic_subscription("c", "delta") == "colony/c/*/delta"
    assert alive_subscription("c") == "colony/c/alive/*"
    assert query_declaration("c", "r1", "snapshot") == "colony/c/r1/snapshot/*"
    assert status_selector("c") == "colony/c/*/status"


def test_status_key_parses_back() -> None:
    assert status_key("c", "r1") == "colony/c/r1/status"
    assert parse_key(status_key("c", "r1")) == ParsedKey("c", "r1", "status")
    with pytest.raises(KeyExprError, match="reserved word"):
        status_key("c", "alive")


@pytest.mark.parametrize(
    "bad", ["", "a/b", "a*", "$x", "a#", "a?b", "@r", "-lead", "a b", "x" * 65, "é"]
)
def test_bad_names_rejected(bad: str) -> None:
    with pytest.raises(KeyExprError, match="must match"):
        validate_name(bad, "origin")


def test_reserved_origin_rejected() -> None:
    with pytest.raises(KeyExprError, match="reserved word 'alive'"):
        topic_key("c", "alive", "pose")


def test_non_string_name_rejected() -> None:
    with pytest.raises(KeyExprError, match="must be a string"):
        validate_name(5)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("key", "match"),
    [
        ("other/c/r/pose", "must look like"),
        ("colony/c/r", "must look like"),
        ("colony/c/r/teleport", "must end in one of"),
        ("colony/c/r/snapshot", "must end in one of"),
        ("colony/c/r/pose/extra", "must end in one of"),
        ("colony/c/alive/r/x", "liveliness key"),
        ("colony/c/*/pose", "origin must match"),
        ("colony/c/r/snapshot/**", "layer must match"),
    ],
)
def test_bad_keys_rejected(key: str, match: str) -> None:
    with pytest.raises(KeyExprError, match=match):
        parse_key(key)


def test_bad_topic_and_query_rejected() -> None:
    with pytest.raises(KeyExprError, match="topic must be one of"):
        topic_key("c", "r", "teleport")  # type: ignore[arg-type]
    with pytest.raises(KeyExprError, match="topic must be one of"):
        topic_subscription("c", "teleport")  # type: ignore[arg-type]
    with pytest.raises(KeyExprError, match="query must be one of"):
        query_key("c", "r", "everything", "r")  # type: ignore[arg-type]
    with pytest.raises(KeyExprError, match="query must be one of"):
        query_declaration("c", "r", "everything")  # type: ignore[arg-type]
    with pytest.raises(KeyExprError, match="key must be a string"):
        parse_key(None)  # type: ignore[arg-type]


def test_key_origin_must_match_frame_origin() -> None:
    from protocol.keyexpr import check_origin

    assert check_origin("colony/c/r1/delta", "r1").kind == "delta"
    with pytest.raises(
        KeyExprError, match="belongs to origin 'r1', found a frame from origin 'r2'"
    ):
        check_origin("colony/c/r1/delta", "r2")
