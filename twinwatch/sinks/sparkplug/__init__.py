"""Machine health as Sparkplug B (Eclipse Sparkplug 3.0) for a SCADA such as Ignition.

The built-in output ``sparkplug`` (table ``[outputs.sparkplug]``). The process is an edge node
(``edge_node_id``) of the group ``group_id``, each machine one of its devices (``device_id``):
one MQTT session for every machine of the process naming the same broker, group and edge node,
each machine's windows delivered from its own store-and-forward outbox (docs/sparkplug.md).

Parts: :mod:`.config`, :mod:`.metrics`, :mod:`.session` (the payloads, no I/O), :mod:`.node`
(the edge node: the client and its thread), :mod:`.publisher` (a machine's device).
"""

from twinwatch.sinks.sparkplug.config import SparkplugConfig
from twinwatch.sinks.sparkplug.metrics import MetricSpec, metric_specs, metric_values
from twinwatch.sinks.sparkplug.publisher import SparkplugPublisher
from twinwatch.sinks.sparkplug.session import DeviceSession, EdgeNodeSession

__all__ = [
    "DeviceSession",
    "EdgeNodeSession",
    "MetricSpec",
    "SparkplugConfig",
    "SparkplugPublisher",
    "metric_specs",
    "metric_values",
]
