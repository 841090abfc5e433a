"""sd_notify datagrams and journald priority prefixes."""

from __future__ import annotations

import logging
import os
import socket
import sys

from colonyd.logs import JournalFormatter, stderr_is_journal
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


def test_journal_prefix_and_detection(monkeypatch):
    rec = logging.LogRecord("x", logging.WARNING, __file__, 1, "careful", None, None)
    assert JournalFormatter("%(message)s").format(rec) == "<4>careful"
    rec = logging.LogRecord("x", logging.ERROR, __file__, 1, "bad", None, None)
    assert JournalFormatter("%(message)s").format(rec) == "<3>bad"
    st = os.fstat(sys.stderr.fileno())
    monkeypatch.setenv("JOURNAL_STREAM", f"{st.st_dev}:{st.st_ino}")
    assert stderr_is_journal()
    monkeypatch.setenv("JOURNAL_STREAM", "1:2")
    assert not stderr_is_journal()
