"""Machine health as Sparkplug B (Eclipse Sparkplug 3.0) for a SCADA such as Ignition.

The built-in output ``sparkplug`` (table ``[outputs.sparkplug]``, a publisher: it gets only the
windows the state database stored). It is the MQTT output's transport and store-and-forward
outbox (:class:`~twinwatch.sinks.mqtt.MqttPublisher`: the connection, the reconnection, the
outbox, the delivery contract of docs/architecture.md) with Sparkplug B's topics, payloads
(Eclipse Tahu's protobuf, :mod:`twinwatch.sinks.sparkplug_pb`) and session state instead of
JSON. With ``G`` the ``group_id``, ``E`` the ``edge_node_id`` and ``D`` the ``device_id`` (by
default both the machine name), the daemon is the edge node ``E`` and the machine its device
``D``:

* ``spBv1.0/G/NBIRTH/E``: on every connection (and rebirth): ``seq`` 0, the metric ``bdSeq``
  (Int64) and ``Node Control/Rebirth`` (Boolean, false);
* ``spBv1.0/G/DBIRTH/E/D``: right after, every device metric (:func:`metric_specs`) with its
  name, alias, datatype, the newest stored window's value and its unit as the property
  ``engUnit``;
* ``spBv1.0/G/DDATA/E/D``: one per stored window, every metric by alias only (with the time the
  window was stored); a window replayed from the outbox (stored before this connection's
  births: a broker outage, a restart, the primary host away) has ``is_historical`` true on
  each metric (the DBIRTH carries the newest window's values as the current ones);
* ``spBv1.0/G/DDEATH/E/D`` then ``spBv1.0/G/NDEATH/E`` on a clean stop (and when a reload
  removes the machine); ``NDEATH`` with the connection's ``bdSeq`` is also the MQTT will, which
  the broker publishes when the daemon dies;
* ``seq`` counts every NBIRTH, DBIRTH, DDATA and DDEATH of the edge node, 0 to 255 and round
  again, from 0 at each NBIRTH; ``bdSeq`` counts the connections (each CONNECT's will), 0 to
  255;
* an ``NCMD`` on ``spBv1.0/G/NCMD/E`` with ``Node Control/Rebirth`` true is answered with a new
  NBIRTH and DBIRTH;
* with ``primary_host_id`` set, nothing is published before the primary host application's
  ``spBv1.0/STATE/<primary_host_id>`` says ``{"online": true, ...}``; when it says ``false``
  the edge node publishes NDEATH, disconnects and waits for it again (windows wait in the
  outbox meanwhile).

What this version does not do: several machines under one edge node (each machine is its own
edge node: ``edge_node_id`` unset is the machine name); ``bdSeq`` starts at 0 at each start of
the daemon (not kept across restarts); DCMD (the device takes no commands: twinwatch only
monitors). QoS: Sparkplug 3.0 asks QoS 0 for births and data; the default here is 1, the
acknowledgement the outbox's at-least-once delivery rests on (``qos = 0``: as the specification
says, a window then counts delivered once written to the socket).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Literal

from pydantic import Field, field_validator

from twinwatch.errors import PublisherError
from twinwatch.sinks.base import OutboxRow, SinkContext
from twinwatch.sinks.mqtt.config import MqttConnectionConfig
from twinwatch.sinks.mqtt.encoding import _std, _view, diagnosis_values
from twinwatch.sinks.mqtt.outbox import _Window
from twinwatch.sinks.mqtt.publisher import MqttPublisher
from twinwatch.sinks.sparkplug_pb import DATATYPE, payload_class

if TYPE_CHECKING:
    import paho.mqtt.client as mqtt

    from twinwatch.twin.health import HealthView
else:
    from twinwatch._lazy import lazy_module

    mqtt = lazy_module("paho.mqtt.client")

logger = logging.getLogger(__name__)

__all__ = [
    "NAMESPACE",
    "MetricSpec",
    "SparkplugConfig",
    "SparkplugPublisher",
    "SparkplugSession",
    "metric_specs",
    "metric_values",
]

NAMESPACE = "spBv1.0"
REBIRTH = "Node Control/Rebirth"
BDSEQ = "bdSeq"
_ALARM_LEVEL = {"normal": 0, "warning": 1, "alarm": 2}


def _check_id(value: str, what: str) -> str:
    """A Sparkplug id (group, edge node, device, host): one MQTT topic level, UTF-8, without
    ``/``, ``+``, ``#`` (Sparkplug 3.0, 1.4.1.8: the MQTT topic rules)."""
    bad = [c for c in ("/", "+", "#", "\x00") if c in value]
    if not value or bad:
        raise ValueError(f"{what} {value!r} must be one non-empty topic level: no "
                         f"{', '.join(repr(c) for c in bad) or 'empty value'} (Sparkplug ids "
                         f"are MQTT topic levels without '/', '+', '#')")
    if len(value.encode("utf-8")) > 1000:
        raise ValueError(f"{what} is longer than 1000 bytes")
    return value


class SparkplugConfig(MqttConnectionConfig):
    """``[outputs.sparkplug]``: the Sparkplug B output (see the module docstring).

    Example::

        [outputs.sparkplug]
        host = "127.0.0.1"
        port = 1883
        group_id = "plant1"             # spBv1.0/plant1/DDATA/<edge node>/<machine>
        edge_node_id = "line3-edge"     # unset: the machine name
        primary_host_id = "ignition"    # wait for spBv1.0/STATE/ignition online
    """

    client_id: str | None = Field(None, min_length=1, max_length=128,
                                  description="unique per broker; unset: "
                                  "twinwatch-sparkplug-<machine>")
    qos: Literal[0, 1] = Field(  # type: ignore[assignment]  # Sparkplug allows 0, not 2
        1, description="1: each window acknowledged (the outbox's delivery); 0: as Sparkplug "
        "3.0 says for births and data")
    group_id: str = Field("twinwatch", description="the Sparkplug group id (a topic level)")
    edge_node_id: str | None = Field(None, description="the edge node id; unset: the machine "
                                     "name")
    device_id: str | None = Field(None, description="the machine's device id; unset: the "
                                  "machine name")
    primary_host_id: str | None = Field(None, description="wait for this primary host "
                                        "application's STATE online before publishing; unset: "
                                        "do not wait")

    @field_validator("group_id", "edge_node_id", "device_id", "primary_host_id")
    @classmethod
    def _ids(cls, value: str | None) -> str | None:
        return None if value is None else _check_id(value, "the id")

    def exclusive_resources(self, cwd: Path) -> set[str]:
        """The client id and the edge node at the broker (a second session of one edge node
        would take its births and deaths over)."""
        return {f"mqtt://{self.host}:{self.port}/{self.client_id or ''}",
                f"sparkplug://{self.host}:{self.port}/{self.group_id}/"
                f"{self.edge_node_id or ''}"}


# -- the metrics --------------------------------------------------------------------------------
@dataclass(frozen=True)
class MetricSpec:
    """One device metric as the birth announces it.

    Attributes:
        name: the metric's name (``/`` makes the folders Ignition shows:
            ``Parameters/Ra/Value``).
        datatype: the Sparkplug B data type's name (``Double``, ``Int64``, ``String``, ...).
        unit: its engineering unit (the ``engUnit`` property), or "".
    """

    name: str
    datatype: str
    unit: str = ""


def metric_specs(parameters: Mapping[str, str], rules: set[str], doc: HealthView | None,
                 *, diagnosis: bool = True) -> list[MetricSpec]:
    """The device's metrics for a machine.

    Args:
        parameters: parameter name -> SI unit (the twin's, in order).
        rules: the parameters with an ``[alarms]`` rule (their alarm level and RUL metrics).
        doc: the newest health message's typed view, or None: adds what it carries beyond the
            configuration (a parameter, an alarm, a ``rul`` field, its counters).
        diagnosis: announce the diagnosis' metrics (with ``doc``: whether it has one).

    Returns:
        The metrics in order: ``Window/*``; per parameter ``Value``, ``Low``, ``High`` (the
        2-sigma interval, unit of the value), ``Deviation`` [%], ``Status``, and with an alarm
        rule ``Alarm`` (text), ``Alarm Level`` (0 normal, 1 warning, 2 alarm), ``RUL`` and
        ``RUL Warning`` [s]; ``Diagnosis/*``; ``Counters/<name>``.
    """
    from twinwatch.twin.health import sent

    params = dict(parameters)
    doc_params = (doc.parameters if doc is not None else None) or {}
    for name, p in doc_params.items():
        params.setdefault(name, str(p.unit or ""))
    alarms = set(rules) | set((doc.alarms if doc is not None else None) or {})
    out = [MetricSpec("Window/Index", "Int64"), MetricSpec("Window/Start", "Double", "s"),
           MetricSpec("Window/End", "Double", "s"), MetricSpec("Window/Trusted", "Boolean"),
           MetricSpec("Window/NRMSE", "Double"), MetricSpec("Window/Run", "String")]
    for name, unit in params.items():
        base = f"Parameters/{name}"
        out += [MetricSpec(f"{base}/Value", "Double", unit),
                MetricSpec(f"{base}/Low", "Double", unit),
                MetricSpec(f"{base}/High", "Double", unit),
                MetricSpec(f"{base}/Deviation", "Double", "%"),
                MetricSpec(f"{base}/Status", "String")]
        if name in alarms or (name in doc_params and sent(doc_params[name], "rul")):
            out += [MetricSpec(f"{base}/Alarm", "String"),
                    MetricSpec(f"{base}/Alarm Level", "Int32"),
                    MetricSpec(f"{base}/RUL", "Double", "s"),
                    MetricSpec(f"{base}/RUL Warning", "Double", "s")]
    if diagnosis if doc is None else doc.diagnosis is not None:
        out += [MetricSpec("Diagnosis/Status", "String"), MetricSpec("Diagnosis/Fault", "String"),
                MetricSpec("Diagnosis/Probability", "Double", "%"),
                MetricSpec("Diagnosis/Action", "String")]
    for name in sorted((doc.counters if doc is not None else None) or {}):
        out.append(MetricSpec(f"Counters/{name}", "Int64"))
    return out


def _num(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(value) else None


def metric_values(doc: HealthView) -> dict[str, Any]:
    """The device metrics' values of one health message (its typed view): metric name ->
    value (None: null). The names of :func:`metric_specs`."""
    out: dict[str, Any] = {
        "Window/Index": doc.window, "Window/Start": _num(doc.t_start),
        "Window/End": _num(doc.t_end), "Window/Trusted": doc.trusted,
        "Window/NRMSE": _num(doc.nrmse), "Window/Run": doc.run}
    alarms = doc.alarms or {}
    for name, p in (doc.parameters or {}).items():
        base = f"Parameters/{name}"
        value = _num(p.value)
        std = _std(value, p.rel_std_pct)
        out[f"{base}/Value"] = value
        out[f"{base}/Low"] = value - 2 * std if value is not None and std else None
        out[f"{base}/High"] = value + 2 * std if value is not None and std else None
        out[f"{base}/Deviation"] = _num(p.deviation_pct)
        out[f"{base}/Status"] = None if p.status is None else str(p.status)
        a = alarms.get(name)
        level = str(a.level or "normal") if a is not None else None
        out[f"{base}/Alarm"] = level
        out[f"{base}/Alarm Level"] = _ALARM_LEVEL.get(level) if level is not None else None
        rul = p.rul
        alarm = rul.alarm if rul is not None else None
        warning = rul.warning if rul is not None else None
        out[f"{base}/RUL"] = _num(alarm.rul_s) if alarm is not None else None
        out[f"{base}/RUL Warning"] = _num(warning.rul_s) if warning is not None else None
    if doc.diagnosis is not None:
        flat = diagnosis_values(doc.diagnosis)
        out["Diagnosis/Status"] = str(doc.diagnosis.status or "no_fault")
        out["Diagnosis/Fault"] = flat["diagnosis/fault"]
        out["Diagnosis/Probability"] = _num(json.loads(flat["diagnosis/probability"]))
        out["Diagnosis/Action"] = flat["diagnosis/action"]
    for name, count in (doc.counters or {}).items():
        out[f"Counters/{name}"] = count if isinstance(count, int) else None
    return out


def _set_value(metric: Any, datatype: str, value: Any) -> None:
    """A metric's value by its data type (Sparkplug B: signed integers in the unsigned fields
    as two's complement), or ``is_null``."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        metric.is_null = True
    elif datatype == "Double":
        metric.double_value = float(value)
    elif datatype == "Int32":
        metric.int_value = int(value) & 0xFFFFFFFF
    elif datatype == "Int64":
        metric.long_value = int(value) & 0xFFFFFFFFFFFFFFFF
    elif datatype == "Boolean":
        metric.boolean_value = bool(value)
    else:
        metric.string_value = str(value)


# -- the edge node's session ---------------------------------------------------------------------
class SparkplugSession:
    """An edge node with one device: its topics, ``seq``, ``bdSeq``, aliases and the payloads
    (no I/O: :class:`SparkplugPublisher` publishes them; used alone by the benchmark).

    Args:
        group_id, edge_node_id, device_id: the Sparkplug ids (checked topic levels).

    Raises:
        ValueError: two metric names that differ only in case (a SCADA's tag paths, Ignition's
            among them, are case-insensitive).
    """

    def __init__(self, group_id: str, edge_node_id: str, device_id: str) -> None:
        self.group_id = group_id
        self.edge_node_id = edge_node_id
        self.device_id = device_id
        node = f"{NAMESPACE}/{group_id}/%s/{edge_node_id}"
        self.nbirth_topic = node % "NBIRTH"
        self.ndeath_topic = node % "NDEATH"
        self.ncmd_topic = node % "NCMD"
        self.dbirth_topic = f"{node % 'DBIRTH'}/{device_id}"
        self.ddata_topic = f"{node % 'DDATA'}/{device_id}"
        self.ddeath_topic = f"{node % 'DDEATH'}/{device_id}"
        self.bd_seq = -1            # the first connection is 0
        self.seq = 0
        self.specs: dict[str, MetricSpec] = {}
        self.aliases: dict[str, int] = {}
        self._payload = payload_class()

    def new_connection(self) -> int:
        """A new MQTT CONNECT: the next ``bdSeq`` (0..255), for its will and NBIRTH."""
        self.bd_seq = (self.bd_seq + 1) % 256
        return self.bd_seq

    def declare(self, specs: list[MetricSpec]) -> bool:
        """Add ``specs`` to the device's metrics (never removes one: a birth announces them
        all); True when one is new (a birth is then due)."""
        new = False
        for spec in specs:
            if spec.name in self.specs:
                continue
            folded = spec.name.casefold()
            clash = next((n for n in self.specs if n.casefold() == folded), None)
            if clash is not None:
                raise ValueError(f"the metrics {clash!r} and {spec.name!r} differ only in case: "
                                 f"a SCADA's tag paths do not tell them apart")
            self.specs[spec.name] = spec
            self.aliases[spec.name] = len(self.aliases) + 1
            new = True
        return new

    def _next_seq(self) -> int:
        seq = self.seq
        self.seq = (self.seq + 1) % 256
        return seq

    def _message(self, seq: int | None, now_ms: int) -> Any:
        p = self._payload()
        p.timestamp = now_ms
        if seq is not None:
            p.seq = seq
        return p

    def nbirth(self, now_ms: int) -> bytes:
        """NBIRTH: ``seq`` 0 (the count starts again), ``bdSeq``, ``Node Control/Rebirth``."""
        self.seq = 0
        p = self._message(self._next_seq(), now_ms)
        m = p.metrics.add(name=BDSEQ, timestamp=now_ms, datatype=DATATYPE["Int64"])
        m.long_value = self.bd_seq
        m = p.metrics.add(name=REBIRTH, timestamp=now_ms, datatype=DATATYPE["Boolean"])
        m.boolean_value = False
        return bytes(p.SerializeToString())

    def ndeath(self, now_ms: int) -> bytes:
        """NDEATH (the will, and on a clean stop): ``bdSeq`` only, no ``seq``."""
        p = self._message(None, now_ms)
        m = p.metrics.add(name=BDSEQ, timestamp=now_ms, datatype=DATATYPE["Int64"])
        m.long_value = max(self.bd_seq, 0)
        return bytes(p.SerializeToString())

    def dbirth(self, values: Mapping[str, Any], now_ms: int, ts_ms: int | None = None) -> bytes:
        """DBIRTH: every declared metric with name, alias, datatype, ``engUnit`` and its value
        in ``values`` (missing: null)."""
        p = self._message(self._next_seq(), now_ms)
        for name, spec in self.specs.items():
            m = p.metrics.add(name=name, alias=self.aliases[name], timestamp=ts_ms or now_ms,
                              datatype=DATATYPE[spec.datatype])
            if spec.unit:
                m.properties.keys.append("engUnit")
                m.properties.values.add(type=DATATYPE["String"], string_value=spec.unit)
            _set_value(m, spec.datatype, values.get(name))
        return bytes(p.SerializeToString())

    def ddata(self, values: Mapping[str, Any], now_ms: int, ts_ms: int,
              historical: bool = False) -> bytes:
        """DDATA: the declared metrics of ``values`` by alias (a name not declared is left
        out: declare it and send a birth first)."""
        p = self._message(self._next_seq(), now_ms)
        specs, aliases = self.specs, self.aliases
        for name, value in values.items():
            spec = specs.get(name)
            if spec is None:
                continue
            m = p.metrics.add(alias=aliases[name], timestamp=ts_ms)
            if historical:
                m.is_historical = True
            _set_value(m, spec.datatype, value)
        return bytes(p.SerializeToString())

    def ddeath(self, now_ms: int) -> bytes:
        """DDEATH: the device is gone (``seq`` only)."""
        return bytes(self._message(self._next_seq(), now_ms).SerializeToString())


def _now_ms() -> int:
    return int(time.time() * 1000)


# -- the output ---------------------------------------------------------------------------------
class SparkplugPublisher(MqttPublisher):
    """The Sparkplug B output (see the module docstring): the built-in ``sparkplug``,
    ``[outputs.sparkplug]``.

    Args:
        config: the validated table.
        context: the daemon's context (machine, parameters, alarm rules; the gate's outbox).

    Raises:
        PublisherError: the machine name is no Sparkplug id (and ``device_id`` or
            ``edge_node_id`` is unset), a TLS or password file cannot be read.
    """

    config_class: ClassVar[type[SparkplugConfig]] = SparkplugConfig  # type: ignore[assignment]
    counter_prefix: ClassVar[str | None] = "sparkplug"
    table: ClassVar[str] = "sparkplug"
    client_prefix: ClassVar[str] = "twinwatch-sparkplug"

    config: SparkplugConfig  # type: ignore[assignment]  # the subclass' table

    def __init__(self, config: SparkplugConfig, context: SinkContext) -> None:
        for key, value in (("edge_node_id", config.edge_node_id),
                           ("device_id", config.device_id)):
            if value is None:
                try:
                    _check_id(context.machine, "the machine name")
                except ValueError as exc:
                    raise PublisherError(f"outputs.sparkplug.{key}: {exc}; set {key}") from None
        self.session = SparkplugSession(config.group_id, config.edge_node_id or context.machine,
                                        config.device_id or context.machine)
        self.rules = set(context.alarm_bands)
        try:
            self.session.declare(metric_specs(context.parameters, self.rules, None))
        except ValueError as exc:
            raise PublisherError(f"outputs.sparkplug: {exc}; rename a parameter") from None
        self.births = 0
        self.device_births = 0
        self.rebirths = 0
        self._born = False          # NBIRTH sent on this connection
        self._device_born = False   # DBIRTH sent since the NBIRTH
        self._host_online: bool | None = None if config.primary_host_id else True
        self._host_ts = -1
        self._leaving = False   # a disconnection of our own (the primary host went offline)
        self._live_since = 0.0  # windows stored before it are replays (historical)
        self._birth_at: float | None = None  # our NBIRTH not yet heard back since (monotonic)
        self._unheard: str | None = None     # the line when it never came back
        super().__init__(config, context)  # type: ignore[arg-type]  # shares its transport

    def _topics(self, context: SinkContext) -> None:
        s = self.session
        self.base = f"{NAMESPACE}/{s.group_id}"
        self.health_topic = s.ddata_topic
        self.availability_topic = s.ndeath_topic
        self.discovery_topic = ""
        self.state_topic = (f"{NAMESPACE}/STATE/{self.config.primary_host_id}"
                            if self.config.primary_host_id else None)

    def _make_client(self) -> mqtt.Client:
        client = super()._make_client()
        client.will_set(self.session.ndeath_topic, self.session.ndeath(_now_ms()), qos=1,
                        retain=False)
        return client

    def _connect(self) -> None:
        """A new CONNECT: a new ``bdSeq`` in a new client's will. A fresh client, not paho's
        reconnection: paho sends the previous connection's unacknowledged messages again after
        the CONNACK, after our NBIRTH, with their old ``seq`` (a host would see the sequence
        broken); those windows are sent again from the outbox instead, after the births."""
        self._flush_acks()
        position = self._position_now()
        self._inflight.clear()
        self._mids.clear()
        self._cursor = position
        self._born = self._device_born = False
        if self.config.primary_host_id:
            self._host_online = None
        old = self.client
        self.session.new_connection()
        self.client = self._make_client()
        self.client.connect_async(self.config.host, self.config.port,
                                  keepalive=self.config.keepalive)
        with contextlib.suppress(Exception):
            old._sock_close()  # noqa: SLF001 - a half-open attempt's socket (no public close)
        super()._connect()

    def _on_connect(self, client: mqtt.Client, userdata: Any, flags: Any, reason: Any,
                    properties: Any) -> None:
        if reason.is_failure and "authori" in str(reason).lower() and self._last_error is None:
            logger.error("outputs.sparkplug: the MQTT broker %s:%d refused the connection (%s): "
                         "the client %r must be allowed to connect with its will on %s (the "
                         "NDEATH) and to publish spBv1.0/%s/#; fix the broker's ACL or "
                         "outputs.sparkplug.username", self.config.host, self.config.port,
                         reason, self.client_id, self.session.ndeath_topic,
                         self.session.group_id)
        super()._on_connect(client, userdata, flags, reason, properties)

    def _on_disconnect(self, client: mqtt.Client, userdata: Any, flags: Any, reason: Any,
                       properties: Any) -> None:
        self._born = self._device_born = False
        if self._leaving:  # our own: quiet, not a take-over
            self._leaving = False
            self._connected = False
            self.disconnects += 1
            self._down_since = time.monotonic()
            return
        super()._on_disconnect(client, userdata, flags, reason, properties)

    def _announce(self, client: mqtt.Client) -> None:
        self._live_since = time.time()
        client.subscribe(self.session.ncmd_topic, qos=1)
        client.subscribe(self.session.nbirth_topic, qos=0)  # our own NBIRTH back: see _check
        if self.state_topic is not None:
            client.subscribe(self.state_topic, qos=1)
        if self._host_online:
            self._births(client)

    def _births(self, client: mqtt.Client) -> None:
        """NBIRTH, then the DBIRTH if a window is stored (else with the first one: its metrics
        and values, not a birth of nulls and a rebirth a window later)."""
        client.publish(self.session.nbirth_topic, self.session.nbirth(_now_ms()),
                       qos=self.config.qos)
        if self._birth_at is None and self._unheard is None:
            self._birth_at = time.monotonic()
        self._born = True
        self._device_born = False
        self.births += 1
        if self._latest_doc is not None:
            self._device_birth(client)

    def _device_birth(self, client: mqtt.Client) -> None:
        """DBIRTH: every metric with the newest stored window's values."""
        doc = self._latest_doc
        values: dict[str, Any] = {}
        if doc is not None:
            with contextlib.suppress(ValueError):  # named when the window is sent
                self.session.declare(metric_specs(self.parameters, self.rules, doc))
            values = metric_values(doc)
        client.publish(self.session.dbirth_topic, self.session.dbirth(values, _now_ms()),
                       qos=self.config.qos)
        self._device_born = True
        self.device_births += 1

    def _on_message(self, client: mqtt.Client, userdata: Any, msg: Any) -> None:
        """NCMD (Node Control/Rebirth), the primary host's STATE, our own NBIRTH back."""
        if msg.topic == self.session.nbirth_topic:
            if self._unheard is not None:
                logger.warning("outputs.sparkplug: the broker delivers the NBIRTH on %s now",
                               msg.topic)
            self._birth_at = None
            self._unheard = None
            return
        if msg.topic == self.session.ncmd_topic:
            try:
                cmd = payload_class().FromString(msg.payload)
            except Exception:  # noqa: BLE001 - a malformed command is counted and ignored
                self.errors += 1
                logger.warning("an NCMD on %s that is not a Sparkplug B payload: ignored",
                               msg.topic)
                return
            if any(m.name == REBIRTH and m.boolean_value for m in cmd.metrics):
                if self._host_online and self._connected:
                    logger.info("Sparkplug rebirth asked on %s: NBIRTH and DBIRTH again",
                                msg.topic)
                    self.rebirths += 1
                    self._births(client)
            return
        if self.state_topic is not None and msg.topic == self.state_topic:
            self._on_state(client, msg.payload)

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
            self._live_since = time.time()
            self._births(client)
            self._wake.set()
        elif not online and self._host_online:
            logger.warning("primary host %s offline: NDEATH, the windows wait in the outbox "
                           "until it is back", self.config.primary_host_id)
            self._host_online = False
            client.publish(self.session.ndeath_topic, self.session.ndeath(_now_ms()), qos=1)
            self._leaving = True
            client.disconnect()
        else:
            self._host_online = online

    def _check_heard(self) -> None:
        """A broker may accept the connection and acknowledge every publish while its ACL
        drops them (Mosquitto 2.0 does, MQTT 3.1.1 has no refusal for a publish nor for a
        will): our NBIRTH, subscribed to, not heard back within 5 s is said once, naming the
        key (the will is then dropped too, most likely)."""
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

    @property
    def problem(self) -> str | None:
        parts = [p for p in (super().problem, self._unheard) if p]
        return "; ".join(parts) or None

    def _feed(self, now: float, all_rows: bool) -> None:
        self._check_heard()
        if not self._born:  # no data before the births (nor while the host is away)
            self._file_changed()
            return
        super()._feed(now, all_rows)

    def _send(self, row: OutboxRow, newest: bool) -> bool:
        """One window's DDATA (historical when it was stored before this connection's births:
        a replay from the outbox); a metric the birth did not announce (a counter, a RUL
        appearing) makes a new birth first."""
        try:
            doc = _view(row.doc)
        except ValueError:
            doc = None
        if doc is None:
            self.errors += 1
            window = _Window(row)
            self._inflight[row.id] = window
            self._on_ack_none(row.id)
            return True
        try:
            grew = self.session.declare(metric_specs(self.parameters, self.rules, doc))
        except ValueError as exc:
            logger.error("outputs.sparkplug: %s; the new metric is left out", exc)
            grew = False
        if newest or self._latest_doc is None:
            self._latest_doc = doc
        if grew and self._device_born:  # a new metric: birth again (NBIRTH and DBIRTH)
            self._births(self.client)
        elif not self._device_born:
            self._device_birth(self.client)
        now = _now_ms()
        payload = self.session.ddata(metric_values(doc), now, int(row.wall * 1000),
                                     historical=row.wall < self._live_since)
        info = self.client.publish(self.session.ddata_topic, payload, qos=self.config.qos)
        if info.rc != mqtt.MQTT_ERR_SUCCESS:
            self.errors += 1
            logger.debug("publishing on %s refused: %s", self.session.ddata_topic,
                         mqtt.error_string(info.rc))
            return False
        window = _Window(row)
        window.mids.add(info.mid)
        self._mids[info.mid] = row.id
        self._inflight[row.id] = window
        if self.config.qos == 0 and info.is_published():
            self._on_publish(self.client, None, info.mid, None, None)
        return True

    def _on_ack_none(self, row_id: int) -> None:
        """A stored row that is no health message: counted delivered (nothing to send)."""
        window = self._inflight.pop(row_id)
        self._acked.append(window.row)

    def _farewell(self) -> list[mqtt.MQTTMessageInfo]:
        """A clean stop: DDEATH, then NDEATH with this connection's ``bdSeq``."""
        infos = []
        now = _now_ms()
        if self._device_born:
            infos.append(self.client.publish(self.session.ddeath_topic,
                                             self.session.ddeath(now), qos=1))
        infos.append(self.client.publish(self.session.ndeath_topic, self.session.ndeath(now),
                                         qos=1))
        self._born = self._device_born = False
        return infos

    def counters(self) -> dict[str, int]:
        """The MQTT output's (``delivered``, ``pending``, ...) and ``births`` (NBIRTHs sent),
        ``device_births`` (DBIRTHs), ``rebirths`` (asked by an NCMD)."""
        return {**super().counters(), "births": int(self.births),
                "device_births": int(self.device_births), "rebirths": int(self.rebirths)}

    @property
    def status(self) -> str:
        return (f"Sparkplug B on mqtt://{self.config.host}:{self.config.port}/"
                f"{self.session.ddata_topic}")

    def summary(self) -> list[str]:
        line = (f"Sparkplug B was published on {self.session.ddata_topic} (broker "
                f"{self.config.host}:{self.config.port}): {self.delivered} windows delivered, "
                f"{self.births} births")
        if self.pending:
            line += f", {self.pending} pending"
        if self.dropped:
            line += f", {self.dropped} dropped undelivered"
        return [line]

    def __repr__(self) -> str:
        state = "closed" if self._closed else ("connected" if self._connected else "connecting")
        return (f"SparkplugPublisher({self.session.ddata_topic!r}, {state}, "
                f"delivered={self.delivered})")
