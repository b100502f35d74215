"""One window's way from the twin to the sinks (the adaptation worker's job, paper Fig. 2;
docs/runtime.md, docs/architecture.md).

:class:`WindowPipeline` runs, for each window the ring buffer completes::

    adapt (TwinAdapter: estimation, re-validation, discovery)
      -> health message (twinwatch.twin.health)
      -> diagnosis (Diagnoser: the fault library's modes ranked, twinwatch.twin.diagnosis)
      -> alarms (AlarmEvaluator: levels, hysteresis, events; FaultAlarms on the diagnosis)
      -> sinks, in order: the gate (state store), then the others (Zenoh, Rerun, plug-ins)
      -> callbacks (the CLI's progress bar)

The health message is typed and frozen, encoded once; every sink writes the same text.
"Stored before published": a window the gate
(:attr:`~twinwatch.daemon.gatekeeper.GateKeeper.gate`) cannot store is not given to the
publishers, its alarm events wait for the next stored window; the recorders still get it.

Once :meth:`WindowPipeline.start` has started the ``twinwatch-outputs`` thread (a live source),
the worker only estimates and hands each window through a bounded queue (:data:`OUTPUT_QUEUE`),
so an output that waits (a locked state database) never holds up the
estimation. While the gate's database is locked the windows wait in memory
(:attr:`WindowPipeline.keeper`, at most
:data:`HELD_MAX`), stored and then published oldest first. Without that thread the outputs are
written from the caller's thread.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import numpy as np

from twinwatch.daemon.alarms import AlarmEvaluator, FaultAlarms
from twinwatch.daemon.gatekeeper import HELD_MAX, GateKeeper
from twinwatch.sinks.base import ProcessedWindow, Sink
from twinwatch.twin.adaptation import AdaptationResult, TwinAdapter, TwinState
from twinwatch.twin.diagnosis import Diagnoser
from twinwatch.twin.health import (
    AlarmStatus,
    DiagnosisHealth,
    HealthMessage,
    SourceHealth,
    build_health,
    complete_health,
    summary_line,
)
from twinwatch.twin.model import WindowData

logger = logging.getLogger(__name__)

__all__ = ["HELD_MAX", "HealthCallback", "ProcessedWindow", "WindowDigest", "WindowPipeline",
           "saved_twin"]

def saved_twin(adapter: TwinAdapter, diagnoser: Diagnoser | None, trusted: bool,
               evidence: bool = True) -> TwinState | None:
    """What the state store saves for a restart to resume from after a window: the accepted
    twin after a ``trusted`` window, and with ``evidence`` (and a diagnoser) the twin with the
    diagnoser's baseline and evidence whatever the window (a fault's windows are often not
    trusted, and a restart mid-fault must find its evidence); else None."""
    if diagnoser is None or not evidence:
        return adapter.state() if trusted else None
    return dataclasses.replace(adapter.state(), diagnosis=diagnoser.state())


EVIDENCE_EVERY = 30
"""The diagnoser's evidence (hundreds of kB: every hypothesis's last windows) is saved with
the first window of a pipeline, then every this many windows (a minute of 2 s windows) and at
its stop (:meth:`WindowPipeline.checkpoint`); the twin with each trusted window. A crash loses
at most this many windows of evidence (docs/diagnosis.md, "A restart resumes the evidence")."""


HealthCallback = Callable[[HealthMessage], None]
"""Called with each window's typed health message (worker thread)."""

OUTPUT_QUEUE = 64
"""Processed windows waiting for the outputs' thread. Full only when an output is slower than
the estimation; the estimation worker then waits (:meth:`WindowPipeline.backpressure`)."""

MEMORY_TAIL = 16
"""With a state store that reads back (:meth:`~twinwatch.sinks.store.StateStore.last_docs`),
the health messages kept in memory besides those waiting for the outputs
(:attr:`WindowPipeline.queued`): the store holds the rest of ``[acquisition] history``. At
least 1: the window the outputs' thread is writing has left the queue."""


class WindowDigest(NamedTuple):
    """What the run's summary reads of each window (about 100 bytes where the message is 9
    KB): the model check's verdict (None: disabled), the adaptation time [s] and the source's
    time-stamp jitter (RMS and largest, [us]; None: none)."""

    model_check_passed: bool | None
    elapsed_s: float
    jitter_rms_us: float | None
    jitter_max_us: float | None


_STOP = object()


class WindowPipeline:
    """Adapt the twin to each window and hand the result to the sinks.

    Args:
        nominal: parameter -> nominal value the deviations are measured from.
        counters: returns the daemon's counters for the health message.
        source: returns the source's state when a window's last sample was read (the health
            message's ``source``).
        history: health messages kept (:attr:`history`).
        diagnoser: ranks the machine's fault modes each window; None: no diagnosis.

    Attributes:
        sinks: written in order for each window (the gate first).
        keeper: the gate (the state store, or None) and the windows held while another
            process locks its database.
        run: the run id of the messages (a reload's pipeline takes the running one's).
    """

    def __init__(self, *, adapter: TwinAdapter, alarms: AlarmEvaluator, machine: str,
                 model_name: str, run: str, nominal: Mapping[str, float],
                 counters: Callable[[], Mapping[str, int]], history: int,
                 source: Callable[[WindowData], tuple[str | None, list[str], list[str]]]
                 | None = None,
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
        self._held_events: deque[dict[str, Any]] = deque(maxlen=1000)
        self.callbacks: list[HealthCallback] = []
        self.latest: HealthMessage | None = None
        #: the last ``history`` health messages as their JSON (a fraction of the typed
        #: message's memory); with a gate that reads back, only those not stored yet and
        #: :data:`MEMORY_TAIL` more
        self.history: deque[str] = deque(maxlen=history)
        self.history_size = history
        #: the last ``history`` windows' :class:`WindowDigest` (the run's summary)
        self.digests: deque[WindowDigest] = deque(maxlen=history)
        self._reader: Callable[[str, str, int], list[str]] | None = None
        self.windows_estimated = 0
        self._failing: set[str] = set()
        self._lock = threading.Lock()
        self.keeper = GateKeeper(machine, self._write, logger)
        self._writing: tuple[str, float] | None = None  # (output, since) while one writes
        self._queue: queue.Queue[Any] | None = None
        self._thread: threading.Thread | None = None
        self._stop_by: float | None = None  # monotonic: give up on the lock after it
        self._blocked = False  # the worker waits for room in the outputs' queue
        self._evidence_age = 0  # 1: this window saves the diagnoser's evidence, then 2, ...

    # -- the outputs' thread -------------------------------------------------------------------
    def start(self, name: str = "twinwatch-outputs") -> None:
        """Write the outputs from a thread of their own from now on (see the module
        docstring). Idempotent."""
        if self._thread is not None:
            return
        self._queue = queue.Queue(maxsize=OUTPUT_QUEUE)
        self._stop_by = None
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def stop(self, timeout: float) -> None:
        """Write the windows queued for the outputs, then stop their thread: windows waiting
        for a locked state database are waited for ``timeout`` seconds [wall], then left
        in the store's backlog and counted as not published."""
        thread, q = self._thread, self._queue
        if thread is None or q is None:
            return
        self._stop_by = time.monotonic() + timeout
        with contextlib.suppress(queue.Full):  # blocks while the queued windows are written
            q.put(_STOP, timeout=timeout + 30.0)
        thread.join(timeout=timeout + 30.0)
        if thread.is_alive():
            logger.warning("%s: the outputs did not finish writing within %.0f s",
                           self.machine, timeout + 30.0)
        self._thread = None
        self._queue = None

    def checkpoint(self) -> bool:
        """After :meth:`stop`: save the diagnoser's evidence of the last window with the
        accepted twin (:meth:`~twinwatch.sinks.base.Gate.save_state`) unless that window saved
        it already. True when it was saved now."""
        gate, last = self.keeper.gate, self.latest
        if (self.diagnoser is None or gate is None or last is None
                or self._evidence_age == 1):
            return False
        self._evidence_age = 1
        try:
            state = saved_twin(self.adapter, self.diagnoser, True)
            assert state is not None
            return gate.save_state(self.machine, last.window, last.t_end, state.as_dict())
        except Exception:  # noqa: BLE001 - the stop goes on; the last checkpoint stays
            logger.warning("%s: the diagnosis evidence of window %d could not be saved at the "
                           "stop; a restart resumes the last one saved, at most %d windows "
                           "older", self.machine, last.window, EVIDENCE_EVERY, exc_info=True)
            return False

    @property
    def queued(self) -> int:
        """Windows waiting for the outputs' thread, and held for a locked state database."""
        q = self._queue
        return (q.qsize() if q is not None else 0) + self.keeper.held

    def backpressure(self) -> str | None:
        """Why the estimation worker waits on the outputs now (their queue is full, or, without
        the outputs' thread, one writes a window for more than a second), or None: what an
        overrun's message names."""
        writing = self._writing or self.keeper.writing
        if not self._blocked and (writing is None or self._thread is not None
                                  or time.monotonic() - writing[1] <= 1.0):
            return None
        if writing is None:
            return f"the outputs are {OUTPUT_QUEUE} windows behind"
        name, since = writing
        gate = self.keeper.gate
        locked = gate is not None and gate.name == name and gate.locked
        why = " (its database is locked by another process)" if locked else ""
        return (f"the {name} output has been writing one window for "
                f"{time.monotonic() - since:.0f} s{why}")

    def counters(self) -> dict[str, int]:
        """``store_delayed`` (windows that waited in memory for the state database's lock,
        in all) and ``outputs_queued`` (windows waiting for the outputs now)."""
        return {**self.keeper.counters(), "outputs_queued": int(self.queued)}

    def summary(self) -> list[str]:
        """The windows that waited for a locked state database, if any."""
        return self.keeper.summary()

    def _run(self) -> None:
        q = self._queue
        assert q is not None
        stopping = False
        while not stopping or self.keeper.held:
            if self.keeper.held:  # the gate's database is locked: take what comes, try again
                stopping = self._drain_into_held(q) or stopping
                past = self._stop_by is not None and time.monotonic() >= self._stop_by
                self._retry_held(give_up=stopping and past)
                continue
            got = q.get()
            if got is _STOP:
                stopping = True
                continue
            self._deliver(got)

    def _drain_into_held(self, q: queue.Queue[Any]) -> bool:
        """Every queued window into the gate's memory (none written now). True if the stop
        marker was among them."""
        stop = False
        while True:
            try:
                got = q.get_nowait()
            except queue.Empty:
                return stop
            if got is _STOP:
                stop = True
            else:
                self._hold(got)

    def _hold(self, out: ProcessedWindow) -> None:
        """A window behind the locked database: the keeper holds it (beyond :data:`HELD_MAX`:
        not published); the recorders get it now."""
        stored = self.keeper.hold(out)
        self._write_others(out, stored=stored)

    def _retry_held(self, give_up: bool) -> None:
        """One more attempt to store the held windows (:meth:`GateKeeper.retry`); stored:
        published, oldest first."""
        released = self.keeper.retry(give_up)
        if released is None:
            return
        held, stored = released
        for out in held:
            if stored:
                self._write_others(out, stored=True, recorders=False)
            else:
                self._held_events.extend(out.events)

    # -- the windows ---------------------------------------------------------------------------
    def _deliver(self, out: ProcessedWindow) -> None:
        """Write one processed window to every output, the gate first."""
        stored = self.keeper.store(out, can_hold=self._thread is not None)
        if stored:
            self._trim_history()
        self._write_others(out, stored=stored)

    def _trim_history(self) -> None:
        """With a gate that reads back, drop the oldest messages in :attr:`history` beyond
        the windows waiting for the outputs and :data:`MEMORY_TAIL` (those are stored)."""
        if self._stored_docs() is None:
            return
        with self._lock:
            while len(self.history) > self.queued + MEMORY_TAIL:
                self.history.popleft()

    def _write_others(self, out: ProcessedWindow, *, stored: bool | None,
                      recorders: bool = True) -> None:
        """The outputs after the gate: the recorders (with ``recorders``), and the publishers
        when ``stored`` (False: its alarm events wait for the next stored window; None: held
        for the gate's lock, published later)."""
        published = out
        if stored is False:  # served by the history query once the store has written it
            self._held_events.extend(out.events)
        elif stored and self._held_events:  # the events of the windows not published
            published = dataclasses.replace(out, events=[*self._held_events, *out.events])
            self._held_events.clear()
        for sink in self.sinks:
            if sink is self.keeper.gate:
                continue
            if sink.publishes:
                if not stored:
                    continue
            elif not recorders:
                continue
            self._writing = (sink.name, time.monotonic())
            try:
                self._write(sink, published if sink.publishes else out)
            finally:
                self._writing = None

    def _write(self, sink: Sink, out: ProcessedWindow) -> bool | None:
        """``sink.write(out)``. An output that raises does not stop the others: the window is
        counted in its ``lost``, logged once until it works again."""
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

    def _diagnose(self, reading: HealthMessage, window: WindowData,
                  result: AdaptationResult) -> DiagnosisHealth | None:
        """The window's diagnosis; None without a diagnoser, or when it failed (logged once:
        the window is published without one)."""
        if self.diagnoser is None:
            return None
        try:
            est = result.estimate
            free = sum(1 for s in est.status.values() if s == "estimated") + (
                0 if est.initial is None else int(np.size(est.initial)))
            return self.diagnoser.update(reading, result.fit, est.simulated, free,
                                         est.initial)
        except Exception:  # noqa: BLE001 - the window is published without a diagnosis
            log = logger.debug if self._diagnosis_failed else logger.exception
            self._diagnosis_failed = True
            log("the diagnosis failed on window %d: published without one", window.index)
            return None

    def _source_health(self, window: WindowData) -> SourceHealth:
        """The window's ``source``: its stamps' jitter against the grid the ring buffer placed
        it on [us], and what the source waited for or lacked when its last sample was read."""
        waiting, silent, faults = (self._source(window) if self._source is not None
                                   else (None, [], []))
        jitter = window.stamp_jitter
        if jitter is None or jitter.size == 0:
            rms = peak = 0.0
        else:
            rms = float(np.sqrt(np.mean(np.square(jitter)))) * 1e6
            peak = float(np.max(np.abs(jitter))) * 1e6
        return SourceHealth(jitter_rms_us=rms, jitter_max_us=peak, waiting=waiting,
                            silent=list(silent), device_faults=list(faults))

    def _stored_docs(self) -> Callable[[str, str, int], list[str]] | None:
        """The gate's reader of stored messages (machine, run, limit -> JSON, oldest first),
        None when the gate keeps none; the last gate's when the outputs are closed."""
        reader = getattr(self.keeper.gate, "last_docs", None)
        if reader is not None:
            self._reader = reader
        return self._reader

    def recent(self) -> list[HealthMessage]:
        """The last ``history`` health messages, typed, oldest first (safe while the worker
        appends): those in memory, and before them, with a state store, the stored ones."""
        with self._lock:
            kept = list(self.history)
        typed = [HealthMessage.model_validate_json(doc) for doc in kept]
        reader = self._stored_docs()
        if reader is None or len(typed) >= self.history_size:
            return typed
        try:
            stored = reader(self.machine, self.run, self.history_size)
        except Exception:  # noqa: BLE001 - what memory holds is still the recent history
            logger.warning("the stored history could not be read: the last %d windows only",
                           len(typed), exc_info=True)
            return typed
        held = {(h.window, h.t_end) for h in typed}
        older = [h for h in (HealthMessage.model_validate_json(doc) for doc in stored)
                 if (h.window, h.t_end) not in held]
        return [*older, *typed][-self.history_size:]

    def digest(self) -> list[WindowDigest]:
        """A snapshot of :attr:`digests` (the last ``history`` windows)."""
        with self._lock:
            return list(self.digests)

    def process(self, window: WindowData) -> HealthMessage:
        """Run one window through the pipeline (see the module docstring).

        Returns:
            The typed health message (its encoding is what the sinks wrote).

        Raises:
            Exception: whatever the adaptation raises on a bad window (the daemon counts it
                as a numeric failure and goes on).
        """
        result = self.adapter.process(window)
        self.windows_estimated += 1
        # the estimation's message: what the diagnosis and the alarms read
        reading = build_health(machine=self.machine, model_name=self.model_name, run=self.run,
                               model=self.adapter.model, window=window, adaptation=result,
                               nominal=self.nominal, counters=self._counters(),
                               discovery_enabled=self.adapter.enabled,
                               source=self._source_health(window))
        diagnosis = self._diagnose(reading, window, result)
        events = self.alarms.update(reading)
        if self.fault_alarms is not None:
            diagnosis, fault_events = self.fault_alarms.update(diagnosis, reading)
            events += fault_events
        # the window's message, built once from everything it carries
        health = complete_health(reading, diagnosis=diagnosis, alarms={
            name: AlarmStatus.model_validate(state)
            for name, state in self.alarms.state().items()})
        self._evidence_age = self._evidence_age % EVIDENCE_EVERY + 1
        out = ProcessedWindow(window=window, result=result, health=health,
                              health_json=health.to_json(), events=events,
                              twin_state=saved_twin(self.adapter, self.diagnoser,
                                                    result.estimate.trusted,
                                                    evidence=self._evidence_age == 1))
        check = health.model_check
        digest = WindowDigest(None if check is None else check.passed, health.elapsed_s,
                              health.source.jitter_rms_us, health.source.jitter_max_us)
        with self._lock:
            self.latest = health
            self.history.append(out.health_json)
            self.digests.append(digest)
        self._trim_history()
        logger.info("%s", summary_line(health))
        q = self._queue
        if q is None:
            self._deliver(out)
        else:  # the outputs' thread; full only when an output is slower than the estimation
            try:
                q.put_nowait(out)
            except queue.Full:
                self._blocked = True
                try:
                    q.put(out)
                finally:
                    self._blocked = False
        for fn in self.callbacks:
            fn(health)
        return health
