"""The daemon: driver -> ring buffer -> adaptation worker -> window pipeline -> sinks.

Threads (see docs/architecture.md):

* the caller's thread (the supervisor's, i.e. the CLI's main thread) runs :meth:`Daemon.run`:
  it reads the driver, fills the ring buffer and hands each full window to the worker. It never
  estimates, so acquisition is never blocked by the optimiser.
* ``twinwatch-adaptation`` (one worker thread) runs the window pipeline
  (:class:`~twinwatch.daemon.pipeline.WindowPipeline`): estimation, health message, alarms,
  then the sinks in order: state database, Zenoh, Rerun. Stored before published: a health
  message a subscriber has seen is always in the database, also after SIGKILL.
* zenoh's threads answer the history query (``twinwatch/<machine>/history``) from the state
  database (one SQLite connection per thread, WAL: readers never block the worker).

Between them a bounded queue. For a live source (a bus, a real-time replay) a full queue means
the estimation does not keep up: the window is dropped and counted as an *overrun* (published in
every health message). For a source on a simulated clock (the simulated plant or a file replayed
as fast as possible) the acquisition waits instead, so no window is ever lost.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Collection, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from twinwatch.daemon.alarms import AlarmEvaluator
from twinwatch.daemon.pipeline import HealthCallback, WindowPipeline
from twinwatch.daemon.ringbuffer import RingBuffer
from twinwatch.drivers import create_driver
from twinwatch.drivers.base import Driver, DriverError, EndOfStream
from twinwatch.twin.adaptation import TwinAdapter
from twinwatch.twin.model import TwinModel, WindowData
from twinwatch.twin.models import create_model

if TYPE_CHECKING:  # the configuration is given by the caller; the daemon never reads files
    from twinwatch.config.schema import TwinwatchConfig
    from twinwatch.daemon.systemd import Watchdog
    from twinwatch.sinks.rerun import RerunRecorder
    from twinwatch.sinks.store import StateStore
    from twinwatch.sinks.zenoh import HealthPublisher

logger = logging.getLogger(__name__)

_STOP = object()

HISTORY_LIMIT = 1000
"""Most windows one history query returns (page on with ``t_from``)."""

SINKS = ("store", "publisher", "recorder")
"""The daemon's sinks, in the order each window is written to them (stored before published);
a reload may hand them from the old daemon to the new one (:meth:`Daemon.close` ``keep``)."""

HANDOVER = ("driver", *SINKS)
"""What a reload may hand from the old daemon to the new one: the open driver (its
configuration unchanged: the source goes on where it was, nothing is opened again) and the
sinks."""

STOP_AT_WINDOW_S = 5.0
"""Longest wait [s, wall] beyond one window's length for the window being filled when a reload
stops a daemon at a window boundary (:meth:`Daemon.stop` ``at_window``); then it stops and the
partial window is dropped (a source that went silent)."""


class Daemon:
    """One machine's monitor.

    Args:
        config: validated configuration.
        base_dir: directory relative paths in the config are resolved against (the config
            file's directory).
        driver: an already-open driver to use instead of the configured one (tests).
        publish: open the Zenoh publisher (``config.zenoh.enabled`` must also be true).
        record: open the Rerun recorder (``config.recording.enabled`` must also be true).
        persist: open the state database (``config.state.enabled`` must also be true):
            restore the last accepted twin and the alarm levels from it, save every window,
            serve the history query. Off by default for library use and tests; the CLI turns
            it on.
        watchdog: the systemd watchdog gate (ticked by the acquisition loop, busy/idle around
            each window).
        reuse: the open driver and sinks (names in :data:`HANDOVER`) a reload hands over from
            the running daemon (see :meth:`close`), used instead of opening new ones; this
            daemon owns them once it took over (:meth:`continue_from`), and a failed start
            leaves them open. The caller (the supervisor) hands over only those whose
            configuration is unchanged.
        resume: restore the saved twin and alarm levels from the state database (False:
            start from the nameplate values, ``twinwatch run --fresh``; a reload restores
            them in :meth:`continue_from`, once the previous daemon has finished).
        defer: sinks (names in :data:`SINKS`) not to open yet: the running daemon holds their
            file or port (a reload that changed their settings); :meth:`open_deferred` opens
            them once it has released them.

    Raises:
        twinwatch.drivers.base.DriverInitializationError, PublisherError, RecorderError,
        StoreError, ValueError: on a start-up problem, with a message that says what to fix.
        Every exclusive resource is taken before any file is touched (the Zenoh port, the
        state database's lock, the recording's lock), and the device last.
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
        resume: bool = True,
        defer: Collection[str] = (),
    ) -> None:
        self.config = config
        self.base_dir = base_dir or Path.cwd()
        self.machine = config.machine.name
        self.model: TwinModel = create_model(config.machine.model, config.machine.options)
        self.nominal = {p.name: config.machine.parameters.get(p.name, p.nominal)
                        for p in self.model.parameters}
        self.adapter = TwinAdapter(self.model, config.estimation, config.discovery,
                                   self.nominal)
        self.estimator = self.adapter.estimator
        acq = config.acquisition
        self.ring = RingBuffer(self.model.required_channels(), window=acq.window,
                               sample_period=acq.sample_period, max_gap=acq.max_gap)
        self.publisher: HealthPublisher | None = None
        self.recorder: RerunRecorder | None = None
        self.store: StateStore | None = None
        self.watchdog = watchdog
        self.alarms = AlarmEvaluator(config.alarms, self.machine)
        self.pipeline = WindowPipeline(
            adapter=self.adapter, alarms=self.alarms, machine=self.machine,
            model_name=config.machine.model, nominal=self.nominal, counters=self.counters,
            history=acq.history)
        self.restored: dict[str, Any] | None = None
        self.resumed: dict[str, Any] | None = None
        self.failure: str | None = None
        self._closed_sinks: dict[str, Any] = {}
        self.driver: Driver | None = None
        self._own_driver = driver is None
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=acq.queue)
        self._stop = threading.Event()
        self._stop_at_window: float | None = None  # monotonic deadline, see stop(at_window)
        self.ended: str | None = None  # why run() returned by itself: source, duration, failure
        self._open_flags = (publish, persist, record)
        self._worker: threading.Thread | None = None
        self.overruns = 0
        self.numeric_failures = 0
        self._ticks: list[Callable[[], None]] = []
        self.abandon = config.acquisition.abandon_on_stop
        reuse = dict(reuse or {})
        try:
            for name, obj in reuse.items():
                if name not in HANDOVER:
                    raise ValueError(f"cannot hand over {name!r}; only {HANDOVER}")
                setattr(self, name, obj)
                logger.info("reload: the %s is kept open (its configuration is unchanged)", name)
            self._open_sinks(skip=defer)
            if self.store is not None and resume:
                self._restore()
            self.driver = self.driver or driver or create_driver(config.driver,
                                                                 base_dir=self.base_dir)
        except BaseException:
            for name in reuse:  # the running daemon's: not ours to close
                setattr(self, name, None)
            self.close()
            raise
        self._wire()

    def _open_sinks(self, skip: Collection[str] = ()) -> None:
        """Open the configured sinks not open yet (handed over, or in ``skip``)."""
        config = self.config
        publish, persist, record = self._open_flags
        # Every exclusive resource before any file is touched: the Zenoh port, then the
        # state database's lock, then the recording's lock (and only then its truncation),
        # so a second twinwatch in the same directory fails without harming the first.
        if publish and config.zenoh.enabled and self.publisher is None \
                and "publisher" not in skip:
            from twinwatch.sinks.zenoh import HealthPublisher

            self.publisher = HealthPublisher(config.zenoh, self.machine, retry_connect=True)
        if persist and config.state.enabled and self.store is None and "store" not in skip:
            from twinwatch.sinks.store import StateStore

            st = config.state
            self.store = StateStore(Path(st.path).expanduser(), synchronous=st.synchronous,
                                    keep_days=st.keep_days, keep_rows=st.keep_rows,
                                    recover_corrupt=st.recover_corrupt,
                                    recent=config.acquisition.history)
        if record and config.recording.enabled and self.recorder is None \
                and "recorder" not in skip:
            from twinwatch.sinks.rerun import RerunRecorder

            rec = config.recording.model_copy()
            path = Path(rec.path)
            if not path.is_absolute():
                rec.path = str(Path.cwd() / path)
            self.recorder = RerunRecorder(
                rec, self.machine, outputs=self.model.output_names,
                parameters={p.name: p.unit for p in self.model.parameters})

    def _wire(self) -> None:
        """Give the open sinks to the pipeline (the store first: stored before published) and
        serve the history query from the state database."""
        self.pipeline.sinks = [s for s in (self.store, self.publisher, self.recorder)
                               if s is not None]
        self.pipeline.gate = self.store  # a window it cannot store is not published
        if self.publisher is not None and self.store is not None:
            self.publisher.add_query_handler("history", self._on_history_query)

    def open_deferred(self) -> None:
        """Open the sinks the constructor's ``defer`` left closed (a reload, once the previous
        daemon has released their file or port).

        Raises:
            PublisherError, RecorderError, StoreError: as the constructor.
        """
        self._open_sinks()
        self._wire()

    def continue_from(self, previous: Daemon) -> None:
        """Take over from ``previous``, the daemon of the configuration before a reload, once
        it has finished its queued windows and released what was not handed over
        (:meth:`close` ``keep``): the window numbering goes on, the twin and the alarm levels
        resume from the state database, the history query is served by this daemon."""
        self.ring.first_index = previous.ring.first_index + previous.ring.windows
        if self.store is not None:
            self._restore()
        self._wire()

    # -- the window pipeline's results ------------------------------------------------------
    @property
    def windows_estimated(self) -> int:
        """Windows the pipeline processed."""
        return self.pipeline.windows_estimated

    @property
    def latest(self) -> dict[str, Any] | None:
        """The last health message."""
        return self.pipeline.latest

    @property
    def history(self) -> deque[dict[str, Any]]:
        """The last ``[acquisition] history`` health messages."""
        return self.pipeline.history

    # -- persistence ------------------------------------------------------------------------
    def _restore(self) -> None:
        """Resume from the state database: the last accepted twin (trusted parameters and
        meta-model terms) and the alarm levels of the last window. Both are read before
        either is used: a corrupt database (moved aside by ``recover_corrupt``) resumes
        nothing."""
        assert self.store is not None
        state = self.store.load_twin_state(self.machine)
        last = self.store.latest_health(self.machine)
        if self.store.recovered:
            state = last = None
        if state is not None:
            try:
                self.adapter.restore(state)
            except (KeyError, TypeError, ValueError) as exc:
                logger.error("the saved twin of %s in %s cannot be used with this "
                             "configuration (%s): starting from the nominal values", self.machine,
                             self.store.path, exc)
            else:
                self.restored = state
                logger.info("resumed the twin of %s from %s: %s; %d meta-model term(s)",
                            self.machine, self.store.path,
                            ", ".join(f"{k}={v:.6g}" for k, v in state["trusted"].items()),
                            len(state.get("terms", [])))
        if last is not None and last.get("alarms"):
            self.alarms.restore(last["alarms"])
        if self.restored is not None or (last is not None and last.get("alarms")):
            self.resumed = {
                "path": str(self.store.path),
                "window": None if last is None else last.get("window"),
                "t_end": None if last is None else last.get("t_end"),
                "trusted": dict((self.restored or {}).get("trusted") or {}),
                "terms": len((self.restored or {}).get("terms") or []),
                "alarms": {k: a.get("level") for k, a in
                           ((last or {}).get("alarms") or {}).items()
                           if a.get("level") not in (None, "normal")},
            }

    def stored_history(self, t_from: float | None = None, t_to: float | None = None,
                limit: int | None = HISTORY_LIMIT, by: str = "plant") -> list[dict[str, Any]]:
        """Stored health messages of this machine in a time range (see
        :meth:`StateStore.history`); empty without a state database."""
        if self.store is None:
            return []
        return self.store.history(t_from, t_to, limit, by=by,  # type: ignore[arg-type]
                                  machine=self.machine)

    def _on_history_query(self, query: Any) -> dict[str, Any]:
        """``get("P/history?t_from=..;t_to=..;by=plant|wall;limit=..")`` (zenoh thread).

        Raises:
            ValueError: a bad parameter (replied as an error naming it).
        """
        t_from, t_to, limit, by = history_parameters(query.parameters)
        windows = self.stored_history(t_from, t_to, limit, by=by)
        more = len(windows) == limit
        return {"machine": self.machine, "by": by, "t_from": t_from, "t_to": t_to,
                "count": len(windows), "more": more, "windows": windows}

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
        c: dict[str, int] = {
            "windows_completed": self.ring.windows,
            "windows_estimated": self.windows_estimated,
            "overruns": self.overruns,
            "numeric_failures": self.numeric_failures,
            "bad_samples": self.ring.bad_samples,
            "windows_abandoned": sum(self.ring.discarded.values()),
        }
        if self.driver is not None:
            c.update({f"driver_{k}": v for k, v in self.driver.stats.as_dict().items()})
        if self.publisher is not None:
            c["zenoh_published"] = int(getattr(self.publisher, "published", 0))
            c["zenoh_errors"] = int(getattr(self.publisher, "errors", 0))
            c["zenoh_not_connected"] = int(getattr(self.publisher, "not_connected", 0))
        if self.store is not None:
            c["store_errors"] = int(self.store.errors)
            c["store_waiting"] = int(self.store.waiting)
            c["store_lost"] = int(self.store.lost)
            c["store_history_lost"] = int(self.store.history_lost)
            c["windows_not_stored"] = self.pipeline.not_stored
        if self.recorder is not None:
            c["recording_lost"] = int(self.recorder.lost)
        c["samples_received"] = self.ring.samples
        c["samples_lost"] = sum(self.ring.lost.values())
        return c

    def _sink(self, name: str) -> Any:
        """The open sink, or the one :meth:`close` closed (its counters stay readable)."""
        obj = getattr(self, name)
        return obj if obj is not None else self._closed_sinks.get(name)

    def problems(self) -> list[str]:
        """What is degraded right now (for systemd's STATUS and the log), empty if nothing."""
        out = []
        store = self._sink("store")
        if store is not None and store.failing:
            out.append(f"state database not writable: {store.waiting} windows waiting "
                       f"in memory, not published")
        if store is not None and store.lost:
            out.append(f"{store.lost} windows lost (never stored)")
        if store is not None and store.history_lost:
            out.append(f"{store.history_lost} stored windows lost with a deleted or replaced "
                       f"state database file")
        recorder = self._sink("recorder")
        problem = getattr(recorder, "problem", None)
        if problem:
            out.append(problem)
        elif getattr(recorder, "lost", 0):
            out.append(f"recording: {recorder.lost} windows not recorded")
        return out

    def lost(self) -> dict[str, int]:
        """Windows estimated but lost: never stored (``store``), stored then lost with a
        deleted or replaced database file (``store_history``), not recorded (``recording``).
        Nonzero values make ``twinwatch run`` exit with status 74."""
        out = {}
        store = self._sink("store")
        if store is not None and store.lost:
            out["store"] = int(store.lost)
        if store is not None and store.history_lost:
            out["store_history"] = int(store.history_lost)
        recorder = self._sink("recorder")
        not_recorded = int(getattr(recorder, "lost", 0)) if recorder is not None else 0
        if not_recorded:
            out["recording"] = not_recorded
        return out

    @property
    def store_stats(self) -> dict[str, int]:
        """The state database's account: ``errors`` (failed writes), ``waiting`` (windows in
        memory), ``lost`` (never stored), ``not_stored`` (windows not stored when estimated,
        hence not published). Zeros without a state database."""
        store = self._sink("store")
        if store is None:
            return {"errors": 0, "waiting": 0, "lost": 0, "not_stored": 0}
        return {"errors": int(store.errors), "waiting": int(store.waiting),
                "lost": int(store.lost), "not_stored": self.pipeline.not_stored}

    def run(self, duration: float | None = None) -> int:
        """Acquire and estimate until the source ends, ``duration`` seconds of source time
        have been acquired, or :meth:`stop` is called.

        Returns:
            The number of windows estimated.
        """
        assert self.driver is not None
        live = self.driver.live
        self._worker = threading.Thread(target=self._work, name="twinwatch-adaptation",
                                        daemon=True)
        self._worker.start()
        if self.watchdog is not None:
            self.watchdog.require_windows = self.config.acquisition.watchdog == "windows"
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
                if window is not None:
                    self._submit(window, block=not live)
        finally:
            self._drain()
        return self.windows_estimated

    def _submit(self, window: WindowData, *, block: bool) -> None:
        if block:
            while not self._stop.is_set():
                try:
                    self._queue.put(window, timeout=0.2)
                    return
                except queue.Full:
                    continue
            return
        try:
            self._queue.put_nowait(window)
        except queue.Full:
            self.overruns += 1
            logger.warning("estimation overrun: window %d dropped (%d so far); the "
                           "estimation does not keep up with acquisition: lower "
                           "[estimation.pso].max_generations or the time budget",
                           window.index, self.overruns)

    def _drain(self) -> None:
        """Stop the worker after the windows already queued."""
        if self._worker is None:
            return
        while self._worker.is_alive():
            try:
                self._queue.put(_STOP, timeout=0.2)
                break
            except queue.Full:
                continue
        self._worker.join(timeout=self.config.acquisition.shutdown_timeout)
        if self._worker.is_alive():
            logger.warning("adaptation worker did not finish within %.0f s",
                           self.config.acquisition.shutdown_timeout)
        self._worker = None

    def _work(self) -> None:
        while True:
            item = self._queue.get()
            if item is _STOP:
                return
            if self._stop.is_set() and self.abandon:
                logger.info("window %d abandoned on stop", item.index)
                continue
            if self.watchdog is not None:
                self.watchdog.busy()
            try:
                self.process_window(item)
            except Exception as exc:  # contained to the window: the daemon goes on
                self.numeric_failures += 1
                logger.error("window %d could not be estimated (%s: %s); it is skipped and "
                             "counted in counters.numeric_failures", item.index,
                             type(exc).__name__, exc)
                logger.debug("window %d failed", item.index, exc_info=True)
            finally:
                if self.watchdog is not None:
                    self.watchdog.idle()

    def process_window(self, window: WindowData) -> dict[str, Any]:
        """Adapt the twin to one window and write it to the sinks (the pipeline's
        :meth:`~twinwatch.daemon.pipeline.WindowPipeline.process`). Returns the health
        message."""
        return self.pipeline.process(window)

    def close(self, keep: Collection[str] = ()) -> dict[str, Any]:
        """Stop everything and release driver, publisher, recorder and state database (after
        the worker has drained). Idempotent.

        Args:
            keep: the driver and sinks (names in :data:`HANDOVER`) to leave open for a new
                daemon (reload).

        Returns:
            name -> object for the kept ones: pass (those still compatible) as ``reuse``.
        """
        self._stop.set()
        self._drain()
        kept: dict[str, Any] = {}
        for name in ("driver", "publisher", "recorder", "store"):
            obj = getattr(self, name, None)
            if obj is None or (name == "driver" and not self._own_driver):
                continue
            if name in keep:
                if name == "publisher":
                    obj.add_query_handler("history", _no_history)
                kept[name] = obj
            else:
                try:
                    obj.close()
                except Exception as exc:  # noqa: BLE001 - the other sinks still close
                    logger.error("error while closing the %s: %s: %s", name,
                                 type(exc).__name__, exc)
                    logger.debug("closing the %s failed", name, exc_info=True)
                self._closed_sinks[name] = obj  # for the final accounting (lost windows)
            setattr(self, name, None)
        self.pipeline.sinks = []
        return kept

    def __enter__(self) -> Daemon:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


HISTORY_PARAMETERS = ("t_from", "t_to", "by", "limit")


def history_parameters(params: Any) -> tuple[float | None, float | None, int, str]:
    """The history query's parameters, checked: ``t_from`` and ``t_to`` finite seconds (either
    may be absent), ``t_from <= t_to``, ``by`` ``plant`` or ``wall``, ``limit`` a whole number
    from 1 (at most :data:`HISTORY_LIMIT` are returned).

    Args:
        params: the selector's parameters (a mapping with ``get``, zenoh's ``Parameters``).

    Returns:
        ``(t_from, t_to, limit, by)``.

    Raises:
        ValueError: naming the bad parameter.
    """
    unknown = [k for k, _ in _items(params) if k not in HISTORY_PARAMETERS]
    if unknown:
        raise ValueError(f"unknown parameter {unknown[0]!r}: use "
                         f"{', '.join(HISTORY_PARAMETERS)}")

    def num(key: str) -> float | None:
        raw = params.get(key)
        if raw in (None, ""):
            return None
        try:
            value = float(raw)
        except ValueError:
            raise ValueError(f"{key}={raw!r} is not a number [s]") from None
        if not math.isfinite(value):
            raise ValueError(f"{key}={raw!r}: give a finite time [s], or leave it out for "
                             f"an open end")
        return value

    by = params.get("by") or "plant"
    if by not in ("plant", "wall"):
        raise ValueError(f"by={by!r}: use by=plant (source time) or by=wall (epoch s)")
    t_from, t_to = num("t_from"), num("t_to")
    if t_from is not None and t_to is not None and t_from > t_to:
        raise ValueError(f"t_from={t_from:g} is after t_to={t_to:g}")
    lim = num("limit")
    if lim is not None and (lim < 1 or not lim.is_integer()):
        raise ValueError(f"limit={params.get('limit')!r}: give a whole number from 1 "
                         f"(at most {HISTORY_LIMIT} are returned)")
    limit = HISTORY_LIMIT if lim is None else min(int(lim), HISTORY_LIMIT)
    return t_from, t_to, limit, by


def _items(params: Any) -> list[tuple[str, str]]:
    """(key, value) pairs of zenoh ``Parameters`` or a plain mapping."""
    if isinstance(params, dict):
        return list(params.items())
    return [(str(k), str(v)) for k, v in params]


def _no_history(query: Any) -> dict[str, Any]:
    raise ValueError("the daemon is reloading: ask again in a moment")
