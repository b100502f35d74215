"""CAN bus driver: decode DBC signals from a live bus or a log file into twin samples.

The driver listens to a python-can bus (``socketcan``, ``pcan``, ``virtual``, ...) or replays a
log file through :func:`can.LogReader` (candump ``.log``, ``.asc``, ``.blf``, ``.trc``, ...),
decodes the frames it needs with a DBC loaded by cantools, and emits one :class:`Sample` each
time the configured *sync message* arrives. The sample holds the latest value of every mapped
signal (sample-and-hold: signals sent at a lower rate than the sync message keep their last
value), converted to the twin's unit as ``value_twin = value_dbc * scale + offset``.

The driver never transmits: it does not even call ``send``. It shuts down a bus it opened
itself and leaves alone a bus it was given (``CanDriver(config, bus=...)``), so a simulated
plant can share an in-process ``virtual`` bus with it.

Bad input is counted, logged once, and skipped (see :class:`~twinwatch.drivers.base.DriverStats`):

* frames whose id is not needed (not in the DBC, or not mapped) count in ``stats.frames`` only;
* frames of needed messages that cannot be decoded (too short, unknown multiplexer value, ...)
  count in ``stats.bad_frames``; frames *longer* than the DBC says are decoded (padding is
  common) and logged once;
* NaN or infinite decoded values count in ``stats.bad_values`` and are delivered as they are;
* the sample counter (:class:`~twinwatch.io.counter.SampleCounter`, unwrapped): a jump of
  ``n > 1`` adds ``n - 1`` to ``stats.gaps``; a repeated value (a duplicated frame) or one a
  few steps back (a late frame a gateway reordered) skips that sample without losing the count
  (``stats.extra["duplicates"]``, ``["reordered"]``); a counter that goes further back (the
  source restarted) counts in ``stats.extra["counter_resets"]`` and its clock restarts;
* error frames and remote (RTR) frames count in ``stats.extra["error_frames"]`` /
  ``stats.extra["remote_frames"]`` (ODrive masters poll with RTR frames: they are normal);
* a sync message that arrives before every mapped signal has been seen once produces no sample
  and counts in ``stats.extra["incomplete_syncs"]`` (the start-up transient);
* a malformed line of a text log (candump ``.log``, ``.asc``, ``.csv``, ``.trc``) is skipped
  and counts in ``stats.frames`` and ``stats.bad_frames``; the replay goes on.

Example configuration (TOML, the ``[driver]`` table of a machine config)::

    [driver]
    type = "can"
    interface = "socketcan"
    channel = "can0"
    dbc = "dcmotor.dbc"                   # relative to the config file's directory
    sync_message = "TW_Motor_Sample"
    time_source = "counter"               # t = sample_counter * sample_period
    counter_signal = "TW_Motor_Sample.sample_counter"
    sample_period = 0.01
    [driver.signals]
    Va = { message = "TW_Motor_Electrical", signal = "Va", unit = "V" }
    omega = { message = "TW_Motor_Mechanical", signal = "omega", unit = "rad/s" }
"""

from __future__ import annotations

import difflib
import logging
import math
import socket
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol

import can
import cantools
import cantools.database
from can.io.generic import TextIOMessageReader
from cantools.database.can import Database
from cantools.database.can import Message as DbcMessage
from cantools.database.errors import DecodeError
from cantools.database.errors import Error as CantoolsError
from pydantic import ConfigDict, Field, StrictFloat, StrictInt, field_validator, model_validator

from twinwatch.drivers.base import (
    Driver,
    DriverConfig,
    DriverConfigError,
    DriverInitializationError,
    DriverOperationError,
    EndOfStream,
    Sample,
    ScaledChannel,
    validated_config,
)
from twinwatch.io.counter import SampleCounter

logger = logging.getLogger(__name__)

__all__ = ["CanDriver", "CanDriverConfig", "CanSignalMap"]

_TIME_SIGNAL_PREFIX = "signal:"
#: frames read(timeout) still processes, without waiting, once its timeout has run out
_MAX_OVERTIME_FRAMES = 1000
#: share of a receive's wall time spent on the processor beyond which a bus that returned no
#: frame counts as spinning on a closed connection
_SPIN_CPU = 0.3


def _split_signal_ref(ref: str) -> tuple[str, str]:
    """Split ``"MESSAGE.SIGNAL"`` into its two names (DBC names cannot contain dots)."""
    parts = ref.split(".")
    if len(parts) != 2 or not all(parts):
        raise ValueError(f"expected 'MESSAGE.SIGNAL', got {ref!r}")
    return parts[0], parts[1]


class CanSignalMap(ScaledChannel):
    """Where one twin channel comes from: ``value_twin = value_dbc * scale + offset``.

    ``value_dbc`` is the physical value cantools decodes (DBC factor and offset applied), in the
    DBC's unit; ``unit`` documents the twin-side unit and is not used for computation.
    """

    message: str = Field(min_length=1)
    signal: str = Field(min_length=1)


class CanDriverConfig(DriverConfig):
    """Configuration of :class:`CanDriver` (the ``[driver]`` table with ``type = "can"``).

    Attributes:
        type: always ``"can"``.
        interface: python-can interface name (``"socketcan"``, ``"pcan"``, ``"virtual"``, ...).
            Required for a live bus; ignored with ``log_file`` or when a bus is passed in.
        channel: python-can channel (``"can0"``, ``"PCAN_USBBUS1"``, ``0``, ...).
        bitrate: bus bit rate [bit/s]; None leaves the interface's setting alone.
        bus_options: extra keyword arguments for :class:`can.Bus` (e.g. ``fd = true``).
        dbc: path of the CAN database (DBC, or any format cantools loads); a relative path is
            resolved against the configuration file's directory (``base_dir``).
        log_file: replay this log (any suffix :func:`can.LogReader` knows) instead of a live
            bus; relative to ``base_dir`` like ``dbc`` (either may be ``twinwatch:<path>``, a
            file shipped in the package: :data:`PACKAGE_PREFIX`). The end of the log raises
            :class:`~twinwatch.drivers.base.EndOfStream`.
        realtime: for ``log_file`` only: pace the replay by the log's time stamps (as
            :class:`can.MessageSync` does); False replays as fast as the caller reads.
        sync_message: DBC message whose arrival emits one sample.
        time_source: ``"frame"``: t [s] is the sync frame's time stamp (bus or log clock);
            ``"counter"``: t = ``counter_signal`` * ``sample_period`` (the plant's clock);
            ``"signal:MESSAGE.SIGNAL"``: t is that signal's latest value, in seconds.
        counter_signal: ``"MESSAGE.SIGNAL"`` of a sample counter (+1 per sample). Optional;
            when given, counter jumps are counted in ``stats.gaps``.
        sample_period: nominal sample period [s] (> 0).
        signals: twin channel name -> :class:`CanSignalMap`, at least one. The order of the
            table is the order of :attr:`CanDriver.channels`.
        reopen_after: a live bus the driver opened that delivers no frame at all for this many
            seconds [s, wall] is given up (:class:`DriverOperationError`), so the daemon
            closes it and opens it again with backoff (a gateway that dropped the connection,
            an interface gone bus-off or down); None: never. Default 2 s.
        silent_after: a mapped message not received for this many seconds of the frames' own
            time [s] while the sync message goes on is *silent* (the node that sends it is
            down): it is named (:attr:`CanDriver.silent`, STATUS, the health message) and its
            channels are left out of the samples until it is back, never held. Default 1 s;
            raise it for a message sent more slowly than that.
    """

    model_config = ConfigDict(extra="forbid")

    type: Literal["can"]
    interface: str | None = None
    channel: str | StrictInt | None = None
    bitrate: StrictInt | None = Field(default=None, gt=0)
    bus_options: dict[str, str | int | float | bool] = Field(default_factory=dict)
    dbc: Path
    log_file: Path | None = None
    realtime: bool = False
    sync_message: str = Field(min_length=1)
    time_source: str = "frame"
    counter_signal: str | None = None
    sample_period: StrictFloat = Field(gt=0, allow_inf_nan=False)
    signals: dict[str, CanSignalMap] = Field(min_length=1)
    reopen_after: StrictFloat | None = Field(2.0, gt=0, allow_inf_nan=False)
    silent_after: StrictFloat = Field(1.0, gt=0, allow_inf_nan=False)

    @field_validator("interface")
    @classmethod
    def _known_interface(cls, value: str | None) -> str | None:
        if value is not None and value not in can.interfaces.VALID_INTERFACES:
            close = difflib.get_close_matches(value, sorted(can.interfaces.VALID_INTERFACES), 1)
            hint = (
                f"did you mean {close[0]!r}?"
                if close
                else "known: " + ", ".join(sorted(can.interfaces.VALID_INTERFACES))
            )
            raise ValueError(f"python-can has no interface {value!r}; {hint}")
        return value

    @field_validator("counter_signal")
    @classmethod
    def _counter_ref(cls, value: str | None) -> str | None:
        if value is not None:
            _split_signal_ref(value)
        return value

    @field_validator("time_source")
    @classmethod
    def _time_source_syntax(cls, value: str) -> str:
        if value in ("frame", "counter"):
            return value
        if value.startswith(_TIME_SIGNAL_PREFIX):
            _split_signal_ref(value.removeprefix(_TIME_SIGNAL_PREFIX))
            return value
        raise ValueError(f"expected 'frame', 'counter' or 'signal:MESSAGE.SIGNAL', got {value!r}")

    @model_validator(mode="after")
    def _counter_needed(self) -> CanDriverConfig:
        if self.time_source == "counter" and self.counter_signal is None:
            raise ValueError("time_source = 'counter' needs counter_signal = 'MESSAGE.SIGNAL'")
        return self

    def twin_channels(self) -> tuple[str, ...]:
        """The twin channels this driver delivers (``signals``)."""
        return tuple(self.signals)

    def required_files(self, base_dir: Path) -> dict[str, Path]:
        """Config key -> file that must exist to start (``dbc``, ``log_file``)."""
        cfg = self.resolved(base_dir)
        files = {"driver.dbc": cfg.dbc}
        if cfg.log_file is not None:
            files["driver.log_file"] = cfg.log_file
        return files

    def resolved(self, base_dir: Path | None) -> CanDriverConfig:
        """Return a copy whose relative ``dbc`` and ``log_file`` are joined to ``base_dir``."""
        if base_dir is None:
            return self
        update: dict[str, Path] = {"dbc": _resolve(self.dbc, base_dir)}
        if self.log_file is not None:
            update["log_file"] = _resolve(self.log_file, base_dir)
        return self.model_copy(update=update)


PACKAGE_PREFIX = "twinwatch:"
"""A ``dbc`` or ``log_file`` written ``twinwatch:plant/odrive-axis0.log.gz`` is a file shipped
inside the installed twinwatch package (``twinwatch/plant/...``): found wherever the
configuration file is copied (a gateway's directory, /etc/twinwatch), unlike a path relative
to the file."""


def _resolve(path: Path, base_dir: Path) -> Path:
    """``path`` as the driver opens it: a file of the package (:data:`PACKAGE_PREFIX`), or
    ``~`` expanded and a relative path joined to ``base_dir`` (the config file's directory)."""
    text = str(path)
    if text.startswith(PACKAGE_PREFIX):
        import twinwatch

        return Path(twinwatch.__file__).resolve().parent / text[len(PACKAGE_PREFIX):]
    path = path.expanduser()
    return path if path.is_absolute() else Path(base_dir) / path


# -- decoding plan ------------------------------------------------------------------------


@dataclass(slots=True)
class _MessagePlan:
    """What to do with one needed DBC message when its frame arrives."""

    message: DbcMessage
    #: (twin channel, DBC signal, scale, offset)
    channels: list[tuple[str, str, float, float]] = field(default_factory=list)
    counter_signal: str | None = None
    time_signal: str | None = None
    is_sync: bool = False


def _as_float(raw: object) -> float:
    """A decoded signal value as float (NaN for anything that is not a number)."""
    return float(raw) if isinstance(raw, int | float) else math.nan


def _did_you_mean(name: str, available: Iterable[str], *, what: str, limit: int = 20) -> str:
    """``"did you mean 'X'? available: ..."`` for an error message (the list only if short)."""
    names = sorted(set(available))
    by_lower = {n.lower(): n for n in names}
    close = difflib.get_close_matches(name.lower(), list(by_lower), n=1)
    hint = f"did you mean {by_lower[close[0]]!r}? " if close else ""
    if not names:
        return hint + f"the DBC defines no {what}"
    if len(names) <= limit:
        return hint + f"available {what}: " + ", ".join(names)
    return hint + f"the DBC defines {len(names)} {what} (list them with `cantools dump`)"


def _find_signal(db: Database, key: str, message_name: str, signal_name: str | None) -> DbcMessage:
    """Return the DBC message, checking that it (and ``signal_name``) exist; ``key`` names
    the configuration entry in the error."""
    try:
        message = db.get_message_by_name(message_name)
    except KeyError:
        hint = _did_you_mean(message_name, (m.name for m in db.messages), what="messages")
        raise DriverConfigError(
            f"{key}: message {message_name!r} not in DBC; {hint}"
        ) from None
    if signal_name is not None and signal_name not in {s.name for s in message.signals}:
        hint = _did_you_mean(signal_name, (s.name for s in message.signals), what="signals")
        raise DriverConfigError(
            f"{key}: message {message_name!r} has no signal {signal_name!r}; {hint}"
        )
    return message


# -- frame sources ------------------------------------------------------------------------


class _FrameSource(Protocol):
    def recv(self, timeout: float | None) -> can.Message | None: ...

    def close(self) -> None: ...


class _BusSource:
    def __init__(self, bus: can.BusABC, *, owned: bool) -> None:
        self.bus = bus
        self.owned = owned

    def recv(self, timeout: float | None) -> can.Message | None:
        start, cpu = time.monotonic(), time.thread_time()
        try:
            frame = self.bus.recv(timeout)
        except (can.CanError, OSError) as exc:
            raise DriverOperationError(
                f"CAN receive failed on {self.bus.channel_info}: {exc}"
            ) from exc
        if frame is None and timeout and self.owned:
            # A bus whose connection is closed may spin instead of waiting (python-can's
            # socketcand bus reads an empty string from the closed socket in a loop until the
            # timeout: a full core): a wait that burnt the processor is given up.
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


#: a text log with more malformed lines than this is refused as not a CAN log at all
_MAX_BAD_LINES = 1000


class _LogSource:
    """Frames of a log file, optionally paced by their time stamps (see can.MessageSync).

    The pacing is done here rather than with :class:`can.MessageSync` because MessageSync
    sleeps inside its iterator and so cannot honour ``read(timeout)``.

    A malformed line of a text log (candump ``.log``, ``.asc``, ``.csv``, ``.trc``) is skipped
    and reported through ``on_bad(line, error)``: python-can's readers are generators that end
    at the first parse error, so a new reader takes over at the next line with the old one's
    state (:meth:`_resume`: O(1) per bad line; re-reading from the top made 300 bad lines in
    18,000 cost a quadratic re-read). A binary log (``.blf``, ``.mf4``) cannot be resumed
    after a corrupt block: the error ends the replay with one clear line.
    """

    def __init__(self, path: Path, *, realtime: bool,
                 on_bad: Callable[[int, BaseException], None] | None = None) -> None:
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


def _gateway_address(config: CanDriverConfig) -> tuple[str, int] | None:
    """(host, port) of a TCP gateway interface (python-can's ``socketcand``), else None."""
    if config.interface != "socketcand":
        return None
    host, port = config.bus_options.get("host"), config.bus_options.get("port")
    if not isinstance(host, str) or not isinstance(port, int) or isinstance(port, bool):
        return None
    return host, port


def _reach_gateway(config: CanDriverConfig, timeout: float = 2.0) -> None:
    """Fail at once, with one line, when a TCP gateway does not accept a connection: python-
    can's socketcand bus would retry for 10 s in a loop without a pause, logging each attempt
    (213,729 lines, a full core) before it fails.

    Raises:
        DriverInitializationError: the gateway refused or did not answer.
    """
    address = _gateway_address(config)
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
    try:
        bus.state = can.BusState.PASSIVE
    except (NotImplementedError, can.CanError, OSError, AttributeError, ValueError):
        return False
    return True


# -- the driver ---------------------------------------------------------------------------


class CanDriver(Driver):
    """Twin samples from DBC-decoded CAN frames (live bus or log replay); never transmits.

    Args:
        config: the validated configuration (see :class:`CanDriverConfig`).
        bus: an already open python-can bus to listen on (e.g. a ``virtual`` bus shared with a
            simulated plant). The driver never shuts it down; the caller owns it. When given,
            ``interface``, ``channel``, ``bitrate`` and ``bus_options`` are ignored.
        base_dir: directory that relative ``dbc`` and ``log_file`` paths are resolved against
            (the configuration file's directory); None means the current directory.

    Attributes:
        channels: twin channel names, in the order of ``config.signals``.
        sample_period: ``config.sample_period`` [s].
        database: the loaded cantools database.

    Raises:
        DriverConfigError: the DBC cannot be loaded, a configured message or signal is not in
            it (the message names the config key and the closest names), or the log file
            cannot be opened.
        DriverInitializationError: the bus cannot be opened.
    """

    config_class = CanDriverConfig
    sample_model = "dc_motor"
    sample_machine = "dc-motor-can"
    sample_title = "a DC motor drive on a CAN bus"

    @classmethod
    def safe_to_probe(cls, config: DriverConfig) -> bool:
        """A log replay can be opened to check its DBC names and log file; a live bus not."""
        return getattr(config, "log_file", None) is not None

    @classmethod
    def probe(cls, config: DriverConfig, *, base_dir: Path | None = None) -> str | None:
        """``check-config``: a log replay is opened (its DBC names, the log); a live interface
        is opened receive-only where python-can's interface allows it, never sent on, and
        closed: the DBC is checked and the interface said to be there or not.

        Raises:
            DriverError: the DBC, the log or the interface cannot be opened.
        """
        assert isinstance(config, CanDriverConfig)
        with cls(config, base_dir=base_dir, listen_only=config.log_file is None) as driver:
            if config.log_file is not None:
                return f"log {str(driver.config.log_file)!r} opened"
            mode = ("receive-only" if driver.receive_only else "this interface has no "
                    "receive-only mode; twinwatch never sends")
            return f"{cls.describe(config)} opened ({mode}), DBC {str(driver.config.dbc)!r}"

    @classmethod
    def reopens(cls, config: DriverConfig) -> bool:
        """A live bus (no ``log_file``) may come and go: waited for and reopened."""
        return getattr(config, "log_file", None) is None

    @classmethod
    def describe(cls, config: DriverConfig) -> str:
        """``"CAN interface 'socketcand' channel 'can0' (127.0.0.1:29536)"``, or the log."""
        assert isinstance(config, CanDriverConfig)
        if config.log_file is not None:
            return f"CAN log {str(config.log_file)!r}"
        address = _gateway_address(config)
        where = f" ({address[0]}:{address[1]})" if address else ""
        return f"CAN interface {config.interface!r} channel {config.channel!r}{where}"

    @classmethod
    def time_starts_over(cls, config: DriverConfig) -> bool:
        """A log replayed from its start is a new run; a live bus goes on."""
        return getattr(config, "log_file", None) is not None

    def __init__(
        self,
        config: CanDriverConfig,
        *,
        bus: can.BusABC | None = None,
        base_dir: Path | None = None,
        listen_only: bool = False,
    ) -> None:
        super().__init__()
        self._source: _FrameSource | None = None
        self._listen_only = listen_only
        #: the bus was put in receive-only mode (``listen_only`` and the interface allows it)
        self.receive_only = False
        try:
            self._setup(config.resolved(base_dir), bus)
        except BaseException:
            self.close()
            raise

    @classmethod
    def from_config(
        cls,
        config: CanDriverConfig | Mapping[str, Any],
        *,
        base_dir: Path | None = None,
        bus: can.BusABC | None = None,
    ) -> CanDriver:
        """Build a driver from a validated config or a raw ``[driver]`` table.

        Raises:
            DriverInitializationError: the table does not validate, or see :class:`CanDriver`.
        """
        config = validated_config(CanDriverConfig, config, "CAN")
        return cls(config, bus=bus, base_dir=base_dir)

    # -- construction -----------------------------------------------------------------------
    def _setup(self, config: CanDriverConfig, bus: can.BusABC | None) -> None:
        self.config = config
        self.channels = tuple(config.signals)
        self.sample_period = config.sample_period
        self.database = self._load_dbc(config.dbc)
        self._plans = self._make_plan(config, self.database)
        #: frames we decode, by (arbitration id, extended id flag)
        self._by_id: dict[tuple[int, bool], _MessagePlan] = {
            (p.message.frame_id, bool(p.message.is_extended_frame)): p for p in self._plans.values()
        }
        #: twin channel -> DBC message name, for diagnostics
        self._channel_message = {ch: m.message for ch, m in config.signals.items()}
        self._time_mode = (
            "signal" if config.time_source.startswith(_TIME_SIGNAL_PREFIX) else config.time_source
        )

        # decoding state
        self._latest: dict[str, float] = {}
        self._time_value: float | None = None
        counter_bits = self._counter_bits(config)
        self._counter = SampleCounter(None if counter_bits is None else 1 << counter_bits)
        self._skip_sync = False  # the counter said the sync's sample is a repeat or late

        # silence: the last frame's wall time (a live bus that delivers nothing is given up
        # after reopen_after) and each mapped message's last frame time (silent_after)
        self._last_frame_wall = time.monotonic()
        self._seen: dict[str, float] = {}
        self._first_stamp: float | None = None
        self._message_channels: dict[str, list[str]] = {}
        for ch, m in config.signals.items():
            self._message_channels.setdefault(m.message, []).append(ch)
        self._silent: tuple[str, ...] = ()
        self._silent_logged: set[str] = set()
        self._source = self._open_source(config, bus)
        self._watch_silence = (isinstance(self._source, _BusSource) and self._source.owned
                               and config.reopen_after is not None)
        logger.info(
            "CAN driver ready: %s, DBC %s, sync on %s, channels %s%s",
            self._describe_source(),
            config.dbc,
            config.sync_message,
            ", ".join(self.channels),
            "; replaying a log: for a live bus, set [driver] interface and channel (e.g. "
            "socketcan, can0) instead of log_file" if config.log_file is not None else "",
        )

    @staticmethod
    def _load_dbc(path: Path) -> Database:
        if not path.is_file():
            raise DriverConfigError(f"dbc: file {str(path)!r} not found")
        try:
            db = cantools.database.load_file(path)
        except (OSError, ValueError, CantoolsError) as exc:
            raise DriverConfigError(f"dbc: cannot load {str(path)!r}: {exc}") from exc
        if not isinstance(db, Database):
            raise DriverConfigError(f"dbc: {str(path)!r} is not a CAN database")
        return db

    @staticmethod
    def _make_plan(config: CanDriverConfig, db: Database) -> dict[str, _MessagePlan]:
        plans: dict[str, _MessagePlan] = {}

        def plan_for(key: str, message_name: str, signal_name: str | None) -> _MessagePlan:
            message = _find_signal(db, key, message_name, signal_name)
            return plans.setdefault(message.name, _MessagePlan(message))

        for channel, sig in config.signals.items():
            plan_for(f"signals.{channel}", sig.message, sig.signal).channels.append(
                (channel, sig.signal, sig.scale, sig.offset)
            )
        plan_for("sync_message", config.sync_message, None).is_sync = True
        if config.counter_signal is not None:
            msg, sig_name = _split_signal_ref(config.counter_signal)
            plan_for("counter_signal", msg, sig_name).counter_signal = sig_name
        if config.time_source.startswith(_TIME_SIGNAL_PREFIX):
            msg, sig_name = _split_signal_ref(config.time_source.removeprefix(_TIME_SIGNAL_PREFIX))
            plan_for("time_source", msg, sig_name).time_signal = sig_name
        return plans

    def _counter_bits(self, config: CanDriverConfig) -> int | None:
        """Bit width of an unsigned integer counter (it wraps modulo 2**bits), else None."""
        if config.counter_signal is None:
            return None
        msg, sig_name = _split_signal_ref(config.counter_signal)
        signal = self.database.get_message_by_name(msg).get_signal_by_name(sig_name)
        if signal.is_float or signal.is_signed or signal.scale != 1 or signal.offset != 0:
            return None
        return int(signal.length)

    def _open_source(self, config: CanDriverConfig, bus: can.BusABC | None) -> _FrameSource:
        if bus is not None:
            if config.log_file is not None:
                raise DriverConfigError("log_file and a bus were both given; pick one")
            return _BusSource(bus, owned=False)
        if config.log_file is not None:
            return _LogSource(config.log_file, realtime=config.realtime,
                              on_bad=self._on_bad_line)
        if config.interface is None or config.channel is None:
            raise DriverConfigError(
                "interface and channel are required for a live bus (or give log_file)"
            )
        kwargs: dict[str, Any] = dict(config.bus_options)
        if config.bitrate is not None:
            kwargs["bitrate"] = config.bitrate
        # Only the frames we decode reach us (filtered in the kernel/adapter where possible).
        kwargs.setdefault(
            "can_filters",
            [
                {
                    "can_id": frame_id,
                    "can_mask": 0x1FFFFFFF if extended else 0x7FF,
                    "extended": extended,
                }
                for frame_id, extended in self._by_id
            ],
        )
        _reach_gateway(config)
        try:
            opened = can.Bus(interface=config.interface, channel=config.channel, **kwargs)
        except (can.CanError, ImportError, OSError, ValueError, TypeError) as exc:
            raise DriverInitializationError(
                f"cannot open CAN interface {config.interface!r} channel {config.channel!r}: {exc}"
            ) from exc
        if self._listen_only:
            self.receive_only = _receive_only(opened)
        return _BusSource(opened, owned=True)

    def _describe_source(self) -> str:
        if isinstance(self._source, _LogSource):
            mode = "real time" if self._source.realtime else "as fast as possible"
            return f"log {str(self._source.path)!r} ({mode})"
        if isinstance(self._source, _BusSource):
            owner = "own" if self._source.owned else "shared"
            return f"{owner} bus {self._source.bus.channel_info}"
        return "no source"

    # -- reading ----------------------------------------------------------------------------
    def _read_internal(self, timeout: float | None) -> Sample | None:
        source = self._source
        if source is None:  # pragma: no cover - only after a failed construction
            raise DriverOperationError("CAN driver has no frame source")
        # Frames already received are processed even when the timeout has run out (so that
        # read(0) returns a sample that is complete in the queue), but at most
        # _MAX_OVERTIME_FRAMES of them, so that a flood without sync messages cannot hold
        # the caller beyond its timeout.
        deadline = None if timeout is None else time.monotonic() + max(timeout, 0.0)
        overtime = 0
        while True:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            if self._watch_silence and remaining is None:
                remaining = 1.0  # a silent bus must not hold a read(None) beyond reopen_after
            frame = source.recv(remaining)
            if frame is None:
                self._check_silence()
                if deadline is None:
                    continue
                return None
            self._last_frame_wall = time.monotonic()
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
            assert isinstance(self._source, _BusSource)
            raise DriverOperationError(
                f"no CAN frame for {quiet:.1f} s on {self._source.bus.channel_info}: the bus "
                f"is silent, the interface down or the gateway's connection closed")

    @property
    def silent(self) -> tuple[str, ...]:
        """The mapped messages not received for ``silent_after`` seconds of frame time (as of
        the last sync message), with their channels and how long."""
        return self._silent

    def _update_silent(self, now: float) -> set[str]:
        """Which mapped messages are silent at frame time ``now`` [s]; their channels."""
        if self._first_stamp is None:
            self._first_stamp = now
        limit = self.config.silent_after
        silent, gone = [], set()
        for message, chans in self._message_channels.items():
            age = now - self._seen.get(message, self._first_stamp)
            if age > limit:
                silent.append(f"{message} ({', '.join(chans)}) for {age:.1f} s")
                gone.update(chans)
                if message not in self._silent_logged:
                    self._silent_logged.add(message)
                    self._bump("silent_messages")
                    logger.warning(
                        "CAN message %s (channels %s) not received for %.1f s (silent_after "
                        "%g s): its channels are left out of the samples until it is back",
                        message, ", ".join(chans), age, limit)
            elif message in self._silent_logged:
                self._silent_logged.discard(message)
                logger.warning("CAN message %s is received again", message)
        self._silent = tuple(silent)
        return gone

    def _on_bad_line(self, line: int, exc: BaseException) -> None:
        self.stats.frames += 1
        self.stats.bad_frames += 1
        self.log_once("log-line", "CAN log line %d is malformed (%s: %s): skipped, counted in "
                      "stats.bad_frames; the replay goes on", line, type(exc).__name__, exc)

    def _bump(self, key: str) -> None:
        self.stats.extra[key] = self.stats.extra.get(key, 0) + 1

    def _on_frame(self, frame: can.Message) -> Sample | None:
        """Account for one frame; return a sample if it was a complete sync message."""
        self.stats.frames += 1
        if frame.is_error_frame:
            self._bump("error_frames")
            return None
        if frame.is_remote_frame:
            self._bump("remote_frames")
            return None
        plan = self._by_id.get((frame.arbitration_id, bool(frame.is_extended_id)))
        if plan is None:
            return None
        message = plan.message
        self._seen[message.name] = float(frame.timestamp)
        data = bytes(frame.data)
        try:
            decoded = message.decode(
                data, decode_choices=False, scaling=True, allow_truncated=False, allow_excess=True
            )
        except (DecodeError, ValueError, KeyError, IndexError) as exc:
            self.stats.bad_frames += 1
            self.log_once(
                f"decode:{message.name}",
                "CAN frame 0x%X (%s, %d bytes) not decodable: %s; counted in stats.bad_frames",
                frame.arbitration_id,
                message.name,
                len(data),
                exc,
            )
            return None
        if not isinstance(decoded, dict):  # container frames decode to lists
            self.stats.bad_frames += 1
            self.log_once(
                f"container:{message.name}", "CAN container message %s ignored", message.name
            )
            return None
        if len(data) > message.length:
            self.log_once(
                f"long:{message.name}",
                "CAN frame 0x%X (%s) has %d bytes, DBC says %d; extra bytes ignored",
                frame.arbitration_id,
                message.name,
                len(data),
                message.length,
                level=logging.INFO,
            )

        for channel, signal, scale, offset in plan.channels:
            raw = decoded.get(signal)
            if raw is None:  # multiplexed signal not in this frame
                continue
            value = _as_float(raw) * scale + offset
            if not math.isfinite(value):
                self.stats.bad_values += 1
                self.log_once(
                    f"nonfinite:{channel}",
                    "CAN signal %s.%s -> %s decoded to %s; counted in stats.bad_values",
                    message.name,
                    signal,
                    channel,
                    value,
                )
            self._latest[channel] = value
        if plan.time_signal is not None and plan.time_signal in decoded:
            self._time_value = _as_float(decoded[plan.time_signal])
        if plan.counter_signal is not None and plan.counter_signal in decoded:
            self._on_counter(_as_float(decoded[plan.counter_signal]))
        if plan.is_sync:
            return self._assemble(frame)
        return None

    def _on_counter(self, value: float) -> None:
        if not value.is_integer():
            self.stats.bad_values += 1
            self.log_once("counter:nonint", "CAN sample counter is not an integer: %s", value)
            return
        raw = int(value)
        before = self._counter.raw
        step, missing = self._counter.update(raw)
        if step in ("duplicate", "stale"):
            key = "duplicates" if step == "duplicate" else "reordered"
            self._bump(key)
            self._skip_sync = True
            self.log_once(
                f"counter:{step}",
                "CAN sample counter %d arrived after %d (%s frame): its sample is skipped, the "
                "count goes on; counted in stats.extra[%r]", raw, before,
                "a repeated" if step == "duplicate" else "a late, reordered", key)
        elif step == "reset":
            self._bump("counter_resets")
            self.log_once(
                "counter:reset",
                "CAN sample counter went back from %d to %d (the source restarted): its clock "
                "restarts from the new value", before, raw)
        elif missing:
            self.stats.gaps += missing
            self.log_once(
                "counter:gap",
                "CAN sample counter jumped from %d to %d: %d samples lost; counted in stats.gaps",
                before, raw, missing)

    def _assemble(self, frame: can.Message) -> Sample | None:
        if self._skip_sync:  # a repeated or late counter frame: not a new sample
            self._skip_sync = False
            return None
        gone = self._update_silent(float(frame.timestamp))
        missing = [ch for ch in self.channels if ch not in self._latest]
        t: float | None
        if self._time_mode == "frame":
            t = float(frame.timestamp)
        elif self._time_mode == "counter":
            count = self._counter.count
            t = None if count is None else count * self.sample_period
        else:
            t = self._time_value
        if missing or t is None:
            self._bump("incomplete_syncs")
            self.log_once(
                "incomplete",
                "CAN sync message %s arrived before %s; no sample yet (waiting for %s)",
                self.config.sync_message,
                ", ".join(missing) if missing else "the time source",
                ", ".join(sorted({self._channel_message[ch] for ch in missing}))
                if missing
                else self.config.time_source,
                level=logging.INFO,
            )
            return None
        return Sample(t, {ch: self._latest[ch] for ch in self.channels if ch not in gone})

    # -- closing ----------------------------------------------------------------------------
    def _close_internal(self) -> None:
        source, self._source = self._source, None
        if source is not None:
            source.close()
            logger.debug("CAN driver closed (%s)", self.stats.as_dict())
