"""Outputs: where every processed window goes (state database, Zenoh, Rerun, plug-ins).

One contract (:class:`~twinwatch.sinks.base.Sink`) and one registry, :data:`SINKS`: a table maps
an output's name to ``"module:Class"``, extended by the entry-point group ``twinwatch.sinks``; a
sink's module is imported only when a configuration uses it. The built-ins keep their historic
top-level tables (``[state]``, ``[zenoh]``, ``[recording]``), every other output is configured
under ``[outputs.<name>]``.

May import :mod:`twinwatch.io`, the twin's top (:mod:`twinwatch.twin.model`,
:mod:`twinwatch.twin.health`, :mod:`twinwatch.twin.adaptation`: the message and the window) and
this room; never the twin's internals, the drivers, the configuration or the daemon.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

from twinwatch.plugins import Registry

if TYPE_CHECKING:
    from twinwatch.sinks.base import Sink

__all__ = ["BUILTIN_SINKS", "ENTRY_POINT_GROUP", "HISTORIC_TABLES", "SINKS", "output_key",
           "sink_class"]

#: Entry-point group through which other packages add outputs.
ENTRY_POINT_GROUP = "twinwatch.sinks"

#: Built-in outputs: name => "module:Class", in the order each window is written to them (the
#: gate, the state store, is written first whatever its place: stored before published).
BUILTIN_SINKS: Mapping[str, str] = {
    "store": "twinwatch.sinks.store:StateStore",
    "zenoh": "twinwatch.sinks.zenoh:HealthPublisher",
    "rerun": "twinwatch.sinks.rerun:RerunRecorder",
    "mqtt": "twinwatch.sinks.mqtt:MqttPublisher",
    "sparkplug": "twinwatch.sinks.sparkplug:SparkplugPublisher",
    "opcua": "twinwatch.sinks.opcua:OpcUaPublisher",
}


#: The built-ins configured in their historic top-level tables.
HISTORIC_TABLES: Mapping[str, str] = {"store": "state", "zenoh": "zenoh", "rerun": "recording"}


def output_key(name: str) -> str:
    """The dotted path of the table that configures the output ``name`` (``"state"``,
    ``"outputs.mqtt"``)."""
    return HISTORIC_TABLES.get(name) or f"outputs.{name}"


def _base() -> type[Sink]:
    from twinwatch.sinks.base import Sink

    return Sink


#: The output registry (:class:`twinwatch.plugins.Registry`): the built-ins and the entry points.
SINKS: Registry[Sink] = Registry("output", ENTRY_POINT_GROUP, BUILTIN_SINKS, base=_base)


def sink_class(name: str) -> type[Sink]:
    """Import and return the output registered as ``name``.

    Raises:
        twinwatch.errors.PluginError: no output has that name (the message lists the known
            ones), or its module cannot be imported (the message says what to install).
    """
    return SINKS.load(name)
