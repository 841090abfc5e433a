"""Errors raised by sensor adapters and data sources."""

from __future__ import annotations


class PluginError(Exception):
    """Base class of every error raised by the plugins package."""


class SensorInputError(PluginError, ValueError):
    """A sensor reading has the wrong shape, type or value."""


class AdapterNotFoundError(PluginError, LookupError):
    """No sensor adapter is registered under the requested name."""


class SourceError(PluginError):
    """A data source (recording, simulated world) cannot be opened or read."""


class SourceSpecError(SourceError, ValueError):
    """A source spec names no known source, or an option it does not take or cannot parse."""


class ParseError(SourceError, ValueError):
    """A recorded file is malformed; the message names the file and line or field."""
