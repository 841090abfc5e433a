"""Logging: journald priority prefixes and detection of stderr as the journal."""

from __future__ import annotations

import logging
import os
import sys

from colonyd.logs import JournalFormatter, stderr_is_journal


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


def test_library_start_up_chatter_is_not_logged_at_info(capsys):
    """The daemon's log said "numexpr.utils: NumExpr defaulting to 2 threads." at start."""
    from colonyd.logs import setup_logging

    root = logging.getLogger()
    saved = (list(root.handlers), root.level)
    try:
        setup_logging("info")
        logging.getLogger("numexpr.utils").info("NumExpr defaulting to 2 threads.")
        logging.getLogger("numexpr.utils").warning("a warning still shows")
        logging.getLogger("colonyd.daemon").info("ready")
        err = capsys.readouterr().err
        assert "NumExpr defaulting" not in err
        assert "a warning still shows" in err and "ready" in err
        setup_logging("debug")
        logging.getLogger("numexpr.utils").info("NumExpr defaulting to 2 threads.")
        assert "NumExpr defaulting" in capsys.readouterr().err
    finally:
        root.handlers[:] = saved[0]
        root.setLevel(saved[1])
        logging.getLogger("numexpr").setLevel(logging.NOTSET)
