"""Publishing machine health to an MQTT broker, store-and-forward (paho-mqtt 2.x).

The built-in output ``mqtt`` (table ``[outputs.mqtt]``). With ``P = {topic_prefix}/{machine}``:
``P/health`` (the stored text, byte for byte), ``P/parameters/<name>/...`` (retained plain
values), ``P/alarm``, ``P/availability`` (with the last will) and optional Home Assistant
discovery. The state database is the outbox: exactly once when nothing fails, at least once
across a crash or a lost connection (docs/mqtt.md).

Threads: one thread owns the paho client and the outbox's reads and writes. paho keeps at most
``inflight`` windows in memory, the rest stay in the state database (paho's own queue ignores
its inflight limit after a reconnect: eclipse-paho/paho.mqtt.python#223, #698).
"""

from twinwatch.sinks.mqtt.config import MqttConfig
from twinwatch.sinks.mqtt.encoding import discovery_payload, flat_values
from twinwatch.sinks.mqtt.publisher import MqttPublisher

__all__ = ["MqttConfig", "MqttPublisher", "discovery_payload", "flat_values"]
