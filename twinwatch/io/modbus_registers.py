"""The Modbus register map and its codec, shared by the Modbus driver
(:mod:`twinwatch.drivers.modbus`, which reads registers) and the simulated Modbus plant
(:mod:`twinwatch.plant.modbus_server`, which serves them).

Bytes inside a register are big-endian. The conversion is pymodbus' own
:meth:`~pymodbus.client.mixin.ModbusClientMixin.convert_from_registers` /
``convert_to_registers``, imported on first use (so loading a configuration does not load
pymodbus).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

from pydantic import ConfigDict, Field, StrictInt, model_validator

from twinwatch._table import StrictTable
from twinwatch.io.sample import ScaledChannel

if TYPE_CHECKING:
    from pymodbus.client.mixin import ModbusClientMixin

__all__ = [
    "FUNCTION_CODES",
    "MAX_READ_REGISTERS",
    "ModbusChannelMap",
    "ModbusCounterMap",
    "ModbusRegister",
    "RegisterBlock",
    "RegisterTable",
    "RegisterType",
    "WordOrder",
    "check_overlaps",
    "plan_blocks",
]

RegisterType = Literal["int16", "uint16", "int32", "uint32", "float32"]
RegisterTable = Literal["input", "holding"]
WordOrder = Literal["big", "little"]

#: Largest number of registers one read request (function code 3 or 4) may ask for.
MAX_READ_REGISTERS = 125
#: Function code of a read request per table.
FUNCTION_CODES: Mapping[str, int] = {"holding": 3, "input": 4}

#: register type -> name of pymodbus' ``ModbusClientMixin.DATATYPE`` member
_DATATYPE: Mapping[str, str] = {
    "int16": "INT16",
    "uint16": "UINT16",
    "int32": "INT32",
    "uint32": "UINT32",
    "float32": "FLOAT32",
}
#: (min, max) of the integer types
_INT_RANGE: Mapping[str, tuple[int, int]] = {
    "int16": (-(1 << 15), (1 << 15) - 1),
    "uint16": (0, (1 << 16) - 1),
    "int32": (-(1 << 31), (1 << 31) - 1),
    "uint32": (0, (1 << 32) - 1),
}


@functools.cache
def _mixin() -> type[ModbusClientMixin]:
    """pymodbus' register converter, imported on first use."""
    from pymodbus.client.mixin import ModbusClientMixin

    return ModbusClientMixin


class ModbusRegister(StrictTable):
    """Where a value lives on the device and how it is encoded.

    Attributes:
        address: 0-based address of the first register (the PDU address).
        table: ``"input"`` (function code 4) or ``"holding"`` (function code 3) registers.
        type: ``int16``, ``uint16`` (one register), ``int32``, ``uint32``, ``float32``
            (IEEE 754 single; two registers).
        word_order: for two-register types: ``"big"`` = high word at ``address``,
            ``"little"`` = low word at ``address``.
    """

    model_config = ConfigDict(frozen=True)

    address: StrictInt = Field(ge=0, le=65535)
    table: RegisterTable = "holding"
    type: RegisterType = "float32"
    word_order: WordOrder = "big"

    @model_validator(mode="after")
    def _fits(self) -> ModbusRegister:
        if self.address + self.count - 1 > 65535:
            raise ValueError(f"a {self.type} at address {self.address} runs past 65535")
        return self

    @property
    def count(self) -> int:
        """Number of 16-bit registers the value takes (1 or 2)."""
        return 1 if self.type in ("int16", "uint16") else 2

    @property
    def end(self) -> int:
        """One past the last register's address."""
        return self.address + self.count

    def decode(self, registers: Sequence[int]) -> float:
        """Decode ``registers`` (exactly :attr:`count` of them) to the raw number.

        Raises:
            ModbusException: wrong number of registers.
        """
        mixin = _mixin()
        value = mixin.convert_from_registers(
            list(registers), getattr(mixin.DATATYPE, _DATATYPE[self.type]),
            word_order=self.word_order
        )
        if not isinstance(value, int | float):  # pragma: no cover - one value, numeric type
            from pymodbus.exceptions import ModbusException

            raise ModbusException(f"{self.type} decoded to {value!r}")
        return float(value)

    def encode(self, raw: float) -> tuple[list[int], bool]:
        """Encode the raw number into :attr:`count` registers (integer types round and saturate;
        NaN becomes 0).

        Returns:
            (registers, exact): ``exact`` is False when the value had to be saturated or was
            NaN for an integer type.
        """
        exact = True
        value: int | float
        if self.type == "float32":
            value = float(raw)
        else:
            lo, hi = _INT_RANGE[self.type]
            if math.isnan(raw):
                value, exact = 0, False
            else:
                clipped = min(max(raw, lo), hi)
                exact = clipped == raw
                value = int(round(clipped))
        mixin = _mixin()
        regs = mixin.convert_to_registers(
            value, getattr(mixin.DATATYPE, _DATATYPE[self.type]), word_order=self.word_order
        )
        return regs, exact

    def describe(self) -> str:
        """``"holding 10-11 (float32, big)"`` for messages."""
        span = str(self.address) if self.count == 1 else f"{self.address}-{self.end - 1}"
        return f"{self.table} {span} ({self.type}, {self.word_order} word order)"


class ModbusChannelMap(ScaledChannel, ModbusRegister):
    """One twin channel's register: ``value_twin = raw * scale + offset``.

    ``raw`` is the decoded register value (an integer, or the float32 as stored); ``unit``
    documents the twin-side unit.
    """


class ModbusCounterMap(ModbusRegister):
    """The device's sample-counter register (incremented by one per sample)."""

    type: Literal["uint16", "uint32"] = "uint32"

    @property
    def modulus(self) -> int:
        """The counter wraps modulo this (2**16 or 2**32)."""
        return 1 << (16 * self.count)


@dataclass(frozen=True, slots=True)
class RegisterBlock:
    """One read request: ``count`` registers of ``table`` from ``address`` on."""

    table: RegisterTable
    address: int
    count: int

    def covers(self, reg: ModbusRegister) -> bool:
        return (
            reg.table == self.table
            and reg.address >= self.address
            and reg.end <= self.address + self.count
        )


def plan_blocks(
    registers: Iterable[ModbusRegister], *, first: ModbusRegister | None = None
) -> list[RegisterBlock]:
    """Group registers into as few read requests as possible.

    One block per table from its lowest to its highest register, split where a block would
    exceed :data:`MAX_READ_REGISTERS` (a value is never split across two blocks).

    Args:
        first: put the block holding this register first (the counter in lock-step).

    Returns:
        The blocks, the one holding ``first`` first, then input before holding registers.
    """
    by_table: dict[str, list[ModbusRegister]] = {}
    for reg in registers:
        by_table.setdefault(reg.table, []).append(reg)
    blocks: list[RegisterBlock] = []
    for table in ("input", "holding"):
        regs = sorted(by_table.get(table, []), key=lambda r: r.address)
        start: int | None = None
        end = 0
        for reg in regs:
            if start is None:
                start, end = reg.address, reg.end
            elif max(end, reg.end) - start <= MAX_READ_REGISTERS:
                end = max(end, reg.end)
            else:
                blocks.append(RegisterBlock(table, start, end - start))
                start, end = reg.address, reg.end
        if start is not None:
            blocks.append(RegisterBlock(table, start, end - start))
    if first is not None:
        blocks.sort(key=lambda b: not b.covers(first))
    return blocks


def check_overlaps(entries: Mapping[str, ModbusRegister]) -> None:
    """Refuse two entries that share a register of the same table.

    Args:
        entries: config key (``"registers.x"``, ``"counter"``) -> register.

    Raises:
        ValueError: naming both keys and the registers.
    """
    items = sorted(entries.items(), key=lambda kv: (kv[1].table, kv[1].address))
    for (key_a, a), (key_b, b) in zip(items, items[1:], strict=False):
        if a.table == b.table and b.address < a.end:
            raise ValueError(f"{key_b} ({b.describe()}) overlaps {key_a} ({a.describe()})")
