"""The state database, the pipeline's gate (the built-in output ``store``, table ``[state]``):
the health history and the last accepted twin in one SQLite file. Its parts:

* :mod:`~twinwatch.sinks.store.schema`: the schema version, the tables, ``[state]``;
* :mod:`~twinwatch.sinks.store.database`: :class:`StateStore` (durability, threads and
  faults: its docstring);
* :mod:`~twinwatch.sinks.store.queries`: the read side;
* :mod:`~twinwatch.sinks.store.outbox`: which stored windows a store-and-forward output has
  delivered.
"""

from __future__ import annotations

from twinwatch.errors import StoreError
from twinwatch.sinks.store.database import StateStore
from twinwatch.sinks.store.schema import SCHEMA_VERSION, StateConfig

__all__ = ["SCHEMA_VERSION", "StateConfig", "StateStore", "StoreError"]
