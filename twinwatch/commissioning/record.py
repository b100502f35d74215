"""The commissioning's Rerun file (:func:`record_fit`: what MATLAB users know as ``compare``
and ``resid``, the residual tests :func:`residual_tests`) and its layout."""

from __future__ import annotations

import math
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from twinwatch._lazy import lazy_module
from twinwatch.commissioning.identify import Comparison, Identification
from twinwatch.commissioning.report import (
    markdown_analysis,
    markdown_parameters,
    markdown_reasons,
    report,
)
from twinwatch.twin.estimation.statistics import autocorrelation

if TYPE_CHECKING:
    import rerun as rr
    import rerun.blueprint as rrb
else:
    rr = lazy_module("rerun")
    rrb = lazy_module("rerun.blueprint")

#: Lags of the residual plots (MATLAB ``resid`` shows 25; 50 shows a periodic structure of
#: up to 50 samples, the MotoShield's sampling phase repeats after 32).
RESID_LAGS = 50
#: The 99 % confidence band of a white residual's correlations: +-Z99/sqrt(N).
Z99 = 2.58

_MEASURED = [150, 150, 150]
_TWIN = [230, 120, 20]
_TRAIN = [60, 130, 230]
_VALID = [230, 120, 20]
_BAND = [235, 70, 70, 120]


def cross_correlation(e: np.ndarray, u: np.ndarray, lags: int) -> np.ndarray:
    """Normalised cross-covariance of a residual e(t) and an input u(t - tau) for tau =
    -lags..lags (means removed; MATLAB ``resid``), shape (2 lags + 1,); zeros when either is
    constant."""
    e = np.asarray(e, dtype=float) - float(np.mean(e))
    u = np.asarray(u, dtype=float) - float(np.mean(u))
    n = e.size
    den = float(np.sqrt((e @ e) * (u @ u)))
    out = np.zeros(2 * lags + 1)
    if den == 0:
        return out
    for k, tau in enumerate(range(-lags, lags + 1)):
        if abs(tau) >= n:
            continue
        out[k] = float(e[tau:] @ u[:n - tau]) / den if tau >= 0 else \
            float(e[:n + tau] @ u[-tau:]) / den
    return out


@dataclass
class ResidualTests:
    """MATLAB ``resid``'s figures of one output (what :func:`record_fit` draws).

    Attributes:
        lags: 0..L (L+1,) in samples; sample_period: [s].
        band: the 99 % band of a white residual's correlations, 2.58/sqrt(N) (N the
            validation residual's samples).
        autocorrelation: range (training, validation) -> the residual's autocorrelation at
            ``lags``.
        cross_correlation: input -> the validation residual e(t) against u(t - tau) at
            ``lags`` (the lags the model check tests).
    """

    lags: np.ndarray
    sample_period: float
    band: float
    autocorrelation: dict[str, np.ndarray]
    cross_correlation: dict[str, np.ndarray]


def residual_tests(result: Identification, output: str) -> ResidualTests:
    """The residual's autocorrelation on both ranges and its cross-correlation with each
    exogenous input on the validation range, at lags 0..min(50, N/4)."""
    tr, va = result.train, result.validation
    j = list(tr.fit_pct).index(output)
    lags = min(RESID_LAGS, max(1, va.samples // 4))
    acf = {what: autocorrelation(s.measured[1:, j] - s.simulated[1:, j], lags)
           for what, s in (("training", tr), ("validation", va))}
    e = va.measured[1:, j] - va.simulated[1:, j]
    xcf = {inp: cross_correlation(e, u[1:], lags)[lags:] for inp, u in va.inputs.items()}
    return ResidualTests(lags=np.arange(lags + 1, dtype=float),
                         sample_period=float(np.median(np.diff(tr.t))) if tr.t.size > 1
                         else 1.0,
                         band=Z99 / math.sqrt(max(va.samples - 1, 1)),
                         autocorrelation=acf, cross_correlation=xcf)


def fit_title(result: Identification, output: str) -> str:
    """``ia [A]: measured and twin; fit 51.0 % training (0-48 s), 50.7 % validation (48-96
    s)``, and ``; model check FAILED`` when a range fails it."""
    tr, va = result.train, result.validation
    title = (f"{output} [{result.output_units.get(output, '')}]: measured and twin; fit "
             f"{tr.fit_pct[output]:.1f} % training ({tr.start:.0f}-{tr.end:.0f} s), "
             f"{va.fit_pct[output]:.1f} % validation ({va.start:.0f}-{va.end:.0f} s)")
    if not va.check.passed or not tr.check.passed:
        title += "; model check FAILED"
    return title


def _esc(name: str) -> str:
    return str(rr.escape_entity_path_part(name))


def identify_blueprint(machine: str, result: Identification,
                       comparison: Comparison | None = None) -> rrb.Blueprint:
    """The layout of :func:`record_fit`'s file: per output, measured and twin over both
    ranges (the x axis the whole recording whatever the time cursor), below them the
    residual's correlation plots; on the right the parameter and fit tables, and in tabs the
    other reports and the residuals."""
    tr, va = result.train, result.validation
    t0, t1 = float(min(tr.t[0], va.t[0])), float(max(tr.t[-1], va.t[-1]))
    fit_views = []
    resid_rows = []
    for out in tr.fit_pct:
        fit_views.append(rrb.TimeSeriesView(
            origin=f"/identify/fit/{_esc(out)}", name=fit_title(result, out),
            plot_legend=rrb.PlotLegend("LeftTop"), **_span(t0, t1)))
        tests = residual_tests(result, out)
        row = [rrb.BarChartView(
            origin=f"/acf/{_esc(out)}", name=f"{out} residual: autocorrelation, lag "
            f"[{tests.sample_period:g} s]", plot_legend=rrb.PlotLegend("RightTop"))]
        for inp in tests.cross_correlation:
            row.append(rrb.BarChartView(
                origin=f"/xcorr/{_esc(out)}_{_esc(inp)}", name=f"{out} residual x {inp}: "
                f"cross-correlation (validation), lag [{tests.sample_period:g} s]",
                plot_legend=rrb.PlotLegend(visible=False)))
        resid_rows.append(rrb.Horizontal(*row))
    title = "what the data determine" + (", structures" if comparison else "")
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(*fit_views, *resid_rows,
                         row_shares=[3] * len(fit_views) + [2] * len(resid_rows)),
            rrb.Vertical(
                rrb.TextDocumentView(origin="/identify/report/parameters",
                                     name=f"{machine}: parameters and fit"),
                rrb.Tabs(rrb.TextDocumentView(origin="/identify/report/analysis", name=title),
                         rrb.TextDocumentView(origin="/identify/report/reasons",
                                              name="why not pasted"),
                         rrb.TextDocumentView(origin="/identify/report/text",
                                              name="report (text)"),
                         rrb.TimeSeriesView(origin="/identify/residual", name="residuals"),
                         active_tab=0),
                row_shares=[11, 9]),
            column_shares=[3, 2]),
        rrb.TimePanel(state="collapsed"),
        collapse_panels=True)


def record_fit(path: Path, machine: str, result: Identification,
               comparison: Comparison | None = None) -> None:
    """Write the commissioning's view to a Rerun file (timeline ``time``, seconds), laid out
    by :func:`identify_blueprint`:

    * ``identify/fit/<output>/{measured,twin}``: both ranges, one plot per output, the fit %
      of each range in its title (MATLAB ``compare``);
    * ``acf/<output>/{training,validation}``: the residual's autocorrelation at lags 0..L
      (bar charts over the lag in samples), its 99 % band ``acf/<output>/band_pm<b>`` shaded;
      ``xcorr/<output>_<input>/validation``: its cross-correlation with the input, and its
      band (MATLAB ``resid``; :class:`ResidualTests`);
    * ``identify/residual/<output>/<range>``: the residuals;
    * ``identify/report/{parameters,analysis,reasons}``: the parameter and fit tables, the
      identifiability analysis and the structures compared, why each parameter not pasted
      is not (Markdown tables); ``identify/report/text``: the console report.
    """
    rec = rr.RecordingStream("twinwatch-identify", recording_id=uuid.uuid4())
    rec.save(str(path))
    rec.send_recording_name(f"{machine} identification")
    tr, va = result.train, result.validation
    for j, out in enumerate(tr.fit_pct):
        esc = _esc(out)
        unit = result.output_units.get(out, "")
        base = f"identify/fit/{esc}"
        t = np.concatenate([tr.t, va.t])
        for kind, series, color, width in (
                ("measured", np.concatenate([tr.measured[:, j], va.measured[:, j]]),
                 _MEASURED, 1.0),
                ("twin", np.concatenate([tr.simulated[:, j], va.simulated[:, j]]), _TWIN,
                 1.5)):
            rec.log(f"{base}/{kind}", rr.SeriesLines(names=f"{out} {kind} [{unit}]",
                                                     colors=color, widths=width), static=True)
            rec.send_columns(f"{base}/{kind}", indexes=[rr.TimeColumn("time", duration=t)],
                             columns=rr.Scalars.columns(scalars=series))
        for what, score in (("training", tr), ("validation", va)):
            e = score.measured[1:, j] - score.simulated[1:, j]
            rec.log(f"identify/residual/{esc}/{what}",
                    rr.SeriesLines(names=f"{out} residual, {what} [{unit}]"), static=True)
            rec.send_columns(f"identify/residual/{esc}/{what}",
                             indexes=[rr.TimeColumn("time", duration=score.t[1:])],
                             columns=rr.Scalars.columns(scalars=e))
        tests = residual_tests(result, out)
        k = tests.lags
        _band(rec, f"acf/{esc}", k, tests.band)
        for (what, acf), color, shift in zip(tests.autocorrelation.items(), (_TRAIN, _VALID),
                                             (-0.2, 0.2), strict=True):
            rec.log(f"acf/{esc}/{what}", rr.BarChart(acf, abscissa=k + shift,
                                                     widths=np.full(k.size, 0.4), color=color),
                    static=True)
        for inp, xcf in tests.cross_correlation.items():
            xbase = f"xcorr/{esc}_{_esc(inp)}"
            _band(rec, xbase, k, tests.band)
            rec.log(f"{xbase}/validation", rr.BarChart(xcf, abscissa=k,
                                                       widths=np.full(k.size, 0.6),
                                                       color=_VALID), static=True)
    for name, text in (("parameters", markdown_parameters(result)),
                       ("analysis", markdown_analysis(result, comparison)),
                       ("reasons", markdown_reasons(result))):
        rec.log(f"identify/report/{name}",
                rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True)
    rec.log("identify/report/text", rr.TextDocument(report(result, comparison)), static=True)
    rec.send_blueprint(identify_blueprint(machine, result, comparison))
    rec.flush(timeout_sec=10.0)
    rec.disconnect()


def _band(rec: Any, base: str, lags: np.ndarray, band: float) -> None:
    """The +-band region of a correlation plot as translucent bars, one up and one down at
    every lag: ``<base>/band_pm0.053``, its half-width in the name (legends show entity
    paths)."""
    x = np.repeat(lags, 2)
    values = np.tile([band, -band], lags.size)
    rec.log(f"{base}/band_pm{band:.3f}", rr.BarChart(values, abscissa=x,
                                                     widths=np.full(x.size, 1.0), color=_BAND),
            static=True)


def _span(start: float, end: float) -> dict[str, Any]:
    """A time-series view's arguments that show [start, end] seconds of the ``time``
    timeline whatever the time cursor: the data queried over that range, the x axis zoomed to
    it and not linked to the other views'."""
    lo = rrb.TimeRangeBoundary.absolute(seconds=start)
    hi = rrb.TimeRangeBoundary.absolute(seconds=end)
    return {"time_ranges": [rrb.VisibleTimeRange("time", start=lo, end=hi)],
            "axis_x": rrb.TimeAxis(link=rrb.components.LinkAxis.Independent,
                                   view_range=rrb.TimeRange(start=lo, end=hi))}


__all__ = ["RESID_LAGS", "ResidualTests", "Z99", "cross_correlation", "fit_title",
           "identify_blueprint", "record_fit", "residual_tests"]
