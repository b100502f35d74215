"""The twin's health as an OPC UA information model a SCADA reads (asyncua).

The built-in output ``opcua`` (table ``[outputs.opcua]``, a publisher: it gets only the windows
the state database stored) serves one read-only object per machine under
``Objects/TwinWatch`` on ``endpoint``. The model, the NE 107 ``DeviceHealth`` mapping
(:func:`device_health`), the Alarms & Conditions events, what clients may do, the threads and
the cost: docs/opcua-output.md. The machines of a process naming one endpoint share one server
(:class:`~twinwatch.sinks.base.SharedResources`); the server runs in its own thread,
``twinwatch-opcua``, on its own asyncio loop, and :meth:`OpcUaPublisher.write` never waits for
a client.

Parts: :mod:`~twinwatch.sinks.opcua.config` (the table), :mod:`~twinwatch.sinks.opcua.model`
(the information model, a window's values), :mod:`~twinwatch.sinks.opcua.server` (the server),
:mod:`~twinwatch.sinks.opcua.publisher` (the sink), ``_ua`` (asyncua, imported when a server
opens).
"""

from __future__ import annotations

from twinwatch.sinks.opcua.config import OpcUaConfig
from twinwatch.sinks.opcua.model import DEVICE_HEALTH, device_health, flat_values
from twinwatch.sinks.opcua.publisher import OpcUaPublisher

__all__ = ["DEVICE_HEALTH", "OpcUaConfig", "OpcUaPublisher", "device_health", "flat_values"]
