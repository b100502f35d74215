"""The window worker: the thread that processes each window the acquisition completes.

:func:`make_pipeline` builds what a window goes through
(:class:`~twinwatch.daemon.pipeline.WindowPipeline`). :class:`WindowWorker` runs it, one window
at a time, in its own thread (``<prefix>-adaptation``), so acquisition is never blocked by the
optimiser.

Between the acquisition and the worker a bounded queue: for a live source a full queue drops
the window as an *overrun* (counted in every health message); on a simulated clock the
acquisition waits instead. In a gateway a window is processed under one of the process's
estimation slots (:class:`~twinwatch.daemon.slots.EstimationSlots`).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from twinwatch.daemon.alarms import AlarmEvaluator, FaultAlarms
from twinwatch.daemon.pipeline import WindowPipeline
from twinwatch.twin.adaptation import TwinAdapter
from twinwatch.twin.diagnosis import Diagnoser

if TYPE_CHECKING:
    from twinwatch.config.schema import TwinwatchConfig
    from twinwatch.daemon.slots import EstimationSlots
    from twinwatch.daemon.systemd import Watchdog
    from twinwatch.twin.model import TwinModel, WindowData

# the daemon's parts log as twinwatch.daemon.runner (journal filters)
logger = logging.getLogger(__name__.rsplit(".", 1)[0] + ".runner")

__all__ = ["QUEUE_WAITS", "RECENT_WINDOWS", "WindowWorker", "make_diagnoser", "make_pipeline"]

_STOP = object()

QUEUE_WAITS = 10000
"""Windows whose queue wait (submission to the start of processing) the daemon keeps
(:attr:`WindowWorker.queue_waits`)."""


RECENT_WINDOWS = 20
"""Windows whose outcome (estimated, failed, abandoned, overrun) the daemon keeps to tell
systemd's STATUS whether estimation works *now* (:meth:`WindowWorker.estimation_problem`)."""


def make_diagnoser(config: TwinwatchConfig, model: TwinModel,
                   nominal: Mapping[str, float]) -> Diagnoser | None:
    """The machine's diagnosis (``[diagnosis]``, :class:`~twinwatch.twin.diagnosis.Diagnoser`);
    None when off or when the model has no fault mode."""
    d = config.diagnosis
    if not d.enabled:
        return None
    library = d.resolve(config.machine.model)
    if not library.faults:
        return None
    source = "configured" if (d.replace or d.library or d.faults) else "shipped"
    resolved = config.estimation.resolved(model)
    return Diagnoser(library, model, nominal, estimate=list(resolved.estimate or ()),
                     ties=dict(resolved.tie or {}), config=d, source=source,
                     resolution=config.estimation.model_error)


def make_pipeline(config: TwinwatchConfig, model: TwinModel, nominal: Mapping[str, float], *,
                  run: str, counters: Callable[[], Mapping[str, int]],
                  source: Callable[[WindowData], tuple[str | None, list[str], list[str]]]
                  ) -> WindowPipeline:
    """The window pipeline of a daemon on ``config``: adapter, alarms and diagnosis; its
    outputs are given later (:meth:`twinwatch.daemon.outputs.Outputs.wire`)."""
    acq = config.acquisition
    adapter = TwinAdapter(model, config.estimation, config.discovery, nominal,
                          prognostics=config.prognostics,
                          thresholds=config.alarms.rul_targets(nominal),
                          adaptive=acq.adaptive, label=config.machine.name)
    machine = config.machine.name
    pipeline = WindowPipeline(
        adapter=adapter, alarms=AlarmEvaluator(config.alarms, machine), machine=machine,
        model_name=config.machine.model, run=run, nominal=nominal, counters=counters,
        history=acq.history, source=source, diagnoser=make_diagnoser(config, model, nominal))
    dc = config.diagnosis
    if pipeline.diagnoser is not None and dc.alarm is not None:
        pipeline.fault_alarms = FaultAlarms(dc.alarm, dc.clear, dc.raise_after_windows,
                                            dc.clear_after_windows, machine)
    return pipeline


class WindowWorker:
    """The thread that processes the windows the acquisition submits, one at a time.

    Args:
        process: processes one window; what it raises is contained to the window (a numeric
            failure, logged once per kind).
        backpressure: names the output that holds up the worker, or None (an overrun's message).
        stopping: set when the daemon was asked to stop.
        slots: the estimation slots a window's processing is taken under (a gateway); None: no
            limit.
        abandon: drop the windows still queued once a stop was asked
            (``[acquisition] abandon_on_stop``; a second SIGTERM sets it).

    Attributes:
        queue_waits: seconds each of the last :data:`QUEUE_WAITS` windows waited from its
            submission to the start of its processing (the queue, and a gateway's slot).
        overruns: windows of a live source dropped because the queue was full.
        dropped_at_stop: windows queued at a stop that the worker did not reach within the
            shutdown timeout.
        recent_outcomes: the last :data:`RECENT_WINDOWS` outcomes: "estimated", "failed",
            "abandoned", "overrun".
    """

    def __init__(self, *, machine: str, process: Callable[[WindowData], object],
                 backpressure: Callable[[], str | None], stopping: threading.Event,
                 queue_size: int, slots: EstimationSlots | None = None,
                 watchdog: Watchdog | None = None, abandon: bool = False) -> None:
        self.machine = machine
        self._process = process
        self._backpressure = backpressure
        self._stopping = stopping
        self.slots = slots
        self.watchdog = watchdog
        self.abandon = abandon
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=queue_size)
        self._thread: threading.Thread | None = None
        self._closing = False
        self._failure: tuple[str | None, int] = (None, 0)
        self.queue_waits: deque[float] = deque(maxlen=QUEUE_WAITS)
        self.overruns = 0
        self._overrun_causes: set[str] = set()   # the causes already said (:meth:`submit`)
        self.numeric_failures = 0
        self.dropped_at_stop = 0
        self.recent_outcomes: deque[str] = deque(maxlen=RECENT_WINDOWS)

    def start(self, name: str) -> None:
        """Start the worker thread ``name``."""
        self._thread = threading.Thread(target=self._work, name=name, daemon=True)
        self._thread.start()

    def submit(self, window: WindowData, *, block: bool) -> None:
        """Queue ``window``; with ``block`` wait for room (a source on a simulated clock) until
        the daemon stops, else a full queue drops it as an overrun (a live source)."""
        item = (window, time.monotonic())
        if block:
            while not self._stopping.is_set():
                try:
                    self._queue.put(item, timeout=0.2)
                    return
                except queue.Full:
                    continue
            return
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            self.overruns += 1
            self.recent_outcomes.append("overrun")
            waiting = self._backpressure()
            # said at the first overrun of each cause and at the 10th, 100th, ...
            cause = "outputs" if waiting is not None else "estimation"
            first = cause not in self._overrun_causes
            self._overrun_causes.add(cause)
            level = (logging.WARNING if first or _power_of_ten(self.overruns)
                     else logging.DEBUG)
            why = (f"the estimation waits for the outputs: {waiting}" if waiting is not None
                   else "the estimation does not keep up with acquisition: lower "
                   "[estimation.pso].max_generations or the time budget")
            logger.log(level, "estimation overrun: window %d dropped (%d so far); %s",
                       window.index, self.overruns, why)

    def abandoned(self, n: int) -> None:
        """``n`` more windows were abandoned by the ring buffer (gaps, bad values, ...)."""
        self.recent_outcomes.extend(["abandoned"] * min(n, RECENT_WINDOWS))

    def drain(self, timeout: float) -> None:
        """Stop the worker after the windows already queued, bounded by ``timeout`` seconds."""
        if self._thread is None:
            return
        deadline = time.monotonic() + timeout
        while self._thread.is_alive():
            try:
                self._queue.put(_STOP, timeout=0.2)
                break
            except queue.Full:  # a worker that does not take windows (stuck, or waiting
                if time.monotonic() > deadline:  # for an estimation slot) bounds the stop
                    break
        self._thread.join(timeout=max(0.0, deadline - time.monotonic()))
        if self._thread.is_alive():
            # the outputs close next: the worker takes no further window
            self._closing = True
            logger.warning("%s: adaptation worker did not finish within %.0f s: the windows "
                           "still queued are dropped", self.machine, timeout)
        self._thread = None

    def _work(self) -> None:
        while True:
            try:
                got = self._queue.get(timeout=0.5)
            except queue.Empty:
                if self._closing:  # the stop gave up on this worker: nothing more comes
                    return
                continue
            if got is _STOP:
                return
            item, submitted = got
            if self._stopping.is_set() and self.abandon:
                logger.info("window %d abandoned on stop", item.index)
                continue
            if self._closing:  # the shutdown timeout has passed: the outputs are closing
                self.dropped_at_stop += 1
                continue
            slots, slot = self.slots, None
            if slots is not None:
                slot = slots.acquire(self.machine, cancelled=lambda: self._closing)
                if slot is None:
                    self.dropped_at_stop += 1
                    continue
            self.queue_waits.append(time.monotonic() - submitted)
            if self.watchdog is not None:
                self.watchdog.busy()
            try:
                self._process(item)
                self.recent_outcomes.append("estimated")
                self._window_failed(None, item.index)
            except Exception as exc:  # contained to the window: the daemon goes on
                self.numeric_failures += 1
                self.recent_outcomes.append("failed")
                self._window_failed(exc, item.index)
                logger.debug("window %d failed", item.index, exc_info=True)
            finally:
                if slots is not None and slot is not None:
                    slots.release(slot)
                if self.watchdog is not None:
                    self.watchdog.idle()

    def _window_failed(self, exc: Exception | None, index: int) -> None:
        """A window's failure is logged once, then counted: the same failure again only adds
        to the count; a different one, or the first window estimated again, is logged with
        how many times the previous one repeated."""
        key = None if exc is None else f"{type(exc).__name__}: {exc}"
        last, repeats = self._failure
        if key is not None and key == last:
            self._failure = (last, repeats + 1)
            return
        if last is not None and repeats:
            logger.warning("%s: the failure above repeated in %d more windows (%s)",
                           self.machine, repeats, last)
        if key is None:
            if last is not None:
                logger.warning("%s: window %d estimated again after %d failed windows",
                               self.machine, index, repeats + 1)
            self._failure = (None, 0)
            return
        logger.error("%s: window %d could not be estimated (%s); it is skipped and counted in "
                     "counters.numeric_failures (the same failure again is counted, not "
                     "logged)", self.machine, index, key)
        self._failure = (key, 0)

    def estimation_problem(self) -> str | None:
        """A line when at least half of the last windows (at least 3 of at most
        :data:`RECENT_WINDOWS`) were not estimated, else None."""
        recent = list(self.recent_outcomes)
        bad = [o for o in recent if o != "estimated"]
        if len(recent) < 3 or 2 * len(bad) < len(recent):
            return None
        kinds = ", ".join(f"{n} {k}" for k, n in sorted(
            {k: bad.count(k) for k in set(bad)}.items()))
        return f"{len(bad)} of the last {len(recent)} windows not estimated ({kinds})"


def _power_of_ten(n: int) -> bool:
    """Whether ``n`` is 10, 100, 1000, ..."""
    while n >= 10 and n % 10 == 0:
        n //= 10
    return n == 1
