"""The daemon: one machine's monitor, composed of its parts.

:class:`Daemon` puts together, for one machine (see docs/architecture.md, "Threads")::

    acquisition (acquisition.py, the caller's thread)
      driver.read() -> RingBuffer -> window
        -> bounded queue -> window worker (window_worker.py, ``<prefix>-adaptation`` thread)
             WindowPipeline.process (pipeline.py): estimation, discovery, prognostics,
             health message, diagnosis, alarms
               -> outputs (outputs.py; a live source: the ``<prefix>-outputs`` thread)
                    the gate (the state database) first, then Zenoh, Rerun, MQTT, plug-ins
    resume (resume.py): the twin, alarm levels and trends from the state database at start and
    after a reload, the run id and the window numbering of a reload

The caller's thread (the machine's) runs :meth:`Daemon.run`: it reads the driver, fills the ring
buffer and hands each full window to the worker, never estimating.
Each part keeps its own state; the daemon forwards to it.
"""

from __future__ import annotations

import logging
import secrets
import threading
import time
from collections import deque
from collections.abc import Callable, Collection, Container, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from twinwatch._forward import Forward
from twinwatch.daemon.acquisition import STOP_AT_WINDOW_S, Acquisition
from twinwatch.daemon.outputs import Outputs, close_logged
from twinwatch.daemon.resume import (
    continue_numbering,
    note_fresh,
    note_new_run,
    restore,
    resumes,
)
from twinwatch.daemon.window_worker import (
    QUEUE_WAITS,
    RECENT_WINDOWS,
    WindowWorker,
    make_diagnoser,
    make_pipeline,
)
from twinwatch.drivers.base import source_problem_lines
from twinwatch.sinks import SINKS
from twinwatch.twin.models import create_model

if TYPE_CHECKING:  # the configuration is given by the caller; the daemon never reads files
    from twinwatch.config.schema import TwinwatchConfig
    from twinwatch.daemon.alarms import AlarmEvaluator
    from twinwatch.daemon.pipeline import HealthCallback, WindowDigest, WindowPipeline
    from twinwatch.daemon.ringbuffer import RingBuffer
    from twinwatch.daemon.slots import EstimationSlots
    from twinwatch.daemon.systemd import Watchdog
    from twinwatch.drivers.base import Driver
    from twinwatch.sinks.base import Gate, SharedResources, Sink
    from twinwatch.twin.adaptation import TwinAdapter, TwinState
    from twinwatch.twin.estimation.estimator import Estimator
    from twinwatch.twin.health import HealthMessage
    from twinwatch.twin.model import TwinModel, WindowData

logger = logging.getLogger(__name__)

__all__ = ["QUEUE_WAITS", "RECENT_WINDOWS", "SINKS", "STOP_AT_WINDOW_S", "Daemon",
           "make_diagnoser", "new_run_id"]


def new_run_id() -> str:
    """A new run id: the start's UTC time and 6 random hex digits, e.g.
    ``20261122T101530Z-3f9a2c`` (sorts by start; unique across machines and restarts within
    the same second; letters, digits and ``-`` only, so it goes in a selector unquoted)."""
    return time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()) + "-" + secrets.token_hex(3)


class Daemon:
    """One machine's monitor.

    Args:
        base_dir: directory relative paths in the config are resolved against (the config
            file's directory).
        driver: an already-open driver to use instead of the configured one (tests).
        publish: open the outputs whose role is ``publisher`` (Zenoh, plug-ins).
        record: open the outputs whose role is ``recorder`` (the Rerun recording).
        persist: open the gate (the state database, if ``[state]`` is enabled): resume from
            it, save every window, serve the history query.
        watchdog: the systemd watchdog gate (ticked by the acquisition, busy/idle by the worker).
        reuse: what a reload hands over from the running daemon (:meth:`handover`): open
            outputs (registry name -> sink) and under ``"driver"`` its open driver.
            They stay the running daemon's until :meth:`continue_from` (a failed start leaves
            them open and bound to it).
        resume: restore the saved twin and alarm levels from the state database (False:
            ``twinwatch run --fresh``; a reload restores them in :meth:`continue_from`).
            None: resume unless the source's time starts over when it opens
            (:meth:`~twinwatch.drivers.base.Driver.time_starts_over`).
        run_id: the run id every health message carries; None: a new one (:func:`new_run_id`).
        defer: outputs (registry names) not to open yet (:meth:`handover`'s ``wait``):
            :meth:`open_deferred` opens them once the running daemon has released them.
        wait_for_source: a live source that cannot be opened now is waited for
            (:mod:`twinwatch.daemon.source`); False raises instead (a reload).
        work_dir: the outputs' files are relative to it (default: the working directory).
        slots: the estimation slots the worker processes a window under; None: no limit.
        shared: what the daemons of one process share (a gateway's
            :class:`~twinwatch.sinks.base.SharedResources`); None: each output opens its own.
        thread_prefix: the threads are ``<prefix>-adaptation`` and ``<prefix>-outputs``.

    Attributes:
        acquisition, worker, pipeline, outputs: the parts (see the module docstring).
        restored, resumed: what was resumed from the state database, or None.
        new_run: the stored windows not resumed because the source's time starts over
            (:func:`~twinwatch.daemon.resume.note_new_run`), or None.

    Raises:
        twinwatch.drivers.base.DriverInitializationError, twinwatch.errors.SinkError (and
        subclasses), PluginError, ValueError: on a start-up problem, saying what to fix.
        Every exclusive resource is taken before any file is touched, the device last.
    """

    def __init__(
        self,
        config: TwinwatchConfig,
        *,
        base_dir: Path | None = None,
        driver: Driver | None = None,
        publish: bool = True,
        record: bool = True,
        persist: bool = False,
        watchdog: Watchdog | None = None,
        reuse: Mapping[str, Any] | None = None,
        resume: bool | None = None,
        defer: Collection[str] = (),
        run_id: str | None = None,
        wait_for_source: bool = True,
        work_dir: Path | None = None,
        slots: EstimationSlots | None = None,
        shared: SharedResources | None = None,
        thread_prefix: str = "twinwatch",
    ) -> None:
        self.config = config
        self.work_dir = work_dir or Path.cwd()
        self.slots = slots
        self.shared = shared
        self._thread_prefix = thread_prefix
        self.base_dir = base_dir or Path.cwd()
        self.machine = config.machine.name
        self.model: TwinModel = create_model(config.machine.model, config.machine.options)
        self.nominal = {p.name: config.machine.parameters.get(p.name, p.nominal)
                        for p in self.model.parameters}
        self.watchdog = watchdog
        #: window index -> the source's state when its last sample was read (:meth:`_submit`)
        self._source_at_window: dict[int, tuple[str | None, list[str], list[str]]] = {}
        self._source_lock = threading.Lock()
        self.pipeline: WindowPipeline = make_pipeline(
            config, self.model, self.nominal, run=run_id or new_run_id(),
            counters=self.counters, source=self.window_source_state)
        self.acquisition = Acquisition(config, self.model, own_driver=driver is None,
                                       watchdog=watchdog)
        if slots is not None and config.acquisition.stagger:
            self.acquisition.stagger(self.machine)
            self.pipeline.adapter.estimator.stagger_guard(self.machine)
        self.worker = WindowWorker(
            machine=self.machine, process=lambda window: self.process_window(window),
            backpressure=self.pipeline.backpressure, stopping=self.acquisition.stopping,
            queue_size=config.acquisition.queue, slots=slots, watchdog=watchdog,
            abandon=config.acquisition.abandon_on_stop)
        self.outputs = Outputs(config, self.model, machine=self.machine, pipeline=self.pipeline,
                               roles={"gate": persist, "publisher": publish,
                                      "recorder": record},
                               run=lambda: self.run_id, base_dir=self.base_dir,
                               work_dir=self.work_dir, shared=shared)
        self.restored: TwinState | None = None
        self.resumed: dict[str, Any] | None = None
        self.new_run: dict[str, Any] | None = None
        reuse = dict(reuse or {})
        handed_driver = reuse.pop("driver", None)
        if handed_driver is not None:
            logger.info("reload: the %s driver is kept open (its configuration is unchanged)",
                        config.driver.type)
        try:
            self.outputs.open(reuse, skip=defer)
            if self.store is not None:
                decision = resumes(config, resume)
                if decision:
                    self._restore()
                elif decision is False:
                    note_fresh(self.store, self.machine)
                elif decision is None:
                    self.new_run = note_new_run(self.store, self.machine,
                                                config.driver.type, self.run_id)
            self.acquisition.open(handed_driver or driver, base_dir=self.base_dir,
                                  wait=wait_for_source)
        except BaseException:
            self.outputs.forget_adopted()  # the running daemon's: not ours to close
            self.close()
            raise
        self.outputs.wire(attach=False)  # an adopted output serves the running daemon until then

    # -- the parts' state, as the callers read it -------------------------------------------
    run_id: Forward[str] = Forward("pipeline.run", "This run's id (kept by a reload).")
    adapter: Forward[TwinAdapter] = Forward(
        "pipeline.adapter", "The twin's estimation, discovery and prognostics.")
    estimator: Forward[Estimator] = Forward(
        "pipeline.adapter.estimator", "The twin's parameter estimator.")
    alarms: Forward[AlarmEvaluator] = Forward(
        "pipeline.alarms", "The alarm evaluator (restored from the state database).")
    ring: Forward[RingBuffer] = Forward("acquisition.ring", "The acquisition's ring buffer.")
    driver: Forward[Driver | None] = Forward(
        "acquisition.driver", "The open driver (None before it opens and after :meth:`close`).")
    ended: Forward[str | None] = Forward("acquisition.ended", ":attr:`Acquisition.ended`.")
    failure: Forward[str | None] = Forward(
        "acquisition.failure", "The driver's failure line (the CLI exits 1), or None.")
    queue_waits: Forward[deque[float]] = Forward(
        "worker.queue_waits", ":attr:`WindowWorker.queue_waits` [s].")
    overruns: Forward[int] = Forward("worker.overruns", ":attr:`WindowWorker.overruns`.")
    numeric_failures: Forward[int] = Forward(
        "worker.numeric_failures", "Windows whose processing raised.")
    dropped_at_stop: Forward[int] = Forward(
        "worker.dropped_at_stop", ":attr:`WindowWorker.dropped_at_stop`.")

    def open_deferred(self) -> None:
        """Open the outputs the constructor's ``defer`` left closed (a reload, once the
        previous daemon has released their file or port).

        Raises:
            twinwatch.errors.SinkError: as the constructor.
        """
        self.outputs.open({})
        self.outputs.wire(attach=False)

    def continue_from(self, previous: Daemon) -> None:
        """Take over from ``previous``, the daemon of the configuration before a reload, once
        it has finished its queued windows and released what it did not hand over
        (:meth:`close` ``keep``): the adopted outputs, the run and its window numbering, the
        twin and the alarm levels."""
        self.pipeline.run = previous.run_id
        continue_numbering(self.ring, previous.ring)
        if self.store is not None:
            self._restore()
        self.outputs.wire()

    def handover(self, config: TwinwatchConfig) -> tuple[list[str], list[str]]:
        """What a reload to ``config`` may do with this daemon's open outputs.

        Returns:
            ``(keep, wait)``: the outputs a daemon on ``config`` may adopt open
            (:meth:`~twinwatch.sinks.base.Sink.keeps`), and those it may open only once this
            daemon has released them (:meth:`~twinwatch.sinks.base.SinkConfig.
            exclusive_resources`).
        """
        return self.outputs.handover(config, create_model(config.machine.model,
                                                          config.machine.options))

    # -- the window pipeline's results ------------------------------------------------------
    windows_estimated: Forward[int] = Forward(
        "pipeline.windows_estimated", "Windows the pipeline processed.")
    latest_health: Forward[HealthMessage | None] = Forward(
        "pipeline.latest", "The last health message (typed).")

    @property
    def health_history(self) -> list[HealthMessage]:
        """The last ``[acquisition] history`` health messages (typed), oldest first."""
        return self.pipeline.recent()

    @property
    def window_digests(self) -> list[WindowDigest]:
        """What the run's summary reads of the last ``[acquisition] history`` windows
        (:class:`~twinwatch.daemon.pipeline.WindowDigest`), oldest first."""
        return self.pipeline.digest()

    @property
    def latest(self) -> dict[str, Any] | None:
        """The last health message, as a subscriber reads it (plain JSON types)."""
        last = self.pipeline.latest
        return None if last is None else last.as_dict()

    @property
    def history(self) -> list[dict[str, Any]]:
        """The last ``[acquisition] history`` health messages, as a subscriber reads them."""
        return [h.as_dict() for h in self.pipeline.recent()]

    # -- the outputs ------------------------------------------------------------------------
    sinks: Forward[dict[str, Sink]] = Forward(
        "outputs.sinks", "Registry name -> the open output, in writing order (the gate first).")
    store: Forward[Gate | None] = Forward(
        "outputs.store", "The gate (the state store) while it is open, or None.")

    # -- persistence ------------------------------------------------------------------------
    def _restore(self) -> None:
        """Resume from the state database (:func:`~twinwatch.daemon.resume.restore`)."""
        assert self.store is not None
        self.restored, self.resumed = restore(self.store, self.machine, self.adapter,
                                              self.alarms, run=self.run_id,
                                              diagnoser=self.pipeline.diagnoser)

    # -- lifecycle --------------------------------------------------------------------------
    def add_tick(self, fn: Callable[[], None]) -> None:
        """Call ``fn()`` from the acquisition loop at each of its ticks
        (:data:`~twinwatch.daemon.acquisition.TICK_S`; at least every
        :data:`~twinwatch.daemon.acquisition.READ_TIMEOUT_S`)."""
        self.acquisition.ticks.append(fn)

    def add_callback(self, fn: HealthCallback) -> None:
        """Call ``fn(health)`` from the worker thread after each window."""
        self.pipeline.callbacks.append(fn)

    def stop(self, at_window: bool = False) -> None:
        """Ask :meth:`run` to return after the current sample (thread- and signal-safe).

        Args:
            at_window: return once the window being filled is complete instead (a reload), at
                most its length plus :data:`STOP_AT_WINDOW_S` of wall time.
        """
        self.acquisition.stop(at_window)

    def counters(self) -> dict[str, int]:
        """The health message's counters: the daemon's, the driver's (``driver_*``), each
        open output's (``<prefix>_<name>``) and the gate's ``windows_not_stored``."""
        c: dict[str, int] = {
            "windows_completed": self.ring.windows,
            "windows_estimated": self.windows_estimated,
            "overruns": self.worker.overruns,
            "numeric_failures": self.worker.numeric_failures,
            "bad_samples": self.ring.bad_samples,
            "windows_abandoned": sum(self.ring.discarded.values()),
            **{f"windows_abandoned_{cause}": n for cause, n in self.ring.causes.items()},
        }
        if self.driver is not None:
            c.update({f"driver_{k}": v for k, v in self.driver.stats.as_dict().items()})
        c.update(self.outputs.counters())
        c.update(self.pipeline.counters())
        c["samples_received"] = self.ring.samples
        c["samples_lost"] = sum(self.ring.lost.values())
        c["samples_missing"] = self.ring.missing
        c["windows_with_missing"] = self.ring.windows_filled
        return c

    def problems(self) -> list[str]:
        """What is degraded right now, for systemd's STATUS and the log (empty if nothing)."""
        out = []
        waiting, silent, faults = self.acquisition.source_state()
        if waiting:
            out.append(f"waiting for the source: {waiting}")
        out.extend(source_problem_lines(silent, faults))
        if (p := self.worker.estimation_problem()) is not None:
            out.append(p)
        last = self.pipeline.latest
        if last is not None and last.diagnosis is not None \
                and last.diagnosis.status == "check_function":
            from twinwatch.twin.health import check_function_line

            out.append(check_function_line(last.diagnosis, label="CHECK FUNCTION"))
        return out + self.outputs.problems()

    def _submit(self, window: WindowData, block: bool) -> None:
        """Queue a completed window for the worker, with the source's state as its last
        sample left it."""
        with self._source_lock:
            self._source_at_window[window.index] = self.acquisition.source_state()
        self.worker.submit(window, block=block)

    def window_source_state(self, window: WindowData) -> tuple[str | None, list[str], list[str]]:
        """The source's state (:meth:`Acquisition.source_state`) when ``window``'s last sample
        was read (on a simulated clock the acquisition runs windows ahead of the estimation);
        the state now for a window that was not submitted by :meth:`run`."""
        with self._source_lock:
            state = self._source_at_window.pop(window.index, None)
            for old in [k for k in self._source_at_window if k < window.index]:
                del self._source_at_window[old]  # overruns: never processed
        return state if state is not None else self.acquisition.source_state()

    def windows_failed(self) -> int:
        """Windows of this run that failed: numeric failures plus windows abandoned."""
        return self.numeric_failures + sum(self.ring.discarded.values())

    def mostly_failed(self) -> bool:
        """More windows failed than were estimated (``twinwatch run`` exits 75)."""
        return self.windows_failed() > self.windows_estimated

    def lost(self) -> dict[str, int]:
        """Windows estimated but lost, by output counter prefix (nonzero: ``twinwatch run``
        exits 74)."""
        return self.outputs.lost()

    def summary(self) -> list[str]:
        """The pipeline's and outputs' lines for the run's summary."""
        return [*self.pipeline.summary(), *self.outputs.summary()]

    def run(self, duration: float | None = None) -> int:
        """Acquire and estimate until the source ends, ``duration`` seconds of source time
        have been acquired, or :meth:`stop` is called.

        Returns:
            The number of windows estimated.
        """
        assert self.driver is not None
        self.worker.start(f"{self._thread_prefix}-adaptation")
        # a live source's outputs get a thread (a locked state database does not hold up the
        # estimation); on a simulated clock the worker writes them
        if self.driver.live:
            self.pipeline.start(f"{self._thread_prefix}-outputs")
        try:
            self.acquisition.run(duration, self._submit, self.worker.abandoned)
        finally:
            self._drain()
        return self.windows_estimated

    def _drain(self) -> None:
        """Stop the worker after the windows already queued, then the outputs' thread after
        the windows it was given."""
        timeout = self.config.acquisition.shutdown_timeout
        try:
            self.worker.drain(timeout)
        finally:
            self.pipeline.stop(timeout)
            self.pipeline.checkpoint()

    def process_window(self, window: WindowData) -> HealthMessage:
        """Process one window (:meth:`~twinwatch.daemon.pipeline.WindowPipeline.process`); with
        the adaptive window, the ring buffer's next window takes the length it asks for. Returns
        the typed health message."""
        health = self.pipeline.process(window)
        acq = health.acquisition
        if acq is not None and acq.next_window is not None:
            self.ring.request_window(acq.next_window)
        return health

    def close(self, keep: Container[str] = ()) -> dict[str, Sink]:
        """Drain the worker, then release the driver and the outputs. Idempotent.

        Args:
            keep: the outputs (registry names; :data:`SINKS` for all) and ``"driver"`` to
                leave open (detached) for a reload's daemon.

        Returns:
            name -> output for the kept outputs.
        """
        self.acquisition.stopping.set()
        self._drain()
        driver = self.acquisition.release(keep_driver="driver" in keep)
        if driver is not None:
            close_logged("driver", driver)
        return self.outputs.close(keep)

    def __enter__(self) -> Daemon:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
