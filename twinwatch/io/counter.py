"""A source's sample counter, unwrapped: new samples, gaps, duplicates, late frames, restarts.

A device that numbers its samples (a CAN drive's 8-bit rolling counter, a Modbus register
incremented once per sample) lets the reader tell a new sample from a repeated one and count
the ones it missed. The counter wraps modulo ``2**bits``; :class:`SampleCounter` keeps the
unwrapped count, which times the sample (``t = count * sample_period``), and classifies each
reading:

* ``"next"``: one or more steps forward; ``missing = step - 1`` samples were not seen (a gap);
* ``"duplicate"``: the same value again (a repeated frame, a poll faster than the device
  samples): skip it;
* ``"stale"``: a few steps back (at most :attr:`SampleCounter.reorder`): a frame that arrived
  late, after a newer one: skip it, keeping the count;
* ``"reset"``: further back, or stale readings several times in a row (:attr:`streak`): the
  device restarted; the count restarts from the new value.

The first reading starts the count (``"first"``). Shared by the CAN and Modbus drivers.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

__all__ = ["CounterStep", "SampleCounter"]

CounterStep = Literal["first", "next", "duplicate", "stale", "reset"]


@dataclass
class SampleCounter:
    """The unwrapped count of a sample counter.

    Args:
        modulus: the counter wraps modulo this (``2**bits``); None for a counter that does not
            wrap (a float or signed signal).
        reorder: the largest step back taken as a late frame (default 8 samples, at most a
            quarter of the modulus: a gateway or an adapter reorders frames within a burst;
            further back is a restart).
        streak: stale readings in a row that mean a restart, not reordering (default 3).

    Attributes:
        raw: the last counter value accepted (None before the first).
        count: the unwrapped count of that value (None before the first).
    """

    modulus: int | None = None
    reorder: int | None = None
    streak: int = 3
    raw: int | None = None
    count: int | None = None
    _stale_run: int = 0

    def __post_init__(self) -> None:
        if self.reorder is None:
            self.reorder = 8 if self.modulus is None else max(1, min(8, self.modulus // 4))

    def update(self, raw: int) -> tuple[CounterStep, int]:
        """Account for one counter reading.

        Returns:
            ``(step, missing)``: the classification (see the module docstring) and, for
            ``"next"``, the samples missed before this one (0 otherwise).
        """
        if self.raw is None or self.count is None:
            self.raw, self.count = raw, raw
            return "first", 0
        step = raw - self.raw
        if self.modulus is not None:
            step %= self.modulus
            if step >= self.modulus // 2:
                step -= self.modulus  # backwards
        if step == 0:
            self._stale_run = 0
            return "duplicate", 0
        if step < 0:
            assert self.reorder is not None
            self._stale_run += 1
            if -step <= self.reorder and self._stale_run < self.streak:
                return "stale", 0
            self._stale_run = 0
            self.raw, self.count = raw, raw
            return "reset", 0
        self._stale_run = 0
        self.raw = raw
        self.count += step
        return "next", step - 1
