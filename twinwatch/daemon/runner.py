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
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from twinwatch.daemon.alarms import AlarmEvaluator
from twinwatch.daemon.pipeline import HealthCallback, WindowPipeline, WindowSink
from twinwatch.daemon.ringbuffer import RingBuffer
from twinwatch.drivers import create_driver
from twinwatch.drivers.base import Driver, EndOfStream
from twinwatch.twin.adaptation import TwinAdapter
from twinwatch.twin.model import TwinModel, WindowData
from twinwatch.twin.registry import create_model

if TYPE_CHECKING:  # the configuration is given by the caller; the daemon never reads files
    from twinwatch.config.schema import TwinwatchConfig
    from twinwatch.daemon.publisher import HealthPublisher
    from twinwatch.daemon.recorder import RerunRecorder
    from twinwatch.daemon.store import StateStore
    from twinwatch.daemon.systemd import Watchdog

logger = logging.getLogger(__name__)

_STOP = object()

HISTORY_LIMIT = 1000
"""Most windows one history query returns (page on with ``t_from``)."""

SINKS = ("store", "publisher", "recorder")
"""The daemon's sinks, in the order each window is written to them (stored before published);
a reload may hand them from the old daemon to the new one (:meth:`Daemon.close` ``keep``)."""


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
        reuse: open sinks (names in :data:`SINKS`) handed over from a previous daemon by a
            reload (see :meth:`close`), used instead of opening new ones. The caller (the
            supervisor) hands over only sinks whose configuration is unchanged.

    Raises:
        twinwatch.drivers.base.DriverInitializationError, PublisherError, RecorderError,
        StoreError, ValueError: on a start-up problem, with a message that says what to fix.
        The state database is opened first: a store error fails before the device is touched.
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
        reuse: Mapping[str, WindowSink] | None = None,
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
        self.driver: Driver | None = None
        self._own_driver = driver is None
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=acq.queue)
        self._stop = threading.Event()
        self._worker: threading.Thread | None = None
        self.overruns = 0
        self.numeric_failures = 0
        self._ticks: list[Callable[[], None]] = []
        self.abandon = config.acquisition.abandon_on_stop
        try:
            for name, sink in (reuse or {}).items():
                if name not in SINKS:
                    raise ValueError(f"unknown sink {name!r}; the sinks are {SINKS}")
                setattr(self, name, sink)
                logger.info("reload: the %s is kept open (its configuration is unchanged)", name)
            if persist and config.state.enabled and self.store is None:
                from twinwatch.daemon.store import StateStore

                st = config.state
                self.store = StateStore(Path(st.path).expanduser(),
                                        synchronous=st.synchronous,
                                        keep_days=st.keep_days, keep_rows=st.keep_rows,
                                        recover_corrupt=st.recover_corrupt)
            if self.store is not None:
                self._restore()
            if record and config.recording.enabled and self.recorder is None:
                from twinwatch.daemon.recorder import RerunRecorder

                rec = config.recording.model_copy()
                path = Path(rec.path)
                if not path.is_absolute():
                    rec.path = str(Path.cwd() / path)
                self.recorder = RerunRecorder(
                    rec, self.machine, outputs=self.model.output_names,
                    parameters={p.name: p.unit for p in self.model.parameters})
            if publish and config.zenoh.enabled and self.publisher is None:
                from twinwatch.daemon.publisher import HealthPublisher

                self.publisher = HealthPublisher(config.zenoh, self.machine,
                                                 retry_connect=True)
            if self.publisher is not None and self.store is not None:
                self.publisher.add_query_handler("history", self._on_history_query)
            self.driver = driver or create_driver(config.driver, base_dir=self.base_dir)
        except BaseException:
            self.close()
            raise
        self.pipeline.sinks = [s for s in (self.store, self.publisher, self.recorder)
                               if s is not None]

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
        meta-model terms) and the alarm levels of the last window."""
        assert self.store is not None
        state = self.store.load_twin_state(self.machine)
        if state is not None:
            try:
                self.adapter.restore(state)
            except (KeyError, TypeError, ValueError) as exc:
                logger.error("the saved twin of %s in %s cannot be used with this "
                             "configuration (%s): starting from the nominal values", self.machine,
                             self.store.path, exc)
            else:
                self.restored = state
                logger.warning("resumed the twin of %s from %s: %s; %d meta-model term(s)",
                               self.machine, self.store.path,
                               ", ".join(f"{k}={v:.6g}" for k, v in state["trusted"].items()),
                               len(state.get("terms", [])))
        last = self.store.latest_health(self.machine)
        if last is not None and last.get("alarms"):
            self.alarms.restore(last["alarms"])

    def stored_history(self, t_from: float | None = None, t_to: float | None = None,
                limit: int | None = HISTORY_LIMIT, by: str = "plant") -> list[dict[str, Any]]:
        """Stored health messages of this machine in a time range (see
        :meth:`StateStore.history`); empty without a state database."""
        if self.store is None:
            return []
        return self.store.history(t_from, t_to, limit, by=by,  # type: ignore[arg-type]
                                  machine=self.machine)

    def _on_history_query(self, query: Any) -> dict[str, Any]:
        """``get("P/history?t_from=..;t_to=..;by=plant|wall;limit=..")`` (zenoh thread)."""
        params = query.parameters

        def num(key: str) -> float | None:
            raw = params.get(key)
            if raw in (None, ""):
                return None
            try:
                return float(raw)
            except ValueError:
                raise ValueError(f"{key}={raw!r} is not a number [s]") from None

        by = params.get("by") or "plant"
        if by not in ("plant", "wall"):
            raise ValueError(f"by={by!r}: use by=plant (source time) or by=wall (epoch s)")
        lim = num("limit")
        limit = HISTORY_LIMIT if lim is None else max(1, min(int(lim), HISTORY_LIMIT))
        t_from, t_to = num("t_from"), num("t_to")
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

    def stop(self) -> None:
        """Ask :meth:`run` to return after the current sample (thread- and signal-safe)."""
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
        return c

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
                if self.watchdog is not None:
                    self.watchdog.tick()
                for fn in self._ticks:
                    fn()
                try:
                    sample = self.driver.read(timeout=0.2)
                except EndOfStream as exc:
                    logger.info("source finished: %s", exc)
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
            except Exception:  # contained to the window: the daemon goes on
                self.numeric_failures += 1
                logger.exception("window %d could not be estimated; it is skipped and "
                                 "counted in counters.numeric_failures", item.index)
            finally:
                if self.watchdog is not None:
                    self.watchdog.idle()

    def process_window(self, window: WindowData) -> dict[str, Any]:
        """Adapt the twin to one window and write it to the sinks (the pipeline's
        :meth:`~twinwatch.daemon.pipeline.WindowPipeline.process`). Returns the health
        message."""
        return self.pipeline.process(window)

    def close(self, keep: tuple[str, ...] = ()) -> dict[str, WindowSink]:
        """Stop everything and release driver, publisher, recorder and state database (after
        the worker has drained). Idempotent.

        Args:
            keep: sinks (names in :data:`SINKS`) to leave open for a new daemon (reload).

        Returns:
            name -> sink for the kept sinks: pass (those still compatible) as ``reuse``.
        """
        self._stop.set()
        self._drain()
        kept: dict[str, WindowSink] = {}
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
                except Exception:
                    logger.exception("error while closing the %s", name)
            setattr(self, name, None)
        self.pipeline.sinks = []
        return kept

    def __enter__(self) -> Daemon:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _no_history(query: Any) -> dict[str, Any]:
    raise ValueError("the daemon is reloading: ask again in a moment")
