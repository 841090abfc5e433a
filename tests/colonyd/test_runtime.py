"""Zenoh runtime in one process: two sessions on loopback, multicast off, a frame and a query
between them."""

from __future__ import annotations

import queue
import time

import zenoh

from colonyd.bench.launcher import free_port
from colonyd.runtime import open_session, zenoh_config
from protocol import VoxelDelta, decode, encode
from protocol.keyexpr import topic_key
from voxel.delta import Delta


def _pair() -> tuple[zenoh.Session, zenoh.Session]:
    """A listening session and one connected to it, both on 127.0.0.1 with multicast scouting
    off."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf_a = zenoh_config(listen=[endpoint])
    conf_b = zenoh_config(listen=["tcp/127.0.0.1:0"], connect=[endpoint])
    for conf in (conf_a, conf_b):
        assert conf.get_json("scouting/multicast/enabled") == "false"
    a = open_session(conf_a)
    try:
        return a, open_session(conf_b)
    except BaseException:
        a.close()
        raise


def test_two_sessions_on_loopback_carry_a_frame_and_a_query() -> None:
    ns = "runtime-test"
    a, b = _pair()
    try:
        got: queue.Queue[bytes] = queue.Queue()
        sub = a.declare_subscriber(
            topic_key(ns, "r1", "delta"), lambda s: got.put(s.payload.to_bytes())
        )
        frame = encode(
            VoxelDelta(
                origin="r1",
                epoch=1,
                seq=1,
                time=1.0,
                frame_id="map",
                delta=Delta(0.1, 0, 1, [[1, 2, 3]], [0.5], [1.0]),
            )
        )
        deadline = time.monotonic() + 10
        received = None
        while received is None and time.monotonic() < deadline:  # the link may still be coming up
            b.put(topic_key(ns, "r1", "delta"), frame)
            try:
                received = got.get(timeout=0.2)
            except queue.Empty:
                continue
        assert received == frame
        msg = decode(received)
        assert isinstance(msg, VoxelDelta) and msg.delta.keys.tolist() == [[1, 2, 3]]
        sub.undeclare()

        answer = a.declare_queryable(f"{ns}/status/a", lambda q: q.reply(q.key_expr, b"a is here"))
        replies: list[bytes] = []
        while not replies and time.monotonic() < deadline + 10:  # the declaration travels too
            replies = [
                r.ok.payload.to_bytes()
                for r in b.get(f"{ns}/status/**", timeout=1.0)
                if r.ok is not None
            ]
        assert replies == [b"a is here"]
        answer.undeclare()
    finally:
        b.close()
        a.close()
