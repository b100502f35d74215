"""CAN bus driver: decode DBC signals from a live bus or a log file into twin samples.

The driver listens to a python-can bus or replays a log file through :func:`can.LogReader`,
decodes the frames it needs with a DBC loaded by cantools, and emits one :class:`Sample` each
time the configured *sync message* arrives. The sample holds the latest value of every mapped
signal (sample-and-hold), converted to the twin's unit as ``value_dbc * scale + offset``.

The driver never transmits. It shuts down a bus it opened itself and leaves alone a bus it was
given (``CanDriver(config, bus=...)``), so a simulated plant can share a ``virtual`` bus.

Bad input is counted, logged once, and skipped (see :class:`~twinwatch.drivers.base.DriverStats`):

* frames whose id is not needed (not in the DBC, or not mapped) count in ``stats.frames`` only;
* frames of needed messages that cannot be decoded (too short, unknown multiplexer value, ...)
  count in ``stats.bad_frames``; frames *longer* than the DBC says are decoded (padding is
  common) and logged once;
* NaN or infinite decoded values count in ``stats.bad_values`` and are delivered as they are;
* the sample counter's jumps, repeats, late frames and restarts: as
  :meth:`~twinwatch.drivers.base.Driver._count` counts them;
* error frames and remote (RTR) frames count in ``stats.extra["error_frames"]`` /
  ``stats.extra["remote_frames"]`` (ODrive masters poll with RTR frames: they are normal);
* a sync message before every mapped signal has been seen once gives no sample
  (``stats.extra["incomplete_syncs"]``);
* a malformed line of a text log is skipped and counts in ``stats.bad_frames``.

A commented ``[driver]`` table: ``twinwatch/config/samples/driver_can.toml``
(``twinwatch sample-config --driver can``).
"""

from __future__ import annotations

import difflib
import logging
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal

import can
import cantools
import cantools.database
from cantools.database.can import Database
from cantools.database.can import Message as DbcMessage
from cantools.database.errors import DecodeError
from cantools.database.errors import Error as CantoolsError
from pydantic import Field, field_validator, model_validator

from twinwatch.drivers.base import DriverConfig, DriverConfigError, Sample, ScaledChannel
from twinwatch.drivers.canbus import (
    BusDriver,
    BusDriverConfig,
    BusSource,
    LogSource,
    gateway_address,
)
from twinwatch.io.counter import SampleCounter

logger = logging.getLogger(__name__)

__all__ = ["CanDriver", "CanDriverConfig", "CanSignalMap"]

_TIME_SIGNAL_PREFIX = "signal:"


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


class CanDriverConfig(BusDriverConfig):
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
            file shipped in the package: :data:`~twinwatch.drivers.base.PACKAGE_PREFIX`). The
            end of the log raises :class:`~twinwatch.drivers.base.EndOfStream`.
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

    file_keys: ClassVar[tuple[str, ...]] = ("dbc", "log_file")

    type: Literal["can"]
    dbc: Path
    sync_message: str = Field(min_length=1)
    time_source: str = "frame"
    counter_signal: str | None = None
    signals: dict[str, CanSignalMap] = Field(min_length=1)

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


# -- the driver ---------------------------------------------------------------------------


class CanDriver(BusDriver):
    """Twin samples from DBC-decoded CAN frames (live bus or log replay); never transmits.

    Args: :class:`~twinwatch.drivers.canbus.BusDriver`'s (``config`` a :class:`CanDriverConfig`).

    Attributes:
        database: the loaded cantools database.

    Raises:
        DriverConfigError: the DBC cannot be loaded, a configured message or signal is not in
            it (the message names the config key and the closest names), or the log file
            cannot be opened.
        DriverInitializationError: the bus cannot be opened.
    """

    config_class = CanDriverConfig
    config: CanDriverConfig
    sample_machine = "dc-motor-can"
    sample_title = "a DC motor drive on a CAN bus"

    @classmethod
    def describe(cls, config: DriverConfig) -> str:
        """``"CAN interface 'socketcand' channel 'can0' (127.0.0.1:29536)"``, or the log."""
        assert isinstance(config, CanDriverConfig)
        if config.log_file is not None:
            return f"CAN log {str(config.log_file)!r}"
        address = gateway_address(config)
        where = f" ({address[0]}:{address[1]})" if address else ""
        return f"CAN interface {config.interface!r} channel {config.channel!r}{where}"

    # -- construction -----------------------------------------------------------------------
    def _setup(self, config: CanDriverConfig) -> None:
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
        self._time_value: float | None = None
        counter_bits = self._counter_bits(config)
        self._counter = SampleCounter(None if counter_bits is None else 1 << counter_bits)
        self._skip_sync = False  # the counter said the sync's sample is a repeat or late
        # each mapped message's channels, watched for silence (silent_after)
        self._message_channels: dict[str, list[str]] = {}
        for ch, m in config.signals.items():
            self._message_channels.setdefault(m.message, []).append(ch)

    def _ready(self) -> None:
        config = self.config
        logger.info(
            "CAN driver ready: %s, DBC %s, sync on %s, channels %s%s",
            self._describe_source(),
            config.dbc,
            config.sync_message,
            ", ".join(self.channels),
            "; replaying a log: for a live bus, set [driver] interface and channel (e.g. "
            "socketcan, can0) instead of log_file" if config.log_file is not None else "",
        )

    def _probed(self, live: bool) -> str:
        return f", DBC {str(self.config.dbc)!r}" if live else ""

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

    def _can_filters(self) -> list[dict[str, Any]]:
        return [{"can_id": frame_id, "can_mask": 0x1FFFFFFF if extended else 0x7FF,
                 "extended": extended} for frame_id, extended in self._by_id]

    def _describe_source(self) -> str:
        if isinstance(self._source, LogSource):
            mode = "real time" if self._source.realtime else "as fast as possible"
            return f"log {str(self._source.path)!r} ({mode})"
        if isinstance(self._source, BusSource):
            owner = "own" if self._source.owned else "shared"
            return f"{owner} bus {self._source.bus.channel_info}"
        return "no source"

    # -- reading ----------------------------------------------------------------------------
    def _on_frame(self, frame: can.Message) -> Sample | None:
        """Account for one frame; return a sample if it was a complete sync message."""
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
        decoded = self._decode(message, frame)
        if decoded is None:
            return None
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

    def _decode(self, message: DbcMessage, frame: can.Message) -> dict[str, Any] | None:
        """A needed message's frame decoded (signal -> physical value); None, counted in
        ``stats.bad_frames`` and logged once, when it cannot be (too short, a container)."""
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
                frame.arbitration_id, message.name, len(data), exc)
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
                frame.arbitration_id, message.name, len(data), message.length,
                level=logging.INFO)
        return decoded

    def _on_counter(self, value: float) -> None:
        if not value.is_integer():
            self.stats.bad_values += 1
            self.log_once("counter:nonint", "CAN sample counter is not an integer: %s", value)
            return
        if self._count(self._counter, int(value), "CAN sample counter"):
            self._skip_sync = True

    def _assemble(self, frame: can.Message) -> Sample | None:
        if self._skip_sync:  # a repeated or late counter frame: not a new sample
            self._skip_sync = False
            return None
        now = float(frame.timestamp)
        if self._first_stamp is None:
            self._first_stamp = now
        silent, gone = self._silent_since(now, self._message_channels, what="CAN message",
                                          key="silent_messages")
        self._silent = tuple(silent)
        missing = [ch for ch in self.channels if ch not in self._latest]
        t = self._sample_time(now)
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

    def _sample_time(self, stamp: float) -> float | None:
        """The sample's time [s] by ``time_source``: the sync frame's ``stamp``, the counter
        times ``sample_period``, or the time signal's latest value (None before one)."""
        if self._time_mode == "frame":
            return stamp
        if self._time_mode == "counter":
            count = self._counter.count
            return None if count is None else count * self.sample_period
        return self._time_value
