"""Alarms on parameter drift: warning and alarm thresholds on the deviation from nominal, with
hysteresis and minimum durations, so a parameter drifting near a threshold does not flap.

The health message gives each parameter's ``deviation_pct`` (estimate vs nominal, percent) and
its ``status``: an ``estimated`` value (this window's) or a ``fused`` one (the evidence of the
windows so far) is evidence; a ``held`` one is the last trusted value, not new evidence;
``tied`` and ``fixed`` ones are not estimated at all.
:class:`AlarmEvaluator` turns the stream of health messages into alarm-state changes, one event
per change, to publish on ``twinwatch/<machine>/alarm``.

Per parameter (``[alarms.parameters.<name>]``) a rule gives thresholds in percent of nominal,
either symmetric on ``|deviation_pct|`` (``warning``, ``alarm``) or one-sided (``warning_high``,
``alarm_high`` > 0; ``warning_low``, ``alarm_low`` < 0), and:

* ``hysteresis`` [percentage points]: a level entered at threshold ``T`` is left only once the
  deviation is back inside ``T - hysteresis`` (for a symmetric or high threshold);
* ``raise_after_s`` / ``raise_after_windows``: the deviation must stay beyond the threshold this
  long (plant time, from the first window's start to the last one's end) *and* for this many
  consecutive evidence windows before the level is raised;
* ``clear_after_s`` / ``clear_after_windows``: likewise, inside the threshold minus the
  hysteresis, before it is lowered.

Parameters not estimated in a window and non-finite deviations are not evidence: they neither
start, extend nor interrupt a run (the run's duration is measured in plant time, so held windows
in between still count as time).
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from twinwatch.config.alarms import LEVELS, AlarmConfig, AlarmRule, Level

if TYPE_CHECKING:
    from twinwatch.twin.health import HealthMessage, ParameterHealth

logger = logging.getLogger(__name__)

__all__ = ["LEVELS", "AlarmConfig", "AlarmEvaluator", "AlarmRule", "Level"]

_RANK = {lvl: i for i, lvl in enumerate(LEVELS)}

_DEFAULT_ACTION: dict[str, str] = {
    "warning": "plan an inspection of the part this parameter describes at the next stop",
    "alarm": "inspect the machine now; if the deviation is real, take it out of service "
             "before it fails",
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


class AlarmEvaluator:
    """Alarm state per parameter, updated by each health message.

    Args:
        config: the ``[alarms]`` table.
        machine: machine name for the events (default: taken from each health message).
        meanings: parameter -> what it describes (``"armature resistance"``), named in the
            event's message next to the symbol; default: the symbol alone.

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

    # -- public ---------------------------------------------------------------------------
    def update(self, health: HealthMessage) -> list[dict[str, Any]]:
        """Feed one window's typed health message (its ``parameters``' ``status`` and
        ``deviation_pct``, the window's times); return the alarm-state changes it caused.

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
                pending: Level | None = None
                if s.up is not None:
                    pending = s.up_level
                elif s.down is not None:
                    pending = s.down_level
                out[name] = {"level": s.level, "since_t": s.since_t,
                             "since_window": s.since_window, "deviation_pct": s.deviation,
                             "pending": pending}
            return out

    def restore(self, snapshot: Mapping[str, Mapping[str, Any]]) -> None:
        """Re-seed levels from a :meth:`state` snapshot (e.g. from the state store at start),
        so a restart neither re-raises nor silently clears an active alarm. Unknown
        parameters and bad levels are ignored with a warning."""
        with self._lock:
            for name, snap in snapshot.items():
                s = self._state.get(name)
                level = snap.get("level")
                if s is None or level not in _RANK:
                    logger.warning("alarm state for %r (%r) not restored: no such rule or "
                                   "level", name, level)
                    continue
                s.level = level
                s.since_t = snap.get("since_t")
                s.since_window = snap.get("since_window")
                s.deviation = snap.get("deviation_pct")

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
        new: Level | None = None
        if _RANK[target] > _RANK[s.level]:
            s.down = None
            s.down_level = None
            if s.up is None:
                s.up = _Run(t_start, 0)
            s.up.windows += 1
            # The run counts for the highest level reached; falling back from alarm to
            # warning territory keeps the run (it is still beyond warning).
            s.up_level = target
            if (s.up.windows >= rule.raise_after_windows
                    and t_end - s.up.since_t + dt >= rule.raise_after_s - 1e-9):
                new = target
        elif _RANK[target] < _RANK[s.level]:
            s.up = None
            s.up_level = None
            if s.down is None:
                s.down = _Run(t_start, 0)
            s.down.windows += 1
            s.down_level = target
            if (s.down.windows >= rule.clear_after_windows
                    and t_end - s.down.since_t + dt >= rule.clear_after_s - 1e-9):
                new = target
        else:
            s.up = s.down = None
            s.up_level = s.down_level = None
        if new is None:
            return None
        run = s.up if s.up is not None else s.down
        assert run is not None
        previous = s.level
        if _RANK[new] < _RANK[previous]:  # lowered: report the threshold that was left
            high, low = rule.thresholds(previous)
            th = high if (dev >= 0 and high is not None) or low is None else low
        s.level, s.since_t, s.since_window = new, t_end, int(health.window)
        s.up = s.down = None
        s.up_level = s.down_level = None
        return self._event(name, rule, new, previous, dev, th, p, health, t_end, run.since_t)

    def _event(self, name: str, rule: AlarmRule, level: Level, previous: Level, dev: float,
               threshold: float | None, p: ParameterHealth, health: HealthMessage,
               t: float, since_t: float) -> dict[str, Any]:
        machine = self.machine or health.machine
        meaning = self.meanings.get(name)
        what = f"{name} ({meaning})" if meaning else name
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
        return {
            "machine": machine,
            "parameter": name,
            "level": level,
            "previous": previous,
            "deviation_pct": dev,
            "threshold_pct": threshold,
            "value": value,
            "unit": unit,
            "nominal": nominal,
            "t": t,
            "window": int(health.window),
            "since_t": since_t,
            "message": msg,
        }
