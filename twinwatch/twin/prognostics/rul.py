"""Remaining useful life: when does a parameter's trend cross a threshold, and how sure is it?

The time to a threshold is a distribution, computed by **Monte Carlo** on the trend's parameter
covariance (as ProgPy's ``MonteCarlo`` predictor samples its uncertain state, and MATLAB's
``predictRUL`` returns a distribution): ``draws`` samples of the level, drift rate and growth
rate ``(c, m, r)`` from the fit's Gaussian (:meth:`DegradationFit.draws`), each solved in closed
form for its crossing of the threshold ``y*``::

    c + m * (exp(r * tau) - 1) / r = y*   ->   tau = ln(1 + r q) / r,   q = (y* - c) / m
    (linear, r = 0: tau = q)

A draw that never reaches the threshold (drifting away from it, or an exponential that
saturates short of it) has an infinite time; one already beyond it has 0. The published median
and interval are the draws' quantiles, so an interval may be open (``high`` null: some draws
never get there). Monte Carlo rather than the delta method because the crossing time is far from
linear in the parameters (a drift rate near zero makes it unbounded) and because it keeps the
probability of never crossing.

Times are plant time [s] (the source's clock): ``t`` the crossing time, ``rul_s`` the time from
the window's end; ``wall`` (seconds since the epoch) is the wall time at the window's end plus
``rul_s`` at the pace the source's clock has kept against the wall clock (1 for a live machine).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt
from numba import njit

from twinwatch.twin.model import FloatArray
from twinwatch.twin.prognostics.degradation import DegradationFit

__all__ = ["Crossing", "Trajectories", "crossing_times", "draw_trajectories", "first_crossings",
           "format_crossing", "format_duration", "predict_crossing", "sort_order"]

#: Monte Carlo draws of the degradation models: each model with its share of ``c``, ``m``,
#: ``r`` (arrays of the model's number of draws).
Trajectories = list[tuple[DegradationFit, dict[str, FloatArray]]]


@dataclass
class Crossing:
    """The predicted crossing of one threshold.

    Attributes:
        level: ``warning`` or ``alarm``.
        threshold: the threshold [SI] the trend heads to (of a two-sided rule, the side its
            level is heading to).
        status: ``crossed`` (the trend's level is beyond it now), ``predicted`` (the median
            crossing is finite), ``not_reached`` (most draws never reach it).
        t, t_low, t_high: median crossing and interval [plant time, s] (None: never).
        rul_s, low_s, high_s: the same as time from the window's end [s].
        wall, wall_low, wall_high: the same on the wall clock [s since the epoch].
        probability: share of the draws that reach it (at any time).
        samples: the draws' times from the window's end [s] (inf: never), for the metrics.
    """

    level: str
    threshold: float
    status: Literal["crossed", "predicted", "not_reached"]
    t: float | None = None
    t_low: float | None = None
    t_high: float | None = None
    rul_s: float | None = None
    low_s: float | None = None
    high_s: float | None = None
    wall: float | None = None
    wall_low: float | None = None
    wall_high: float | None = None
    probability: float = 0.0
    samples: FloatArray | None = None


def crossing_times(c: FloatArray, m: FloatArray, r: FloatArray, tau0: float,
                   threshold: float, direction: int) -> FloatArray:
    """Time [s] from ``tau0`` until ``c + m (exp(r tau) - 1)/r`` reaches ``threshold``, per
    draw (inf: never; 0: already beyond it at ``tau0``).

    Args:
        c, m, r: (n,) draws of the level [SI], drift rate [SI/s] and growth rate [1/s] at the
            reference time (tau = 0).
        tau0: the window's end minus the reference time [s] (>= 0).
        threshold: [SI].
        direction: +1 for a threshold crossed upwards (a high one), -1 downwards (a low one).

    Returns:
        (n,) times [s] (compiled, one pass over the draws).
    """
    c, m, r = (np.ascontiguousarray(a, dtype=float) for a in (c, m, r))
    return _crossing_times(c, m, r, float(tau0), float(threshold), int(direction))


@njit(cache=True, nogil=True, error_model="numpy")
def _crossing_times(c: FloatArray, m: FloatArray, r: FloatArray, tau0: float,
                    threshold: float, direction: int) -> FloatArray:
    out = np.empty(c.size)
    for i in range(c.size):
        out[i] = _crossing(c[i], m[i], r[i], _level(c[i], m[i], r[i], tau0), tau0, threshold,
                           direction)
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _level(c: float, m: float, r: float, tau0: float) -> float:
    """One draw's level at ``tau0``."""
    if abs(r) < 1e-12:
        return c + m * tau0
    return c + m * (math.expm1(min(max(r * tau0, -700.0), 700.0)) / r)


@njit(cache=True, nogil=True, error_model="numpy")
def _crossing(c: float, m: float, r: float, level_now: float, tau0: float, threshold: float,
              direction: int) -> float:
    """One draw's :func:`crossing_times`, its level at ``tau0`` given (:func:`_level`)."""
    q = (threshold - c) / m
    if abs(r) < 1e-12 or q < 0:
        # the line's time; heading away (q < 0) the exponential's is negative or undefined
        # too (ln(1 + r q) / r < 0 for either sign of r): never, without the logarithm
        tau = q
    else:
        arg = 1.0 + r * q
        tau = math.log(arg) / r if arg > 0 else math.inf
    # heading away from the threshold (q < 0), or no drift: never
    if not (math.isfinite(tau) and m != 0 and tau >= 0):
        tau = math.inf
    if (level_now - threshold) * direction >= 0:
        return 0.0
    return max(tau - tau0, 0.0)


@njit(cache=True, nogil=True, error_model="numpy")
def _first_crossings(c: FloatArray, m: FloatArray, r: FloatArray, tau0: float,
                     thresholds: FloatArray) -> FloatArray:
    """:func:`first_crossings`' arithmetic: (L, n) times, ``thresholds`` (L, 2) a level's
    high and low threshold per row (NaN where absent)."""
    out = np.full((thresholds.shape[0], c.size), np.inf)
    for i in range(c.size):
        now = _level(c[i], m[i], r[i], tau0)
        for k in range(thresholds.shape[0]):
            for side in range(2):
                th = thresholds[k, side]
                if not math.isnan(th):
                    out[k, i] = min(out[k, i], _crossing(c[i], m[i], r[i], now, tau0, th,
                                                         1 - 2 * side))
    return out


def first_crossings(trajectories: Trajectories, t_end: float,
                    levels: Sequence[tuple[float | None, float | None]]) -> list[FloatArray]:
    """Each draw's crossing time [s from ``t_end``] of each level: the earlier of its high
    threshold upwards and its low one downwards (inf: neither reached; 0: beyond one now),
    the draws of every model in ``trajectories``' order, in one pass over them.

    Args:
        trajectories: the draws (:func:`draw_trajectories`).
        t_end: the window's end [plant time, s].
        levels: each level's (high, low) thresholds [SI] (None: absent).

    Returns:
        Per level, the draws' times (draws,).
    """
    th = np.array([[math.nan if h is None else float(h), math.nan if lo is None else float(lo)]
                   for h, lo in levels]).reshape(len(levels), 2)
    parts = [_first_crossings(p["c"], p["m"], p["r"], max(t_end - f.t_ref, 0.0), th)
             for f, p in trajectories]
    out = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=1)
    return list(out)


def _ranks(n: int, q: float) -> tuple[int, int]:
    """The two ranks (0-based) of ``n`` sorted draws the ``q`` quantile interpolates."""
    i = int(math.floor(q * (n - 1)))
    return i, min(i + 1, n - 1)


def _quantile(s: FloatArray, q: float) -> float | None:
    """The ``q`` quantile of draws ``s`` that may be infinite (never), None when infinite
    (linear interpolation between ranks; between a finite and an infinite rank: infinite);
    ``s`` sorted, or partitioned at the ranks it reads (:func:`_ranks`)."""
    if not s.size:
        return None
    pos = q * (s.size - 1)
    i, j = _ranks(s.size, q)
    if not (math.isfinite(s[i]) and math.isfinite(s[j])):
        return None
    return float(s[i] + (pos - i) * (s[j] - s[i]))


def draw_trajectories(fit: DegradationFit, mixture: Sequence[tuple[DegradationFit, float]],
                      draws: int, rng: np.random.Generator | None = None, *,
                      normals: FloatArray | None = None) -> Trajectories:
    """``draws`` samples of ``(c, m, r)`` shared among the plausible models by weight (largest
    remainders), each from its fit's Gaussian (:meth:`DegradationFit.draws`).

    Args:
        fit: the selected model (alone when ``mixture`` is empty).
        mixture: the plausible models with their weights (Bayesian model averaging).
        draws: Monte Carlo samples in all.
        rng: the generator.
        normals: standard normals (draws, 4) instead of ``rng``: each model takes the next
            rows (its number of draws) and its first ``k`` columns.

    Returns:
        Each model drawn from with its draws.

    Raises:
        ValueError: neither ``rng`` nor ``normals``.
    """
    out: Trajectories = []
    row = 0
    for f, n_f in _share(mixture or [(fit, 1.0)], draws):
        if normals is None:
            out.append((f, f.draws(n_f, rng)))
        else:
            out.append((f, f.draws(n_f, normals=normals[row:row + n_f])))
        row += n_f
    return out


def predict_crossing(fit: DegradationFit, level: str, high: float | None, low: float | None,
                     *, t_end: float, interval: float, draws: int,
                     rng: np.random.Generator | None = None,
                     wall_end: float | None = None, pace: float = 1.0,
                     mixture: Sequence[tuple[DegradationFit, float]] = (),
                     trajectories: Trajectories | None = None,
                     times: FloatArray | None = None,
                     order: npt.NDArray[np.intp] | None = None) -> Crossing:
    """The crossing of a level's threshold(s) by the trend ``fit``.

    Args:
        fit: the selected degradation model.
        mixture: the plausible models with their weights (Bayesian model averaging: the
            draws are shared among them by weight); empty: ``fit`` alone.
        level: ``warning`` or ``alarm``.
        high, low: the level's thresholds [SI], crossed upwards and downwards (None: absent);
            each draw takes the first it reaches.
        t_end: the window's end [plant time, s] (the RUL counts from it).
        interval: central probability of the published interval (0.95: the 2.5-97.5 %
            quantiles).
        draws: Monte Carlo samples.
        rng: the generator (seeded by the caller); not needed with ``trajectories``.
        wall_end: the wall-clock time at the window's end [s since the epoch], or None.
        pace: wall seconds per plant second over the recent windows.
        trajectories: the draws (:func:`draw_trajectories`); drawn here when None. One set
            for every level of a window: each draw's warning comes before its alarm.
        times: the draws' crossing times of this level (:func:`first_crossings` of
            ``trajectories``, every level in one pass); computed here when None.
        order: indices that sort ``times`` (:func:`sort_order`); None: the quantiles'
            ranks are selected by a partition.

    Returns:
        The crossing; ``samples`` holds the draws' times from ``t_end`` [s] (inf: never).

    Raises:
        ValueError: neither ``trajectories`` nor ``rng`` given.
    """
    level_end = fit.value_band(t_end)[0]
    target = high if (fit.m >= 0 and high is not None) or low is None else low
    assert target is not None, "a level needs a threshold"
    if (high is not None and level_end >= high) or (low is not None and level_end <= low):
        crossed = high if high is not None and level_end >= high else low
        assert crossed is not None
        return Crossing(level, crossed, "crossed", t=t_end, t_low=t_end, t_high=t_end,
                        rul_s=0.0, low_s=0.0, high_s=0.0, wall=wall_end, wall_low=wall_end,
                        wall_high=wall_end, probability=1.0, samples=np.zeros(draws))
    if times is None:
        if trajectories is None:
            if rng is None:
                raise ValueError("predict_crossing needs trajectories or a generator (rng)")
            trajectories = draw_trajectories(fit, mixture, draws, rng)
        times = first_crossings(trajectories, t_end, [(high, low)])[0]
    a = 0.5 * (1.0 - interval)
    # the ranks the three quantiles read, in place of a sort of every draw
    qs = (0.5, a, 1.0 - a)
    if order is not None:
        ranked = times[order]
    else:
        ranks = sorted({r for q in qs for r in _ranks(times.size, q)})
        ranked = np.partition(times, ranks) if times.size else times
    med, lo, hi = (_quantile(ranked, q) for q in qs)
    prob = float(np.count_nonzero(np.isfinite(times))) / times.size if times.size else \
        math.nan
    status: Literal["crossed", "predicted", "not_reached"] = (
        "predicted" if med is not None else "not_reached")

    def at(x: float | None) -> float | None:
        return None if x is None else t_end + x

    def wall(x: float | None) -> float | None:
        return None if x is None or wall_end is None else wall_end + x * pace

    return Crossing(level, target, status, t=at(med), t_low=at(lo), t_high=at(hi), rul_s=med,
                    low_s=lo, high_s=hi, wall=wall(med), wall_low=wall(lo),
                    wall_high=wall(hi), probability=prob, samples=times)


def sort_order(times: FloatArray, hint: npt.NDArray[np.intp] | None = None
               ) -> npt.NDArray[np.intp]:
    """Indices that sort ``times`` (n,), found from ``hint`` (n,), the order of a similar
    set (the previous window's draws of the same level, which the common random numbers keep
    nearly sorted: a stable sort of the nearly sorted times costs half a partition)."""
    if hint is None or hint.size != times.size:
        return np.argsort(times, kind="stable")
    out: npt.NDArray[np.intp] = hint[np.argsort(times[hint], kind="stable")]
    return out


def _share(mixture: Sequence[tuple[DegradationFit, float]], draws: int
           ) -> list[tuple[DegradationFit, int]]:
    """``draws`` shared among the models by weight (largest remainders)."""
    if len(mixture) == 1:
        return [(mixture[0][0], draws)]
    w = np.array([max(wi, 0.0) for _, wi in mixture], dtype=float)
    w = w / w.sum() if w.sum() > 0 else np.full(w.size, 1.0 / w.size)
    raw = w * draws
    n = np.floor(raw).astype(int)
    for i in np.argsort(raw - n)[::-1][:draws - int(n.sum())]:
        n[i] += 1
    return [(f, int(k)) for (f, _), k in zip(mixture, n, strict=True) if k > 0]


_UNITS = ((172800.0, 86400.0, "d"), (7200.0, 3600.0, "h"), (120.0, 60.0, "min"), (0.0, 1.0, "s"))


def _unit(seconds: float) -> tuple[float, str]:
    for limit, size, name in _UNITS:
        if seconds >= limit:
            return size, name
    return 1.0, "s"


def _num(x: float) -> str:
    return f"{x:.1f}".rstrip("0").rstrip(".") if x < 10 else f"{x:.0f}"


def format_duration(seconds: float | None) -> str:
    """A time for a person: ``45 s``, ``6 min``, ``3.5 h``, ``12 d``; ``never`` for None or
    inf."""
    if seconds is None or not math.isfinite(seconds):
        return "never"
    size, name = _unit(abs(seconds))
    return f"{_num(seconds / size)} {name}"


def format_crossing(median: float | None, low: float | None, high: float | None) -> str:
    """``6 min (4-9 min)``: a median time with its interval in the median's unit (``4 min -
    never`` when the interval is open: some draws never get there)."""
    if median is None or not math.isfinite(median):
        return "never" if low is None else f"not likely (at the earliest {format_duration(low)})"
    size, name = _unit(abs(median))
    lo = "?" if low is None else _num(low / size)
    hi = "never" if high is None or not math.isfinite(high) else _num(high / size)
    if hi == "never":
        return f"{_num(median / size)} {name} ({lo} {name} - never)"
    return f"{_num(median / size)} {name} ({lo}-{hi} {name})"
