"""Every error twinwatch raises on purpose, by the lifecycle phase it belongs to.

Modelled on python-can's ``can/exceptions.py``: one base class, subclasses by phase, and library
errors translated at the boundary with ``raise ... from``. A caller that only wants to know
"twinwatch refused" catches :class:`TwinwatchError`; the command line maps the phases to exit
statuses (a configuration that cannot run here: 78; a start or an operation failure: 1).

Phases::

    TwinwatchError
    ├── ConfigError              loading: the file or a key in it is wrong (ValueError)
    ├── PluginError              a registry name is unknown or its module cannot be imported
    ├── StartError               start: the daemon cannot open a device, a port or a file
    ├── DriverError              a source (twinwatch.drivers, twinwatch.plant)
    │   ├── DriverInitializationError     opening it failed
    │   │   └── DriverConfigError         ... because of its configuration or files
    │   ├── DriverOperationError          reading failed and the driver cannot go on
    │   └── EndOfStream                   a finite source delivered its last sample
    ├── SinkError                an output cannot be opened or used (twinwatch.sinks)
    │   ├── PublisherError                the Zenoh session or a declaration
    │   ├── RecorderError                 the Rerun recording
    │   └── StoreError                    the state database
    ├── LockedError              another process holds a file's lock (also an OSError)
    ├── CommissionError          ``twinwatch identify``: the recording cannot be identified from
    └── WatchError               ``twinwatch watch`` / ``tail``: the Zenoh network is unreachable

Recoverable bad input (a bad frame, a NaN, a gap, a dropped link) is never raised: it is counted,
logged once and survived. This module imports nothing of twinwatch.
"""

from __future__ import annotations

__all__ = [
    "CommissionError",
    "ConfigError",
    "DriverConfigError",
    "DriverError",
    "DriverInitializationError",
    "DriverOperationError",
    "EndOfStream",
    "LockedError",
    "PluginError",
    "PublisherError",
    "RecorderError",
    "SinkError",
    "StartError",
    "StoreError",
    "TwinwatchError",
    "WatchError",
]


class TwinwatchError(Exception):
    """Base class of every error twinwatch raises on purpose."""


# -- loading --------------------------------------------------------------------------------------
class ConfigError(TwinwatchError, ValueError):
    """A configuration that cannot be used; the message names the key and why."""


class PluginError(TwinwatchError, ValueError):
    """A registry name (a driver, a model, a meta-model, a sink) is unknown, or the module that
    provides it cannot be imported; the message lists the known names or says what to install."""


# -- start ----------------------------------------------------------------------------------------
class StartError(TwinwatchError):
    """The daemon cannot start (a device, a port, the recording or the state database); the
    message says what failed and what to do.

    Attributes:
        config_error: the configuration (or a file it names) is at fault, not the machine:
            starting again will not help (``twinwatch run`` exits 78).
    """

    def __init__(self, message: str, *, config_error: bool = False) -> None:
        super().__init__(message)
        self.config_error = config_error


# -- sources --------------------------------------------------------------------------------------
class DriverError(TwinwatchError):
    """Base class of every error a sample source raises."""


class DriverInitializationError(DriverError):
    """The driver could not be opened (device, file, DBC or mapping problem)."""


class DriverConfigError(DriverInitializationError):
    """The driver cannot start because of its configuration or the files it names (a DBC
    without the configured message, a recording without the mapped column, ...): starting
    again will not help (``twinwatch run`` exits 78). The message names the key of its table
    first (``path: ...``)."""

    def keyed(self) -> str:
        """The message with its key as the configuration names it (``driver.path: ...``; a
        message naming no key: ``driver: ...``)."""
        text = str(self)
        head, sep, _ = text.partition(": ")
        if sep and head and " " not in head and not head.startswith("driver"):
            return f"driver.{text}"
        return text if text.startswith("driver") else f"driver: {text}"


class DriverOperationError(DriverError):
    """The driver failed while reading and cannot go on."""


class EndOfStream(DriverError):  # noqa: N818 - mirrors StopIteration, not an error condition
    """A finite source has delivered its last sample."""


# -- outputs --------------------------------------------------------------------------------------
class SinkError(TwinwatchError):
    """An output cannot be opened or used; the message says what to change."""


class PublisherError(SinkError):
    """The zenoh session or one of its declarations could not be created; the message names
    the endpoint involved and what to change in the configuration."""


class RecorderError(SinkError):
    """The recording file cannot be created or written."""


class StoreError(SinkError):
    """The state database cannot be used; the message says what happened and what to do.

    Attributes:
        corrupt: the file is corrupt or not a database (SQLite's SQLITE_CORRUPT/NOTADB).
        detail: SQLite's own message, without the advice.
    """

    def __init__(self, message: str, *, corrupt: bool = False, detail: str = "") -> None:
        super().__init__(message)
        self.corrupt = corrupt
        self.detail = detail or message


class LockedError(TwinwatchError, OSError):
    """Another process holds the lock; the message names the file and, if known, the pid."""


# -- commissioning --------------------------------------------------------------------------------
class CommissionError(TwinwatchError, ValueError):
    """The recording cannot be identified from (the message says why and what to change)."""


# -- watching -------------------------------------------------------------------------------------
class WatchError(TwinwatchError, ValueError):
    """``twinwatch watch`` / ``tail`` cannot reach the Zenoh network (or an endpoint or key is
    malformed); the message names the endpoint and what to change."""
