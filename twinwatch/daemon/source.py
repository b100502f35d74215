"""Sources that come and go: a live source is opened with retries and reopened when it fails
(docs/sources.md).

:class:`SourceKeeper` wraps the driver of a *live* source (its class says
:meth:`~twinwatch.drivers.base.Driver.reopens`: a CAN bus, a Modbus device; not a log replay):

* at start, a source that cannot be opened (:class:`~twinwatch.errors.DriverInitializationError`,
  an ``OSError``) is retried in its own thread (``twinwatch-source``) with a capped, jittered
  exponential backoff (0.5 s doubling up to ``[acquisition] reopen_max``) until it opens or
  the daemon stops; meanwhile READY is sent, STATUS and the health message say what it waits
  for (:attr:`SourceKeeper.waiting`). A
  :class:`~twinwatch.errors.DriverConfigError` or a finite source still fails at once;
* at a reload (``wait=False``) one attempt is made: a failure fails the reload;
* while running, a driver that gives up (:class:`~twinwatch.errors.DriverOperationError`) is
  closed and opened again with the same backoff; reads return None meanwhile after their
  timeout.

The counters of every driver the keeper opened add up (:attr:`stats`; they never go back).
"""

from __future__ import annotations

import logging
import random
import threading
import time
from collections.abc import Callable
from dataclasses import fields
from pathlib import Path

from twinwatch.drivers import create_driver, get_driver_class
from twinwatch.drivers.base import (
    Driver,
    DriverConfig,
    DriverConfigError,
    DriverError,
    DriverOperationError,
    DriverStats,
    EndOfStream,
    Sample,
)

logger = logging.getLogger(__name__)

__all__ = ["BACKOFF_INITIAL", "SourceKeeper", "open_source"]

BACKOFF_INITIAL = 0.5
"""First delay [s] before opening a failed source again (doubling up to ``backoff_max``)."""


class SourceKeeper(Driver):
    """A live source's driver, opened with retries and reopened when it fails.

    Args:
        open_driver: opens the driver; raises on failure.
        config: the ``[driver]`` table (for the channels and the period before it opens).
        describe: the source for a person (``"can socketcand can0@10.0.0.7:29536"``).
        wait: a source that cannot open at once is retried in the background (at start);
            False: the first failure is raised (a reload).
        backoff_max: cap of the delay between attempts [s].

    Raises:
        DriverConfigError: the configuration is at fault (never retried).
        DriverError: ``wait`` is False and the source cannot be opened.
    """

    @classmethod
    def from_config(cls, config: DriverConfig, *, base_dir: Path | None = None) -> Driver:
        """A live source's driver kept open (:func:`open_source`, waiting for it)."""
        return open_source(config, base_dir=base_dir or Path.cwd(), wait=True)

    def __init__(self, open_driver: Callable[[], Driver], *, config: DriverConfig,
                 describe: str, wait: bool = True, backoff_max: float = 30.0,
                 rng: random.Random | None = None) -> None:
        self._own = DriverStats(extra={"open_failures": 0, "reopens": 0})
        super().__init__()
        self._open_driver = open_driver
        self.config = config
        self.source_name = describe
        twin_channels = getattr(config, "twin_channels", None)
        self.channels = tuple(twin_channels()) if callable(twin_channels) else ()
        period = getattr(config, "sample_period", None)
        if period is not None:
            self.sample_period = float(period)
        self.backoff_max = max(backoff_max, BACKOFF_INITIAL)
        self._rng = rng or random.Random()
        self._lock = threading.Lock()
        self._inner: Driver | None = None
        self._base: dict[str, int] = {}  # counters of the drivers closed so far
        self._ready = threading.Event()  # the opener thread has opened one
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._since: float | None = None  # monotonic time the source went missing
        self._error = ""
        self._refusal = ""  # the last configuration refusal said at ERROR
        self._attempts = 0
        self._next_try: float | None = None
        try:
            self._inner = self._attempt()
        except DriverConfigError:
            raise
        except (DriverError, OSError) as exc:
            if not wait:
                raise
            self._missing(exc, first=True)
            self._start_opener()

    # -- what the daemon reads ------------------------------------------------------------
    @property
    def live(self) -> bool:
        """The open driver's (a lock-step Modbus device is not live); True while waiting."""
        inner = self._inner
        return True if inner is None else inner.live

    @live.setter
    def live(self, value: bool) -> None:
        """Refused (``Driver.live`` is a class attribute; the keeper's is its driver's).

        Raises:
            AttributeError: always.
        """
        raise AttributeError("SourceKeeper.live is its open driver's; it cannot be set")

    @property
    def stats(self) -> DriverStats:
        """The counters of the drivers opened so far, the open one's and the keeper's own
        (``open_failures``, ``reopens``)."""
        total = dict(self._base)
        inner = self._inner
        if inner is not None:
            for k, v in inner.stats.as_dict().items():
                total[k] = total.get(k, 0) + v
        for k, v in self._own.extra.items():
            total[k] = total.get(k, 0) + v
        names = {f.name for f in fields(DriverStats)} - {"extra"}
        return DriverStats(**{k: total.pop(k, 0) for k in names}, extra=total)

    @stats.setter
    def stats(self, value: DriverStats) -> None:
        """Ignored: the base class's counters (``Driver.__init__``) are the keeper's own."""

    @property
    def waiting(self) -> str | None:
        """What the keeper waits for (opening the source again, or the first sample of the
        driver opened again: an outage ends with a sample), or the driver's own."""
        inner = self._inner
        since = self._since
        if inner is not None:
            if since is None or inner.waiting is not None:
                return inner.waiting
            return (f"{self.source_name} open again, no sample for "
                    f"{time.monotonic() - since:.0f} s ({self._error})")
        if since is None:
            return None
        left = "" if self._next_try is None else (
            f"; next attempt in {max(0.0, self._next_try - time.monotonic()):.0f} s")
        return (f"{self.source_name} cannot be opened for {time.monotonic() - since:.0f} s "
                f"({self._error}); {self._attempts} attempts{left}")

    @property
    def silent(self) -> tuple[str, ...]:
        inner = self._inner
        return () if inner is None else inner.silent

    @property
    def device_faults(self) -> tuple[str, ...]:
        inner = self._inner
        return () if inner is None else inner.device_faults

    # -- reading ----------------------------------------------------------------------------
    def _read_internal(self, timeout: float | None) -> Sample | None:
        inner = self._inner
        if inner is None:
            if not self._ready.wait(1.0 if timeout is None else max(timeout, 0.0)):
                return None
            inner = self._take_opened()
            if inner is None:
                return None
        try:
            sample = inner.read(timeout)
        except EndOfStream:
            raise
        except DriverOperationError as exc:
            self._lost(inner, exc)
            return None
        if sample is not None and self._since is not None:  # the outage ends with a sample
            logger.warning("%s is open again after %.1f s (%d attempts); acquisition goes on",
                           self.source_name, time.monotonic() - self._since, self._attempts)
            self._since = None
            self._attempts = 0
        return sample

    def _take_opened(self) -> Driver | None:
        """The driver the opener thread has opened, or None. The outage lasts until it
        delivers a sample (a bus that opens but stays silent fails again without a second
        ERROR line)."""
        with self._lock:
            self._ready.clear()
            inner = self._inner
        if inner is not None:
            logger.debug("%s opened again (%d attempts); waiting for its first sample",
                         self.source_name, self._attempts)
            self._next_try = None
        return inner

    def _lost(self, inner: Driver, exc: BaseException) -> None:
        """The driver gave up: count it, close it, open it again in the background."""
        with self._lock:
            self._inner = None
            self._fold(inner)
        try:
            inner.close()
        except Exception as close_exc:  # noqa: BLE001 - the source is being replaced
            logger.debug("closing the failed %s: %s", self.source_name, close_exc)
        self._missing(exc, first=True)
        self._start_opener()

    def _fold(self, inner: Driver) -> None:
        """Add a closed driver's counters to the base (under the lock)."""
        for k, v in inner.stats.as_dict().items():
            self._base[k] = self._base.get(k, 0) + v

    # -- opening ----------------------------------------------------------------------------
    def _attempt(self) -> Driver:
        self._attempts += 1
        try:
            return self._open_driver()
        except DriverConfigError:
            raise
        except (DriverError, OSError):
            self._own.extra["open_failures"] += 1
            raise

    def _missing(self, exc: BaseException, *, first: bool) -> None:
        self._error = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        if first and self._since is None:
            self._since = time.monotonic()
            logger.error("%s is not available (%s): the daemon waits for it and opens it "
                         "again with a backoff up to %.0f s (STATUS and the health message "
                         "say so; further attempts at DEBUG)", self.source_name, self._error,
                         self.backoff_max)
        else:
            logger.debug("%s still not available: %s", self.source_name, self._error)

    def _refused(self, exc: DriverConfigError) -> None:
        """The source answers but refuses the configuration (a server reconfigured while the
        daemon waited): at ERROR once per reason, naming the key; the keeper goes on trying."""
        line = exc.keyed()
        if line != self._refusal:
            self._refusal = line
            logger.error("%s answers but refuses the configuration: %s; the daemon keeps "
                         "trying (fix the configuration and reload, or the source)",
                         self.source_name, line)
        self._missing(exc, first=False)

    def _start_opener(self) -> None:
        if self._stopping.is_set():
            return
        self._thread = threading.Thread(target=self._open_loop, name="twinwatch-source",
                                        daemon=True)
        self._thread.start()

    def _open_loop(self) -> None:
        """Try to open the source with a capped, jittered exponential backoff until it opens
        or the keeper closes (the ``twinwatch-source`` thread)."""
        step = BACKOFF_INITIAL
        while True:
            delay = step * (0.5 + 0.5 * self._rng.random())
            self._next_try = time.monotonic() + delay
            if self._stopping.wait(delay):
                return
            self._next_try = None
            try:
                driver = self._attempt()
            except DriverConfigError as exc:  # the configuration changed under us: keep trying
                self._refused(exc)
            except (DriverError, OSError) as exc:
                self._missing(exc, first=False)
            except Exception as exc:  # noqa: BLE001 - a driver's bug must not end the retries
                logger.debug("opening %s raised", self.source_name, exc_info=True)
                self._missing(exc, first=False)
            else:
                with self._lock:
                    closed = self._stopping.is_set()
                    if not closed:
                        self._inner = driver
                        self._own.extra["reopens"] += 1
                if closed:
                    driver.close()
                    return
                self._ready.set()
                return
            step = min(2.0 * step, self.backoff_max)

    # -- closing ----------------------------------------------------------------------------
    def _close_internal(self) -> None:
        self._stopping.set()
        with self._lock:
            inner, self._inner = self._inner, None
            if inner is not None:
                self._fold(inner)
        if inner is not None:
            inner.close()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=1.0)  # an open in progress closes what it opens once it returns


def open_source(config: DriverConfig, *, base_dir: Path, wait: bool = True,
                backoff_max: float = 30.0) -> Driver:
    """Open the configured source: a live one (its driver class's
    :meth:`~twinwatch.drivers.base.Driver.reopens`) inside a :class:`SourceKeeper`, any other
    directly.

    Args:
        wait, backoff_max: as :class:`SourceKeeper`'s.

    Raises:
        DriverConfigError: the configuration is at fault.
        DriverError: a source that is not live, or ``wait`` is False, cannot be opened.
    """
    cls = get_driver_class(config.type)
    if not cls.reopens(config):
        return create_driver(config, base_dir=base_dir)
    return SourceKeeper(lambda: create_driver(config, base_dir=base_dir), config=config,
                        describe=cls.describe(config), wait=wait, backoff_max=backoff_max)
