"""A parameter's projection to its alarm threshold, drawn in a 2-D view (``BOX``, y down: plant
time across, % of nominal up): the thresholds, now, the recent deviations, the trend to the
crossing with its 95 % interval; and the RUL in words.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from twinwatch.sinks.rerun.style import (
    ALARM,
    DEVIATION,
    NOMINAL,
    TREND,
    TREND_BAND,
    as_number,
    clock,
    span,
)

if TYPE_CHECKING:
    from twinwatch.twin.health import ParameterView, RulView


HISTORY = 1000
"""Deviations kept per parameter for its projection view."""
BOX = (240.0, 100.0)
"""The projection view's drawing [view units]: width, height (y down); the view's bounds."""
_MARGIN = (2.0, 2.0, 15.0, 15.0)
"""Room kept in the drawing for the labels: left, right, top, bottom [view units]."""
_CHAR_W, _LABEL_PAD = 6.5, 5.0
"""A label's character width and its box's padding in the drawing's units (to keep labels
inside the view)."""
_UNDER, _OVER = 0.0, 17.0
"""Where a label's anchor goes to write it under a line, or over it (the viewer writes a
label in a box under its point)."""


class _Strip(NamedTuple):
    xy: np.ndarray
    color: tuple[int, ...]
    width: float  # [ui points]


class _Label(NamedTuple):
    xy: tuple[float, float]
    label: str
    color: tuple[int, ...]
    size: float  # the point's radius [ui points]


def draw_projection(p: str, ph: ParameterView, t: float, history: Sequence[tuple[float, float]],
                limits: Sequence[tuple[str, float, tuple[int, ...]]],
                ) -> tuple[list[_Strip], list[_Label]] | None:
    """What ``p``'s projection view draws at plant time ``t``, in the view's units (``BOX``):
    None without a trend level and a predicted alarm crossing. The time axis runs from as far
    before now as the interval's end is after it to the interval's end (twice the median's
    distance when some draws never cross); the value axis spans what is drawn and the alarm
    threshold."""
    predicted = _predicted_crossing(ph, t)
    if predicted is None:
        return None
    nom, level, th, t_cross, t_low, t_high = predicted

    def pct(v: Any) -> Any:
        return (np.asarray(v, dtype=float) / nom - 1.0) * 100.0

    end = t_high if math.isfinite(t_high) and t_high > t_cross else t + 2.0 * (t_cross - t)
    start = t - (end - t)
    growth = as_number(ph.trend.growth) if ph.trend is not None else math.nan
    rate = None if not math.isfinite(growth) else growth
    curves = []
    for x in (t_low, t_high, t_cross):  # the band's ends, then the median
        if math.isfinite(x) and x > t:
            curve = _growth_curve(t, level, x, th, rate)
            curves.append(np.column_stack([curve[:, 0], pct(curve[:, 1])]))
    past = np.array([(ti, v) for ti, v in history if start <= ti <= t], dtype=float)
    past = past.reshape(-1, 2)
    th_pct = float(pct(th))
    values = [th_pct, *past[:, 1], *(c[:, 1] for c in curves)]
    finite = np.concatenate([np.atleast_1d(np.asarray(v, dtype=float)) for v in values])
    finite = finite[np.isfinite(finite)]
    low, high = float(finite.min()), float(finite.max())
    pad = 0.08 * (high - low or abs(high) or 1.0)
    frame = _Frame(start, end, low - pad, high + pad)
    others = [(name, v, c) for name, v, c in limits
              if frame.low <= v <= frame.high and not math.isclose(v, th_pct, abs_tol=1e-9)]
    strips = _projection_strips(frame, t, th_pct, others, past, curves)
    labels = _projection_labels(frame, t, float(pct(level)), th_pct, (t_cross, t_low, t_high),
                                others)
    return strips, labels


def _predicted_crossing(ph: ParameterView, t: float
                        ) -> tuple[float, float, float, float, float, float] | None:
    """What :func:`draw_projection` draws from: (nominal, trend level, alarm threshold [SI],
    crossing's plant time, its interval's ends [s], nan where open); None unless the message
    predicts the alarm's crossing after ``t`` from a trend level, on a nonzero nominal."""
    trend, rul = ph.trend, ph.rul
    crossing = rul.alarm if rul is not None else None
    nom = as_number(ph.nominal)
    level = as_number(trend.level if trend is not None else None)
    if (crossing is None or crossing.status != "predicted" or not math.isfinite(level)
            or not math.isfinite(nom) or nom == 0.0):
        return None
    th, t_cross = as_number(crossing.threshold), as_number(crossing.t)
    if not (math.isfinite(th) and math.isfinite(t_cross) and t_cross > t):
        return None
    return nom, level, th, t_cross, as_number(crossing.t_low), as_number(crossing.t_high)


@dataclass(frozen=True)
class _Frame:
    """The projection's axes: plant time ``start`` to ``end`` [s] across, the deviation
    ``low`` to ``high`` [% of nominal] up, mapped into the drawing (:data:`BOX`, inside
    :data:`_MARGIN`; y down)."""

    start: float
    end: float
    low: float
    high: float

    def xy(self, ts: Any, vs: Any) -> np.ndarray:
        """Points (k, 2) in the drawing of times ``ts`` [s] and deviations ``vs`` [%]."""
        w, h = BOX
        left, right, top, bottom = _MARGIN
        x = (left + (np.asarray(ts, dtype=float) - self.start) / (self.end - self.start)
             * (w - left - right))
        y = top + (self.high - np.asarray(vs, dtype=float)) / (self.high - self.low) * (
            h - top - bottom)
        return np.column_stack([np.atleast_1d(x), np.atleast_1d(y)])

    def x(self, ts: float) -> float:
        """The drawing's x of plant time ``ts`` [s]."""
        return float(self.xy([ts], [0.0])[0, 0])

    def y(self, t: float, v: float) -> float:
        """The drawing's y of the deviation ``v`` [%] (at plant time ``t``)."""
        return float(self.xy([t], [v])[0, 1])


def _projection_strips(frame: _Frame, t: float, th_pct: float,
                       others: Sequence[tuple[str, float, tuple[int, ...]]],
                       past: np.ndarray, curves: Sequence[np.ndarray]) -> list[_Strip]:
    """The projection's lines: the other thresholds in range, the alarm threshold, now, the
    recent deviations ``past`` (k, 2), the trend's ``curves`` (the band's ends, the median
    last)."""
    start, end = frame.start, frame.end
    strips = [_Strip(frame.xy([start, end], [v, v]), c, 1.0) for _, v, c in others]
    strips.append(_Strip(frame.xy([start, end], [th_pct, th_pct]), ALARM, 1.5))
    strips.append(_Strip(frame.xy([t, t], [frame.low, frame.high]), NOMINAL, 0.75))
    if len(past) > 1:
        strips.append(_Strip(frame.xy(past[:, 0], past[:, 1]), DEVIATION, 1.0))
    for i, c in enumerate(curves):
        median = i == len(curves) - 1
        strips.append(_Strip(frame.xy(c[:, 0], c[:, 1]), TREND if median else TREND_BAND,
                             2.0 if median else 1.0))
    return strips


def _projection_labels(frame: _Frame, t: float, level_pct: float, th_pct: float,
                       times: tuple[float, float, float],
                       others: Sequence[tuple[str, float, tuple[int, ...]]]) -> list[_Label]:
    """The projection's points and texts (``times``: the crossing, the interval's ends, nan
    where open), written under or over their lines and kept inside the view."""
    w = BOX[0]
    t_cross, t_low, t_high = times
    below = th_pct < level_pct  # the threshold under the trend: its labels under it
    y_th = frame.y(t, th_pct)
    y_low, y_high = frame.y(t, frame.low), frame.y(t, frame.high)
    outer = y_th + _UNDER if below else y_th - _OVER
    inner = y_high - _OVER if below else y_low + _UNDER
    band = (f" ({clock(t_low) if math.isfinite(t_low) else 'n/a'}-"
            f"{clock(t_high) if math.isfinite(t_high) else 'never'})")

    def at(x: float, y: float, text: str) -> tuple[float, float]:
        """A label's anchor (the viewer centres the text under it) kept inside the view."""
        half = _CHAR_W * len(text) / 2.0 + _LABEL_PAD
        return float(min(max(x, half), w - half)), y

    texts = [(f"alarm {th_pct:+.3g} %", frame.x(frame.start), outer, ALARM, 0.5),
             *((f"{name.split()[0]} {v:+.3g} %", frame.x(frame.start),
                frame.y(t, v) + (_UNDER if v < level_pct else -_OVER), c, 0.5)
               for name, v, c in others),
             (f"now {clock(t)}", frame.x(t), inner, NOMINAL, 0.5),
             (f"{clock(t_cross)}{band}", frame.x(t_cross), outer, ALARM, 0.5)]
    labels = [_Label(tuple(frame.xy([t], [level_pct])[0]), f"{level_pct:+.3g} %", TREND, 2.5),
              _Label(tuple(frame.xy([t_cross], [th_pct])[0]), "", ALARM, 3.0)]
    labels += [_Label(at(x, y, text), text, c, size) for text, x, y, c, size in texts]
    return [_Label((float(q.xy[0]), float(q.xy[1])), q.label, q.color, q.size)
            for q in labels]


def _growth_curve(t0: float, y0: float, t1: float, y1: float, r: float | None,
                  n: int = 32) -> np.ndarray:
    """(n, 2) points of ``y0 + a (exp(r (t - t0)) - 1)/r`` from ``(t0, y0)`` through
    ``(t1, y1)`` (a line for r None or 0): the trend's shape, scaled to pass the threshold at
    a crossing time."""
    t = np.linspace(t0, t1, n)
    if r is None or abs(r) * (t1 - t0) < 1e-9:
        g, g1 = t - t0, t1 - t0
    else:
        g, g1 = np.expm1(r * (t - t0)) / r, np.expm1(r * (t1 - t0)) / r
    a = (y1 - y0) / g1 if g1 else 0.0
    return np.column_stack([t, y0 + a * g])

def trend_pct(ph: ParameterView) -> tuple[float, float, float] | None:
    """The parameter's trend (``trend.level`` +- 2 ``level_std``, when the message has one) in
    % of nominal: (low, high, level); None without a trend level."""
    trend = ph.trend
    nom = as_number(ph.nominal)
    level = as_number(trend.level if trend is not None else None)
    std = as_number(trend.level_std if trend is not None else None)
    if not math.isfinite(level) or not math.isfinite(nom) or nom == 0.0:
        return None
    std = std if math.isfinite(std) else 0.0

    def pct(v: float) -> float:
        return (v / nom - 1.0) * 100.0

    return pct(level - 2 * std), pct(level + 2 * std), pct(level)


def _crossings(rul: RulView | None) -> list[tuple[str, Any]]:
    """(level, crossing) of the warning and the alarm threshold, those the RUL has."""
    if rul is None:
        return []
    return [(level, c) for level, c in (("warning", rul.warning), ("alarm", rul.alarm))
            if c is not None]


def rul_text(ph: ParameterView, at: bool = False) -> str:
    """``RUL to alarm 3m 40s (2m 50s-5m 10s)`` from the message's ``rul`` (empty without);
    with ``at``, the crossing's plant time too (``, at 18:10 (17:30-19:50)``). An open end
    (some draws never reach it) is ``never``."""
    parts = []
    for level, c in _crossings(ph.rul):
        if c.status == "crossed":
            parts.append(f"{level} crossed")
        elif c.status == "predicted" and math.isfinite(as_number(c.rul_s)):
            low, high = as_number(c.low_s), as_number(c.high_s)
            text = (f"RUL to {level} {span(as_number(c.rul_s))} ({span(low)}-"
                    f"{span(high) if math.isfinite(high) else 'never'})")
            t, t_low, t_high = as_number(c.t), as_number(c.t_low), as_number(c.t_high)
            if at and math.isfinite(t):
                text += (f", at {clock(t)} ({clock(t_low)}-"
                         f"{clock(t_high) if math.isfinite(t_high) else 'never'})")
            parts.append(text)
    return ", ".join(parts)


def rul_short(ph: ParameterView) -> str:
    """``RUL alarm 3m 32s`` (the median to the nearest threshold not crossed yet), else
    ``alarm crossed``, or empty."""
    crossed = ""
    for level, c in _crossings(ph.rul):
        if c.status == "crossed":
            crossed = f"{level} crossed"
        elif c.status == "predicted" and math.isfinite(as_number(c.rul_s)):
            return f"RUL {level} {span(as_number(c.rul_s))}"
    return crossed
