"""Publishing machine health to an MQTT broker, store-and-forward (paho-mqtt 2.x).

The built-in output ``mqtt`` (table ``[outputs.mqtt]``, a publisher: it gets only the windows
the state database stored). With ``P = {topic_prefix}/{machine}`` it publishes:

* ``P/health``: the health message (the stored text, byte for byte), QoS ``qos`` (1), one per
  window, oldest first;
* ``P/parameters/<name>/{value, deviation_pct, status}``, and ``rul`` / ``rul_warning`` (the
  median time [s] to the alarm / warning threshold, ``parameters.<name>.rul.<level>.rul_s``)
  when the message has a ``rul`` field, and ``alarm`` (the level: ``normal``, ``warning``,
  ``alarm``) for a parameter with an alarm rule: retained, plain text (a number as JSON writes
  it, ``null`` when there is none), the state of the newest stored window for tools that do
  not parse JSON;
* ``P/alarm``: one JSON event per alarm-level change (QoS ``qos``, not retained): the alarm
  evaluator's event when this process estimated the window, else the change read from two
  consecutive stored messages (``"reconstructed": true``);
* ``P/availability``: ``online`` (retained) while connected, ``offline`` when it stops, and
  ``offline`` through the broker's last will when the process dies (SIGKILL, power loss,
  network loss past the keepalive): the MQTT counterpart of Zenoh's liveliness token;
* optional Home Assistant device discovery on ``<discovery prefix>/device/twinwatch_<machine>/
  config`` (retained; sent again when Home Assistant's ``<discovery prefix>/status`` says
  ``online``; an empty retained payload clears it when ``[outputs.mqtt.home_assistant]
  discovery`` is false).

**The delivery contract** (docs/architecture.md, docs/mqtt.md). The state database is the
outbox (:class:`~twinwatch.sinks.base.Outbox`): a window is published only once stored, and is
*delivered* once the broker acknowledged every message it produced (PUBACK for QoS 1, PUBCOMP
for QoS 2); the outbox records that (keyed by output, machine, run and window) in the state
database. After a broker outage and after a restart of the daemon, every stored window not yet
delivered is sent, oldest first, at most ``inflight`` windows unacknowledged at a time and at
most ``rate`` windows a second, for as long as the state database's retention keeps it
(windows it deletes undelivered are counted as ``dropped``). Hence: exactly once when nothing
fails; at least once across a crash (a window acknowledged but not yet recorded is sent again
after the restart) and across a connection lost with windows in flight (paho sends them again
with the DUP flag; with QoS 1 the broker may then deliver a window twice). A repeat is the
stored text again, byte for byte: a subscriber that must not count a window twice drops a
message it has already seen.

Threads: one thread, ``twinwatch-mqtt``, owns the paho client (its network loop, the
reconnection with a capped, jittered backoff, the callbacks) and the outbox's reads and writes
(its own SQLite connection): :meth:`MqttPublisher.write`, called by the window pipeline, only
notes the window's alarm events and wakes it, so a slow or absent broker never holds up the
estimation. paho keeps at most ``inflight`` windows in memory; the rest stay in the state
database (paho's own queue is memory only, and after a reconnect it sends all of it at once,
ignoring its inflight limit: eclipse-paho/paho.mqtt.python#223, #698).

Without a state database (``[state] enabled = false``, or a library daemon without a gate) the
outbox is in memory (the last ``memory_outbox`` windows): a restart loses what was pending.
"""

from twinwatch.sinks.mqtt.config import (
    HomeAssistantConfig,
    MqttConfig,
    MqttConnectionConfig,
    MqttTlsConfig,
)
from twinwatch.sinks.mqtt.encoding import (
    diagnosis_values,
    discovery_payload,
    flat_values,
    ha_device_id,
    reconstructed_events,
)
from twinwatch.sinks.mqtt.outbox import MemoryOutbox
from twinwatch.sinks.mqtt.publisher import MqttPublisher

__all__ = [
    "HomeAssistantConfig",
    "MemoryOutbox",
    "MqttConfig",
    "MqttConnectionConfig",
    "MqttPublisher",
    "MqttTlsConfig",
    "diagnosis_values",
    "discovery_payload",
    "flat_values",
    "ha_device_id",
    "reconstructed_events",
]
