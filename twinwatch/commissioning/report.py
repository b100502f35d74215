"""The commissioning's report: the identification (:mod:`~twinwatch.commissioning.identify`)
as the text ``twinwatch identify`` prints (:func:`report`) and as the Markdown tables of the
Rerun file (:func:`markdown_parameters`, :func:`markdown_analysis`, :func:`markdown_reasons`).
"""

from __future__ import annotations

from twinwatch.commissioning.identify import Comparison, Identification, StretchScore
from twinwatch.commissioning.identify import percent as _pct


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
    lines += _identifiability_lines(result)
    lines += _parameter_lines(result)
    lines += _fit_lines(result)
    if len(result.starts) > 1:
        lines.append(f"{len(result.starts)} starts reached a training nRMSE of "
                     + ", ".join(f"{c:.5g}" for c in result.starts)
                     + f"; kept {min(result.starts):.5g}")
    lines.append(f"{result.evaluations} twin simulations in {result.elapsed_s:.1f} s"
                 + (f" ({result.structure})" if comparison is not None else ""))
    return "\n".join(lines)


def _identifiability_lines(result: Identification) -> list[str]:
    """The analysis at the fit with every parameter free (rank, condition, the undetermined
    combinations, the strong correlations, the parameters at a bound) and a blank line; none
    without an analysis."""
    a = result.identifiability
    if a is None:
        return []
    full = result.full
    n = len(result.estimated)
    lines = [f"identifiability at the fit with all {n} parameters free "
             f"(information matrix of the ln-parameters, {n} x {n}):",
             f"  rank {a.rank} of {n}, condition number {a.condition:.3g}; "
             f"{a.determined_rank} of {n} combinations determined within "
             f"{_pct(result.max_rel_std)} (1 sigma)"]
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
    return lines


def _parameter_lines(result: Identification) -> list[str]:
    """The parameter table: each estimated parameter determined (value, 1 sigma), held (the
    stated value and why) or not determined, then the tied ones."""
    full = result.full
    n = len(result.estimated)
    lines: list[str] = []
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
    return lines


def _fit_lines(result: Identification) -> list[str]:
    """Fit % per output on both ranges (and with every parameter free when some are held),
    the model check of each range."""
    full = result.full
    lines = ["fit % (100 (1 - |y - y_hat| / |y - mean(y)|)):"]
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
    return lines


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


__all__ = ["markdown_analysis", "markdown_parameters", "markdown_reasons", "report"]
