"""Logging to stderr, with journald `<N>` priority prefixes when stderr is the journal."""

from __future__ import annotations

import logging
import os
import sys

_PRIORITY = {
    logging.CRITICAL: 2,
    logging.ERROR: 3,
    logging.WARNING: 4,
    logging.INFO: 6,
    logging.DEBUG: 7,
}


def stderr_is_journal() -> bool:
    """True when JOURNAL_STREAM names stderr's device and inode (systemd connected it)."""
    value = os.environ.get("JOURNAL_STREAM", "")
    try:
        dev, ino = (int(x) for x in value.split(":"))
        st = os.fstat(sys.stderr.fileno())
    except (ValueError, OSError, AttributeError):
        return False
    return (st.st_dev, st.st_ino) == (dev, ino)


class JournalFormatter(logging.Formatter):
    """`<N>message`: the journal reads the priority from the prefix and adds its own time."""

    def format(self, record: logging.LogRecord) -> str:
        level = max((lvl for lvl in _PRIORITY if lvl <= record.levelno), default=logging.DEBUG)
        return f"<{_PRIORITY[level]}>{super().format(record)}"


#: Loggers of libraries whose info lines say nothing about the daemon.
QUIET_LIBRARIES = ("numexpr",)


def setup_logging(level: str = "info", *, agent: str | None = None) -> None:
    """Configure the root logger once; the daemon, CLI and tests all use this."""
    handler = logging.StreamHandler(sys.stderr)
    tag = f"[{agent}] " if agent else ""
    if stderr_is_journal():
        handler.setFormatter(JournalFormatter(f"{tag}%(name)s: %(message)s"))
    else:
        handler.setFormatter(
            logging.Formatter(f"%(asctime)s %(levelname)s {tag}%(name)s: %(message)s")
        )
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(getattr(logging, level.upper(), logging.INFO))
    # Libraries' start-up chatter is not the daemon's news ("NumExpr defaulting to 2 threads",
    # logged at info by the first pandas/numexpr import): their warnings still show.
    for name in QUIET_LIBRARIES:  # (all of it with --log-level debug)
        quiet = root.level > logging.DEBUG
        logging.getLogger(name).setLevel(max(logging.WARNING, root.level) if quiet else 0)
