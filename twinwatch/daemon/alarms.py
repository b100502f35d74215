"""Alarms on parameter drift: warning and alarm thresholds on the deviation from nominal, with
hysteresis and minimum durations, so a parameter drifting near a threshold does not flap.

:class:`AlarmEvaluator` turns the stream of health messages into alarm-state changes, one event
per change, to publish on ``twinwatch/<machine>/alarm``. A parameter's ``deviation_pct`` is
evidence when its ``status`` is ``estimated`` or ``fused``; ``held``, ``tied``, ``fixed`` and
non-finite deviations neither start, extend nor interrupt a run (durations are plant time).
The rule keys (``[alarms.parameters.<name>]``) are in docs/configuration.md.

**Remaining useful life** (docs/prognostics.md): ``rul_warning`` / ``rul_alarm`` [s] alarm on
``parameters.<name>.rul`` (the median, or the early end with ``rul_basis = "low"``) in a second
state per parameter, once the whole 95 % interval is within the rule's horizon
(``rul_warning``, else ``rul_alarm``); a level clears once the RUL is above its threshold times
``1 + rul_hysteresis`` (or the trend is not degrading), whatever the interval. An
``insufficient`` RUL is not evidence. Events carry ``kind`` (``deviation`` or ``rul``).

**Faults.** :class:`FaultAlarms` raises an alarm on a fault mode (``diagnosis.faults[]``) whose
probability has been at least ``[diagnosis] alarm`` (0.8) for ``raise_after_windows`` windows in
a row, and clears it once below ``clear`` (0.5) for ``clear_after_windows`` sound windows (a
window not ``trusted`` is not counted); ``diagnosis.alarms`` lists the raised ones. The check
function (NAMUR NE 107) is raised and cleared as the fault ``check_function``.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from twinwatch.config.alarms import LEVELS, AlarmConfig, AlarmRule, Level
from twinwatch.twin.prognostics.rul import format_crossing, format_duration

if TYPE_CHECKING:
    from twinwatch.twin.health import DiagnosisHealth, HealthMessage, ParameterHealth

logger = logging.getLogger(__name__)

__all__ = ["LEVELS", "AlarmConfig", "AlarmEvaluator", "AlarmRule", "FaultAlarms", "Level"]

_RANK = {lvl: i for i, lvl in enumerate(LEVELS)}

_DEFAULT_ACTION: dict[str, str] = {
    "warning": "plan an inspection of the part this parameter describes at the next stop",
    "alarm": "inspect the machine now; if the deviation is real, take it out of service "
             "before it fails",
    "normal": "no action needed",
}

_RUL_ACTION: dict[str, str] = {
    "warning": "plan the maintenance of the part this parameter describes before then",
    "alarm": "schedule the intervention now: it is needed before then",
    "normal": "no action needed",
}


@dataclass
class _Run:
    """A run of consecutive evidence windows on one side of a threshold."""

    since_t: float
    windows: int


@dataclass
class _ParamState:
    level: Level = "normal"
    since_t: float | None = None
    since_window: int | None = None
    deviation: float | None = None
    up: _Run | None = None        # run beyond the next level up (escalation)
    up_level: Level | None = None
    down: _Run | None = None      # run back inside the current level (clearing)
    down_level: Level | None = None
    rul: float | None = None      # last RUL evidence [s] (the RUL state only)


class AlarmEvaluator:
    """Alarm state per parameter, updated by each health message.

    Args:
        machine: machine name for the events (default: taken from each health message).
        meanings: parameter -> what it describes (``"armature resistance"``), named in the
            event's message next to the symbol.

    Thread-safe: :meth:`update` runs on the adaptation worker, :meth:`state` may be read from
    a Zenoh queryable thread.
    """

    def __init__(self, config: AlarmConfig, machine: str | None = None, *,
                 meanings: Mapping[str, str] | None = None) -> None:
        self.config = config
        self.machine = machine
        self.meanings = dict(meanings or {})
        self._lock = threading.Lock()
        self._state: dict[str, _ParamState] = {n: _ParamState() for n in config.parameters}
        self._rul: dict[str, _ParamState] = {n: _ParamState() for n, r in
                                             config.parameters.items() if r.has_rul}

    # -- public ---------------------------------------------------------------------------
    def update(self, health: HealthMessage) -> list[dict[str, Any]]:
        """Feed one window's typed health message; return the alarm-state changes it caused.

        Returns:
            One event per parameter whose level changed: ``machine``, ``parameter``, ``level``
            and ``previous`` (``normal|warning|alarm``), ``deviation_pct``, ``threshold_pct``
            (the signed threshold crossed; for a clear, the one left), ``value``, ``unit``,
            ``nominal``, ``t`` (the window's ``t_end`` [s]), ``window``, ``since_t`` (plant
            time the evidence run began), ``message`` (for an operator: what happened and
            what to do). Empty when nothing changed or alarms are disabled.
        """
        if not self.config.enabled:
            return []
        events: list[dict[str, Any]] = []
        t_start = float(health.t_start)
        t_end = float(health.t_end)
        n = int(health.samples or 0)
        dt = (t_end - t_start) / (n - 1) if n > 1 else 0.0
        with self._lock:
            for name, rule in self.config.parameters.items():
                p = health.parameters.get(name)
                if p is None or p.status not in ("estimated", "fused"):
                    continue
                dev = p.deviation_pct
                if dev is None or not math.isfinite(dev):
                    continue
                ev = self._step(name, rule, float(dev), p, health, t_start, t_end, dt)
                if ev is not None:
                    events.append(ev)
            for name, s in self._rul.items():
                rule = self.config.parameters[name]
                p = health.parameters.get(name)
                ev = self._rul_step(name, rule, s, p, health, t_start, t_end, dt) \
                    if p is not None else None
                if ev is not None:
                    events.append(ev)
        for ev in events:  # a clear is logged like a raise: an ALARM line is never left open
            logger.warning("%s", ev["message"])
        return events

    def state(self) -> dict[str, dict[str, Any]]:
        """Snapshot for the health message (``health["alarms"]``) and the state store:
        parameter -> ``level``, ``since_t``, ``since_window`` (when the level was entered),
        ``deviation_pct`` (last evidence), ``pending`` (level a running evidence run would
        move to, or None)."""
        with self._lock:
            out: dict[str, dict[str, Any]] = {}
            for name, s in self._state.items():
                out[name] = {"level": s.level, "since_t": s.since_t,
                             "since_window": s.since_window, "deviation_pct": s.deviation,
                             "pending": _pending(s), **_run_state(s)}
                r = self._rul.get(name)
                if r is not None:
                    out[name]["rul"] = {"level": r.level, "since_t": r.since_t,
                                        "since_window": r.since_window, "rul_s": r.rul,
                                        "pending": _pending(r), **_run_state(r)}
            return out

    def restore(self, snapshot: Mapping[str, Any]) -> None:
        """Re-seed levels from a :meth:`state` snapshot (read through
        :class:`~twinwatch.twin.health.AlarmView`), so a restart neither re-raises nor silently
        clears an active alarm. Unknown parameters, bad levels and entries of another shape
        are ignored with a warning."""
        from twinwatch.twin.health import AlarmView

        with self._lock:
            for name, raw in snapshot.items():
                try:
                    snap = raw if isinstance(raw, AlarmView) else AlarmView.model_validate(raw)
                except ValueError:
                    snap = None
                s = self._state.get(name)
                level = snap.level if snap is not None else None
                if s is None or snap is None or level not in _RANK:
                    logger.warning("alarm state for %r (%r) not restored: no such rule or "
                                   "level", name, level)
                    continue
                _restore(s, snap)
                s.deviation = snap.deviation_pct
                r, rsnap = self._rul.get(name), snap.rul
                if r is not None and rsnap is not None and rsnap.level in _RANK:
                    _restore(r, rsnap)
                    r.rul = rsnap.rul_s

    # -- internals --------------------------------------------------------------------------
    def _target(self, rule: AlarmRule, dev: float, current: Level) -> tuple[Level, float | None]:
        """Level the deviation supports, with hysteresis for levels already active."""
        for lvl in ("alarm", "warning"):
            margin = rule.hysteresis if _RANK[current] >= _RANK[lvl] else 0.0
            th = rule.beyond(lvl, dev, margin)  # type: ignore[arg-type]
            if th is not None:
                return lvl, th  # type: ignore[return-value]
        return "normal", None

    def _step(self, name: str, rule: AlarmRule, dev: float, p: ParameterHealth,
              health: HealthMessage, t_start: float, t_end: float, dt: float
              ) -> dict[str, Any] | None:
        s = self._state[name]
        s.deviation = dev
        target, th = self._target(rule, dev, s.level)
        moved = _advance(s, rule, target, t_start, t_end, dt, int(health.window))
        if moved is None:
            return None
        previous, new, since_t = moved
        if _RANK[new] < _RANK[previous]:  # lowered: report the threshold that was left
            high, low = rule.thresholds(previous)
            th = high if (dev >= 0 and high is not None) or low is None else low
        return self._event(name, rule, new, previous, dev, th, p, health, t_end, since_t)

    def _rul_step(self, name: str, rule: AlarmRule, s: _ParamState, p: ParameterHealth,
                  health: HealthMessage, t_start: float, t_end: float, dt: float
                  ) -> dict[str, Any] | None:
        """The RUL state of one parameter (module docstring)."""
        rul = p.rul
        if rul is None or rul.status == "insufficient":
            return None
        crossing = rul.alarm or rul.warning
        value = math.inf
        if rul.status == "degrading" and crossing is not None:
            v = crossing.low_s if rule.rul_basis == "low" else crossing.rul_s
            value = math.inf if v is None else float(v)
        s.rul = value if math.isfinite(value) else None
        target: Level = "normal"
        for lvl in ("alarm", "warning"):
            th = rule.rul_threshold(lvl)  # type: ignore[arg-type]
            if th is None:
                continue
            margin = 1.0 + rule.rul_hysteresis if _RANK[s.level] >= _RANK[lvl] else 1.0
            if value <= th * margin:
                target = lvl  # type: ignore[assignment]
                break
        if _RANK[target] > _RANK[s.level] and not _interval_agrees(rule, rul, crossing):
            target = s.level  # raised only on an interval that agrees; an active level stays
        moved = _advance(s, rule, target, t_start, t_end, dt, int(health.window))
        if moved is None:
            return None
        previous, new, since_t = moved
        return self._rul_event(name, rule, new, previous, value, p, health, t_end, since_t)

    def _who(self, name: str, health: HealthMessage) -> tuple[str, str]:
        """The machine of an event and the parameter as named in its message."""
        meaning = self.meanings.get(name)
        return self.machine or health.machine, f"{name} ({meaning})" if meaning else name

    def _rul_event(self, name: str, rule: AlarmRule, level: Level, previous: Level,
                   value: float, p: ParameterHealth, health: HealthMessage, t: float,
                   since_t: float) -> dict[str, Any]:
        machine, what = self._who(name, health)
        rul = p.rul
        crossing = (rul.alarm or rul.warning) if rul is not None else None
        which = "alarm" if rul is not None and rul.alarm is not None else "warning"
        unit = p.unit or ""
        th_level = rule.rul_threshold(level if level != "normal" else previous)
        if crossing is not None and crossing.status == "crossed":
            when = "now (the trend is beyond it)"
        elif crossing is not None:
            when = "in " + format_crossing(crossing.rul_s, crossing.low_s, crossing.high_s)
        else:
            when = "never (not degrading)"
        th_txt = (f" ({crossing.threshold:.6g} {unit})" if crossing is not None
                  and crossing.threshold is not None else "")
        trend = p.trend
        model = ""
        if trend is not None and trend.model is not None:
            model = (f"; {trend.model} trend"
                     + (f" from plant time {trend.onset:.0f} s" if trend.onset is not None
                        else ""))
        if _RANK[level] > _RANK[previous]:
            action = _RUL_ACTION[level]
            msg = (f"{machine}: RUL {level.upper()}: {what} reaches its {which} threshold"
                   f"{th_txt} {when}{model}; the {level} is raised below "
                   f"{format_duration(th_level)}: {action}")
        else:
            msg = (f"{machine}: RUL {previous} cleared to {level}: {what} reaches its {which} "
                   f"threshold{th_txt} {when}"
                   + ("" if level == "normal" else f"; still {level}: {_RUL_ACTION[level]}"))
        return _param_event(
            machine, "rul", name, level, previous, p, health, t, since_t, msg,
            rul_s=value if math.isfinite(value) else None,
            rul_low_s=crossing.low_s if crossing is not None else None,
            rul_high_s=crossing.high_s if crossing is not None else None,
            t_cross=crossing.t if crossing is not None else None, threshold_s=th_level)

    def _event(self, name: str, rule: AlarmRule, level: Level, previous: Level, dev: float,
               threshold: float | None, p: ParameterHealth, health: HealthMessage,
               t: float, since_t: float) -> dict[str, Any]:
        machine, what = self._who(name, health)
        unit = p.unit or ""
        value, nominal = p.value, p.nominal
        side = "above" if dev >= 0 else "below"
        vals = (f" ({value:.6g} {unit} vs nominal {nominal:.6g} {unit})"
                if isinstance(value, float | int) and isinstance(nominal, float | int) else "")
        th = f"{threshold:+g} %" if threshold is not None else "n/a"
        if _RANK[level] > _RANK[previous]:
            action = rule.action or _DEFAULT_ACTION[level]
            msg = (f"{machine}: {level.upper()}: {what} is {abs(dev):.2f} % {side} nominal"
                   f"{vals} since plant time {since_t:.0f} s, beyond the {level} threshold "
                   f"{th}: {action}")
        else:
            still = (_DEFAULT_ACTION["normal"] if level == "normal" else
                     f"still {level}: {rule.action or _DEFAULT_ACTION[level]}")
            msg = (f"{machine}: {previous.upper()} CLEARED to {level}: {what} is {abs(dev):.2f} "
                   f"% {side} nominal{vals} since plant time {since_t:.0f} s, back within the "
                   f"{previous} threshold {th} (with {rule.hysteresis:g} %-points hysteresis): "
                   f"{still}")
        return _param_event(machine, "deviation", name, level, previous, p, health, t, since_t,
                            msg, deviation_pct=dev, threshold_pct=threshold)


def _param_event(machine: str, kind: str, name: str, level: Level, previous: Level,
                 p: ParameterHealth, health: HealthMessage, t: float, since_t: float,
                 message: str, **evidence: Any) -> dict[str, Any]:
    """A parameter's alarm event (:meth:`AlarmEvaluator.update`): the change, ``evidence``
    (its deviation, or its RUL), the parameter's value and the window."""
    return {"machine": machine, "kind": kind, "parameter": name, "level": level,
            "previous": previous, **evidence,
            "value": p.value, "unit": p.unit or "", "nominal": p.nominal,
            "t": t, "window": int(health.window), "since_t": since_t, "message": message}


def rul_horizon(rule: AlarmRule) -> float:
    """The rule's RUL horizon [s]: its longest RUL threshold (``rul_warning``, else
    ``rul_alarm``)."""
    th = rule.rul_warning if rule.rul_warning is not None else rule.rul_alarm
    assert th is not None
    return float(th)


def _interval_agrees(rule: AlarmRule, rul: Any, crossing: Any) -> bool:
    """Whether a RUL prediction may raise a level: its whole 95 % interval of the crossing
    lies within :func:`rul_horizon` (or the threshold is already crossed), so an early, weak
    trend whose median is near but whose interval reaches far beyond raises nothing."""
    if rul.status != "degrading" or crossing is None:
        return False
    if crossing.status == "crossed":
        return True
    high = crossing.high_s
    return high is not None and math.isfinite(high) and high <= rul_horizon(rule)


def _run_state(s: _ParamState) -> dict[str, Any]:
    """The running evidence run of ``s`` for the snapshot: when it began, its windows."""
    run = s.up if s.up is not None else s.down
    return {"pending_since_t": run.since_t if run else None,
            "pending_windows": run.windows if run else None}


def _restore(s: _ParamState, snap: Any) -> None:
    """Re-seed a state's level and the evidence run a snapshot (an ``AlarmView`` or its
    ``rul``) recorded."""
    s.level = snap.level
    s.since_t = snap.since_t
    s.since_window = snap.since_window
    pending, since_t, windows = snap.pending, snap.pending_since_t, snap.pending_windows
    if pending not in _RANK or since_t is None or not windows or pending == s.level:
        return
    run = _Run(float(since_t), int(windows))
    if _RANK[pending] > _RANK[s.level]:  # type: ignore[index]
        s.up, s.up_level = run, pending  # type: ignore[assignment]
    else:
        s.down, s.down_level = run, pending  # type: ignore[assignment]


def _pending(s: _ParamState) -> Level | None:
    """The level a running evidence run would move ``s`` to."""
    if s.up is not None:
        return s.up_level
    if s.down is not None:
        return s.down_level
    return None


def _advance(s: _ParamState, rule: AlarmRule, target: Level, t_start: float, t_end: float,
             dt: float, window: int) -> tuple[Level, Level, float] | None:
    """One evidence window towards ``target``: the runs, the minimum durations. Returns
    (previous, new level, the time the run began) when the level changes."""
    reached = False
    if _RANK[target] > _RANK[s.level]:
        s.down = s.down_level = None
        s.up, reached = _extend(s.up, t_start, t_end, dt, rule.raise_after_windows,
                                rule.raise_after_s)
        # falling back from alarm to warning territory keeps the run (still beyond warning)
        s.up_level = target
    elif _RANK[target] < _RANK[s.level]:
        s.up = s.up_level = None
        s.down, reached = _extend(s.down, t_start, t_end, dt, rule.clear_after_windows,
                                  rule.clear_after_s)
        s.down_level = target
    else:
        s.up = s.down = None
        s.up_level = s.down_level = None
    if not reached:
        return None
    run = s.up if s.up is not None else s.down
    assert run is not None
    previous = s.level
    s.level, s.since_t, s.since_window = target, t_end, window
    s.up = s.down = None
    s.up_level = s.down_level = None
    return previous, target, run.since_t


def _extend(run: _Run | None, t_start: float, t_end: float, dt: float, windows: int,
            seconds: float) -> tuple[_Run, bool]:
    """``run`` one window (``t_start`` to ``t_end`` [s], sample period ``dt`` [s]) longer
    (None: a run from this window), and whether it now holds ``windows`` windows and
    ``seconds`` [s]."""
    run = _Run(t_start, 0) if run is None else run
    run.windows += 1
    return run, run.windows >= windows and t_end - run.since_t + dt >= seconds - 1e-9


#: The fault id of the diagnosis' check-function state in the alarms (``diagnosis.alarms``,
#: an event's ``fault``): the twin does not describe the machine (NAMUR NE 107).
CHECK_FUNCTION = "check_function"


class FaultAlarms:
    """Alarms on the diagnosis' fault probabilities, with hysteresis (the module's "Faults").

    Args:
        alarm: probability that raises an alarm (None: off); clear: the one that clears it.
        raise_after, clear_after: windows in a row before raising / clearing.
    """

    def __init__(self, alarm: float | None, clear: float, raise_after: int, clear_after: int,
                 machine: str | None = None) -> None:
        self.alarm, self.clear = alarm, clear
        self.raise_after, self.clear_after = raise_after, clear_after
        self.machine = machine
        self.raised: dict[str, float] = {}   # fault -> plant time it was raised
        self._above: dict[str, int] = {}
        self._below: dict[str, int] = {}

    def update(self, d: DiagnosisHealth | None, health: HealthMessage
               ) -> tuple[DiagnosisHealth | None, list[dict[str, Any]]]:
        """Advance on one window's diagnosis.

        Returns:
            A copy of ``d`` with ``alarms``, the faults raised now (``d`` itself when the alarms
            are off), and the events.
        """
        if d is None or self.alarm is None:
            return d, []
        probs: dict[str, tuple[float, str]] = {
            f.id: (f.probability, f"{f.component}: {f.action}") for f in d.faults}
        if d.status == "check_function":  # NAMUR NE 107: the twin does not fit this machine
            since = d.check_function_since
            probs[CHECK_FUNCTION] = (1.0, (
                f"the twin does not describe this machine since plant time "
                f"{since if since is not None else health.t_start:.0f} s "
                f"({d.check_failed or 'its model check failing'}): its estimates are held and "
                f"no fault is named; check the sensors, their wiring and scaling, and the "
                f"model's configuration"))
        events = []
        for fid in set(probs) | set(self.raised) | set(self._above):
            p, what = probs.get(fid, (0.0, ""))
            if fid not in self.raised:
                self._above[fid] = self._above.get(fid, 0) + 1 if p >= self.alarm else 0
                if self._above[fid] >= self.raise_after and fid in probs:
                    self.raised[fid] = health.t_end
                    self._above.pop(fid)
                    events.append(self._event(health, fid, "alarm", "normal", p, what))
            else:
                if p < self.clear and not health.trusted and fid != CHECK_FUNCTION:
                    # an untrusted window is no evidence against the fault: not counted
                    continue
                self._below[fid] = self._below.get(fid, 0) + 1 if p < self.clear else 0
                if self._below[fid] >= self.clear_after:
                    self.raised.pop(fid)
                    self._below.pop(fid)
                    events.append(self._event(health, fid, "normal", "alarm", p,
                                              "cleared: the evidence no longer supports it"))
            if not self._above.get(fid, 1):
                self._above.pop(fid, None)
        for e in events:
            logger.warning("%s", e["message"])
        return d.model_copy(update={"alarms": sorted(self.raised)}), events

    def _event(self, health: HealthMessage, fid: str, level: str, previous: str, p: float,
               what: str) -> dict[str, Any]:
        machine = self.machine or health.machine
        word = "FAULT" if level == "alarm" else "FAULT CLEARED"
        if fid == CHECK_FUNCTION:
            word = "CHECK FUNCTION" if level == "alarm" else "CHECK FUNCTION CLEARED"
            if level != "alarm":
                what = ("the twin describes the machine again (its model check passes): its "
                        "estimates are trusted again")
            message = f"{machine}: {word}: {what}"
        else:
            message = f"{machine}: {word}: {fid} (probability {p:.2f}): {what}"
        return {"machine": machine, "kind": "diagnosis", "fault": fid, "level": level,
                "previous": previous, "probability": p, "t": health.t_end,
                "window": int(health.window), "message": message}
