"""The frame plumbing the CAN bus drivers share (DBC-decoded CAN, CANopen): where frames come
from, how a read waits for them, and what a sample counter or a silent message means.

:class:`BusDriverConfig` holds the keys both drivers' tables share; :class:`BusSource` and
:class:`LogSource` deliver frames; :class:`BusDriver` opens the source, reads within a
deadline, gives up a live bus without a frame for ``reopen_after`` seconds and names the
messages not received for ``silent_after`` seconds. A driver adds what its frames mean
(:meth:`BusDriver._setup`, :meth:`BusDriver._on_frame`).

Nothing here sends: a driver builds no network object and never calls ``send`` on its bus.
"""

from __future__ import annotations

import difflib
import logging
import socket
import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, Self

from pydantic import Field, StrictFloat, StrictInt, field_validator

from twinwatch.drivers.base import (
    Driver,
    DriverConfig,
    DriverConfigError,
    DriverInitializationError,
    DriverOperationError,
    EndOfStream,
    Sample,
    validated_config,
)

if TYPE_CHECKING:  # imported when a source opens: validating a config loads no CAN stack
    import can

__all__ = ["BusDriver", "BusDriverConfig", "BusSource", "FrameSource", "LogSource"]

#: frames read(timeout) still processes, without waiting, once its timeout has run out
_MAX_OVERTIME_FRAMES = 1000

#: share of a receive's wall time spent on the processor beyond which a bus that returned no
#: frame counts as spinning on a closed connection
_SPIN_CPU = 0.3
#: a text log with more malformed lines than this is refused as not a CAN log at all
_MAX_BAD_LINES = 1000

class BusDriverConfig(DriverConfig):
    """The keys of a python-can bus or a log replay, shared by the CAN bus drivers' tables
    (each driver's class documents them for its own table)."""

    interface: str | None = None
    channel: str | StrictInt | None = None
    bitrate: StrictInt | None = Field(default=None, gt=0)
    bus_options: dict[str, str | int | float | bool] = Field(default_factory=dict)
    log_file: Path | None = None
    realtime: bool = False
    sample_period: StrictFloat = Field(gt=0, allow_inf_nan=False)
    reopen_after: StrictFloat | None = Field(2.0, gt=0, allow_inf_nan=False)
    silent_after: StrictFloat = Field(1.0, gt=0, allow_inf_nan=False)

    @field_validator("interface")
    @classmethod
    def _known_interface(cls, value: str | None) -> str | None:
        import can

        known = sorted(can.interfaces.VALID_INTERFACES)
        if value is not None and value not in known:
            close = difflib.get_close_matches(value, known, 1)
            hint = f"did you mean {close[0]!r}?" if close else "known: " + ", ".join(known)
            raise ValueError(f"python-can has no interface {value!r}; {hint}")
        return value

    def twin_channels(self) -> tuple[str, ...]:
        """The twin channels the driver delivers (each driver's table maps them)."""
        raise NotImplementedError


# -- frame sources ------------------------------------------------------------------------


class FrameSource(Protocol):
    """Where a driver's frames come from: :meth:`recv` waits at most ``timeout`` [s]."""

    def recv(self, timeout: float | None) -> can.Message | None: ...

    def close(self) -> None: ...


class BusSource:
    """A python-can bus: the driver's own (``owned``: shut down on close) or one it was given."""

    def __init__(self, bus: can.BusABC, *, owned: bool) -> None:
        import can

        self.bus = bus
        self.owned = owned
        self._errors = (can.CanError, OSError)

    def recv(self, timeout: float | None) -> can.Message | None:
        """The next frame, or None after ``timeout`` [s].

        Raises:
            DriverOperationError: the receive failed, or an owned bus returned nothing without
                waiting (its connection is closed).
        """
        watch = bool(timeout) and self.owned
        try:
            # A bus whose connection is closed may spin instead of waiting (python-can's
            # socketcand bus, a full core): a wait that burnt the processor is given up. Only
            # a wait is timed (the clocks cost more than a frame): a frame queued comes first.
            frame = self.bus.recv(0.0 if watch else timeout)
            if frame is not None or not watch:
                return frame
            start, cpu = time.monotonic(), time.thread_time()
            frame = self.bus.recv(timeout)
        except self._errors as exc:
            raise DriverOperationError(
                f"CAN receive failed on {self.bus.channel_info}: {exc}"
            ) from exc
        if frame is None:
            wall = time.monotonic() - start
            if wall >= 0.04 and time.thread_time() - cpu > _SPIN_CPU * wall:
                raise DriverOperationError(
                    f"the CAN interface {self.bus.channel_info} returns no frame without "
                    f"waiting (its connection is closed)")
        return frame

    def close(self) -> None:
        if self.owned:
            self.bus.shutdown()


class _Lines:
    """The lines of a text log, as the file object a python-can text reader iterates,
    counting the lines handed out (``lineno``, 1-based)."""

    def __init__(self, path: Path) -> None:
        self._file = path.open(encoding="utf-8", errors="replace", newline=None)
        self.lineno = 0
        self._front: list[str] = []

    def __iter__(self) -> _Lines:
        return self

    def push_front(self, line: str) -> None:
        """Hand out ``line`` next (not counted as a line of the file)."""
        self._front.append(line)

    def __next__(self) -> str:
        if self._front:
            return self._front.pop()
        line = next(self._file)
        self.lineno += 1
        return line

    def readline(self) -> str:
        try:
            return next(self)
        except StopIteration:
            return ""

    def close(self) -> None:
        self._file.close()


class LogSource:
    """Frames of a log file, optionally paced by their time stamps (see can.MessageSync).

    The pacing is done here: :class:`can.MessageSync` sleeps inside its iterator and so cannot
    honour ``read(timeout)``.

    A malformed line of a text log (candump ``.log``, ``.asc``, ``.csv``, ``.trc``) is skipped
    and reported through ``on_bad(line, error)``: python-can's readers are generators that end
    at the first parse error, so a new reader takes over at the next line with the old one's
    state (:meth:`_resume`, O(1) per bad line). A binary log (``.blf``, ``.mf4``) cannot be
    resumed after a corrupt block: the error ends the replay with one clear line.
    """

    def __init__(self, path: Path, *, realtime: bool,
                 on_bad: Callable[[int, BaseException], None] | None = None) -> None:
        import can
        from can.io.generic import TextIOMessageReader

        self.path = path
        self.realtime = realtime
        self._on_bad = on_bad
        try:
            self._reader = can.LogReader(path)
        except (OSError, ValueError, ImportError) as exc:
            raise DriverConfigError(f"log_file: cannot read {str(path)!r}: {exc}") from exc
        self._lines: _Lines | None = None
        self._bad_lines = 0
        if isinstance(self._reader, TextIOMessageReader) and path.suffix.lower() != ".gz":
            self._reader.stop()
            self._text_reader: type[TextIOMessageReader] | None = type(self._reader)
            self._lines = _Lines(self.path)
            # _Lines reads as a text file does (python-can's readers ask a TextIO)
            self._reader = self._text_reader(file=self._lines)  # type: ignore[arg-type]
        else:
            self._text_reader = None
        self._frames: Iterator[can.Message] = iter(self._reader)
        self._delivered = 0
        self._pending: can.Message | None = None
        self._origin: tuple[float, float] | None = None  # (wall clock, log time) of 1st frame

    def _resume(self) -> None:
        """Go on reading after a malformed line, at the next line, in O(1): a new reader of
        the same class takes over the old one's state (the header it parsed: an ASC file's
        number base and start time, a TRC file's version and columns) and reads on from the
        current line without parsing a header again (a CSV log's header line is given to it
        as a placeholder it skips)."""
        import can

        assert self._lines is not None and self._text_reader is not None
        old = self._reader
        new = object.__new__(type(old))
        new.__dict__.update(old.__dict__)
        new.file = self._lines  # type: ignore[attr-defined]
        if hasattr(new, "_extract_header"):  # ASC, TRC: the header is in the state copied
            new._extract_header = lambda: None
        if isinstance(old, can.CSVReader):  # its __iter__ skips one header line first
            self._lines.push_front("header\n")
        self._reader = new
        self._frames = iter(new)

    def _next_frame(self) -> can.Message:
        import can

        while True:
            try:
                frame = next(self._frames)
            except StopIteration:
                raise EndOfStream(f"end of CAN log {str(self.path)!r}") from None
            except (ValueError, IndexError, KeyError, TypeError, OSError, EOFError,
                    can.CanError) as exc:
                if self._lines is None or self._text_reader is None:
                    raise DriverOperationError(
                        f"CAN log {str(self.path)!r} is corrupt after frame {self._delivered} "
                        f"({type(exc).__name__}: {exc}); the rest of it cannot be read"
                    ) from exc
                bad = self._lines.lineno
                self._bad_lines += 1
                if self._bad_lines > _MAX_BAD_LINES:
                    raise DriverOperationError(
                        f"CAN log {str(self.path)!r}: more than {_MAX_BAD_LINES} malformed "
                        f"lines (the last at line {bad}): is it really a "
                        f"{self.path.suffix} CAN log ({self._text_reader.__name__})?"
                    ) from exc
                if self._on_bad is not None:
                    self._on_bad(bad, exc)
                self._resume()
                continue
            self._delivered += 1
            return frame

    def recv(self, timeout: float | None) -> can.Message | None:
        """The next frame of the log; None when pacing (``realtime``) holds it beyond
        ``timeout`` [s].

        Raises:
            EndOfStream: the log has ended.
            DriverOperationError: the rest of the log cannot be read.
        """
        if self._pending is None:
            self._pending = self._next_frame()
        if self.realtime:
            now = time.monotonic()
            if self._origin is None:
                self._origin = (now, self._pending.timestamp)
            wait = self._origin[0] + (self._pending.timestamp - self._origin[1]) - now
            if wait > 0:
                if timeout is not None and wait > timeout:
                    time.sleep(max(timeout, 0.0))
                    return None
                time.sleep(wait)
        frame, self._pending = self._pending, None
        return frame

    def close(self) -> None:
        self._reader.stop()
        if self._lines is not None:
            self._lines.close()


def gateway_address(config: BusDriverConfig) -> tuple[str, int] | None:
    """(host, port) of a TCP gateway interface (python-can's ``socketcand``), else None."""
    if config.interface != "socketcand":
        return None
    host, port = config.bus_options.get("host"), config.bus_options.get("port")
    if not isinstance(host, str) or not isinstance(port, int) or isinstance(port, bool):
        return None
    return host, port


def _reach_gateway(config: BusDriverConfig, timeout: float = 2.0) -> None:
    """Fail at once, with one line, when a TCP gateway does not accept a connection: python-
    can's socketcand bus would retry for 10 s in a busy loop, logging each attempt.

    Raises:
        DriverInitializationError: the gateway refused or did not answer.
    """
    address = gateway_address(config)
    if address is None:
        return
    try:
        with socket.create_connection(address, timeout=timeout):
            pass
    except OSError as exc:
        raise DriverInitializationError(
            f"cannot reach the {config.interface} gateway at {address[0]}:{address[1]} "
            f"(channel {config.channel!r}): {exc}") from exc


def _receive_only(bus: can.BusABC) -> bool:
    """Put a bus in receive-only (listen-only, passive) mode where python-can's interface
    allows it; True if it did. twinwatch never calls ``send`` either way."""
    import can

    try:
        bus.state = can.BusState.PASSIVE
    except (NotImplementedError, can.CanError, OSError, AttributeError, ValueError):
        return False
    return True


# -- the driver ---------------------------------------------------------------------------


class BusDriver(Driver):
    """What a CAN bus driver does whatever its frames mean: opens its source, waits for frames
    within a read's timeout, gives up a silent live bus, counts a sample counter's steps and
    names the messages gone silent.

    Args:
        config: the validated configuration (a :class:`BusDriverConfig`).
        bus: an already open python-can bus to listen on (a simulated plant's ``virtual``
            bus); the driver never shuts it down. When given, ``interface``, ``channel``,
            ``bitrate`` and ``bus_options`` are ignored.
        base_dir: as for :meth:`Driver.from_config`.
        listen_only: put a live interface in receive-only mode (``check-config``).

    A subclass sets :attr:`~Driver.driver_name`, implements :meth:`_setup` (what to decode),
    :meth:`_on_frame` (one frame, maybe a sample), :meth:`_can_filters` and :meth:`_ready`.
    """

    driver_name: ClassVar[str] = "CAN"
    config: BusDriverConfig

    @classmethod
    def safe_to_probe(cls, config: DriverConfig) -> bool:
        """A log replay can be opened; a live bus is probed receive-only (:meth:`probe`)."""
        return getattr(config, "log_file", None) is not None

    @classmethod
    def probe(cls, config: DriverConfig, *, base_dir: Path | None = None) -> str | None:
        """``check-config``: the source opened (a live interface receive-only where
        python-can allows it) and closed, nothing sent; what its description file says.

        Raises:
            DriverError: the description file, a channel, the log or the interface.
        """
        assert isinstance(config, BusDriverConfig)
        with cls(config, base_dir=base_dir, listen_only=config.log_file is None) as driver:
            if config.log_file is not None:
                return f"log {str(driver.config.log_file)!r} opened{driver._probed(False)}"
            mode = ("receive-only" if driver.receive_only else "this interface has no "
                    "receive-only mode; twinwatch never sends")
            return f"{cls.describe(config)} opened ({mode}){driver._probed(True)}"

    @classmethod
    def reopens(cls, config: DriverConfig) -> bool:
        """A live bus (no ``log_file``) may come and go: waited for and reopened."""
        return getattr(config, "log_file", None) is None

    @classmethod
    def time_starts_over(cls, config: DriverConfig) -> bool:
        """A log replayed from its start is a new run; a live bus goes on."""
        return getattr(config, "log_file", None) is not None

    @classmethod
    def from_config(cls, config: Any, *, base_dir: Path | None = None,
                    bus: can.BusABC | None = None) -> Self:
        """As :meth:`Driver.from_config`, and ``bus``: see the class."""
        return cls(validated_config(cls.config_class, config, cls.driver_name), bus=bus,
                   base_dir=base_dir)

    def __init__(self, config: BusDriverConfig, *, bus: can.BusABC | None = None,
                 base_dir: Path | None = None, listen_only: bool = False) -> None:
        super().__init__()
        self._source: FrameSource | None = None
        self._listen_only = listen_only
        #: the bus was put in receive-only mode (``listen_only`` and the interface allows it)
        self.receive_only = False
        self._log = logging.getLogger(type(self).__module__)
        self._latest: dict[str, float] = {}  # each channel's latest value
        self._seen: dict[str, float] = {}  # each message's last frame time [s]
        self._first_stamp: float | None = None
        self._silent: tuple[str, ...] = ()
        self._silent_logged: set[str] = set()
        try:
            self.config = config = config.resolved(base_dir)
            self.channels = config.twin_channels()
            self.sample_period = config.sample_period
            self._setup(config)
            self._last_frame_wall = time.monotonic()
            self._source = source = self._open_source(config, bus)
            opened = isinstance(source, BusSource) and source.owned
            self._watch_silence = opened and config.reopen_after is not None
            # An interface the driver opened, or a log paced in real time, delivers frames
            # whatever the estimation does: windows it delivers while the worker is behind
            # are dropped and counted as overruns, not waited for (the interface's receive
            # queue would overflow and lose frames). A bus passed in is a simulated plant's.
            self.live = opened or (config.log_file is not None and config.realtime)
            self._ready()
        except BaseException:
            self.close()
            raise

    # -- for subclasses -------------------------------------------------------------------------
    def _setup(self, config: Any) -> None:
        """Read the description file and prepare the decoding (before the source opens)."""
        raise NotImplementedError

    def _ready(self) -> None:
        """Log the one INFO line that says what the driver listens to."""

    def _can_filters(self) -> list[dict[str, Any]]:
        """The receive filters of a live bus the driver opens (python-can's ``can_filters``)."""
        raise NotImplementedError

    def _probed(self, live: bool) -> str:
        """What :meth:`probe` adds after ``opened`` (``live``: an interface, not a log)."""
        return ""

    def _on_frame(self, frame: can.Message) -> Sample | None:
        """Account for one frame; a sample when it completes one."""
        raise NotImplementedError

    # -- the source -----------------------------------------------------------------------------
    def _open_source(self, config: BusDriverConfig, bus: can.BusABC | None) -> FrameSource:
        if bus is not None:
            if config.log_file is not None:
                raise DriverConfigError("log_file and a bus were both given; pick one")
            return BusSource(bus, owned=False)
        if config.log_file is not None:
            return LogSource(config.log_file, realtime=config.realtime, on_bad=self._on_bad_line)
        if config.interface is None or config.channel is None:
            raise DriverConfigError(
                "interface and channel are required for a live bus (or give log_file)")
        import can

        kwargs: dict[str, Any] = dict(config.bus_options)
        if config.bitrate is not None:
            kwargs["bitrate"] = config.bitrate
        # Only the frames we decode reach us (filtered in the kernel/adapter where possible).
        kwargs.setdefault("can_filters", self._can_filters())
        _reach_gateway(config)
        try:
            opened = can.Bus(interface=config.interface, channel=config.channel, **kwargs)
        except (can.CanError, ImportError, OSError, ValueError, TypeError) as exc:
            raise DriverInitializationError(
                f"cannot open CAN interface {config.interface!r} channel {config.channel!r}: "
                f"{exc}") from exc
        if self._listen_only:
            self.receive_only = _receive_only(opened)
        return BusSource(opened, owned=True)

    # -- reading --------------------------------------------------------------------------------
    def _read_internal(self, timeout: float | None) -> Sample | None:
        source = self._source
        if source is None:  # pragma: no cover - only after a failed construction
            raise DriverOperationError(f"{self.driver_name} driver has no frame source")
        # Frames already received are processed even once the timeout has run out (read(0)
        # returns a sample complete in the queue), but at most _MAX_OVERTIME_FRAMES of them.
        deadline = None if timeout is None else time.monotonic() + max(timeout, 0.0)
        overtime = 0
        while True:
            start = time.monotonic()
            remaining = None if deadline is None else max(0.0, deadline - start)
            if self._batch_nap(remaining, time.sleep):  # a batch of frames came meanwhile
                start = time.monotonic()
                remaining = None if deadline is None else max(0.0, deadline - start)
            if self._watch_silence and remaining is None:
                remaining = 1.0  # a silent bus must not hold a read(None) beyond reopen_after
            frame = source.recv(remaining)
            if frame is None:
                self._check_silence()
                if deadline is None:
                    continue
                return None
            self._caught_up = self._waited_since(start)
            self._last_frame_wall = time.monotonic()
            self.stats.frames += 1
            sample = self._on_frame(frame)
            if sample is not None:
                return sample
            if remaining == 0.0:
                overtime += 1
                if overtime >= _MAX_OVERTIME_FRAMES:
                    return None

    def _check_silence(self) -> None:
        """Give up a live bus that has delivered no frame for ``reopen_after`` seconds.

        Raises:
            DriverOperationError: so that the daemon closes it and opens it again.
        """
        if not self._watch_silence:
            return
        quiet = time.monotonic() - self._last_frame_wall
        assert self.config.reopen_after is not None
        if quiet > self.config.reopen_after:
            raise DriverOperationError(
                f"no CAN frame for {quiet:.1f} s ({self.describe(self.config)}): the bus is "
                "silent, the interface down or the gateway's connection closed")

    def _on_bad_line(self, line: int, exc: BaseException) -> None:
        self.stats.frames += 1
        self.stats.bad_frames += 1
        self.log_once("log-line", "CAN log line %d is malformed (%s: %s): skipped, counted in "
                      "stats.bad_frames; the replay goes on", line, type(exc).__name__, exc)

    def _silent_since(self, now: float, watched: Mapping[str, list[str]], *, what: str,
                      key: str, quiet: Callable[[float], bool] | None = None,
                      ) -> tuple[list[str], set[str]]:
        """Which of ``watched`` (a message's name -> its channels) have not been received for
        ``silent_after`` seconds of frame time at ``now`` [s], and their channels. Each newly
        silent one counts in ``stats.extra[key]`` and is logged (``what`` names it; at DEBUG
        when ``quiet(age)``), and logged again when it is back.

        Returns:
            (``"NAME (channels) for 3.1 s"`` per silent one, their channels).
        """
        assert self._first_stamp is not None
        limit = self.config.silent_after
        silent, gone = [], set()
        for name, chans in watched.items():
            age = now - self._seen.get(name, self._first_stamp)
            if age > limit:
                silent.append(f"{name} ({', '.join(chans)}) for {age:.1f} s")
                gone.update(chans)
                if name not in self._silent_logged:
                    self._silent_logged.add(name)
                    self._bump(key)
                    log = self._log.debug if quiet is not None and quiet(age) else \
                        self._log.warning
                    log("%s %s (channels %s) not received for %.1f s (silent_after %g s): its "
                        "channels are left out of the samples until it is back", what, name,
                        ", ".join(chans), age, limit)
            elif name in self._silent_logged:
                self._silent_logged.discard(name)
                self._log.warning("%s %s is received again", what, name)
        return silent, gone

    @property
    def silent(self) -> tuple[str, ...]:
        """The messages (CANopen: held PDOs; the drive's heartbeat when missing) not received
        for ``silent_after`` seconds of frame time, with their channels and how long."""
        return self._silent

    def _close_internal(self) -> None:
        source, self._source = self._source, None
        if source is not None:
            source.close()
            self._log.debug("%s driver closed (%s)", self.driver_name, self.stats.as_dict())
