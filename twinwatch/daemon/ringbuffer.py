"""Fixed-size ring buffer that turns a stream of samples into acquisition windows.

The acquisition side appends one sample at a time; every ``window`` consecutive good samples
become one :class:`~twinwatch.twin.model.WindowData`. Memory is allocated once.

A window is only ever made of consecutive, finite samples on a regular clock: a time-stamp gap
(more than ``max_gap`` sample periods), a jump backwards, a missing channel or a NaN/inf value
abandons the partial window (logged once per reason) and acquisition starts a fresh window at
the next good sample. Nothing is estimated silently on broken data.

Loss accounting: :attr:`RingBuffer.lost` counts, by reason, the samples received that did not
become part of a window (the bad sample itself and the good ones of the partial window it
cut). :attr:`RingBuffer.discarded` counts, by reason, the *windows* abandoned: a stretch of
lost samples between two completed windows costs ``ceil(lost / window)`` windows, so a source
whose every other sample is NaN loses 20 windows over 20 windows of samples, not one per cut.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Mapping, Sequence

import numpy as np

from twinwatch.twin.model import WindowData

logger = logging.getLogger(__name__)


class RingBuffer:
    """Ring buffer of samples for a fixed set of channels.

    Args:
        channels: channel names stored (others in a sample are ignored).
        window: samples per window (default 200).
        sample_period: nominal sample period [s].
        capacity: ring size in samples (default 4 windows).
        max_gap: largest allowed step between time stamps, in sample periods.
        first_index: index of the first window (a reload goes on from the last window of the
            run instead of numbering from 0 again).
    """

    def __init__(
        self,
        channels: Sequence[str],
        *,
        window: int = 200,
        sample_period: float = 0.01,
        capacity: int | None = None,
        max_gap: float = 1.5,
        first_index: int = 0,
    ) -> None:
        if window < 2:
            raise ValueError("window must hold at least 2 samples")
        self.channels = tuple(channels)
        self.window = window
        self.sample_period = sample_period
        self.capacity = capacity or 4 * window
        if self.capacity < window:
            raise ValueError("capacity must be at least one window")
        self.max_gap = max_gap
        self._t = np.empty(self.capacity)
        self._v = np.empty((self.capacity, len(self.channels)))
        self._head = 0  # next write position
        self._count = 0  # samples in the current (partial) window
        self._last_t: float | None = None
        self._windows = 0
        self.first_index = first_index
        self.discarded: Counter[str] = Counter()  #: reason -> windows abandoned
        self.lost: Counter[str] = Counter()  #: reason -> samples received but not in a window
        self.samples = 0  #: samples received
        self.bad_samples = 0
        self._stretch_lost = 0  # samples lost since the last completed window
        self._stretch_windows = 0  # windows counted as abandoned for them
        self._warned: set[str] = set()
        self._next_window: int | None = None

    def request_window(self, n: int) -> None:
        """Make the next window that starts ``n`` samples long (the adaptive window; called
        from the worker thread: the length is read when a window starts, so a window never
        changes length half-way).

        Raises:
            ValueError: ``n`` below 2 or above the ring's capacity.
        """
        if not 2 <= n <= self.capacity:
            raise ValueError(f"a window of {n} samples does not fit the ring buffer "
                             f"(2 .. {self.capacity})")
        self._next_window = int(n)

    def _lose(self, reason: str, n: int) -> None:
        """Account ``n`` lost samples to ``reason`` (see the module docstring)."""
        if n <= 0:
            return
        self.lost[reason] += n
        self._stretch_lost += n
        windows = -(-self._stretch_lost // self.window)
        if windows > self._stretch_windows:
            self.discarded[reason] += windows - self._stretch_windows
            self._stretch_windows = windows

    def _abandon(self, reason: str, t: float, bad: int = 0) -> None:
        self._lose(reason, self._count + bad)
        msg = "%s at t=%.3f s: partial window of %d samples abandoned, a fresh window starts"
        if reason not in self._warned:
            self._warned.add(reason)
            logger.warning(msg + " (logged once per reason; counted in health counters)",
                           reason, t, self._count)
        else:
            logger.debug(msg, reason, t, self._count)
        self._count = 0

    def append(self, t: float, values: Mapping[str, float]) -> WindowData | None:
        """Add one sample; return a completed window, else None.

        Missing channels and non-finite values abandon the partial window (counted).
        """
        self.samples += 1
        if self._last_t is not None:
            dt = t - self._last_t
            if dt <= 0:
                self._abandon("time stamp jumped backwards or repeated", t)
            elif dt > self.max_gap * self.sample_period:
                self._abandon("time stamp gap", t)
        self._last_t = t
        try:
            row = [float(values[c]) for c in self.channels]
        except KeyError as exc:
            self.bad_samples += 1
            self._abandon(f"sample without channel {exc.args[0]!r}", t, bad=1)
            return None
        if not all(np.isfinite(row)):
            self.bad_samples += 1
            bad = [c for c, v in zip(self.channels, row, strict=True) if not np.isfinite(v)]
            self._abandon(f"NaN or inf in {', '.join(repr(c) for c in bad)}", t, bad=1)
            self._last_t = t
            return None
        if self._count == 0 and self._next_window is not None:
            self.window, self._next_window = self._next_window, None
        self._t[self._head] = t
        self._v[self._head] = row
        self._head = (self._head + 1) % self.capacity
        self._count += 1
        if self._count < self.window:
            return None
        self._count = 0
        self._stretch_lost = self._stretch_windows = 0
        idx = (self._head - self.window + np.arange(self.window)) % self.capacity
        win = WindowData(
            t=self._t[idx].copy(),
            channels={c: self._v[idx, j].copy() for j, c in enumerate(self.channels)},
            index=self.first_index + self._windows,
        )
        self._windows += 1
        return win

    @property
    def windows(self) -> int:
        """Windows completed so far."""
        return self._windows

    @property
    def pending(self) -> int:
        """Samples in the partial window being filled."""
        return self._count
