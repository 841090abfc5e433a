"""Tests of the history codec and the history messages: round trips, size, hostile bodies."""

from __future__ import annotations

import numpy as np
import pytest

from protocol import HistoryReply, HistoryRequest, decode, encode, fields
from protocol.errors import MalformedError, OversizedError, ProtocolError, RangeError, VersionError
from protocol.historycodec import MAX_RECORDS, decode_history, encode_history
from voxel.grid import VoxelGrid
from voxel.history import HistoryPage


def _grid(scans: int = 6, points: int = 400) -> VoxelGrid:
    grid = VoxelGrid(0.1)
    rng = np.random.default_rng(3)
    for t in range(scans):
        origin = rng.uniform(-0.5, 0.5, 3)
        pts = origin + rng.normal(size=(points, 3)) * 1.5
        ids = np.where(rng.random(points) < 0.2, 4, -1)
        grid.integrate(pts, origin, time=1.7e9 + t * 0.25, agent=f"r{t % 2}", object_ids=ids)
    return grid


def _sorted(rec: np.ndarray) -> np.ndarray:
    return rec[np.lexsort((rec["key"], rec["version"]))]


def test_a_page_round_trips_exactly_in_a_few_bytes_per_record() -> None:
    grid = _grid()
    page, to, _more = grid.history.page(0, 10**6)
    msg = HistoryReply(
        origin="r0", time=1.0, layer="r0", request_id=7, layer_epoch=2, from_version=0,
        to_version=to, records=page,
    )  # fmt: skip
    frame = encode(msg)
    back = decode(frame)
    assert isinstance(back, HistoryReply) and back.records is not None
    a, b = _sorted(page.records), _sorted(back.records.records)
    for name in a.dtype.names:
        np.testing.assert_array_equal(a[name], b[name])
    assert back.records.agents == page.agents
    sa, sb = _sorted(page.seen), _sorted(back.records.seen)
    assert sa.size > 0 and all(np.array_equal(sa[n], sb[n]) for n in sa.dtype.names)
    entries = page.records.size + page.seen.size
    assert len(frame) / entries <= 8  # the target, bytes per record on the wire


def test_an_empty_reply_and_a_request_round_trip() -> None:
    empty = HistoryReply(
        origin="r0", time=1.0, layer="r0", request_id=1, layer_epoch=0, from_version=5,
        to_version=5,
    )  # fmt: skip
    assert decode(encode(empty)).records is None
    req = HistoryRequest(origin="r1", time=1.0, layer="r0", request_id=1, from_version=3)
    assert decode(encode(req)) == req
    with pytest.raises(ProtocolError, match="max_records"):
        decode(encode(req.model_copy(update={"max_records": 0})))


def _body(**changes: object) -> bytes:
    page, _to, _more = _grid(2, 50).history.page(0, 10**6)
    body = fields.unpack(encode_history(page), "history body", fields.Limits())
    body.update(changes)
    return fields.pack(body)


@pytest.mark.parametrize(
    ("change", "error", "match"),
    [
        ({"v": 2}, VersionError, "codec version 1"),
        ({"n": MAX_RECORDS + 1}, OversizedError, "records"),
        ({"n": 3}, MalformedError, "key bytes"),
        ({"agents": ["a b"]}, RangeError, "agent names"),
        ({"agents": []}, RangeError, "'agent': expected an index below 0"),
        ({"state": [np.array([5], "i1").tobytes(), b""]}, MalformedError, "codes"),
        ({"time": [b"\x00" * 7, b""]}, MalformedError, "8-byte values"),
        ({"time": None}, MalformedError, "table bin, codes bin"),
        ({"key": b""}, MalformedError, "key bytes"),
    ],
)
def test_hostile_bodies_are_rejected(change: dict[str, object], error: type, match: str) -> None:
    with pytest.raises(error, match=match):
        decode_history(_body(**change))


def test_values_out_of_range_are_rejected() -> None:
    page, _to, _more = _grid(2, 50).history.page(0, 10**6)
    for name, value, match in (
        ("state", 3, "'state': expected -1, 0 or 1"),
        ("time", np.inf, "'time': expected a finite time"),
        ("version", 0, "'version': expected a version > 0"),
        ("reliability", 2.0, "reliability in"),
        ("sensor", 77, "sensor kind code"),
        ("key", -5, "packed key"),
    ):
        rec = page.records.copy()
        rec[name][0] = value
        with pytest.raises(RangeError, match=match):
            decode_history(encode_history(HistoryPage(rec, page.agents)))


def test_a_reply_with_records_outside_its_versions_is_rejected() -> None:
    page, to, _more = _grid(3, 50).history.page(0, 10**6)
    msg = HistoryReply(
        origin="r0", time=1.0, layer="r0", request_id=7, layer_epoch=2, from_version=0,
        to_version=to, records=page,
    )  # fmt: skip
    bad = msg.model_copy(update={"to_version": 1})
    with pytest.raises(RangeError, match=r"records must have versions in \(0, 1\]"):
        decode(encode(bad))
