"""The base of every configuration table: :class:`StrictTable` (the ground room: it imports
nothing of twinwatch, so that every room can derive its tables from it)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class StrictTable(BaseModel):
    """A configuration table (a TOML table validated by pydantic) that refuses unknown keys
    (``extra="forbid"``): a misspelt key is an error naming it, not a setting silently ignored.
    Every table of the configuration (and of a plug-in's) derives from it; a table that needs
    more settings adds them in its own ``model_config``, which pydantic merges with this one.
    """

    model_config = ConfigDict(extra="forbid")
