"""The fleet summary: one machine's health in a few hundred bytes, what crosses sites.

The full health message (:mod:`twinwatch.twin.health`, about 11 kB a window) stays on a box's
own router and in its state database; each machine also publishes a compact summary on
``<key_prefix>/<machine>/summary`` (docs/fleet.md, "The fleet summary") that a fleet view and
the fleet report read (:mod:`twinwatch.watch.ranking`). It is built from one window's
message by :func:`fleet_summary` and published when it changed (:func:`summary_changed`) and
at least every ``[zenoh] summary_interval`` seconds.

Layout, version :data:`SUMMARY_SCHEMA` (plain JSON types; numbers rounded)::

    {"summary": 1, "machine": "m1", "model": "dc_motor", "box": "gw-line1", "run": "...",
     "window": 299, "t_end": 599.99, "wall": 1764043200.5,
     "state": "normal" | "warning" | "alarm" | "check_function",
     "alarms": {"Ra": {"level": "normal", "rul": "warning"}},
     "deviation": {"Ra": -1.85},
     "diagnosis": {"status": "fault", "fault": "winding_short", "probability": 0.95,
                   "part": "armature winding", "action": "...", "urgency": "high",
                   "alarm": true} | null,
     "rul": {"parameter": "Ra", "status": "predicted", "median_s": 479.4, "low_s": 475.1,
             "high_s": 483.7} | null}

``state``: ``alarm`` when a parameter's level or its RUL level is ``alarm`` or the
diagnosis' fault alarm is raised; ``check_function`` when the diagnosis says the twin does not
describe the machine (NAMUR NE 107); ``warning`` when a level is ``warning``; else
``normal``. ``alarms`` and ``deviation``: each parameter with an alarm rule (its level, the
level on its RUL, its deviation from nominal [%]). ``rul``: the remaining useful life to the
alarm threshold of the parameter that reaches it first (by its interval's earliest end), from
the window's end [s]: median and 95 % interval (``high_s`` null: some draws never reach it);
``status`` ``crossed`` (beyond it now, 0 s) or ``predicted``; null when no parameter is
predicted to cross. ``diagnosis``: the most probable outcome and, for ``fault``, the fault,
its part, action and urgency; ``alarm``: its probability alarm is raised. ``wall``: when the
summary was made [s since the epoch].
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from twinwatch.twin.health import HealthView

SUMMARY_SCHEMA = 1
"""The summary's layout version (its ``summary`` field)."""

STATES = ("normal", "warning", "alarm", "check_function")
"""The summary's ``state`` values."""

RUL_CHANGE = 0.1
"""A RUL median that moved by more than this share since the last published summary is a
change (published at once)."""

__all__ = ["RUL_CHANGE", "STATES", "SUMMARY_SCHEMA", "fleet_summary", "summary_changed"]


def _num(x: Any, digits: int = 4) -> float | None:
    """A finite number rounded to ``digits`` significant digits, else None."""
    if not isinstance(x, int | float) or isinstance(x, bool) or not math.isfinite(x):
        return None
    if x == 0:
        return 0.0
    return float(f"{x:.{digits}g}")


def _rul(health: HealthView) -> dict[str, Any] | None:
    """The soonest crossing of an alarm threshold among the parameters (by the interval's
    earliest end, then the median)."""
    best: tuple[float, float, dict[str, Any]] | None = None
    for name, p in (health.parameters or {}).items():
        rul = p.rul if p is not None else None
        crossing = rul.alarm if rul is not None else None
        if crossing is None or crossing.status not in ("crossed", "predicted"):
            continue
        median: float | None
        low: float | None
        high: float | None
        if crossing.status == "crossed":
            median, low, high = 0.0, 0.0, 0.0
        else:
            median, low, high = (_num(crossing.rul_s), _num(crossing.low_s),
                                 _num(crossing.high_s))
            if median is None:
                continue
        entry: dict[str, Any] = {"parameter": name, "status": crossing.status,
                                 "median_s": median, "low_s": low, "high_s": high}
        first = low if low is not None else median
        assert median is not None and first is not None
        if best is None or (first, median) < best[:2]:
            best = (first, median, entry)
    return best[2] if best is not None else None


def _diagnosis(health: HealthView) -> dict[str, Any] | None:
    d = health.diagnosis
    if d is None:
        return None
    faults = d.faults or []
    top = faults[0] if d.status == "fault" and faults else None
    return {"status": d.status,
            "fault": top.id if top is not None else None,
            "probability": _num(d.probability, 3),
            "part": top.component if top is not None else None,
            "action": top.action if top is not None else None,
            "urgency": top.urgency if top is not None else None,
            "alarm": bool(top is not None and top.id in (d.alarms or []))}


def fleet_summary(health: HealthView, *, box: str, wall: float) -> dict[str, Any]:
    """The fleet summary of one window's health message (the module docstring gives its
    layout).

    Args:
        health: the window's message, the daemon's own or its readers' typed view
            (:func:`~twinwatch.twin.health.read_health`: a part the message lacks is None).
        box: what identifies the publishing daemon's host (``[zenoh] box``, its host name by
            default): the fleet view groups machines by it.
        wall: the wall time the summary is made [s since the epoch].

    Returns:
        The summary as plain JSON types (about 300-500 bytes as JSON).
    """
    alarms: dict[str, dict[str, str | None]] = {}
    deviation: dict[str, float | None] = {}
    levels: set[str] = set()
    params = health.parameters or {}
    for name, a in (health.alarms or {}).items():
        if a is None:
            continue
        rul_level = a.rul.level if a.rul is not None else None
        alarms[name] = {"level": a.level, "rul": rul_level}
        levels.update(x for x in (a.level, rul_level) if x is not None)
        p = params.get(name)
        deviation[name] = _num(p.deviation_pct if p is not None else None)
    diagnosis = _diagnosis(health)
    if "alarm" in levels or (diagnosis is not None and diagnosis["alarm"]):
        state = "alarm"
    elif diagnosis is not None and diagnosis["status"] == "check_function":
        state = "check_function"
    elif "warning" in levels:
        state = "warning"
    else:
        state = "normal"
    return {"summary": SUMMARY_SCHEMA, "machine": health.machine, "model": health.model,
            "box": box, "run": health.run, "window": health.window,
            "t_end": _num(health.t_end, 8), "wall": round(wall, 3), "state": state,
            "alarms": alarms, "deviation": deviation, "diagnosis": diagnosis,
            "rul": _rul(health)}


def summary_changed(old: dict[str, Any] | None, new: dict[str, Any]) -> bool:
    """Whether ``new`` says something ``old`` (the last published) did not: the state, an
    alarm level, the diagnosis' outcome, fault, urgency or alarm, the RUL's parameter or
    status, or its median moved by more than :data:`RUL_CHANGE` of it. Deviations and
    probabilities that drift every window are not a change (they go out at the interval).
    """
    if old is None:
        return True
    if (old.get("state"), old.get("alarms"), old.get("run")) != (
            new.get("state"), new.get("alarms"), new.get("run")):
        return True
    keys = ("status", "fault", "urgency", "alarm")
    od, nd = old.get("diagnosis") or {}, new.get("diagnosis") or {}
    if any(od.get(k) != nd.get(k) for k in keys):
        return True
    orul, nrul = old.get("rul"), new.get("rul")
    if (orul is None) != (nrul is None):
        return True
    if orul is None or nrul is None:
        return False
    if (orul.get("parameter"), orul.get("status")) != (nrul.get("parameter"),
                                                       nrul.get("status")):
        return True
    a, b = orul.get("median_s"), nrul.get("median_s")
    if not isinstance(a, int | float) or not isinstance(b, int | float):
        return bool(a != b)
    return bool(abs(b - a) > RUL_CHANGE * max(abs(a), 1.0))
