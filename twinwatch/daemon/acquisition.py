"""Acquisition: the driver -> ring buffer loop of one machine.

:class:`Acquisition` runs in the machine's thread (:meth:`twinwatch.daemon.runner.Daemon.run`):
it reads the driver, fills the :class:`~twinwatch.daemon.ringbuffer.RingBuffer` and hands each
full window to the window worker's queue; it never estimates. It stops when the
source ends, the duration is reached, the driver fails, or :meth:`Acquisition.stop` is called
(at once, or at the next window boundary: a reload neither loses nor repeats a sample).
"""

from __future__ import annotations

import logging
import threading
import time
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from twinwatch.daemon.ringbuffer import RingBuffer
from twinwatch.daemon.source import open_source
from twinwatch.drivers.base import Driver, DriverError, EndOfStream, Sample

if TYPE_CHECKING:
    from twinwatch.config.schema import TwinwatchConfig
    from twinwatch.daemon.systemd import Watchdog
    from twinwatch.drivers.base import FloatArray
    from twinwatch.twin.model import TwinModel, WindowData

logger = logging.getLogger(__name__.rsplit(".", 1)[0] + ".runner")

__all__ = ["READ_TIMEOUT_S", "STOP_AT_WINDOW_S", "TICK_S", "Acquisition"]

TICK_S = 0.05
"""Seconds [wall] between the acquisition loop's ticks (the watchdog, the supervisor's reload
and STATUS checks) while a live source's samples arrive, and after each read that had none. A
source on a simulated clock ticks every sample (its 2 s windows may pass in milliseconds)."""

READ_TIMEOUT_S = 1.0
"""Longest one read of the driver waits [s, wall]: while no sample comes the loop ticks at
least this often (and at least twice per watchdog interval, ``WatchdogSec=`` / 2, when systemd
asks for pings), and it sees a stop within it. A real-time replay sleeps up to it
(:data:`twinwatch.drivers.file.PACE_SLACK`), so its thread wakes about twice a 2 s window: each
wake-up costs a few tenths of a millisecond of CPU on a shared box
(``benchmarks/bench_window.py``, ``benchmarks/bench_density.py``)."""

STOP_AT_WINDOW_S = 5.0
"""Longest wait [s, wall] beyond one window's length for the window being filled when a reload
stops a daemon at a window boundary (:meth:`Acquisition.stop` ``at_window``); then it stops and
the partial window is dropped (a source that went silent)."""


class Acquisition:
    """The driver and the ring buffer of one machine, and the loop between them.

    Args:
        own_driver: the driver is ours to close (:meth:`release`; False: given by the caller).

    Attributes:
        driver: the open driver (None before :meth:`open` and after :meth:`release`).
        stopping: set by :meth:`stop` (the window worker reads it too).
        ended: why :meth:`run` returned by itself (``end of the source``, ``duration
            reached``, ``driver failure``), else None.
    """

    def __init__(self, config: TwinwatchConfig, model: TwinModel, *, own_driver: bool,
                 watchdog: Watchdog | None = None) -> None:
        self.config = config
        acq = config.acquisition
        longest = acq.adaptive.max_window if acq.adaptive.enabled else acq.window
        self.ring = RingBuffer(model.required_channels(), window=acq.window,
                               sample_period=acq.sample_period,
                               jitter_tolerance=acq.jitter_tolerance,
                               capacity=4 * max(longest, acq.window),
                               max_missing=acq.max_missing,
                               max_missing_run=acq.max_missing_run)
        self.driver: Driver | None = None
        self._own_driver = own_driver
        self.phase = 0
        self._phase_pending = False
        self.watchdog = watchdog
        self.stopping = threading.Event()
        self._stop_at_window: float | None = None  # monotonic deadline, see stop(at_window)
        self.ended: str | None = None
        self.failure: str | None = None
        self.ticks: list[Callable[[], None]] = []
        self._abandoned_seen = 0

    def open(self, driver: Driver | None, *, base_dir: Path, wait: bool) -> None:
        """Take ``driver`` (handed over by a reload, or given by the caller) or open the
        configured source (:func:`~twinwatch.daemon.source.open_source`)."""
        self.driver = driver or open_source(self.config.driver, base_dir=base_dir, wait=wait,
                                            backoff_max=self.config.acquisition.reopen_max)

    def stagger(self, name: str) -> int:
        """Lengthen the first window by a phase of 0 to ``window - 1`` samples from ``name``
        (CRC-32: the same machine keeps its phase across restarts), so the windows of machines
        started together complete spread over a window's length. Returns the phase [samples]."""
        window = self.config.acquisition.window
        self.phase = zlib.crc32(name.encode()) % window
        if self.phase:
            self.ring.request_window(window + self.phase)
            self._phase_pending = True
        return self.phase

    def run(self, duration: float | None, submit: Callable[[WindowData, bool], None],
            abandoned: Callable[[int], None]) -> None:
        """Read the driver and fill the ring buffer until the source ends, ``duration`` seconds
        of source time have been acquired, or :meth:`stop`; each full window goes to
        ``submit(window, block)`` (``block``: the source is on a simulated clock, wait for the
        worker), each window the ring buffer abandoned to ``abandoned(n)``."""
        assert self.driver is not None
        live = self.driver.live
        if self.watchdog is not None:
            self.watchdog.require_windows = self.config.acquisition.watchdog == "windows"
            self.watchdog.source_waiting = self.source_waiting
            self.watchdog.reset()
        t_first: float | None = None
        stall_timeout = self.config.acquisition.stall_timeout
        last_sample = time.monotonic()
        stalled = False
        driver_said = False  # the driver said the stall's cause itself (at ERROR)
        next_tick = 0.0
        tick_s = TICK_S if live else 0.0
        timeout = self.read_timeout()
        columns = self._block_columns()
        while not self.stopping.is_set():
            if self._stop_at_window is not None and (
                    self.ring.pending == 0 or time.monotonic() > self._stop_at_window):
                break
            if last_sample >= next_tick:  # the last sample's arrival, or the idle read's end
                next_tick = last_sample + tick_s
                if self.watchdog is not None:
                    self.watchdog.tick()
                for fn in self.ticks:
                    fn()
            try:
                got = self._read(columns, timeout)
            except EndOfStream as exc:
                logger.info("source finished: %s", exc)
                self.ended = "end of the source"
                break
            except DriverError as exc:
                # the driver gave up: the queued windows are finished, the caller decides
                self.failure = f"the {self.config.driver.type} driver failed: {exc}"
                logger.error("%s", self.failure)
                self.ended = "driver failure"
                break
            now = time.monotonic()
            if got is None:
                next_tick = 0.0  # nothing came within the read's timeout: tick now
                if not stalled and now - last_sample > stall_timeout:
                    stalled = True
                    driver_said = self._say_stall(now - last_sample)
                continue
            if stalled:
                (logger.info if driver_said else logger.warning)(
                    "driver delivers samples again after a stall of %.1f s", now - last_sample)
                stalled = False
            last_sample = now
            if t_first is None:
                t_first = got.t if isinstance(got, Sample) else float(got[0][0])
            windows, reached = self._store(got, columns, t_first, duration)
            n_abandoned = sum(self.ring.causes.values())
            if n_abandoned > self._abandoned_seen:
                abandoned(n_abandoned - self._abandoned_seen)
                self._abandoned_seen = n_abandoned
            for window in windows:
                submit(window, not live)
            if reached:
                self.ended = "duration reached"
                break

    def read_timeout(self) -> float:
        """The loop's read timeout [s]: :data:`READ_TIMEOUT_S`, or half the watchdog's ping
        interval when that is shorter (the pings ride on the loop's ticks)."""
        wd = self.watchdog
        if wd is None or wd.interval is None or not wd.enabled:
            return READ_TIMEOUT_S
        return min(READ_TIMEOUT_S, 0.5 * wd.interval)

    def _read(self, columns: list[int] | None, timeout: float
              ) -> Sample | tuple[FloatArray, FloatArray] | None:
        """The driver's next rows: a block up to the window's end (``columns``:
        :meth:`_block_columns`, once the staggered first window has started), else one
        sample; None when none came within ``timeout`` [s]."""
        assert self.driver is not None
        if columns is not None and not self._phase_pending:
            return self.driver.read_block(timeout, self.ring.window - self.ring.pending)
        return self.driver.read(timeout=timeout)

    def _store(self, got: Sample | tuple[FloatArray, FloatArray], columns: list[int] | None,
               t_first: float, duration: float | None) -> tuple[list[WindowData], bool]:
        """Put what :meth:`_read` returned into the ring buffer. Returns the windows it
        completed and whether ``duration`` [s] after ``t_first`` was reached (the rows from
        there on are not stored)."""
        if isinstance(got, Sample):
            if duration is not None and got.t - t_first >= duration:
                return [], True
            window = self.ring.append(got.t, got.values)
            if self._phase_pending and not self.ring.window_requested:
                # the staggered first window has started: the next ones are of the usual length
                self._phase_pending = False
                self.ring.request_window(self.config.acquisition.window)
            return ([] if window is None else [window]), False
        t, values = got
        if duration is not None and t[-1] - t_first >= duration:
            keep = int(np.argmax(t - t_first >= duration))
            return self.ring.append_block(t[:keep], values[:keep, columns]), True
        return self.ring.append_block(t, values[:, columns]), False

    def _block_columns(self) -> list[int] | None:
        """The driver's columns in the ring buffer's channel order when it reads blocks
        (:attr:`~twinwatch.drivers.base.Driver.reads_blocks`) and delivers every channel the
        twin needs; None: sample by sample (a block is stored as those samples would be,
        :meth:`RingBuffer.append_block`)."""
        driver = self.driver
        if driver is None or not driver.reads_blocks:
            return None
        if not set(self.ring.channels) <= set(driver.channels):
            return None
        return [driver.channels.index(c) for c in self.ring.channels]

    def _say_stall(self, quiet: float) -> bool:
        """Say once that no sample came for ``quiet`` seconds, asking the driver what it knows
        first, so an outage is one ERROR line (a driver that waits for its source,
        :attr:`Driver.waiting`, said so itself: the stall is at INFO). Returns whether the
        driver said it."""
        kind = self.config.driver.type
        waiting, silent, _ = self.source_state()
        if waiting:
            logger.info("no sample from the %s driver for %.1f s: %s; waiting for data",
                        kind, quiet, waiting)
            return True
        if silent:
            logger.error("no sample from the %s driver for %.1f s: silent: %s; waiting for "
                         "data", kind, quiet, ", ".join(silent))
        else:
            logger.error("no sample from the %s driver for %.1f s: check the device, cable "
                         "and bus configuration; waiting for data", kind, quiet)
        return False

    def stop(self, at_window: bool = False) -> None:
        """Ask :meth:`run` to return after the current sample (thread- and signal-safe), or
        with ``at_window`` once the window being filled is complete (at most its length plus
        :data:`STOP_AT_WINDOW_S` of wall time)."""
        if at_window:
            acq = self.config.acquisition
            self._stop_at_window = (time.monotonic() + acq.window * acq.sample_period
                                    + STOP_AT_WINDOW_S)
        else:
            self.stopping.set()

    def source_state(self) -> tuple[str | None, list[str], list[str]]:
        """What the driver waits for (None when it delivers), its silent messages and its
        :attr:`~twinwatch.drivers.base.Driver.device_faults`."""
        driver = self.driver
        if driver is None:
            return None, [], []
        return driver.waiting, list(driver.silent), list(driver.device_faults)

    def source_waiting(self) -> bool:
        """The driver waits for its source (a device absent, a bus being reopened)."""
        driver = self.driver
        return driver is not None and driver.waiting is not None

    def release(self, keep_driver: bool = False) -> Driver | None:
        """Let go of the driver. Returns it when the caller is to close it (ours, and not kept
        for a reload's daemon), else None."""
        driver, self.driver = self.driver, None
        if driver is not None and self._own_driver and not keep_driver:
            return driver
        return None
