"""sd_notify datagrams: ready, watchdog and stopping, and a no-op without a socket."""

from __future__ import annotations

import os
import socket

from colonyd.notify import Notifier


def test_notify_sends_datagrams(tmp_path, monkeypatch):
    path = str(tmp_path / "notify.sock")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(path)
        monkeypatch.setenv("WATCHDOG_USEC", "4000000")
        monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
        n = Notifier(path)
        assert n.watchdog_s == 4.0
        assert n.ready("up")
        assert sock.recv(256) == b"READY=1\nSTATUS=up"
        assert n.watchdog() and sock.recv(256) == b"WATCHDOG=1"
        assert n.stopping() and sock.recv(256) == b"STOPPING=1"


def test_notify_without_socket_is_a_no_op(monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    monkeypatch.delenv("WATCHDOG_USEC", raising=False)
    n = Notifier()
    assert not n.ready() and n.watchdog_s is None
