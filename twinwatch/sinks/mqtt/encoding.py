"""What the MQTT output publishes for a window, from its typed health message: the retained
plain values (:func:`flat_values`), the alarm events read back from two stored messages
(:func:`reconstructed_events`) and Home Assistant's discovery payload
(:func:`discovery_payload`). No broker, no state.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Collection, Mapping
from typing import TYPE_CHECKING, Any

from twinwatch import __version__

if TYPE_CHECKING:
    from twinwatch.twin.health import DiagnosisView, HealthView, ParameterView


#: what a Home Assistant id may not contain
_HA_ID_RE = re.compile(r"[^A-Za-z0-9_-]")


def _number(value: Any) -> str:
    """A flat value's text: a number as JSON writes it, ``null`` when absent or not finite."""
    if isinstance(value, bool) or value is None:
        return "null" if value is None else json.dumps(value)
    if isinstance(value, int | float):
        return json.dumps(value) if math.isfinite(value) else "null"
    return "null"


def standard_error(value: Any, rel_std_pct: Any) -> float | None:
    """The standard error of ``value`` [its unit] from its relative one ``rel_std_pct`` [%]:
    ``|value| rel_std_pct / 100``; None when either is not a finite number or the relative
    one is not positive. Shared by the MQTT and Sparkplug outputs."""
    if (isinstance(value, int | float) and isinstance(rel_std_pct, int | float)
            and not isinstance(rel_std_pct, bool) and math.isfinite(value)
            and math.isfinite(rel_std_pct) and rel_std_pct > 0):
        return abs(value) * rel_std_pct / 100.0
    return None


def _rounded(value: Any, std: float | None, *, floor: float | None = None,
             digits: int = 6) -> Any:
    """``value`` rounded to what its interval supports: two significant digits of its
    standard error ``std``, never finer than ``floor``; without one, ``digits`` significant
    digits (so a float's rounding noise is published as 0.0)."""
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


def rul_s(param: ParameterView, level: str) -> Any:
    """The median time [s] to ``level``'s threshold (``rul.<level>.rul_s``; ``level``:
    ``"alarm"`` or ``"warning"``), or None without one. Shared by the MQTT and Sparkplug
    outputs."""
    rul = param.rul
    crossing = (rul.alarm if level == "alarm" else rul.warning) if rul is not None else None
    return crossing.rul_s if crossing is not None else None


def known_parameters(parameters: Mapping[str, str], view: HealthView | None
                     ) -> tuple[dict[str, str], Mapping[str, ParameterView]]:
    """The configured parameters (name -> unit) with those ``view`` carries beyond them, and
    ``view``'s parameters."""
    params = dict(parameters)
    doc_params = (view.parameters if view is not None else None) or {}
    for name, p in doc_params.items():
        params.setdefault(name, str(p.unit or ""))
    return params, doc_params


def health_view(doc: HealthView | Mapping[str, Any] | str | bytes) -> HealthView:
    """``doc`` (a typed view, the decoded message or its JSON text) as a typed view.

    Raises:
        ValueError: text that is not a health message (:func:`~twinwatch.twin.health.read_health`).
    """
    from twinwatch.twin.health import HealthView, read_health

    return doc if isinstance(doc, HealthView) else read_health(doc)


def flat_values(doc: HealthView | Mapping[str, Any]) -> dict[str, str]:
    """The retained flat topics of one health message: suffix (``parameters/Ra/value``) ->
    plain-text payload.

    Per parameter: ``value``, ``deviation_pct`` (``null`` when there is none), ``status``;
    ``rul`` and ``rul_warning`` (median seconds to the threshold) when the message has a
    ``rul`` field; ``alarm`` (the level) when the parameter has an alarm rule.
    """
    from twinwatch.twin.health import sent

    doc = health_view(doc)
    out: dict[str, str] = {}
    alarms = doc.alarms or {}
    for name, p in (doc.parameters or {}).items():
        base = f"parameters/{name}"
        value, dev, rel = p.value, p.deviation_pct, p.rel_std_pct
        std = standard_error(value, rel)
        out[f"{base}/value"] = _number(_rounded(value, std))
        nom = p.nominal
        dev_std = (std / abs(nom) * 100.0
                   if isinstance(nom, int | float) and nom and std else None)
        out[f"{base}/deviation_pct"] = _number(_rounded(dev, dev_std, floor=1e-4))
        out[f"{base}/status"] = str(p.status or "")
        if sent(p, "rul"):
            out[f"{base}/rul"] = _number(rul_s(p, "alarm"))
            out[f"{base}/rul_warning"] = _number(rul_s(p, "warning"))
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
    ``no_fault`` / ``unknown`` / ``check_function``), ``diagnosis/probability`` [%],
    ``diagnosis/action`` (never empty: an empty retained payload deletes the topic; at most
    255 characters, Home Assistant's limit of a state)."""
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


def levels(doc: HealthView | None) -> dict[str, str]:
    """Each alarm rule's level in ``doc`` (``normal``, ``warning``, ``alarm``)."""
    alarms = (doc.alarms if doc is not None else None) or {}
    return {k: str(v.level or "normal") for k, v in alarms.items() if v is not None}


def reconstructed_events(doc: HealthView | None, previous: dict[str, str]
                         ) -> list[dict[str, Any]]:
    """Alarm-level changes between the previous stored message's levels and ``doc``'s (None:
    an unreadable message, no change), as events marked ``"reconstructed": true``."""
    events: list[dict[str, Any]] = []
    if doc is None:
        return events
    params = doc.parameters or {}
    for name, level in levels(doc).items():
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
    """Home Assistant's device-based discovery payload for one machine (abbreviated keys).

    Args:
        machine: the machine name.
        model: the twin model (the device's model).
        base: the machine's topic base ``<prefix>/<machine>``.
        doc: the newest health message, or None: which parameters have an alarm rule and a
            ``rul`` field.
        parameters: parameter name -> SI unit (the twin's, in order).
        qos: the QoS Home Assistant subscribes with.
        device_name: the device's name (default: the machine name).
        rules: the parameters with an ``[alarms]`` rule: their alarm and RUL entities are
            announced before any health message.
        nominal: parameter -> nominal value, for each value entity's display precision.

    Returns:
        The payload: ``dev``, ``o``, ``avty_t``, ``qos`` and ``cmps``: per parameter sensors
        for its value, deviation [%] and status; a ``binary_sensor`` per alarm rule; a
        duration sensor [s] for the RUL where the message has one; the diagnosis' sensors
        unless the message has no ``diagnosis``.
    """
    from twinwatch.twin.health import sent

    view = health_view(doc) if doc is not None else None
    dev_id = ha_device_id(machine)
    params, doc_params = known_parameters(parameters, view)
    alarms = set(levels(view)) | set(rules or ())
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


def components(doc: HealthView) -> tuple[frozenset[str], frozenset[str]]:
    """What the discovery depends on in a message: parameters with an alarm rule, with a
    ``rul`` field."""
    from twinwatch.twin.health import sent

    params = doc.parameters or {}
    return (frozenset(levels(doc)), frozenset(k for k, p in params.items() if sent(p, "rul")))
