"""Fixed-size ring buffer that turns a stream of samples into acquisition windows.

The acquisition side appends one sample at a time; every ``window`` consecutive good samples
become one :class:`~twinwatch.twin.model.WindowData`. Memory is allocated once. The rules
(docs/sources.md, docs/runtime.md) in short:

* sample ``k`` of a window belongs to slot ``t_first + k * T`` (``T`` the nominal
  ``sample_period``); its offsets ``o_k = t_k - t_first - k * T`` must lie within a band
  narrower than ``2 * tol * T`` (``tol`` = ``[acquisition] jitter_tolerance``, at most 0.5).
  A sample that would widen the band is classified by its distance ``rho`` (in periods) from
  the band's centre: ``rho >= 1 - tol`` is a *gap*; otherwise (or offsets on a line leaving
  the band: a clock at another rate) *jitter beyond tolerance*. A stamp before the previous
  one: *time stamp jumped backwards*; the previous stamp with other values: *time stamp
  repeated with other values* (that sample is dropped too). An exact duplicate is dropped and
  counted. A band, not a distance from the mean, because a poll clock's jitter is one-sided
  (a poll is late, never early).
* a completed window is put on its grid ``t0 + k * T`` (``t0`` the mean offset); the stamps'
  residuals (:attr:`WindowData.stamp_jitter`, RMS and maximum) travel with it. Stamps within
  :data:`GRID_EXACT` periods of the grid are kept as they are.
* up to ``max_missing_run`` missing samples in a row and ``max_missing`` of a window are
  filled (zero-order hold, stamped at the band's centre); with both at 0 (the default) every
  missing sample abandons its window.
* a longer gap, a stamp going back, jitter beyond tolerance, a missing channel or a NaN/inf
  abandons the partial window (logged once per reason); a fresh window starts at the next
  good sample.

Loss accounting: :attr:`RingBuffer.lost` counts by reason the samples that did not become part
of a window; :attr:`RingBuffer.discarded` the *windows* abandoned (a stretch of lost samples
between two completed windows costs ``ceil(lost / window)``); :attr:`RingBuffer.causes` the
same windows by cause (:data:`CAUSES`), the health counters ``windows_abandoned_<cause>``.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Mapping, Sequence
from typing import Literal

import numpy as np

from twinwatch.twin.model import WindowData

logger = logging.getLogger(__name__)

__all__ = ["CAUSES", "GRID_EXACT", "MAX_JITTER_TOLERANCE", "Cause", "RingBuffer"]

Cause = Literal["gap", "time_back", "jitter", "bad_value", "missing_channel"]
#: Why a window is abandoned, the suffixes of the health counters ``windows_abandoned_<cause>``.
CAUSES: tuple[Cause, ...] = ("gap", "time_back", "jitter", "bad_value", "missing_channel")
#: The largest ``jitter_tolerance`` [periods]: a band of offsets one period wide or wider
#: cannot tell a late sample from the next one.
MAX_JITTER_TOLERANCE = 0.5
#: Offsets are compared with the band less this many periods: a stamp exactly one period late
#: (a missing sample on an exact clock) is a gap at tolerance 0.5 whatever the rounding.
_BAND_MARGIN = 1e-6
#: A steady drift is told from a gap only over this many samples of a window.
_DRIFT_MIN_SAMPLES = 10
#: Stamps within this fraction of a period of their grid are kept as they are (exact sources).
GRID_EXACT = 1e-6
#: The reason an exact duplicate sample is counted under in :attr:`RingBuffer.lost`.
_DUPLICATE = "exact duplicates dropped (same time stamp, same values: a logger's retry)"


class RingBuffer:
    """Ring buffer of samples for a fixed set of channels.

    Args:
        channels: channel names stored (others in a sample are ignored).
        window: samples per window (default 200).
        sample_period: nominal sample period ``T`` [s]: the grid the windows are placed on.
        capacity: ring size in samples (default 4 windows).
        jitter_tolerance: half the widest band a window's stamp offsets from their grid
            slots may span, in sample periods (0 < tolerance <= 0.5; see the module
            docstring).
        first_index: index of the first window (a reload goes on from the run's last).
        max_missing: the largest fraction of a window's samples that may be missing and
            filled (0 <= fraction < 1; 0: none).
        max_missing_run: the most missing samples in a row that are filled [samples; 0:
            none].

    Raises:
        ValueError: ``window`` < 2, ``capacity`` below one window, a tolerance outside
            (0, 0.5], or a missing-sample limit out of its range.
    """

    def __init__(
        self,
        channels: Sequence[str],
        *,
        window: int = 200,
        sample_period: float = 0.01,
        capacity: int | None = None,
        jitter_tolerance: float = MAX_JITTER_TOLERANCE,
        first_index: int = 0,
        max_missing: float = 0.0,
        max_missing_run: int = 0,
    ) -> None:
        if window < 2:
            raise ValueError("window must hold at least 2 samples")
        if not 0 < jitter_tolerance <= MAX_JITTER_TOLERANCE:
            raise ValueError(f"jitter_tolerance must be in (0, {MAX_JITTER_TOLERANCE}] sample "
                             f"periods, not {jitter_tolerance}")
        self.channels = tuple(channels)
        self.window = window
        self.sample_period = sample_period
        self.capacity = capacity or 4 * window
        if self.capacity < window:
            raise ValueError("capacity must be at least one window")
        self.jitter_tolerance = jitter_tolerance
        if not 0.0 <= max_missing < 1.0 or max_missing_run < 0:
            raise ValueError(f"max_missing must be a fraction in [0, 1) and max_missing_run "
                             f">= 0 samples, not {max_missing} and {max_missing_run}")
        self.max_missing = float(max_missing)
        self.max_missing_run = int(max_missing_run)
        self._t = np.empty(self.capacity)
        self._v = np.empty((self.capacity, len(self.channels)))
        self._filled = np.zeros(self.capacity, dtype=bool)  # slot filled (no sample of its own)
        self._head = 0  # next write position
        self._count = 0  # samples in the current (partial) window, filled slots included
        self._n_filled = 0  # filled slots in the current (partial) window
        self._fill = 0  # slots to fill before the sample being appended (set by _check_time)
        self._lo = self._hi = 0.0  # band of the partial window's offsets t_k - t_first - k*T
        self._sums = (0.0, 0.0, 0.0, 0.0)  # sum k, k^2, offset, k*offset (the drift line)
        self._t_first = 0.0  # stamp of the partial window's first sample
        self._last_t: float | None = None
        self._last_row: list[float] | None = None  # values of the last sample in a window
        self.duplicates = 0  #: exact duplicates dropped (same stamp, same values)
        self._windows = 0
        self.first_index = first_index
        self.discarded: Counter[str] = Counter()  #: reason -> windows abandoned
        self.causes: Counter[str] = Counter({c: 0 for c in CAUSES})  #: cause -> windows
        self.lost: Counter[str] = Counter()  #: reason -> samples received but not in a window
        self.samples = 0  #: samples received
        self.bad_samples = 0
        self.missing = 0  #: missing samples filled in completed windows (held values)
        self.windows_filled = 0  #: completed windows with at least one filled slot
        self._stretch_lost = 0  # samples lost since the last completed window
        self._stretch_windows = 0  # windows counted as abandoned for them
        self._warned: set[str] = set()
        self._next_window: int | None = None

    def request_window(self, n: int) -> None:
        """Make the next window that starts ``n`` samples long (the adaptive window; called
        from the worker thread: a window never changes length half-way).

        Raises:
            ValueError: ``n`` below 2 or above the ring's capacity.
        """
        if not 2 <= n <= self.capacity:
            raise ValueError(f"a window of {n} samples does not fit the ring buffer "
                             f"(2 .. {self.capacity})")
        self._next_window = int(n)

    @property
    def window_requested(self) -> bool:
        """A :meth:`request_window` not yet taken by a window start."""
        return self._next_window is not None

    def _lose(self, reason: str, cause: Cause, n: int) -> None:
        """Account ``n`` lost samples to ``reason`` (see the module docstring)."""
        if n <= 0:
            return
        self.lost[reason] += n
        self._stretch_lost += n
        windows = -(-self._stretch_lost // self.window)
        if windows > self._stretch_windows:
            self.discarded[reason] += windows - self._stretch_windows
            self.causes[cause] += windows - self._stretch_windows
            self._stretch_windows = windows

    def _abandon(self, reason: str, cause: Cause, t: float, bad: int = 0,
                 detail: str = "") -> None:
        received = self._count - self._n_filled
        self._lose(reason, cause, received + bad)
        msg = "%s at t=%.6f s%s: partial window of %d samples abandoned, a fresh window starts"
        if reason not in self._warned:
            self._warned.add(reason)
            logger.warning(msg + " (logged once per reason; counted in health counters)",
                           reason, t, detail, received)
        else:
            logger.debug(msg, reason, t, detail, received)
        self._count = 0
        self._n_filled = 0
        self._fill = 0

    def _check_time(self, t: float) -> None:
        """Match ``t`` to the partial window's grid; abandon the window if it does not fit."""
        if self._last_t is None or self._count == 0:
            return
        if t < self._last_t:
            self._abandon("time stamp jumped backwards", "time_back", t,
                          detail=f" ({self._last_t - t:.6g} s back: a capture that restarts its "
                          f"clock, or a clock set back)")
            return
        if t == self._last_t:  # the previous sample again, after one that was not kept
            self._abandon("time stamp repeated with other values", "time_back", t)
            return
        period = self.sample_period
        n = self._count
        offset = (t - self._t_first) - n * period
        lo, hi = min(self._lo, offset), max(self._hi, offset)
        tol = self.jitter_tolerance
        if hi - lo < (2.0 * tol - _BAND_MARGIN) * period:
            return
        drift = self._drift(n, offset)
        rho = (offset - 0.5 * (self._lo + self._hi)) / period
        if drift is not None:
            self._abandon(
                "time stamp jitter beyond tolerance", "jitter", t,
                detail=f" (the stamps step by {drift:.6g} s on average, not by "
                f"acquisition.sample_period = {period:g} s: they drift off the grid; is the "
                f"period right?)")
        elif rho >= 1.0 - tol:
            m, why = self._fillable(n, offset)
            if m:
                self._fill = m
                return
            self._abandon("time stamp gap", "gap", t,
                          detail=f" ({rho:.2f} periods after its slot: about "
                          f"{max(1, round(rho))} samples missing{why})")
        else:
            self._abandon(
                "time stamp jitter beyond tolerance", "jitter", t,
                detail=f" ({rho:+.2f} periods from the window's slots, which span "
                f"{(self._hi - self._lo) / period:.2f} periods; the band may not reach "
                f"{2 * tol:g}: a clock that jitters this much; a sample counter as time "
                f"source avoids it)")

    def _fillable(self, n: int, offset: float) -> tuple[int, str]:
        """How many missing slots to fill before the sample at ``offset`` [s] from slot ``n``
        (0 when it is not to be filled) and, when not, why (for the gap's line)."""
        if self.max_missing_run == 0 or self.max_missing == 0:
            return 0, ""
        period = self.sample_period
        m = round((offset - 0.5 * (self._lo + self._hi)) / period)
        if m < 1:
            return 0, ""
        if m > self.max_missing_run:
            return 0, (f"; more than acquisition.max_missing_run = {self.max_missing_run} "
                       f"in a row")
        budget = self.missing_budget
        if self._n_filled + min(m, self.window - n) > budget:
            return 0, (f"; with the {self._n_filled} missing before, more than "
                       f"acquisition.max_missing = {self.max_missing:g} of the window allows "
                       f"({budget} of {self.window})")
        shifted = offset - m * period
        lo, hi = min(self._lo, shifted), max(self._hi, shifted)
        if hi - lo >= (2.0 * self.jitter_tolerance - _BAND_MARGIN) * period:
            return 0, ""  # not on a later slot either: jitter and a gap
        return m, ""

    def _fill_slots(self, m: int, t: float) -> WindowData | None:
        """Fill ``m`` missing slots with the previous sample's values (a zero-order hold);
        the window they complete, if they do (the sample at ``t`` then starts the next)."""
        prev = self._v[(self._head - 1) % self.capacity].copy()
        centre = 0.5 * (self._lo + self._hi)
        if "missing" not in self._warned:
            self._warned.add("missing")
            logger.warning(
                "%d samples missing before t=%.6f s: their slots hold the previous sample's "
                "values and the window goes on (up to %d samples in a row and %d of a window "
                "of %d: acquisition.max_missing_run, acquisition.max_missing); logged once, "
                "counted in samples_missing", m, t, self.max_missing_run, self.missing_budget,
                self.window)
        for _ in range(m):
            head = self._head
            self._t[head] = self._t_first + self._count * self.sample_period + centre
            self._v[head] = prev
            self._filled[head] = True
            self._head = (head + 1) % self.capacity
            self._count += 1
            self._n_filled += 1
            if self._count == self.window:
                return self._complete()
        return None

    def _repeated(self, t: float, values: Mapping[str, float]) -> bool:
        """A sample stamped as the previous one: True when it is dropped (an exact duplicate,
        or other values: the partial window is abandoned too); False after a sample that was
        not kept (it is taken as a new sample)."""
        if self._last_row is None:
            return False
        try:
            row = [float(values[c]) for c in self.channels]
        except KeyError:
            row = None
        if row == self._last_row:
            self.duplicates += 1
            self.lost[_DUPLICATE] += 1
            if _DUPLICATE not in self._warned:
                self._warned.add(_DUPLICATE)
                logger.warning("%s at t=%.6f s (logged once; counted)", _DUPLICATE, t)
            return True
        self._abandon("time stamp repeated with other values", "time_back", t, bad=1,
                      detail=" (which of the two samples is the plant's is unknown: both "
                      "dropped)")
        self._last_row = None
        return True

    def _drift(self, n: int, offset: float) -> float | None:
        """The mean step [s] of stamps that drift off the grid at a steady rate (a clock at
        another rate than the period), when the offsets so far and ``offset`` (sample ``n``)
        lie on a line within the tolerance and that line spans the band; else None."""
        points = n - self._n_filled  # the filled slots have no stamp of their own
        if points < _DRIFT_MIN_SAMPLES:
            return None
        sk, sk2, so, sko = self._sums
        den = points * sk2 - sk * sk
        slope = (points * sko - sk * so) / den
        icpt = (so - slope * sk) / points
        period = self.sample_period
        tol = self.jitter_tolerance * period
        if abs(offset - (icpt + slope * n)) > 0.5 * tol or abs(slope * n) < tol:
            return None
        return period + slope

    def append(self, t: float, values: Mapping[str, float]) -> WindowData | None:
        """Add one sample (time stamp ``t`` [s] on the source's clock); return a completed
        window, else None (the rules: see the module docstring).
        """
        self.samples += 1
        if not math.isfinite(t):  # no slot on the grid: the sample and the partial window go
            self.bad_samples += 1
            self._abandon("time stamp NaN or inf", "bad_value", math.nan, bad=1)
            return None
        if t == self._last_t and self._repeated(t, values):
            return None
        self._check_time(t)
        fill, self._fill = self._fill, 0
        self._last_t = t
        self._last_row = None
        try:
            row = [float(values[c]) for c in self.channels]
        except KeyError as exc:
            self.bad_samples += 1
            self._abandon(f"sample without channel {exc.args[0]!r}", "missing_channel", t,
                          bad=1)
            return None
        if not all(map(math.isfinite, row)):  # a tenth of np.isfinite's CPU on five floats
            self.bad_samples += 1
            bad = [c for c, v in zip(self.channels, row, strict=True) if not math.isfinite(v)]
            self._abandon(f"NaN or inf in {', '.join(repr(c) for c in bad)}", "bad_value", t,
                          bad=1)
            return None
        done = self._fill_slots(fill, t) if fill else None
        if self._count == 0 and self._next_window is not None:
            self.window, self._next_window = self._next_window, None
        if self._count == 0:
            self._t_first = t
            self._lo = self._hi = 0.0
            self._sums = (0.0, 0.0, 0.0, 0.0)
        else:
            k = self._count
            offset = (t - self._t_first) - k * self.sample_period
            self._lo, self._hi = min(self._lo, offset), max(self._hi, offset)
            sk, sk2, so, sko = self._sums
            self._sums = (sk + k, sk2 + k * k, so + offset, sko + k * offset)
        self._t[self._head] = t
        self._v[self._head] = row
        self._filled[self._head] = False
        self._last_row = row
        self._head = (self._head + 1) % self.capacity
        self._count += 1
        if done is not None:  # missing slots completed a window; this sample starts the next
            return done
        if self._count < self.window:
            return None
        return self._complete()

    def append_block(self, t: np.ndarray, values: np.ndarray) -> list[WindowData]:
        """Add ``N`` samples at once; return the windows they complete, in order.

        The same windows, counters, gaps, fills and drops as :meth:`append` called on each
        sample in turn (``append(t[i], dict(zip(channels, values[i])))``): the stretches of
        samples that fall in the partial window's band, in order, finite and not the
        window's first are stored together (their stamps' offsets, the band and the drift
        line's sums computed with numpy in the order :meth:`append` computes them); every
        other sample goes through :meth:`append`.

        Args:
            t: (N,) time stamps [s] on the source's clock.
            values: (N, C) the samples' values, the columns in the order of
                :attr:`channels`.

        Raises:
            ValueError: ``t`` and ``values`` do not have these shapes.
        """
        t = np.asarray(t, dtype=np.float64)
        values = np.asarray(values, dtype=np.float64)
        n = t.shape[0]
        if t.ndim != 1 or values.shape != (n, len(self.channels)):
            raise ValueError(f"expected t (N,) and values (N, {len(self.channels)}), got "
                             f"{t.shape} and {values.shape}")
        ok = np.isfinite(t) & np.isfinite(values).all(axis=1)
        windows: list[WindowData] = []
        i = 0
        while i < n:
            m = self._plain_run(t, ok, i) if self._count else 0
            if m == 0:
                win = self.append(float(t[i]), dict(zip(self.channels, values[i].tolist(),
                                                        strict=True)))
                i += 1
            else:
                win = self._store_run(t[i:i + m], values[i:i + m])
                i += m
            if win is not None:
                windows.append(win)
        return windows

    def _plain_run(self, t: np.ndarray, ok: np.ndarray, i: int) -> int:
        """How many samples from ``t[i]`` on :meth:`append` would store without a second
        look, up to the end of the partial window: finite, each stamp after the one before,
        every offset within the band (:meth:`_check_time`'s first return)."""
        assert self._last_t is not None
        k0 = self._count
        end = min(t.shape[0], i + self.window - k0)
        stamps = t[i:end]
        prev = np.concatenate(([self._last_t], stamps[:-1]))
        k = np.arange(k0, k0 + stamps.shape[0])
        offsets = (stamps - self._t_first) - k * self.sample_period
        lo = np.minimum.accumulate(np.concatenate(([self._lo], offsets)))[1:]
        hi = np.maximum.accumulate(np.concatenate(([self._hi], offsets)))[1:]
        band = (2.0 * self.jitter_tolerance - _BAND_MARGIN) * self.sample_period
        plain = ok[i:end] & (stamps > prev) & (hi - lo < band)
        return int(stamps.shape[0] if plain.all() else np.argmin(plain))

    def _store_run(self, t: np.ndarray, values: np.ndarray) -> WindowData | None:
        """Store ``m`` samples :meth:`_plain_run` admitted, as :meth:`append` stores each;
        the window they complete, if they do."""
        m = t.shape[0]
        k = np.arange(self._count, self._count + m)
        offsets = (t - self._t_first) - k * self.sample_period
        # min and max keep the first of equal values (0.0 and -0.0), as append's do
        self._lo = min(self._lo, float(offsets[np.argmin(offsets)]))
        self._hi = max(self._hi, float(offsets[np.argmax(offsets)]))
        kf = k.astype(np.float64)
        terms = np.stack((kf, (k * k).astype(np.float64), offsets, kf * offsets))
        sums = np.add.accumulate(  # one addition after another, as append adds them
            np.concatenate((np.array(self._sums)[:, None], terms), axis=1), axis=1)[:, -1]
        self._sums = (float(sums[0]), float(sums[1]), float(sums[2]), float(sums[3]))
        slots = (self._head + np.arange(m)) % self.capacity
        self._t[slots] = t
        self._v[slots] = values
        self._filled[slots] = False
        self._head = (self._head + m) % self.capacity
        self._count += m
        self.samples += m
        self._last_t = float(t[-1])
        self._last_row = values[-1].tolist()
        if self._count < self.window:
            return None
        return self._complete()

    def _complete(self) -> WindowData:
        """The window of the last ``window`` slots; a fresh window starts."""
        if self._n_filled:
            self.missing += self._n_filled
            self.windows_filled += 1
        self._count = self._n_filled = 0
        self._stretch_lost = self._stretch_windows = 0
        idx = (self._head - self.window + np.arange(self.window)) % self.capacity
        stamps = self._t[idx].copy()
        t_win, jitter = self._on_grid(stamps, self._filled[idx])
        win = WindowData(
            t=t_win,
            channels={c: self._v[idx, j].copy() for j, c in enumerate(self.channels)},
            index=self.first_index + self._windows,
            stamp_jitter=jitter,
        )
        self._windows += 1
        return win

    def _on_grid(self, stamps: np.ndarray, filled: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray | None]:
        """The window's times on its nominal grid ``t0 + k*T`` (``t0``: the mean offset of the
        received samples' stamps) and the stamps' residuals from it [s] (0 at a filled slot);
        the stamps themselves (and None) when they are on the grid already."""
        k = np.arange(stamps.shape[0], dtype=np.float64)
        period = self.sample_period
        rel = (stamps - stamps[0]) - k * period
        real = ~filled
        mean = float(np.mean(rel[real]))
        offset = stamps[0] + mean
        jitter = np.where(real, rel - mean, 0.0)
        if float(np.max(np.abs(jitter))) <= GRID_EXACT * period:
            return stamps, None
        return offset + k * period, jitter

    @property
    def missing_budget(self) -> int:
        """The most missing samples the current window may have filled: ``max_missing``
        times its length, rounded down [samples]."""
        return math.floor(self.max_missing * self.window + 1e-9)

    @property
    def windows(self) -> int:
        """Windows completed so far."""
        return self._windows

    @property
    def pending(self) -> int:
        """Samples in the partial window being filled."""
        return self._count
