"""CANopen driver: a CiA 301 / CiA 402 drive's PDOs decoded passively into twin samples.

The TPDO and RPDO mapping (0x1800+n/0x1A00+n, 0x1400+n/0x1600+n) is read from the drive's EDS or
DCF with the ``canopen`` library (:func:`canopen.import_od`), never from the drive. A channel
names an object (``"0x606C"``, ``"0x6078sub0"`` or its EDS name) and
``value = raw * factor + offset``, the factor a number or a named unit (:data:`FACTORS`).
Passive: no ``canopen.Network``, no ``send``; a live interface is receive-only where python-can
allows it. Samples (``sample_on = "sync"`` or ``"TPDO1"``), the drive's state from EMCY, the
statusword 0x6041 and the heartbeat (:attr:`CanopenDriver.device_faults`,
:attr:`CanopenDriver.silent`) and the counters of bad input: docs/canopen.md.

A commented ``[driver]`` table: ``twinwatch/config/samples/driver_canopen.toml``
(``twinwatch sample-config --driver canopen``).
"""
from __future__ import annotations

import logging
import math
import re
import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Literal

from pydantic import ConfigDict, Field, StrictFloat, StrictInt, field_validator

from twinwatch._table import StrictTable
from twinwatch.drivers.base import DriverConfig, DriverConfigError, Sample
from twinwatch.drivers.canbus import BusDriver, BusDriverConfig
from twinwatch.io.counter import SampleCounter

if TYPE_CHECKING:  # imported when the driver opens: validating a config loads no CAN stack
    import can

logger = logging.getLogger(__name__)

__all__ = ["FACTORS", "CanopenChannel", "CanopenDriver", "CanopenDriverConfig", "load_plan"]

_RPM = 2.0 * math.pi / 60.0

#: Named factors, raw value -> SI unit. Numbers need no name; these are the CiA 402 units a
#: drive's manual states. ``per_mille_rated_current`` / ``per_mille_rated_torque`` read the
#: motor rated current 0x6075 [mA] / rated torque 0x6076 [mN m] from the EDS/DCF; ``inc/s`` and
#: ``inc`` the position encoder resolution 0x608F (increments per motor revolutions).
FACTORS: Mapping[str, float | None] = {
    "rad/s": 1.0,
    "rpm": _RPM,
    "0.1rpm": _RPM * 0.1,
    "0.01rpm": _RPM * 0.01,
    "0.001rpm": _RPM * 0.001,
    "rev/s": 2.0 * math.pi,
    "V": 1.0,
    "mV": 1e-3,
    "A": 1.0,
    "mA": 1e-3,
    "Nm": 1.0,
    "mNm": 1e-3,
    "per_mille_rated_current": None,
    "per_mille_rated_torque": None,
    "inc/s": None,
    "inc": None,
}

_OBJECT_RE = re.compile(r"^0x([0-9A-Fa-f]{1,4})(?:sub(?:0x)?([0-9A-Fa-f]{1,2}))?$")
_TPDO_RE = re.compile(r"^[Tt][Pp][Dd][Oo]([1-9][0-9]{0,2})$")

#: ODVariable data types (CiA 301) the driver decodes as numbers: (signed, float)
_INTEGER_TYPES = {0x2: True, 0x3: True, 0x4: True, 0x10: True, 0x12: True, 0x13: True,
                  0x14: True, 0x15: True, 0x5: False, 0x6: False, 0x7: False, 0x16: False,
                  0x18: False, 0x19: False, 0x1A: False, 0x1B: False, 0x1: False}
_FLOAT_TYPES = {0x8: struct.Struct("<f"), 0x11: struct.Struct("<d")}
#: struct codes of the entries a PDO's compiled layout unpacks: (bits, signed) / (type, bits)
_INT_CODES: dict[tuple[int, bool | None], str] = {
    (8, True): "b", (8, False): "B", (16, True): "h", (16, False): "H", (32, True): "i",
    (32, False): "I"}
_FLOAT_CODES = {(0x8, 32): "f", (0x11, 64): "d"}

_NMT_STATES = {0: "BOOT-UP", 4: "STOPPED", 5: "OPERATIONAL", 127: "PRE-OPERATIONAL"}


class CanopenChannel(StrictTable):
    """Where one twin channel comes from: ``value_twin = raw * factor + offset``.

    Attributes:
        object: the mapped object: ``"0x606C"`` (sub-index 0), ``"0x6078sub0"``, or its EDS
            ``ParameterName`` (``"Velocity actual value"``; a record's member as
            ``"Record name.Member name"``).
        factor: raw value -> the twin's SI unit: a number, or a name of :data:`FACTORS`.
        offset: added after scaling, in the twin's unit.
        unit: the twin channel's unit, for documentation.
    """

    model_config = ConfigDict(frozen=True)

    object: str = Field(min_length=1)
    factor: StrictFloat | str = 1.0
    offset: StrictFloat = Field(0.0, allow_inf_nan=False)
    unit: str | None = None

    @field_validator("factor")
    @classmethod
    def _known_factor(cls, value: float | str) -> float | str:
        if isinstance(value, str):
            if value not in FACTORS:
                raise ValueError(f"unknown factor {value!r}; give a number or one of: "
                                 f"{', '.join(FACTORS)}")
        elif not math.isfinite(value) or value == 0.0:
            raise ValueError("factor must be a finite number other than 0")
        return value

class CanopenDriverConfig(BusDriverConfig):
    """Configuration of :class:`CanopenDriver` (the ``[driver]`` table, ``type = "canopen"``).

    Attributes:
        type: always ``"canopen"``.
        interface, channel, bitrate, bus_options: the python-can bus, as for the CAN driver
            (``socketcan``/``can0``, ``pcan``/``PCAN_USBBUS1``, ...).
        log_file: replay a candump ``.log`` / ``.asc`` / ``.blf`` ... instead of a live bus.
        realtime: pace a log replay by its time stamps.
        node_id: the drive's node id, 1-127 (its PDO, EMCY and heartbeat COB-IDs).
        eds: the drive's EDS or DCF (relative to the configuration file's directory, or
            ``twinwatch:plant/dcmotor-cia402.eds``): its PDO mapping is read from it.
        sample_period: the nominal sample period [s] (the SYNC period).
        sample_on: ``"sync"``, or ``"TPDO<n>"``: one sample per frame of that TPDO.
        heartbeat_time: the drive's heartbeat producer time [s]; None: 0x1017 of the EDS/DCF;
            0: not watched.
        heartbeat_margin: the heartbeat is missing after this many producer times.
        channels: twin channel -> :class:`CanopenChannel`, at least one.
        reopen_after, silent_after: as the CAN driver's (a live bus with no frame at all for
            ``reopen_after`` s is reopened; a held PDO not received for ``silent_after`` s of
            frame time leaves its channels out).
    """

    file_keys: ClassVar[tuple[str, ...]] = ("eds", "log_file")

    type: Literal["canopen"]
    node_id: StrictInt = Field(ge=1, le=127)
    eds: Path
    sample_on: str = "sync"
    heartbeat_time: StrictFloat | None = Field(None, ge=0, allow_inf_nan=False)
    heartbeat_margin: StrictFloat = Field(1.5, ge=1.0, allow_inf_nan=False)
    channels: dict[str, CanopenChannel] = Field(min_length=1)

    @field_validator("sample_on")
    @classmethod
    def _sample_on(cls, value: str) -> str:
        if value != "sync" and not _TPDO_RE.match(value):
            raise ValueError(f"expected 'sync' or 'TPDO<n>' (e.g. 'TPDO1'), got {value!r}")
        return value

    def twin_channels(self) -> tuple[str, ...]:
        """The twin channels this driver delivers (``channels``)."""
        return tuple(self.channels)


# -- the plan: what the EDS/DCF says the drive sends ------------------------------------------


@dataclass(slots=True)
class _Entry:
    """One mapped object of a PDO: where it sits and how it decodes."""

    index: int
    subindex: int
    name: str
    bit_offset: int
    bits: int
    data_type: int


@dataclass(slots=True)
class _Pdo:
    """One PDO of the EDS/DCF (a TPDO the drive sends or an RPDO the master sends)."""

    name: str  # "TPDO1", "RPDO1"
    cob_id: int
    trans_type: int
    entries: list[_Entry]
    #: the mapping's length [bits], dummy entries included: a shorter frame is truncated
    bits: int
    #: (twin channel, entry, factor, offset) decoded from each frame
    channels: list[tuple[str, _Entry, float, float]] = field(default_factory=list)
    statusword: _Entry | None = None
    #: a TPDO, the drive's own frame (an RPDO is the master's)
    own: bool = field(init=False)
    #: compiled by :meth:`compile`: data -> the raw values of the entries used, in one call
    unpack: Callable[[bytes | bytearray], tuple[Any, ...]] | None = None
    #: (twin channel, its raw value's place in ``unpack``'s tuple, factor, offset)
    scaled: tuple[tuple[str, int, float, float], ...] = ()
    #: the statusword's place in ``unpack``'s tuple
    status_at: int | None = None

    def compile(self) -> None:
        """Precompile the decoding of the entries used (the channels' and the statusword):
        one :class:`struct.Struct` for the frame where each sits on a byte boundary in a
        standard width (8/16/32-bit integers, a REAL32/REAL64 of its own width), else
        :func:`_decode` entry by entry. Either gives :func:`_decode`'s raw values, as int or
        float: ``raw * factor`` is the same number."""
        used = {e.bit_offset: e for _, e, _, _ in self.channels}
        if self.statusword is not None:
            used[self.statusword.bit_offset] = self.statusword
        entries = [used[offset] for offset in sorted(used)]
        codes = [_struct_code(e) for e in entries]
        if None in codes:
            self.unpack = lambda data: tuple(_decode(e, data) for e in entries)
        else:
            fmt, end = "<", 0
            for e, code in zip(entries, codes, strict=True):
                fmt += "x" * ((e.bit_offset - end) // 8) + str(code)
                end = e.bit_offset + e.bits
            self.unpack = struct.Struct(fmt).unpack_from
        at = {e.bit_offset: n for n, e in enumerate(entries)}
        self.scaled = tuple((ch, at[e.bit_offset], factor, offset)
                            for ch, e, factor, offset in self.channels)
        if self.statusword is not None:
            self.status_at = at[self.statusword.bit_offset]

    def __post_init__(self) -> None:
        self.own = self.name.startswith("T")

    @property
    def every_sync(self) -> bool:
        """Sent (TPDO) on every SYNC: a sample waits for it."""
        return self.own and self.trans_type == 1


@dataclass(slots=True)
class CanopenPlan:
    """What the driver listens for, from the configuration and the EDS/DCF.

    Attributes:
        pdos: COB-ID -> the PDO carrying channels or the statusword.
        all_pdos: every enabled PDO of the EDS/DCF, by name (``TPDO1``, ``RPDO1``).
        sync_id: the SYNC COB-ID (0x1005).
        sync_counter: the SYNC counter overflow value (0x1019; 0/1: no counter).
        heartbeat_s: the producer time [s] watched (0: not watched).
        channels: twin channel -> ``"TPDO1 0x606C Velocity actual value"``.
    """

    pdos: dict[int, _Pdo]
    all_pdos: dict[str, _Pdo]
    sync_id: int
    sync_counter: int
    heartbeat_s: float
    channels: dict[str, str]


def _od_value(var: Any) -> Any:
    """A variable's value as the EDS/DCF gives it: a DCF's value, else the default."""
    return var.value if getattr(var, "value", None) is not None else var.default


def _lookup(od: Any, text: str) -> Any:
    """The OD variable an ``object`` key names, or None."""
    import canopen.objectdictionary as cod

    m = _OBJECT_RE.match(text.strip())
    try:
        if m:
            index = int(m.group(1), 16)
            sub = int(m.group(2), 16) if m.group(2) is not None else None
            obj = od[index]
            if isinstance(obj, cod.ODVariable):
                return obj if sub in (None, 0) else None
            return obj[0 if sub is None else sub]
        if text in od:
            obj = od[text]
            return obj if isinstance(obj, cod.ODVariable) else None
        head, dot, tail = text.partition(".")
        if dot and head in od:
            obj = od[head]
            if not isinstance(obj, cod.ODVariable):
                return obj[tail]
    except KeyError:
        return None
    return None


def _read_pdos(od: Any, node_id: int, eds: Path) -> dict[str, _Pdo]:
    """Every enabled PDO the EDS/DCF describes (communication and mapping parameters)."""
    pdos: dict[str, _Pdo] = {}
    for kind, com_base, map_base, predefined in (("TPDO", 0x1800, 0x1A00, 0x180),
                                                 ("RPDO", 0x1400, 0x1600, 0x200)):
        for n in range(512):
            if com_base + n not in od or map_base + n not in od:
                continue
            name = f"{kind}{n + 1}"
            com, mapping = od[com_base + n], od[map_base + n]
            try:
                cob_raw = int(_od_value(com[1]))
                trans = int(_od_value(com[2]) or 0) if 2 in com else 255
                count = int(_od_value(mapping[0]) or 0)
                words = [int(_od_value(mapping[s]) or 0) for s in range(1, count + 1)]
            except (KeyError, TypeError, ValueError) as exc:
                raise DriverConfigError(
                    f"eds: {str(eds)!r}: {name}'s parameters 0x{com_base + n:04X} / "
                    f"0x{map_base + n:04X} are incomplete ({type(exc).__name__}: {exc})"
                ) from None
            if cob_raw & 0x80000000:
                continue  # not valid: the PDO is not sent
            cob_id = cob_raw & 0x1FFFFFFF
            if n < 4 and cob_id == predefined + n * 0x100:
                cob_id += node_id  # a default written without $NODEID: the predefined set
            entries, bits = _mapped(od, words, name, eds)
            pdos[name] = _Pdo(name, cob_id, trans, entries, bits)
    return pdos


def _mapped(od: Any, words: list[int], name: str, eds: Path) -> tuple[list[_Entry], int]:
    """A PDO's mapping parameter's words as entries (a dummy entry is padding), and the
    mapping's length [bits].

    Raises:
        DriverConfigError: an entry maps an object the file does not define.
    """
    entries, offset = [], 0
    for word in words:
        index, sub, bits = word >> 16, (word >> 8) & 0xFF, word & 0xFF
        if index == 0 or bits == 0:
            continue
        if index < 0x20:  # a dummy entry (a data type's index): padding
            offset += bits
            continue
        try:
            var = od.get_variable(index, sub)
        except KeyError:
            var = None
        if var is None:
            raise DriverConfigError(
                f"eds: {str(eds)!r}: {name} maps 0x{index:04X}sub{sub}, which the "
                f"file does not define")
        entries.append(_Entry(index, sub, var.name, offset, bits, int(var.data_type)))
        offset += bits
    return entries, offset


def load_plan(config: CanopenDriverConfig) -> CanopenPlan:
    """Read the EDS/DCF and check the configuration against it (no bus is touched).

    Args:
        config: the resolved configuration (``eds`` an absolute path or relative to the
            current directory).

    Returns:
        The :class:`CanopenPlan`.

    Raises:
        DriverConfigError: the EDS/DCF is missing or does not parse (``eds: ...``), a channel's
            object is not in it or mapped to no PDO (``channels.<ch>.object: ...``), its
            factor needs an object the file lacks (``channels.<ch>.factor: ...``), a channel's
            REAL32/REAL64 is mapped in fewer or more bits than its width, or ``sample_on``
            names no enabled TPDO. A statusword (0x6041) mapped as anything but an integer is
            not watched for its fault bit.
    """
    eds = config.eds
    od = _import_od(eds, config.node_id)
    all_pdos = _read_pdos(od, config.node_id, eds)
    used: dict[int, _Pdo] = {}
    described = _map_channels(config, od, all_pdos, used)
    for pdo in all_pdos.values():  # the statusword's fault bit, wherever it is mapped
        for entry in pdo.entries:
            if (entry.index == 0x6041 and entry.subindex == 0 and pdo.name.startswith("T")
                    and entry.data_type in _INTEGER_TYPES):  # CiA 402: UNSIGNED16
                pdo.statusword = entry
                used[pdo.cob_id] = pdo
    if config.sample_on != "sync":
        target = all_pdos.get(config.sample_on.upper())
        if target is None or not target.name.startswith("T"):
            raise DriverConfigError(
                f"sample_on: {config.sample_on!r} is not an enabled TPDO of {str(eds)!r}; "
                f"its TPDOs: {', '.join(n for n in all_pdos if n.startswith('T')) or 'none'}")
        used[target.cob_id] = target
    for pdo in used.values():
        pdo.compile()
    sync_id, counter, heartbeat = _supervision(od, config.heartbeat_time)
    return CanopenPlan(pdos=used, all_pdos=all_pdos, sync_id=sync_id, sync_counter=counter,
                       heartbeat_s=heartbeat, channels=described)


def _import_od(eds: Path, node_id: int) -> Any:
    """The EDS/DCF's object dictionary (canopen's ``import_od``).

    Raises:
        DriverConfigError: ``eds: ...``: the file is missing, not an .eds/.dcf, does not parse
            or defines no object.
    """
    import canopen

    if not eds.is_file():
        raise DriverConfigError(f"eds: file {str(eds)!r} not found")
    if eds.suffix.lower() not in (".eds", ".dcf"):
        raise DriverConfigError(f"eds: {str(eds)!r} is not an .eds or .dcf file")
    try:
        od = canopen.import_od(str(eds), node_id)
    except Exception as exc:  # noqa: BLE001 - a parse of a user's file: configparser, int(), KeyError...
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DriverConfigError(
            f"eds: {str(eds)!r} does not parse as an EDS/DCF ({type(exc).__name__}: {first})"
        ) from None
    if len(od) == 0:
        raise DriverConfigError(f"eds: {str(eds)!r} defines no object: is it an EDS/DCF?")
    return od


def _map_channels(config: CanopenDriverConfig, od: Any, all_pdos: dict[str, _Pdo],
                  used: dict[int, _Pdo]) -> dict[str, str]:
    """Each channel to the PDO entry that carries its object (a TPDO, the drive's own, before
    an RPDO, the master's), with its factor; the PDOs used go into ``used`` (by COB-ID).

    Returns:
        channel -> what carries it (``TPDO1 0x606C Velocity actual value``).

    Raises:
        DriverConfigError: ``channels.<ch>.object`` / ``.factor``: an object not in the file,
            mapped to no PDO or not a number, a factor the file gives nothing for.
    """
    eds = config.eds
    by_object: dict[tuple[int, int], list[tuple[_Pdo, _Entry]]] = {}
    for pdo in all_pdos.values():
        for entry in pdo.entries:
            by_object.setdefault((entry.index, entry.subindex), []).append((pdo, entry))
    described: dict[str, str] = {}
    for ch, spec in config.channels.items():
        var = _lookup(od, spec.object)
        if var is None:
            raise DriverConfigError(
                f"channels.{ch}.object: {spec.object!r} is not an object of {str(eds)!r} "
                "(write 0x6064, 0x6078sub0 or the EDS ParameterName)")
        sub = var.subindex if var.parent is not None and var.parent is not od else 0
        found = by_object.get((var.index, sub))
        if not found:
            mapped = sorted({f"0x{e.index:04X} {e.name}" for p in all_pdos.values()
                             for e in p.entries})
            raise DriverConfigError(
                f"channels.{ch}.object: {spec.object!r} (0x{var.index:04X}sub{sub} "
                f"{var.name}) is mapped to no TPDO or RPDO of {str(eds)!r}: the drive does not "
                f"send it; mapped: {', '.join(mapped) or 'nothing'}")
        pdo, entry = sorted(found, key=lambda pe: (pe[0].name[0] != "T", pe[0].name))[0]
        _check_number(ch, var.name, entry, pdo.name, eds)
        factor = _factor(od, ch, spec.factor, eds)
        pdo.channels.append((ch, entry, factor, spec.offset))
        used[pdo.cob_id] = pdo
        described[ch] = f"{pdo.name} 0x{entry.index:04X} {entry.name}"
    return described


def _supervision(od: Any, heartbeat_time: float | None) -> tuple[int, int, float]:
    """The SYNC's COB-ID (0x1005, default 0x80), its counter overflow (0x1019, 0: none) and
    the heartbeat producer time [s] (the configured one, else 0x1017; 0: none)."""
    sync_id, counter = 0x80, 0
    if 0x1005 in od:
        sync_id = int(_od_value(od[0x1005]) or 0x80) & 0x7FF
    if 0x1019 in od:
        counter = int(_od_value(od[0x1019]) or 0)
    if heartbeat_time is not None:
        heartbeat = heartbeat_time
    elif 0x1017 in od:
        heartbeat = float(_od_value(od[0x1017]) or 0) / 1000.0
    else:
        heartbeat = 0.0
    return sync_id, counter, heartbeat


def _factor(od: Any, ch: str, factor: float | str, eds: Path) -> float:
    """A channel's factor as a number (a named one that needs the EDS/DCF read from it)."""
    if not isinstance(factor, str):
        return float(factor)
    fixed = FACTORS[factor]
    if fixed is not None:
        return fixed

    def need(index: int, sub: int, what: str) -> float:
        try:
            var = od.get_variable(index, sub)
            value = None if var is None else _od_value(var)
        except KeyError:
            value = None
        if not value:
            raise DriverConfigError(
                f"channels.{ch}.factor: {factor!r} needs the {what} (0x{index:04X}sub{sub}) "
                f"and {str(eds)!r} gives none; write the factor as a number")
        return float(value)

    if factor == "per_mille_rated_current":
        return need(0x6075, 0, "motor rated current [mA]") * 1e-3 / 1000.0
    if factor == "per_mille_rated_torque":
        return need(0x6076, 0, "motor rated torque [mN m]") * 1e-3 / 1000.0
    increments = need(0x608F, 1, "position encoder increments")
    revolutions = need(0x608F, 2, "position encoder motor revolutions")
    return 2.0 * math.pi * revolutions / increments  # inc/s -> rad/s, inc -> rad


def _check_number(ch: str, name: str, entry: _Entry, pdo: str, eds: Path) -> None:
    """Channel ``ch``'s object ``name`` as ``pdo`` maps it: an integer, or a float mapped in its
    whole width.

    Raises:
        DriverConfigError: ``channels.<ch>.object: ...``, another data type, or a
            REAL32/REAL64 mapped in fewer or more bits.
    """
    if entry.data_type not in _INTEGER_TYPES and entry.data_type not in _FLOAT_TYPES:
        raise DriverConfigError(
            f"channels.{ch}.object: {name} has data type 0x{entry.data_type:X}, not a number")
    real = _FLOAT_TYPES.get(entry.data_type)
    if real is not None and entry.bits != 8 * real.size:
        raise DriverConfigError(
            f"channels.{ch}.object: {name} is a REAL{8 * real.size} mapped in {entry.bits} "
            f"bits of {pdo} in {str(eds)!r}: a float is mapped whole")


def _struct_code(entry: _Entry) -> str | None:
    """The :mod:`struct` code that unpacks ``entry`` as :func:`_decode` does, if it sits on a
    byte boundary in a standard width (an 8/16/32-bit integer, a REAL32/REAL64 of its own
    width); else None."""
    if entry.bit_offset % 8:
        return None
    if entry.data_type in _FLOAT_TYPES:
        return _FLOAT_CODES.get((entry.data_type, entry.bits))
    return _INT_CODES.get((entry.bits, _INTEGER_TYPES.get(entry.data_type)))


def _decode(entry: _Entry, data: bytes | bytearray) -> float:
    """One mapped object's raw value from a PDO's data (little endian, bit offsets)."""
    if entry.data_type in _FLOAT_TYPES and entry.bit_offset % 8 == 0:
        start = entry.bit_offset // 8
        return float(_FLOAT_TYPES[entry.data_type].unpack_from(data, start)[0])
    raw = (int.from_bytes(data, "little") >> entry.bit_offset) & ((1 << entry.bits) - 1)
    if _INTEGER_TYPES.get(entry.data_type) and raw >> (entry.bits - 1):
        raw -= 1 << entry.bits
    return float(raw)

# -- the driver ------------------------------------------------------------------------------


class CanopenDriver(BusDriver):
    """Twin samples from a CANopen drive's PDOs, decoded from its EDS/DCF; never transmits.

    Args: :class:`~twinwatch.drivers.canbus.BusDriver`'s (``config`` a
    :class:`CanopenDriverConfig`).

    Attributes:
        plan: what the EDS/DCF says (:class:`CanopenPlan`).

    Raises:
        DriverConfigError: see :func:`load_plan`; a log file that cannot be read.
        DriverInitializationError: the bus cannot be opened.
    """

    config_class = CanopenDriverConfig
    config: CanopenDriverConfig
    driver_name = "CANopen"
    sample_machine = "dc-motor-canopen"
    sample_title = "a CiA 402 drive on a CANopen bus"

    @classmethod
    def describe(cls, config: DriverConfig) -> str:
        """``"CANopen node 5 on CAN interface 'socketcan' channel 'can0'"``, or the log."""
        assert isinstance(config, CanopenDriverConfig)
        if config.log_file is not None:
            return f"CANopen node {config.node_id} in log {str(config.log_file)!r}"
        return (f"CANopen node {config.node_id} on CAN interface {config.interface!r} "
                f"channel {config.channel!r}")

    # -- construction -------------------------------------------------------------------------
    def _setup(self, config: CanopenDriverConfig) -> None:
        self.plan = plan = load_plan(config)
        node = config.node_id
        self._emcy_id, self._heartbeat_id = 0x80 + node, 0x700 + node
        self._sync_id = plan.sync_id if config.sample_on == "sync" else None
        self._sample_pdo = (None if config.sample_on == "sync"
                            else plan.all_pdos[config.sample_on.upper()].cob_id)
        #: the TPDOs a SYNC's sample waits for (sent on every SYNC, carrying a channel)
        self._every_sync = frozenset(p.cob_id for p in plan.pdos.values()
                                     if p.channels and p.every_sync)
        #: every PDO carrying channels, watched for silence (PDO name -> its channels)
        self._watched = {p.name: [ch for ch, *_ in p.channels] for p in plan.pdos.values()
                         if p.channels}
        #: the PDOs whose channels hold their latest value: left out of the samples when silent
        self._held = {name: chans for name, chans in self._watched.items()
                      if self._holds(plan.all_pdos[name])}
        #: COB-ID -> the PDO a frame of it is (a PDO on the SYNC's COB-ID is the SYNC)
        self._pdos = {cob: pdo for cob, pdo in plan.pdos.items() if cob != self._sync_id}
        #: the heartbeat is missing after this long [s] (0: not watched)
        self._heartbeat_limit = plan.heartbeat_s * config.heartbeat_margin
        self._cycle_t: float | None = None  # the open SYNC cycle's stamp
        self._pending: set[int] = set()
        self._in_order: dict[str, float] | None = None  # _latest, once in the channels' order
        #: a lower bound of the watched PDOs' last frame times [s] (-inf: one not received
        #: yet): none is silent while ``now - _oldest_seen <= silent_after``
        self._oldest_seen = -math.inf
        self._skip_cycle = False
        self._counter = SampleCounter(plan.sync_counter if plan.sync_counter > 1 else None)
        # the drive's state
        self._emcy: str | None = None
        self._status_fault = False
        self._nmt: int | None = None
        #: the last heartbeat's stamp, else the first frame's (NaN before any frame)
        self._heartbeat_since = math.nan
        self._heartbeat_missing = False
        self._now: float | None = None  # the last frame's stamp
        self._faults: tuple[str, ...] = ()
        #: a frame of the drive's own (a TPDO, its EMCY or heartbeat) was received
        self._own_heard = False
        #: other nodes heard on the bus: node id -> the first frame of it (``heartbeat 0x705``)
        self._nodes_heard: dict[int, str] = {}

    def _holds(self, pdo: _Pdo) -> bool:
        """A PDO whose channels hold their latest value: not one a sample waits for (sent on
        every SYNC, or the TPDO samples are taken on)."""
        return (self._sync_id is None or not pdo.every_sync) and pdo.cob_id != self._sample_pdo

    def _ready(self) -> None:
        config, plan = self.config, self.plan
        logger.info("CANopen driver ready: node %d, %s, EDS %s, %s; %s; heartbeat %s",
                    config.node_id, self.describe(config), config.eds,
                    f"sample on SYNC 0x{plan.sync_id:X}" if self._sync_id is not None
                    else f"sample on {config.sample_on}",
                    "; ".join(f"{ch} <- {w}" for ch, w in plan.channels.items()),
                    f"{plan.heartbeat_s:g} s" if plan.heartbeat_s else "not watched")

    def _probed(self, live: bool) -> str:
        return "; " + "; ".join(f"{ch} <- {where}" for ch, where in self.plan.channels.items())

    def _can_filters(self) -> list[dict[str, Any]]:
        ids = {self._emcy_id, self._heartbeat_id, *self.plan.pdos}
        if self._sync_id is not None:
            ids.add(self._sync_id)
        # and every node's heartbeat (0x701-0x77F, one frame per node per producer time): a
        # node id that never speaks is told apart from a drive at another id
        return ([{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in sorted(ids)]
                + [{"can_id": 0x700, "can_mask": 0x780, "extended": False}])

    # -- state for STATUS and the health message ------------------------------------------------
    @property
    def device_faults(self) -> tuple[str, ...]:
        """The drive in fault (its EMCY, its statusword's fault bit) or not operational."""
        return self._faults

    def _update_faults(self) -> None:
        node = self.config.node_id
        faults = []
        if self._emcy is not None:
            faults.append(f"node {node} in fault: EMCY {self._emcy}")
        if self._status_fault:
            faults.append(f"node {node} in fault: statusword 0x6041 fault bit set")
        if self._nmt is not None and self._nmt not in (5,):
            faults.append(f"node {node} NMT state "
                          f"{_NMT_STATES.get(self._nmt, hex(self._nmt))}")
        self._faults = tuple(faults)

    def _heartbeat_changed(self, now: float) -> None:
        """The heartbeat went missing, or came back, at frame time ``now`` [s] (as
        :meth:`_on_frame` tests each frame)."""
        age = now - self._heartbeat_since
        self._heartbeat_missing = missing = not self._heartbeat_missing
        if missing:
            self._bump("heartbeat_lost")
            log = logger.debug if self._say_not_heard(age) else logger.warning
            log("CANopen node %d: no heartbeat for %.2f s (producer time %g s): the drive may "
                "be off the bus or its firmware stuck", self.config.node_id, age,
                self.plan.heartbeat_s)
        else:
            logger.warning("CANopen node %d: heartbeat received again", self.config.node_id)
        self._update_silent(now, age if missing else None)

    def _update_silent(self, now: float, heartbeat_age: float | None) -> None:
        silent = []
        if not self._own_heard and self._nodes_heard:
            silent.append(f"node {self.config.node_id} never heard (heard on the bus: "
                          f"{self._heard_text()})")
        if heartbeat_age is not None:
            silent.append(f"node {self.config.node_id} heartbeat for {heartbeat_age:.1f} s "
                          f"(producer time {self.plan.heartbeat_s:g} s)")
        pdos, _ = self._silent_since(now, self._watched, what="CANopen", key="silent_pdos",
                                     quiet=self._say_not_heard)
        self._oldest_seen = min((self._seen.get(name, -math.inf) for name in self._watched),
                                default=math.inf)  # none watched: none can be silent
        self._silent = tuple(silent + pdos)

    def _heard_text(self) -> str:
        """The other nodes heard, for a person: ``node 5 (heartbeat 0x705)``."""
        return ", ".join(f"node {n} ({what})" for n, what in sorted(self._nodes_heard.items()))

    def _say_not_heard(self, age: float) -> bool:
        """While the drive has sent nothing at all but other nodes have: say so once, naming
        them (the node id is likely wrong), and return True (the symptoms, its heartbeat and
        PDOs missing, are then logged at DEBUG only); else False."""
        if self._own_heard or not self._nodes_heard:
            return False
        self.log_once("not-heard", "CANopen node %d not heard on the bus for %.2f s (no "
                      "heartbeat, no PDO of its EDS) while the bus carries %s: is "
                      "driver.node_id right? No sample until it is heard", self.config.node_id,
                      age, self._heard_text())
        return True

    def _other_node(self, cob: int) -> None:
        """Note the node a frame of the predefined connection set comes from (its heartbeat,
        EMCY or a TPDO1-4), when it is not the drive's."""
        node, function = cob & 0x7F, cob & 0x780
        what = {0x700: "heartbeat", 0x080: "EMCY", 0x180: "TPDO1", 0x280: "TPDO2",
                0x380: "TPDO3", 0x480: "TPDO4"}.get(function)
        if what is None or node == 0 or node == self.config.node_id:
            return
        self._nodes_heard.setdefault(node, f"{what} 0x{cob:03X}")

    # -- reading --------------------------------------------------------------------------------
    def _on_frame(self, frame: can.Message) -> Sample | None:
        """Account for one frame; a sample when it completes one."""
        if frame.is_error_frame or frame.is_remote_frame or frame.is_extended_id:
            self._bump("other_frames")
            return None
        cob = frame.arbitration_id
        self._now = now = float(frame.timestamp)
        if self._first_stamp is None:
            self._first_stamp = self._heartbeat_since = now
        data = frame.data
        sample = None
        if cob == self._sync_id:
            sample = self._on_sync(now, data)
        elif (pdo := self._pdos.get(cob)) is not None:
            sample = self._on_pdo(pdo, now, data)
        elif cob == self._emcy_id:
            self._on_emcy(bytes(data), now)
        elif cob == self._heartbeat_id:
            self._on_heartbeat(data, now)
        else:
            self._bump("other_frames")  # another node, or an object not needed
            self._other_node(cob)
        if self._heartbeat_limit and (now - self._heartbeat_since > self._heartbeat_limit
                                      ) != self._heartbeat_missing:
            self._heartbeat_changed(now)
        return sample

    def _on_sync(self, now: float, data: bytes | bytearray) -> Sample | None:
        if self._cycle_t is not None and self._pending:
            self._bump("incomplete_syncs")
            names = [p.name for p in self.plan.pdos.values() if p.cob_id in self._pending]
            msg = ("CANopen SYNC cycle at %.3f s ended without %s: no sample for it; counted "
                   "in stats.extra['incomplete_syncs']")
            if self._own_heard:
                self.log_once("incomplete", msg, self._cycle_t, ", ".join(names))
            else:  # the drive not heard yet: its heartbeat's or PDOs' absence says it
                logger.debug(msg, self._cycle_t, ", ".join(names))
            self._update_silent(now, self._heartbeat_age())  # no sample: say what is missing
        self._skip_cycle = False
        if data and self._counter.modulus is not None:
            self._skip_cycle = self._count(self._counter, data[0] - 1, "CANopen SYNC counter",
                                           shown=1)
        self._cycle_t = now
        self._pending = set(self._every_sync)
        if not self._pending and not self._skip_cycle:
            return self._assemble(now)
        return None

    def _on_pdo(self, pdo: _Pdo, now: float, data: bytes | bytearray) -> Sample | None:
        self._own_heard |= pdo.own  # the drive's own frame (an RPDO is the master's)
        if len(data) * 8 < pdo.bits:
            self.stats.bad_frames += 1
            self._bump("truncated_pdos")
            self.log_once(f"short:{pdo.name}", "CANopen %s (0x%X) has %d bytes, its mapping %d "
                          "bits: truncated, its values not used; counted in stats.bad_frames",
                          pdo.name, pdo.cob_id, len(data), pdo.bits)
            return None
        self._seen[pdo.name] = now
        if now < self._oldest_seen:  # a late frame
            self._oldest_seen = now
        assert pdo.unpack is not None
        raw = pdo.unpack(data)
        latest = self._latest
        for ch, at, factor, offset in pdo.scaled:
            value = raw[at] * factor + offset
            if not math.isfinite(value):
                self.stats.bad_values += 1
                name = next(e.name for c, e, *_ in pdo.channels if c == ch)
                self.log_once(f"nonfinite:{ch}", "CANopen %s -> %s decoded to %s; counted in "
                              "stats.bad_values", name, ch, value)
            latest[ch] = value
        if pdo.status_at is not None:
            self._on_statusword(int(raw[pdo.status_at]))
        if pdo.cob_id == self._sample_pdo:
            return self._assemble(now)
        if self._cycle_t is not None and pdo.cob_id in self._pending:
            self._pending.discard(pdo.cob_id)
            if not self._pending and not self._skip_cycle:
                return self._assemble(self._cycle_t)
        return None

    def _on_statusword(self, word: int) -> None:
        """The statusword's fault bit (bit 3): a change is logged, counted when set and
        updates the drive's faults."""
        fault = bool(word & 0x08)
        if fault != self._status_fault:
            self._status_fault = fault
            if fault:
                self._bump("statusword_faults")
            logger.warning("CANopen node %d: statusword fault bit %s", self.config.node_id,
                           "set: the drive is in fault" if fault else "cleared")
            self._update_faults()

    def _on_emcy(self, data: bytes, now: float) -> None:
        self._own_heard = True
        if len(data) < 3:
            self.stats.bad_frames += 1
            self.log_once("emcy-short", "CANopen EMCY of node %d with %d bytes (8 expected): "
                          "counted in stats.bad_frames", self.config.node_id, len(data))
            return
        from canopen.emcy import EmcyError

        code, register = int.from_bytes(data[:2], "little"), data[2]
        if code & 0xFF00 == 0:
            if self._emcy is not None:
                logger.warning("CANopen node %d: EMCY error reset (was %s)",
                               self.config.node_id, self._emcy)
            self._emcy = None
        else:
            text = f"{EmcyError(code, register, data[3:], now)}, error register 0x{register:02X}"
            if text != self._emcy:
                self._bump("emcy_faults")
                logger.warning("CANopen node %d: EMCY %s: the drive is in fault",
                               self.config.node_id, text)
            self._emcy = text
        self._update_faults()

    def _on_heartbeat(self, data: bytes | bytearray, now: float) -> None:
        self._own_heard = True
        if not data:
            self.stats.bad_frames += 1
            return
        state = data[0] & 0x7F
        if state == 0:
            self._bump("boot_ups")
            logger.warning("CANopen node %d: boot-up message (the drive restarted)",
                           self.config.node_id)
        self._heartbeat_since = now
        if state != self._nmt:
            self._nmt = state
            self._update_faults()

    def _assemble(self, t: float) -> Sample | None:
        self._pending = set()
        self._cycle_t = None
        now = self._now
        assert now is not None
        self._look_for_silence(now)
        latest = self._latest
        if len(latest) < len(self.channels):
            missing = [ch for ch in self.channels if ch not in latest]
            self._bump("incomplete_syncs")
            self.log_once("first", "CANopen sample at %.3f s before %s was received: no sample "
                          "yet", t, ", ".join(missing), level=logging.INFO)
            return None
        if self._silent_logged:  # a PDO every SYNC waits for gives no sample while silent
            gone = {ch for name, chans in self._held.items() if name in self._silent_logged
                    for ch in chans}
            return Sample(t, {ch: latest[ch] for ch in self.channels if ch not in gone})
        if self._in_order is not latest:  # from now on in the channels' order: copied as is
            self._latest = self._in_order = {ch: latest[ch] for ch in self.channels}
        return Sample(t, self._latest.copy())

    def _look_for_silence(self, now: float) -> None:
        """At a sample: the silent PDOs and nodes looked for (:meth:`_update_silent`) only
        when one can be (one is, the oldest PDO is older than ``silent_after``, or another
        node speaks while this one does not)."""
        if (self._silent or now - self._oldest_seen > self.config.silent_after
                or (self._nodes_heard and not self._own_heard)):
            self._update_silent(now, self._heartbeat_age())

    def _heartbeat_age(self) -> float | None:
        if not self._heartbeat_missing or self._now is None:
            return None
        return self._now - self._heartbeat_since
