"""``twinwatch identify``: read a whole recording through the configured driver, identify the
baseline on its training range (:mod:`~twinwatch.twin.estimation.identify`: the fit, what the
recording determines, the re-fit with the rest held), for the configured structure and every
candidate ``[identify.candidates]`` lists, pick the winner, score it on the validation range,
record it in a Rerun file and hand back the ``[machine.parameters]`` block.

Any driver works: a file (CSV, .mat), a CAN log, the simulated plants, or a live bus for
``duration`` seconds. Samples that lack a channel the twin needs or hold NaN/inf are counted
and left out; a range that the source interrupted (a time step above ``max_gap`` sample
periods) is refused with the time of the gap, since one free-run simulation cannot cross it.

The Rerun file (:func:`record_fit`) is what MATLAB users know as ``compare`` and ``resid``:
per output, measured and twin overlaid over both ranges with the fit % in the title; the
residual's autocorrelation with its 99 % band (+-2.58/sqrt(N)) and the residual-input
cross-correlation; the parameter table and the identifiability analysis as Markdown tables.
"""

from __future__ import annotations

import logging
import math
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from twinwatch._lazy import lazy_module
from twinwatch.drivers import EndOfStream, create_driver
from twinwatch.errors import CommissionError
from twinwatch.twin.estimation.identify import (
    AS_CONFIGURED,
    Comparison,
    Identification,
    StretchScore,
    compare_structures,
    identify,
    merge_options,
)
from twinwatch.twin.estimation.statistics import autocorrelation
from twinwatch.twin.model import TwinModel, WindowData
from twinwatch.twin.models import create_model

if TYPE_CHECKING:
    import rerun as rr
    import rerun.blueprint as rrb

    from twinwatch.config.schema import TwinwatchConfig
else:
    rr = lazy_module("rerun")
    rrb = lazy_module("rerun.blueprint")

logger = logging.getLogger(__name__)

#: Lags of the residual plots (MATLAB ``resid`` shows 25; 50 shows a periodic structure of
#: up to 50 samples, the MotoShield's sampling phase repeats after 32).
RESID_LAGS = 50
#: The 99 % confidence band of a white residual's correlations: +-Z99/sqrt(N).
Z99 = 2.58


@dataclass
class Recording:
    """A whole recording as arrays: times (N,), channel -> values (N,), and what was left out.

    Attributes:
        t: sample times [s].
        channels: twin channel -> values [SI].
        dropped: samples left out (a channel missing, NaN or inf).
        source: what was read, for the report.
    """

    t: np.ndarray
    channels: dict[str, np.ndarray]
    dropped: int
    source: str

    def stretch(self, frac: tuple[float, float], max_gap: float, what: str) -> WindowData:
        """The samples of a fraction range [start, end) of the recording as one window.

        Raises:
            CommissionError: fewer than 10 samples, or a gap inside (the time is named).
        """
        n = self.t.size
        a, b = int(round(frac[0] * n)), int(round(frac[1] * n))
        t = self.t[a:b]
        if t.size < 10:
            raise CommissionError(f"the {what} range {frac[0]:g}-{frac[1]:g} holds {t.size} "
                                  f"of the recording's {n} samples: too few")
        dt = np.diff(t)
        period = float(np.median(dt))
        bad = np.flatnonzero((dt > max_gap * period) | (dt <= 0))
        if bad.size:
            k = int(bad[0])
            raise CommissionError(
                f"the {what} range is interrupted at t = {t[k]:.3f} s (next sample "
                f"{t[k + 1]:.3f} s; sample period {period:g} s): choose [identify] ranges "
                "without a gap")
        return WindowData(t=t, channels={c: v[a:b] for c, v in self.channels.items()}, index=0)


@dataclass
class Commissioning:
    """What :func:`commission` found.

    Attributes:
        result: the winning structure's identification (the configured one when no
            candidates are listed).
        data: the recording read.
        comparison: every structure's identification and the ranking (None when
            ``[identify.candidates]`` is empty).
    """

    result: Identification
    data: Recording
    comparison: Comparison | None = None


def read_recording(cfg: TwinwatchConfig, base_dir: Path, duration: float | None = None
                   ) -> Recording:
    """Read every sample the configured driver delivers (to its end, or ``duration`` seconds
    of source time).

    Raises:
        CommissionError: the source ended before a single usable sample.
        twinwatch.drivers.DriverError: the driver could not be opened or failed.
    """
    model = create_model(cfg.machine.model, cfg.machine.options)
    need = model.required_channels()
    times: list[float] = []
    values: dict[str, list[float]] = {c: [] for c in need}
    dropped = 0
    t0: float | None = None
    driver = create_driver(cfg.driver, base_dir=base_dir)
    with driver:
        while True:
            try:
                sample = driver.read(timeout=1.0)
            except EndOfStream:
                break
            if sample is None:
                continue
            if t0 is None:
                t0 = sample.t
            if duration is not None and sample.t - t0 > duration:
                break
            row = [sample.values.get(c, math.nan) for c in need]
            if not all(math.isfinite(v) for v in row):
                dropped += 1
                continue
            times.append(sample.t)
            for c, v in zip(need, row, strict=True):
                values[c].append(v)
    if not times:
        raise CommissionError(f"the {cfg.driver.type} source delivered no sample with every "
                              f"channel the twin needs ({', '.join(need)})")
    if dropped:
        logger.warning("%d samples left out: a channel the twin needs was missing or not "
                       "finite", dropped)
    return Recording(t=np.asarray(times), channels={c: np.asarray(v) for c, v in values.items()},
                     dropped=dropped, source=f"the {cfg.driver.type} source of "
                     f"machine '{cfg.machine.name}'")


def _structures(cfg: TwinwatchConfig) -> list[tuple[str, dict[str, Any], TwinModel]]:
    """(name, options over [machine.options], model) of the configured structure and every
    candidate."""
    out: list[tuple[str, dict[str, Any], TwinModel]] = [
        (AS_CONFIGURED, {}, create_model(cfg.machine.model, cfg.machine.options))]
    for k, cand in enumerate(cfg.identify.candidates):
        try:
            model = create_model(cfg.machine.model,
                                 merge_options(cfg.machine.options, cand.options))
        except ValueError as exc:
            raise CommissionError(f"identify.candidates[{k}] ({cand.name}).options: {exc}"
                                  ) from exc
        out.append((cand.name, dict(cand.options), model))
    return out


def commission(cfg: TwinwatchConfig, base_dir: Path, *, duration: float | None = None,
               record: Path | None = None) -> Commissioning:
    """Identify the baseline of ``cfg``'s machine from its source (see the module docstring).

    Args:
        cfg: the validated configuration (``[identify]`` says the ranges, the weights, what to
            hold and the candidate structures).
        base_dir: directory relative paths of the configuration resolve against.
        duration: stop reading after this many seconds of source time (a live bus).
        record: write the fits, the residual tests and the tables to this Rerun file.

    Raises:
        CommissionError, twinwatch.drivers.DriverError: as :func:`read_recording`, or a range
            that cannot be identified from, or a candidate whose options the model refuses.
    """
    data = read_recording(cfg, base_dir, duration)
    gap = cfg.acquisition.max_gap
    train = data.stretch(cfg.identify.train, gap, "training")
    validation = data.stretch(cfg.identify.validate_, gap, "validation")
    results: list[Identification] = []
    first: dict[str, float] | None = None
    for name, options, model in _structures(cfg):
        table = cfg.identify.for_structure(model)
        params = {k: v for k, v in cfg.machine.parameters.items()
                  if k in model.parameter_names}
        try:
            result = identify(model, cfg.estimation, table, train, validation, params,
                              start=first, structure=name, options=options)
        except ValueError as exc:
            raise CommissionError(f"{name}: {exc}" if cfg.identify.candidates
                                  else str(exc)) from exc
        if first is None and result.full is not None:
            first = result.full.values  # a warm start for the candidates
        results.append(result)
    comparison = compare_structures(results) if len(results) > 1 else None
    best = comparison.best if comparison is not None else results[0]
    if record is not None:
        record_fit(record, cfg.machine.name, best, comparison)
    return Commissioning(best, data, comparison)


# -- the report ------------------------------------------------------------------------------
def _pct(x: float) -> str:
    if not math.isfinite(x):
        return "inf %"
    p = 100.0 * x
    return f"{p:.3g} %" if p < 1e3 else f"{p:.0f} %" if p < 1e5 else f"{p:.1e} %"


def _check_text(score: StretchScore) -> str:
    return "passed" if score.check.passed else "FAILED: " + "; ".join(score.check.reasons)


def _comparison_lines(comparison: Comparison) -> list[str]:
    outs = comparison.outputs or list(comparison.best.train.fit_pct)
    width = max(len("structure"), *(len(r.structure) for r in comparison.results))
    head = (f"  {'structure':<{width}} {'n_p':>4} {'nRMSE':>8} "
            + " ".join(f"{'val ' + o:>10}" for o in outs)
            + f" {'check':>7} {'AIC':>11} {'BIC':>11}")
    lines = ["structures compared (the fit with every parameter free; fit % on the "
             "validation range, AIC/BIC on the training residual):", head]
    for k, r in enumerate(comparison.results):
        f = r.full
        assert f is not None
        mark = "*" if k == comparison.winner else " "
        lines.append(f"{mark} {r.structure:<{width}} {f.criteria.parameters:>4} {f.nrmse:>8.5f} "
                     + " ".join(f"{f.validation.fit_pct[o]:>10.1f}" for o in outs)
                     + f" {'passed' if f.validation.check.passed else 'FAILED':>7}"
                     f" {comparison.criteria[k].aic:>11.1f} {comparison.criteria[k].bic:>11.1f}")
    best = comparison.best
    lines.append(f"winner: {best.structure} ({comparison.rule})")
    if best.options:
        lines.append("  its options: " + ", ".join(f"{k} = {v!r}"
                                                   for k, v in best.options.items()))
    return lines


def report(result: Identification, comparison: Comparison | None = None) -> str:
    """The identification as text: the structures compared, the identifiability analysis,
    every parameter (determined with its interval, or held with the reason), fit % per output
    on both ranges for both fits, the model check of each range."""
    lines: list[str] = []
    if comparison is not None:
        lines += _comparison_lines(comparison)
        lines.append("")
    a = result.identifiability
    full = result.full
    n = len(result.estimated)
    if a is not None:
        lines.append(f"identifiability at the fit with all {n} parameters free "
                     f"(information matrix of the ln-parameters, {n} x {n}):")
        lines.append(f"  rank {a.rank} of {n}, condition number {a.condition:.3g}; "
                     f"{a.determined_rank} of {n} combinations determined within "
                     f"{_pct(result.max_rel_std)} (1 sigma)")
        if a.undetermined:
            lines.append("  not determined (relative changes; 1 sigma):")
            for comb in a.undetermined:
                lines.append(f"    +-{_pct(comb.std):>9}  {comb.label()}")
        if a.strong_pairs:
            lines.append("  strongly correlated: " + ", ".join(
                f"{x}/{y} {rho:+.3f}" for x, y, rho in a.strong_pairs))
        for name, side in a.at_bound.items():
            lo, hi = result.bounds[name]
            lines.append(f"  AT A BOUND: {name} = {full.values[name] if full else 0:.4g} at "
                         f"its {side} bound [{lo:.4g}, {hi:.4g}]")
        lines.append("")
    if not result.validation.check.passed:
        lines.append("NOTHING IS PASTED: the validation range fails the model check (below)")
    lines.append(f"parameters ({len(result.determined)} of {n} determined within "
                 f"{_pct(result.max_rel_std)} (1 sigma); {len(result.held)} held at a stated "
                 f"value or a bound and the rest re-fitted; {len(result.undetermined)} not "
                 "determined):")
    lines.append(f"  {'parameter':<10} {'value':<13} {'1 sigma':>9}  {'all free':>9}  status")
    for name in result.estimated:
        free_sd = _pct(full.rel_std[name]) if full else ""
        if name in result.determined:
            lines.append(f"  {name:<10} {result.values[name]:<13.6g} "
                         f"{'+-' + _pct(result.rel_std[name]):>9}  {free_sd:>9}  determined"
                         + ("" if name in result.pasted else
                            " (not pasted: the model check failed)"))
        elif name in result.held:
            h = result.held[name]
            lines.append(f"  {name:<10} {h.value:<13.6g} {'held':>9}  {free_sd:>9}  held "
                         f"({h.source}: {h.stated}); not determined: {h.why}")
        else:
            lines.append(f"  {name:<10} {result.values[name]:<13.6g} "
                         f"{'+-' + _pct(result.rel_std[name]):>9}  {free_sd:>9}  NOT "
                         f"DETERMINED: {result.undetermined.get(name, '')}")
    if result.undetermined:
        lines.append("  (to determine more, state a value of one parameter of each combination in "
                     "[identify.fixed]: a nameplate, a datasheet, another experiment)")
    for dep, src in result.tied.items():
        lines.append(f"  {dep:<10} {result.values[dep]:<13.6g} {'':>9}  {'':>9}  tied to "
                     f"{src}")
    lines.append("fit % (100 (1 - |y - y_hat| / |y - mean(y)|)):")
    label = "with the held values" if result.held else "identified"
    for name in result.train.fit_pct:
        line = (f"  {name:<10} training {result.train.fit_pct[name]:6.1f}   validation "
                f"{result.validation.fit_pct[name]:6.1f}   ({label})")
        if full is not None and result.held:
            line += (f";  all free: {full.train.fit_pct[name]:.1f} / "
                     f"{full.validation.fit_pct[name]:.1f}")
        lines.append(line)
    for what, score in (("training", result.train), ("validation", result.validation)):
        lines.append(f"model check ({what}): {_check_text(score)}")
    if len(result.starts) > 1:
        lines.append(f"{len(result.starts)} starts reached a training nRMSE of "
                     + ", ".join(f"{c:.5g}" for c in result.starts)
                     + f"; kept {min(result.starts):.5g}")
    lines.append(f"{result.evaluations} twin simulations in {result.elapsed_s:.1f} s"
                 + (f" ({result.structure})" if comparison is not None else ""))
    return "\n".join(lines)


def report_markdown(result: Identification, comparison: Comparison | None = None) -> str:
    """The report as Markdown tables (what the Rerun file shows): the parameters and fits,
    the identifiability analysis and the structures, why each parameter not pasted is not."""
    return "\n".join((markdown_parameters(result), markdown_analysis(result, comparison),
                      markdown_reasons(result)))


def markdown_parameters(result: Identification) -> str:
    """The parameter table (value, 1 sigma given the held ones and with all free, status),
    the fit % table and the model checks, as Markdown."""
    full = result.full
    outs = list(result.train.fit_pct)
    pasted = ("only those are pasted." if result.validation.check.passed else
              "**none is pasted: the validation range fails the model check.**")
    md = [f"**{len(result.determined)} of {len(result.estimated)} parameters determined** "
          f"within {_pct(result.max_rel_std)} (1 sigma, given the held ones): {pasted}", "",
          "| parameter | value | 1 sigma | all free | status |", "|---|---|---|---|---|"]
    for name in result.estimated:
        unit = result.units.get(name, "")
        free_sd = _pct(full.rel_std[name]) if full else ""
        if name in result.determined:
            md.append(f"| **{name}** [{unit}] | **{result.values[name]:.5g}** | "
                      f"**{_pct(result.rel_std[name])}** | {free_sd} | **determined** |")
        elif name in result.held:
            h = result.held[name]
            where = (f"at its {result.at_bound[name]} bound" if name in result.at_bound
                     else f"held ({h.source})")
            sd = f"({_pct(h.rel_std)})" if h.rel_std > 0 else "-"
            md.append(f"| {name} [{unit}] | {h.value:.5g} | {sd} | {free_sd} | {where} |")
        else:
            md.append(f"| {name} [{unit}] | {result.values[name]:.5g} | "
                      f"{_pct(result.rel_std[name])} | {free_sd} | NOT determined |")
    md.append("")
    md.append("| fit % | " + " | ".join(f"{o} train | {o} valid." for o in outs) + " |")
    md.append("|---|" + "---|---|" * len(outs))
    rows = [("pasted" if result.held else "identified", result.train, result.validation)]
    if full is not None and result.held:
        rows.append(("all free", full.train, full.validation))
    for label, tr, va in rows:
        md.append(f"| {label} | " + " | ".join(
            f"{tr.fit_pct[o]:.1f} | {va.fit_pct[o]:.1f}" for o in outs) + " |")
    md.append("")
    for what, score in (("training", result.train), ("validation", result.validation)):
        md.append(f"- model check ({what}): " + ("passed" if score.check.passed else
                  "**FAILED**: " + "; ".join(score.check.reasons)))
    return "\n".join(md) + "\n"


def markdown_analysis(result: Identification, comparison: Comparison | None = None,
                      rows: int = 5) -> str:
    """The identifiability analysis (rank, condition, the weakest ``rows`` combinations,
    strong correlations, parameters at a bound) and the structures compared, as Markdown."""
    md: list[str] = []
    outs = list(result.train.fit_pct)
    a = result.identifiability
    if a is not None:
        n = len(a.names)
        md.append(f"**Information matrix** ({n} x {n}, all free): rank {a.rank}, condition "
                  f"{a.condition:.2g}; {a.determined_rank} of {n} combinations within "
                  f"{_pct(result.max_rel_std)}.")
        md.append("")
        if a.undetermined:
            md.append("| 1 sigma | undetermined combination (relative changes) |")
            md.append("|---|---|")
            for comb in a.undetermined[:rows]:
                md.append(f"| {_pct(comb.std)} | {comb.label(cut=0.3)} |")
            if len(a.undetermined) > rows:
                md.append(f"| ... | {len(a.undetermined) - rows} more (text report) |")
        extra = []
        if a.strong_pairs:
            extra.append("strongly correlated: " + ", ".join(
                f"{x}/{y} {rho:+.2f}" for x, y, rho in a.strong_pairs[:5]))
        if a.at_bound:
            extra.append("**at a bound**: " + ", ".join(
                f"{k} ({v})" for k, v in a.at_bound.items()))
        if extra:
            md.append("")
            md.append("; ".join(extra) + ".")
    if comparison is not None:
        md.append("")
        outs = comparison.outputs or outs
        md.append("| structure (all free) | " + " | ".join(f"{o} valid." for o in outs)
                  + " | check | BIC |")
        md.append("|---|" + "---|" * len(outs) + "---|---|")
        for k, r in enumerate(comparison.results):
            f = r.full
            assert f is not None
            name = f"**{r.structure} (winner)**" if k == comparison.winner else r.structure
            md.append(f"| {name} | " + " | ".join(f"{f.validation.fit_pct[o]:.1f}"
                                                  for o in outs)
                      + f" | {'passed' if f.validation.check.passed else '**failed**'} | "
                      f"{comparison.criteria[k].bic:.0f} |")
    return "\n".join(md) + "\n"


def markdown_reasons(result: Identification) -> str:
    """Why each parameter that is not pasted is not, as a Markdown list."""
    md = []
    for name, h in result.held.items():
        stated = f"{h.source}: {h.stated}" if h.stated else h.source
        md.append(f"- **{name}** held at {h.value:.4g} ({stated}); not determined: {h.why}")
    for name, why in result.undetermined.items():
        md.append(f"- **{name}** not determined (+-{_pct(result.rel_std[name])}): {why}")
    return "\n".join(md or ["Every estimated parameter is determined."]) + "\n"


def summary(result: Identification) -> dict[str, Any]:
    """The figures as plain data (for tests and scripts)."""
    return {"values": result.values, "rel_std": result.rel_std,
            "determined": list(result.determined), "pasted": result.pasted,
            "held": {k: {"value": h.value, "source": h.source, "why": h.why}
                     for k, h in result.held.items()},
            "undetermined": dict(result.undetermined),
            "at_bound": dict(result.at_bound),
            "fit_train": result.train.fit_pct, "fit_validation": result.validation.fit_pct,
            "check_train": result.train.check.passed,
            "check_validation": result.validation.check.passed}


# -- the Rerun file --------------------------------------------------------------------------
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
    ranges (the fit % in the title, the x axis the whole recording whatever the time
    cursor); below them, per output, the residual's autocorrelation and its cross-correlation
    with each input, the 99 % band shaded; on the right the parameter and fit tables, and in
    tabs the identifiability analysis with the structures, why each parameter not pasted is
    not, the console report and the residuals."""
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
    * ``acf/<output>/{training,validation}``: the residual's autocorrelation at lags
      0..L (bar charts over the lag in samples), with ``acf/<output>/band_pm<b>``, the 99 %
      band +-2.58/sqrt(N) of a white residual, shaded; ``xcorr/<output>_<input>/validation``:
      the cross-correlation of the residual e(t) and the input u(t - tau), tau = 0..L (the
      lags the model check tests) and its band (MATLAB ``resid``; :func:`residual_tests`);
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
        _band(rec, f"acf/{esc}/band_{_band_name(tests.band)}", k, tests.band)
        for (what, acf), color, shift in zip(tests.autocorrelation.items(), (_TRAIN, _VALID),
                                             (-0.2, 0.2), strict=True):
            rec.log(f"acf/{esc}/{what}", rr.BarChart(acf, abscissa=k + shift,
                                                     widths=np.full(k.size, 0.4), color=color),
                    static=True)
        for inp, xcf in tests.cross_correlation.items():
            xbase = f"xcorr/{esc}_{_esc(inp)}"
            _band(rec, f"{xbase}/band_{_band_name(tests.band)}", k, tests.band)
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


def _band(rec: Any, entity: str, lags: np.ndarray, band: float) -> None:
    """The +-band region of a correlation plot as translucent bars, one up and one down at
    every lag."""
    x = np.repeat(lags, 2)
    values = np.tile([band, -band], lags.size)
    rec.log(entity, rr.BarChart(values, abscissa=x, widths=np.full(x.size, 1.0),
                                color=_BAND), static=True)


def _band_name(band: float) -> str:
    """``pm0.053``: the band's half-width in an entity name (legends show entity paths)."""
    return f"pm{band:.3f}"


def _span(start: float, end: float) -> dict[str, Any]:
    """A time-series view's arguments that show [start, end] seconds of the ``time``
    timeline whatever the time cursor: the data queried over that range, the x axis zoomed to
    it and not linked to the other views'."""
    lo = rrb.TimeRangeBoundary.absolute(seconds=start)
    hi = rrb.TimeRangeBoundary.absolute(seconds=end)
    return {"time_ranges": [rrb.VisibleTimeRange("time", start=lo, end=hi)],
            "axis_x": rrb.TimeAxis(link=rrb.components.LinkAxis.Independent,
                                   view_range=rrb.TimeRange(start=lo, end=hi))}


__all__ = ["CommissionError", "Commissioning", "Recording", "ResidualTests", "commission",
           "cross_correlation", "fit_title", "identify_blueprint", "markdown_analysis",
           "markdown_parameters", "markdown_reasons", "read_recording", "record_fit", "report",
           "report_markdown", "residual_tests", "summary"]
