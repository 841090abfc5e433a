"""Source specs: `KIND:key=value,...` (or `replay:PATH,key=value,...`) parsed into typed options."""

from __future__ import annotations

import types
from dataclasses import dataclass, field
from typing import Any, Literal, TypeVar, Union, get_args, get_origin

from pydantic import BaseModel, ConfigDict, ValidationError

from plugins.errors import SourceSpecError

#: Option texts that mean "no value" for an option that may be None.
_NONE = ("none", "")
#: pydantic error types that mean "not of the option's type" (the rest are range or choice errors).
_TYPE_ERRORS = (
    "int_parsing",
    "int_from_float",
    "float_parsing",
    "bool_parsing",
    "int_type",
    "float_type",
    "bool_type",
    "string_type",
)


class Options(BaseModel):
    """Base of every source's options model: typed fields with defaults and help, nothing else."""

    model_config = ConfigDict(extra="forbid", frozen=True)


OptionsT = TypeVar("OptionsT", bound=Options)


@dataclass(frozen=True)
class SourceSpec:
    """A parsed source spec: kind, path (replay only), options as strings, and the spec's text."""

    kind: str
    path: str | None = None
    options: dict[str, str] = field(default_factory=dict)
    text: str = ""


def split_spec(
    spec: str, usages: dict[str, str], with_path: frozenset[str] = frozenset()
) -> SourceSpec:
    """Split `spec` into kind, path and `key=value` options.

    `usages` maps every known kind to its usage line (for the error message); kinds in
    `with_path` take a path before their options. Empty parts (`a=1,,b=2`, a trailing comma) are
    ignored.
    """
    kind, sep, body = spec.partition(":")
    if not sep or kind not in usages:
        msg = f"source spec: expected {_one_of([repr(u) for u in usages.values()])}, found {spec!r}"
        raise SourceSpecError(msg)
    parts = body.split(",") if body else []
    path = None
    if kind in with_path:
        if not parts or not parts[0] or "=" in parts[0]:
            msg = f"source spec: expected {usages[kind]!r}, found {spec!r}"
            raise SourceSpecError(msg)
        path, parts = parts[0], parts[1:]
    options: dict[str, str] = {}
    for part in filter(str.strip, parts):
        key, eq, value = part.partition("=")
        key = key.strip()
        if not eq or not key:
            msg = f"source spec {spec!r}: expected key=value, found {part!r}"
            raise SourceSpecError(msg)
        if key in options:
            msg = f"source spec {spec!r}: expected each option once, found {key!r} twice"
            raise SourceSpecError(msg)
        options[key] = value.strip()
    return SourceSpec(kind=kind, path=path, options=options, text=spec)


def parse_options(model: type[OptionsT], options: dict[str, str], spec: str) -> OptionsT:
    """`options` validated by `model`: unknown options and values of the wrong type fail naming the
    option."""
    allowed = sorted(model.model_fields)
    values: dict[str, Any] = {}
    for key, text in options.items():
        if key not in model.model_fields:
            msg = (
                f"source spec {spec!r}: option {key!r}: expected one of {allowed}, "
                "found unknown option"
            )
            raise SourceSpecError(msg)
        nullable = type(None) in get_args(model.model_fields[key].annotation)
        values[key] = None if nullable and text.lower() in _NONE else text
    try:
        return model(**values)
    except ValidationError as exc:
        problems = [_problem(model, error, options) for error in exc.errors()]
        msg = f"source spec {spec!r}: {'; '.join(problems)}"
        raise SourceSpecError(msg) from None


@dataclass(frozen=True)
class OptionDoc:
    """One option of a source as documented: name, type, default as spec text, and help."""

    name: str
    type: str
    default: str
    help: str


def option_docs(model: type[Options], exclude: tuple[str, ...] = ()) -> list[OptionDoc]:
    """The options of `model` (but `exclude`), in declaration order, as documented."""
    return [
        OptionDoc(
            name, type_name(info.annotation), default_text(info.default), info.description or ""
        )
        for name, info in model.model_fields.items()
        if name not in exclude
    ]


def default_text(value: object) -> str:
    """A default value as it would be written in a spec: `none`, `true`/`false`, numbers, text."""
    if value is None:
        return "none"
    if isinstance(value, bool):
        return str(value).lower()
    return str(value)


def type_name(annotation: Any) -> str:
    """A short name of an option's type: int, float, bool, str, `int or None`, `'a' or 'b'`."""
    origin = get_origin(annotation)
    if origin is Union or isinstance(annotation, types.UnionType):
        return " or ".join(type_name(a) for a in get_args(annotation))
    if origin is Literal:
        return _one_of([repr(a) for a in get_args(annotation)])
    if annotation is type(None):
        return "None"
    return getattr(annotation, "__name__", str(annotation))


def _problem(model: type[Options], error: Any, options: dict[str, str]) -> str:
    """One validation error as `option 'x': expected ..., found '...'`."""
    key = str(error["loc"][0]) if error["loc"] else "?"
    found = options.get(key, error.get("input"))
    if error["type"] in _TYPE_ERRORS and key in model.model_fields:
        expected = type_name(model.model_fields[key].annotation)
    else:
        expected = str(error["msg"]).removeprefix("Input should be ")
        if error["type"].startswith(("greater_than", "less_than")):
            expected = f"a number {expected}"
    return f"option {key!r}: expected {expected}, found {found!r}"


def _one_of(items: list[str]) -> str:
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " or " + items[-1]
