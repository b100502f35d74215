"""The OPC UA information model of one machine and the encoding of a window into it: the NE 107
device health (:func:`device_health`), the window's values by node path (:func:`flat_values`),
the nodes of a machine (:class:`_Builder`) with their engineering units and ranges, and the
window's source time stamps.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

from twinwatch.sinks.opcua import _ua

# the real modules once a server opens (:func:`~twinwatch.sinks.opcua._ua.rebinds`)
asyncua: Any = _ua.asyncua
ua: Any = _ua.ua
_ua.rebinds(globals())

if TYPE_CHECKING:
    from twinwatch.sinks.base import SinkContext
    from twinwatch.twin.health import AlarmStatus, DiagnosisHealth, HealthMessage, ParameterHealth

__all__ = ["COUNTERS_EVERY_S", "DEVICE_HEALTH", "SEVERITY", "device_health", "flat_values"]

#: The counters are written at most this often [s of plant time] (every window's other values
#: are written as they change).
COUNTERS_EVERY_S = 10.0

#: OPC UA Part 100 (Devices) DeviceHealthEnumeration: NAMUR NE 107's states, by value.
DEVICE_HEALTH: Mapping[str, int] = {"NORMAL": 0, "FAILURE": 1, "CHECK_FUNCTION": 2,
                                    "OFF_SPEC": 3, "MAINTENANCE_REQUIRED": 4}

_NAN = "NaN"  # a NaN's key among the values written last
_WALL_CLOCK_FROM = 946_684_800.0  # 2000-01-01: a source time after it is on the wall clock

#: Alarm event severity by the level an event moves to (OPC UA 1..1000).
SEVERITY: Mapping[str, int] = {"alarm": 800, "warning": 500, "normal": 200}

#: UN/CEFACT common codes of the SI units the twins use (EUInformation.UnitId); others -1.
_CEFACT: Mapping[str, str] = {"ohm": "OHM", "H": "81", "A": "AMP", "V": "VLT", "s": "SEC",
                              "rad/s": "2A", "rad": "C81", "kg m^2": "B32", "N m": "NU",
                              "Pa": "PAL", "m": "MTR", "m/s": "MTS", "N": "NEW", "kg": "KGM",
                              "m^3/s": "MQS", "W": "WTT", "1/s": "C97"}
_UNITS_URI = "http://www.opcfoundation.org/UA/units/un/cefact"


def device_health(health: HealthMessage) -> tuple[int, str]:
    """The window's DeviceHealth (OPC UA Part 100, NAMUR NE 107) and why, for a person: the
    first that applies (docs/opcua-output.md's table): ``FAILURE`` (a deviation alarm),
    ``CHECK_FUNCTION`` (the diagnosis' check function, a silent source), ``OFF_SPEC`` (a
    deviation warning), ``MAINTENANCE_REQUIRED`` (a RUL level raised, a raised fault alarm),
    else ``NORMAL``.

    Args:
        health: the window's typed health message.

    Returns:
        ``(value, reason)``: a :data:`DEVICE_HEALTH` value and one line.
    """
    alarms = health.alarms
    diag = health.diagnosis
    dev_alarm = [n for n, a in alarms.items() if a.level == "alarm"]
    if dev_alarm:
        return (DEVICE_HEALTH["FAILURE"], "failure: " + "; ".join(
            f"{n} beyond its alarm threshold (inspect the machine now)" for n in dev_alarm))
    if diag is not None and diag.status == "check_function":
        return (DEVICE_HEALTH["CHECK_FUNCTION"], "check function: the twin does not describe "
                "this machine" + (f" ({diag.check_failed})" if diag.check_failed else ""))
    if health.source.silent:
        return (DEVICE_HEALTH["CHECK_FUNCTION"],
                "check function: silent on the bus: " + ", ".join(health.source.silent))
    warn = [n for n, a in alarms.items() if a.level == "warning"]
    if warn:
        return (DEVICE_HEALTH["OFF_SPEC"],
                "off spec: " + "; ".join(f"{n} beyond its warning threshold" for n in warn))
    todo = [f"{n} RUL {a.rul.level}" for n, a in alarms.items()
            if a.rul is not None and a.rul.level != "normal"]
    todo += [f"fault {f} (urgency {u}): {action}" if action else f"fault {f} (urgency {u})"
             for f, u, action in _raised_faults(diag)]
    if todo:
        return DEVICE_HEALTH["MAINTENANCE_REQUIRED"], "maintenance required: " + "; ".join(todo)
    return DEVICE_HEALTH["NORMAL"], "normal"


def _raised_faults(diag: DiagnosisHealth | None) -> list[tuple[str, str, str]]:
    """(fault id, urgency, action) of the diagnosis' raised fault alarms (the check function
    aside)."""
    if diag is None:
        return []
    known = {f.id: f for f in diag.faults}
    return [(f, known[f].urgency, known[f].action) if f in known else (f, "medium", "")
            for f in diag.alarms if f != "check_function"]


class _Machine:
    """One machine's nodes: its object, the variables by path, the run's clock anchor."""

    def __init__(self, name: str, obj: Any, stale_after: float) -> None:
        self.name = name
        self.obj = obj
        self.stale_after = stale_after                  # s without a window: CHECK_FUNCTION
        self.vars: dict[str, tuple[Any, Any]] = {}     # path -> (NodeId, VariantType)
        self.anchor: tuple[str, float] | None = None    # (run, wall - plant) for plant time
        self.last_window = time.monotonic()
        self.stale = False
        self.health: tuple[int, str] = (DEVICE_HEALTH["NORMAL"], "no window yet")
        self.events: list[Any] = []                     # event generators (machine, Server)
        self.last: dict[str, tuple[Any, int | None]] = {}  # path -> what was written last
        self.nodes: list[Any] = []                      # every node made for it
        self.active: dict[str, dict[str, Any]] = {}     # condition -> its raising event
        self.counters_t: float | None = None            # plant time the counters were written


_PARAM_LEAVES: tuple[tuple[str, str], ...] = (
    ("Low", "Double"), ("High", "Double"), ("Status", "String"), ("Nominal", "Double"),
    ("Deviation_pct", "Double"), ("RelStd_pct", "Double"), ("AlarmLevel", "String"),
    ("RulAlarmLevel", "String"), ("Trend.Model", "String"), ("Trend.Rate", "Double"),
    ("Trend.RateLow", "Double"), ("Trend.RateHigh", "Double"), ("Trend.RatePctPerHour", "Double"),
    ("Trend.Degrading", "Boolean"), ("RUL.Status", "String"), ("RUL.Alarm_s", "Double"),
    ("RUL.AlarmLow_s", "Double"), ("RUL.AlarmHigh_s", "Double"), ("RUL.Warning_s", "Double"),
    ("RUL.WarningLow_s", "Double"), ("RUL.WarningHigh_s", "Double"))

_DIAG_LEAVES: tuple[tuple[str, str], ...] = (
    ("Status", "String"), ("TopFault", "String"), ("Part", "String"), ("Probability", "Double"),
    ("Action", "String"), ("Urgency", "String"), ("NoFault", "Double"), ("Unknown", "Double"),
    ("Alarms", "String"), ("Faults.Ids", "String"), ("Faults.Parts", "String"),
    ("Faults.Probabilities", "Double"), ("Faults.Actions", "String"),
    ("Faults.Urgencies", "String"))


class _Builder:
    """The AddNodesItems of one machine, created in one AddNodes call."""

    def __init__(self, ns: int, machine: str) -> None:
        self.ns = ns
        self.machine = machine
        self.items: list[Any] = []
        self.references: list[Any] = []
        self.nodes: dict[str, Any] = {}

    def _add(self, path: str | None, browse: Any, parent: Any, reference: Any, node_class: Any,
             type_definition: Any, attrs: Any) -> Any:
        nid = ua.NodeId(self.machine if path is None else f"{self.machine}.{path}", self.ns)
        item = ua.AddNodesItem()
        item.RequestedNewNodeId = nid
        item.BrowseName = browse
        item.ParentNodeId = parent
        item.ReferenceTypeId = ua.NodeId(reference)
        item.NodeClass = node_class
        item.TypeDefinition = type_definition
        item.NodeAttributes = attrs
        self.items.append(item)
        return nid

    def object(self, m: _Machine | None, path: str | None, parent: Any, *,
               browse: str | None = None, folder_parent: bool = False) -> Any:
        name = browse or (path or self.machine).rsplit(".", 1)[-1]
        attrs = ua.ObjectAttributes()
        attrs.DisplayName = ua.LocalizedText(name)
        attrs.Description = ua.LocalizedText(name)
        attrs.EventNotifier = 1 if path is None else 0   # the machine: SubscribeToEvents
        attrs.WriteMask = attrs.UserWriteMask = 0
        nid = self._add(path, ua.QualifiedName(name, self.ns), parent,
                        ua.ObjectIds.Organizes if folder_parent else ua.ObjectIds.HasComponent,
                        ua.NodeClass.Object, ua.NodeId(ua.ObjectIds.BaseObjectType), attrs)
        if path is None:  # the Server object notifies of the machine's events
            ref = ua.AddReferencesItem()
            ref.SourceNodeId = ua.NodeId(ua.ObjectIds.Server)
            ref.ReferenceTypeId = ua.NodeId(ua.ObjectIds.HasNotifier)
            ref.IsForward = True
            ref.TargetNodeId = nid
            ref.TargetNodeClass = ua.NodeClass.Object
            self.references.append(ref)
        if path is not None:
            self.nodes[path] = nid
        return nid

    def variable(self, m: _Machine, parent: Any, path: str, value: Any, datatype: Any, *,
                 browse: str | None = None, vtype: Any = None, history: bool = False) -> Any:
        name = browse or path.rsplit(".", 1)[-1]
        nid = self._add(path, ua.QualifiedName(name, self.ns), parent, ua.ObjectIds.HasComponent,
                        ua.NodeClass.Variable,
                        vtype or ua.NodeId(ua.ObjectIds.BaseDataVariableType),
                        _var_attrs(name, value, datatype, history=history))
        m.vars[path] = (nid, value.VariantType)
        return nid

    def prop(self, parent: Any, path: str, browse: str, value: Any, datatype: Any) -> Any:
        return self._add(path, ua.QualifiedName(browse, 0), parent, ua.ObjectIds.HasProperty,
                         ua.NodeClass.Variable, ua.NodeId(ua.ObjectIds.PropertyType),
                         _var_attrs(browse, value, datatype))


def _var_attrs(name: str, value: Any, datatype: Any, *, history: bool = False) -> Any:
    """A read-only variable's attributes: ``AccessLevel`` ``CurrentRead``, with ``HistoryRead``
    (and ``Historizing``) only where ``history`` is kept."""
    attrs = ua.VariableAttributes()
    attrs.DisplayName = ua.LocalizedText(name)
    attrs.Description = ua.LocalizedText(name)
    attrs.DataType = datatype
    attrs.Value = value
    if isinstance(value.Value, list):
        attrs.ValueRank = ua.ValueRank.OneDimension
        attrs.ArrayDimensions = [0]
    else:
        attrs.ValueRank = ua.ValueRank.Scalar
    attrs.WriteMask = attrs.UserWriteMask = 0
    access = ua.AccessLevel.CurrentRead.mask
    if history:
        access |= ua.AccessLevel.HistoryRead.mask
    attrs.AccessLevel = attrs.UserAccessLevel = access
    attrs.Historizing = history
    return attrs


def _eu(unit: str) -> Any:
    """EUInformation of an SI unit (UN/CEFACT code where there is one, else UnitId -1)."""
    code = _CEFACT.get(unit)
    unit_id = -1
    if code is not None:
        unit_id = 0
        for c in code:
            unit_id = (unit_id << 8) | ord(c)
    return ua.EUInformation(NamespaceUri=_UNITS_URI, UnitId=unit_id,
                            DisplayName=ua.LocalizedText(unit),
                            Description=ua.LocalizedText(unit))


def _eu_range(p: str, ctx: SinkContext) -> Any:
    """EURange: the parameter's ``[alarms]`` alarm band around nominal when it has a rule
    (what a bar graph should span), else 0 .. 2 x nominal."""
    nom = float(ctx.nominal.get(p, math.nan))
    bands = ctx.alarm_bands.get(p)
    if not math.isfinite(nom):
        return ua.Range(Low=math.nan, High=math.nan)
    lo, hi = 0.0, 2.0 * nom
    if bands is not None:
        high = bands.alarm_high if bands.alarm_high is not None else bands.warning_high
        low = bands.alarm_low if bands.alarm_low is not None else bands.warning_low
        if high is not None:
            hi = nom * (1.0 + high / 100.0)
        if low is not None:
            lo = nom * (1.0 + low / 100.0)
    return ua.Range(Low=min(lo, hi), High=max(lo, hi))


def _source_time(m: _Machine, run: str | None, t: float, now: datetime) -> datetime:
    """The wall-clock time of plant time ``t``: ``t`` itself on a wall-clock source, else
    anchored once per run (the run's first window written at ``now``)."""
    if t >= _WALL_CLOCK_FROM:
        return datetime.fromtimestamp(t, UTC)
    if run is not None and (m.anchor is None or m.anchor[0] != run):
        m.anchor = (run, now.timestamp() - t)
    offset = m.anchor[1] if m.anchor is not None else now.timestamp() - t
    return datetime.fromtimestamp(offset + t, UTC)


def _num(x: Any) -> float:
    return float(x) if isinstance(x, int | float) and not isinstance(x, bool) else math.nan


_PARAM_STATUS: Mapping[str, int] = {"held": 0x40900000,     # UncertainLastUsableValue
                                    "suspect": 0x40000000}  # Uncertain


def flat_values(h: HealthMessage, health: tuple[int, str], counters: bool = True
                ) -> dict[str, tuple[Any, int | None]]:
    """The window's values by node path (``Parameters.Ra.Value``), each with its OPC UA status
    code (None: Good). A null of the message is NaN (numbers) or ``""`` (texts).

    Args:
        h: the typed health message.
        health: its :func:`device_health`.
        counters: with the ``Counters.<name>`` values (False: a window whose counters are not
            written, :data:`COUNTERS_EVERY_S`).
    """
    out: dict[str, tuple[Any, int | None]] = {
        "DeviceHealth": (health[0], None), "DeviceHealthReason": (health[1], None),
        "Model": (h.model, None), "Run": (h.run, None), "Window": (h.window, None),
        "WindowStart_s": (h.t_start, None), "WindowEnd_s": (h.t_end, None),
        "Trusted": (h.trusted, None), "NRMSE": (_num(h.nrmse), None),
        "Terms": ([t.equation for t in h.terms], None)}
    for name, p in h.parameters.items():
        _parameter_values(out, f"Parameters.{name}.", p, h.alarms.get(name))
    if h.diagnosis is not None:
        out.update(_diagnosis_values(h.diagnosis))
    if counters:
        for name, v in h.counters.items():
            out[f"Counters.{name}"] = (int(v), None)
    return out


def _parameter_values(out: dict[str, tuple[Any, int | None]], base: str, p: ParameterHealth,
                      a: AlarmStatus | None) -> None:
    """One parameter's values (its value, 2-sigma interval, status, alarm levels, trend and
    RUL) into ``out`` under ``base`` (``Parameters.Ra.``)."""
    value = _num(p.value)
    half = 2.0 * abs(value) * (_num(p.rel_std_pct) / 100.0)
    out[base + "Value"] = (value, _PARAM_STATUS.get(p.status))
    out[base + "Low"] = (value - half, None)
    out[base + "High"] = (value + half, None)
    out[base + "Status"] = (p.status, None)
    out[base + "Nominal"] = (_num(p.nominal), None)
    out[base + "Deviation_pct"] = (_num(p.deviation_pct), None)
    out[base + "RelStd_pct"] = (_num(p.rel_std_pct), None)
    out[base + "AlarmLevel"] = (a.level if a is not None else "", None)
    out[base + "RulAlarmLevel"] = (a.rul.level if a is not None and a.rul is not None
                                   else "", None)
    t = p.trend
    if t is None:
        trend: tuple[Any, ...] = ("", math.nan, math.nan, math.nan, math.nan, False)
    else:
        trend = (t.model or "", _num(t.rate), _num(t.rate_low), _num(t.rate_high),
                 _num(t.rate_pct_per_h), bool(t.degrading))
    for key, v in zip(("Model", "Rate", "RateLow", "RateHigh", "RatePctPerHour", "Degrading"),
                      trend, strict=True):
        out[base + "Trend." + key] = (v, None)
    rul = p.rul
    out[base + "RUL.Status"] = (rul.status if rul is not None else "", None)
    for level, c in (("Alarm", rul.alarm if rul else None),
                     ("Warning", rul.warning if rul else None)):
        out[base + f"RUL.{level}_s"] = (_num(c.rul_s) if c else math.nan, None)
        out[base + f"RUL.{level}Low_s"] = (_num(c.low_s) if c else math.nan, None)
        out[base + f"RUL.{level}High_s"] = (_num(c.high_s) if c else math.nan, None)


def _diagnosis_values(d: DiagnosisHealth) -> dict[str, tuple[Any, int | None]]:
    """The diagnosis' values: its status, the top fault's part, probability, action and
    urgency, and the ranked list."""
    top = d.faults[0] if d.status == "fault" and d.faults else None
    return {
        "Diagnosis.Status": (d.status, None),
        "Diagnosis.TopFault": (top.id if top else "", None),
        "Diagnosis.Part": (top.component if top else "", None),
        "Diagnosis.Probability": (float(d.probability), None),
        "Diagnosis.Action": (top.action if top else "", None),
        "Diagnosis.Urgency": (top.urgency if top else "", None),
        "Diagnosis.NoFault": (float(d.no_fault), None),
        "Diagnosis.Unknown": (float(d.unknown), None),
        "Diagnosis.Alarms": (list(d.alarms), None),
        "Diagnosis.Faults.Ids": ([f.id for f in d.faults], None),
        "Diagnosis.Faults.Parts": ([f.component for f in d.faults], None),
        "Diagnosis.Faults.Probabilities": ([float(f.probability) for f in d.faults], None),
        "Diagnosis.Faults.Actions": ([f.action for f in d.faults], None),
        "Diagnosis.Faults.Urgencies": ([f.urgency for f in d.faults], None)}
