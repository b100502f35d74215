"""Resume: what a daemon takes over from the state database and from the daemon before it.

A daemon with a gate (``[state]``) resumes at start the last accepted twin, the alarm levels
and the trends (:func:`restore`), unless the source's time starts over when it opens: a new
run, said once (:func:`note_new_run`). A reload's daemon resumes once the previous one has
finished (:meth:`~twinwatch.daemon.runner.Daemon.continue_from`) and goes on with its run id and
window numbering (:func:`continue_numbering`). Nothing here holds state.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

from twinwatch.twin.adaptation import TwinAdapter, TwinState

if TYPE_CHECKING:
    from twinwatch.config.schema import TwinwatchConfig
    from twinwatch.daemon.alarms import AlarmEvaluator
    from twinwatch.daemon.ringbuffer import RingBuffer
    from twinwatch.sinks.base import Gate
    from twinwatch.twin.diagnosis import Diagnoser
    from twinwatch.twin.health import HealthView
    from twinwatch.twin.prognostics import Prognostics

logger = logging.getLogger(__name__.rsplit(".", 1)[0] + ".runner")

__all__ = ["continue_numbering", "note_fresh", "note_new_run", "replay_trends",
           "restore", "resumes", "say_trend"]


def resumes(config: TwinwatchConfig, resume: bool | None) -> bool | None:
    """Whether a daemon on ``config`` resumes from its state database: ``resume`` when given;
    else None when the source's time starts over when it opens (a new run,
    :func:`note_new_run`), True otherwise.
    """
    from twinwatch.drivers import get_driver_class

    if resume is not None:
        return resume
    if get_driver_class(config.driver.type).time_starts_over(config.driver):
        return None
    return True


def restore(store: Gate, machine: str, adapter: TwinAdapter, alarms: AlarmEvaluator,
            run: str | None = None, diagnoser: Diagnoser | None = None
            ) -> tuple[TwinState | None, dict[str, Any] | None]:
    """Resume from the state database: the last accepted twin and the alarm levels of the last
    window. Both are read before either is used: a corrupt database resumes nothing. The trends
    are replayed (:func:`replay_trends`) and one line says so (:func:`say_trend`).

    Returns:
        ``(restored, resumed)``: the twin state given to the adapter (None when none was
        stored or it does not fit the configuration), and what was resumed for the start's
        line (None when nothing was).
    """
    state = store.load_twin_state(machine)
    last = store.latest_health(machine)
    if store.recovered:
        state = last = None
    restored: TwinState | None = None
    if state is not None:
        try:
            twin = TwinState.from_dict(state)
            adapter.restore(twin)
        except (KeyError, TypeError, ValueError) as exc:
            logger.error("the saved twin of %s in %s cannot be used with this "
                         "configuration (%s): starting from the nominal values", machine,
                         store.path, exc)
        else:
            restored = twin
            if diagnoser is not None and twin.diagnosis:
                diagnoser.restore(twin.diagnosis)
            logger.info("resumed the twin of %s from %s: %s; %d meta-model term(s)",
                        machine, store.path,
                        ", ".join(f"{k}={v:.6g}" for k, v in twin.trusted.items()),
                        len(twin.terms))
    raised = last.alarms if last is not None and last.alarms else None
    if raised is not None:
        alarms.restore(raised)
    if last is not None:  # a restart: whether the trends go on, in one line (say_trend)
        if adapter.prognostics is None:
            say_trend(machine, last, "not resumed: [prognostics] enabled = false")
        elif state is None:
            say_trend(machine, last, "not resumed: no twin was saved (no window of the "
                                     "previous run was trusted)")
        else:
            say_trend(machine, last, replay_trends(store, machine, adapter.prognostics,
                                                   run=run))
    if restored is None and raised is None:
        return restored, None
    return restored, {
        "path": str(store.path),
        "window": None if last is None else last.window,
        "t_end": None if last is None else last.t_end,
        "trusted": {} if restored is None else dict(restored.trusted),
        "terms": 0 if restored is None else len(restored.terms),
        "alarms": {k: a.level for k, a in (raised or {}).items()
                   if a is not None and a.level not in (None, "normal")},
    }


def replay_trends(store: Gate, machine: str, prognostics: Prognostics,
                  run: str | None = None) -> str:
    """Rebuild the parameters' trends from the evidence the stored windows published (the last
    ``[prognostics] horizon`` seconds of plant time, across earlier restarts:
    :meth:`~twinwatch.sinks.base.Gate.timeline`), so a restart resumes the trends and their RUL
    instead of waiting ``min_evidence`` windows.

    Args:
        run: the resuming daemon's run id: windows of that run are "this run" (a reload's),
            the others "previous" (a restart's).

    Returns:
        What was resumed, for :func:`say_trend` (``resumed from 57 windows ...``, or ``not
        resumed: ...``).
    """
    from twinwatch.twin.prognostics.rul import format_duration

    last = store.latest_health(machine)
    if last is None or last.t_end is None:
        return "not resumed: the last stored window has no time"
    horizon = prognostics.config.horizon
    messages = store.timeline(machine, float(last.t_end) - horizon)
    if not prognostics.replay(messages):
        return (f"not resumed: the stored windows of the last {format_duration(horizon)} "
                "([prognostics] horizon) carry no trend evidence")
    trends = prognostics.trends.values()
    windows = max(t.evidence for t in trends)
    first = min(t.t[0] for t in trends if t.t)
    runs = {m.run for m in messages if m.t_end is not None and m.t_end >= first}
    earlier = len(runs - {run})
    where = ("of this run" if not earlier else
             f"of this run and {earlier} earlier" if run in runs else
             "of the previous run" if earlier == 1 else f"of the previous {earlier} runs")
    parts = []
    for name, p in prognostics.predict(float(last.t_end)).items():
        if not p.trend.degrading:
            continue
        alarm = p.rul.alarm if p.rul is not None else None
        if alarm is None:
            parts.append(f"{name} degrading")
        elif alarm.status == "crossed":
            parts.append(f"{name} degrading, beyond its alarm threshold")
        elif alarm.status == "predicted":
            parts.append(f"{name} degrading: RUL {format_duration(alarm.rul_s)} to its alarm "
                         "threshold")
        else:
            parts.append(f"{name} degrading, its alarm threshold not likely reached")
    return (f"resumed from {windows} windows {where} "
            f"({'; '.join(parts) or 'no parameter degrading'})")


def say_trend(machine: str, last: HealthView, what: str) -> None:
    """One line per machine at a restart: whether its trends were resumed or why not. A
    warning when the last stored window reported a parameter degrading (a RUL that did not
    resume starts over from no evidence); else at info."""
    degrading = any(p.trend is not None and p.trend.degrading
                    for p in (last.parameters or {}).values())
    level = logging.WARNING if degrading else logging.INFO
    logger.log(level, "%s: trend %s", machine, what)


def note_fresh(store: Gate, machine: str) -> None:
    """``twinwatch run --fresh``: say that the stored twin and trends are not resumed
    (:func:`say_trend`) when the database holds this machine's earlier windows."""
    last = store.latest_health(machine)
    if last is None or store.recovered:
        return
    say_trend(machine, last, "not resumed: twinwatch run --fresh starts from the nameplate "
                             f"values ({store.path} keeps the earlier runs)")


def note_new_run(store: Gate, machine: str, driver_type: str, run_id: str
                 ) -> dict[str, Any] | None:
    """The source's time starts over, so the stored twin is not resumed: say so when the
    database holds earlier windows of this machine.

    Returns:
        ``reason``, ``path`` (the database), ``run`` (the id of the last stored run); None when
        the database holds none of this machine's windows (or was recovered).
    """
    last = store.latest_health(machine)
    if last is None or store.recovered:
        return None
    reason = f"the {driver_type} source's time starts over when it opens"
    logger.info("a new run %s of %s: %s; the twin starts from the nameplate values, the "
                "alarms from normal (%s keeps the earlier runs)", run_id, machine, reason,
                store.path)
    say_trend(machine, last, f"not resumed: a new run ({reason}; twinwatch run --resume "
                             "continues the last run)")
    return {"reason": reason, "path": str(store.path), "run": last.run}


def continue_numbering(ring: RingBuffer, previous: RingBuffer) -> None:
    """A reload's ring buffer numbers its windows on from the previous daemon's last one."""
    ring.first_index = previous.first_index + previous.windows
