"""The device metrics of a machine (what a DBIRTH announces and a DDATA carries), read from the
typed health message: pure functions, no I/O.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from twinwatch.sinks.mqtt.encoding import (
    diagnosis_values,
    known_parameters,
    rul_s,
    standard_error,
)

if TYPE_CHECKING:
    from twinwatch.twin.health import HealthView

__all__ = ["MetricSpec", "metric_specs", "metric_values", "set_value"]

_ALARM_LEVEL = {"normal": 0, "warning": 1, "alarm": 2}


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

    params, doc_params = known_parameters(parameters, doc)
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
        std = standard_error(value, p.rel_std_pct)
        out[f"{base}/Value"] = value
        out[f"{base}/Low"] = value - 2 * std if value is not None and std else None
        out[f"{base}/High"] = value + 2 * std if value is not None and std else None
        out[f"{base}/Deviation"] = _num(p.deviation_pct)
        out[f"{base}/Status"] = None if p.status is None else str(p.status)
        a = alarms.get(name)
        level = str(a.level or "normal") if a is not None else None
        out[f"{base}/Alarm"] = level
        out[f"{base}/Alarm Level"] = _ALARM_LEVEL.get(level) if level is not None else None
        out[f"{base}/RUL"] = _num(rul_s(p, "alarm"))
        out[f"{base}/RUL Warning"] = _num(rul_s(p, "warning"))
    if doc.diagnosis is not None:
        flat = diagnosis_values(doc.diagnosis)
        out["Diagnosis/Status"] = str(doc.diagnosis.status or "no_fault")
        out["Diagnosis/Fault"] = flat["diagnosis/fault"]
        out["Diagnosis/Probability"] = _num(json.loads(flat["diagnosis/probability"]))
        out["Diagnosis/Action"] = flat["diagnosis/action"]
    for name, count in (doc.counters or {}).items():
        out[f"Counters/{name}"] = count if isinstance(count, int) else None
    return out


def set_value(metric: Any, datatype: str, value: Any) -> None:
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
