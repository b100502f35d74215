"""The edge node's transport: one paho client and one thread for every machine (device) of the
process that names the same broker, ``group_id`` and ``edge_node_id``.

The node publishes NBIRTH, then each device's DBIRTH and DDATA from the device's own outbox
(each machine's :class:`~twinwatch.sinks.sparkplug.publisher.SparkplugPublisher` keeps its
delivery state), answers rebirths, honours the primary host's STATE, and publishes DDEATH and
NDEATH as devices leave. Every message goes out from the node's thread, so ``seq`` (one count
per edge node) is in the order the broker receives them.
"""

from __future__ import annotations

import contextlib
import json
import logging
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from twinwatch._forward import Forward
from twinwatch.errors import PublisherError
from twinwatch.sinks.mqtt.session import MqttSession, SessionThread
from twinwatch.sinks.sparkplug.config import NAMESPACE, NODE_KEYS, SparkplugConfig, key_clash
from twinwatch.sinks.sparkplug.session import (
    DEVICE_REBIRTH,
    REBIRTH,
    BdSeqFile,
    EdgeNodeSession,
    now_ms,
)
from twinwatch.sinks.sparkplug_pb import payload_class

if TYPE_CHECKING:
    import paho.mqtt.client as mqtt

    from twinwatch.sinks.sparkplug.publisher import SparkplugPublisher

logger = logging.getLogger(__package__)

__all__ = ["EdgeNode"]


class EdgeNode(SessionThread["SparkplugPublisher"]):
    """One Sparkplug edge node: its MQTT session (:class:`MqttSession`) and thread, shared by
    its devices.

    Args:
        config: the first device's table (its :data:`~twinwatch.sinks.sparkplug.config.NODE_KEYS`
            are the session's).
        edge_node_id: the edge node id.
        password: the password read from ``password_file`` (or ``password``), or None.
        directory: where ``bdSeq`` is kept across restarts (:class:`BdSeqFile`); None: not kept.
        machine: the first device's machine (named when another one's settings differ).

    Raises:
        PublisherError: the TLS setup fails.
    """

    def __init__(self, config: SparkplugConfig, edge_node_id: str, password: str | None,
                 directory: Path | None, machine: str) -> None:
        self.config = config
        self.machine = machine
        self.bd_file = (BdSeqFile(directory, config.group_id, edge_node_id)
                        if directory is not None else None)
        self.session = EdgeNodeSession(config.group_id, edge_node_id,
                                       self.bd_file.load() if self.bd_file else None)
        self.state_topic = (f"{NAMESPACE}/STATE/{config.primary_host_id}"
                            if config.primary_host_id else None)
        self.devices: dict[str, SparkplugPublisher] = {}
        self._owners: dict[str, str] = {}  # device id -> machine
        self._lock = threading.Lock()
        self.wake = threading.Event()
        self._stop = threading.Event()
        self.born = False            # NBIRTH sent on this connection (the host online)
        self.births = 0
        self.rebirths = 0
        self.errors = 0
        self._host_online: bool | None = None if config.primary_host_id else True
        self._host_ts = -1
        self._leaving = False        # a disconnection of our own (the primary host offline)
        self.live_since = 0.0        # windows stored before it are replays (historical)
        self._birth_at: float | None = None  # our NBIRTH not yet heard back since (monotonic)
        self._unheard: str | None = None
        self.commands_refused = 0    # NCMD/DCMD metrics other than the rebirth (writes)
        self._refused_said: set[str] = set()
        self._mid_owner: dict[int, SparkplugPublisher] = {}
        self.mqtt = MqttSession(   # the TLS setup checked now
            config, self, table="sparkplug", password=password,
            client_id=(config.client_id
                       or f"twinwatch-sparkplug-{config.group_id}-{edge_node_id}"),
            will=lambda: (self.session.ndeath_topic, self.session.ndeath(now_ms()), False),
            log=logger, paho_log=f"{__name__}.paho", stopping=self._stop.is_set,
            conflict="give each process its own edge node (outputs.sparkplug.edge_node_id) "
                     "or client_id; connecting less often meanwhile")
        self.client_id = self.mqtt.client_id
        self._thread = threading.Thread(target=self._run, daemon=True,
                                        name=f"twinwatch-sparkplug-{edge_node_id}"[:64])
        self._thread.start()

    client: Forward[mqtt.Client] = Forward(
        "mqtt.client", "The session's paho client (a new one at each connection).")
    connects: Forward[int] = Forward("mqtt.connects", "Connections made so far.")
    disconnects: Forward[int] = Forward("mqtt.disconnects", "Connections lost so far.")

    # -- the devices ------------------------------------------------------------------------
    def join(self, device: SparkplugPublisher, config: SparkplugConfig, machine: str) -> None:
        """Add ``device`` (its DBIRTH follows with its first stored window).

        Raises:
            PublisherError: one line naming ``outputs.sparkplug.<key>``: a session key set
                otherwise than by the node's first machine, or a device id already used.
        """
        s = self.session
        where = (f"edge node {s.group_id}/{s.edge_node_id} on {self.config.host}:"
                 f"{self.config.port}")
        for key in NODE_KEYS:
            if getattr(config, key) != getattr(self.config, key):
                raise PublisherError(key_clash(key, machine, where, repr(self.machine)))
        with self._lock:
            owner = self._owners.get(device.device.device_id)
            if owner is not None:
                raise PublisherError(
                    f"outputs.sparkplug.device_id: {device.device.device_id!r} is already "
                    f"machine {owner!r}'s device of {where}; set device_id (unset: the "
                    f"machine name)")
            self.devices[device.device.device_id] = device
            self._owners[device.device.device_id] = machine
        self.wake.set()

    def leave(self, device: SparkplugPublisher) -> None:
        """``device``'s output closes: the node delivers what it has pending for up to its
        ``close_timeout`` and publishes its DDEATH, then sets ``device.left``."""
        device.leave_by = time.monotonic() + device.config.close_timeout
        self.wake.set()
        if not self._thread.is_alive():
            self._retire(device)

    def _retire(self, device: SparkplugPublisher) -> None:
        if device.device_born and self.connected:
            self.client.publish(device.device.ddeath_topic, device.device.ddeath(now_ms()),
                                qos=1)
        device.device_born = False
        device.delivery.finish()
        with self._lock:
            self.devices.pop(device.device.device_id, None)
            self._owners.pop(device.device.device_id, None)
        for mid in [m for m, d in self._mid_owner.items() if d is device]:
            del self._mid_owner[mid]
        device.left.set()

    def close(self) -> None:
        """The last device has left: NDEATH, disconnect, the thread ends."""
        if not self._stop_thread(self.config.connect_timeout + 10):
            logger.warning("the Sparkplug thread of edge node %s did not stop in time",
                           self.session.edge_node_id)

    # -- the client -------------------------------------------------------------------------
    def _connect(self) -> None:
        """A new CONNECT: a new ``bdSeq`` (kept in its file first) in a new client's will. A
        fresh client, not paho's reconnection: paho would send the previous connection's
        unacknowledged messages after our NBIRTH with their old ``seq``; those windows are
        sent again from the devices' outboxes instead, after the births."""
        for d in self._members():
            d.reset_connection()
        self._mid_owner.clear()
        self.born = False
        if self.config.primary_host_id:
            self._host_online = None
        old = self.client
        bd_seq = self.session.new_connection()
        if self.bd_file is not None:
            self.bd_file.save(bd_seq)
        self.mqtt.new_client().connect_async(self.config.host, self.config.port,
                                             keepalive=self.config.keepalive)
        with contextlib.suppress(Exception):
            old._sock_close()  # noqa: SLF001 - a half-open attempt's socket (no public close)
        self.mqtt.attempt()

    def session_refused(self, reason: Any) -> None:
        """A refusal for authorisation names the ACL the node needs, once."""
        if "authori" in str(reason).lower() and self.mqtt.last_error is None:
            logger.error("outputs.sparkplug: the MQTT broker %s refused the connection (%s): "
                         "the client %r must be allowed to connect with its will on %s (the "
                         "NDEATH) and to publish spBv1.0/%s/#; fix the broker's ACL or "
                         "outputs.sparkplug.username", self.mqtt.broker, reason,
                         self.client_id, self.session.ndeath_topic, self.session.group_id)

    def session_up(self, client: mqtt.Client, again: bool) -> None:
        """Connected: subscribe to the commands, the STATE and our NBIRTH; the births when
        the primary host is online."""
        devices = ", ".join(sorted(d.device.device_id for d in self._members()))
        if again:
            logger.warning("MQTT broker %s reached: Sparkplug edge node %s (devices %s) "
                           "publishes again", self.mqtt.broker, self.session.edge_node_id,
                           devices)
        else:
            logger.info("Sparkplug edge node %s/%s on MQTT broker %s (devices %s)",
                        self.session.group_id, self.session.edge_node_id, self.mqtt.broker,
                        devices)
        self.live_since = time.time()
        client.subscribe(self.session.ncmd_topic, qos=1)
        client.subscribe(self.session.dcmd_topics, qos=1)
        client.subscribe(self.session.nbirth_topic, qos=0)  # our own NBIRTH back: _turn_done
        if self.state_topic is not None:
            client.subscribe(self.state_topic, qos=1)
        if self._host_online:
            self._births(client)
        self.wake.set()

    def session_down(self) -> bool:
        """The connection is gone: nothing is born; True when we closed it ourselves (the
        primary host went offline)."""
        self.born = False
        for d in self._members():
            d.device_born = False
        own, self._leaving = self._leaving, False
        return own

    def in_flight(self) -> str:
        """What a lost connection sends again."""
        return "the windows in flight"

    def on_publish(self, client: mqtt.Client | None, userdata: Any, mid: int, reason: Any,
                   properties: Any) -> None:
        """paho's acknowledgement of a DDATA: handed to its device's delivery."""
        device = self._mid_owner.pop(mid, None)
        if device is not None:
            device.delivery.acknowledged(mid)

    def track(self, mid: int, device: SparkplugPublisher) -> None:
        """A DDATA's message id, to hand its acknowledgement to ``device``."""
        self._mid_owner[mid] = device

    # -- births, commands, the primary host -------------------------------------------------
    def _births(self, client: mqtt.Client) -> None:
        """NBIRTH, then the DBIRTH of every device with a stored window (the others' comes
        with their first, not a birth of nulls)."""
        client.publish(self.session.nbirth_topic, self.session.nbirth(now_ms()),
                       qos=self.config.qos)
        if self._birth_at is None and self._unheard is None:
            self._birth_at = time.monotonic()
        self.born = True
        self.births += 1
        for d in self._members():
            d.device_born = False
            if d.latest_doc is not None:
                d.device_birth()

    def on_message(self, client: mqtt.Client, userdata: Any, msg: Any) -> None:
        """NCMD (Node Control/Rebirth), DCMD (Device Control/Rebirth), the primary host's
        STATE, our own NBIRTH back."""
        topic = msg.topic
        if topic == self.session.nbirth_topic:
            if self._unheard is not None:
                logger.warning("outputs.sparkplug: the broker delivers the NBIRTH on %s now",
                               topic)
            self._birth_at = None
            self._unheard = None
            return
        if self.state_topic is not None and topic == self.state_topic:
            self._on_state(client, msg.payload)
            return
        try:
            cmd = payload_class().FromString(msg.payload)
        except Exception:  # noqa: BLE001 - a malformed command is counted and ignored
            self.errors += 1
            logger.warning("a command on %s that is not a Sparkplug B payload: ignored", topic)
            return
        names = {m.name for m in cmd.metrics if m.boolean_value}
        if topic == self.session.ncmd_topic:
            if REBIRTH in names and self._host_online and self.connected:
                logger.info("Sparkplug rebirth asked on %s: NBIRTH and every DBIRTH again",
                            topic)
                self.rebirths += 1
                self._births(client)
            self._refuse_writes(topic, "NCMD", cmd, REBIRTH)
            return
        with self._lock:
            device = self.devices.get(topic.rsplit("/", 1)[-1])
        if DEVICE_REBIRTH in names and device is not None and self.born:
            logger.info("Sparkplug device rebirth asked on %s: its DBIRTH again", topic)
            self.rebirths += 1
            if device.latest_doc is not None:
                device.device_birth()
        self._refuse_writes(topic, "DCMD", cmd, DEVICE_REBIRTH)

    def _refuse_writes(self, topic: str, kind: str, cmd: Any, rebirth: str) -> None:
        """A command's metrics other than the rebirth are a write attempt: nothing is written
        (twinwatch only monitors), counted in ``commands_refused``, logged once per topic."""
        writes = [m.name or f"alias {m.alias}" for m in cmd.metrics if m.name != rebirth]
        if not writes:
            return
        self.commands_refused += 1
        shown = ", ".join(writes[:10]) + (f" and {len(writes) - 10} more"
                                          if len(writes) > 10 else "")
        level = logging.DEBUG if topic in self._refused_said else logging.WARNING
        self._refused_said.add(topic)
        logger.log(level, "outputs.sparkplug: %s %s on %s writes %s: refused, nothing "
                   "written (twinwatch only monitors: it writes to no machine; only %s is "
                   "answered); logged once per topic, counted in sparkplug_commands_refused",
                   "an" if kind == "NCMD" else "a", kind, topic, shown, rebirth)

    def _on_state(self, client: mqtt.Client, payload: bytes) -> None:
        """Sparkplug 3.0 STATE: ``{"online": bool, "timestamp": ms}``; an older timestamp than
        the last one seen is ignored."""
        try:
            state = json.loads(payload)
            online = state["online"]
            stamp = int(state.get("timestamp", 0))
            if not isinstance(online, bool):
                raise ValueError("online is not a boolean")
        except (ValueError, TypeError, KeyError, AttributeError):
            self.errors += 1
            logger.warning("a STATE on %s that is not Sparkplug 3.0's {\"online\": true|false, "
                           "\"timestamp\": ms}: ignored", self.state_topic)
            return
        if stamp < self._host_ts:
            return
        self._host_ts = stamp
        if online and not self._host_online:
            logger.info("primary host %s online: publishing", self.config.primary_host_id)
            self._host_online = True
            self.live_since = time.time()
            self._births(client)
            self.wake.set()
        elif not online and self._host_online:
            logger.warning("primary host %s offline: NDEATH, the windows wait in the outbox "
                           "until it is back", self.config.primary_host_id)
            self._host_online = False
            client.publish(self.session.ndeath_topic, self.session.ndeath(now_ms()), qos=1)
            self._leaving = True
            client.disconnect()
        else:
            self._host_online = online

    def _turn_done(self, now: float) -> None:
        """A connected turn's end: a broker may acknowledge every publish while its ACL drops
        them (MQTT 3.1.1 has no refusal for a publish): our NBIRTH, subscribed to, not heard
        back within 5 s is said once."""
        if self._birth_at is None or self._unheard is not None:
            return
        if time.monotonic() - self._birth_at < 5.0:
            return
        self._unheard = (
            f"outputs.sparkplug: the MQTT broker {self.config.host}:{self.config.port} took "
            f"the NBIRTH on {self.session.nbirth_topic} but did not deliver it back to this "
            f"client (subscribed) in 5 s: its ACL most likely forbids client "
            f"{self.client_id!r} to publish (or to read) spBv1.0/{self.session.group_id}/#, "
            f"and then drops its will (the NDEATH) too; allow both")
        logger.error("%s", self._unheard)

    def problem(self, pending: int) -> str | None:
        """What is degraded in the session (one line), for a device with ``pending``
        windows; None when it works."""
        out = self.mqtt.problems(pending)
        if self._unheard:
            out.append(self._unheard)
        return "; ".join(out) or None

    # -- the thread (a SessionThread of the devices) ----------------------------------------
    def _members(self) -> list[SparkplugPublisher]:
        with self._lock:
            return list(self.devices.values())

    def _failed(self) -> None:
        self.errors += 1
        logger.exception("the Sparkplug edge node %s failed; it goes on in 1 s",
                         self.session.edge_node_id)

    def _ready(self, d: SparkplugPublisher) -> bool:
        """Born at once when it joined with a stored window; fed once the node is born."""
        if self.born and not d.device_born and d.latest_doc is not None:
            d.device_birth()  # a device joined with a stored window: born at once
        return self.born

    def _finish(self) -> None:
        self.mqtt.leave(self.session.ndeath_topic, self.session.ndeath(now_ms()))
        self.born = False
        logger.info("Sparkplug edge node %s/%s closed (NDEATH, bdSeq %d)",
                    self.session.group_id, self.session.edge_node_id,
                    max(self.session.bd_seq, 0))
