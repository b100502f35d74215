"""The daemon: driver -> ring buffer -> adaptation worker -> window pipeline -> sinks.

Threads (see docs/architecture.md):

* the caller's thread (the supervisor's, i.e. the CLI's main thread) runs :meth:`Daemon.run`:
  it reads the driver, fills the ring buffer and hands each full window to the worker. It never
  estimates, so acquisition is never blocked by the optimiser.
* ``twinwatch-adaptation`` (one worker thread) runs the window pipeline
  (:class:`~twinwatch.daemon.pipeline.WindowPipeline`): estimation, health message, alarms,
  then the sinks in order: the gate (the state database), then the others (Zenoh, Rerun,
  plug-ins). Stored before published: a health message a subscriber has seen is always in the
  database, also after SIGKILL.
* zenoh's threads answer the history query (``twinwatch/<machine>/history``) from the state
  database (one SQLite connection per thread, WAL: readers never block the worker).

The daemon opens the configured outputs through the sink registry
(:data:`twinwatch.sinks.SINKS`, :class:`~twinwatch.sinks.base.Sink`) and knows none by name:
their roles decide the order of writing, their counters, losses and problems are merged.

Between them a bounded queue. For a live source (a bus, a real-time replay) a full queue means
the estimation does not keep up: the window is dropped and counted as an *overrun* (published in
every health message). For a source on a simulated clock (the simulated plant or a file replayed
as fast as possible) the acquisition waits instead, so no window is ever lost.
"""

from __future__ import annotations

import logging
import queue
import secrets
import threading
import time
from collections import deque
from collections.abc import Callable, Collection, Container, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from twinwatch.daemon.alarms import AlarmEvaluator, FaultAlarms
from twinwatch.daemon.outputs import Outputs, close_logged
from twinwatch.daemon.pipeline import HealthCallback, WindowPipeline
from twinwatch.daemon.resume import continue_numbering, note_new_run, restore, resumes
from twinwatch.daemon.ringbuffer import RingBuffer
from twinwatch.daemon.source import open_source
from twinwatch.drivers.base import Driver, DriverError, EndOfStream
from twinwatch.sinks import SINKS
from twinwatch.sinks.base import Gate, Outbox, SharedResources, Sink
from twinwatch.twin.adaptation import TwinAdapter
from twinwatch.twin.diagnosis import Diagnoser
from twinwatch.twin.health import HealthMessage
from twinwatch.twin.model import TwinModel, WindowData
from twinwatch.twin.models import create_model

if TYPE_CHECKING:  # the configuration is given by the caller; the daemon never reads files
    from twinwatch.config.schema import TwinwatchConfig
    from twinwatch.daemon.slots import EstimationSlots
    from twinwatch.daemon.systemd import Watchdog

logger = logging.getLogger(__name__)

_STOP = object()

__all__ = ["SINKS", "Daemon", "new_run_id"]

def new_run_id() -> str:
    """A new run id: the start's UTC time and 6 random hex digits, e.g.
    ``20261122T101530Z-3f9a2c`` (sorts by start; unique across machines and restarts within
    the same second; letters, digits and ``-`` only, so it goes in a selector unquoted)."""
    return time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()) + "-" + secrets.token_hex(3)


STOP_AT_WINDOW_S = 5.0
"""Longest wait [s, wall] beyond one window's length for the window being filled when a reload
stops a daemon at a window boundary (:meth:`Daemon.stop` ``at_window``); then it stops and the
partial window is dropped (a source that went silent)."""


QUEUE_WAITS = 10000
"""Windows whose queue wait (submission to the start of processing) the daemon keeps
(:attr:`Daemon.queue_waits`)."""


RECENT_WINDOWS = 20
"""Windows whose outcome (estimated, failed, abandoned, overrun) the daemon keeps to tell
systemd's STATUS whether estimation works *now* (:meth:`Daemon.estimation_problem`)."""


def make_diagnoser(config: TwinwatchConfig) -> Diagnoser | None:
    """The machine's diagnosis (``[diagnosis]``): its fault library (shipped for the model,
    extended by the configuration) in a :class:`~twinwatch.twin.diagnosis.Diagnoser`; None when
    off or when the model has no fault mode."""
    d = config.diagnosis
    if not d.enabled:
        return None
    library = d.resolve(config.machine.model)
    if not library.faults:
        return None
    source = "configured" if (d.replace or d.library or d.faults) else "shipped"
    return Diagnoser(library, unknown_prior=d.unknown_prior, listed=d.listed, source=source)


class Daemon:
    """One machine's monitor.

    Args:
        config: validated configuration.
        base_dir: directory relative paths in the config are resolved against (the config
            file's directory).
        driver: an already-open driver to use instead of the configured one (tests).
        publish: open the outputs whose role is ``publisher`` (Zenoh, plug-ins; each only if
            its table is enabled).
        record: open the outputs whose role is ``recorder`` (the Rerun recording).
        persist: open the gate (the state database, if ``[state]`` is enabled): restore the
            last accepted twin and the alarm levels from it, save every window, serve the
            history query. Off by default for library use and tests; the CLI turns it on.
        watchdog: the systemd watchdog gate (ticked by the acquisition loop, busy/idle around
            each window).
        reuse: what a reload hands over from the running daemon (:meth:`handover`): open
            outputs (registry name -> sink) whose table and context are unchanged
            (:meth:`~twinwatch.sinks.base.Sink.keeps`), adopted instead of opening new ones,
            and under ``"driver"`` its open driver (the ``[driver]`` table unchanged: the
            source goes on where it was, nothing is opened again). They stay the running
            daemon's until :meth:`continue_from` (a failed start leaves them open and bound
            to it); one that does not fit is left alone.
        resume: restore the saved twin and alarm levels from the state database (False:
            start from the nameplate values, ``twinwatch run --fresh``; a reload restores
            them in :meth:`continue_from`, once the previous daemon has finished). None (the
            default): resume unless the source's time starts over when it opens (a simulated
            plant from t = 0, a replayed recording:
            :meth:`~twinwatch.drivers.base.Driver.time_starts_over`): such a run is a new
            run, not the continuation of the stored one (:attr:`new_run`).
        run_id: the run id every health message carries (a reload passes the running
            daemon's: the same run goes on); None: a new one (:func:`new_run_id`).
        defer: outputs (registry names) not to open yet: the running daemon holds their file
            or port (a reload that changed their table, :meth:`handover`'s ``wait``);
            :meth:`open_deferred` opens them once it has released them.
        wait_for_source: a live source that cannot be opened now is waited for
            (:mod:`twinwatch.daemon.source`: the daemon starts and says what it waits for);
            False raises instead (a reload: the running configuration goes on).
        work_dir: the directory the files the outputs create are relative to (the state
            database, the recording); default the working directory. A gateway gives each
            machine its own (``<working directory>/<machine>``).
        slots: the estimation slots the worker takes a window's processing under (a gateway:
            one pool sized to the cores, shared by every machine; the time waited for one is
            part of the window's queue wait); None: no limit (one daemon per process).
        shared: what the daemons of one process share (a gateway's
            :class:`~twinwatch.sinks.base.SharedResources`: the Zenoh session), given to the
            outputs in their context; None: each output opens its own.
        thread_prefix: the worker thread is ``<prefix>-adaptation`` (a gateway names each
            machine's).

    Attributes:
        sinks: registry name -> the open output, in the order each window is written to them
            (the gate first: stored before published).
        run_id: this run's id (in every health message and stored row; kept by a reload).
        new_run: set when the state database holds this machine's earlier windows that were
            not resumed because the source's time starts over (``resume`` not given):
            ``reason``, ``path`` (the database), ``run`` (the id of the last stored run);
            None otherwise.

    Raises:
        twinwatch.drivers.base.DriverInitializationError, twinwatch.errors.SinkError (its
        subclasses PublisherError, RecorderError, StoreError, a plug-in's), PluginError,
        ValueError: on a start-up problem, with a message that says what to fix. Every
        exclusive resource is taken before any file is touched (the outputs open in their
        ``open_order``: the Zenoh port, the state database's lock, the recording's lock),
        and the device last.
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
        #: seconds each window waited between its submission and the start of its processing
        #: (the queue, and in a gateway the estimation slot), the last QUEUE_WAITS windows
        self.queue_waits: deque[float] = deque(maxlen=QUEUE_WAITS)
        self.run_id = run_id or new_run_id()
        self.base_dir = base_dir or Path.cwd()
        self.machine = config.machine.name
        self.model: TwinModel = create_model(config.machine.model, config.machine.options)
        self.nominal = {p.name: config.machine.parameters.get(p.name, p.nominal)
                        for p in self.model.parameters}
        acq = config.acquisition
        self.adapter = TwinAdapter(self.model, config.estimation, config.discovery,
                                   self.nominal, prognostics=config.prognostics,
                                   thresholds=config.alarms.rul_targets(self.nominal),
                                   adaptive=acq.adaptive)
        self.estimator = self.adapter.estimator
        longest = acq.adaptive.max_window if acq.adaptive.enabled else acq.window
        self.ring = RingBuffer(self.model.required_channels(), window=acq.window,
                               sample_period=acq.sample_period,
                               jitter_tolerance=acq.jitter_tolerance,
                               capacity=4 * max(longest, acq.window))
        self.watchdog = watchdog
        self.alarms = AlarmEvaluator(config.alarms, self.machine)
        self.pipeline = WindowPipeline(
            adapter=self.adapter, alarms=self.alarms, machine=self.machine,
            model_name=config.machine.model, run=self.run_id, nominal=self.nominal,
            counters=self.counters, history=acq.history, source=self.source_state,
            diagnoser=make_diagnoser(config))
        dc = config.diagnosis
        if self.pipeline.diagnoser is not None and dc.alarm is not None:
            self.pipeline.fault_alarms = FaultAlarms(dc.alarm, dc.clear, dc.raise_after_windows,
                                                     dc.clear_after_windows, self.machine)
        self.restored: dict[str, Any] | None = None
        self.resumed: dict[str, Any] | None = None
        self.new_run: dict[str, Any] | None = None
        self.failure: str | None = None
        self.driver: Driver | None = None
        self._own_driver = driver is None
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=acq.queue)
        self._stop = threading.Event()
        self._stop_at_window: float | None = None  # monotonic deadline, see stop(at_window)
        self.ended: str | None = None  # why run() returned by itself: source, duration, failure
        self._worker: threading.Thread | None = None
        self.overruns = 0
        self.numeric_failures = 0
        #: windows queued at a stop that the worker did not reach within ``shutdown_timeout``
        self.dropped_at_stop = 0
        self._closing = False
        #: the last RECENT_WINDOWS outcomes: "estimated", "failed" (numeric failure),
        #: "abandoned" (gap, bad value, ...), "overrun"
        self.recent_outcomes: deque[str] = deque(maxlen=RECENT_WINDOWS)
        self._abandoned_seen = 0
        self._ticks: list[Callable[[], None]] = []
        self.abandon = config.acquisition.abandon_on_stop
        self.outputs = Outputs(config, self.model, machine=self.machine, pipeline=self.pipeline,
                               roles={"gate": persist, "publisher": publish,
                                      "recorder": record},
                               run=lambda: self.run_id, base_dir=self.base_dir,
                               work_dir=self.work_dir, shared=shared)
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
                elif decision is None:
                    self.new_run = note_new_run(self.store, self.machine,
                                                config.driver.type, self.run_id)
            self.driver = handed_driver or driver or open_source(
                config.driver, base_dir=self.base_dir, wait=wait_for_source,
                backoff_max=config.acquisition.reopen_max)
        except BaseException:
            self.outputs.forget_adopted()  # the running daemon's: not ours to close
            self.close()
            raise
        self.outputs.wire(attach=False)  # an adopted output serves the running daemon until then

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
        (:meth:`close` ``keep``): the adopted outputs are bound to this daemon, the window
        numbering goes on (and the run: :attr:`run_id`), the twin and the alarm levels resume
        from the state database."""
        self.run_id = self.pipeline.run = previous.run_id
        continue_numbering(self.ring, previous.ring)
        if self.store is not None:
            self._restore()
        self.outputs.wire()

    def handover(self, config: TwinwatchConfig) -> tuple[list[str], list[str]]:
        """What a reload to ``config`` may do with this daemon's open outputs.

        Returns:
            ``(keep, wait)``: the outputs a daemon on ``config`` may adopt open (their table
            and context unchanged: :meth:`~twinwatch.sinks.base.Sink.keeps`), and those it may
            open only once this daemon has released them (another table, but the same file or
            port: :meth:`~twinwatch.sinks.base.SinkConfig.exclusive_resources`).
        """
        return self.outputs.handover(config, create_model(config.machine.model,
                                                          config.machine.options))

    # -- the window pipeline's results ------------------------------------------------------
    @property
    def windows_estimated(self) -> int:
        """Windows the pipeline processed."""
        return self.pipeline.windows_estimated

    @property
    def latest_health(self) -> HealthMessage | None:
        """The last health message (typed)."""
        return self.pipeline.latest

    @property
    def health_history(self) -> list[HealthMessage]:
        """The last ``[acquisition] history`` health messages (typed), oldest first."""
        return self.pipeline.recent()

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
    @property
    def sinks(self) -> dict[str, Sink]:
        """Registry name -> the open output, in the order each window is written to them (the
        gate first: stored before published)."""
        return self.outputs.sinks

    @property
    def store(self) -> Gate | None:
        """The gate (the state store) while it is open, or None."""
        return self.outputs.store

    # -- persistence ------------------------------------------------------------------------
    def _restore(self) -> None:
        """Resume from the state database (:func:`~twinwatch.daemon.resume.restore`)."""
        assert self.store is not None
        self.restored, self.resumed = restore(self.store, self.machine, self.adapter,
                                              self.alarms)

    def stored_history(self, t_from: float | None = None, t_to: float | None = None,
                       limit: int | None = 1000, by: Literal["plant", "wall"] = "plant",
                       run: str | None = None, after: float | None = None
                       ) -> list[dict[str, Any]]:
        """Stored health messages of this machine in a time range, of one run with ``run``
        (the gate's :meth:`~twinwatch.sinks.base.Gate.history`); empty without a state
        database. The outputs ask it through their context (the Zenoh history query)."""
        return self.outputs.stored_history(t_from, t_to, limit, by=by, run=run, after=after)

    def outbox(self, output: str) -> Outbox | None:
        """The gate's outbox of ``output`` for this machine (store-and-forward outputs ask it
        through their context), None without a gate."""
        return self.outputs.outbox(output)

    # -- lifecycle --------------------------------------------------------------------------
    def add_tick(self, fn: Callable[[], None]) -> None:
        """Call ``fn()`` from the acquisition loop every iteration (at least every 0.2 s)."""
        self._ticks.append(fn)

    def add_callback(self, fn: HealthCallback) -> None:
        """Call ``fn(health)`` from the worker thread after each window."""
        self.pipeline.callbacks.append(fn)

    def stop(self, at_window: bool = False) -> None:
        """Ask :meth:`run` to return after the current sample (thread- and signal-safe).

        Args:
            at_window: return once the window being filled is complete instead (a reload: the
                source, handed to the next daemon, goes on there exactly where this one
                stopped; a replayed file neither loses nor repeats a row). A source that does
                not complete the window within its length plus :data:`STOP_AT_WINDOW_S` of
                wall time stops then (the partial window is dropped).
        """
        if at_window:
            acq = self.config.acquisition
            self._stop_at_window = (time.monotonic() + acq.window * acq.sample_period
                                    + STOP_AT_WINDOW_S)
        else:
            self._stop.set()

    def counters(self) -> dict[str, int]:
        """The health message's counters: the daemon's, the driver's (``driver_*``), each
        open output's (``<prefix>_<name>``) and the gate's ``windows_not_stored``."""
        c: dict[str, int] = {
            "windows_completed": self.ring.windows,
            "windows_estimated": self.windows_estimated,
            "overruns": self.overruns,
            "numeric_failures": self.numeric_failures,
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
        return c

    def problems(self) -> list[str]:
        """What is degraded right now, for systemd's STATUS and the log (empty if nothing):
        what the source waits for or lacks (:meth:`source_state`), estimation that fails
        (:meth:`estimation_problem`), each output's :attr:`~twinwatch.sinks.base.Sink.problem`.
        """
        out = []
        waiting, silent = self.source_state()
        if waiting:
            out.append(f"waiting for the source: {waiting}")
        if silent:
            out.append("silent: " + ", ".join(silent))
        if (p := self.estimation_problem()) is not None:
            out.append(p)
        return out + self.outputs.problems()

    def source_state(self) -> tuple[str | None, list[str]]:
        """What the driver waits for (a device absent, a bus being reopened; None when it
        delivers) and its silent messages (:attr:`~twinwatch.drivers.base.Driver.waiting`,
        :attr:`~twinwatch.drivers.base.Driver.silent`)."""
        driver = self.driver
        if driver is None:
            return None, []
        return driver.waiting, list(driver.silent)

    def _source_waiting(self) -> bool:
        driver = self.driver
        return driver is not None and driver.waiting is not None

    def estimation_problem(self) -> str | None:
        """A line when at least half of the last windows (at least 3 of at most
        :data:`RECENT_WINDOWS`) were not estimated (numeric failures, abandoned: gaps, bad
        values, jitter, time jumps; overruns), else None."""
        recent = list(self.recent_outcomes)
        bad = [o for o in recent if o != "estimated"]
        if len(recent) < 3 or 2 * len(bad) < len(recent):
            return None
        kinds = ", ".join(f"{n} {k}" for k, n in sorted(
            {k: bad.count(k) for k in set(bad)}.items()))
        return f"{len(bad)} of the last {len(recent)} windows not estimated ({kinds})"

    def windows_failed(self) -> int:
        """Windows of this run that failed: numeric failures plus windows abandoned (gaps, bad
        values, jitter beyond tolerance, time jumps, missing channels)."""
        return self.numeric_failures + sum(self.ring.discarded.values())

    def mostly_failed(self) -> bool:
        """More windows failed than were estimated (``twinwatch run`` exits 75)."""
        return self.windows_failed() > self.windows_estimated

    def lost(self) -> dict[str, int]:
        """Windows estimated but lost, by output (its counter prefix: ``store`` never stored,
        ``recording`` not recorded, ...). Nonzero values make ``twinwatch run`` exit with
        status 74."""
        return self.outputs.lost()

    def status(self) -> list[str]:
        """What the open outputs serve, in the order they opened (systemd's STATUS)."""
        return self.outputs.status()

    def summary(self) -> list[str]:
        """The outputs' lines for the run's summary (where the windows went, what was lost),
        in writing order."""
        return [*self.pipeline.summary(), *self.outputs.summary()]

    def run(self, duration: float | None = None) -> int:
        """Acquire and estimate until the source ends, ``duration`` seconds of source time
        have been acquired, or :meth:`stop` is called.

        Returns:
            The number of windows estimated.
        """
        assert self.driver is not None
        live = self.driver.live
        self._worker = threading.Thread(target=self._work,
                                        name=f"{self._thread_prefix}-adaptation",
                                        daemon=True)
        self._worker.start()
        if live:  # the outputs write from their own thread: a state database locked by
            # another process (each write waits the busy timeout) does not hold up the
            # estimation, so no window of a live source is dropped for it. A source on a
            # simulated clock waits for the worker anyway (no window is lost): its outputs
            # are written by the worker, each health message counting what they did before.
            self.outputs.start(self._thread_prefix)
        if self.watchdog is not None:
            self.watchdog.require_windows = self.config.acquisition.watchdog == "windows"
            self.watchdog.source_waiting = self._source_waiting
            self.watchdog.reset()
        t_first: float | None = None
        stall_timeout = self.config.acquisition.stall_timeout
        last_sample = time.monotonic()
        stalled = False
        try:
            while not self._stop.is_set():
                if self._stop_at_window is not None and (
                        self.ring.pending == 0 or time.monotonic() > self._stop_at_window):
                    break
                if self.watchdog is not None:
                    self.watchdog.tick()
                for fn in self._ticks:
                    fn()
                try:
                    sample = self.driver.read(timeout=0.2)
                except EndOfStream as exc:
                    logger.info("source finished: %s", exc)
                    self.ended = "end of the source"
                    break
                except DriverError as exc:
                    # the driver gave up: one clear line (the driver said what failed), then
                    # the queued windows are finished and the caller decides (the CLI exits 1)
                    self.failure = f"the {self.config.driver.type} driver failed: {exc}"
                    logger.error("%s", self.failure)
                    self.ended = "driver failure"
                    break
                now = time.monotonic()
                if sample is None:
                    if not stalled and now - last_sample > stall_timeout:
                        stalled = True
                        logger.error(
                            "no sample from the %s driver for %.1f s: check the device, "
                            "cable and bus configuration; waiting for data",
                            self.config.driver.type, now - last_sample)
                    continue
                if stalled:
                    logger.warning("driver delivers samples again after a stall of %.1f s",
                                   now - last_sample)
                    stalled = False
                last_sample = now
                if t_first is None:
                    t_first = sample.t
                if duration is not None and sample.t - t_first >= duration:
                    self.ended = "duration reached"
                    break
                window = self.ring.append(sample.t, sample.values)
                abandoned = sum(self.ring.causes.values())
                if abandoned > self._abandoned_seen:
                    self.recent_outcomes.extend(["abandoned"] * min(
                        abandoned - self._abandoned_seen, RECENT_WINDOWS))
                    self._abandoned_seen = abandoned
                if window is not None:
                    self._submit(window, block=not live)
        finally:
            self._drain()
        return self.windows_estimated

    def _submit(self, window: WindowData, *, block: bool) -> None:
        item = (window, time.monotonic())
        if block:
            while not self._stop.is_set():
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
            waiting = self.pipeline.backpressure()
            if waiting is not None:  # the real cause: an output holds up the worker
                logger.warning("estimation overrun: window %d dropped (%d so far); the "
                               "estimation waits for the outputs: %s", window.index,
                               self.overruns, waiting)
                return
            logger.warning("estimation overrun: window %d dropped (%d so far); the "
                           "estimation does not keep up with acquisition: lower "
                           "[estimation.pso].max_generations or the time budget",
                           window.index, self.overruns)

    def _drain(self) -> None:
        """Stop the worker after the windows already queued, then the outputs' thread after
        the windows it was given."""
        try:
            self._drain_worker()
        finally:
            self.outputs.stop(self.config.acquisition.shutdown_timeout)

    def _drain_worker(self) -> None:
        """Stop the worker after the windows already queued."""
        if self._worker is None:
            return
        timeout = self.config.acquisition.shutdown_timeout
        deadline = time.monotonic() + timeout
        while self._worker.is_alive():
            try:
                self._queue.put(_STOP, timeout=0.2)
                break
            except queue.Full:  # a worker that does not take windows (stuck, or waiting
                if time.monotonic() > deadline:  # for an estimation slot) bounds the stop
                    break
        self._worker.join(timeout=max(0.0, deadline - time.monotonic()))
        if self._worker.is_alive():
            # the outputs close next: the worker takes no further window (one it is in the
            # middle of cannot be stopped; its outputs count it as lost if they are closed)
            self._closing = True
            logger.warning("%s: adaptation worker did not finish within %.0f s: the windows "
                           "still queued are dropped", self.machine,
                           self.config.acquisition.shutdown_timeout)
        self._worker = None

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
            if self._stop.is_set() and self.abandon:
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
                self.process_window(item)
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
        """A window's failure is logged once, then counted: the same failure again (its type
        and message) only adds to the count; a different one, or the first window estimated
        again, is logged with how many times the previous one repeated (a machine whose
        every window raises logged one ERROR a window, about 1,800 an hour)."""
        key = None if exc is None else f"{type(exc).__name__}: {exc}"
        last, repeats = getattr(self, "_failure", (None, 0))
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

    def process_window(self, window: WindowData) -> HealthMessage:
        """Adapt the twin to one window and write it to the sinks (the pipeline's
        :meth:`~twinwatch.daemon.pipeline.WindowPipeline.process`); with the adaptive window,
        the ring buffer's next window takes the length it asks for. Returns the typed health
        message."""
        health = self.pipeline.process(window)
        acq = health.acquisition
        if acq is not None and acq.next_window is not None:
            self.ring.request_window(acq.next_window)
        return health

    def close(self, keep: Container[str] = ()) -> dict[str, Sink]:
        """Stop everything and release the driver and the outputs (after the worker has
        drained): the driver first, then the outputs in writing order reversed (the gate, the
        state database, last). Idempotent.

        Args:
            keep: the outputs (registry names; :data:`SINKS` for all) and ``"driver"`` to
                leave open for a new daemon (a reload): each output is detached from this
                daemon.

        Returns:
            name -> output for the kept outputs.
        """
        self._stop.set()
        self._drain()
        if self.driver is not None and self._own_driver and "driver" not in keep:
            close_logged("driver", self.driver)
        self.driver = None
        return self.outputs.close(keep)

    def __enter__(self) -> Daemon:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
