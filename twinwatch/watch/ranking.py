"""The fleet's question from the machines' summaries (:mod:`twinwatch.twin.summary`): which
machines first (:func:`urgency`, :func:`fleet_view`: ``twinwatch watch --fleet``) and which
need service within a horizon (:func:`due`, :func:`service_report`: ``twinwatch fleet
report``). Pure functions of the summaries as received (plain JSON types), the wall time they
arrived and the wall time now; no Zenoh.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from twinwatch.watch.view import number

URGENCY_RANK = {"high": 3, "medium": 2, "low": 1}
"""A fault mode's ``urgency`` as a rank (higher first)."""

STATE_RANK = {"alarm": 3, "check_function": 2, "warning": 1, "normal": 0}
"""A summary's ``state`` as a rank (higher first)."""

URGES_PROBABILITY = 0.5
"""A diagnosed fault of urgency ``high`` this probable urges action even before its
probability alarm is raised (``[diagnosis] alarm``, 0.8 for 3 windows)."""

STALE_AFTER_S = 180.0
"""A machine whose last summary arrived longer ago than this is shown ``stale`` [s] (3
``[zenoh] summary_interval`` of 60 s)."""


@dataclass(frozen=True)
class Received:
    """One machine's last summary, the wall time [s since the epoch] it arrived and its
    :func:`urgency` (computed once, when it arrived: a view of 10 000 machines sorts these);
    ``gone_at``: when its presence (its daemon's liveliness token, or its box's) went, None
    while it is there: a stopped daemon's machines are stale at once."""

    summary: Mapping[str, Any]
    at: float
    key: tuple[float, float, float, str] = field(default=(0.0, 0.0, 0.0, ""), compare=False)
    gone_at: float | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "key", urgency(self.summary))

    @property
    def made(self) -> float:
        """When the summary was made [s since the epoch]: its ``wall``, but never after it
        arrived (a box's clock ahead of this one's), else its arrival. A summary asked
        with a get arrives now but may be up to ``[zenoh] summary_interval`` old: its RUL
        has run down meanwhile."""
        wall = number(self.summary.get("wall"))
        return min(wall, self.at) if wall is not None and math.isfinite(wall) else self.at


def diagnosis_rank(summary: Mapping[str, Any]) -> int:
    """How strongly the diagnosis urges action: a raised fault alarm 4; a fault at least
    :data:`URGES_PROBABILITY` probable its urgency's rank (high 3, medium 2, low 1);
    ``check_function`` 2 (the twin cannot see the machine); an ``unknown`` fault that
    probable 1; else 0."""
    d = summary.get("diagnosis")
    if not isinstance(d, Mapping):
        return 0
    p = number(d.get("probability")) or 0.0
    if d.get("status") == "fault":
        if d.get("alarm"):
            return 4
        return URGENCY_RANK.get(str(d.get("urgency")), 0) if p >= URGES_PROBABILITY else 0
    if d.get("status") == "check_function":
        return 2
    if d.get("status") == "unknown" and p >= URGES_PROBABILITY:
        return 1
    return 0


def rul_median(summary: Mapping[str, Any]) -> float | None:
    """The soonest RUL median to an alarm threshold [s from the summary's window], or None."""
    rul = summary.get("rul")
    return number(rul.get("median_s")) if isinstance(rul, Mapping) else None


def urgency(summary: Mapping[str, Any]) -> tuple[float, float, float, str]:
    """The sort key of a machine, most urgent first: its state (alarm, check_function,
    warning, normal), how strongly its diagnosis urges action (:func:`diagnosis_rank`), its
    RUL median (sooner first; none last), its name."""
    rul = rul_median(summary)
    return (-STATE_RANK.get(str(summary.get("state")), 0), -diagnosis_rank(summary),
            rul if rul is not None else math.inf, str(summary.get("machine", "")))


def seen(r: Received, now: float, stale_after: float = STALE_AFTER_S) -> str:
    """``stale`` when the machine's presence went (its daemon stopped: its liveliness token
    is gone) or its summary arrived more than ``stale_after`` [s] ago (the link, whatever the
    clocks), else ``alive``."""
    return "stale" if r.gone_at is not None or now - r.at > stale_after else "alive"


def entry(r: Received, now: float, stale_after: float = STALE_AFTER_S) -> dict[str, Any]:
    """One machine's row of the fleet view: its summary plus ``age_s`` (since it was made:
    :attr:`Received.made`), ``seen`` (:func:`seen`) and ``gone_s`` (since its presence went,
    None while it is there)."""
    return {**r.summary, "age_s": round(max(now - r.made, 0.0), 1),
            "seen": seen(r, now, stale_after),
            "gone_s": None if r.gone_at is None else round(max(now - r.gone_at, 0.0), 1)}


def fleet_view(received: Mapping[str, Received], now: float, *,
               states: Collection[str] = (), models: Collection[str] = (),
               limit: int | None = None, stale_after: float = STALE_AFTER_S
               ) -> dict[str, Any]:
    """The fleet ranked by urgency (:func:`urgency`), filtered and counted by box.

    Args:
        received: machine -> its last summary.
        now: wall time [s since the epoch].
        states: keep only these states (a summary's ``state``, or ``stale``/``alive``:
            whether a summary came within ``stale_after``); empty: every one.
        models: keep only these twin models; empty: every one.
        limit: rows listed (the most urgent; None: every matching machine).
        stale_after: [s], see :func:`entry`.

    Returns:
        ``{"t", "machines_total", "matched", "shown", "more", "states": {state: n},
        "boxes": {box: {"machines", "alarm", "warning", "check_function", "normal",
        "stale", "first"}}, "machines": [entry, ...]}``: counts of the matching machines;
        ``first``: each box's most urgent machine; ``more``: matching machines not listed.
    """
    wanted = set(states)
    rows: list[tuple[tuple[float, float, float, str], Received, str]] = []
    counts: dict[str, int] = {}
    boxes: dict[str, dict[str, Any]] = {}
    for r in received.values():  # each machine once; a row is made for those shown only
        s = r.summary
        was = seen(r, now, stale_after)
        state = str(s.get("state"))
        if wanted and state not in wanted and was not in wanted:
            continue
        if models and s.get("model") not in models:
            continue
        key = r.key
        rows.append((key, r, was))
        counts[state] = counts.get(state, 0) + 1
        box = boxes.get(str(s.get("box")))
        if box is None:
            box = boxes[str(s.get("box"))] = {
                "machines": 0, "alarm": 0, "warning": 0, "check_function": 0, "normal": 0,
                "stale": 0, "first": s.get("machine"), "_key": key}
        box["machines"] += 1
        if state in box:
            box[state] += 1
        if was == "stale":
            box["stale"] += 1
        if key < box["_key"]:
            box["first"], box["_key"] = s.get("machine"), key
    for box in boxes.values():
        del box["_key"]
    if limit is None or limit >= len(rows):
        rows.sort(key=lambda x: x[0])
        top = rows
    else:
        import heapq

        top = heapq.nsmallest(max(limit, 0), rows, key=lambda x: x[0])
    shown = [entry(r, now, stale_after) for _, r, _ in top]
    return {"t": now, "machines_total": len(received), "matched": len(rows),
            "shown": len(shown), "more": len(rows) - len(shown), "states": counts,
            "boxes": dict(sorted(boxes.items())), "machines": shown}


def due(summary: Mapping[str, Any], horizon_s: float, age_s: float = 0.0) -> list[str]:
    """Why a machine needs service within ``horizon_s`` [s] from now, or ``[]``:

    * ``rul``: its RUL interval reaches into the horizon: the earliest end (else the median)
      of the soonest alarm threshold's crossing, less the summary's age ``age_s`` [s], is at
      most ``horizon_s`` (a threshold ``crossed`` is 0);
    * ``diagnosis``: the diagnosis urges action: its fault alarm is raised, or a fault of
      urgency ``high`` is at least :data:`URGES_PROBABILITY` probable, or the twin is in
      ``check_function``;
    * ``alarm``: a parameter's level is ``alarm``.
    """
    reasons = []
    rul = summary.get("rul")
    if isinstance(rul, Mapping):
        first = number(rul.get("low_s"))
        if first is None:
            first = number(rul.get("median_s"))
        if first is not None and first - age_s <= horizon_s:
            reasons.append("rul")
    if diagnosis_rank(summary) >= 3 or (
            isinstance(summary.get("diagnosis"), Mapping)
            and summary["diagnosis"].get("status") == "check_function"):
        reasons.append("diagnosis")
    alarms = summary.get("alarms")
    if isinstance(alarms, Mapping) and any(
            isinstance(a, Mapping) and a.get("level") == "alarm" for a in alarms.values()):
        reasons.append("alarm")
    return reasons


REPORT_COLUMNS = ("machine", "box", "model", "state", "why", "part", "action", "fault",
                  "probability", "urgency", "rul_parameter", "rul_median_s", "rul_low_s",
                  "rul_high_s", "age_s")
"""The fleet report's columns (CSV header, JSON keys)."""


def service_report(received: Mapping[str, Received], now: float, horizon_s: float
                   ) -> list[dict[str, Any]]:
    """What needs service within ``horizon_s`` [s]: each machine :func:`due` names, most urgent
    first (:func:`urgency`), with the part and the action: the diagnosed fault's when the
    diagnosis names one, else the parameter whose RUL runs out and "inspect". RUL times are
    from now (the summary's less its age since it was made: :attr:`Received.made`) [s].
    Keys: :data:`REPORT_COLUMNS`."""
    out = []
    for r in sorted(received.values(), key=lambda r: urgency(r.summary)):
        s = r.summary
        age = max(now - r.made, 0.0)
        why = due(s, horizon_s, age)
        if not why:
            continue
        d = s.get("diagnosis") if isinstance(s.get("diagnosis"), Mapping) else {}
        rul = s.get("rul") if isinstance(s.get("rul"), Mapping) else {}
        assert isinstance(d, Mapping) and isinstance(rul, Mapping)
        param = rul.get("parameter")

        def left(key: str, rul: Mapping[str, Any] = rul, age: float = age) -> float | None:
            x = number(rul.get(key))
            return None if x is None else round(max(x - age, 0.0), 1)

        if d.get("status") == "fault" and d.get("part"):
            part, action = d.get("part"), d.get("action")
        elif d.get("status") == "check_function":
            part, action = "sensors and model", ("the twin does not describe this machine: "
                                                 "check the sensors and the model")
        elif param:
            part, action = (f"the part behind {param}",
                            f"inspect: {param} reaches its alarm threshold")
        else:
            part, action = None, "inspect: an alarm is raised"
        out.append({"machine": s.get("machine"), "box": s.get("box"), "model": s.get("model"),
                    "state": s.get("state"), "why": "+".join(why), "part": part,
                    "action": action, "fault": d.get("fault"),
                    "probability": d.get("probability"), "urgency": d.get("urgency"),
                    "rul_parameter": param, "rul_median_s": left("median_s"),
                    "rul_low_s": left("low_s"), "rul_high_s": left("high_s"),
                    "age_s": round(age, 1)})
    return out


def parse_duration(text: str) -> float:
    """``7d``, ``12h``, ``30min``/``30m``, ``90s`` or a number of seconds -> seconds.

    Raises:
        ValueError: not a duration (the message says the form).
    """
    units = {"d": 86400.0, "h": 3600.0, "min": 60.0, "m": 60.0, "s": 1.0, "w": 604800.0}
    t = text.strip().lower()
    for suffix in sorted(units, key=len, reverse=True):
        if t.endswith(suffix):
            amount, scale = t[: -len(suffix)], units[suffix]
            break
    else:
        amount, scale = t, 1.0
    try:
        value = float(amount) * scale
    except ValueError:
        raise ValueError(f"{text!r} is not a duration: give e.g. 7d, 12h, 30min, 90s") from None
    if not math.isfinite(value) or value < 0:
        raise ValueError(f"{text!r}: give a finite duration from 0")
    return value


def flat(rows: Iterable[Mapping[str, Any]]) -> list[list[Any]]:
    """The report's rows as lists in :data:`REPORT_COLUMNS` order (CSV)."""
    return [[r.get(c) for c in REPORT_COLUMNS] for r in rows]
