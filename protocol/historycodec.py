"""History codec: a page of a layer's history records as dictionary-coded, byte-shuffled columns.

`encode_history` turns a `voxel.history.HistoryPage` into the codec body (a msgpack map of
binary columns; the envelope compresses it); `decode_history` turns hostile bytes back into a
page, checking every column. Layout in docs/PROTOCOL.md ("History body").
"""

from __future__ import annotations

import re
from typing import Any

import numpy as np

from protocol import fields
from protocol.errors import MalformedError, OversizedError, RangeError, VersionError
from protocol.keyexpr import NAME_PATTERN
from protocol.limits import DEFAULT_LIMITS, Limits
from voxel.history import RECORD_COLUMNS, HistoryPage
from voxel.keys import AXIS_BITS
from voxel.record import RECORD_DTYPE, SEEN_DTYPE
from voxel.sensor import SENSOR_KINDS

#: Version of the history body layout (field "v").
CODEC_VERSION = 1
#: Most records one history body may carry.
MAX_RECORDS = 1_000_000
#: Most agents one page may name (record agent codes are u16).
MAX_AGENTS = 4096
#: Wire dtype (little-endian) of each dictionary-coded column; `key` travels apart.
WIRE_DTYPES: dict[str, str] = {
    "time": "<f8",
    "agent": "<u2",
    "sensor": "u1",
    "evidence": "<f4",
    "logodds": "<f4",
    "state": "i1",
    "flip": "u1",
    "object_id": "<i4",
    "object_prob": "<f4",
    "error": "<f4",
    "reliability": "<f4",
    "bias": "<f4",
    "version": "<u4",
}
#: Wire dtype of the seen log's dictionary-coded columns (`key` travels like records' keys).
SEEN_WIRE_DTYPES: dict[str, str] = {"time": "<f8", "version": "<u4"}
_NAME = re.compile(NAME_PATTERN)
_KEY_LIMIT = 1 << (3 * AXIS_BITS)


def _code_width(table_len: int) -> int:
    return 1 if table_len <= 1 << 8 else 2 if table_len <= 1 << 16 else 4


def _column(values: np.ndarray, wire: str) -> list[bytes]:
    """[table, codes]: the distinct values (wire dtype) and each record's index into them."""
    arr = np.ascontiguousarray(values.astype(wire))
    bits = arr.view(f"u{arr.dtype.itemsize}")  # distinct by bit pattern (NaN, -0.0 kept exact)
    uniq, codes = np.unique(bits, return_inverse=True)
    width = _code_width(uniq.size)
    return [uniq.view(arr.dtype).tobytes(), codes.astype(f"<u{width}").tobytes()]


def encode_history(page: HistoryPage) -> bytes:
    """Codec body of a page: records sorted by (version, key); keys as byte-shuffled i8
    differences; every other column as a table of distinct values plus u1/u2/u4 codes."""
    rec = page.records
    if rec.dtype != RECORD_DTYPE:
        msg = f"history records must have dtype {RECORD_DTYPE}, found {rec.dtype}"
        raise MalformedError(msg)
    rec = rec[np.lexsort((rec["key"], rec["version"]))]
    seen = page.seen[np.lexsort((page.seen["key"], page.seen["version"]))]
    body: dict[str, Any] = {
        "v": CODEC_VERSION,
        "n": int(rec.size),
        "agents": list(page.agents),
        "key": _shuffled_keys(rec["key"]),
        "seen_n": int(seen.size),
        "seen_key": _shuffled_keys(seen["key"]),
    }
    for name, wire in WIRE_DTYPES.items():
        body[name] = _column(rec[name], wire)
    for name, wire in SEEN_WIRE_DTYPES.items():
        body[f"seen_{name}"] = _column(seen[name], wire)
    return fields.pack(body)


def _shuffled_keys(keys: np.ndarray) -> bytes:
    """Packed keys as i8 differences from the previous (the first from 0), byte-shuffled."""
    diffs = np.diff(keys.astype("<i8"), prepend=np.int64(0)).astype("<i8")
    return diffs.view(np.uint8).reshape(-1, 8).T.copy().tobytes()  # high byte planes: zeros


def _unshuffled_keys(raw: bytes, n: int, what: str) -> np.ndarray:
    if len(raw) != 8 * n:
        msg = f"history body: expected {8 * n} {what} bytes for {n} entries, found {len(raw)}"
        raise MalformedError(msg)
    diffs = np.frombuffer(raw, dtype=np.uint8).reshape(8, n).T.copy().view("<i8")[:, 0]
    with np.errstate(over="ignore"):
        keys: np.ndarray = np.cumsum(diffs, dtype=np.int64)
    return keys


def _decode_column(raw: Any, name: str, n: int, wire_name: str | None = None) -> np.ndarray:
    wire = np.dtype(wire_name or WIRE_DTYPES[name])
    if not isinstance(raw, list) or len(raw) != 2 or not all(isinstance(x, bytes) for x in raw):
        msg = (
            f"history column {name!r}: expected [table bin, codes bin], found {type(raw).__name__}"
        )
        raise MalformedError(msg)
    table_raw, codes_raw = raw
    if len(table_raw) % wire.itemsize:
        msg = (
            f"history column {name!r}: expected a table of {wire.itemsize}-byte values, found "
            f"{len(table_raw)} bytes"
        )
        raise MalformedError(msg)
    table = np.frombuffer(table_raw, dtype=wire)
    if n and table.size == 0:
        msg = f"history column {name!r}: expected a table for {n} records, found none"
        raise MalformedError(msg)
    width = _code_width(table.size)
    if len(codes_raw) != n * width:
        msg = (
            f"history column {name!r}: expected {n} codes of {width} bytes for a table of "
            f"{table.size}, found {len(codes_raw)} bytes"
        )
        raise MalformedError(msg)
    codes = np.frombuffer(codes_raw, dtype=f"<u{width}")
    if n and int(codes.max()) >= table.size:
        msg = (
            f"history column {name!r}: expected codes below {table.size}, found {int(codes.max())}"
        )
        raise RangeError(msg)
    out: np.ndarray = table[codes]
    return out


def _check_values(rec: np.ndarray, agents: list[str]) -> None:
    """RangeError unless every column holds what a record may hold."""
    checks = (
        ("key", (rec["key"] >= 0) & (rec["key"] < _KEY_LIMIT), "a packed key in [0, 2^63)"),
        ("time", np.isfinite(rec["time"]), "a finite time"),
        ("agent", rec["agent"] < len(agents), f"an index below {len(agents)} agents"),
        ("sensor", np.isin(rec["sensor"], list(SENSOR_KINDS.values())), "a sensor kind code"),
        ("evidence", np.isfinite(rec["evidence"]), "a finite log-odds"),
        ("logodds", np.isfinite(rec["logodds"]), "a finite log-odds"),
        ("state", np.isin(rec["state"], (-1, 0, 1)), "-1, 0 or 1"),
        ("flip", rec["flip"].view(np.uint8) <= 1, "0 or 1"),
        ("object_id", rec["object_id"] >= -1, "an object id >= -1"),
        (
            "object_prob",
            (rec["object_prob"] >= 0) & (rec["object_prob"] <= 1),
            "a probability in [0, 1]",
        ),
        ("error", np.isfinite(rec["error"]) & (rec["error"] >= 0), "an error >= 0"),
        (
            "reliability",
            (rec["reliability"] >= 0) & (rec["reliability"] <= 1),
            "a reliability in [0, 1]",
        ),
        ("bias", np.isfinite(rec["bias"]), "a finite number"),
        ("version", rec["version"] > 0, "a version > 0"),
    )
    for name, ok, expected in checks:
        if not bool(np.all(ok)):
            bad = rec[name][~ok][0]
            msg = f"history column {name!r}: expected {expected}, found {bad!r}"
            raise RangeError(msg)


def decode_history(data: bytes, limits: Limits = DEFAULT_LIMITS) -> HistoryPage:
    """A validated page of hostile history-body bytes, or a ProtocolError saying why not."""
    body = fields.as_map(fields.unpack(data, "history body", limits), "history body")
    version = fields.field(body, "v", int, "history body")
    if version != CODEC_VERSION:
        msg = f"history body: expected codec version {CODEC_VERSION}, found {version}"
        raise VersionError(msg)
    n = fields.field(body, "n", int, "history body")
    if not 0 <= n <= MAX_RECORDS:
        msg = f"history body: expected 0..{MAX_RECORDS} records, found {n}"
        raise OversizedError(msg) if n > MAX_RECORDS else RangeError(msg)
    agents = fields.field(body, "agents", list, "history body")
    if len(agents) > MAX_AGENTS or not all(
        isinstance(a, str) and _NAME.fullmatch(a) for a in agents
    ):
        msg = f"history body: expected at most {MAX_AGENTS} agent names, found {agents[:3]!r}…"
        raise RangeError(msg)
    rec = np.zeros(n, dtype=RECORD_DTYPE)
    rec["key"] = _unshuffled_keys(fields.field(body, "key", bytes, "history body"), n, "key")
    for name in RECORD_COLUMNS:
        if name != "key":
            rec[name] = _decode_column(body.get(name), name, n)
    _check_values(rec, agents)
    m = body.get("seen_n", 0)  # optional: absent means no seen entries
    if isinstance(m, bool) or not isinstance(m, int) or not 0 <= m <= MAX_RECORDS:
        msg = f"history body: expected 0..{MAX_RECORDS} seen entries, found {m!r}"
        raise RangeError(msg)
    seen = np.zeros(m, dtype=SEEN_DTYPE)
    if m:
        raw = fields.field(body, "seen_key", bytes, "history body")
        seen["key"] = _unshuffled_keys(raw, m, "seen_key")
        for name, wire in SEEN_WIRE_DTYPES.items():
            seen[name] = _decode_column(body.get(f"seen_{name}"), f"seen_{name}", m, wire)
        checks = (
            ("seen_key", (seen["key"] >= 0) & (seen["key"] < _KEY_LIMIT), "a packed key"),
            ("seen_time", np.isfinite(seen["time"]), "a finite time"),
            ("seen_version", seen["version"] > 0, "a version > 0"),
        )
        for name, ok, expected in checks:
            if not bool(np.all(ok)):
                msg = f"history column {name!r}: expected {expected}, found a value outside"
                raise RangeError(msg)
    return HistoryPage(rec, [str(a) for a in agents], seen)
