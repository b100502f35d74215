"""The state database's layout: its schema version, its tables and its ``[state]`` table
(:class:`StateConfig`), and what SQLite's errors mean for it (:func:`is_corrupt`)."""

from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import Literal

from pydantic import Field, StrictFloat, StrictInt

from twinwatch.sinks.base import SinkConfig

__all__ = ["CACHE_KIB", "SCHEMA", "SCHEMA_VERSION", "StateConfig", "is_corrupt"]

SCHEMA_VERSION = 1

#: SQLite page cache per connection [KiB] (``PRAGMA cache_size``): the writer appends and the
#: readers page, neither rereads much, and in a fleet every machine has several connections
CACHE_KIB = 256

SCHEMA = """
CREATE TABLE IF NOT EXISTS schema_version (
    version INTEGER NOT NULL,
    applied_wall REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS health (
    id INTEGER PRIMARY KEY,
    machine TEXT NOT NULL,
    run TEXT NOT NULL,
    window INTEGER NOT NULL,
    t_start REAL NOT NULL,
    t_end REAL NOT NULL,
    wall REAL NOT NULL,
    doc TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS health_plant ON health (machine, t_start);
CREATE INDEX IF NOT EXISTS health_wall ON health (machine, wall);
CREATE INDEX IF NOT EXISTS health_run ON health (machine, run, t_start);
CREATE TABLE IF NOT EXISTS twin (
    machine TEXT PRIMARY KEY,
    run TEXT NOT NULL,
    window INTEGER NOT NULL,
    t_end REAL NOT NULL,
    wall REAL NOT NULL,
    state TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS diagnosis (
    machine TEXT PRIMARY KEY,
    run TEXT NOT NULL,
    window INTEGER NOT NULL,
    wall REAL NOT NULL,
    state TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS outbox_position (
    output TEXT NOT NULL,
    machine TEXT NOT NULL,
    health_id INTEGER NOT NULL,
    wall REAL NOT NULL,
    PRIMARY KEY (output, machine)
);
CREATE TABLE IF NOT EXISTS outbox_ack (
    output TEXT NOT NULL,
    machine TEXT NOT NULL,
    run TEXT NOT NULL,
    window INTEGER NOT NULL,
    health_id INTEGER NOT NULL,
    wall REAL NOT NULL,
    PRIMARY KEY (output, machine, run, window)
);
"""


class StateConfig(SinkConfig):
    """``[state]``: the state database (health history and last accepted twin)."""

    enabled: bool = Field(True, description="keep the history and the twin; restore at start")
    path: str = Field("state.sqlite", min_length=1,
                      description="SQLite file, relative to the working directory")
    synchronous: Literal["FULL", "NORMAL"] = Field(
        "FULL", description="FULL fsyncs every window (power-loss safe), NORMAL does not")
    keep_days: StrictFloat = Field(30.0, gt=0, description="delete history older than this [days]")
    keep_rows: StrictInt = Field(1_000_000, ge=1, description="keep at most this many windows")
    recover_corrupt: bool = Field(False, description="move a corrupt database aside and start "
                                  "a new one instead of refusing to start")

    def output_files(self, cwd: Path) -> dict[str, Path]:
        """The database file (its directory must exist and be writable)."""
        path = Path(self.path).expanduser()
        return {"path": path if path.is_absolute() else cwd / path}


def is_corrupt(exc: BaseException) -> bool:
    """SQLite's "database disk image is malformed" / "file is not a database"."""
    msg = str(exc)
    return isinstance(exc, sqlite3.DatabaseError) and ("not a database" in msg
                                                      or "malformed" in msg)
