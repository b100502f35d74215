"""The state database, the pipeline's gate (the built-in output ``store``, table ``[state]``):
the health history and the last accepted twin in one SQLite file. Its parts:

* :mod:`~twinwatch.sinks.store.schema`: the schema version, the tables, ``[state]``
  (:class:`StateConfig`);
* :mod:`~twinwatch.sinks.store.database`: :class:`StateStore`, a connection per thread, the
  file lock, recovery from a corrupt, deleted or replaced file, the write path and its
  in-memory backlog (durability, threads and faults: its docstring);
* :mod:`~twinwatch.sinks.store.queries`: the read side, functions over one connection
  (history and its paging cursor, the time line, the latest message, a run's last ones);
* :mod:`~twinwatch.sinks.store.outbox`: :class:`.outbox.StoreOutbox`, which stored windows a
  store-and-forward output has delivered.
"""

from __future__ import annotations

from twinwatch.errors import StoreError
from twinwatch.sinks.store.database import StateStore
from twinwatch.sinks.store.schema import SCHEMA_VERSION, StateConfig

__all__ = ["SCHEMA_VERSION", "StateConfig", "StateStore", "StoreError"]
