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
