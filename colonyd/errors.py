"""Errors raised by the colonyd package."""

from __future__ import annotations


class ColonydError(Exception):
    """Base class of every error raised by the daemon."""


class ConfigError(ColonydError, ValueError):
    """The configuration file, environment or flags are invalid."""


class DuplicateAgentError(ConfigError):
    """Another daemon is alive in the colony with this daemon's agent id."""


class RuntimeSetupError(ColonydError):
    """The Zenoh session could not be opened with the given configuration."""


class PersistenceError(ColonydError):
    """The state directory holds something the daemon cannot read or cannot write to."""


class WireError(ColonydError, ValueError):
    """A message from the network is malformed, oversized or of the wrong version."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


class StatusError(ColonydError):
    """A running colony could not be queried."""


class NoAnswerError(StatusError):
    """No daemon of the colony answered a query (none reachable, or the wrong colony name)."""


class StoppedError(ColonydError):
    """The daemon is stopping: work under way was abandoned."""
