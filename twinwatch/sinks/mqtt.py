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

from __future__ import annotations

import hashlib
import itertools
import json
import logging
import math
import random
import re
import ssl
import threading
import time
from collections import deque
from collections.abc import Collection, Hashable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Literal, Self

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictFloat,
    StrictInt,
    field_validator,
    model_validator,
)

from twinwatch import __version__
from twinwatch._lazy import lazy_module
from twinwatch.errors import PublisherError, StoreError
from twinwatch.sinks.base import (
    Outbox,
    OutboxRow,
    ProcessedWindow,
    Sink,
    SinkConfig,
    SinkContext,
)

if TYPE_CHECKING:
    import paho.mqtt.client as mqtt

    from twinwatch.twin.health import DiagnosisView, HealthView, ParameterView
else:  # imported when the output opens: loading a configuration does not load paho
    mqtt = lazy_module("paho.mqtt.client")

logger = logging.getLogger(__name__)
#: At stop, with windows still to deliver and no connection: the spacing of the connection
#: attempts until ``close_timeout`` [s].
CLOSE_RETRY_S = 1.0

__all__ = [
    "HomeAssistantConfig",
    "MemoryOutbox",
    "MqttConfig",
    "MqttConnectionConfig",
    "MqttPublisher",
    "MqttTlsConfig",
    "discovery_payload",
    "flat_values",
]

TAKEOVERS = 3
"""Connections lost in a row, each within :data:`TAKEOVER_S` of being made, that name a
client-id conflict (another client connecting with the same id takes the session over)."""

TAKEOVER_S = 10.0
"""A connection lost within this many seconds of being made counts as taken over [s]."""

# A topic level: no wildcards, no NUL; '/' separates levels.
_LEVEL_RE = re.compile(r"^[^#+\x00/]+$")
_HA_ID_RE = re.compile(r"[^A-Za-z0-9_-]")


def _check_topic(value: str, what: str) -> str:
    """A topic (prefix) by MQTT's rules (MQTT 3.1.1 Section 4.7): non-empty levels, no
    wildcards, no NUL, at most 65535 bytes of UTF-8, and not a ``$`` topic (``$SYS/...`` is the
    broker's own: a subscriber's ``#`` never receives it, and a broker may refuse publishing
    there: 10 windows were counted delivered that no subscriber could receive)."""
    if not value or any(_LEVEL_RE.match(level) is None for level in value.split("/")):
        raise ValueError(f"{what} {value!r} must be non-empty topic levels separated by '/', "
                         f"without the wildcards '+' and '#', NUL (and no leading or trailing "
                         f"'/')")
    if value.startswith("$"):
        raise ValueError(f"{what} {value!r} starts with '$': such topics are the broker's "
                         f"own ($SYS), not for applications (MQTT 3.1.1 Section 4.7.2)")
    if len(value.encode("utf-8")) > 60_000:  # the machine and the suffixes need room
        raise ValueError(f"{what} is {len(value.encode('utf-8'))} bytes: an MQTT topic is "
                         f"at most 65535 bytes with its machine and suffix")
    return value


class MqttTlsConfig(BaseModel):
    """``[outputs.mqtt.tls]``: TLS to the broker (``port`` is then usually 8883). Paths are
    relative to the configuration file's directory; the private key is a secret (refused when
    others can read it: install it ``0640 root:twinwatch``).
    """

    model_config = ConfigDict(extra="forbid")

    ca_certs: str | None = Field(None,
                                 description="the broker's CA (PEM); unset: the system's CAs")
    certfile: str | None = Field(None,
                                 description="our client certificate (PEM), if asked for")
    keyfile: str | None = Field(None, description="its private key (PEM; a secret: 0640)")
    verify_hostname: bool = Field(True,
                                  description="check the broker's name against its certificate")

    FILES: ClassVar[tuple[str, ...]] = ("ca_certs", "certfile", "keyfile")
    SECRET_FILES: ClassVar[tuple[str, ...]] = ("keyfile",)

    @model_validator(mode="after")
    def _pair(self) -> Self:
        if bool(self.certfile) != bool(self.keyfile):
            raise ValueError("certfile and keyfile go together (a client certificate and its "
                             "private key)")
        return self


class HomeAssistantConfig(BaseModel):
    """``[outputs.mqtt.home_assistant]``: Home Assistant's MQTT device discovery."""

    model_config = ConfigDict(extra="forbid")

    discovery: bool = Field(False, description="announce a Home Assistant device; false clears it")
    prefix: str = Field("homeassistant",
                        description="Home Assistant's discovery prefix (birth on <prefix>/status)")
    device_name: str | None = Field(None,
                                    description="its name; unset: the machine name")

    @field_validator("prefix")
    @classmethod
    def _prefix(cls, value: str) -> str:
        return _check_topic(value, "prefix")


class MqttConnectionConfig(SinkConfig):
    """The broker connection and the outbox's pace: the keys ``[outputs.mqtt]`` shares with
    ``[outputs.sparkplug]`` (:mod:`twinwatch.sinks.sparkplug`)."""

    enabled: bool = Field(True, description="false: the output is not opened")
    host: str = Field("127.0.0.1", min_length=1, description="the broker's host name or address")
    port: StrictInt = Field(1883, ge=1, le=65535, description="the broker's port (8883 for TLS)")
    client_id: str | None = Field(None, min_length=1, max_length=128,
                                  description="unique per broker; unset: twinwatch-<machine>")
    username: str | None = Field(None, min_length=1,
                                 description="user name, if the broker asks for one")
    password_file: str | None = Field(None,
                                      description="the password's file (first line; a secret)")
    password: str | None = Field(None,
                                 description="the password inline (the file is then a secret)")
    tls: MqttTlsConfig | None = Field(None, description="TLS to the broker")
    keepalive: StrictInt = Field(
        30, ge=5, le=65535,
        description="s between pings; silent for 1.5x: offline (last will)")
    qos: Literal[1, 2] = Field(1, description="1: at least once; 2: exactly once while connected")
    inflight: StrictInt = Field(10, ge=1, le=1000,
                                description="windows sent, not yet acknowledged, at most")
    rate: StrictFloat = Field(20.0, gt=0, description="windows a second, at most, when catching up")
    reconnect_min: StrictFloat = Field(0.5, gt=0,
                                       description="s to the first retry; doubles to reconnect_max")
    reconnect_max: StrictFloat = Field(30.0, gt=0,
                                       description="s, the longest retry delay (+-25 % jitter)")
    ack_timeout: StrictFloat = Field(
        30.0, gt=0, allow_inf_nan=False,
        description="s a window may wait for the broker's acknowledgement before DEGRADED")
    connect_timeout: StrictFloat = Field(
        5.0, gt=0, description="s, one connection attempt's timeout")
    close_timeout: StrictFloat = Field(5.0, ge=0,
                                       description="s at stop to deliver what is pending "
                                       "(reconnecting every second meanwhile if the broker "
                                       "is away)")
    memory_outbox: StrictInt = Field(10_000, ge=1,
                                     description="windows kept in memory without a state database")

    @field_validator("client_id")
    @classmethod
    def _client_id(cls, value: str | None) -> str | None:
        # MQTT 3.1.1 Section 3.1.3.1: a UTF-8 string; a NUL or a control character passed
        # check-config, then nothing was delivered and nothing said why
        if value is not None and any(ord(c) < 0x20 or ord(c) == 0x7F for c in value):
            raise ValueError("client_id must not contain NUL or control characters")
        return value

    @model_validator(mode="after")
    def _check(self) -> Self:
        if self.password is not None and self.password_file is not None:
            raise ValueError("give password_file or password, not both")
        if (self.password is not None or self.password_file is not None) and not self.username:
            raise ValueError("a password needs a username")
        if self.reconnect_min > self.reconnect_max:
            raise ValueError("reconnect_min must not exceed reconnect_max")
        return self

    def input_files(self) -> dict[str, str]:
        """Key -> path of the files read at open (certificates, key, password file)."""
        out = {}
        if self.tls is not None:
            out.update({f"tls.{k}": v for k in MqttTlsConfig.FILES
                        if (v := getattr(self.tls, k))})
        if self.password_file:
            out["password_file"] = self.password_file
        return out

    def secret_input_files(self) -> dict[str, str]:
        """The private key and the password file: refused when others can read them."""
        secret = {f"tls.{k}" for k in MqttTlsConfig.SECRET_FILES} | {"password_file"}
        return {k: v for k, v in self.input_files().items() if k in secret}

    def inline_secret_keys(self) -> list[str]:
        """``password`` written in the configuration itself."""
        return ["password"] if self.password is not None else []

    def resolve_paths(self, base_dir: Path) -> None:
        """Make the file paths absolute against ``base_dir`` (``~`` expanded)."""
        def resolve(v: str) -> str:
            p = Path(v).expanduser()
            return str(p if p.is_absolute() else (base_dir / p).resolve())

        if self.tls is not None:
            for k in MqttTlsConfig.FILES:
                if (v := getattr(self.tls, k)):
                    setattr(self.tls, k, resolve(v))
        if self.password_file:
            self.password_file = resolve(self.password_file)

    def exclusive_resources(self, cwd: Path) -> set[str]:
        """The client id at the broker (a second connection with it would take the session
        over): a reload that keeps it waits for the running output to disconnect."""
        return {f"mqtt://{self.host}:{self.port}/{self.client_id or ''}"}


class MqttConfig(MqttConnectionConfig):
    """``[outputs.mqtt]``: the MQTT output (see the module docstring).

    Example::

        [outputs.mqtt]
        host = "127.0.0.1"
        port = 1883
        topic_prefix = "twinwatch"       # twinwatch/<machine>/health
        username = "twinwatch"
        password_file = "/etc/twinwatch/mqtt.password"   # 0640 root:twinwatch
        [outputs.mqtt.home_assistant]
        discovery = true
    """

    topic_prefix: str = Field("twinwatch",
                              description="<prefix>/<machine>/health, .../parameters/<name>/value")
    home_assistant: HomeAssistantConfig = Field(default_factory=HomeAssistantConfig)

    @field_validator("topic_prefix")
    @classmethod
    def _prefix(cls, value: str) -> str:
        return _check_topic(value, "topic_prefix")


# -- what is published ------------------------------------------------------------------------
def _number(value: Any) -> str:
    """A flat value's text: a number as JSON writes it, ``null`` when absent or not finite."""
    if isinstance(value, bool) or value is None:
        return "null" if value is None else json.dumps(value)
    if isinstance(value, int | float):
        return json.dumps(value) if math.isfinite(value) else "null"
    return "null"


def _std(value: Any, rel_std_pct: Any) -> float | None:
    """The standard error of ``value`` from its relative one [%], or None."""
    if (isinstance(value, int | float) and isinstance(rel_std_pct, int | float)
            and not isinstance(rel_std_pct, bool) and math.isfinite(value)
            and math.isfinite(rel_std_pct) and rel_std_pct > 0):
        return abs(value) * rel_std_pct / 100.0
    return None


def _rounded(value: Any, std: float | None, *, floor: float | None = None,
             digits: int = 6) -> Any:
    """``value`` rounded to what its interval supports: two significant digits of its
    standard error ``std`` (Ra 6.16593 +- 0.0006: 6.16593), never finer than ``floor``;
    without one, ``digits`` significant digits. A deviation of 4.440892098500626e-14 %
    (a float's rounding) is published as 0.0."""
    if not isinstance(value, int | float) or isinstance(value, bool) or not math.isfinite(value):
        return value
    step = std if std is not None and std > 0 else None
    if floor is not None:
        step = max(step, floor) if step is not None else floor
    if step is not None:
        decimals = max(0, 1 - math.floor(math.log10(step)))
        return round(float(value), min(decimals, 15))
    if value == 0:
        return 0.0
    return float(f"{value:.{digits}g}")


def _rul_s(param: ParameterView, level: str) -> Any:
    rul = param.rul
    crossing = (rul.alarm if level == "alarm" else rul.warning) if rul is not None else None
    return crossing.rul_s if crossing is not None else None


def _view(doc: HealthView | Mapping[str, Any] | str | bytes) -> HealthView:
    """``doc`` (a typed view, the decoded message or its JSON text) as the health message's
    typed view (parsed once).

    Raises:
        ValueError: text that is not a health message (:func:`~twinwatch.twin.health.read_health`).
    """
    from twinwatch.twin.health import HealthView, read_health

    return doc if isinstance(doc, HealthView) else read_health(doc)


def flat_values(doc: HealthView | Mapping[str, Any]) -> dict[str, str]:
    """The retained flat topics of one health message (its typed view,
    :func:`~twinwatch.twin.health.read_health`, or the decoded message): suffix
    (``parameters/Ra/value``) -> plain-text payload.

    Per parameter: ``value``, ``deviation_pct`` (numbers; ``null`` when there is none),
    ``status``; ``rul`` and ``rul_warning`` (median seconds to the alarm / warning threshold,
    ``parameters.<name>.rul.<level>.rul_s``) when the message has a ``rul`` field (the
    prognostics); ``alarm`` (the level) when the parameter has an alarm rule (``alarms``).
    """
    from twinwatch.twin.health import sent

    doc = _view(doc)
    out: dict[str, str] = {}
    alarms = doc.alarms or {}
    for name, p in (doc.parameters or {}).items():
        base = f"parameters/{name}"
        value, dev, rel = p.value, p.deviation_pct, p.rel_std_pct
        std = _std(value, rel)
        out[f"{base}/value"] = _number(_rounded(value, std))
        nom = p.nominal
        dev_std = (std / abs(nom) * 100.0
                   if isinstance(nom, int | float) and nom and std else None)
        out[f"{base}/deviation_pct"] = _number(_rounded(dev, dev_std, floor=1e-4))
        out[f"{base}/status"] = str(p.status or "")
        if sent(p, "rul"):
            out[f"{base}/rul"] = _number(_rul_s(p, "alarm"))
            out[f"{base}/rul_warning"] = _number(_rul_s(p, "warning"))
        alarm = alarms.get(name)
        if alarm is not None:
            out[f"{base}/alarm"] = str(alarm.level or "normal")
    if doc.diagnosis is not None:
        out.update(diagnosis_values(doc.diagnosis))
    return out


_NO_ACTION = {"no_fault": "none",
              "unknown": "inspect: the twin found a change no fault mode of the library "
                         "explains (twinwatch explain)",
              "check_function": "check the sensors (wiring, scaling, offsets) and the model: "
                                "the twin does not describe this machine, its estimates are "
                                "held (twinwatch explain)"}


def diagnosis_values(diag: DiagnosisView) -> dict[str, str]:
    """The diagnosis' flat topics: ``diagnosis/fault`` (the most probable fault's id, or
    ``no_fault`` / ``unknown`` / ``check_function``), ``diagnosis/probability`` (its
    probability [%], one decimal),
    ``diagnosis/action`` (the fault's maintenance action, or what to do without one; never
    empty: an empty retained payload deletes the topic; at most 255 characters, Home
    Assistant's limit of a state)."""
    status = str(diag.status or "no_fault")
    faults = diag.faults or []
    top = faults[0] if status == "fault" and faults else None
    prob = diag.probability
    return {
        "diagnosis/fault": str(top.id) if top else status,
        "diagnosis/probability": _number(round(100.0 * prob, 1)
                                         if isinstance(prob, int | float) else None),
        "diagnosis/action": (str(top.action or "") if top else _NO_ACTION.get(
            status, "none"))[:255],
    }


def _levels(doc: HealthView | None) -> dict[str, str]:
    alarms = (doc.alarms if doc is not None else None) or {}
    return {k: str(v.level or "normal") for k, v in alarms.items() if v is not None}


def reconstructed_events(doc: HealthView | None, previous: dict[str, str]
                         ) -> list[dict[str, Any]]:
    """Alarm-level changes between the previous stored message's levels and ``doc``'s (its
    typed view; None: an unreadable message, no change), as events (the evaluator's keys it
    can give, ``"reconstructed": true``)."""
    events: list[dict[str, Any]] = []
    if doc is None:
        return events
    params = doc.parameters or {}
    for name, level in _levels(doc).items():
        before = previous.get(name, "normal")
        if level == before:
            continue
        a = (doc.alarms or {})[name]
        p = params.get(name)
        dev = a.deviation_pct
        events.append({
            "machine": doc.machine, "parameter": name, "level": level,
            "previous": before, "deviation_pct": dev,
            "value": p.value if p is not None else None,
            "unit": p.unit if p is not None else None,
            "nominal": p.nominal if p is not None else None, "t": doc.t_end,
            "window": doc.window, "since_t": a.since_t,
            "message": (f"{doc.machine}: {name} {before} -> {level}"
                        + (f" ({dev:+.2f} % of nominal)" if isinstance(dev, int | float)
                           and math.isfinite(dev) else "")
                        + " (reconstructed from the stored health messages)"),
            "reconstructed": True})
    return events


def ha_device_id(machine: str) -> str:
    """Home Assistant's device id for ``machine``: ``twinwatch_<machine>``, characters outside
    ``[A-Za-z0-9_-]`` replaced by ``_`` (the discovery topic's object id)."""
    return _HA_ID_RE.sub("_", f"twinwatch_{machine}")


def discovery_payload(machine: str, model: str, base: str,
                      doc: HealthView | Mapping[str, Any] | None,
                      parameters: dict[str, str], *, qos: int = 1,
                      device_name: str | None = None,
                      rules: Collection[str] | None = None,
                      nominal: Mapping[str, float] | None = None) -> dict[str, Any]:
    """Home Assistant's device-based discovery payload for one machine (abbreviated keys, as
    Home Assistant's MQTT documentation lists them).

    Args:
        machine: the machine name.
        model: the twin model (the device's model).
        base: the machine's topic base ``<prefix>/<machine>``.
        doc: the newest health message (its typed view, or decoded), or None: which
            parameters have an alarm
            rule (``alarms``) and a ``rul`` field; without it, every parameter of
            ``parameters`` gets its value, deviation and status only.
        parameters: parameter name -> SI unit (the twin's, in order).
        qos: the QoS Home Assistant subscribes with.
        device_name: the device's name (default: the machine name).
        rules: the parameters with an ``[alarms]`` rule (the configuration's): their alarm
            and RUL entities are announced in the first message, before any health message
            (before, the first discovery had 18 components and the next, once a message
            came, 25), and only theirs (a RUL without a rule stayed ``unknown`` for ever).
        nominal: parameter -> nominal value, for each value entity's display precision.

    Returns:
        The payload: ``dev`` (ids, name, mf, mdl, sw), ``o`` (name, sw, url), ``avty_t``,
        ``qos`` and ``cmps``: per parameter a ``sensor`` for its value (unit,
        ``state_class: measurement``), its deviation [%] and its status; a ``binary_sensor``
        ``device_class: problem`` per alarm rule (on while the level is not ``normal``); a
        ``sensor`` ``device_class: duration`` [s] for the RUL where the message has one; the
        diagnosis' most probable fault, its probability [%] and the maintenance action
        (unless the message has no ``diagnosis``: ``[diagnosis] enabled = false``).
    """
    from twinwatch.twin.health import sent

    view = _view(doc) if doc is not None else None
    dev_id = ha_device_id(machine)
    params = dict(parameters)
    doc_params = (view.parameters if view is not None else None) or {}
    for name, p in doc_params.items():
        params.setdefault(name, str(p.unit or ""))
    alarms = set(_levels(view)) | set(rules or ())
    number = "{{ value_json }}"  # JSON null -> None -> Home Assistant's "unknown"
    cmps: dict[str, dict[str, Any]] = {}

    def add(key: str, platform: str, name: str, topic: str, **extra: Any) -> None:
        cmps[key] = {"p": platform, "name": name, "uniq_id": f"{dev_id}_{key}",
                     "stat_t": f"{base}/{topic}", **extra}

    for name, unit in params.items():
        t = f"parameters/{name}"
        value: dict[str, Any] = {"stat_cla": "measurement", "val_tpl": number}
        if unit:
            value["unit_of_meas"] = unit
        nom = (nominal or {}).get(name)
        if nom is not None and math.isfinite(nom) and nom != 0:
            # four significant digits of the nameplate value: Ra 6.500 ohm, J 0.001171
            value["suggested_display_precision"] = max(0, 3 - math.floor(math.log10(abs(nom))))
        add(f"{name}_value", "sensor", name, f"{t}/value", **value)
        add(f"{name}_deviation", "sensor", f"{name} deviation", f"{t}/deviation_pct",
            unit_of_meas="%", stat_cla="measurement", val_tpl=number, ic="mdi:delta",
            suggested_display_precision=2)
        add(f"{name}_status", "sensor", f"{name} status", f"{t}/status",
            ic="mdi:information-outline")
        if name in alarms:
            add(f"{name}_alarm", "binary_sensor", f"{name} alarm", f"{t}/alarm",
                dev_cla="problem", val_tpl="{{ 'OFF' if value == 'normal' else 'ON' }}")
        if name in alarms and (rules is not None or (
                name in doc_params and sent(doc_params[name], "rul"))):
            add(f"{name}_rul", "sensor", f"{name} remaining useful life", f"{t}/rul",
                dev_cla="duration", unit_of_meas="s", stat_cla="measurement", val_tpl=number,
                suggested_display_precision=0)
    if view is None or view.diagnosis is not None:  # [diagnosis] is on by default
        add("diagnosis_fault", "sensor", "most probable fault", "diagnosis/fault",
            ic="mdi:stethoscope")
        add("diagnosis_probability", "sensor", "most probable fault probability",
            "diagnosis/probability", unit_of_meas="%", stat_cla="measurement",
            val_tpl=number, suggested_display_precision=1)
        add("diagnosis_action", "sensor", "maintenance action", "diagnosis/action",
            ic="mdi:wrench")
    return {
        "dev": {"ids": [dev_id], "name": device_name or machine, "mf": "twinwatch",
                "mdl": f"{model} digital twin" if model else "digital twin", "sw": __version__},
        "o": {"name": "twinwatch", "sw": __version__},
        "avty_t": f"{base}/availability",
        "qos": qos,
        "cmps": cmps,
    }


# -- the outbox without a state database --------------------------------------------------------
class MemoryOutbox:
    """An :class:`~twinwatch.sinks.base.Outbox` in memory (no state database): the last
    ``size`` windows given to :meth:`add`; older undelivered ones are :attr:`dropped`."""

    def __init__(self, size: int) -> None:
        self._rows: deque[OutboxRow] = deque()
        self._size = size
        self._next = 1
        self._delivered: set[int] = set()
        self._lock = threading.Lock()
        self.dropped = 0

    def add(self, doc: str, window: int) -> None:
        with self._lock:
            self._rows.append(OutboxRow(self._next, "memory", window, time.time(), doc))
            self._next += 1
            while len(self._rows) > self._size:
                old = self._rows.popleft()
                if old.id not in self._delivered:
                    self.dropped += 1
                self._delivered.discard(old.id)

    def start(self) -> int:
        with self._lock:
            return self._rows[0].id - 1 if self._rows else self._next - 1

    def pending(self, after: int, limit: int) -> list[OutboxRow]:
        with self._lock:
            return [r for r in self._rows if r.id > after
                    and r.id not in self._delivered][:limit]

    def count(self, position: int) -> int:
        with self._lock:
            return sum(1 for r in self._rows if r.id > position and r.id not in self._delivered)

    def latest_id(self) -> int | None:
        with self._lock:
            return self._rows[-1].id if self._rows else None

    def doc_at_or_before(self, health_id: int) -> str | None:
        with self._lock:
            return next((r.doc for r in reversed(self._rows) if r.id <= health_id), None)

    def ack(self, delivered: list[OutboxRow], position: int) -> None:
        with self._lock:
            self._delivered.update(r.id for r in delivered)
            self._delivered = {i for i in self._delivered if i > position}
            while self._rows and self._rows[0].id <= position:
                self._rows.popleft()


class _Window:
    """A window handed to paho: its row and the message ids not acknowledged yet."""

    __slots__ = ("mids", "row", "sent")

    def __init__(self, row: OutboxRow) -> None:
        self.row = row
        self.mids: set[int] = set()
        self.sent = time.monotonic()


class MqttPublisher(Sink):
    """The MQTT output (see the module docstring): the built-in ``mqtt``, ``[outputs.mqtt]``.

    Args:
        config: the validated table.
        context: the daemon's context (machine, model, parameters; the gate's outbox).

    Raises:
        PublisherError: a TLS or password file cannot be read, or the TLS setup fails. An
            unreachable broker is not an error: it is tried again in the background while
            the windows wait in the outbox.
    """

    config_class: ClassVar[type[MqttConfig]] = MqttConfig
    counter_prefix: ClassVar[str | None] = "mqtt"
    #: the table's name in messages (``outputs.<table>.<key>``)
    table: ClassVar[str] = "mqtt"
    #: the default client id is ``<client_prefix>-<machine>``
    client_prefix: ClassVar[str] = "twinwatch"

    config: MqttConfig

    def __init__(self, config: MqttConfig, context: SinkContext) -> None:
        self._closed = True  # until fully open
        self.config = config
        self.machine = context.machine
        self.model = context.model
        self.parameters = dict(context.parameters)
        self.client_id = config.client_id or f"{self.client_prefix}-{context.machine}"
        self._topics(context)
        # counters (written by the thread, read by the worker and the main thread)
        self.delivered = 0
        self.pending = 0
        self.errors = 0
        self.connects = 0
        self.disconnects = 0
        self._memory: MemoryOutbox | None = None
        self._outbox: Outbox | None = None
        self._events: dict[str, list[dict[str, Any]]] = {}
        self._events_lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._rebind = threading.Event()
        self._connected = False
        self._down_since: float | None = time.monotonic()
        self._unacked_logged = False
        self._connected_at = 0.0
        self._takeovers = 0          # connections lost soon after they were made, in a row
        self._takeover_total = 0
        self._hold_until = 0.0       # no connection attempt before (a client-id conflict)
        self._last_error: str | None = None
        self._refused = False  # the last attempt's CONNACK refused the connection
        self._failing_store = False
        self._inflight: dict[int, _Window] = {}  # health row id -> window
        self._mids: dict[int, int] = {}          # message id -> health row id
        self._acked: list[OutboxRow] = []        # delivered, not yet recorded
        self._position = 0
        self._cursor = 0
        self._latest_doc: HealthView | None = None
        self._previous_levels: dict[str, str] | None = None
        self._discovery_sent: str | None = None
        self._discovery_due: float | None = None
        self._tokens = float(config.inflight)
        self._token_time = time.monotonic()
        self._password = self._read_password()
        if context.outbox is None:  # no state database: the outbox is in memory
            self._memory = MemoryOutbox(config.memory_outbox)
        self.context = context
        self._bind(context)
        self.client = self._make_client()
        self.client.connect_async(config.host, config.port, keepalive=config.keepalive)
        self._thread = threading.Thread(target=self._run, name=f"twinwatch-{self.table}",
                                        daemon=True)
        self._closed = False
        self._thread.start()

    def _topics(self, context: SinkContext) -> None:
        """The topics (set before the client is made; a subclass publishes others)."""
        config = self.config
        self.base = f"{config.topic_prefix}/{context.machine}"
        _check_topic(self.base, "topic_prefix/machine")
        self.health_topic = f"{self.base}/health"
        self.availability_topic = f"{self.base}/availability"
        ha = config.home_assistant
        self.discovery_topic = f"{ha.prefix}/device/{ha_device_id(context.machine)}/config"

    # -- opening ------------------------------------------------------------------------------
    @classmethod
    def from_config(cls, config: MqttConfig, context: SinkContext) -> Self:
        """Open the output; the broker is connected to in the background."""
        return cls(config, context)

    @classmethod
    def reload_key(cls, config: MqttConfig, context: SinkContext) -> Hashable:
        """The table's values and what its files hold now (the password file, the TLS
        certificates and key): a SIGHUP after a password or a certificate was renewed opens
        the output again with them; the same table and files keep it connected. (Before,
        only the table counted: a fixed password file was read again only by a restart.)"""
        files = []
        for key, path in sorted(config.input_files().items()):
            try:
                files.append((key, hashlib.sha256(Path(path).read_bytes()).hexdigest()))
            except OSError as exc:  # the reload's own open names it
                files.append((key, f"unreadable: {exc.strerror or exc}"))
        return (super().reload_key(config, context), tuple(files))

    def _read_password(self) -> str | None:
        cfg = self.config
        if cfg.password_file is None:
            return cfg.password
        try:
            with open(cfg.password_file, encoding="utf-8") as f:
                return f.readline().rstrip("\r\n")
        except OSError as exc:
            raise PublisherError(f"cannot read outputs.{self.table}.password_file = "
                                 f"{cfg.password_file}"
                                 f": {exc.strerror or exc}; fix the path or the file's "
                                 f"permissions (the service user must read it)") from exc

    def _make_client(self) -> mqtt.Client:
        cfg = self.config
        client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=self.client_id,
                             clean_session=True, protocol=mqtt.MQTTv311)
        client.connect_timeout = cfg.connect_timeout
        client.max_inflight_messages_set(0)   # the inflight limit is ours, in windows
        client.max_queued_messages_set(0)
        client.enable_logger(logging.getLogger(f"{__name__}.paho"))
        if cfg.username:
            client.username_pw_set(cfg.username, self._password)
        if cfg.tls is not None:
            tls = cfg.tls
            try:
                client.tls_set(ca_certs=tls.ca_certs, certfile=tls.certfile,
                               keyfile=tls.keyfile, cert_reqs=ssl.CERT_REQUIRED,
                               tls_version=ssl.PROTOCOL_TLS_CLIENT)
            except (OSError, ssl.SSLError, ValueError) as exc:
                raise PublisherError(f"outputs.{self.table}.tls: cannot set up TLS: {exc}; "
                                     f"check the certificate and key files") from exc
            client.tls_insecure_set(not tls.verify_hostname)
        client.will_set(self.availability_topic, "offline", qos=1, retain=True)
        client.on_connect = self._on_connect
        client.on_disconnect = self._on_disconnect
        client.on_publish = self._on_publish
        client.on_message = self._on_message
        return client

    # -- the sink contract --------------------------------------------------------------------
    def attach(self, context: SinkContext) -> None:
        """A reload's daemon adopts the output: its outbox from now on."""
        super().attach(context)
        self._bind(context)

    def detach(self) -> None:
        """The daemon that opened it stops (a reload): nothing new is read from its outbox
        until :meth:`attach`."""
        super().detach()
        self._rebind.set()

    def _bind(self, context: SinkContext) -> None:
        self.context = context
        if context.outbox is not None:
            # The delivered position exists before the output's thread first runs: created
            # there, lazily, it was placed at the newest stored window, and the windows the
            # daemon stored meanwhile were taken for old history and never sent (issue 26;
            # the reload hand-over test lost its first 3 windows in 4 of 8 runs).
            try:
                box = context.outbox(self.name or self.table)
                if box is not None:
                    box.start()
            except StoreError:
                pass  # the thread binds again and reports it (_store_failed)
        self._rebind.set()
        self._wake.set()

    def write(self, out: ProcessedWindow) -> None:
        """The window pipeline's call (a stored window): remember its alarm events, keep it
        in memory when there is no state database, wake the thread. Never blocks on the
        broker."""
        if self._closed:
            return
        if out.events:
            with self._events_lock:
                self._events[out.health_json] = list(out.events)
                while len(self._events) > 1000:
                    self._events.pop(next(iter(self._events)))
        if self._memory is not None:
            self._memory.add(out.health_json, out.health.window)
        self._wake.set()

    def counters(self) -> dict[str, int]:
        """``delivered`` (windows acknowledged by the broker), ``pending`` (stored, not yet
        delivered), ``dropped`` (deleted by the retention, or pushed out of the memory outbox,
        before delivery), ``connects``, ``disconnects``, ``errors`` (publishes refused,
        outbox reads or writes that failed)."""
        return {"delivered": int(self.delivered), "pending": int(self.pending),
                "dropped": self.dropped, "connects": int(self.connects),
                "disconnects": int(self.disconnects), "errors": int(self.errors)}

    @property
    def dropped(self) -> int:
        box = self._outbox
        return int(getattr(box, "dropped", 0) or 0) if box is not None else 0

    @property
    def lost(self) -> int:  # type: ignore[override]
        """Windows that will never be delivered: dropped, and without a state database the
        windows still pending when it closed."""
        lost = self.dropped
        if self._memory is not None and self._closed:
            lost += self.pending
        return lost

    @property
    def connected(self) -> bool:
        """The broker has accepted the connection (CONNACK) and it is not known lost."""
        return self._connected

    @property
    def problem(self) -> str | None:
        out = []
        if not self._connected and self._down_since is not None and not self._closed:
            since = time.monotonic() - self._down_since
            if since > 2 * self.config.connect_timeout or self.connects:
                why = f" ({self._last_error})" if self._last_error else ""
                out.append(f"MQTT broker {self.config.host}:{self.config.port} unreachable for "
                           f"{since:.0f} s{why}: {self.pending} windows pending, sent when it "
                           f"is back")
        unacked = self._unacknowledged()
        if unacked is not None:
            out.append(unacked)
        if self._takeovers >= TAKEOVERS and not self._closed:
            out.append(f"another client uses MQTT client id {self.client_id!r} on "
                       f"{self.config.host}:{self.config.port} ({self._takeover_total} "
                       f"connections taken over): {self.pending} windows pending")
        if self.dropped:
            out.append(f"MQTT: {self.dropped} windows dropped undelivered")
        return "; ".join(out) or None

    def _unacknowledged(self) -> str | None:
        """Connected, but the oldest window handed to the broker waits for its
        acknowledgement longer than ``ack_timeout``: a broker that accepts and never
        acknowledges (issue 26: 36 windows pending for 70 s, STATUS never said DEGRADED, not
        one log line). Logged once per episode."""
        if not self._connected or self._closed:
            self._unacked_logged = False
            return None
        sent = [w.sent for w in list(self._inflight.values())]
        age_s = time.monotonic() - min(sent) if sent else 0.0
        if age_s <= self.config.ack_timeout:
            self._unacked_logged = False
            return None
        line = (f"MQTT broker {self.config.host}:{self.config.port} has not acknowledged "
                f"{len(sent)} windows for {age_s:.0f} s (ack_timeout "
                f"{self.config.ack_timeout:g} s): {self.pending} windows pending")
        if not self._unacked_logged:
            self._unacked_logged = True
            logger.warning("%s; they are kept and sent again on the next connection", line)
        return line

    @property
    def status(self) -> str:
        return f"health on mqtt://{self.config.host}:{self.config.port}/{self.health_topic}"

    def summary(self) -> list[str]:
        where = ("kept in the state database for the next start" if self._memory is None
                 else "lost (no state database)")
        line = (f"health was published on {self.health_topic} (MQTT, broker "
                f"{self.config.host}:{self.config.port}): {self.delivered} windows delivered")
        if self.pending:
            line += f", {self.pending} pending ({where})"
        if self.dropped:
            line += f", {self.dropped} dropped undelivered"
        return [line]

    def close(self) -> None:
        """Deliver what is pending for up to ``close_timeout`` s, record the deliveries,
        publish ``offline`` and disconnect. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=self.config.close_timeout + self.config.connect_timeout + 10)
        if self._thread.is_alive():
            logger.warning("the MQTT thread of %s did not stop in time", self.machine)
        logger.info("MQTT output of %s closed (%d windows delivered, %d pending)",
                    self.machine, self.delivered, self.pending)

    # -- the thread ---------------------------------------------------------------------------
    def _run(self) -> None:
        """The thread: :meth:`_loop`, restarted after an unexpected error (logged with its
        traceback, counted in ``errors``): the output must not die silently."""
        while True:
            try:
                self._loop()
                return
            except Exception:  # noqa: BLE001 - logged; the loop goes on
                self.errors += 1
                logger.exception("the MQTT output of %s failed; it goes on in 1 s",
                                 self.machine)
                if self._stop.wait(1.0):
                    self._finish()
                    return

    def _loop(self) -> None:
        delay = self.config.reconnect_min
        next_attempt = 0.0
        last_poll = 0.0
        last_count = 0.0
        deadline: float | None = None
        close_attempt = 0.0
        while True:
            now = time.monotonic()
            if self._rebind.is_set():
                self._rebind_outbox()
            if self._stop.is_set():  # closing: deliver what is pending, for a while
                if deadline is None:
                    deadline = now + self.config.close_timeout
                if now >= deadline:
                    break
                if not self._connected:
                    # while windows wait: an attempt at once and then every
                    # CLOSE_RETRY_S until the deadline (the backoff may be sleeping through a
                    # broker that is back; a single attempt gave up on a broker started a
                    # second after a short run's end, its backlog left for the next start)
                    if not (self._inflight or self._has_pending()):
                        break
                    if now >= close_attempt:
                        self._connect()
                        close_attempt = time.monotonic() + CLOSE_RETRY_S
                    if not self._connected:
                        self._flush_acks()
                        time.sleep(max(0.0, min(0.2, deadline - time.monotonic())))
                    continue
                if not self._inflight:
                    self._feed(now, all_rows=True)
                    if not self._inflight and not self._has_pending():
                        break
            if not self._connected:
                if now >= next_attempt and now >= self._hold_until:
                    self._connect()
                    if not self._connected:  # capped exponential backoff, +-25 % jitter
                        next_attempt = time.monotonic() + delay * random.uniform(0.75, 1.25)
                        delay = min(2 * delay, self.config.reconnect_max)
                if not self._connected:
                    self._flush_acks()
                    if now - last_count > 1.0:
                        self._count()
                        last_count = now
                    if self._wake.wait(min(0.2, max(next_attempt - time.monotonic(), 0.01))):
                        self._wake.clear()
                        self._count()  # a window stored: one more pending
                        last_count = time.monotonic()
                    continue
            delay = self.config.reconnect_min
            self.client.loop(timeout=0.05)
            if not self._connected:
                continue
            woken = self._wake.is_set()
            self._wake.clear()
            if woken or self._stop.is_set() or now - last_poll > 0.5:
                self._feed(now, all_rows=woken or self._stop.is_set())
                last_poll = now
            if self._discovery_due is not None and now >= self._discovery_due:
                self._send_discovery(force=True)
            self._flush_acks()
            if now - last_count > 1.0:
                self._count()
                last_count = now
        self._finish()

    def _has_pending(self) -> bool:
        """A stored window beyond the ones handed to paho is not delivered yet."""
        box = self._outbox
        try:
            return box is not None and bool(box.pending(self._cursor, 1))
        except StoreError:
            return False

    def _rebind_outbox(self) -> None:
        """Use the outbox of the current context (at start, and after a reload)."""
        self._rebind.clear()
        self._flush_acks()
        ctx = self.context
        getter = ctx.outbox if ctx is not None else None
        box: Outbox | None = self._memory
        try:
            if box is None and getter is not None:
                box = getter(self.name or self.table)
            if box is None:
                self._outbox = None  # detached (a reload): wait for attach()
                return
            if box is self._outbox and not getattr(box, "changed", False):
                return
            position = box.start()
            latest = box.doc_at_or_before(box.latest_id() or position)
        except (StoreError, ValueError) as exc:
            self._store_failed(exc)
            self._rebind.set()
            return
        self._outbox = box
        self._position = position
        self._cursor = max(position, max(self._inflight, default=position))
        if latest is not None and self._latest_doc is None:
            try:
                self._latest_doc = _view(latest)
            except ValueError:
                pass
        self._count()

    def _connect(self) -> None:
        """One connection attempt: TCP (and TLS), CONNECT, then wait for the CONNACK (not
        past a refusal: its socket is closed, and polling it made paho log an error on every
        retry)."""
        self._refused = False
        try:
            self.client.reconnect()
        except (OSError, ssl.SSLError, ValueError) as exc:
            self._unreachable(str(exc) or type(exc).__name__)
            return
        # the CONNACK is waited for while closing too: the closing loop's attempts are how a
        # backlog reaches a broker that is back after the run's end (leaving at once, each
        # attempt's socket was closed by the next before its CONNACK was read: a broker back
        # 25 s after an outage, during the stop, saw a connection a second and got nothing)
        end = time.monotonic() + self.config.connect_timeout
        while not self._connected and not self._refused and time.monotonic() < end:
            if self.client.loop(timeout=0.05) != mqtt.MQTT_ERR_SUCCESS:
                break

    def _unreachable(self, why: str) -> None:
        if self._last_error != why:
            level = logging.WARNING if self._last_error is None else logging.DEBUG
            logger.log(level, "MQTT broker %s:%d unreachable (%s); windows wait in the "
                       "state database and are sent once it answers", self.config.host,
                       self.config.port, why)
        self._last_error = why

    def _on_connect(self, client: mqtt.Client, userdata: Any, flags: Any, reason: Any,
                    properties: Any) -> None:
        if reason.is_failure:
            self._unreachable(f"connection refused: {reason}")
            self._refused = True
            client.disconnect()
            return
        self._connected = True
        self._connected_at = time.monotonic()
        self._down_since = None
        self.connects += 1
        if self._last_error is not None or self.connects > 1:
            logger.warning("MQTT broker %s:%d reached: %d windows pending are sent now",
                           self.config.host, self.config.port, self.pending)
        else:
            logger.info("publishing health of %s on %s (MQTT broker %s:%d)", self.machine,
                        self.health_topic, self.config.host, self.config.port)
        self._last_error = None
        self._announce(client)
        self._wake.set()

    def _announce(self, client: mqtt.Client) -> None:
        """Connected: ``online`` on the availability topic, the discovery (or its clearing)."""
        client.publish(self.availability_topic, "online", qos=1, retain=True)
        ha = self.config.home_assistant
        if ha.discovery:
            client.subscribe(f"{ha.prefix}/status", qos=1)
            self._discovery_sent = None
            self._send_discovery(force=True)
        else:
            client.publish(self.discovery_topic, b"", qos=1, retain=True)

    def _on_disconnect(self, client: mqtt.Client, userdata: Any, flags: Any, reason: Any,
                       properties: Any) -> None:
        if self._connected and not self._stop.is_set():
            self._taken_over(time.monotonic() - self._connected_at)
        if self._connected:
            self.disconnects += 1
            if self._takeovers >= TAKEOVERS:
                logger.debug("MQTT connection of client id %r taken over again", self.client_id)
            elif not self._stop.is_set():
                logger.warning("MQTT connection to %s:%d lost (%s): %d windows in flight are "
                               "sent again on reconnection", self.config.host, self.config.port,
                               reason, len(self._inflight))
        self._connected = False
        if self._down_since is None:
            self._down_since = time.monotonic()

    def _taken_over(self, lasted: float) -> None:
        """A connection lost ``lasted`` seconds after it was made. The broker closes a
        session when another client connects with the same client id (MQTT 3.1.1: no reason
        given); two daemons with one id take it from each other in turn (issue 26: 78
        take-overs in 45 s, 13 of 39 windows never received, about 80 warnings per daemon and
        no line naming the cause). :data:`TAKEOVERS` such losses in a row, each within
        :data:`TAKEOVER_S` of the connection: named once, and the next attempts wait longer
        (doubling from 5 s to 60 s); a connection that lasts resets it."""
        if lasted > TAKEOVER_S:
            if self._takeovers >= TAKEOVERS:
                logger.warning("MQTT client id %r: the connection has lasted %.0f s, no longer "
                               "taken over", self.client_id, lasted)
            self._takeovers = 0
            return
        self._takeovers += 1
        self._takeover_total += 1
        if self._takeovers < TAKEOVERS:
            return
        if self._takeovers == TAKEOVERS:
            logger.error("another client uses client id %r on MQTT broker %s:%d: the "
                         "connection was taken over %d times in a row, each within %.0f s: "
                         "give each daemon its own [outputs.%s] client_id (or machine "
                         "name); connecting less often meanwhile, windows wait in the outbox",
                         self.client_id, self.config.host, self.config.port, self._takeovers,
                         TAKEOVER_S, self.table)
        hold = min(5.0 * 2 ** (self._takeovers - TAKEOVERS), 60.0) * random.uniform(0.75, 1.25)
        self._hold_until = time.monotonic() + hold

    def _on_message(self, client: mqtt.Client, userdata: Any, msg: Any) -> None:
        """Home Assistant's birth message: send the discovery again after a short random
        delay (its documentation asks for one, to spread the load)."""
        if msg.payload.strip().lower() == b"online":
            self._discovery_due = time.monotonic() + random.uniform(0.0, 1.0)

    def _on_publish(self, client: mqtt.Client, userdata: Any, mid: int, reason: Any,
                    properties: Any) -> None:
        row_id = self._mids.pop(mid, None)
        if row_id is None:
            return
        window = self._inflight.get(row_id)
        if window is None:
            return
        window.mids.discard(mid)
        if not window.mids:
            del self._inflight[row_id]
            self._acked.append(window.row)
            self.delivered += 1

    # -- sending ------------------------------------------------------------------------------
    def _send_discovery(self, force: bool = False) -> None:
        self._discovery_due = None
        ha = self.config.home_assistant
        if not ha.discovery or not self._connected:
            return
        ctx = self.context
        payload = json.dumps(discovery_payload(
            self.machine, self.model, self.base, self._latest_doc, self.parameters,
            qos=self.config.qos, device_name=ha.device_name,
            rules=set(ctx.alarm_bands) if ctx is not None else None,
            nominal=dict(ctx.nominal) if ctx is not None and ctx.nominal else None),
            separators=(",", ":"))
        if payload == self._discovery_sent and not force:
            return
        self.client.publish(self.discovery_topic, payload, qos=1, retain=True)
        self._discovery_sent = payload

    def _feed(self, now: float, all_rows: bool) -> None:
        """Hand paho the next pending windows, within the inflight limit and the rate."""
        self._file_changed()
        box = self._outbox
        if box is None or not self._connected:
            return
        self._tokens = min(float(self.config.inflight),
                           self._tokens + (now - self._token_time) * self.config.rate)
        self._token_time = now
        room = min(self.config.inflight - len(self._inflight), int(self._tokens))
        if room <= 0:
            return
        try:
            rows = box.pending(self._cursor, room)
            latest = box.latest_id() if rows else None
            if rows and self._previous_levels is None:
                before = box.doc_at_or_before(rows[0].id - 1)
                self._previous_levels = _levels(_view(before)) if before else {}
        except (StoreError, ValueError) as exc:
            self._store_failed(exc)
            return
        if self._failing_store:
            logger.info("the MQTT outbox in the state database can be read again")
            self._failing_store = False
        if not all_rows:  # a poll: leave the newest windows to write() (their events)
            settled = time.time() - 1.0
            rows = list(itertools.takewhile(lambda r: r.wall < settled, rows))
        for row in rows:
            if row.id in self._inflight:
                continue
            if not self._send(row, newest=row.id == latest):
                break
            self._cursor = max(self._cursor, row.id)
            self._tokens -= 1.0

    def _send(self, row: OutboxRow, newest: bool) -> bool:
        """Publish one window's messages; False if paho refused (the connection is gone)."""
        qos = self.config.qos
        doc: HealthView | None
        try:
            doc = _view(row.doc)
        except ValueError:
            doc = None
        window = _Window(row)
        messages: list[tuple[str, str | bytes, bool]] = [(self.health_topic, row.doc, False)]
        with self._events_lock:
            events = self._events.pop(row.doc, None)
        if events is None:
            events = reconstructed_events(doc, self._previous_levels or {})
        messages += [(f"{self.base}/alarm", json.dumps(e), False) for e in events]
        if newest:
            messages += [(f"{self.base}/{k}", v, True)
                         for k, v in (flat_values(doc) if doc is not None else {}).items()]
        for topic, payload, retain in messages:
            info = self.client.publish(topic, payload, qos=qos, retain=retain)
            if info.rc != mqtt.MQTT_ERR_SUCCESS and info.rc != mqtt.MQTT_ERR_NO_CONN:
                self.errors += 1
                logger.debug("publishing on %s refused: %s", topic, mqtt.error_string(info.rc))
            window.mids.add(info.mid)
            self._mids[info.mid] = row.id
        self._inflight[row.id] = window
        self._previous_levels = _levels(doc)
        if newest and doc is not None and doc.model_fields_set:
            had = self._latest_doc
            self._latest_doc = doc
            if self.config.home_assistant.discovery and (
                    had is None or _components(had) != _components(doc)):
                self._send_discovery()
        return True

    def _position_now(self) -> int:
        if self._inflight:
            return min(self._inflight) - 1
        return self._cursor

    def _flush_acks(self) -> None:
        """Record the delivered windows and the position in the outbox (a failure keeps them
        for the next try)."""
        box = self._outbox
        if box is None or not self._acked:
            return
        acked, position = list(self._acked), self._position_now()
        try:
            box.ack(acked, position)
        except StoreError as exc:
            self._store_failed(exc)
            return
        del self._acked[:len(acked)]
        self._position = position
        self._count()

    def _count(self) -> None:
        self._file_changed()
        box = self._outbox
        if box is None:
            return
        try:
            stored = box.count(self._position)
        except StoreError as exc:
            self._store_failed(exc)
            return
        self.pending = max(stored - len(self._acked), 0)

    def _file_changed(self) -> bool:
        """The state database's file was deleted, replaced or moved away and the store has
        opened the one at the path (noticed by the store at the next window or read): the
        outbox's row ids are stale. The windows in flight and delivered but not yet recorded
        are forgotten (sent again from the new file: at least once), the outbox is bound
        again: the windows the store wrote to the new file and this output had not
        delivered are pending there (delivery went on silently nowhere before, issue 26)."""
        box = self._outbox
        if box is None or not getattr(box, "changed", False):
            return False
        logger.warning("the MQTT output of %s goes on with the state database's new file "
                       "(%d windows in flight or acknowledged and not yet recorded are sent "
                       "again from it)", self.machine, len(self._inflight) + len(self._acked))
        self._inflight.clear()
        self._mids.clear()
        self._acked.clear()
        self._previous_levels = None
        self._outbox = None
        self._rebind_outbox()
        return True

    def _store_failed(self, exc: BaseException) -> None:
        if self._file_changed():
            return
        self.errors += 1
        if not self._failing_store:
            logger.error("the MQTT output cannot use the outbox in the state database (%s): "
                         "tried again", exc)
            self._failing_store = True

    def _finish(self) -> None:
        """Leaving the thread: record the deliveries, go offline, disconnect."""
        self._flush_acks()
        self._count()
        if self._connected:
            infos = self._farewell()
            end = time.monotonic() + 2.0
            while (self._connected and not all(i.is_published() for i in infos)
                   and time.monotonic() < end):
                self.client.loop(timeout=0.05)
            self.client.disconnect()
        self._connected = False
        self._flush_acks()
        if self._memory is not None:
            self.pending = self._memory.count(self._position_now())

    def _farewell(self) -> list[mqtt.MQTTMessageInfo]:
        """A clean stop, still connected: ``offline`` on the availability topic."""
        return [self.client.publish(self.availability_topic, "offline", qos=1, retain=True)]

    def __repr__(self) -> str:
        state = "closed" if self._closed else ("connected" if self._connected else "connecting")
        return f"MqttPublisher({self.health_topic!r}, {state}, delivered={self.delivered})"


def _components(doc: HealthView) -> tuple[frozenset[str], frozenset[str]]:
    """What the discovery depends on in a message: parameters with an alarm rule, with a
    ``rul`` field."""
    from twinwatch.twin.health import sent

    params = doc.parameters or {}
    return (frozenset(_levels(doc)), frozenset(k for k, p in params.items() if sent(p, "rul")))
