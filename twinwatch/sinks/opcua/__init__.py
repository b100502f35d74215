"""The twin's health as an OPC UA information model a SCADA reads (asyncua).

The built-in output ``opcua`` (table ``[outputs.opcua]``) serves one read-only object per
machine under ``Objects/TwinWatch`` on ``endpoint`` (docs/opcua-output.md). The machines of a
process naming one endpoint share one server, which runs in its own thread on its own asyncio
loop: :meth:`OpcUaPublisher.write` never waits for a client.

Parts: :mod:`~twinwatch.sinks.opcua.config`, :mod:`~twinwatch.sinks.opcua.model` (the
information model), :mod:`~twinwatch.sinks.opcua.server`, :mod:`~twinwatch.sinks.opcua.publisher`
(the sink), ``_ua`` (asyncua, imported when a server opens).
"""

from __future__ import annotations

from twinwatch.sinks.opcua.config import OpcUaConfig
from twinwatch.sinks.opcua.model import DEVICE_HEALTH, device_health, flat_values
from twinwatch.sinks.opcua.publisher import OpcUaPublisher

__all__ = ["DEVICE_HEALTH", "OpcUaConfig", "OpcUaPublisher", "device_health", "flat_values"]
