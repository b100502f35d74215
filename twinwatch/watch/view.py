"""What each machine shows in the fleet's snapshot (:meth:`~twinwatch.watch.fleet.Fleet.snapshot`):
its state (alive, stale, gone, unknown: :func:`machine_state`), its estimated parameters with
their deviation, alarm level and remaining useful life, its raised alarms, terms, the most
probable fault and its data quality (the counters that report a loss), as plain JSON types.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

if TYPE_CHECKING:
    from twinwatch.twin.health import DiagnosisView, HealthView


MachineState = Literal["alive", "stale", "gone", "unknown"]
"""``alive``: its liveliness token is present (and a window came recently); ``stale``: the token
is present but no window for longer than the stale time (a silent source, a stuck worker);
``gone``: the token went (the daemon stopped or died, or the link to it is lost); ``unknown``:
heard only through a health message, no token seen."""


#: Counters that report a loss or a fault (nonzero: shown under data quality, "losses"); not
#: the driver's activity (``driver_polls``, ``driver_duplicates``, ``driver_reconnects``...).
PROBLEM_COUNTERS = ("windows_abandoned", "overruns", "numeric_failures", "samples_lost",
                    "bad_samples", "windows_not_stored", "store_waiting", "store_lost",
                    "store_history_lost", "store_errors", "recording_lost", "zenoh_errors",
                    "driver_bad_frames", "driver_bad_values", "driver_gaps", "driver_errors",
                    "driver_dropped", "driver_error_frames", "driver_incomplete_syncs",
                    "driver_outages", "mqtt_lost")


def number(x: Any, default: float | None = None) -> Any:
    return x if isinstance(x, int | float) and not isinstance(x, bool) else default


def _parameters(h: HealthView) -> dict[str, dict[str, Any]]:
    alarms = h.alarms or {}
    out: dict[str, dict[str, Any]] = {}
    for name, p in (h.parameters or {}).items():
        if p.status in ("tied", "fixed"):
            continue
        crossing = p.rul.alarm if p.rul is not None else None
        alarm = alarms.get(name)
        out[name] = {"value": number(p.value), "unit": p.unit,
                     "nominal": number(p.nominal),
                     "deviation_pct": number(p.deviation_pct), "status": p.status,
                     "alarm": alarm.level if alarm is not None else None,
                     "rul_s": number(crossing.rul_s if crossing is not None else None),
                     "rul_status": crossing.status if crossing is not None else None}
    return out


def problem_counters(h: HealthView) -> dict[str, int]:
    """The counters of losses that are not zero."""
    return {k: v for k, v in (h.counters or {}).items()
            if k in PROBLEM_COUNTERS and isinstance(v, int) and v}


def _quality(h: HealthView) -> dict[str, Any]:
    counters = h.counters or {}
    problems = problem_counters(h)
    check = h.model_check
    elapsed = number(h.elapsed_s)
    return {"nrmse": number(h.nrmse),
            "model_check": check.passed if check is not None else None,
            "trusted": h.trusted,
            "elapsed_ms": None if elapsed is None else round(elapsed * 1e3, 1),
            "windows_estimated": counters.get("windows_estimated"),
            "problems": problems}


def _diagnosis(d: DiagnosisView | None) -> dict[str, Any] | None:
    """The message's diagnosis in short: the most probable fault (``no_fault``, ``unknown``,
    ``check_function``: the twin does not fit), its probability and action; null without one."""
    if d is None:
        return None
    faults = d.faults or []
    top = faults[0] if d.status == "fault" and faults else None
    action = top.action if top is not None else None
    if d.status == "check_function":
        since = d.check_function_since
        action = ("the twin does not describe this machine"
                  + (f" since {since:.0f} s" if isinstance(since, int | float) else "")
                  + ": check the sensors and the model")
    return {"fault": (top.id if top is not None else None) or d.status,
            "probability": d.probability,
            "action": action}


@dataclass
class Machine:
    """What the network showed of one machine (the fleet's record of it)."""

    name: str
    token: bool | None = None  # None: never seen a token
    since: float | None = None  # wall time of the last token change seen (None: before us)
    health: HealthView | None = None
    received: float | None = None  # wall time the last health arrived
    events: deque[dict[str, Any]] = field(default_factory=lambda: deque(maxlen=5))
    missed: int = 0  # windows zenoh reported missed
    recovered: int = 0  # windows then got from the history
    gap_error: str | None = None  # why the last gap could not be asked from the history


def machine_state(token: bool | None, age: float | None, stale_after: float) -> MachineState:
    """``gone`` when its liveliness token went, ``unknown`` when no token was seen, ``stale``
    when the last window is older than ``stale_after`` [s], else ``alive``."""
    if token is False:
        return "gone"
    if token is None:
        return "unknown"
    if age is not None and age > stale_after:
        return "stale"
    return "alive"


def machine_view(m: Machine, now: float, stale_after: float) -> dict[str, Any]:
    """One machine's entry of the snapshot at wall time ``now`` [s] (:meth:`~twinwatch.watch.
    fleet.Fleet.snapshot` gives its keys), shown ``stale`` after ``stale_after`` [s] without a
    window (at least 3 window lengths)."""
    h = m.health
    age = None if m.received is None else max(now - m.received, 0.0)
    window_s = (number(h.t_end, 0.0) - number(h.t_start, 0.0)) if h is not None else 0.0
    state = machine_state(m.token, age, max(stale_after, 3.0 * window_s))
    return {
        "machine": m.name,
        "state": state,
        "token": m.token,
        "state_since_s": None if m.since is None else max(now - m.since, 0.0),
        "last_window_age_s": age,
        **{k: getattr(h, k) if h is not None else None
           for k in ("model", "run", "window", "t_start", "t_end")},
        "parameters": _parameters(h) if h is not None else {},
        "alarms": {k: {"level": a.level, "since_t": a.since_t,
                       "deviation_pct": a.deviation_pct,
                       "rul": ({"level": a.rul.level, "since_t": a.rul.since_t,
                                "rul_s": a.rul.rul_s} if a.rul is not None else None)}
                   for k, a in ((h.alarms if h is not None else None) or {}).items()},
        "terms": [{"equation": t.equation, "meaning": t.meaning}
                  for t in (h.terms if h is not None else None) or []],
        "diagnosis": _diagnosis(h.diagnosis if h is not None else None),
        "quality": _quality(h) if h is not None else None,
        "delivery": {"missed": m.missed, "recovered": m.recovered, "error": m.gap_error},
        "last_event": m.events[-1] if m.events else None,
    }
