"""The acquisition driver contract (docs/extending.md, "Where a new driver plugs in").

Modelled on python-can's ``BusABC``: one abstract base owns the public :meth:`Driver.read`,
backends override the protected :meth:`Driver._read_internal`; :meth:`Driver.close` is
idempotent, a driver is a context manager, and a driver never closed warns when collected. A
driver delivers :class:`Sample` objects, one time stamp [s] and one value per *twin* channel
(mapping bus signals to twin channels, with unit scaling, is the driver's job).

Errors follow the lifecycle, as in ``can/exceptions.py``: :class:`DriverInitializationError`
while opening (its subclass :class:`DriverConfigError` when the configuration or a file it
names is at fault), :class:`DriverOperationError` for a failure while reading that the driver
could not survive, :class:`EndOfStream` when a finite source is exhausted. Recoverable bad
input (an undecodable frame, a NaN, a gap) is *not* raised: it is counted in
:attr:`Driver.stats`, logged once, and the driver goes on.
"""

from __future__ import annotations

import abc
import contextlib
import logging
import queue
import random
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Self, TypeVar

from pydantic import BaseModel, ValidationError

from twinwatch._lifecycle import Closeable
from twinwatch._table import StrictTable
from twinwatch.errors import (
    DriverConfigError,
    DriverError,
    DriverInitializationError,
    DriverOperationError,
    EndOfStream,
)
from twinwatch.io.counter import SampleCounter
from twinwatch.io.sample import Sample, ScaledChannel
from twinwatch.plugins import commented_table

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt

    FloatArray = npt.NDArray[np.float64]

logger = logging.getLogger(__name__)

__all__ = [
    "PACKAGE_PREFIX",
    "Driver",
    "DriverError",
    "DriverInitializationError",
    "DriverOperationError",
    "DriverConfig",
    "DriverStats",
    "EndOfStream",
    "PlantDriver",
    "QueuedDriver",
    "Sample",
    "ScaledChannel",
    "resolve_path",
    "validated_config",
]


PACKAGE_PREFIX = "twinwatch:"
"""A ``dbc``, ``eds``, ``log_file`` (any of :attr:`DriverConfig.file_keys`) written
``twinwatch:plant/odrive-axis0.log.gz`` is a file shipped inside the installed twinwatch
package (``twinwatch/plant/...``), found wherever the configuration file is copied."""


def resolve_path(path: Path, base_dir: Path | None) -> Path:
    """``path`` as the driver opens it: a file of the package (:data:`PACKAGE_PREFIX`), or
    ``~`` expanded and a relative path joined to ``base_dir`` (the config file's directory;
    None: left relative to the current directory)."""
    text = str(path)
    if text.startswith(PACKAGE_PREFIX):
        import twinwatch

        return Path(twinwatch.__file__).resolve().parent / text[len(PACKAGE_PREFIX):]
    path = path.expanduser()
    return path if path.is_absolute() or base_dir is None else Path(base_dir) / path


class DriverConfig(StrictTable):
    """Base of every driver's configuration model (its ``[driver]`` table).

    Attributes:
        type: the driver's registry name (``"can"``, ``"file"``, ...); subclasses narrow it
            to their own name (``type: Literal["can"]``).
    """

    #: the keys naming a file (a ``Path`` or None): resolved against the configuration file's
    #: directory (:meth:`resolved`), each given one required to start (:meth:`required_files`)
    file_keys: ClassVar[tuple[str, ...]] = ()

    type: str

    def resolved(self, base_dir: Path | None) -> Self:
        """A copy whose :attr:`file_keys` are resolved against ``base_dir``
        (:func:`resolve_path`)."""
        update = {k: resolve_path(v, base_dir) for k in self.file_keys
                  if (v := getattr(self, k)) is not None}
        return self.model_copy(update=update) if update else self

    def required_files(self, base_dir: Path) -> dict[str, Path]:
        """Config key -> file that must exist to start (the :attr:`file_keys` given)."""
        cfg = self.resolved(base_dir)
        return {f"driver.{k}": v for k in self.file_keys if (v := getattr(cfg, k)) is not None}


ConfigT = TypeVar("ConfigT", bound=BaseModel)


def validated_config(model: type[ConfigT], config: ConfigT | Mapping[str, Any],
                     what: str) -> ConfigT:
    """A driver's ``from_config`` input as its config model: returned as is when it already is
    one, validated when it is a raw ``[driver]`` table.

    Args:
        what: the driver's name for the message, e.g. ``"CAN"``.

    Raises:
        DriverConfigError: the table does not validate (the message names the keys).
    """
    if isinstance(config, model):
        return config
    try:
        return model.model_validate(config)
    except ValidationError as exc:
        raise DriverConfigError(f"invalid {what} driver config: {exc}") from exc


@dataclass(slots=True)
class DriverStats:
    """Counters every driver keeps. They are published with health and never reset."""

    frames: int = 0  #: raw frames / rows / register reads received
    samples: int = 0  #: samples delivered to the caller
    bad_frames: int = 0  #: frames of a mapped message that could not be decoded
    bad_values: int = 0  #: decoded values that were NaN, inf or out of range
    gaps: int = 0  #: missing samples detected from time stamps or counters
    errors: int = 0  #: recoverable read errors (timeouts, dropped links)
    extra: dict[str, int] = field(default_factory=dict)

    def as_dict(self) -> dict[str, int]:
        """The counters, the fixed ones first, then :attr:`extra`'s."""
        d = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "extra"}
        return {**d, **self.extra}


def source_problem_lines(silent: Sequence[str], faults: Sequence[str]) -> list[str]:
    """A driver's silent messages and the faults its device reports (:attr:`Driver.silent`,
    :attr:`Driver.device_faults`) as lines of the daemon's STATUS and of the run's summary:
    ``silent: a, b`` and ``device fault: c``, each only when there is any."""
    return [f"{what}: {', '.join(items)}"
            for what, items in (("silent", silent), ("device fault", faults)) if items]


class Driver(Closeable, abc.ABC):
    """Base class of every acquisition driver.

    Subclasses set :attr:`config_class`, :attr:`driver_name`, :attr:`channels` (and
    :attr:`live` if the source cannot wait), implement ``__init__(config, *, base_dir)`` (or
    :meth:`from_config`), :meth:`_read_internal` and, if they hold resources,
    :meth:`_close_internal`, and override the configuration queries
    (:meth:`nominal_sample_period`, :meth:`duration`, :meth:`safe_to_probe`,
    :meth:`time_starts_over`) where the defaults do not fit.
    """

    #: The pydantic model of this driver's ``[driver]`` table (a :class:`DriverConfig`).
    config_class: ClassVar[type[DriverConfig]]
    #: The twin channels this driver delivers, in a fixed order.
    channels: tuple[str, ...] = ()
    #: Nominal sample period [s] (used by the daemon to detect gaps).
    sample_period: float = 0.01
    #: A read caught up with a live source sleeps :data:`BATCH_S` for a batch (the bus and
    #: queued drivers); False for a simulated plant's inner driver, which reads what the plant
    #: has just served (:class:`PlantDriver`).
    batches: bool = True
    _caught_up = False  # the last read's sample or frame came after a wait (:data:`BATCH_S`)

    #: The source cannot wait (a live bus, a real-time replay): when the estimation falls
    #: behind, the daemon drops windows and counts overruns instead of waiting.
    live: bool = False
    #: ``twinwatch sample-config --driver <name>``: the machine its sample monitors (a twin
    #: model's registry name, whose sample tables ``config/samples/<model>.toml`` are used),
    #: the machine's name there (default ``<model>-<name>``) and what the sample runs (default:
    #: the first line of the class docstring).
    sample_model: ClassVar[str] = "dc_motor"
    sample_machine: ClassVar[str | None] = None
    sample_title: ClassVar[str | None] = None
    #: the driver in messages and in a validation error (``"CAN"``, ``"Modbus"``, ``"file"``)
    driver_name: ClassVar[str] = "acquisition"
    #: The driver also delivers rows in blocks (:meth:`read_block`), which the acquisition
    #: stores with :meth:`~twinwatch.daemon.ringbuffer.RingBuffer.append_block`.
    reads_blocks: ClassVar[bool] = False

    # -- what a configuration says about the source ---------------------------------------
    @classmethod
    def from_config(cls, config: Any, *, base_dir: Path | None = None) -> Driver:
        """Open a driver from its configuration (a driver may take further keyword-only
        arguments, e.g. an open ``bus=`` for CAN).

        Args:
            config: a :attr:`config_class` instance or the raw ``[driver]`` table.
            base_dir: directory relative paths in the configuration are resolved against (the
                configuration file's directory); None: the current directory.

        Raises:
            DriverInitializationError: the table does not validate (naming the key), or the
                source cannot be opened.
        """
        checked = validated_config(cls.config_class, config, cls.driver_name)
        return cls(checked, base_dir=base_dir)  # type: ignore[call-arg]

    @classmethod
    def nominal_sample_period(cls, config: DriverConfig) -> float | None:
        """The sample period [s] the configured source delivers, or None when only the data
        tell (cross-checked against ``acquisition.sample_period`` at load time). Default: the
        table's ``sample_period`` key, if any."""
        value = getattr(config, "sample_period", None)
        return None if value is None else float(value)

    @classmethod
    def duration(cls, config: DriverConfig) -> float | None:
        """Source time [s] a finite configured source lasts (a simulation's duration), or None
        when unknown before reading (a bus, a file). Used for the progress bar's total."""
        return None

    @classmethod
    def safe_to_probe(cls, config: DriverConfig) -> bool:
        """Whether ``check-config`` may open (and close, without reading) the configured
        driver to check what only opening can (a file's columns, a DBC's names): only where
        opening cannot touch a device (a file, a log replay)."""
        return False

    @classmethod
    def probe(cls, config: DriverConfig, *, base_dir: Path | None = None) -> str | None:
        """What ``check-config`` does to the configured source: open it without reading and
        without sending, and close it. Default: a source :meth:`safe_to_probe` is opened
        through :meth:`from_config`; others are not touched (None).

        Returns:
            What was checked, for a person, or None when nothing was opened.

        Raises:
            DriverError: the source cannot be opened (the message says why).
        """
        if not cls.safe_to_probe(config):
            return None
        cls.from_config(config, base_dir=base_dir).close()
        return "opened"

    @classmethod
    def reopens(cls, config: DriverConfig) -> bool:
        """Whether the configured source is *live* and may come and go (a bus, a device, a
        gateway): the daemon then waits for it at start and reopens it, with a capped backoff,
        when the driver raises :class:`~twinwatch.errors.DriverOperationError`
        (:mod:`twinwatch.daemon.source`). False for a finite source: a failure to open fails."""
        return False

    @classmethod
    def describe(cls, config: DriverConfig) -> str:
        """The configured source for a person, in log lines and STATUS (default: ``"the
        <type> source"``)."""
        return f"the {config.type} source"

    @classmethod
    def time_starts_over(cls, config: DriverConfig) -> bool:
        """Whether the configured source's time starts over each time it is opened (a
        simulated plant, a recording or log replayed): ``twinwatch run`` on it then starts a
        new run from the nameplate twin and normal alarm levels unless ``--resume`` is given.
        False for a bus or a device: a restart resumes."""
        return False

    @classmethod
    def sample(cls, name: str) -> str:
        """The commented sample of its ``[driver]`` table for ``twinwatch sample-config
        --driver <name>`` (a built-in ships its own, ``config/samples/driver_<name>.toml``).
        Default: generated from :attr:`config_class` (every key, its default and description;
        optional keys commented out)."""
        return commented_table(cls.config_class, "driver", fixed={"type": name})

    def __init__(self) -> None:
        self.stats = DriverStats()
        self._closed = False
        self._logged_once: set[str] = set()

    # -- public API -----------------------------------------------------------------------
    def read(self, timeout: float | None = None) -> Sample | None:
        """Return the next sample, or None if none arrived within ``timeout`` seconds.

        Args:
            timeout: seconds to wait; None waits until a sample arrives or the stream ends.

        Raises:
            EndOfStream: the source is exhausted (file replayed, simulation finished).
            DriverOperationError: the driver failed and cannot recover.
        """
        if self._closed:
            raise DriverOperationError(f"{type(self).__name__} is closed")
        sample = self._read_internal(timeout)
        if sample is not None:
            self.stats.samples += 1
        return sample

    def read_block(self, timeout: float | None, limit: int
                   ) -> tuple[FloatArray, FloatArray] | None:
        """Return the next 1 to ``limit`` samples at once, as :meth:`read` would return them
        one by one (the same counters), or None if none arrived within ``timeout`` seconds;
        only where :attr:`reads_blocks`.

        Returns:
            ``(t (n,) [s], values (n, len(channels)))``, the columns in :attr:`channels`
            order.

        Raises:
            EndOfStream, DriverOperationError: as :meth:`read`.
        """
        if self._closed:
            raise DriverOperationError(f"{type(self).__name__} is closed")
        block = self._read_block_internal(timeout, limit)
        if block is not None:
            self.stats.samples += len(block[0])
        return block

    def close(self) -> None:
        """Release the driver's resources. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._close_internal()

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def waiting(self) -> str | None:
        """What the source is waiting for, for a person (``"Modbus device tcp 10.0.0.5:502
        device 1 not answering for 12 s: connection refused"``), while the driver is
        recovering it; None while it delivers. Shown in systemd's STATUS and the health
        message; the watchdog stays fed meanwhile. Thread-safe to read."""
        return None

    @property
    def silent(self) -> tuple[str, ...]:
        """The parts of the source that went silent while the rest delivers (a bus message
        and the channels it carries: ``"TW_Motor_Electrical (Va, ia) for 3.1 s"``), for the
        health message and systemd's STATUS. Thread-safe to read."""
        return ()

    @property
    def device_faults(self) -> tuple[str, ...]:
        """What the device reports wrong with itself while it delivers (a drive's EMCY, its
        CiA 402 statusword's fault bit, an NMT state other than operational), for the health
        message (``source.device_faults``) and systemd's STATUS. Thread-safe to read."""
        return ()

    def log_once(self, key: str, msg: str, *args: object, level: int = logging.WARNING) -> None:
        """Log ``msg`` at ``level`` the first time ``key`` is seen, at DEBUG afterwards, on
        the driver module's logger."""
        log = logging.getLogger(type(self).__module__)
        if key in self._logged_once:
            log.debug(msg, *args)
        else:
            self._logged_once.add(key)
            log.log(level, msg, *args)

    def _bump(self, key: str, n: int = 1) -> None:
        self.stats.extra[key] = self.stats.extra.get(key, 0) + n

    def _count(self, counter: SampleCounter, raw: int, what: str, shown: int = 0, *,
               unit: str = "frame", repeats_expected: bool = False) -> bool:
        """Feed a sample counter's value ``raw``: a jump counts the samples lost in
        ``stats.gaps``; a repeat or a late ``unit`` (a frame, a poll's answer) counts in
        ``stats.extra["duplicates"]`` / ``["reordered"]``, a step further back (the source
        restarted) in ``["counter_resets"]``; each logged once (a repeat not at all when
        ``repeats_expected``: a poll faster than the device samples). ``what`` names the
        counter in the log, whose values are shown ``raw + shown``.

        Returns:
            True when the sample of this value is to be skipped (a repeat, a late one).
        """
        before = counter.raw
        step, missing = counter.update(raw)
        old = None if before is None else before + shown
        if step in ("duplicate", "stale"):
            key = "duplicates" if step == "duplicate" else "reordered"
            self._bump(key)
            if step == "stale" or not repeats_expected:
                self.log_once(
                    f"counter:{step}",
                    "%s %d arrived after %d (%s %s): its sample is skipped, the count goes on; "
                    "counted in stats.extra[%r]", what, raw + shown, old,
                    "a repeated" if step == "duplicate" else "a late, reordered", unit, key)
            return True
        if step == "reset":
            self._bump("counter_resets")
            self.log_once("counter:reset", "%s went back from %d to %d (the source restarted): "
                          "its clock restarts from the new value", what, old, raw + shown)
        elif missing:
            self.stats.gaps += missing
            self.log_once("counter:gap", "%s jumped from %d to %d: %d samples lost; counted in "
                          "stats.gaps", what, old, raw + shown, missing)
        return False

    # -- for subclasses -------------------------------------------------------------------
    @abc.abstractmethod
    def _read_internal(self, timeout: float | None) -> Sample | None:
        """Read one sample; see :meth:`read`."""

    def _read_block_internal(self, timeout: float | None, limit: int
                             ) -> tuple[FloatArray, FloatArray] | None:
        """Read up to ``limit`` samples; see :meth:`read_block`."""
        raise NotImplementedError(f"{type(self).__name__} does not read blocks")

    def _close_internal(self) -> None:  # noqa: B027 - optional hook
        """Release resources; called once by :meth:`close`."""

    def _batch_nap(self, timeout: float | None, sleep: Callable[[float], object]) -> bool:
        """Before a receive: when the last read caught up with a live source, ``sleep``
        :data:`BATCH_S` (at most ``timeout`` [s]; not when it is 0) for a batch. True if it
        slept."""
        if not (self._caught_up and BATCH_S and (timeout is None or timeout > 0)):
            return False
        self._caught_up = False
        sleep(BATCH_S if timeout is None else min(BATCH_S, timeout))
        return True

    def _waited_since(self, start: float) -> bool:
        """The receive that began at monotonic ``start`` [s] waited (:data:`WAITED_S`), and
        this driver takes batches."""
        return self.batches and time.monotonic() - start > WAITED_S


#: Once a read of a live source has caught up with it (its sample or frame came after a
#: wait), the next read first sleeps this long [s] (at most its timeout) and then takes what
#: was queued meanwhile one after the other: the acquisition thread wakes about twice a batch,
#: not once a sample or frame (a wake-up costs more CPU than a frame's decoding:
#: benchmarks/bench_canopen.py, "live bus"). Time stamps are the source's; a sample is
#: delivered at most this much later. 0: no batches.
BATCH_S = 0.1

#: a receive that took longer than this [s] waited: the read had caught up with the source
WAITED_S = 0.001


class QueuedDriver(Driver):
    """A driver whose own thread hands complete samples to :meth:`read` through a queue (the
    Modbus and OPC UA drivers): the read with its deadline, the oldest sample dropped for a
    reader that falls behind, the jittered reconnect delay and an outage's bookkeeping (the
    first failure at ERROR, the rest at DEBUG, the recovery at WARNING).

    Subclasses call :meth:`_init_queue` from their constructor and set
    :attr:`~Driver.driver_name`.
    """

    def _init_queue(self, maxsize: int) -> None:
        self._queue: queue.Queue[Sample] = queue.Queue(maxsize=maxsize)
        self._stop = threading.Event()
        self._fatal: str | None = None
        self._down_since: float | None = None
        self._last_error = ""
        self._rng = random.Random()

    def _read_internal(self, timeout: float | None) -> Sample | None:
        start = time.monotonic()
        deadline = None if timeout is None else start + max(timeout, 0.0)
        if self._batch_nap(timeout, self._stop.wait):
            start = time.monotonic()
        while True:
            if self._fatal is not None:
                raise DriverOperationError(self._fatal)
            remaining = 0.1 if deadline is None else min(0.1, deadline - time.monotonic())
            try:
                if remaining <= 0:
                    return self._queue.get_nowait()
                sample = self._queue.get(timeout=remaining)
                self._caught_up = self.live and self._waited_since(start)
                return sample
            except queue.Empty:
                if deadline is not None and time.monotonic() >= deadline:
                    if self._fatal is not None:
                        raise DriverOperationError(self._fatal) from None
                    return None

    def _put_dropping_oldest(self, sample: Sample) -> None:
        """Queue ``sample``; a full queue (a reader that does not read) loses its oldest one
        (``stats.extra["dropped"]``)."""
        try:
            self._queue.put_nowait(sample)
        except queue.Full:
            with contextlib.suppress(queue.Empty):  # the reader just emptied it
                self._queue.get_nowait()
            self.stats.extra["dropped"] += 1
            self.log_once("dropped", "%s driver: %d samples not read; dropping the oldest "
                          "(stats.extra.dropped)", self.driver_name, self._queue.maxsize)
            self._queue.put_nowait(sample)

    def _jittered(self, backoff: float) -> float:
        return backoff * (0.5 + 0.5 * self._rng.random())

    def _outage(self, reason: str, first: str, *args: object, again: str) -> None:
        """A failure: counted in ``stats.errors``; the first of an outage starts it
        (``stats.extra["outages"]``) and is logged at ERROR (``first % args``), the others at
        DEBUG (``again``)."""
        self.stats.errors += 1
        self._last_error = reason
        log = logging.getLogger(type(self).__module__)
        if self._down_since is None:
            self._down_since = time.monotonic()
            self.stats.extra["outages"] += 1
            log.error(first, *args)
        else:
            log.debug("%s", again)

    def _recovered(self) -> float | None:
        """The outage's duration [s] when one has ended (``stats.extra["reconnects"]``), else
        None."""
        if self._down_since is None:
            return None
        down = time.monotonic() - self._down_since
        self._down_since = None
        self.stats.extra["reconnects"] += 1
        return down


InnerT = TypeVar("InnerT", bound=Driver)


class PlantDriver(Driver):
    """A driver over a simulated plant of its own (its table's ``plant``), read through one of
    the real drivers (:meth:`_open_inner`), whose counters are this driver's: the plant's sample
    period and duration, its time starting over at every open.

    Subclasses set :attr:`driver_name` and implement ``__init__(config)`` (calling this one's,
    then :meth:`_open_inner`). Closing closes the inner driver, stops :attr:`server` and shuts
    the virtual buses of :meth:`_virtual_pair` down.

    Args:
        config: the validated table (its ``plant`` has the ``sample_period`` [s]).
        live: the plant runs in real time (:attr:`Driver.live`).
    """

    driver_name: ClassVar[str] = "simulated"
    #: what serves the plant (a Modbus device, an OPC UA server: ``start``, ``stop``, ``port``)
    server: Any = None

    def __init__(self, config: Any, *, live: bool) -> None:
        super().__init__()
        self.config = config
        self.sample_period = config.plant.sample_period
        self.live = live
        self._t0_wall: float | None = None  # monotonic time of plant time 0 (real time)
        self._inner_driver: Driver | None = None
        self._buses: list[Any] = []  # the virtual buses opened (shut down on close)

    def _open_inner(self, open_inner: Callable[[], InnerT], failure: str) -> InnerT:
        """Open the real driver that reads the plant and take over its channels and counters.

        Args:
            open_inner: opens what serves the plant and the driver reading it; returns the
                driver.
            failure: the message when it fails, ``{exc}`` standing for the error.

        Raises:
            DriverInitializationError: it failed (whatever opened is closed first).
        """
        try:
            inner = open_inner()
            inner.batches = False  # it reads what the plant has just served
        except Exception as exc:
            self.close()
            if isinstance(exc, DriverInitializationError):
                raise
            raise DriverInitializationError(failure.format(exc=exc)) from exc
        self.channels = inner.channels
        self.stats = inner.stats
        self._inner_driver = inner
        return inner

    def _virtual_pair(self, channel: str, **tx_options: Any) -> tuple[Any, Any]:
        """(receiving, sending) python-can ``virtual`` buses on ``channel``, shut down on
        close."""
        import can

        for options in ({}, tx_options):
            self._buses.append(can.Bus(interface="virtual", channel=channel, **options))
        return self._buses[-2], self._buses[-1]

    @property
    def port(self) -> int:
        """The TCP port the simulated server listens on."""
        return int(self.server.port)

    def _pace(self, t: float) -> None:
        """Wait until plant time ``t`` [s] is due on the wall clock (real-time pacing: the
        first call ties plant time 0 to the wall clock)."""
        if self._t0_wall is None:
            self._t0_wall = time.monotonic() - t
        delay = self._t0_wall + t - time.monotonic()
        if delay > 0:
            time.sleep(delay)

    @classmethod
    def nominal_sample_period(cls, config: DriverConfig) -> float | None:
        """The plant's sample period [s]."""
        return float(config.plant.sample_period)  # type: ignore[attr-defined]

    @classmethod
    def duration(cls, config: DriverConfig) -> float | None:
        """The plant's duration [s of plant time]."""
        return float(config.plant.duration)  # type: ignore[attr-defined]

    @classmethod
    def time_starts_over(cls, config: DriverConfig) -> bool:
        """The plant starts from t = 0 at every open: a new run."""
        return True

    @classmethod
    def from_config(cls, config: Any, *, base_dir: Path | None = None) -> Self:
        """As :meth:`Driver.from_config`; a plant has no file: ``base_dir`` is not used."""
        return cls(validated_config(cls.config_class, config, cls.driver_name))  # type: ignore[call-arg]

    # what the real driver reports of its source, reported as the simulated plant's
    @property
    def waiting(self) -> str | None:
        inner = self._inner_driver
        return None if inner is None else inner.waiting

    @property
    def silent(self) -> tuple[str, ...]:
        inner = self._inner_driver
        return () if inner is None else inner.silent

    @property
    def device_faults(self) -> tuple[str, ...]:
        inner = self._inner_driver
        return () if inner is None else inner.device_faults

    def _close_internal(self) -> None:
        if self._inner_driver is not None:
            self._inner_driver.close()
        if self.server is not None:
            self.server.stop()
        for bus in self._buses:
            bus.shutdown()

    def _take(self, timeout: float) -> Sample | None:
        """The inner driver's next sample within ``timeout`` [s], counted once (by this
        driver's :meth:`read`)."""
        inner = self._inner_driver
        assert inner is not None
        sample = inner.read(timeout=timeout)
        if sample is not None:
            self.stats.samples -= 1  # counted again by Driver.read of this driver
        return sample
