"""The launcher's ports: below the ephemeral range, free, never handed out twice."""

from __future__ import annotations

import socket

from colonyd.bench import launcher


def test_free_ports_come_from_below_the_ephemeral_range_and_are_distinct() -> None:
    floor = launcher._ephemeral_floor()
    ports = [launcher.free_port() for _ in range(50)]
    assert len(set(ports)) == 50
    assert all(launcher.PORT_FLOOR <= p < floor for p in ports)
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", ports[-1]))  # still free to bind


def test_a_port_in_use_is_skipped() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        taken = int(held.getsockname()[1])
        assert not launcher._bindable(taken)
    assert launcher._bindable(taken)
