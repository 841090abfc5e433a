"""Tests of the spec parser: splitting specs and validating options against a source's model."""

from __future__ import annotations

from typing import Literal

import pytest
from pydantic import Field

from plugins.errors import SourceError, SourceSpecError
from plugins.spec import Options, default_text, option_docs, parse_options, split_spec, type_name

USAGES = {"toy": "toy:key=value,...", "file": "file:PATH[,key=value...]"}


class ToyOptions(Options):
    """A model with one option of each kind of type."""

    count: int = Field(3, description="how many")
    scale: float = Field(1.0, gt=0, description="how big")
    loud: bool = Field(False, description="whether to shout")
    limit: int | None = Field(None, description="at most this many")
    name: str = Field("toy", description="what to call it")
    mode: Literal["fast", "slow"] = Field("fast", description="how to run")


def test_split_spec() -> None:
    spec = split_spec("toy:count=2, name = box ,", USAGES)
    assert (spec.kind, spec.path, spec.options, spec.text) == (
        "toy",
        None,
        {"count": "2", "name": "box"},
        "toy:count=2, name = box ,",
    )
    spec = split_spec("file:/data/a b.log,count=1", USAGES, frozenset({"file"}))
    assert (spec.path, spec.options) == ("/data/a b.log", {"count": "1"})
    assert split_spec("toy:", USAGES).options == {}
    assert split_spec("toy:a=1,,b=2", USAGES).options == {"a": "1", "b": "2"}


@pytest.mark.parametrize(
    ("text", "match"),
    [
        (
            "toy",
            (
                r"^source spec: expected 'toy:key=value,...' or 'file:PATH\[,key=value...\]', "
                r"found 'toy'$"
            ),
        ),
        (
            "boat:x=1",
            r"expected 'toy:key=value,...' or 'file:PATH\[,key=value...\]', found 'boat:x=1'",
        ),
        ("file:", r"^source spec: expected 'file:PATH\[,key=value...\]', found 'file:'$"),
        ("file:count=1", r"expected 'file:PATH\[,key=value...\]', found 'file:count=1'"),
        ("toy:count", r"^source spec 'toy:count': expected key=value, found 'count'$"),
        ("toy:=3", r"expected key=value, found '=3'"),
        ("toy:count=1,count=2", r"expected each option once, found 'count' twice"),
    ],
)
def test_split_spec_errors(text: str, match: str) -> None:
    with pytest.raises(SourceSpecError, match=match) as info:
        split_spec(text, USAGES, frozenset({"file"}))
    assert isinstance(info.value, SourceError) and isinstance(info.value, ValueError)


def test_parse_options_types_and_defaults() -> None:
    options = parse_options(
        ToyOptions,
        {"count": "7", "scale": "0.5", "loud": "yes", "limit": "none", "mode": "slow"},
        "toy:",
    )
    assert (
        options.count,
        options.scale,
        options.loud,
        options.limit,
        options.name,
        options.mode,
    ) == (7, 0.5, True, None, "toy", "slow")
    assert parse_options(ToyOptions, {"loud": "off", "limit": "4"}, "toy:") == ToyOptions(
        loud=False, limit=4
    )
    assert parse_options(ToyOptions, {"name": ""}, "toy:").name == ""
    assert parse_options(ToyOptions, {"limit": ""}, "toy:").limit is None


@pytest.mark.parametrize(
    ("options", "match"),
    [
        (
            {"cuont": "1"},
            (
                r"^source spec 'toy:': option 'cuont': expected one of \['count', 'limit', 'loud', "
                r"'mode', 'name', 'scale'\], found unknown option$"
            ),
        ),
        ({"count": "many"}, r"^source spec 'toy:': option 'count': expected int, found 'many'$"),
        ({"count": "1.5"}, r"option 'count': expected int, found '1.5'"),
        ({"scale": "big"}, r"option 'scale': expected float, found 'big'"),
        ({"loud": "maybe"}, r"option 'loud': expected bool, found 'maybe'"),
        ({"limit": "all"}, r"option 'limit': expected int or None, found 'all'"),
        ({"mode": "warp"}, r"option 'mode': expected 'fast' or 'slow', found 'warp'"),
        ({"scale": "0"}, r"option 'scale': expected a number greater than 0, found '0'"),
        (
            {"count": "x", "loud": "y?"},
            r"option 'count': expected int, found 'x'; option 'loud': expected bool, found 'y\?'",
        ),
    ],
)
def test_parse_options_errors_name_the_option(options: dict[str, str], match: str) -> None:
    with pytest.raises(SourceSpecError, match=match):
        parse_options(ToyOptions, options, "toy:")


def test_option_docs_and_type_names() -> None:
    docs = {d.name: d for d in option_docs(ToyOptions)}
    assert list(docs) == ["count", "scale", "loud", "limit", "name", "mode"]
    assert (docs["limit"].type, docs["limit"].default, docs["limit"].help) == (
        "int or None",
        "none",
        "at most this many",
    )
    assert (docs["loud"].type, docs["loud"].default) == ("bool", "false")
    assert docs["mode"].type == "'fast' or 'slow'"
    assert [d.name for d in option_docs(ToyOptions, exclude=("count", "mode"))] == [
        "scale",
        "loud",
        "limit",
        "name",
    ]
    assert (
        type_name(float) == "float"
        and default_text(True) == "true"
        and default_text(0.25) == "0.25"
    )
