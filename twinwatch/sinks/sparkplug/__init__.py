"""Machine health as Sparkplug B (Eclipse Sparkplug 3.0) for a SCADA such as Ignition.

The built-in output ``sparkplug`` (table ``[outputs.sparkplug]``, a publisher: it gets only the
windows the state database stored). The process is an **edge node** ``E`` (``edge_node_id``) of
the group ``G`` (``group_id``) and each machine that names it one of its **devices** ``D``
(``device_id``, by default the machine name): one MQTT session (one paho client, one NDEATH
will) for every machine of the process naming the same broker, group and edge node
(:class:`~twinwatch.sinks.base.SharedResources`, as the gateway shares a Zenoh session), each
machine's windows delivered from its own store-and-forward outbox (the MQTT output's delivery
contract, docs/architecture.md). Topics and payloads (Eclipse Tahu's protobuf,
:mod:`twinwatch.sinks.sparkplug_pb`):

* ``spBv1.0/G/NBIRTH/E``: on every connection (and rebirth): ``seq`` 0, the metric ``bdSeq``
  (Int64) and ``Node Control/Rebirth`` (Boolean, false);
* ``spBv1.0/G/DBIRTH/E/D``: right after (or with the device's first stored window, or when a
  reload adds the machine), every device metric (:func:`metric_specs`) with its name, alias,
  datatype, the newest stored window's value and its unit as the property ``engUnit``;
* ``spBv1.0/G/DDATA/E/D``: one per stored window, every metric by alias only (with the time the
  window was stored); a window replayed from the outbox (stored before this connection's
  births: a broker outage, a restart, the primary host away) has ``is_historical`` true on
  each metric;
* ``spBv1.0/G/DDEATH/E/D`` when the machine's output closes (a clean stop, a reload that
  removes the machine), then, once the last device has left, ``spBv1.0/G/NDEATH/E``; the NDEATH
  with the connection's ``bdSeq`` is also the MQTT will, which the broker publishes when the
  process dies;
* ``seq`` counts every NBIRTH, DBIRTH, DDATA and DDEATH of the edge node, whichever device, 0
  to 255 and round again, from 0 at each NBIRTH (every message goes out from the node's one
  thread, in ``seq`` order); ``bdSeq`` counts the connections (each CONNECT's will), 0 to 255,
  kept across restarts in ``sparkplug-<G>-<E>.bdseq`` (the host's working directory);
* an ``NCMD`` ``Node Control/Rebirth`` is answered with a new NBIRTH and every DBIRTH; a
  ``DCMD`` ``Device Control/Rebirth`` with that device's DBIRTH (other commands are ignored:
  twinwatch only monitors);
* with ``primary_host_id`` set, nothing is published before the primary host application's
  ``spBv1.0/STATE/<primary_host_id>`` says ``{"online": true, ...}``; when it says ``false``
  the edge node publishes NDEATH, disconnects and waits for it again.

QoS: Sparkplug 3.0 asks QoS 0 for births and data; the default here is 1, the acknowledgement
the outbox's at-least-once delivery rests on (``qos = 0``: as the specification says, a window
then counts delivered once written to the socket).

Parts: :mod:`.config` (the table), :mod:`.metrics` (a message's metrics), :mod:`.session` (the
payloads, ``seq``, ``bdSeq`` and its file; no I/O), :mod:`.node` (the edge node: the client and
its thread), :mod:`.publisher` (a machine's output: its device and outbox).
"""

from twinwatch.sinks.sparkplug.config import NAMESPACE, SparkplugConfig, node_key
from twinwatch.sinks.sparkplug.metrics import MetricSpec, metric_specs, metric_values
from twinwatch.sinks.sparkplug.node import EdgeNode
from twinwatch.sinks.sparkplug.publisher import SparkplugPublisher
from twinwatch.sinks.sparkplug.session import BdSeqFile, DeviceSession, EdgeNodeSession

__all__ = [
    "NAMESPACE",
    "BdSeqFile",
    "DeviceSession",
    "EdgeNode",
    "EdgeNodeSession",
    "MetricSpec",
    "SparkplugConfig",
    "SparkplugPublisher",
    "metric_specs",
    "metric_values",
    "node_key",
]
