"""The status server on two real Zenoh sessions in one process (loopback, multicast off): a query
whose requester has gone while it waited in the queue is dropped, not answered."""

from __future__ import annotations

import threading
import time

from colonyd.status import StatusServer, json_replies, query_status
from protocol.keyexpr import status_selector
from tests.colonyd.test_runtime import _pair


def test_a_status_query_whose_requester_has_gone_is_not_answered() -> None:
    ns = "status-test"
    a, b = _pair()
    answered: list[dict[str, str]] = []

    def answer(params: dict[str, str]) -> dict[str, object]:
        answered.append(params)
        time.sleep(1.0)  # a digest of a large layer
        return {"agent": "a", "n": len(answered)}

    server = StatusServer(a, ns, "a", answer)
    try:
        time.sleep(0.5)  # the queryable reaches b
        # three at once, each waiting 0.1 s: the first is taken at once (and answered too late),
        # the other two are still queued when their requesters have gone
        asks = [
            threading.Thread(target=query_status, args=(b, ns), kwargs={"timeout": 0.1})
            for _ in range(3)
        ]
        for t in asks:
            t.start()
        for t in asks:
            t.join()
        time.sleep(1.2)  # the first one's answer is done
        assert len(answered) == 1
        assert "timeout_ms" not in answered[0]  # taken by the server, not passed on
        # one that waits is answered, and so is one that does not say how long it waits
        assert [r["n"] for r in query_status(b, ns, timeout=5.0)] == [2]
        assert [r["n"] for r in json_replies(b, status_selector(ns), 5.0)] == [3]
    finally:
        server.close()
        b.close()
        a.close()


def test_a_timeout_ms_parameter_from_the_network_is_parsed_or_ignored() -> None:
    from colonyd.status import asked_timeout_ms

    assert asked_timeout_ms("250") == 250
    assert asked_timeout_ms("9999999999") == 0xFFFF_FFFF
    for hostile in ("", "²", "-5", "1e3", "5.0", "1" * 400, " 5"):
        assert asked_timeout_ms(hostile) == 0, hostile  # no ValueError, no OverflowError


def test_nobody_answered_names_the_colonies_it_does_see() -> None:
    """`colonyd status` without the daemon's --colony: the error names the colony it found."""
    from colonyd.config import load_config
    from colonyd.status import nobody_answered
    from protocol.keyexpr import alive_key

    a, b = _pair()
    try:
        config = load_config(None, colony="default", multicast=False, connect=["tcp/x:1"])
        assert nobody_answered(b, config, 3.0) == (
            "no daemon of colony namespace 'default' answered within 3 s (looked through "
            "tcp/x:1): expected a running colonyd there, found none"
        )
        token = a.liveliness().declare_token(alive_key("site-a", "robot-1"))
        try:
            deadline = time.monotonic() + 5.0
            while "site-a" not in (text := nobody_answered(b, config, 3.0)):
                assert time.monotonic() < deadline, text
            assert text.endswith(
                "expected a member of that colony, found daemons of 'site-a' only: give "
                "--colony (or --namespace)"
            )
        finally:
            token.undeclare()
    finally:
        a.close()
        b.close()


def test_the_table_says_which_members_are_aligned_with_the_colony_frame() -> None:
    """`colonyd status` without --json showed no alignment at all, though alignment is what a
    user of a new colony waits for: one line per view of the colony frame follows the members."""
    from colonyd.status import format_status

    now = time.time()
    frame = {"root": "robot-a", "agents": {"robot-a": [], "robot-b": []}}
    reports = [
        {"agent": "robot-a", "time": now, "colony_frame": frame, "members": []},
        {"agent": "robot-b", "time": now, "colony_frame": frame, "members": []},
        {
            "agent": "robot-c",
            "time": now,
            "colony_frame": {"root": "robot-c", "agents": {"robot-c": []}},
            "members": [
                {"agent": "robot-d", "last_seen": now - 4.0, "alive": True},  # not answering
                {"agent": "robot-e", "last_seen": now - 9.0, "alive": False},  # stopped
            ],
        },
    ]
    lines = format_status(reports).splitlines()
    assert lines[4].startswith("robot-d") and lines[4].endswith("(not answering)")
    assert lines[5].startswith("robot-e") and lines[5].endswith("(left)")  # was "not answering"
    del lines[5]
    assert lines[5:] == [
        "colony frame: root robot-a; aligned: robot-a, robot-b; not aligned: robot-c, robot-d, "
        "robot-e (as robot-a, robot-b see it)",
        "colony frame: root robot-c; aligned: robot-c; not aligned: robot-a, robot-b, robot-d, "
        "robot-e (as robot-c see it)",
    ]
    one = format_status(reports[:2]).splitlines()[-1]
    assert one == "colony frame: root robot-a; aligned: robot-a, robot-b; not aligned: none"


def test_the_table_shows_each_members_sources_and_a_resumed_recordings_position() -> None:
    """A recording's progress (and where it resumed after a restart) was in `--json` only."""
    from colonyd.status import format_status

    now = time.time()
    sources = [
        {
            "spec": "replay:run.log",
            "delivered": 129,
            "skipped": 2,
            "position": 160,
            "resumed_after": 31,
            "done": True,
        },
        {"spec": "sim:agent=lidar-1", "delivered": 40, "skipped": 0},
    ]
    reports = [{"agent": "robot-a", "time": now, "members": [], "sources": sources}]
    assert format_status(reports).splitlines()[-2:] == [
        "robot-a: source replay:run.log: 160 frames (31 from before a restart), 2 skipped, "
        "read to its end",
        "robot-a: source sim:agent=lidar-1: 40 frames",
    ]
