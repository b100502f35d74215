"""The Sparkplug B output of one machine: a device of its edge node.

Each machine's output keeps the MQTT output's delivery state over its own outbox (the state
database's: which stored windows this output has delivered; the methods of
:class:`~twinwatch.sinks.mqtt.MqttPublisher` that feed, acknowledge and count) and its device's
metrics and aliases; the :class:`~twinwatch.sinks.sparkplug.node.EdgeNode` it joins (one per
broker, group and edge node id in the process, shared through
:class:`~twinwatch.sinks.base.SharedResources`) holds the one MQTT client and the thread that
drives every device's delivery.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from typing import TYPE_CHECKING, Any, ClassVar

from twinwatch.errors import PublisherError
from twinwatch.sinks.base import OutboxRow, SinkContext
from twinwatch.sinks.mqtt.encoding import _view
from twinwatch.sinks.mqtt.outbox import MemoryOutbox, _Window
from twinwatch.sinks.mqtt.publisher import MqttPublisher
from twinwatch.sinks.sparkplug.config import SparkplugConfig, check_id, node_key
from twinwatch.sinks.sparkplug.metrics import metric_specs, metric_values
from twinwatch.sinks.sparkplug.node import EdgeNode
from twinwatch.sinks.sparkplug.session import DeviceSession, now_ms

if TYPE_CHECKING:
    import paho.mqtt.client as mqtt

    from twinwatch.twin.health import HealthView
else:
    from twinwatch._lazy import lazy_module

    mqtt = lazy_module("paho.mqtt.client")

logger = logging.getLogger(__package__)

__all__ = ["SparkplugPublisher"]


class SparkplugPublisher(MqttPublisher):
    """The Sparkplug B output (docs/sparkplug.md): the built-in ``sparkplug``,
    ``[outputs.sparkplug]``; the machine is the device ``device_id`` (unset: its name) of the
    edge node ``edge_node_id`` (unset: its name).

    Args:
        config: the validated table.
        context: the daemon's context (machine, parameters, alarm rules; the gate's outbox;
            ``shared``: the process's edge nodes).

    Raises:
        PublisherError: one line naming ``outputs.sparkplug.<key>``: the machine name is no
            Sparkplug id (and ``device_id`` or ``edge_node_id`` is unset), two metrics differ
            only in case, a TLS or password file cannot be read, the edge node's other
            devices set a session key otherwise, the device id is taken.
    """

    config_class: ClassVar[type[SparkplugConfig]] = SparkplugConfig  # type: ignore[assignment]
    counter_prefix: ClassVar[str | None] = "sparkplug"
    table: ClassVar[str] = "sparkplug"
    client_prefix: ClassVar[str] = "twinwatch-sparkplug"

    config: SparkplugConfig  # type: ignore[assignment]  # the subclass' table

    def __init__(self, config: SparkplugConfig, context: SinkContext) -> None:
        # Not MqttPublisher.__init__: the edge node holds the client and the thread; this
        # object holds what MqttPublisher's delivery methods read and write.
        self._closed = True  # until fully open
        for key, value in (("edge_node_id", config.edge_node_id),
                           ("device_id", config.device_id)):
            if value is None:
                try:
                    check_id(context.machine, "the machine name")
                except ValueError as exc:
                    raise PublisherError(f"outputs.sparkplug.{key}: {exc}; set {key}") from None
        self.config = config
        self.machine = context.machine
        self.model = context.model
        self.parameters = dict(context.parameters)
        self.rules = set(context.alarm_bands)
        self.delivered = 0
        self.pending = 0
        self.errors = 0
        self.device_births = 0
        self.device_born = False
        self.leave_by: float | None = None   # closing: deliver until then (monotonic)
        self.left = threading.Event()        # the node has retired this device
        self._memory: MemoryOutbox | None = (MemoryOutbox(config.memory_outbox)
                                             if context.outbox is None else None)
        self._outbox = None
        self._events: dict[str, list[dict[str, Any]]] = {}
        self._events_lock = threading.Lock()
        self._rebind = threading.Event()
        self._unacked_logged = False
        self._failing_store = False
        self._inflight: dict[int, _Window] = {}
        self._mids: dict[int, int] = {}
        self._acked: list[OutboxRow] = []
        self._position = 0
        self._cursor = 0
        self._latest_doc: HealthView | None = None
        self._previous_levels: dict[str, str] | None = None
        self._discovery_sent: str | None = None
        self._discovery_due: float | None = None
        self._tokens = float(config.inflight)
        self._token_time = time.monotonic()
        password = self._read_password()
        edge = config.edge_node_id or context.machine
        self._shared = context.shared
        self._key = node_key(config, context.machine)
        directory = getattr(self._shared, "directory", None) or context.cwd

        def open_node() -> EdgeNode:
            return EdgeNode(config, edge, password, directory, context.machine)

        node: EdgeNode = (open_node() if self._shared is None
                          else self._shared.acquire(self._key, open_node, EdgeNode.close))
        self._node = node
        try:
            self.client_id = node.client_id
            self._wake = node.wake
            self.device = DeviceSession(node.session, config.device_id or context.machine)
            try:
                self.device.declare(metric_specs(context.parameters, self.rules, None))
            except ValueError as exc:
                raise PublisherError(f"outputs.sparkplug: {exc}; rename a parameter") from None
            self.base = node.session.node_topic % "DDATA"
            self.health_topic = self.device.ddata_topic
            self.availability_topic = node.session.ndeath_topic
            self.discovery_topic = ""
            self.context = context
            self._bind(context)
            node.join(self, config, context.machine)
        except BaseException:
            self._release()
            raise
        self._closed = False

    def _release(self) -> None:
        if self._shared is None:
            self._node.close()
        else:
            self._shared.release(self._key)

    # -- what MqttPublisher's delivery methods read -----------------------------------------
    @property  # type: ignore[override]
    def _connected(self) -> bool:
        """The edge node is connected and born (the host online): DDATA may go out."""
        return self._node.connected and self._node.born

    @_connected.setter
    def _connected(self, value: bool) -> None:
        pass  # the node's

    @property
    def latest_doc(self) -> HealthView | None:
        """The newest stored window of this run's typed message (a DBIRTH's values), or None:
        a new run births with its first window, never with the previous run's last (its run
        id, its alarms, its diagnosis: issue 56), which the outbox holds at a restart."""
        doc = self._latest_doc
        return doc if doc is not None and self._this_run(doc) else None

    def _this_run(self, doc: HealthView) -> bool:
        """``doc`` is of the daemon's run (any, when the context names none)."""
        run = self.context.run if self.context is not None else ""
        return not run or getattr(doc, "run", None) == run

    def rebind_due(self) -> bool:
        """A reload re-bound the output (or the outbox must be read again)."""
        return self._rebind.is_set()

    def reset_connection(self) -> None:
        """A new connection: the windows in flight are sent again from the outbox, after the
        births, with the new connection's ``seq``."""
        self._flush_acks()
        position = self._position_now()
        self._inflight.clear()
        self._mids.clear()
        self._cursor = position
        self.device_born = False

    def finish(self) -> None:
        """Retired by the node: record the deliveries."""
        self._flush_acks()
        self._count()
        if self._memory is not None:
            self.pending = self._memory.count(self._position_now())

    # -- the device's messages (in the node's thread) ----------------------------------------
    def device_birth(self) -> None:
        """DBIRTH: every metric with the newest stored window of this run's values (none yet:
        nulls, e.g. before a previous run's windows the outbox still holds are replayed)."""
        doc = self.latest_doc
        values: dict[str, Any] = {}
        if doc is not None:
            with contextlib.suppress(ValueError):  # named when the window is sent
                self.device.declare(metric_specs(self.parameters, self.rules, doc))
            values = metric_values(doc)
        self._node.client.publish(self.device.dbirth_topic,
                                  self.device.dbirth(values, now_ms()), qos=self.config.qos)
        self.device_born = True
        self.device_births += 1

    def _send(self, row: OutboxRow, newest: bool) -> bool:
        """One window's DDATA (historical when it was stored before this connection's births:
        a replay from the outbox); a metric the birth did not announce (a counter, a RUL
        appearing) makes a new DBIRTH of the device first."""
        try:
            doc = _view(row.doc)
        except ValueError:
            doc = None
        if doc is None:
            self.errors += 1
            self._inflight[row.id] = _Window(row)
            self._on_ack_none(row.id)
            return True
        try:
            grew = self.device.declare(metric_specs(self.parameters, self.rules, doc))
        except ValueError as exc:
            logger.error("outputs.sparkplug: %s; the new metric is left out", exc)
            grew = False
        if self._this_run(doc) and (newest or self.latest_doc is None):
            self._latest_doc = doc
        if grew or not self.device_born:
            self.device_birth()
        node = self._node
        payload = self.device.ddata(metric_values(doc), now_ms(), int(row.wall * 1000),
                                    historical=row.wall < node.live_since)
        info = node.client.publish(self.device.ddata_topic, payload, qos=self.config.qos)
        if info.rc != mqtt.MQTT_ERR_SUCCESS:
            self.errors += 1
            logger.debug("publishing on %s refused: %s", self.device.ddata_topic,
                         mqtt.error_string(info.rc))
            return False
        window = _Window(row)
        window.mids.add(info.mid)
        self._mids[info.mid] = row.id
        self._inflight[row.id] = window
        node.track(info.mid, self)
        if self.config.qos == 0 and info.is_published():
            node._on_publish(node.client, None, info.mid, None, None)
        return True

    def _on_ack_none(self, row_id: int) -> None:
        """A stored row that is no health message: counted delivered (nothing to send)."""
        window = self._inflight.pop(row_id)
        self._acked.append(window.row)

    # -- the sink contract ------------------------------------------------------------------
    def close(self) -> None:
        """Deliver what is pending for up to ``close_timeout`` s, DDEATH, leave the edge node
        (the last device to leave: NDEATH, disconnect). Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._node.leave(self)
        if not self.left.wait(timeout=self.config.close_timeout
                              + self.config.connect_timeout + 10):
            logger.warning("the Sparkplug device %s did not leave its edge node in time",
                           self.device.device_id)
        self._release()
        logger.info("Sparkplug output of %s closed (%d windows delivered, %d pending)",
                    self.machine, self.delivered, self.pending)

    def counters(self) -> dict[str, int]:
        """The MQTT output's (``delivered``, ``pending``, ``dropped``, ``errors``; the edge
        node's ``connects``, ``disconnects``) and ``births`` (the node's NBIRTHs),
        ``device_births`` (this device's DBIRTHs), ``rebirths`` (asked by NCMD or DCMD),
        ``commands_refused`` (the node's NCMD and DCMD that tried to write a metric)."""
        node = self._node
        return {"delivered": int(self.delivered), "pending": int(self.pending),
                "dropped": self.dropped, "connects": int(node.connects),
                "disconnects": int(node.disconnects),
                "errors": int(self.errors + node.errors), "births": int(node.births),
                "device_births": int(self.device_births), "rebirths": int(node.rebirths),
                "commands_refused": int(node.commands_refused)}

    @property
    def births(self) -> int:
        """NBIRTHs of the edge node so far."""
        return self._node.births

    @property
    def problem(self) -> str | None:
        parts = [self._node.problem(self.pending), self._unacknowledged()]
        if self.dropped:
            parts.append(f"Sparkplug: {self.dropped} windows dropped undelivered")
        return "; ".join(p for p in parts if p) or None

    @property
    def status(self) -> str:
        return (f"Sparkplug B on mqtt://{self.config.host}:{self.config.port}/"
                f"{self.device.ddata_topic}")

    def summary(self) -> list[str]:
        line = (f"Sparkplug B was published on {self.device.ddata_topic} (broker "
                f"{self.config.host}:{self.config.port}): {self.delivered} windows delivered, "
                f"{self.device_births} device births")
        if self.pending:
            line += f", {self.pending} pending"
        if self.dropped:
            line += f", {self.dropped} dropped undelivered"
        return [line]

    def __repr__(self) -> str:
        state = ("closed" if self._closed else
                 ("connected" if self._node.connected else "connecting"))
        return (f"SparkplugPublisher({self.device.ddata_topic!r}, {state}, "
                f"delivered={self.delivered})")
