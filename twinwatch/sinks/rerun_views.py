"""What a twinwatch recording shows: its entities, their styles, and the default blueprint.

:class:`RecordingViews` turns one window (its samples, estimates, health message and alarm
changes) into what :class:`~twinwatch.sinks.rerun.RerunRecorder` logs, and describes the layout
an operator opens: the story of the machine's health at one glance.

Entity paths, with ``M`` the machine name and ``plant_time`` the timeline [s]:

* ``M/outputs/<output>/measured`` and ``M/outputs/<output>/twin``: the window's measured and
  twin-simulated output samples in the output's unit (:class:`rerun.Scalars`, one
  ``send_columns`` per series and window); ``M/outputs/<output>/frame``: two transparent
  values per window that give the axis two labelled ticks, with room for their labels
  (:func:`_frame`, :meth:`RecordingViews._output_frame`);
  ``M/residual/<output>``: measured - twin, every sample (``.../frame``: the same for its
  axis); ``M/residual_rmse/dt_prime`` and
  ``.../dt_second``: per window, the RMSE of the twin
  without (DT') and with (DT'') its meta-model terms, one series per output (its unit);
* ``M/parameters``: every parameter's estimate [SI], one series per parameter (the twin's
  order), one point per window;
* ``M/health/<name>/...`` for each estimated parameter, in percent of its nominal value:
  ``deviation`` (series, in drawing order: the 2-sigma band's low and high ends, 0 = nominal,
  the ``[alarms]`` thresholds (or a +-10 % scale when it has no rule), two transparent headroom
  series that keep the thresholds off the axis' edges, and last the deviation itself),
  ``frame`` (two transparent values: two labelled ticks over the run), ``estimated`` /
  ``fused`` / ``held`` (the deviation again, one point per window on the entity of the
  window's status: drawn as different markers), ``events/warning``, ``events/alarm``,
  ``events/cleared`` (the deviation rule's changes, a large marker at the event's deviation),
  ``events/rul_warning``, ``events/rul_alarm`` (the RUL rule's raises, a down-triangle at the
  parameter's deviation then); ``health/<name>/trend``: the parameter's trend when the message
  carries one (``parameters.<name>.trend.level`` +- 2 ``level_std``, in %: low, high, level);
  ``health/<name>/projection/lines`` and ``.../labels``, for a parameter with an alarm rule
  while its message predicts the alarm's crossing (cleared, ``health/<name>/projection``,
  when it stops): a drawing of the trend's projection in a 2-D view's units (``_BOX``, y down;
  plant time across, % of nominal up): the thresholds in range, the moment now, the
  deviations of the recent windows, the trend from its level now to the alarm threshold at the
  median crossing (pink) and at both ends of its 95 % interval (dim), and as labels the
  thresholds, now, the level and the crossing's plant time with its interval;
  ``health/<name>/summary``: what the panel says in words under its plot, every window
  (markdown): the deviation, status and trend, the RUL to each threshold of the rule (median,
  95 % interval, and the plant time of the crossing), the moments the deviation alarm and the
  RUL alarm were raised or cleared (apart), a 2-sigma band beyond the view; the RUL's median is
  also in the log row;
* ``M/quality/nrmse`` (the published twin's), ``M/quality/nrmse_dt_prime`` and
  ``.../nrmse_dt_second`` (without and with the terms), ``M/quality/model_check_failed`` (the
  nRMSE of the windows whose model check failed), all in ppm, ``M/quality/frame`` (its axis'
  frame), ``M/quality/elapsed_ms`` (adaptation time per window [ms]; ``.../frame`` its
  axis' frame, :func:`_sparse_frame`), ``M/quality/problems`` (the counters of lost or bad
  data, cumulative: abandoned windows, overruns, gaps, bad samples, windows not stored or not
  recorded, ... one series each, named after the counter);
* ``M/model``: the twin DT'' as a markdown document, every window: the diagnosis, each
  meta-model term's equation with its meaning and evidence, the fit; ``M/parameter_table``:
  beside it, every parameter's value and status (a table; the fixed ones in a line under it,
  why the held ones are held); ``M/health``: the window's health message (JSON); ``M/log``: one
  short :class:`rerun.TextLog` row per window (at most about 80 characters: a row is not
  wrapped) with the ruled parameters' deviations and levels, at the machine's state (INFO;
  WARN while a parameter is in warning or has a RUL level raised, the model check fails, the
  structure changed or data were lost; ERROR only while one is in deviation alarm) and one row
  per alarm change (``15:08 ALARM raised: Ra -10.02 % of nominal``; a deviation alarm's raise
  ERROR, every other raise and a clear WARN; the event's full message is in the health
  message);
  ``M/key``: what the colours mean (static).

The default blueprint (:meth:`RecordingViews.blueprint`): the time panel follows the newest
data (a finished file opens on its end); the parameters' health and the data-quality strip show
the whole run, the outputs and residuals the last ``recent_s`` seconds before the time cursor,
the model, the parameters' table, the log and the projections the state at the cursor; no
legend covers a trace (the key says what the colours mean), no axis zooms in on noise
(deviations in % with their thresholds or a scale).
Plant time is written as minutes:seconds (``14:38``) in the summaries, the log and the model;
the axes' ticks are the viewer's (``+10m``).

The trend's projection to the alarm threshold is drawn beside the panel of each parameter
with an alarm rule, in a 2-D view (``health/<name>/projection``), not in its time-series view:
Rerun (0.41) draws every row ever logged at a time of a time-series view's range, so each
window's projection into the future would stay beside the next (a ``Clear`` only breaks a
line), and points logged at future plant times move the time cursor, which follows the newest
data, past the last window (the outputs' views, the last ``recent_s`` before it, go empty). A
2-D view shows what is latest at the cursor: the window's own projection, any window's when
the cursor is moved back.
"""

from __future__ import annotations

import collections
import json
import math
import re
import time
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, NamedTuple

import numpy as np

from twinwatch._lazy import lazy_module
from twinwatch.sinks.base import AlarmBands

if TYPE_CHECKING:
    import rerun as rr
    import rerun.blueprint as rrb

    from twinwatch.twin.health import (
        AlarmView,
        DiagnosisView,
        HealthView,
        ParameterView,
        RulView,
    )
else:  # imported when a recording opens: loading a configuration does not load rerun
    rr = lazy_module("rerun")
    rrb = lazy_module("rerun.blueprint")

__all__ = ["TIMELINE", "RecordingViews", "emit"]

TIMELINE = "plant_time"
"""Name of the Rerun timeline carrying plant time [s]: a duration timeline, or a timestamp
timeline when the source's clock is the wall clock (times past ``WALL_CLOCK_AFTER``)."""

WALL_CLOCK_AFTER = 1e9
"""Plant times from this many seconds on (2001-09-09) are the source's wall clock, seconds
since the epoch (a recorded log with its time stamps, a drive's clock): the timeline is then a
timestamp (the viewer shows the date and time of day, not ``+490000h``) and the text says the
UTC time of day (``14:38:05Z``)."""

# Colours for the viewer's dark theme, each meaning one thing everywhere.
_MEASURED = (86, 164, 255)
_TWIN = (255, 140, 30)
_RESIDUAL = (196, 150, 255)
_DT_PRIME = (240, 70, 70)
_DT_SECOND = (90, 205, 100)
_DEVIATION = (215, 215, 215)
_NOMINAL = (140, 140, 140)
_BAND = (95, 150, 235)
_SCALE = (105, 105, 105)
_HIDDEN = (0, 0, 0, 0)
_ELAPSED = (200, 200, 120)
_TREND = (230, 120, 200)
_TREND_BAND = (150, 80, 130)
_WARNING = (255, 190, 0)
_ALARM = (240, 60, 60)
_Marker = Literal["circle", "diamond", "cross", "up", "down", "square"]
_STATUS_STYLE: dict[str, tuple[tuple[int, int, int], _Marker, float]] = {
    "estimated": ((90, 205, 100), "circle", 2.0),
    "fused": ((86, 164, 255), "diamond", 2.5),
    "held": ((150, 150, 150), "cross", 2.5),
}
_EVENT_STYLE: dict[str, tuple[tuple[int, int, int], _Marker, float]] = {
    "warning": (_WARNING, "up", 9.0),
    "alarm": (_ALARM, "circle", 9.0),
    "cleared": ((90, 205, 100), "square", 8.0),
    "rul_warning": (_WARNING, "down", 9.0),
    "rul_alarm": (_ALARM, "down", 11.0),
}
"""Alarm changes on a parameter's view: the deviation rule's raises (``warning``, ``alarm``)
and clears, the RUL rule's raises (``rul_warning``, ``rul_alarm``), apart."""
_VARIANTS = (("dt_prime", "DT'", _DT_PRIME), ("dt_second", "DT''", _DT_SECOND))
"""The twin without (DT') and with (DT'') its meta-model terms: key, label, colour."""
_QUALITY_COLORS = (
    (240, 60, 60), (255, 190, 0), (196, 150, 255), (86, 164, 255), (255, 140, 30),
    (90, 205, 100), (230, 120, 200), (160, 160, 160), (40, 200, 200), (190, 190, 60),
)
_SCALE_PCT = 10.0
"""Half-height of the scale drawn for a parameter without an alarm rule [%] (its axis never
zooms in on the noise of a held value)."""
_HEADROOM = 1.6
"""The axis of a parameter's view reaches at least this many times its outermost threshold (or
scale) on each side that has one: the lines never sit on its edge."""
_SCALE_HEADROOM = 1.15
"""The same for the +-10 % scale of a parameter without a rule: its small panel then labels
the ticks -10, 0, 10 (at 1.6 it labelled only 0)."""
_TICK_ROOM = 0.12
"""The least room between an axis' outermost labelled tick and its edge, as a share of the
axis (:func:`_tick_room`): half a label's height on a small panel at 1600x1000."""
_VIEWER_MARGIN = 0.06
"""How far beyond the data, as a share of the axis, the viewer may still draw a labelled tick
(its own margin is 5 %: a stroke ending at 0.8999 m was labelled 0.9 on the plot's edge)."""
_BAND_CLIP = 1.5
"""The 2-sigma band is drawn at most this many times the outer threshold (or scale) away from
nominal: a parameter the data do not determine (+-400 %) does not flatten its plot, and the
panel's summary says so (``2-sigma band from -420 to +420 %, drawn to +-15 %``; within
``_SCALE_HEADROOM`` for a parameter without a rule). At 3 a +-30 % band took a small panel's
axis to -100..100 (its labelled ticks a hundred apart)."""
_PPM = 1e6
"""The fit panel shows the nRMSE in parts per million (ppm) of the output's scale: 1.6e-4 and
3e-7 have readable ticks (160 and 0.3), the bare fraction's ticks read ``0``."""
_PROBLEM_COUNTER = re.compile(
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


class RecordingViews:
    """The entities, styles and layout of one machine's recording.

    Args:
        machine: machine name, first part of every entity path.
        outputs: the twin's outputs, e.g. ``("ia", "omega")``.
        parameters: parameter name -> unit.
        output_units: output -> unit, for the titles.
        nominal: parameter -> nominal value [SI], for the health views' titles.
        estimated: the parameters that get a health view.
        alarm_bands: parameter -> its alarm thresholds [% of nominal].
        recent_s: plant time before the cursor that the outputs' views show [s].
    """

    def __init__(self, machine: str, outputs: Sequence[str], parameters: Mapping[str, str], *,
                 output_units: Mapping[str, str] | None = None,
                 nominal: Mapping[str, float] | None = None,
                 estimated: Sequence[str] | None = None,
                 alarm_bands: Mapping[str, AlarmBands] | None = None,
                 recent_s: float = 10.0) -> None:
        self.machine = machine
        self.outputs = tuple(outputs)
        self.parameters = dict(parameters)
        self.output_units = dict(output_units or {})
        self.nominal = dict(nominal or {})
        self.estimated = tuple(p for p in (estimated if estimated is not None else parameters)
                               if p in self.parameters)
        self.alarm_bands = dict(alarm_bands or {})
        self.recent_s = float(recent_s)
        self._problem_counters: list[str] = []
        self._last_counters: dict[str, int] = {}
        self._ranges: dict[str, tuple[float, float]] = {}
        """view -> the range of its values over the run so far, for its axis frame."""
        self._recent: dict[str, collections.deque[tuple[float, float, float]]] = {}
        """output -> (window end [s], frame low, frame high) of the windows its view shows."""
        self._frames: dict[str, list[float]] = {}
        """view -> the axis frame last logged (logged again only when it changes, and in
        every new file: :meth:`static_ops` forgets them)."""
        self._moments: dict[str, dict[tuple[str, str], tuple[str, float]]] = {}
        """parameter -> (rule kind, level) -> (raised or cleared, plant time [s]): the alarm
        changes seen, for the parameter's summary."""
        self._history: dict[str, deque[tuple[float, float]]] = {}
        """parameter with an alarm rule -> its recent deviations (plant time [s], % of
        nominal), drawn before its projection."""
        self._projected: set[str] = set()
        """parameters whose projection view shows something (cleared when it has none)."""

    def set_alarm_bands(self, alarm_bands: Mapping[str, AlarmBands]) -> list[Op]:
        """New thresholds (a reload): the styles to log again (empty when unchanged)."""
        if dict(alarm_bands) == self.alarm_bands:
            return []
        self.alarm_bands = dict(alarm_bands)
        return self.health_styles()

    def _unit(self, output: str) -> str:
        unit = self.output_units.get(output)
        return f" [{unit}]" if unit else ""

    def _health_title(self, p: str) -> str:
        """``Ra [% of 6.5 ohm]: warning +-5, alarm +-10 %``."""
        nominal = self.nominal.get(p)
        unit = self.parameters.get(p, "")
        of = f"{nominal:.6g} {unit}".rstrip() if nominal is not None else "nominal"
        rule = []
        bands = self.alarm_bands.get(p)
        for name, high, low in (("warning", bands.warning_high, bands.warning_low),
                                ("alarm", bands.alarm_high, bands.alarm_low)) if bands else ():
            if high is not None and low is not None and high == -low:
                rule.append(f"{name} +-{high:g}")
            else:
                rule += [f"{name} {v:+g}" for v in (high, low) if v is not None]
        return f"{p} [% of {of}]" + (": " + ", ".join(rule) + " %" if rule else "")

    def blueprint(self) -> rrb.Blueprint:
        """The default layout: the parameters' health and the data quality over the whole run
        (left), each output measured vs twin and its residual over the last ``recent_s``
        seconds (right), the model DT'', the parameters' table and the log (bottom, side by
        side: each whole at 1600x1000), a one-line key on top; the time panel follows the
        newest data."""
        m = self.machine
        inf = rrb.TimeRangeBoundary.infinite()
        back = rrb.TimeRangeBoundary.cursor_relative(seconds=-self.recent_s)
        now = rrb.TimeRangeBoundary.cursor_relative()

        # Each view property is a chunk of its own (about 3 kB in every file and stream): the
        # whole run is the x axis' range (the data queried are the whole run by default), the
        # recent range the data queried (the x axis follows them).
        def whole() -> dict[str, Any]:
            return {"axis_x": rrb.TimeAxis(view_range=rr.TimeRange(start=inf, end=inf)),
                    "plot_legend": rrb.PlotLegend(visible=False)}

        def recent() -> dict[str, Any]:
            return {"time_ranges": rrb.VisibleTimeRange(TIMELINE, start=back, end=now),
                    "plot_legend": rrb.PlotLegend(visible=False)}

        def origin(*parts: str) -> str:
            return "/" + entity(m, *parts)

        def panel(p: str, beside: bool = False) -> rrb.Container:
            """A parameter's panel: its summary written under its plot (the RUL, the moments
            its alarms were raised, a band beyond the view); beside them, for a parameter
            with an alarm rule, its projection to the alarm threshold at the cursor. With
            ``beside`` (a parameter without a rule whose grid shares the column with ruled
            ones), the summary beside the plot, which keeps the row's height: under it, the
            plot was about 50 px at 1600x1000, too short for its +-10 labels."""
            series = rrb.TimeSeriesView(origin=origin("health", p), name=self._health_title(p),
                                        contents=["$origin/**", "- $origin/summary",
                                                  "- $origin/projection/**"], **whole())
            summary = rrb.TextDocumentView(origin=origin("health", p, "summary"),
                                           name=f"{p}: RUL and alarms", titlebar=False)
            if beside:  # the plot wide enough for a title "D [% of 0.00143 N m s/rad]"
                return rrb.Horizontal(series, summary, column_shares=[2.6, 1.0], name=p)
            plot = rrb.Vertical(series, summary, row_shares=[1.0, 0.5], name=p)
            if p not in self.alarm_bands:
                return plot
            return rrb.Horizontal(plot, rrb.Spatial2DView(
                origin=origin("health", p, "projection"), name=f"{p}: trend to alarm [%]",
                background=(18, 18, 18), visual_bounds=rrb.VisualBounds2D(
                    x_range=[0.0, _BOX[0]], y_range=[0.0, _BOX[1]])),
                column_shares=[2.0, 1.0], name=p)

        ruled = [p for p in self.estimated if p in self.alarm_bands]
        others = [p for p in self.estimated if p not in self.alarm_bands]
        health: list[rrb.Container | rrb.View] = [panel(p) for p in ruled]
        shares = [2.0] * len(ruled)
        if others:
            # beside the ruled panels, the grid's rows are short (1.4 to their 2.0): each
            # summary beside its plot; alone in the column (discovery, the leak), under it
            # (beside, the discovery's 300 s axis lost its minute labels: too narrow)
            views = [panel(p, beside=bool(ruled)) for p in others]
            columns = 1 if len(others) == 1 else 2
            health.append(rrb.Grid(*views, grid_columns=columns, name="other parameters"))
            shares.append(float(math.ceil(len(others) / columns)) * (1.4 if ruled else 2.0))
        quality = rrb.Horizontal(
            rrb.TimeSeriesView(origin=origin("quality"), contents=[
                origin("quality", "nrmse_dt_prime"), origin("quality", "nrmse_dt_second"),
                origin("quality", "nrmse"), origin("quality", "model_check_failed"),
                origin("quality", "frame")],
                name="fit: nRMSE [ppm] DT' DT''", **whole()),
            rrb.TimeSeriesView(origin=origin("quality", "elapsed_ms"),
                               name="estimation [ms]", **whole()),
            rrb.TimeSeriesView(origin=origin("quality", "problems"),
                               name="lost or bad [count]", **whole()),
            column_shares=[1.6, 1.0, 1.0], name="data quality")
        left = rrb.Vertical(
            rrb.Vertical(*health, row_shares=shares, name="health"), quality,
            # the quality strip a sixth of the column at least: with five small panels
            # (the discovery example) its ticks were cut at 1600x1000
            row_shares=[max(sum(shares), 1.0), max(1.0, 0.21 * sum(shares))],
            name="health and data quality")
        pairs = [(rrb.TimeSeriesView(origin=origin("outputs", o),
                                     name=f"{o}{self._unit(o)}: measured, twin", **recent()),
                  rrb.TimeSeriesView(origin=origin("residual", o),
                                     name=f"{o} residual{self._unit(o)}", **recent()))
                 for o in self.outputs]
        right = rrb.Grid(*(v for pair in pairs for v in pair), grid_columns=2,
                         column_shares=[3, 2], name="outputs: measured vs twin")
        bottom = rrb.Horizontal(
            rrb.Tabs(
                rrb.TextDocumentView(origin=origin("model"), name="model: DT'' at the cursor"),
                rrb.TextDocumentView(origin=origin("health"), contents=origin("health"),
                                     name="health message (JSON)"),
                active_tab=0),
            rrb.TextDocumentView(origin=origin("parameter_table"),
                                 name="parameters at the cursor"),
            rrb.TextLogView(
                origin=origin("log"), name="log",
                columns=rrb.TextLogColumns(
                    timeline_columns=[rrb.encodings.TimelineColumn(TIMELINE, visible=False),
                                      rrb.encodings.TimelineColumn("log_time", visible=False),
                                      rrb.encodings.TimelineColumn("log_tick", visible=False)],
                    text_log_columns=[rrb.encodings.TextLogColumn("loglevel"),
                                      rrb.encodings.TextLogColumn("body"),
                                      rrb.encodings.TextLogColumn("entitypath", visible=False)])),
            column_shares=[0.9, 0.6, 1.0])
        key = rrb.TextDocumentView(origin=origin("key"), name="key", titlebar=False)
        return rrb.Blueprint(
            rrb.Vertical(
                key,
                rrb.Horizontal(left, right, column_shares=[1.05, 1]),
                bottom,
                row_shares=[0.42, 5.0, 2.3]),
            rrb.TimePanel(timeline=TIMELINE, play_state="following", state="collapsed"),
            collapse_panels=True,
        )

    def _key(self) -> str:
        return ("**health** [% of nominal] per window: estimated (green dot), fused (blue "
                "diamond), held (grey x); 2-sigma band (blue), trend (pink), warning (amber) and "
                "alarm (red) thresholds; raised: warning (amber triangle), alarm (red dot), RUL "
                "warning / alarm (down-triangles); cleared (green square). **outputs**: measured "
                "(blue), twin (orange), residual (violet). **fit**: nRMSE [ppm] DT' (red), DT'' "
                "(green), model check failed (red x). Plant time in minutes:seconds (a wall clock: "
                "UTC time of day).")

    def static_ops(self) -> list[Op]:
        """What every file and the live stream need once: the key and every series' style
        (and the whole-run views' axis frames are logged again with the next window)."""
        m = self.machine
        self._frames.clear()

        def lines(path: tuple[str, ...], names: Any, colors: Any, widths: Any) -> Op:
            return Op(entity(m, *path), rr.SeriesLines(names=names, colors=colors,
                                                       widths=widths), static=True)

        ops = [Op(entity(m, "key"), rr.TextDocument(self._key(),
                                                    media_type=rr.MediaType.MARKDOWN),
                  static=True)]
        for o in self.outputs:
            u = self._unit(o)
            ops += [lines(("outputs", o, "frame"), [f"{o} axis frame low", f"{o} axis frame high"],
                          [_HIDDEN, _HIDDEN], [1.0, 1.0]),
                    lines(("outputs", o, "measured"), f"{o} measured{u}", _MEASURED, 3.5),
                    lines(("outputs", o, "twin"), f"{o} twin{u}", _TWIN, 1.5),
                    lines(("residual", o), f"{o} measured - twin{u}", _RESIDUAL, 1.0),
                    lines(("residual", o, "frame"), [f"{o} residual axis frame low",
                                                     f"{o} residual axis frame high"],
                          [_HIDDEN, _HIDDEN], [1.0, 1.0])]
        n = len(self.outputs)
        for variant, label, _ in _VARIANTS:
            ops.append(lines(("residual_rmse", variant),
                             [f"{o} RMSE {label}{self._unit(o)}" for o in self.outputs],
                             list(_QUALITY_COLORS[:n]), [1.5] * n))
        n = len(self.parameters)
        ops.append(lines(("parameters",), [f"{p} [{u}]" for p, u in self.parameters.items()],
                         [_QUALITY_COLORS[i % len(_QUALITY_COLORS)] for i in range(n)],
                         [1.0] * n))
        ops += self.health_styles()
        ops.append(lines(("quality", "nrmse"), "nRMSE [ppm] (the twin published)", _DEVIATION,
                         1.0))
        for variant, label, color in _VARIANTS:
            ops.append(lines(("quality", f"nrmse_{variant}"), f"nRMSE {label} [ppm]", color, 2.0))
        ops.append(Op(entity(m, "quality", "model_check_failed"), rr.SeriesPoints(
            names="model check failed [ppm]", colors=_ALARM, markers="cross", marker_sizes=4.0),
            static=True))
        ops.append(lines(("quality", "elapsed_ms"), "estimation time [ms]", _ELAPSED, 1.5))
        for path in (("quality", "frame"), ("quality", "problems", "frame"),
                     ("quality", "elapsed_ms", "frame")):
            ops.append(lines(path, ["axis frame low", "axis frame high"], [_HIDDEN, _HIDDEN],
                             [1.0, 1.0]))
        if self._problem_counters:
            ops.append(self._problem_style())
        return ops

    def _limits(self, p: str) -> list[tuple[str, float, tuple[int, ...]]]:
        """The reference lines of ``p``'s view [%]: its alarm thresholds, or a dim +-5 % scale
        when it has no rule (name, value, colour)."""
        bands = self.alarm_bands.get(p)
        if bands is None:
            return [(f"scale +{_SCALE_PCT:g} % (no alarm rule)", _SCALE_PCT, _SCALE),
                    (f"scale -{_SCALE_PCT:g} % (no alarm rule)", -_SCALE_PCT, _SCALE)]
        return [(f"{name} {value:+g} %", value, color) for name, value, color in (
            ("warning", bands.warning_high, _WARNING), ("warning", bands.warning_low, _WARNING),
            ("alarm", bands.alarm_high, _ALARM), ("alarm", bands.alarm_low, _ALARM))
            if value is not None]

    def _band_clip(self, p: str) -> float:
        """How far from nominal ``p``'s 2-sigma band is drawn at most [%]: ``_BAND_CLIP`` times
        its outer threshold, or within the headroom of its scale when it has no rule (a small
        panel then keeps its ticks -10, 0, 10: at +-15 % it labelled only 0)."""
        outer = max(abs(value) for _, value, _ in self._limits(p))
        return (_BAND_CLIP if p in self.alarm_bands else _SCALE_HEADROOM) * outer

    def _series(self, p: str) -> list[tuple[str, tuple[int, ...], float]]:
        """The series of ``health/<p>/deviation``, in drawing order: name, colour, width (the
        two headroom series are transparent: the axis keeps the thresholds off its edges)."""
        return [("2-sigma low", _BAND, 1.0), ("2-sigma high", _BAND, 1.0),
                ("nominal", _NOMINAL, 1.0),
                *((name, color, 1.5) for name, _, color in self._limits(p)),
                ("headroom high", _HIDDEN, 1.0), ("headroom low", _HIDDEN, 1.0),
                (f"{p} deviation [%]", _DEVIATION, 1.0)]

    def health_styles(self) -> list[Op]:
        """The styles of every health view's series."""
        m = self.machine
        ops: list[Op] = []
        for p in self.estimated:
            series = self._series(p)
            ops.append(Op(entity(m, "health", p, "deviation"), rr.SeriesLines(
                names=[s[0] for s in series], colors=[s[1] for s in series],
                widths=[s[2] for s in series]), static=True))
            for status, (color, marker, size) in _STATUS_STYLE.items():
                ops.append(Op(entity(m, "health", p, status), rr.SeriesPoints(
                    names=f"{p} {status}", colors=color, markers=marker, marker_sizes=size),
                    static=True))
            for kind, (color, marker, size) in _EVENT_STYLE.items():
                label = ("cleared" if kind == "cleared"
                         else f"{kind.replace('_', ' ').replace('rul', 'RUL')} raised")
                ops.append(Op(entity(m, "health", p, "events", kind), rr.SeriesPoints(
                    names=f"{p} {label}", colors=color, markers=marker, marker_sizes=size),
                    static=True))
            ops.append(Op(entity(m, "health", p, "frame"), rr.SeriesLines(
                names=["axis frame low", "axis frame high"], colors=[_HIDDEN, _HIDDEN],
                widths=[1.0, 1.0]), static=True))
            ops.append(Op(entity(m, "health", p, "trend"), rr.SeriesLines(
                names=[f"{p} trend 2-sigma low", f"{p} trend 2-sigma high", f"{p} trend"],
                colors=[_TREND_BAND, _TREND_BAND, _TREND], widths=[1.0, 1.0, 2.0]),
                static=True))
        return ops

    def _problem_style(self) -> Op:
        """The style of the data-lost series (one per problem counter seen so far)."""
        names = self._problem_counters
        return Op(entity(self.machine, "quality", "problems"), rr.SeriesLines(
            names=names, colors=[_QUALITY_COLORS[i % len(_QUALITY_COLORS)]
                                 for i in range(len(names))],
            widths=[1.5] * len(names)), static=True)

    def window_ops(self, times: np.ndarray, meas: Mapping[str, np.ndarray],
                    sim: Mapping[str, np.ndarray], estimates: Mapping[str, float],
                    doc: HealthView, health_json: str, terms_changed: bool,
                    events: list[Mapping[str, Any]]) -> list[Op]:
        """Everything one window logs, in order (called with the lock held). ``doc`` is the
        health message's typed view (:func:`~twinwatch.twin.health.read_health` of
        ``health_json``)."""
        m = self.machine
        t0, t_end = float(times[0]), float(times[-1])
        ops: list[Op] = []
        index = [rr.TimeColumn(TIMELINE, timestamp=times) if t0 >= WALL_CLOCK_AFTER
                 else rr.TimeColumn(TIMELINE, duration=times)]
        for kind, channels in (("measured", meas), ("twin", sim)):
            for name, values in channels.items():
                ops.append(Op(entity(m, "outputs", name, kind),
                               rr.Scalars.columns(scalars=values), index=index))
        for name, values in meas.items():
            frame = self._output_frame(name, t_end, np.concatenate([values, sim[name]])
                                       if name in sim else values)
            if frame is not None:
                ops.append(Op(entity(m, "outputs", name, "frame"), rr.Scalars(frame), t_end))
        for name in meas.keys() & sim.keys():
            residual = meas[name] - sim[name]
            ops.append(Op(entity(m, "residual", name),
                           rr.Scalars.columns(scalars=residual), index=index))
            frame = self._output_frame(f"residual/{name}", t_end, residual, two_ticks=False)
            if frame is not None:
                ops.append(Op(entity(m, "residual", name, "frame"), rr.Scalars(frame), t_end))
        for variant, rmse in _residual_rmse(doc).items():
            per_output = [_num(rmse.get(o)) for o in self.outputs]
            if any(math.isfinite(v) for v in per_output):
                ops.append(Op(entity(m, "residual_rmse", variant), rr.Scalars(per_output),
                              t_end))
        ops.append(Op(entity(m, "parameters"), rr.Scalars(
            [estimates.get(p, math.nan) for p in self.parameters]), t_end))
        params = doc.parameters or {}
        for p in self.estimated:
            ph = params.get(p)
            if ph is not None:
                ops += self._health_ops(p, ph, t_end)
                if p in self.alarm_bands:
                    ops += self._projection_ops(p, ph, t_end)
        for ev in events:
            ops += self._event_ops(ev, t_end, params)
        alarms = doc.alarms or {}
        for p in self.estimated:
            ph = params.get(p)
            if ph is not None:
                ops.append(Op(entity(m, "health", p, "summary"), rr.TextDocument(
                    self._summary(p, ph, alarms.get(p)),
                    media_type=rr.MediaType.MARKDOWN), t_end))
        ops += self._quality_ops(doc, t_end)
        ops.append(Op(entity(m, "model"), rr.TextDocument(
            _model_document(m, t_end, doc), media_type=rr.MediaType.MARKDOWN), t_end))
        table = _parameter_table(doc)
        if table:
            ops.append(Op(entity(m, "parameter_table"), rr.TextDocument(
                table, media_type=rr.MediaType.MARKDOWN), t_end))
        pretty = json.dumps(json.loads(health_json), indent=2)
        ops.append(Op(entity(m, "health"), rr.TextDocument(
            f"## {m}: health at t = {t_end:.3f} s\n\n```json\n{pretty}\n```\n",
            media_type=rr.MediaType.MARKDOWN), t_end))
        text, level = _log_row(t0, t_end, doc, terms_changed, self._new_problems(doc),
                               health_json)
        ops.append(Op(entity(m, "log"), rr.TextLog(text, level=level), t_end))
        return ops

    def _health_ops(self, p: str, ph: ParameterView, t: float) -> list[Op]:
        """The deviation of ``p`` with its band, nominal and thresholds, and its status marker
        (the series of :meth:`_series`)."""
        dev = _num(ph.deviation_pct)
        if not math.isfinite(dev):
            return []
        limits = [value for _, value, _ in self._limits(p)]
        outer = max(abs(v) for v in limits)
        clip = self._band_clip(p)
        low, high = _band_pct(ph)
        band = [float(np.clip(v, -clip, clip)) if math.isfinite(v) else math.nan
                for v in (low, high)]
        top, bottom = max(0.0, *limits), min(0.0, *limits)
        room = _HEADROOM if p in self.alarm_bands else _SCALE_HEADROOM
        headroom = [room * top if top > 0 else 0.2 * outer,
                    room * bottom if bottom < 0 else -0.2 * outer]
        values = [*band, 0.0, *limits, *headroom, dev]
        m = self.machine
        ops = [Op(entity(m, "health", p, "deviation"), rr.Scalars(values), t)]
        frame = self._run_frame(f"health/{p}", values)
        if frame is not None:
            ops.append(Op(entity(m, "health", p, "frame"), rr.Scalars(frame), t))
        status = ph.status
        if status in _STATUS_STYLE:
            ops.append(Op(entity(m, "health", p, str(status)), rr.Scalars(dev), t))
        trend = _trend_pct(ph)
        if trend is not None:
            ops.append(Op(entity(m, "health", p, "trend"), rr.Scalars(
                [float(np.clip(v, -clip, clip)) for v in trend]), t))
        return ops

    def _projection_ops(self, p: str, ph: ParameterView, t: float) -> list[Op]:
        """``p``'s projection view (``health/<p>/projection``, a 2-D view: latest at the
        cursor, so only the window's own projection is on screen): the recent deviations, the
        trend from its level now to the alarm threshold at the median crossing and at both
        ends of the 95 % interval, the thresholds, the moment now and the crossing, written.
        Cleared while the message predicts no crossing (none yet, crossed, not degrading)."""
        m = self.machine
        path = entity(m, "health", p, "projection")
        dev = _num(ph.deviation_pct)
        if math.isfinite(dev):
            history = self._history.setdefault(p, deque(maxlen=_HISTORY))
            if history and history[-1][0] >= t:  # a file reopened, a restart: time went back
                history.clear()
            history.append((t, dev))
        drawing = _projection(p, ph, t, list(self._history.get(p, ())),
                              self._limits(p))
        if drawing is None:
            if p not in self._projected:
                return []
            self._projected.discard(p)
            return [Op(path, rr.Clear(recursive=True), t)]
        self._projected.add(p)
        strips, points = drawing
        return [Op(f"{path}/lines", rr.LineStrips2D(
                    [s.xy for s in strips], colors=[s.color for s in strips],
                    radii=rr.Radius.ui_points([s.width for s in strips])), t),
                Op(f"{path}/labels", rr.Points2D(
                    [q.xy for q in points], colors=[q.color for q in points],
                    radii=rr.Radius.ui_points([q.size for q in points]),
                    labels=[q.label for q in points], show_labels=True), t)]

    def _event_ops(self, ev: Mapping[str, Any], t_end: float,
                   params: Mapping[str, ParameterView]) -> list[Op]:
        """An alarm change: its message in the log, a marker on its parameter's view (a
        deviation rule's at the event's deviation, a RUL rule's at the parameter's deviation in
        this window), its moment kept for the parameter's summary."""
        m = self.machine
        p = str(ev.get("parameter", ""))
        level, previous = ev.get("level"), ev.get("previous")
        rule = "rul" if ev.get("kind") == "rul" else "deviation"
        t = _num(ev.get("t"))
        t = t if math.isfinite(t) else t_end
        raised = _RANK.get(str(level), 0) > _RANK.get(str(previous), 0)
        kind = str(level) if raised else "cleared"
        # ERROR only for a deviation alarm raised (stop now); a RUL alarm plans maintenance
        severity = (rr.TextLogLevel.ERROR if (raised and level == "alarm" and rule == "deviation")
                    else rr.TextLogLevel.WARN)
        ops = [Op(entity(m, "log"), rr.TextLog(_event_row(ev, t, rule, raised, params),
                                               level=severity), t)]
        if p:  # a diagnosis names no parameter
            self._moments.setdefault(p, {})[(rule, str(level if raised else previous))] = (
                "raised" if raised else "cleared", t)
        if rule == "rul":
            ph = params.get(p)
            dev = _num(ph.deviation_pct if ph is not None else None)
            kind = f"rul_{kind}" if raised else ""
        else:
            dev = _num(ev.get("deviation_pct"))
        if p in self.estimated and kind in _EVENT_STYLE and math.isfinite(dev):
            ops.append(Op(entity(m, "health", p, "events", kind), rr.Scalars(dev), t))
        return ops

    def _summary(self, p: str, ph: ParameterView, alarm: AlarmView | None) -> str:
        """What ``p``'s panel says in words (markdown, two to four short lines): its deviation
        and status, its trend, the RUL to each threshold of its rule (median and 95 %
        interval, and the plant time of the crossing), the moments its deviation and RUL alarms
        were raised or cleared, and its 2-sigma band when that leaves the view."""
        dev = _num(ph.deviation_pct)
        status = _str(ph.status)
        rel = _num(ph.rel_std_pct)
        head = f"**{p} {_fmt(dev, '+.2f')} %** {status}"
        if status in ("estimated", "fused") and math.isfinite(rel):
            head += f" +- {2 * rel:.2g} % (2 sigma)"  # as the summary and the diagnosis say
        trend = ph.trend
        if trend is None or trend.model is None:
            head += "; no trend yet" if trend is not None and trend.model_fields_set else ""
        elif trend.degrading is False:
            head += "; not degrading"
        else:
            rate = _num(trend.rate_pct_per_h)
            head += f"; trend {trend.model} {_fmt(rate, '+.3g')} %/h"
        lines = [head]
        rul = ph.rul
        if p in self.alarm_bands:
            text = _rul_text(ph, at=True)
            if text:
                lines.append(f"**{text}**")
            elif rul is not None and rul.status in ("insufficient", "not_degrading"):
                lines.append("RUL: " + str(rul.status).replace("_", " "))
        moments = dict(self._moments.get(p, {}))
        for rule, state in (("deviation", alarm), ("rul", alarm.rul if alarm else None)):
            level = _str(state.level, "normal") if state is not None else "normal"
            since = _num(state.since_t if state is not None else None)
            if _RANK.get(level, 0) > 0 and (rule, level) not in moments and \
                    math.isfinite(since):
                moments[(rule, level)] = ("raised", since)  # raised before this recording
        said = []
        for rule, name in (("deviation", "deviation"), ("rul", "RUL")):
            seen = sorted(((t, what, level) for (r, level), (what, t) in moments.items()
                           if r == rule))
            if seen:
                said.append(f"{name} " + ", ".join(
                    f"{level} {what} at {clock(t)}" for t, what, level in seen))
        if said:
            lines.append("; ".join(said))
        low, high = _band_pct(ph)
        clip = self._band_clip(p)
        if any(math.isfinite(v) and abs(v) > clip for v in (low, high)):
            # words between the numbers, and no exponent below 10^5 %: a narrow summary
            # wraps at the spaces (``-95.5..+2.1e+03`` was broken after its ``-`` and ``e+``)
            lines.append(f"2-sigma band from {_pct_text(low)} to {_pct_text(high)} %, "
                         f"drawn to +-{clip:g} %")
        return "  \n".join(lines) + "\n"

    def _quality_ops(self, doc: HealthView, t: float) -> list[Op]:
        """nRMSE and the model check, the adaptation time, the counters of lost data."""
        m = self.machine
        ops = []
        residual = doc.residual
        fits = ((residual.dt_prime, residual.dt_second) if residual is not None
                else (None, None))
        for variant, fit in zip(("dt_prime", "dt_second"), fits, strict=True):
            value = _num(fit.nrmse) if fit is not None else math.nan
            if math.isfinite(value):
                ops.append(Op(entity(m, "quality", f"nrmse_{variant}"),
                               rr.Scalars(value * _PPM), t))
        nrmse = _num(doc.nrmse)
        values = [_num(f.nrmse if f is not None else None) for f in fits] + [nrmse]
        frame = self._run_frame("quality", [v * _PPM for v in values])
        if frame is not None:
            ops.append(Op(entity(m, "quality", "frame"), rr.Scalars(frame), t))
        if math.isfinite(nrmse):
            ops.append(Op(entity(m, "quality", "nrmse"), rr.Scalars(nrmse * _PPM), t))
            check = doc.model_check
            if check is not None and check.passed is False:
                ops.append(Op(entity(m, "quality", "model_check_failed"),
                              rr.Scalars(nrmse * _PPM), t))
        elapsed = _num(doc.elapsed_s)
        if math.isfinite(elapsed):
            ops.append(Op(entity(m, "quality", "elapsed_ms"), rr.Scalars(elapsed * 1e3), t))
            # its axis frame over the run (logged when it changes, and in every new file)
            view = "quality/elapsed_ms"
            high = max(self._ranges.get(view, (0.0, 0.0))[1], elapsed * 1e3)
            self._ranges[view] = (0.0, high)
            frame = _sparse_frame(high)
            if frame != self._frames.get(view):
                self._frames[view] = frame
                ops.append(Op(entity(m, "quality", "elapsed_ms", "frame"), rr.Scalars(frame),
                              t))
        counters = doc.counters
        if counters is not None:
            new = [k for k in counters if k not in self._problem_counters
                   and _PROBLEM_COUNTER.search(k) and isinstance(counters[k], int | float)]
            if new:
                self._problem_counters += sorted(new)
                ops.append(self._problem_style())
            if self._problem_counters:
                counts = [_num(counters.get(k)) for k in self._problem_counters]
                ops.append(Op(entity(m, "quality", "problems"), rr.Scalars(counts), t))
            frame = self._run_frame("problems", [0.0, 1.0, *(
                _num(counters.get(k)) for k in self._problem_counters)])
            if frame is not None:
                ops.append(Op(entity(m, "quality", "problems", "frame"), rr.Scalars(frame), t))
        return ops

    def _output_frame(self, output: str, t_end: float, values: np.ndarray,
                      two_ticks: bool = True) -> list[float] | None:
        """The axis frame (:func:`_frame`; without ``two_ticks`` the window's range: a
        residual keeps its scale) of an output's window, its labels' room
        (:func:`_tick_room`) at the scale of the windows its view shows (those ending in the
        last ``recent_s``): the viewer labels the view's range, and room at the window's own
        scale left the view's outer labels cut (``0.9`` over a 0.78-0.9 m stroke)."""
        finite = values[np.isfinite(values)]
        if not finite.size:
            return None
        frame = (_frame(finite, room=False) if two_ticks
                 else [float(finite.min()), float(finite.max())])
        if frame is None:
            return None
        recent = self._recent.setdefault(output, collections.deque())
        recent.append((t_end, frame[0], frame[1]))
        while recent[0][0] < t_end - self.recent_s or recent[0][0] > t_end:
            recent.popleft()  # out of the view, or from before the source's clock went back
        width = max(hi for _, _, hi in recent) - min(lo for _, lo, _ in recent)
        return _tick_room(frame[0], frame[1], scale=width)

    def _run_frame(self, view: str, values: Sequence[float], room: bool = True
                   ) -> list[float] | None:
        """The axis frame (:func:`_frame`) of a view that shows the whole run: over every
        finite value it has shown so far; None when it is the one last logged."""
        finite = [v for v in values if math.isfinite(v)]
        if not finite:
            return None
        low, high = self._ranges.get(view, (min(finite), max(finite)))
        low, high = min(low, *finite), max(high, *finite)
        self._ranges[view] = (low, high)
        frame = _frame(np.array([low, high]), room)
        if frame is None or frame == self._frames.get(view):
            return None  # unchanged: one chunk less per view and window in the file
        self._frames[view] = frame
        return frame

    def _new_problems(self, doc: HealthView) -> dict[str, int]:
        """The problem counters that grew since the last window, and by how much."""
        counters = doc.counters
        if counters is None:
            return {}
        grew = {}
        for k, v in counters.items():
            if isinstance(v, int) and _PROBLEM_COUNTER.search(k):
                if v > self._last_counters.get(k, 0):
                    grew[k] = v - self._last_counters.get(k, 0)
                self._last_counters[k] = v
        return grew


def emit(rec: rr.RecordingStream, ops: Sequence[Op]) -> None:
    """Log ``ops`` to ``rec`` in order."""
    for op in ops:
        if op.static:
            rec.log(op.entity, op.payload, static=True)
        elif op.index is not None:
            rec.send_columns(op.entity, indexes=op.index, columns=op.payload)
        else:
            t = op.t if op.t is not None else 0.0
            if t >= WALL_CLOCK_AFTER:
                rec.set_time(TIMELINE, timestamp=t)
            else:
                rec.set_time(TIMELINE, duration=t)
            rec.log(op.entity, op.payload)


_RANK = {"normal": 0, "warning": 1, "alarm": 2}


def _str(x: Any, default: str = "") -> str:
    """A text field of the message as text (``default`` when the message lacks it)."""
    return default if x is None else str(x)


def _num(x: Any) -> float:
    """A JSON number as a float (NaN for null or anything else: a gap in a plot)."""
    if isinstance(x, int | float) and not isinstance(x, bool):
        return float(x)
    return math.nan


def _residual_rmse(doc: HealthView) -> dict[str, Mapping[str, float | None]]:
    """``residual.<dt_prime|dt_second>.rmse``: output -> RMSE of the twin without and with its
    terms (empty for a variant the message does not hold)."""
    residual = doc.residual
    if residual is None:
        return {"dt_prime": {}, "dt_second": {}}
    return {"dt_prime": (residual.dt_prime.rmse if residual.dt_prime else None) or {},
            "dt_second": (residual.dt_second.rmse if residual.dt_second else None) or {}}


def _frame(values: np.ndarray, room: bool = True) -> list[float] | None:
    """Two transparent values that give an axis two labelled ticks. The viewer labels ticks at
    powers of ten only, and only when at most about four of them span the axis (seen at
    1600x1000): a pressure of 50 380-50 425 Pa gets one label (50 400). The frame is the range,
    widened on its nearer side to the next multiple of that power of ten when fewer than two
    lie inside (50 380-50 500 Pa: 50 400 and 50 500); with ``room``, then widened so its
    outermost labels are not cut (:func:`_tick_room`). None without finite values."""
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
    return _tick_room(*frame) if room else list(frame)


def _sparse_frame(high: float) -> list[float]:
    """The axis frame ``[0, top]`` (the unit of ``high``) of a small panel of positive values
    up to ``high`` (the estimation time [ms]); ``[0, 1]`` when ``high`` is not positive. From 0
    to ``high`` when at most 2.3 steps of its power of ten span it (0, 100, 200 for 220 ms),
    else to the next power of ten (0, 1000 for 322 ms: with 0, 100, 200, 300 in the strip's
    55 px the viewer labelled 0 alone, its labels at least about 19 px apart), and
    ``_TICK_ROOM`` above for the top label (0 sits on the viewer's own margin)."""
    if not math.isfinite(high) or high <= 0.0:
        return [0.0, 1.0]
    step = 10.0 ** math.floor(math.log10(high))
    label = math.floor(high / step) * step if high <= 2.3 * step else 10.0 * step
    return [0.0, max(high, label / (1.0 - _TICK_ROOM))]


def _tick_room(low: float, high: float, scale: float | None = None) -> list[float]:
    """``[low, high]`` widened on a side whose outermost labelled tick lies within
    ``_TICK_ROOM`` of the axis' height from its edge: the viewer centres a label on its tick
    and clips what leaves the plot (the fit strip's ``100``, the outputs' outer labels were
    cut in half at 1600x1000). The viewer labels ticks at least about 22 px apart: a
    parameter's +-10 panel needs about 70 px of plot for the widened axis (the layout gives it
    about 100: its summary beside the plot, :meth:`RecordingViews.blueprint`). ``scale``: the
    width of the range the view shows when it is wider than ``[low, high]`` (its ticks and
    room are the view's)."""
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


def _pct_text(value: float) -> str:
    """A signed percentage for a summary: three significant digits, or whole from 100 %
    up to 10^5 % (``+2104``, not ``+2.1e+03``), an exponent only beyond."""
    if math.isfinite(value) and 100.0 <= abs(value) < 1e5:
        return f"{value:+.0f}"
    return f"{value:+.3g}"


def _band_pct(ph: ParameterView) -> tuple[float, float]:
    """The 2-sigma band of a parameter's published value, in % of nominal (NaN when the
    message gives none): the fused interval for a fused or held value that has one, else the
    value +- 2 relative standard errors."""
    nom, value, rel = _num(ph.nominal), _num(ph.value), _num(ph.rel_std_pct)
    if not math.isfinite(nom) or nom == 0.0:
        return math.nan, math.nan
    fused = ph.fused
    if ph.status != "estimated" and fused is not None:
        low, high = _num(fused.low), _num(fused.high)
    elif math.isfinite(value) and math.isfinite(rel):
        low, high = value * (1.0 - 0.02 * rel), value * (1.0 + 0.02 * rel)
    else:
        return math.nan, math.nan
    return (low / nom - 1.0) * 100.0, (high / nom - 1.0) * 100.0


_HISTORY = 1000
"""Deviations kept per parameter for its projection view (the last 1000 windows at most)."""
_BOX = (240.0, 100.0)
"""The projection view's drawing [view units]: width, height (about the view's shape at
1600x1000, y down); the view's bounds (:meth:`RecordingViews.blueprint`)."""
_MARGIN = (2.0, 2.0, 15.0, 15.0)
"""Room kept in the drawing for the labels: left, right, top, bottom [view units]."""
_CHAR_W, _LABEL_PAD = 6.5, 5.0
"""A label's character width and its box's padding in the drawing's units (the viewer's text
is about 12 px high, the drawing about 270 px wide at 1600x1000, seen): labels are kept inside
the view."""
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


def _projection(p: str, ph: ParameterView, t: float, history: Sequence[tuple[float, float]],
                limits: Sequence[tuple[str, float, tuple[int, ...]]],
                ) -> tuple[list[_Strip], list[_Label]] | None:
    """What ``p``'s projection view draws at plant time ``t`` (:meth:`RecordingViews.
    _projection_ops`), in the view's units (``_BOX``): None without a trend level and a
    predicted alarm crossing. The time axis runs from as far before now as the interval's end
    is after it (the recent deviations) to the interval's end (twice the median's distance when
    some draws never cross); the value axis spans what is drawn and the alarm threshold.
    The steps: what the message predicts (:func:`_predicted_crossing`), the curves, the frame
    (:class:`_Frame`), the strips (:func:`_projection_strips`) and the labels
    (:func:`_projection_labels`)."""
    predicted = _predicted_crossing(ph, t)
    if predicted is None:
        return None
    nom, level, th, t_cross, t_low, t_high = predicted

    def pct(v: Any) -> Any:
        return (np.asarray(v, dtype=float) / nom - 1.0) * 100.0

    end = t_high if math.isfinite(t_high) and t_high > t_cross else t + 2.0 * (t_cross - t)
    start = t - (end - t)
    growth = _num(ph.trend.growth) if ph.trend is not None else math.nan
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
    """What :func:`_projection` draws from: (nominal, trend level, alarm threshold [SI],
    crossing's plant time, its interval's ends [s], nan where open); None unless the message
    predicts the alarm's crossing after ``t`` from a trend level, on a nonzero nominal."""
    trend, rul = ph.trend, ph.rul
    crossing = rul.alarm if rul is not None else None
    nom = _num(ph.nominal)
    level = _num(trend.level if trend is not None else None)
    if (crossing is None or crossing.status != "predicted" or not math.isfinite(level)
            or not math.isfinite(nom) or nom == 0.0):
        return None
    th, t_cross = _num(crossing.threshold), _num(crossing.t)
    if not (math.isfinite(th) and math.isfinite(t_cross) and t_cross > t):
        return None
    return nom, level, th, t_cross, _num(crossing.t_low), _num(crossing.t_high)


@dataclass(frozen=True)
class _Frame:
    """The projection's axes: plant time ``start`` to ``end`` [s] across, the deviation
    ``low`` to ``high`` [% of nominal] up, mapped into the drawing (:data:`_BOX`, inside
    :data:`_MARGIN`; y down)."""

    start: float
    end: float
    low: float
    high: float

    def xy(self, ts: Any, vs: Any) -> np.ndarray:
        """Points (k, 2) in the drawing of times ``ts`` [s] and deviations ``vs`` [%]."""
        w, h = _BOX
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
    strips.append(_Strip(frame.xy([start, end], [th_pct, th_pct]), _ALARM, 1.5))
    strips.append(_Strip(frame.xy([t, t], [frame.low, frame.high]), _NOMINAL, 0.75))
    if len(past) > 1:
        strips.append(_Strip(frame.xy(past[:, 0], past[:, 1]), _DEVIATION, 1.0))
    for i, c in enumerate(curves):
        median = i == len(curves) - 1
        strips.append(_Strip(frame.xy(c[:, 0], c[:, 1]), _TREND if median else _TREND_BAND,
                             2.0 if median else 1.0))
    return strips


def _projection_labels(frame: _Frame, t: float, level_pct: float, th_pct: float,
                       times: tuple[float, float, float],
                       others: Sequence[tuple[str, float, tuple[int, ...]]]) -> list[_Label]:
    """The projection's points and texts: the level now, the crossing, each threshold's
    value, now and the crossing's plant time with its interval (``times``: the crossing, the
    interval's ends, nan where open), written under or over their lines and kept inside the
    view."""
    w = _BOX[0]
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

    texts = [(f"alarm {th_pct:+.3g} %", frame.x(frame.start), outer, _ALARM, 0.5),
             *((f"{name.split()[0]} {v:+.3g} %", frame.x(frame.start),
                frame.y(t, v) + (_UNDER if v < level_pct else -_OVER), c, 0.5)
               for name, v, c in others),
             (f"now {clock(t)}", frame.x(t), inner, _NOMINAL, 0.5),
             (f"{clock(t_cross)}{band}", frame.x(t_cross), outer, _ALARM, 0.5)]
    labels = [_Label(tuple(frame.xy([t], [level_pct])[0]), f"{level_pct:+.3g} %", _TREND, 2.5),
              _Label(tuple(frame.xy([t_cross], [th_pct])[0]), "", _ALARM, 3.0)]
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

def _trend_pct(ph: ParameterView) -> tuple[float, float, float] | None:
    """The parameter's trend (``trend.level`` +- 2 ``level_std``, when the message has one) in
    % of nominal: (low, high, level); None without a trend level."""
    trend = ph.trend
    nom = _num(ph.nominal)
    level = _num(trend.level if trend is not None else None)
    std = _num(trend.level_std if trend is not None else None)
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


def _rul_text(ph: ParameterView, at: bool = False) -> str:
    """``RUL to alarm 3m 40s (2m 50s-5m 10s)`` from the message's ``rul`` (empty without);
    with ``at``, the crossing's plant time too (``, at 18:10 (17:30-19:50)``). An open end
    (some draws never reach it) is ``never``."""
    parts = []
    for level, c in _crossings(ph.rul):
        if c.status == "crossed":
            parts.append(f"{level} crossed")
        elif c.status == "predicted" and math.isfinite(_num(c.rul_s)):
            low, high = _num(c.low_s), _num(c.high_s)
            text = (f"RUL to {level} {span(_num(c.rul_s))} ({span(low)}-"
                    f"{span(high) if math.isfinite(high) else 'never'})")
            t, t_low, t_high = _num(c.t), _num(c.t_low), _num(c.t_high)
            if at and math.isfinite(t):
                text += (f", at {clock(t)} ({clock(t_low)}-"
                         f"{clock(t_high) if math.isfinite(t_high) else 'never'})")
            parts.append(text)
    return ", ".join(parts)


def _rul_short(ph: ParameterView) -> str:
    """``RUL alarm 3m 32s`` (the median to the nearest threshold not crossed yet; the
    interval is on the parameter's panel), else ``alarm crossed``, or empty."""
    crossed = ""
    for level, c in _crossings(ph.rul):
        if c.status == "crossed":
            crossed = f"{level} crossed"
        elif c.status == "predicted" and math.isfinite(_num(c.rul_s)):
            return f"RUL {level} {span(_num(c.rul_s))}"
    return crossed


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


def _fmt(x: Any, spec: str = ".6g") -> str:
    v = _num(x)
    return format(v, spec) if math.isfinite(v) else "n/a"


def _diagnosis_lines(d: DiagnosisView | None, parameters: Any = None) -> list[str]:
    """The diagnosis as markdown lines (none without one): the outcome, the first fault's
    action and its evidence for and against, the next faults with their probabilities; with
    no fault yet, what is developing (:func:`~twinwatch.twin.health.developing_line`)."""
    if d is None:
        return []
    faults = d.faults or []
    status = d.status
    if status == "fault" and faults:
        f = faults[0]
        lines = [f"**Diagnosis: {f.id}** ({f.component}), probability "
                 f"{_fmt(f.probability, '.2f')}, urgency {f.urgency}: "
                 f"{f.action}  "]
        lines += [f"+ {x}  " for x in f.evidence_for or []]
        lines += [f"- {x}  " for x in f.evidence_against or []]
    elif status == "check_function":
        since = d.check_function_since
        lines = ["**CHECK FUNCTION: the twin does not describe this machine**"
                 + (f" since {_fmt(since, '.0f')} s" if since is not None else "")
                 + f" ({d.check_failed or 'its model check failing'}): its "
                 "estimates are held and no fault is named; check the sensors and the model  "]
    elif status == "unknown":
        lines = [f"**Diagnosis: a fault the library does not know** (probability "
                 f"{_fmt(d.unknown, '.2f')}): " + "; ".join(
                     [f"`{t}`" for t in d.unknown_terms or []]
                     + list(d.unexplained or [])) + "  "]
    else:
        lines = [f"**Diagnosis: no fault** (probability {_fmt(d.no_fault, '.2f')})"]
        from twinwatch.twin.health import developing_line

        developing = developing_line(d, parameters or {})
        if developing:
            lines[0] += "  "
            lines.append(f"*{developing}*")
    others = [f"{f.id} {_fmt(f.probability, '.2f')}"
              for f in faults[1 if status == "fault" else 0:4]]
    if others:
        lines.append("next: " + ", ".join(others) + "  ")
    if status != "fault":  # no part named: why the plausible ones were ruled out, short
        lines += [f"*{x.split(' (expects ')[0]}*  " for x in (d.ruled_out or [])[:2]]
        # and what the diagnosis cannot see (its "no fault" there is the prior)
        lines += [f"*{x}*  " for x in (getattr(d, "unobserved", None) or [])[:2]]
    return [*lines, ""]


def _parameter_table(doc: HealthView) -> str:
    """Every parameter at the window as markdown (the model panel's neighbour): a table of the
    parameters not fixed (value and status; each estimated one's deviation from nominal is on
    its panel), the fixed ones in a line under it, then why the held ones are held. Empty
    without parameters."""
    table = doc.parameters or {}
    if not table:
        return ""
    lines = ["| parameter | value | status (+- 2 sigma) |", "|---|---:|---|"]
    reasons: dict[str, list[str]] = {}
    fixed = []
    for name, p in table.items():
        status = _str(p.status)
        value = f"{_fmt(p.value)} {_str(p.unit)}".rstrip()
        if status == "fixed":
            fixed.append(f"{name} {value}")
            continue
        rel = _num(p.rel_std_pct)
        if status in ("estimated", "fused") and math.isfinite(rel):
            status += f" +- {2 * rel:.2g} %"  # 2 sigma, as the header says
        elif status == "tied" and p.reason:
            status = str(p.reason)
        elif status == "held" and p.reason:
            reasons.setdefault(str(p.reason).removesuffix(_HELD), []).append(str(name))
        lines.append(f"| {name} | {value} | {status} |")
    notes = []
    if fixed:
        notes.append("fixed: " + ", ".join(fixed))
    notes += [f"{', '.join(names)} held: {reason}" for reason, names in reasons.items()]
    if notes:
        lines += ["", "  \n".join(notes)]
    return "\n".join(lines) + "\n"


_HELD = ": held at last trusted value"
"""The end of every reason a parameter is held (:mod:`twinwatch.twin.estimation.gate`): the
table says "held" already."""


def _model_document(machine: str, t: float, doc: HealthView) -> str:
    """The twin DT'' as markdown: the diagnosis first (the most probable fault, its action and
    evidence), each meta-model term (equation, meaning, evidence), then the fit (every
    parameter's value is beside it: :func:`_parameter_table`)."""
    terms = doc.terms or []
    model = doc.model
    twin = f"`{model}`" if model else "the physical twin"
    window = doc.window
    at = f"at {clock(t)}" + (f", window {window}" if window is not None else "")
    lines = _diagnosis_lines(doc.diagnosis, doc.parameters)
    if not terms:
        lines.append(f"**DT'' = DT** {at}: {twin} alone explains the data.")
    else:
        n = len(terms)
        lines.append(f"**DT'' = {twin} + {n} meta-model term{'s' if n > 1 else ''}** {at} "
                     "(paper Eq. 3):")
        for i, term in enumerate(terms, 1):
            lines.append("")
            lines.append(f"**{i}.** `{_str(term.equation, '?')}`  ")
            if term.meaning:
                lines.append(f"{term.meaning}  ")
            params = term.params or {}
            std = term.params_std or {}
            values = ", ".join(
                f"{k} = {_fmt(v, '.5g')}" + (f" +- {_fmt(std[k], '.2g')}"
                                             if math.isfinite(_num(std.get(k))) else "")
                for k, v in params.items())
            evidence = []
            if term.since_window is not None:
                evidence.append(f"found in window {term.since_window}")
            if math.isfinite(_num(term.significance)):
                evidence.append(f"significance {_fmt(term.significance, '.3g')}")
            if values:
                evidence.append(values + " (1 sigma)")
            if math.isfinite(_num(term.evidence_windows)):
                evidence.append(f"evidence of {_fmt(term.evidence_windows, '.3g')} windows")
            if evidence:
                lines.append("; ".join(evidence))
    disc = doc.discovery
    if disc is not None and disc.too_large:
        lines += ["", f"The residual is too large for the twin ({disc.consecutive} "
                  "windows in a row): discovery searches for what the model lacks."]
    rmse = doc.rmse
    if rmse:
        fit = ", ".join(f"{k} {_fmt(v, '.3g')}" for k, v in rmse.items())
        lines += ["", f"fit: nRMSE {_fmt(doc.nrmse, '.3g')}; RMSE {fit}"]
    return "\n".join(lines) + "\n"


def _event_row(ev: Mapping[str, Any], t: float, rule: str, raised: bool,
               params: Mapping[str, ParameterView]) -> str:
    """An alarm change as one short log row (the event's full ``message`` is in the health
    message): ``15:08 ALARM raised: Ra -10.02 % of nominal``, ``16:20 Ra alarm cleared to
    warning (-8.00 %)``, ``8:08 RUL WARNING raised: Ra, alarm in 7m 12s``, ``4:46 fault cleared:
    unbalance (probability 0.12)``."""
    p, level, previous = str(ev.get("parameter", "")), ev.get("level"), ev.get("previous")
    when = clock(t)
    if ev.get("kind") == "diagnosis":
        word = "FAULT raised" if raised else "fault cleared"
        odds = _fmt(ev.get("probability"), ".2f")
        return f"{when} {word}: {ev.get('fault')} (probability {odds})"
    if not p:  # an event of another kind: its own message, without the machine's name
        return f"{when} " + str(ev.get("message", "")).removeprefix(f"{ev.get('machine')}: ")
    if rule == "rul":
        if not raised:
            return f"{when} {p} RUL {previous} cleared to {level}"
        ph = params.get(p)
        rul = _rul_short(ph) if ph is not None else ""
        rul = rul.replace("RUL ", "", 1).replace(" ", " in ", 1) if rul.startswith("RUL") else rul
        return f"{when} RUL {str(level).upper()} raised: {p}" + (f", {rul}" if rul else "")
    dev = _num(ev.get("deviation_pct"))
    if raised:
        return f"{when} {str(level).upper()} raised: {p} {_fmt(dev, '+.2f')} % of nominal"
    return f"{when} {p} {previous} cleared to {level} ({_fmt(dev, '+.2f')} %)"


def _log_row(t0: float, t_end: float, doc: HealthView, terms_changed: bool,
             grew: Mapping[str, int], health_json: str = "{}") -> tuple[str, rr.TextLogLevel]:
    """One short line for the window (a Rerun log row is not wrapped: about 85 characters fit
    the log panel at 1600x1000), and its level, the machine's state: ERROR while a parameter is
    in deviation alarm, WARN while one is in warning or has a RUL level raised, the model check
    fails, the structure changed or data were lost, else INFO.
    The window and the plant time of its end; each parameter with an alarm rule: its
    deviation [% of nominal], value, status when not ``estimated``, its deviation and RUL
    levels when raised (else the RUL's median); then what went wrong (model check, DT''
    changed, data lost). The other parameters and the fit are in the table and panels at the
    cursor, the whole message in its tab. ``t0`` is the window's start (unused: the row gives
    its end). A document that is no health message (``health_json``, as logged) shows its
    top-level scalars."""
    del t0
    parts = [f"window {_str(doc.window, '?')} {clock(t_end)}"]
    alarms = doc.alarms or {}
    params = doc.parameters or {}
    ruled, worst = _ruled_parts(alarms, params)
    if ruled:
        parts.append("; ".join(ruled))
    elif params:  # no alarm rule: the estimated deviations
        parts.append(", ".join(f"{name} {_fmt(ph.deviation_pct, '+.2f')} %"
                               for name, ph in params.items()
                               if ph.status in ("estimated", "fused")))
    wrong, failed, changed = _wrong_parts(doc, terms_changed, grew)
    if wrong:
        parts.append("| " + ", ".join(wrong))
    if not alarms and not params and len(parts) == 1:  # not a health message: its scalars
        parts.append(", ".join(f"{k}={v}" for k, v in json.loads(health_json).items()
                               if isinstance(v, bool | str | int | float) or v is None))
    if worst == 2:
        level = rr.TextLogLevel.ERROR
    elif worst == 1 or failed or changed or grew:
        level = rr.TextLogLevel.WARN
    else:
        level = rr.TextLogLevel.INFO
    return " ".join(parts), level


def _ruled_parts(alarms: Mapping[str, AlarmView],
                 params: Mapping[str, ParameterView]) -> tuple[list[str], int]:
    """The log row's part for each parameter with an alarm rule (tied and fixed ones left
    out): ``Ra -5.14 % (6.16593 ohm) WARNING, RUL ALARM``; and the machine's state as the
    row's level (0 normal, 1 warning, 2 alarm, :data:`_RANK`): 2 only for a deviation alarm
    (the one level that says inspect now, NE 107 FAILURE); a deviation warning or any RUL
    level raised is 1 (the OPC UA output's OFF_SPEC and MAINTENANCE_REQUIRED)."""
    worst = 0
    ruled = []
    for name, a in alarms.items():
        words = []
        ph = params.get(name)
        if ph is not None and ph.status in ("tied", "fixed"):
            continue
        if ph is not None and ph.status not in (None, "estimated"):
            words.append(str(ph.status))
        level = str(a.level)
        if _RANK.get(level, 0) > 0:
            worst = max(worst, _RANK[level])
            words.append(level.upper())
        rul_level = str(a.rul.level if a.rul is not None else None)
        if _RANK.get(rul_level, 0) > 0:
            # a RUL level asks to plan the maintenance (NE 107 MAINTENANCE_REQUIRED): WARN,
            # whatever its level; only a deviation alarm (stop now) is ERROR
            worst = max(worst, 1)
            words.append(f"RUL {rul_level.upper()}")
        elif ph is not None and (rul := _rul_short(ph)):
            words.append(rul)
        dev = a.deviation_pct if ph is None else ph.deviation_pct
        head = f"{name} {_fmt(dev, '+.2f')} %"
        if ph is not None and ph.status != "held":  # a held value is the last trusted one
            head += f" ({_fmt(ph.value, '.5g')} {_str(ph.unit)})"
        ruled.append(" ".join([head, ", ".join(words)]).strip())
    return ruled, worst


def _wrong_parts(doc: HealthView, terms_changed: bool,
                 grew: Mapping[str, int]) -> tuple[list[str], bool, bool]:
    """What went wrong in the window, for the log row: a failed model check with its
    reasons, DT'' changed (the terms added and dropped), the counters of lost data that grew;
    and whether the check failed and whether the structure changed."""
    wrong = []
    check = doc.model_check
    failed = check is not None and check.passed is False
    if check is not None and failed:  # a check that passed is the rule: in the model panel
        wrong.append("model check FAILED: " + "; ".join(map(str, check.reasons or [])))
    disc = doc.discovery
    changed = terms_changed or (disc is not None and bool(disc.changed))
    if changed and disc is not None:
        kept, dropped = disc.kept or [], disc.dropped or []
        wrong.append("DT'' changed" + "".join(f"; added {e}" for e in kept)
                     + "".join(f"; dropped {e}" for e in dropped))
    elif changed:
        wrong.append("DT'' changed")
    if grew:
        wrong.append("lost: " + ", ".join(f"{k} +{v}" for k, v in grew.items()))
    return wrong, failed, changed
