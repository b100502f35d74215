"""A library's log records from one of twinwatch's threads, demoted to DEBUG: the thread's
owner reports what matters itself (an outage once, at ERROR; the recovery at WARNING; a refusal
in one line). Shared by the Modbus and OPC UA drivers and the simulated OPC UA server."""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterable

__all__ = ["demote_thread_records"]


class _Demote(logging.Filter):
    def __init__(self, prefix: str, top: int) -> None:
        super().__init__()
        self.prefix, self.top = prefix, top

    def filter(self, record: logging.LogRecord) -> bool:
        if (logging.DEBUG < record.levelno < self.top
                and threading.current_thread().name.startswith(self.prefix)):
            # the logger's level check has passed at the record's original level: redo it
            if not logging.getLogger(record.name).isEnabledFor(logging.DEBUG):
                return False
            record.levelno, record.levelname = logging.DEBUG, "DEBUG"
        return True


def demote_thread_records(prefix: str, loggers: Iterable[str], *,
                          critical: bool = False) -> None:
    """From now on, the records each of ``loggers`` emits itself (a logger's filter sees only
    its own) from a thread whose name starts with ``prefix`` are DEBUG records; CRITICAL ones
    too when ``critical``, else they stay. Idempotent."""
    top = logging.CRITICAL + 1 if critical else logging.CRITICAL
    for name in loggers:
        log = logging.getLogger(name)
        if not any(isinstance(f, _Demote) and f.prefix == prefix for f in log.filters):
            log.addFilter(_Demote(prefix, top))
