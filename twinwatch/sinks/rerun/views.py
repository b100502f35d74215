"""What a twinwatch recording shows: its entities, their styles, and the default blueprint.

:class:`RecordingViews` turns one window (its samples, estimates, health message and alarm
changes) into what :class:`~twinwatch.sinks.rerun.RerunRecorder` logs, and describes the layout
an operator opens. The entity paths (``M`` the machine name, ``plant_time`` the timeline [s])
are tabulated in docs/operating.md ("What an operator sees: the recording").

The projection is a 2-D view beside the panel, not in the time-series view: Rerun (0.41) draws
every row ever logged at a time of a time-series view's range, and points at future plant times
move the following time cursor past the last window. A 2-D view shows what is latest at the
cursor.
"""

from __future__ import annotations

import collections
import json
import math
from collections import deque
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from twinwatch.sinks.base import AlarmBands
from twinwatch.sinks.rerun.projection import BOX, HISTORY, draw_projection, rul_text, trend_pct
from twinwatch.sinks.rerun.style import (
    ALARM,
    BAND,
    BAND_CLIP,
    DEVIATION,
    ELAPSED,
    EVENT_STYLE,
    HEADROOM,
    HIDDEN,
    MEASURED,
    NOMINAL,
    PPM,
    PROBLEM_COUNTER,
    QUALITY_COLORS,
    RANK,
    RESIDUAL,
    SCALE,
    SCALE_HEADROOM,
    SCALE_PCT,
    STATUS_STYLE,
    TIMELINE,
    TREND,
    TREND_BAND,
    TWIN,
    VARIANTS,
    WALL_CLOCK_AFTER,
    WARNING,
    Op,
    as_number,
    as_text,
    axis_frame,
    band_pct,
    clock,
    entity,
    fmt,
    pct_text,
    residual_rmse,
    rr,
    rrb,
    sparse_frame,
    tick_room,
)
from twinwatch.sinks.rerun.texts import event_row, log_row, model_document, parameter_table

if TYPE_CHECKING:
    from twinwatch.twin.health import AlarmView, HealthView, ParameterView


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
        """view -> the axis frame last logged (:meth:`static_ops` forgets them)."""
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
        (left), the outputs and residuals over the last ``recent_s`` seconds (right), the
        model, the parameters' table and the log (bottom), a key on top."""
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
            """A parameter's panel: its plot with its summary under it (``beside``: beside
            it, in a short row), and for a parameter with an alarm rule its projection."""
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
                    x_range=[0.0, BOX[0]], y_range=[0.0, BOX[1]])),
                column_shares=[2.0, 1.0], name=p)

        ruled = [p for p in self.estimated if p in self.alarm_bands]
        others = [p for p in self.estimated if p not in self.alarm_bands]
        health: list[rrb.Container | rrb.View] = [panel(p) for p in ruled]
        shares = [2.0] * len(ruled)
        if others:
            # beside the ruled panels the grid's rows are short: each summary beside its plot
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
            # the quality strip a sixth of the column at least (its ticks readable at 1600x1000)
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
        """What every file and the live stream need once: the key and every series' style."""
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
                          [HIDDEN, HIDDEN], [1.0, 1.0]),
                    lines(("outputs", o, "measured"), f"{o} measured{u}", MEASURED, 3.5),
                    lines(("outputs", o, "twin"), f"{o} twin{u}", TWIN, 1.5),
                    lines(("residual", o), f"{o} measured - twin{u}", RESIDUAL, 1.0),
                    lines(("residual", o, "frame"), [f"{o} residual axis frame low",
                                                     f"{o} residual axis frame high"],
                          [HIDDEN, HIDDEN], [1.0, 1.0])]
        n = len(self.outputs)
        for variant, label, _ in VARIANTS:
            ops.append(lines(("residual_rmse", variant),
                             [f"{o} RMSE {label}{self._unit(o)}" for o in self.outputs],
                             list(QUALITY_COLORS[:n]), [1.5] * n))
        n = len(self.parameters)
        ops.append(lines(("parameters",), [f"{p} [{u}]" for p, u in self.parameters.items()],
                         [QUALITY_COLORS[i % len(QUALITY_COLORS)] for i in range(n)],
                         [1.0] * n))
        ops += self.health_styles()
        ops.append(lines(("quality", "nrmse"), "nRMSE [ppm] (the twin published)", DEVIATION,
                         1.0))
        for variant, label, color in VARIANTS:
            ops.append(lines(("quality", f"nrmse_{variant}"), f"nRMSE {label} [ppm]", color, 2.0))
        ops.append(Op(entity(m, "quality", "model_check_failed"), rr.SeriesPoints(
            names="model check failed [ppm]", colors=ALARM, markers="cross", marker_sizes=4.0),
            static=True))
        ops.append(lines(("quality", "elapsed_ms"), "estimation time [ms]", ELAPSED, 1.5))
        for path in (("quality", "frame"), ("quality", "problems", "frame"),
                     ("quality", "elapsed_ms", "frame")):
            ops.append(lines(path, ["axis frame low", "axis frame high"], [HIDDEN, HIDDEN],
                             [1.0, 1.0]))
        if self._problem_counters:
            ops.append(self._problem_style())
        return ops

    def _limits(self, p: str) -> list[tuple[str, float, tuple[int, ...]]]:
        """The reference lines of ``p``'s view [%]: its alarm thresholds, or a dim +-5 % scale
        when it has no rule (name, value, colour)."""
        bands = self.alarm_bands.get(p)
        if bands is None:
            return [(f"scale +{SCALE_PCT:g} % (no alarm rule)", SCALE_PCT, SCALE),
                    (f"scale -{SCALE_PCT:g} % (no alarm rule)", -SCALE_PCT, SCALE)]
        return [(f"{name} {value:+g} %", value, color) for name, value, color in (
            ("warning", bands.warning_high, WARNING), ("warning", bands.warning_low, WARNING),
            ("alarm", bands.alarm_high, ALARM), ("alarm", bands.alarm_low, ALARM))
            if value is not None]

    def _band_clip(self, p: str) -> float:
        """How far from nominal ``p``'s 2-sigma band is drawn at most [%]: ``BAND_CLIP`` times
        its outer threshold, or within its scale's headroom when it has no rule."""
        outer = max(abs(value) for _, value, _ in self._limits(p))
        return (BAND_CLIP if p in self.alarm_bands else SCALE_HEADROOM) * outer

    def _series(self, p: str) -> list[tuple[str, tuple[int, ...], float]]:
        """The series of ``health/<p>/deviation``, in drawing order: name, colour, width (the
        transparent headroom series keep the thresholds off the axis' edges)."""
        return [("2-sigma low", BAND, 1.0), ("2-sigma high", BAND, 1.0),
                ("nominal", NOMINAL, 1.0),
                *((name, color, 1.5) for name, _, color in self._limits(p)),
                ("headroom high", HIDDEN, 1.0), ("headroom low", HIDDEN, 1.0),
                (f"{p} deviation [%]", DEVIATION, 1.0)]

    def health_styles(self) -> list[Op]:
        """The styles of every health view's series."""
        m = self.machine
        ops: list[Op] = []
        for p in self.estimated:
            series = self._series(p)
            ops.append(Op(entity(m, "health", p, "deviation"), rr.SeriesLines(
                names=[s[0] for s in series], colors=[s[1] for s in series],
                widths=[s[2] for s in series]), static=True))
            for status, (color, marker, size) in STATUS_STYLE.items():
                ops.append(Op(entity(m, "health", p, status), rr.SeriesPoints(
                    names=f"{p} {status}", colors=color, markers=marker, marker_sizes=size),
                    static=True))
            for kind, (color, marker, size) in EVENT_STYLE.items():
                label = ("cleared" if kind == "cleared"
                         else f"{kind.replace('_', ' ').replace('rul', 'RUL')} raised")
                ops.append(Op(entity(m, "health", p, "events", kind), rr.SeriesPoints(
                    names=f"{p} {label}", colors=color, markers=marker, marker_sizes=size),
                    static=True))
            ops.append(Op(entity(m, "health", p, "frame"), rr.SeriesLines(
                names=["axis frame low", "axis frame high"], colors=[HIDDEN, HIDDEN],
                widths=[1.0, 1.0]), static=True))
            ops.append(Op(entity(m, "health", p, "trend"), rr.SeriesLines(
                names=[f"{p} trend 2-sigma low", f"{p} trend 2-sigma high", f"{p} trend"],
                colors=[TREND_BAND, TREND_BAND, TREND], widths=[1.0, 1.0, 2.0]),
                static=True))
        return ops

    def _problem_style(self) -> Op:
        names = self._problem_counters
        return Op(entity(self.machine, "quality", "problems"), rr.SeriesLines(
            names=names, colors=[QUALITY_COLORS[i % len(QUALITY_COLORS)]
                                 for i in range(len(names))],
            widths=[1.5] * len(names)), static=True)

    def _output_ops(self, times: np.ndarray, meas: Mapping[str, np.ndarray],
                    sim: Mapping[str, np.ndarray]) -> list[Op]:
        m = self.machine
        t_end = float(times[-1])
        ops: list[Op] = []
        index = [rr.TimeColumn(TIMELINE, timestamp=times) if float(times[0]) >= WALL_CLOCK_AFTER
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
        return ops

    def _parameter_ops(self, doc: HealthView, events: list[Mapping[str, Any]],
                       t_end: float) -> list[Op]:
        """Each estimated parameter's health view and projection, the window's alarm events,
        then each parameter's summary in words."""
        ops: list[Op] = []
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
                ops.append(Op(entity(self.machine, "health", p, "summary"), rr.TextDocument(
                    self._summary(p, ph, alarms.get(p)),
                    media_type=rr.MediaType.MARKDOWN), t_end))
        return ops

    def window_ops(self, times: np.ndarray, meas: Mapping[str, np.ndarray],
                    sim: Mapping[str, np.ndarray], estimates: Mapping[str, float],
                    doc: HealthView, health_json: str, terms_changed: bool,
                    events: list[Mapping[str, Any]]) -> list[Op]:
        """Everything one window logs, in order (called with the lock held). ``doc`` is
        ``health_json``'s typed view."""
        m = self.machine
        t_end = float(times[-1])
        ops = self._output_ops(times, meas, sim)
        for variant, rmse in residual_rmse(doc).items():
            per_output = [as_number(rmse.get(o)) for o in self.outputs]
            if any(math.isfinite(v) for v in per_output):
                ops.append(Op(entity(m, "residual_rmse", variant), rr.Scalars(per_output),
                              t_end))
        ops.append(Op(entity(m, "parameters"), rr.Scalars(
            [estimates.get(p, math.nan) for p in self.parameters]), t_end))
        ops += self._parameter_ops(doc, events, t_end)
        ops += self._quality_ops(doc, t_end)
        ops.append(Op(entity(m, "model"), rr.TextDocument(
            model_document(m, t_end, doc), media_type=rr.MediaType.MARKDOWN), t_end))
        table = parameter_table(doc)
        if table:
            ops.append(Op(entity(m, "parameter_table"), rr.TextDocument(
                table, media_type=rr.MediaType.MARKDOWN), t_end))
        pretty = json.dumps(json.loads(health_json), indent=2)
        ops.append(Op(entity(m, "health"), rr.TextDocument(
            f"## {m}: health at t = {t_end:.3f} s\n\n```json\n{pretty}\n```\n",
            media_type=rr.MediaType.MARKDOWN), t_end))
        text, level = log_row(t_end, doc, terms_changed, self._new_problems(doc), health_json)
        ops.append(Op(entity(m, "log"), rr.TextLog(text, level=level), t_end))
        return ops

    def _health_ops(self, p: str, ph: ParameterView, t: float) -> list[Op]:
        """The deviation of ``p`` with its band, nominal and thresholds, and its status marker
        (the series of :meth:`_series`)."""
        dev = as_number(ph.deviation_pct)
        if not math.isfinite(dev):
            return []
        limits = [value for _, value, _ in self._limits(p)]
        outer = max(abs(v) for v in limits)
        clip = self._band_clip(p)
        low, high = band_pct(ph)
        band = [float(np.clip(v, -clip, clip)) if math.isfinite(v) else math.nan
                for v in (low, high)]
        top, bottom = max(0.0, *limits), min(0.0, *limits)
        room = HEADROOM if p in self.alarm_bands else SCALE_HEADROOM
        headroom = [room * top if top > 0 else 0.2 * outer,
                    room * bottom if bottom < 0 else -0.2 * outer]
        values = [*band, 0.0, *limits, *headroom, dev]
        m = self.machine
        ops = [Op(entity(m, "health", p, "deviation"), rr.Scalars(values), t)]
        frame = self._run_frame(f"health/{p}", values)
        if frame is not None:
            ops.append(Op(entity(m, "health", p, "frame"), rr.Scalars(frame), t))
        status = ph.status
        if status in STATUS_STYLE:
            ops.append(Op(entity(m, "health", p, str(status)), rr.Scalars(dev), t))
        trend = trend_pct(ph)
        if trend is not None:
            ops.append(Op(entity(m, "health", p, "trend"), rr.Scalars(
                [float(np.clip(v, -clip, clip)) for v in trend]), t))
        return ops

    def _projection_ops(self, p: str, ph: ParameterView, t: float) -> list[Op]:
        """``p``'s projection view (2-D): the recent deviations, the trend to the alarm
        threshold at the median crossing and at both ends of the 95 % interval, the
        thresholds. Cleared while the message predicts no crossing."""
        m = self.machine
        path = entity(m, "health", p, "projection")
        dev = as_number(ph.deviation_pct)
        if math.isfinite(dev):
            history = self._history.setdefault(p, deque(maxlen=HISTORY))
            if history and history[-1][0] >= t:  # a file reopened, a restart: time went back
                history.clear()
            history.append((t, dev))
        drawing = draw_projection(p, ph, t, list(self._history.get(p, ())),
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
        """An alarm change: its message in the log, a marker on its parameter's view, its
        moment kept for the parameter's summary."""
        m = self.machine
        p = str(ev.get("parameter", ""))
        level, previous = ev.get("level"), ev.get("previous")
        rule = "rul" if ev.get("kind") == "rul" else "deviation"
        t = as_number(ev.get("t"))
        t = t if math.isfinite(t) else t_end
        raised = RANK.get(str(level), 0) > RANK.get(str(previous), 0)
        kind = str(level) if raised else "cleared"
        # ERROR only for a deviation alarm raised (stop now); a RUL alarm plans maintenance
        severity = (rr.TextLogLevel.ERROR if (raised and level == "alarm" and rule == "deviation")
                    else rr.TextLogLevel.WARN)
        ops = [Op(entity(m, "log"), rr.TextLog(event_row(ev, t, rule, raised, params),
                                               level=severity), t)]
        if p:  # a diagnosis names no parameter
            self._moments.setdefault(p, {})[(rule, str(level if raised else previous))] = (
                "raised" if raised else "cleared", t)
        if rule == "rul":
            ph = params.get(p)
            dev = as_number(ph.deviation_pct if ph is not None else None)
            kind = f"rul_{kind}" if raised else ""
        else:
            dev = as_number(ev.get("deviation_pct"))
        if p in self.estimated and kind in EVENT_STYLE and math.isfinite(dev):
            ops.append(Op(entity(m, "health", p, "events", kind), rr.Scalars(dev), t))
        return ops

    def _summary(self, p: str, ph: ParameterView, alarm: AlarmView | None) -> str:
        """What ``p``'s panel says in words (markdown, two to four short lines): deviation,
        status, trend, RUL, the alarms' moments, a 2-sigma band beyond the view."""
        lines = [_summary_head(p, ph)]
        rul = ph.rul
        if p in self.alarm_bands:
            text = rul_text(ph, at=True)
            if text:
                lines.append(f"**{text}**")
            elif rul is not None and rul.status in ("insufficient", "not_degrading"):
                lines.append("RUL: " + str(rul.status).replace("_", " "))
        said = self._moments_said(p, alarm)
        if said:
            lines.append(said)
        low, high = band_pct(ph)
        clip = self._band_clip(p)
        if any(math.isfinite(v) and abs(v) > clip for v in (low, high)):
            # words between the numbers: a narrow summary wraps at the spaces
            lines.append(f"2-sigma band from {pct_text(low)} to {pct_text(high)} %, "
                         f"drawn to +-{clip:g} %")
        return "  \n".join(lines) + "\n"

    def _moments_said(self, p: str, alarm: AlarmView | None) -> str:
        """When ``p``'s alarms were raised or cleared: ``deviation warning raised at 14:38``."""
        moments = dict(self._moments.get(p, {}))
        for rule, state in (("deviation", alarm), ("rul", alarm.rul if alarm else None)):
            level = as_text(state.level, "normal") if state is not None else "normal"
            since = as_number(state.since_t if state is not None else None)
            if RANK.get(level, 0) > 0 and (rule, level) not in moments and \
                    math.isfinite(since):
                moments[(rule, level)] = ("raised", since)  # raised before this recording
        said = []
        for rule, name in (("deviation", "deviation"), ("rul", "RUL")):
            seen = sorted(((t, what, level) for (r, level), (what, t) in moments.items()
                           if r == rule))
            if seen:
                said.append(f"{name} " + ", ".join(
                    f"{level} {what} at {clock(t)}" for t, what, level in seen))
        return "; ".join(said)

    def _quality_ops(self, doc: HealthView, t: float) -> list[Op]:
        m = self.machine
        ops = []
        residual = doc.residual
        fits = ((residual.dt_prime, residual.dt_second) if residual is not None
                else (None, None))
        for variant, fit in zip(("dt_prime", "dt_second"), fits, strict=True):
            value = as_number(fit.nrmse) if fit is not None else math.nan
            if math.isfinite(value):
                ops.append(Op(entity(m, "quality", f"nrmse_{variant}"),
                               rr.Scalars(value * PPM), t))
        nrmse = as_number(doc.nrmse)
        values = [as_number(f.nrmse if f is not None else None) for f in fits] + [nrmse]
        frame = self._run_frame("quality", [v * PPM for v in values])
        if frame is not None:
            ops.append(Op(entity(m, "quality", "frame"), rr.Scalars(frame), t))
        if math.isfinite(nrmse):
            ops.append(Op(entity(m, "quality", "nrmse"), rr.Scalars(nrmse * PPM), t))
            check = doc.model_check
            if check is not None and check.passed is False:
                ops.append(Op(entity(m, "quality", "model_check_failed"),
                              rr.Scalars(nrmse * PPM), t))
        return ops + self._elapsed_ops(doc, t) + self._problem_ops(doc, t)

    def _elapsed_ops(self, doc: HealthView, t: float) -> list[Op]:
        m = self.machine
        ops = []
        elapsed = as_number(doc.elapsed_s)
        if math.isfinite(elapsed):
            ops.append(Op(entity(m, "quality", "elapsed_ms"), rr.Scalars(elapsed * 1e3), t))
            view = "quality/elapsed_ms"
            high = max(self._ranges.get(view, (0.0, 0.0))[1], elapsed * 1e3)
            self._ranges[view] = (0.0, high)
            frame = sparse_frame(high)
            if frame != self._frames.get(view):
                self._frames[view] = frame
                ops.append(Op(entity(m, "quality", "elapsed_ms", "frame"), rr.Scalars(frame),
                              t))
        return ops

    def _problem_ops(self, doc: HealthView, t: float) -> list[Op]:
        """The counters of lost data (a counter seen for the first time restyles the view)."""
        m = self.machine
        ops = []
        counters = doc.counters
        if counters is not None:
            new = [k for k in counters if k not in self._problem_counters
                   and PROBLEM_COUNTER.search(k) and isinstance(counters[k], int | float)]
            if new:
                self._problem_counters += sorted(new)
                ops.append(self._problem_style())
            if self._problem_counters:
                counts = [as_number(counters.get(k)) for k in self._problem_counters]
                ops.append(Op(entity(m, "quality", "problems"), rr.Scalars(counts), t))
            frame = self._run_frame("problems", [0.0, 1.0, *(
                as_number(counters.get(k)) for k in self._problem_counters)])
            if frame is not None:
                ops.append(Op(entity(m, "quality", "problems", "frame"), rr.Scalars(frame), t))
        return ops

    def _output_frame(self, output: str, t_end: float, values: np.ndarray,
                      two_ticks: bool = True) -> list[float] | None:
        """The axis frame (:func:`axis_frame`; without ``two_ticks`` the window's range) of an
        output's window, its labels' room (:func:`tick_room`) at the scale of the windows its
        view shows: the viewer labels the view's range, not the window's."""
        finite = values[np.isfinite(values)]
        if not finite.size:
            return None
        frame = (axis_frame(finite, room=False) if two_ticks
                 else [float(finite.min()), float(finite.max())])
        if frame is None:
            return None
        recent = self._recent.setdefault(output, collections.deque())
        recent.append((t_end, frame[0], frame[1]))
        while recent[0][0] < t_end - self.recent_s or recent[0][0] > t_end:
            recent.popleft()  # out of the view, or from before the source's clock went back
        width = max(hi for _, _, hi in recent) - min(lo for _, lo, _ in recent)
        return tick_room(frame[0], frame[1], scale=width)

    def _run_frame(self, view: str, values: Sequence[float], room: bool = True
                   ) -> list[float] | None:
        """The axis frame (:func:`axis_frame`) of a view that shows the whole run: over every
        finite value it has shown so far; None when it is the one last logged."""
        finite = [v for v in values if math.isfinite(v)]
        if not finite:
            return None
        low, high = self._ranges.get(view, (min(finite), max(finite)))
        low, high = min(low, *finite), max(high, *finite)
        self._ranges[view] = (low, high)
        frame = axis_frame(np.array([low, high]), room)
        if frame is None or frame == self._frames.get(view):
            return None  # unchanged: one chunk less per view and window in the file
        self._frames[view] = frame
        return frame

    def _new_problems(self, doc: HealthView) -> dict[str, int]:
        counters = doc.counters
        if counters is None:
            return {}
        grew = {}
        for k, v in counters.items():
            if isinstance(v, int) and PROBLEM_COUNTER.search(k):
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


def _summary_head(p: str, ph: ParameterView) -> str:
    """A parameter panel's first line: ``**Ra -5.14 %** estimated +- 0.066 % (2 sigma); trend
    exponential -1.2 %/h``."""
    dev = as_number(ph.deviation_pct)
    status = as_text(ph.status)
    rel = as_number(ph.rel_std_pct)
    head = f"**{p} {fmt(dev, '+.2f')} %** {status}"
    if status in ("estimated", "fused") and math.isfinite(rel):
        head += f" +- {2 * rel:.2g} % (2 sigma)"  # as the summary and the diagnosis say
    trend = ph.trend
    if trend is None or trend.model is None:
        head += "; no trend yet" if trend is not None and trend.model_fields_set else ""
    elif trend.degrading is False:
        head += "; not degrading"
    else:
        rate = as_number(trend.rate_pct_per_h)
        head += f"; trend {trend.model} {fmt(rate, '+.3g')} %/h"
    return head
