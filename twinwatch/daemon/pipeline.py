"""One window's way from the twin to the sinks (the adaptation worker's job, paper Fig. 2).

:class:`WindowPipeline` runs, for each window the ring buffer completes::

    adapt (TwinAdapter: estimation, re-validation, discovery)
      -> health message (twinwatch.twin.health)
      -> diagnosis (Diagnoser: the fault library's modes ranked, twinwatch.twin.diagnosis)
      -> alarms (AlarmEvaluator: levels, hysteresis, events; FaultAlarms on the diagnosis)
      -> sinks, in order: the gate (state store), then the others (Zenoh, Rerun, plug-ins)
      -> callbacks (the CLI's progress bar)

The health message is typed (:class:`~twinwatch.twin.health.HealthMessage`) from end to end
(the alarms, the sinks and the callbacks read it typed), built once and encoded once
(:meth:`~twinwatch.twin.health.HealthMessage.to_json`): every sink writes the same text. The
sinks share one contract, :class:`~twinwatch.sinks.base.Sink` (``write(ProcessedWindow)``,
``close()``, its role); the pipeline knows none by name. Their order is the guarantee "stored
before published": a health message a subscriber has seen is always in the state database, also
after SIGKILL. The sink whose role is ``gate`` (the state store) is the pipeline's
:attr:`~WindowPipeline.gate`: a window it cannot store (a full disk, a read-only file; it waits
in the store's backlog) is not given to the sinks that publish (role ``publisher``: Zenoh, a
plug-in by default), and its alarm events wait for the next window that is stored; the
recorders (Rerun) still get it.

The pipeline holds no thread: :class:`~twinwatch.daemon.runner.Daemon` calls
:meth:`WindowPipeline.process` from its ``twinwatch-adaptation`` worker, one window at a time.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from twinwatch.daemon.alarms import AlarmEvaluator, FaultAlarms
from twinwatch.sinks.base import ProcessedWindow, Sink
from twinwatch.twin.adaptation import TwinAdapter
from twinwatch.twin.diagnosis import Diagnoser, shaft_speed
from twinwatch.twin.health import (
    AlarmStatus,
    HealthMessage,
    SourceHealth,
    build_health,
    summary_line,
)
from twinwatch.twin.model import WindowData

logger = logging.getLogger(__name__)

__all__ = ["HealthCallback", "ProcessedWindow", "WindowPipeline"]

HealthCallback = Callable[[HealthMessage], None]
"""Called with each window's typed health message (worker thread)."""


class WindowPipeline:
    """Adapt the twin to each window and hand the result to the sinks.

    Args:
        adapter: the twin's estimation and discovery.
        alarms: the alarm evaluator (restored from the state store by the daemon).
        machine: machine name (the Zenoh key segment).
        model_name: registry name of the twin model, for the health message.
        run: the run id every health message carries (:attr:`run`).
        nominal: parameter -> nominal value the deviations are measured from.
        counters: returns the daemon's counters for the health message.
        source: returns what the source waits for (None when it delivers) and its silent
            messages, for the health message's ``source``.
        history: health messages kept in memory (:attr:`history`).
        diagnoser: ranks the machine's fault modes each window (the message's ``diagnosis``);
            None: no diagnosis.

    Attributes:
        sinks: written in order for each window (the gate first: stored before published).
        gate: the sink that must take a window before the publishing sinks get it (the state
            store), or None.
        latest: the last health message (typed); ``history`` the last ``history`` of them.
        windows_estimated: windows processed.
        run: the run id of the messages (a reload's pipeline takes the running one's).
    """

    def __init__(self, *, adapter: TwinAdapter, alarms: AlarmEvaluator, machine: str,
                 model_name: str, run: str, nominal: Mapping[str, float],
                 counters: Callable[[], Mapping[str, int]], history: int,
                 source: Callable[[], tuple[str | None, list[str]]] | None = None,
                 diagnoser: Diagnoser | None = None) -> None:
        self.adapter = adapter
        self.run = run
        self.alarms = alarms
        self.machine = machine
        self.model_name = model_name
        self.nominal = dict(nominal)
        self._counters = counters
        self._source = source
        self.diagnoser = diagnoser
        self.fault_alarms: FaultAlarms | None = None
        self._diagnosis_failed = False
        self.sinks: list[Sink] = []
        self.gate: Sink | None = None
        self._held_events: deque[dict[str, Any]] = deque(maxlen=1000)
        self.callbacks: list[HealthCallback] = []
        self.latest: HealthMessage | None = None
        self.history: deque[HealthMessage] = deque(maxlen=history)
        self.windows_estimated = 0
        self._failing: set[str] = set()
        self._lock = threading.Lock()

    def _write(self, sink: Sink, out: ProcessedWindow) -> bool | None:
        """``sink.write(out)``. An output that raises (a plug-in's bug) does not stop the
        others: the window is counted in its ``lost`` (``twinwatch run`` exits 74), logged
        once until it works again; for the gate it is a window not stored."""
        try:
            result = sink.write(out)
        except Exception as exc:  # noqa: BLE001 - one output must not stop the others
            sink.lost += 1
            log = logger.debug if sink.name in self._failing else logger.error
            self._failing.add(sink.name)
            log("the %s output failed on window %d (%s: %s): the window is lost for it "
                "(%d so far)", sink.name, out.health.window, type(exc).__name__, exc, sink.lost)
            logger.debug("the %s output failed", sink.name, exc_info=True)
            return False
        if sink.name in self._failing:
            self._failing.discard(sink.name)
            logger.warning("the %s output works again", sink.name)
        return result

    def _source_health(self, window: WindowData) -> SourceHealth:
        """The window's ``source``: its stamps' jitter against the grid the ring buffer placed
        it on [us], and what the source waits for or lacks now."""
        waiting, silent = self._source() if self._source is not None else (None, [])
        jitter = window.stamp_jitter
        if jitter is None or jitter.size == 0:
            rms = peak = 0.0
        else:
            rms = float(np.sqrt(np.mean(np.square(jitter)))) * 1e6
            peak = float(np.max(np.abs(jitter))) * 1e6
        return SourceHealth(jitter_rms_us=rms, jitter_max_us=peak, waiting=waiting,
                            silent=list(silent))

    def recent(self) -> list[HealthMessage]:
        """A snapshot of :attr:`history` (safe while the worker appends)."""
        with self._lock:
            return list(self.history)

    def process(self, window: WindowData) -> HealthMessage:
        """Adapt the twin to one window (estimation, then discovery when needed), evaluate
        the alarms, write the window to every sink, call the callbacks.

        Returns:
            The typed health message (its encoding is what the sinks wrote).

        Raises:
            Exception: whatever the adaptation raises on a bad window (the daemon counts it
                as a numeric failure and goes on).
        """
        result = self.adapter.process(window)
        self.windows_estimated += 1
        health = build_health(machine=self.machine, model_name=self.model_name, run=self.run,
                              model=self.adapter.model, window=window, adaptation=result,
                              nominal=self.nominal, counters=self._counters(),
                              discovery_enabled=self.adapter.enabled)
        health.source = self._source_health(window)
        if self.diagnoser is not None:
            try:
                health.diagnosis = self.diagnoser.update(
                    health, shaft_speed(window, self.diagnoser.library.speed_channel))
            except Exception:  # noqa: BLE001 - the window is published without a diagnosis
                log = logger.debug if self._diagnosis_failed else logger.exception
                self._diagnosis_failed = True
                log("the diagnosis failed on window %d: published without one", window.index)
        events = self.alarms.update(health)
        if self.fault_alarms is not None:
            events += self.fault_alarms.update(health)
        health.alarms = {name: AlarmStatus.model_validate(state)
                         for name, state in self.alarms.state().items()}
        out = ProcessedWindow(window=window, result=result, health=health,
                              health_json=health.to_json(), events=events,
                              twin_state=self.adapter.state() if result.estimate.trusted
                              else None)
        with self._lock:
            self.latest = health
            self.history.append(health)
        logger.info("%s", summary_line(health))
        stored = self.gate is None or self._write(self.gate, out) is not False
        published = out
        if not stored:  # served by the history query once the store has written it
            self._held_events.extend(out.events)
        elif self._held_events:  # the alarm events of the windows that were not published
            published = dataclasses.replace(out, events=[*self._held_events, *out.events])
            self._held_events.clear()
        for sink in self.sinks:
            if sink is self.gate or (sink.publishes and not stored):
                continue
            self._write(sink, published if sink.publishes else out)
        for fn in self.callbacks:
            fn(health)
        return health
