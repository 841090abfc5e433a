"""A holder's snapshot serving, with real daemons on loopback: a query whose requester has
stopped waiting is dropped, not served in full, and the next one is answered."""

from __future__ import annotations

import time
from typing import Any

import zenoh

from colonyd.frames import Sender
from protocol import SnapshotReply, SnapshotRequest
from protocol.codec import decode
from protocol.keyexpr import query_key
from protocol.limits import Limits

#: Enough voxels that making and encoding the snapshot takes far longer than 1 ms.
VOXELS = 200_000


def _ask(session: zenoh.Session, ns: str, timeout_ms: int, rid: int) -> list[SnapshotReply]:
    sender = Sender("asker", 1)
    request = SnapshotRequest(
        **sender.header(),
        layer="big",
        request_id=rid,
        timeout_ms=timeout_ms,
        max_part_bytes=1 << 20,
    )
    out: list[SnapshotReply] = []
    replies = session.get(
        query_key(ns, "big", "snapshot", "big"),
        payload=sender.encode(request),
        consolidation=zenoh.ConsolidationMode.NONE,
        timeout=20.0,  # this test waits on: only the request's timeout_ms tells the holder
    )
    for reply in replies:
        if reply.ok is not None:
            msg = decode(reply.ok.payload.to_bytes(), limits=Limits(max_voxels=VOXELS))
            assert isinstance(msg, SnapshotReply) and msg.request_id == rid
            out.append(msg)
    return out


def _counts(colony: Any) -> tuple[dict[str, int], list[dict[str, float]]]:
    (big,) = colony.reports(["big"]).values()
    return big["metrics"]["counts"], [m for layer, m in big["metrics"]["serves"] if layer == "big"]


def test_a_snapshot_query_whose_requester_gave_up_is_dropped(make_colony) -> None:
    colony = make_colony("serve")
    big = colony.add("big", [f"bulk:voxels={VOXELS}"], start=False)
    big.env["COLONYD_SNAPSHOT_CHUNK_VOXELS"] = "25000"  # 8 parts
    big.start()
    colony.wait_status(
        lambda rs: any(r["agent"] == "big" and r["layers"].get("big", {}).get("seq") for r in rs)
    )
    session = colony.session()
    # Requesters that wait 1 ms: gone before the holder has made the snapshot, let alone sent it.
    for rid in (1, 2, 3):
        assert _ask(session, colony.namespace, 1, rid) == []
    counts, serves = _counts(colony)
    assert counts.get("queries_abandoned", 0) == 3
    assert counts.get("snapshots_served", 0) == 0 and counts.get("bytes_served", 0) == 0
    # (one dropped while it waited in the queue has no serve timeline)
    assert len(serves) <= 3 and all("abandoned" in m and "replied" not in m for m in serves)
    # One that waits: every part, with the serve's timeline.
    t0 = time.monotonic()
    parts = _ask(session, colony.namespace, 20_000, 4)
    assert len(parts) == parts[0].parts > 1 and sorted(p.part for p in parts) == list(
        range(parts[0].parts)
    )
    assert sum(len(p.delta) for p in parts) == VOXELS
    counts, serves = _counts(colony)
    assert counts["snapshots_served"] == 1 and counts["queries_abandoned"] == 3
    last = serves[-1]
    order = ["arrived", "query", "locked", "snapshot", "encoded_first", "encoded"]
    order += ["first_reply", "replied"]
    assert t0 <= last["arrived"] and [last[k] for k in order] == sorted(last[k] for k in order)
