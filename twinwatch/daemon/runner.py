"""The daemon: driver -> ring buffer -> adaptation worker -> Zenoh and Rerun.

Threads (see docs/architecture.md):

* the caller's thread (the CLI's main thread) runs :meth:`Daemon.run`: it reads the driver,
  fills the ring buffer and hands each full window to the worker. It never estimates, so
  acquisition is never blocked by the optimiser.
* ``twinwatch-adaptation`` (one worker thread) estimates each window, builds its health
  message, publishes it over Zenoh and records it to Rerun.

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
from collections.abc import Callable
from pathlib import Path
from typing import Any

from twinwatch.config.schema import TwinwatchConfig
from twinwatch.daemon.ringbuffer import RingBuffer
from twinwatch.drivers import create_driver
from twinwatch.drivers.base import Driver, EndOfStream
from twinwatch.twin.adaptation import AdaptationResult, TwinAdapter
from twinwatch.twin.health import build_health, summary_line
from twinwatch.twin.model import TwinModel, WindowData
from twinwatch.twin.registry import create_model

logger = logging.getLogger(__name__)

_STOP = object()

HealthCallback = Callable[[dict[str, Any]], None]


class Daemon:
    """One machine's monitor.

    Args:
        config: validated configuration.
        base_dir: directory relative paths in the config are resolved against (the config
            file's directory).
        driver: an already-open driver to use instead of the configured one (tests).
        publish: open the Zenoh publisher (``config.zenoh.enabled`` must also be true).
        record: open the Rerun recorder (``config.recording.enabled`` must also be true).

    Raises:
        twinwatch.drivers.base.DriverInitializationError, PublisherError, RecorderError,
        ValueError: on a start-up problem, with a message that says what to fix.
    """

    def __init__(
        self,
        config: TwinwatchConfig,
        *,
        base_dir: Path | None = None,
        driver: Driver | None = None,
        publish: bool = True,
        record: bool = True,
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
        self.publisher: Any = None
        self.recorder: Any = None
        self.driver: Driver | None = None
        self._own_driver = driver is None
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=acq.queue)
        self._stop = threading.Event()
        self._worker: threading.Thread | None = None
        self.overruns = 0
        self.numeric_failures = 0
        self.windows_estimated = 0
        self.history: deque[dict[str, Any]] = deque(maxlen=acq.history)
        self.latest: dict[str, Any] | None = None
        self._callbacks: list[HealthCallback] = []
        self._lock = threading.Lock()
        try:
            if record and config.recording.enabled:
                from twinwatch.daemon.recorder import RerunRecorder

                rec = config.recording.model_copy()
                path = Path(rec.path)
                if not path.is_absolute():
                    rec.path = str(Path.cwd() / path)
                self.recorder = RerunRecorder(
                    rec, self.machine, outputs=self.model.output_names,
                    parameters={p.name: p.unit for p in self.model.parameters})
            if publish and config.zenoh.enabled:
                from twinwatch.daemon.publisher import HealthPublisher

                self.publisher = HealthPublisher(config.zenoh, self.machine)
            self.driver = driver or create_driver(config.driver, base_dir=self.base_dir)
        except BaseException:
            self.close()
            raise

    # -- lifecycle --------------------------------------------------------------------------
    def add_callback(self, fn: HealthCallback) -> None:
        """Call ``fn(health)`` from the worker thread after each window."""
        self._callbacks.append(fn)

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
        return c

    def run(self, duration: float | None = None) -> int:
        """Acquire and estimate until the source ends, ``duration`` seconds of source time
        have been acquired, or :meth:`stop` is called.

        Returns:
            The number of windows estimated.
        """
        assert self.driver is not None
        live = bool(getattr(self.driver, "live", False))
        self._worker = threading.Thread(target=self._work, name="twinwatch-adaptation",
                                        daemon=True)
        self._worker.start()
        t_first: float | None = None
        stall_timeout = self.config.acquisition.stall_timeout
        last_sample = time.monotonic()
        stalled = False
        try:
            while not self._stop.is_set():
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
            if self._stop.is_set() and self.config.acquisition.abandon_on_stop:
                continue
            try:
                self.process_window(item)
            except Exception:  # contained to the window: the daemon goes on
                self.numeric_failures += 1
                logger.exception("window %d could not be estimated; it is skipped and "
                                 "counted in counters.numeric_failures", item.index)

    def process_window(self, window: WindowData) -> dict[str, Any]:
        """Adapt the twin to one window (estimation, then discovery when needed), publish and
        record its health. Returns the health message."""
        result: AdaptationResult = self.adapter.process(window)
        est = result.estimate
        self.windows_estimated += 1
        health = build_health(machine=self.machine, model_name=self.config.machine.model,
                              model=self.model, window=window, estimate=est,
                              nominal=self.nominal, counters=self.counters(),
                              adaptation=result, discovery_enabled=self.adapter.enabled)
        with self._lock:
            self.latest = health
            self.history.append(health)
        logger.info("%s", summary_line(health))
        if self.publisher is not None:
            self.publisher.publish(health)
        if self.recorder is not None:
            outs = self.model.output_names
            self.recorder.log_window(
                t=window.t,
                measured={o: window[o] for o in outs},
                simulated={o: est.simulated[:, j] for j, o in enumerate(outs)},
                parameters=est.values,
                health=health,
                terms_changed=result.changed,
            )
        for fn in self._callbacks:
            fn(health)
        return health

    def close(self) -> None:
        """Stop everything and release drivers, publisher and recorder. Idempotent."""
        self._stop.set()
        self._drain()
        for name in ("driver", "publisher", "recorder"):
            obj = getattr(self, name, None)
            if obj is None or (name == "driver" and not self._own_driver):
                continue
            try:
                obj.close()
            except Exception:
                logger.exception("error while closing the %s", name)
            setattr(self, name, None)

    def __enter__(self) -> Daemon:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
