"""The recording's vocabulary: the timeline, the colours and markers (each meaning one thing
everywhere), the operations a view logs (:class:`Op`), entity paths, and how numbers and
times read for a person.
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, Literal, NamedTuple

import numpy as np

from twinwatch._lazy import lazy_module

if TYPE_CHECKING:
    import rerun as rr
    import rerun.blueprint as rrb

    from twinwatch.twin.health import HealthView, ParameterView
else:  # imported when a recording opens: loading a configuration does not load rerun
    rr = lazy_module("rerun")
    rrb = lazy_module("rerun.blueprint")


TIMELINE = "plant_time"
"""Name of the Rerun timeline carrying plant time [s]: a duration timeline, or a timestamp
timeline when the source's clock is the wall clock (times past ``WALL_CLOCK_AFTER``)."""

WALL_CLOCK_AFTER = 1e9
"""Plant times from this many seconds on (2001-09-09) are the source's wall clock, seconds
since the epoch: the timeline is then a timestamp and the text says the UTC time of day."""

# Colours for the viewer's dark theme, each meaning one thing everywhere.
MEASURED = (86, 164, 255)
TWIN = (255, 140, 30)
RESIDUAL = (196, 150, 255)
_DT_PRIME = (240, 70, 70)
_DT_SECOND = (90, 205, 100)
DEVIATION = (215, 215, 215)
NOMINAL = (140, 140, 140)
BAND = (95, 150, 235)
SCALE = (105, 105, 105)
HIDDEN = (0, 0, 0, 0)
ELAPSED = (200, 200, 120)
TREND = (230, 120, 200)
TREND_BAND = (150, 80, 130)
WARNING = (255, 190, 0)
ALARM = (240, 60, 60)
_Marker = Literal["circle", "diamond", "cross", "up", "down", "square"]
STATUS_STYLE: dict[str, tuple[tuple[int, int, int], _Marker, float]] = {
    "estimated": ((90, 205, 100), "circle", 2.0),
    "fused": ((86, 164, 255), "diamond", 2.5),
    "held": ((150, 150, 150), "cross", 2.5),
}
EVENT_STYLE: dict[str, tuple[tuple[int, int, int], _Marker, float]] = {
    "warning": (WARNING, "up", 9.0),
    "alarm": (ALARM, "circle", 9.0),
    "cleared": ((90, 205, 100), "square", 8.0),
    "rul_warning": (WARNING, "down", 9.0),
    "rul_alarm": (ALARM, "down", 11.0),
}
"""Alarm changes on a parameter's view: the deviation rule's raises (``warning``, ``alarm``)
and clears, the RUL rule's raises (``rul_warning``, ``rul_alarm``), apart."""
VARIANTS = (("dt_prime", "DT'", _DT_PRIME), ("dt_second", "DT''", _DT_SECOND))
"""The twin without (DT') and with (DT'') its meta-model terms: key, label, colour."""
QUALITY_COLORS = (
    (240, 60, 60), (255, 190, 0), (196, 150, 255), (86, 164, 255), (255, 140, 30),
    (90, 205, 100), (230, 120, 200), (160, 160, 160), (40, 200, 200), (190, 190, 60),
)
SCALE_PCT = 10.0
"""Half-height of the scale drawn for a parameter without an alarm rule [%]."""
HEADROOM = 1.6
"""The axis of a parameter's view reaches at least this many times its outermost threshold (or
scale) on each side that has one: the lines never sit on its edge."""
SCALE_HEADROOM = 1.15
"""The same for the +-10 % scale of a parameter without a rule."""
_TICK_ROOM = 0.12
"""The least room between an axis' outermost labelled tick and its edge, as a share of the
axis (:func:`tick_room`): half a label's height on a small panel at 1600x1000."""
_VIEWER_MARGIN = 0.06
"""How far beyond the data, as a share of the axis, the viewer may still draw a labelled tick
(its own margin is 5 %)."""
BAND_CLIP = 1.5
"""The 2-sigma band is drawn at most this many times the outer threshold away from nominal
(within ``SCALE_HEADROOM`` without a rule): a parameter the data do not determine does not
flatten its plot, and the panel's summary says so."""
PPM = 1e6
"""The fit panel shows the nRMSE in parts per million (ppm) of the output's scale: the bare
fraction's ticks read ``0``."""
PROBLEM_COUNTER = re.compile(
    r"abandon|overrun|lost|gap|bad|error|fail|silent|stall|jitter|missing|dropped|timeout|"
    r"not_stored|not_connected|waiting")
"""Counters drawn in the data-quality strip: those counting lost or bad data."""


class Op(NamedTuple):
    """One thing to log: ``payload`` on ``entity`` at plant time ``t``, columns with their
    ``index`` (a window's samples), or a ``static`` style."""

    entity: str
    payload: Any
    t: float | None = None
    index: Any = None
    static: bool = False


def entity(*parts: str) -> str:
    """An entity path from raw parts, each escaped (a '/' in a name stays inside its part)."""
    return "/".join(rr.escape_entity_path_part(p) for p in parts)


RANK = {"normal": 0, "warning": 1, "alarm": 2}


def as_text(x: Any, default: str = "") -> str:
    """A text field of the message as text (``default`` when the message lacks it)."""
    return default if x is None else str(x)


def as_number(x: Any) -> float:
    """A JSON number as a float (NaN for null or anything else: a gap in a plot)."""
    if isinstance(x, int | float) and not isinstance(x, bool):
        return float(x)
    return math.nan


def residual_rmse(doc: HealthView) -> dict[str, Mapping[str, float | None]]:
    """``residual.<dt_prime|dt_second>.rmse``: output -> RMSE of the twin without and with its
    terms (empty for a variant the message does not hold)."""
    residual = doc.residual
    if residual is None:
        return {"dt_prime": {}, "dt_second": {}}
    return {"dt_prime": (residual.dt_prime.rmse if residual.dt_prime else None) or {},
            "dt_second": (residual.dt_second.rmse if residual.dt_second else None) or {}}


def axis_frame(values: np.ndarray, room: bool = True) -> list[float] | None:
    """Two transparent values that give an axis two labelled ticks. The viewer labels ticks at
    powers of ten only, and only when at most about four of them span the axis. The frame is
    the range, widened on its nearer side to the next multiple of that power of ten when fewer
    than two lie inside; with ``room``, then widened so its outermost labels are not cut
    (:func:`tick_room`). None without finite values."""
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return None
    low, high = float(finite.min()), float(finite.max())
    width = high - low
    if width <= 0.0:
        width = abs(high) * 1e-3 or 1.0
    step = 10.0 ** math.ceil(math.log10(width / 4.0))
    first, last = math.ceil(low / step), math.floor(high / step)
    lo, hi = math.floor(low / step) * step, math.ceil(high / step) * step
    if last - first >= 1:
        frame = (low, high)
    elif last == first:  # one labelled tick inside: reach the next one on the nearer side
        frame = (lo, high) if (low - lo) <= (hi - high) else (low, hi)
    else:
        frame = (lo, hi)
    return tick_room(*frame) if room else list(frame)


def sparse_frame(high: float) -> list[float]:
    """The axis frame ``[0, top]`` of a small panel of positive values up to ``high`` (the
    estimation time [ms]); ``[0, 1]`` when ``high`` is not positive. To ``high`` when at most
    2.3 steps of its power of ten span it, else to the next power of ten (the strip is too
    short for more labels), and ``_TICK_ROOM`` above for the top label."""
    if not math.isfinite(high) or high <= 0.0:
        return [0.0, 1.0]
    step = 10.0 ** math.floor(math.log10(high))
    label = math.floor(high / step) * step if high <= 2.3 * step else 10.0 * step
    return [0.0, max(high, label / (1.0 - _TICK_ROOM))]


def tick_room(low: float, high: float, scale: float | None = None) -> list[float]:
    """``[low, high]`` widened on a side whose outermost labelled tick lies within
    ``_TICK_ROOM`` of the axis' height from its edge: the viewer centres a label on its tick
    and clips what leaves the plot. ``scale``: the width of the range the view shows when it
    is wider than ``[low, high]``."""
    width = high - low
    if width <= 0.0:
        width = abs(high) * 1e-3 or 1.0
        low, high = low - width / 2.0, high + width / 2.0
    width = max(width, scale or 0.0)
    step = 10.0 ** math.ceil(math.log10(width / 4.0))
    room = _TICK_ROOM / (1.0 - 2.0 * _TICK_ROOM) * width  # of the widened axis
    near = _VIEWER_MARGIN * width  # the outermost ticks inside, or just outside it
    top = math.floor((high + near) / step) * step
    bottom = math.ceil((low - near) / step) * step
    return [min(low, bottom - room), max(high, top + room)]


def pct_text(value: float) -> str:
    """A signed percentage for a summary: three significant digits, or whole from 100 %
    up to 10^5 % (``+2104``, not ``+2.1e+03``), an exponent only beyond."""
    if math.isfinite(value) and 100.0 <= abs(value) < 1e5:
        return f"{value:+.0f}"
    return f"{value:+.3g}"


def band_pct(ph: ParameterView) -> tuple[float, float]:
    """The 2-sigma band of a parameter's published value, in % of nominal (NaN when the
    message gives none): the fused interval for a fused or held value that has one, else the
    value +- 2 relative standard errors."""
    nom, value, rel = as_number(ph.nominal), as_number(ph.value), as_number(ph.rel_std_pct)
    if not math.isfinite(nom) or nom == 0.0:
        return math.nan, math.nan
    fused = ph.fused
    if ph.status != "estimated" and fused is not None:
        low, high = as_number(fused.low), as_number(fused.high)
    elif math.isfinite(value) and math.isfinite(rel):
        low, high = value * (1.0 - 0.02 * rel), value * (1.0 + 0.02 * rel)
    else:
        return math.nan, math.nan
    return (low / nom - 1.0) * 100.0, (high / nom - 1.0) * 100.0


def clock(t: float) -> str:
    """Plant time for a person: ``14:38`` (minutes:seconds), ``1:02:05`` past an hour,
    ``-0:05`` before zero, the UTC time of day ``14:38:05Z`` for a wall clock (from
    ``WALL_CLOCK_AFTER``); ``n/a`` when not finite. Rounded to the second."""
    if not math.isfinite(t):
        return "n/a"
    if t >= WALL_CLOCK_AFTER:
        return time.strftime("%H:%M:%SZ", time.gmtime(round(t)))
    sign, s = ("-" if t < 0 else ""), int(round(abs(t)))
    h, rest = divmod(s, 3600)
    m, sec = divmod(rest, 60)
    return f"{sign}{h}:{m:02d}:{sec:02d}" if h else f"{sign}{m}:{sec:02d}"


def span(seconds: float) -> str:
    """A duration for a person: ``45 s``, ``3m 40s``, ``2h 05m``, ``3.2 d``; ``n/a`` when not
    finite."""
    if not math.isfinite(seconds):
        return "n/a"
    s = abs(seconds)
    sign = "-" if seconds < 0 else ""
    if s < 60:
        return f"{sign}{s:.0f} s"
    if s < 3600:
        m, sec = divmod(int(round(s)), 60)
        return f"{sign}{m}m {sec:02d}s"
    if s < 86400 * 2:
        h, m = divmod(int(round(s / 60)), 60)
        return f"{sign}{h}h {m:02d}m"
    return f"{sign}{s / 86400:.1f} d"


def fmt(x: Any, spec: str = ".6g") -> str:
    v = as_number(x)
    return format(v, spec) if math.isfinite(v) else "n/a"
