"""Unknown-component discovery: the DT'' step (paper Section 3.3, Table 1, Eq. 3).

When re-estimating the physical parameters cannot explain a window (the DT' residual stays
above the exit criterion), a second optimisation fits interpretable meta-model terms attached to
the twin's equations: DT'' = DT(p, x) + sum_i U_i(z_i). The specialist's configuration says which
meta-models are candidates, what each takes as input (time or a measured channel) and where it
attaches (an :class:`~twinwatch.twin.model.AttachPoint` of the model: additive to a state
equation such as ``d(omega)/dt``, multiplicative on an equation such as the pressure ``p``).

How the search is made reliable (the paper's single PSO over every meta-model with on/off
weights is not: it misses terms and keeps spurious ones):

1. **One small search per candidate.** Each (attach point, input, kind) is fitted alone by PSO
   in normalised coordinates (2-4 dimensions), then polished by bounded least squares.
   Periodic candidates on time get the residual's periodogram peaks as seed particles: a forcing
   keeps its frequency through the twin's linear(ised) dynamics.
2. **Forward selection with an information criterion.** The candidate that lowers the Bayesian
   information criterion most is kept if it (a) lowers it by at least ``bic_threshold``, with
   the sample size corrected for the residuals' autocorrelation (a term that only half-explains
   a smooth drift leaves correlated residuals and earns little), (b) removes at least
   ``min_improvement`` of the residual, and (c) has a main coefficient at least
   ``min_significance`` standard errors from zero. Then the next candidate is sought with the
   kept ones in place, up to ``max_terms``. Optional offsets are dropped unless they too earn
   their place.
3. **Re-validation and refinement.** Every later window polishes the kept terms and refines
   them with its evidence (:meth:`~.terms.Term.refine`, ``[discovery.refinement]``). Each term
   is then checked to still earn its place (the same criterion, as a removal test); a term that
   fails ``drop_after`` windows in a row is switched off.

Beyond the paper's Table 1 the library has the non-smooth terms real drives need (rectifier,
dead zone, Coulomb friction, saturation); a search that keeps nothing says so, with the closest
candidate and the criteria it fails (:attr:`DiscoveryReport.verdict`).

Meta-model inputs are *measured* signals (time, or a measured input, output or state), so the
composed twin still simulates the whole swarm in one call (:mod:`.terms`).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from pydantic import (
    Field,
    StrictFloat,
    StrictInt,
    field_validator,
    model_validator,
)

from twinwatch._table import StrictTable
from twinwatch.twin.discovery.metamodels import TABLE_1, MetaModel, get_meta_model
from twinwatch.twin.discovery.separable import CandidateInput, SeparableFit
from twinwatch.twin.discovery.terms import TIME, Term, compose, format_terms, term_input
from twinwatch.twin.discovery.trigger import WindowStructure, residual_structure
from twinwatch.twin.estimation.estimator import Estimator, PSOSettings
from twinwatch.twin.estimation.fit import (
    ParameterMap,
    WindowFit,
    parameter_covariance,
    pso_minimize,
)
from twinwatch.twin.estimation.statistics import delta_bic, noise_level
from twinwatch.twin.model import AttachPoint, FloatArray, TwinModel, WindowData

logger = logging.getLogger(__name__)


class CandidateConfig(StrictTable):
    """One ``[[discovery.candidates]]`` entry: meta-models to try at one attach point.

    Attributes:
        attach: the model's attach point (``d(omega)/dt``, ``p``, ...).
        input: ``t`` (time [s]) or a measured channel name (``omega``, ``Va``, ...).
        kinds: meta-model kinds to try (default: the six of paper Table 1).
        amplitude: largest plausible magnitude of the term in the attach point's unit (bounds
            the main coefficient and offsets); default the attach point's own scale.
    """

    attach: str
    input: str = TIME
    kinds: list[str] = Field(default_factory=lambda: list(TABLE_1))
    amplitude: StrictFloat | None = Field(None, gt=0)

    @field_validator("kinds")
    @classmethod
    def _kinds(cls, v: list[str]) -> list[str]:
        for k in v:
            get_meta_model(k)
        if not v:
            raise ValueError("list at least one meta-model kind")
        return v


class RefinementConfig(StrictTable):
    """The ``[discovery.refinement]`` table: how a kept term accumulates evidence across
    windows (:meth:`~twinwatch.twin.discovery.terms.Term.refine`)."""

    enabled: bool = Field(True, description="combine every window's evidence on a kept term; "
                          "false: each window's polish replaces the parameters")
    memory: StrictFloat = Field(
        600.0, gt=0, allow_inf_nan=False,
        description="time constant of the forgetting of older evidence [s]: "
        "a window this much older weighs e times less")
    jump_threshold: StrictFloat = Field(
        25.0, gt=0, allow_inf_nan=False,
        description="a window whose estimate lies further than this "
        "normalised square per parameter from the refined one is "
        "a change: older evidence is discounted at once")
    joint: bool = Field(
        True, description="polish a kept term jointly with the parameters the estimator "
        "estimates, so its window evidence is marginal over them (false: conditional on the "
        "window's estimates, which lets a parameter that the window confounds with the term "
        "absorb the term's error: the leak example's D +36 %)")


class DiscoveryConfig(StrictTable):
    """The ``[discovery]`` table: when discovery runs and what it may add."""

    enabled: bool = Field(False, description="run the DT'' step")
    candidates: list[CandidateConfig] = Field(default_factory=list)
    trigger_windows: StrictInt = Field(3, ge=1, description="windows whose residual structure "
                                       "tests are combined before discovery runs (K; Fisher's "
                                       "method)")
    false_alarm: StrictFloat = Field(
        1e-6, gt=0, lt=1, description="level of the combined test: discovery runs when the "
        "last trigger_windows windows' residuals are together less likely than this in white "
        "noise (at most one needless search in 1/false_alarm windows); also the floor of one "
        "window's p-value when trigger_windows > 1, so no single window decides")
    window_alpha: StrictFloat = Field(
        1e-3, gt=0, lt=1, description="a window whose residual is this unlikely in white noise "
        "is structured: the model lacks something, its estimates are published suspect")
    whiteness_lags: StrictInt = Field(
        10, ge=1, le=100, description="autocorrelation lags of the Ljung-Box whiteness test")
    residual_ratio: StrictFloat | None = Field(
        None, gt=1, description="no longer used (the trigger was the normalised RMSE over this "
        "many times the noise level, per window: it missed a moderate fault on a running "
        "machine); the trigger is the whiteness test (false_alarm, window_alpha). Accepted "
        "with a warning")
    min_nrmse: StrictFloat = Field(
        2e-3, ge=0, description="the smallest structured residual that matters: its RMS "
        "beyond the white noise, normalised by the output's scale")
    bic_threshold: StrictFloat = Field(10.0, ge=0, description="BIC decrease a term must bring")
    min_improvement: StrictFloat = Field(
        0.2, ge=0, lt=1, description="fraction of the residual RMSE "
        "a term must remove")
    min_significance: StrictFloat = Field(5.0, ge=0, description="main coefficient over its "
                                          "standard error")
    max_terms: StrictInt = Field(3, ge=1)
    drop_after: StrictInt = Field(3, ge=1, description="windows in a row a kept term may fail "
                                  "re-validation before it is switched off")
    retry_after: StrictInt = Field(10, ge=1, description="windows to wait after a discovery that "
                                   "kept nothing")
    max_evaluations: StrictInt = Field(
        50_000, ge=1, description="twin evaluations one discovery may spend (its budget: the "
        "same windows and seed give the same terms on an idle box and on a loaded one)")
    time_budget: StrictFloat = Field(
        30.0, gt=0, description="wall-time safety net of one discovery [s]: a search it cuts "
        "is logged and counted (Discovery.time_cuts), and what it keeps then depends on the "
        "box's load; the budget is max_evaluations")
    refinement: RefinementConfig = Field(default_factory=RefinementConfig)
    pso: PSOSettings = Field(default_factory=lambda: PSOSettings(max_generations=30))
    seed: StrictInt = 0

    @model_validator(mode="after")
    def _check(self) -> DiscoveryConfig:
        if self.enabled and not self.candidates:
            raise ValueError("candidates: discovery is enabled but no candidate is listed")
        if self.residual_ratio is not None:
            logger.warning(
                "discovery.residual_ratio is no longer used: discovery runs on a whiteness "
                "test of the residual (discovery.false_alarm, discovery.window_alpha); remove "
                "the key")
        return self

    def check_against(self, model: TwinModel) -> None:
        """Raise ValueError naming the key if an attach point or input is not the model's."""
        names = [a.name for a in model.attach_points]
        channels = set(model.required_channels())
        for i, c in enumerate(self.candidates):
            if c.attach not in names:
                raise ValueError(f"discovery.candidates[{i}].attach: unknown attach point "
                                 f"{c.attach!r}; the model offers {names}")
            if c.input != TIME and c.input not in channels:
                raise ValueError(f"discovery.candidates[{i}].input: {c.input!r} is neither "
                                 f"'t' nor a channel of the model {sorted(channels)}")


def window_structure(r: FloatArray, n_out: int, config: DiscoveryConfig,
                     names: Sequence[str] | None = None) -> WindowStructure:
    """:func:`~twinwatch.twin.discovery.trigger.residual_structure` of normalised residuals
    ``r`` (M,) with ``n_out`` interleaved outputs, scaled by ``1/sqrt(M)``; ``names`` (n_out,)
    default to ``y0, y1, ...``.

    Raises:
        ValueError: ``M`` is not a multiple of ``n_out``, or ``names`` has another length."""
    r = np.asarray(r, dtype=float)
    res = r.reshape(-1, n_out) * math.sqrt(r.size)
    return residual_structure(res, list(names) if names is not None else
                              [f"y{j}" for j in range(n_out)],
                              lags=config.whiteness_lags, min_nrmse=config.min_nrmse,
                              window_alpha=config.window_alpha)


@dataclass
class _Candidate:
    meta: MetaModel
    attach: AttachPoint
    input: str
    amplitude: float


@dataclass
class _Fitted:
    """A candidate fitted on one window (normalised coordinates)."""

    cand: _Candidate
    p_norm: FloatArray
    active: tuple[bool, ...]
    z_ref: float
    t_ref: float
    r: FloatArray
    dbic: float
    improvement: float
    significance: float

    def to_term(self, window_index: int) -> Term:
        meta = self.cand.meta
        raw = meta.to_raw(self.p_norm, self.z_ref)
        raw = np.where(self.active, raw, 0.0)
        raw = meta.canonical(raw)
        t_ref = self.t_ref
        if self.cand.input == TIME:
            raw, t_ref = meta.shift_origin(raw, t_ref)
        return Term(meta, self.cand.attach, self.cand.input, raw, self.active,
                    t_ref=t_ref, significance=self.significance, since_window=window_index)


@dataclass
class DiscoveryReport:
    """What a discovery or re-validation did in one window."""

    ran: bool = False
    kept: list[Term] = field(default_factory=list)
    dropped: list[Term] = field(default_factory=list)
    elapsed_s: float = 0.0
    evaluations: int = 0
    tried: int = 0
    candidates: int = 0
    closest: str = ""
    cut: str = ""  # "", "evaluations" (max_evaluations) or "time" (the time_budget safety net)

    @property
    def verdict(self) -> str:
        """One line: what the search kept, or that no candidate describes the misfit (the
        closest one and the criteria it failed)."""
        if self.kept:
            return "kept: " + "; ".join(t.equation() for t in self.kept)
        if not self.ran:
            return "no search"
        what = (f"no candidate meta-model earns its place ({self.tried} of {self.candidates} "
                "tried")
        what += ")" if self.tried >= self.candidates else (
            "; the evaluation budget ran out)" if self.cut == "evaluations"
            else "; the time safety net cut it)")
        return what + (f"; closest: {self.closest}" if self.closest else "")


class Discovery:
    """Fits, selects and re-validates meta-model terms for one twin.

    Args:
        model: the twin (its attach points).
        config: the ``[discovery]`` table.
        estimator: the window estimator: its window fit scores DT' and DT'' alike, and its
            ``model_error`` floors the terms' standard errors as it floors the parameters'.

    Raises:
        ValueError: a candidate names an attach point or input the model does not have.
    """

    def __init__(self, model: TwinModel, config: DiscoveryConfig, estimator: Estimator) -> None:
        config.check_against(model)
        self.model = model
        self.config = config
        self.est = estimator
        self.candidates: list[_Candidate] = []
        for c in config.candidates:
            ap = model.attach_point(c.attach)
            amp = c.amplitude or ap.scale
            for kind in c.kinds:
                self.candidates.append(_Candidate(get_meta_model(kind), ap, c.input, amp))
        self._rng = np.random.default_rng(config.seed)
        self.evaluations = 0
        #: discoveries the wall-time safety net (``time_budget``) cut short
        self.time_cuts = 0

    def _fit(self, window: WindowData | WindowFit) -> WindowFit:
        return window if isinstance(window, WindowFit) else self.est.window_fit(window)

    def _resid(self, fit: WindowFit, theta: FloatArray,
               terms: Mapping[str, FloatArray] | None) -> FloatArray:
        """Normalised residuals (P, M) of the twin at ``theta`` (n_params,) with per-particle
        term values (attach -> (P, N) or (N,))."""
        before = fit.evaluations
        r = fit.residuals(np.asarray(theta, dtype=float)[None, :], terms)
        self.evaluations += fit.evaluations - before
        return r

    # -- discovery ------------------------------------------------------------------------
    def discover(self, window: WindowData | WindowFit, theta: FloatArray, kept: Sequence[Term]
                 ) -> tuple[list[Term], DiscoveryReport]:
        """Search the candidates on one window and return the newly kept terms.

        Args:
            window: the window (every required channel, finite), or its fit.
            theta: the physical parameters (n_params,) to hold while fitting.
            kept: terms already in DT'' (held while the new ones are fitted).

        Returns:
            (new terms, report). New terms are ordered by selection.
        """
        t0 = time.perf_counter()
        fit = self._fit(window)
        win = fit.window
        self.evaluations = 0
        cfg = self.config
        n_out = fit.n_out
        base_vals = compose(kept, win)
        r_base = self._resid(fit, theta, base_vals)[0]
        new: list[Term] = []
        report = DiscoveryReport(ran=True)
        deadline = t0 + cfg.time_budget
        pool = list(self.candidates)
        for _ in range(cfg.max_terms - len(kept)):
            fitted: list[_Fitted] = []
            for cand in pool:
                if self.evaluations >= cfg.max_evaluations:
                    report.cut = "evaluations"
                    logger.warning("discovery spent its budget (%d twin evaluations) after %d "
                                   "candidates", cfg.max_evaluations, report.tried)
                    break
                left = deadline - time.perf_counter()
                if left <= 0:
                    report.cut = "time"
                    self.time_cuts += 1
                    logger.warning("discovery cut by its wall-time safety net (%.2f s) after "
                                   "%d candidates (%d so far): the terms now depend on the "
                                   "box's load; raise [discovery] time_budget",
                                   cfg.time_budget, report.tried, self.time_cuts)
                    break
                # the candidate's own swarm stops on generations and stalls (evaluations);
                # the time left is only its safety net
                f = self._fit_candidate(cand, fit, theta, base_vals, r_base, left)
                report.tried += 1
                if f is not None:
                    fitted.append(f)
            best = self._select_term(fitted)
            if best is None:
                if not new and fitted:
                    report.closest = self._closest(fitted)
                break
            term = best.to_term(win.index)
            new.append(term)
            pool = [c for c in pool if not (c.meta is best.cand.meta and
                                            c.attach is best.cand.attach and
                                            c.input == best.cand.input)]
            base_vals = compose([*kept, *new], win)
            r_base = self._resid(fit, theta, base_vals)[0]
            if not window_structure(r_base, n_out, cfg).structured:
                break  # the residual is down to the noise: nothing left to explain
        report.kept = new
        report.candidates = len(self.candidates)
        report.elapsed_s = time.perf_counter() - t0
        report.evaluations = self.evaluations
        if not new:
            logger.info("window %d: %s", win.index, report.verdict)
        return new, report

    def _select_term(self, fitted: Sequence[_Fitted]) -> _Fitted | None:
        """The candidate to keep: among those that earn their place, the lowest BIC, unless a
        candidate with fewer parameters comes within ``bic_threshold`` of it (the extra
        parameters must earn their place too)."""
        ok = [f for f in fitted if self._earns_place(f)]
        if not ok:
            return None
        best = min(ok, key=lambda f: f.dbic)
        simpler = [f for f in ok if sum(f.active) < sum(best.active)
                   and f.dbic - best.dbic < self.config.bic_threshold]
        if simpler:
            best = min(simpler, key=lambda f: (sum(f.active), f.dbic))
        return best

    def _closest(self, fitted: Sequence[_Fitted]) -> str:
        """The candidate nearest to earning its place (lowest BIC) and what it lacks."""
        cfg = self.config
        f = min(fitted, key=lambda f: f.dbic)
        term = f.to_term(0)
        return (f"{term.equation()} removes {100 * f.improvement:.0f} % of the residual "
                f"(needs {100 * cfg.min_improvement:.0f} %), BIC change {f.dbic:+.1f} (needs "
                f"<= {-cfg.bic_threshold:g}), {f.significance:.1f} standard errors from zero "
                f"(needs {cfg.min_significance:g})")

    def _earns_place(self, f: _Fitted) -> bool:
        cfg = self.config
        return (f.dbic <= -cfg.bic_threshold and f.improvement >= cfg.min_improvement
                and f.significance >= cfg.min_significance)

    def _fit_candidate(self, cand: _Candidate, fit: WindowFit, theta: FloatArray,
                       base_vals: Mapping[str, FloatArray], r_base: FloatArray,
                       budget: float) -> _Fitted | None:
        """Fit one candidate on a window, the physical parameters ``theta`` and the kept
        terms ``base_vals`` held: a PSO over its nonlinear parameter with the coefficients
        from separable least squares (:class:`~.separable.SeparableFit`), then every form of it
        polished by bounded least squares; returns :meth:`_simplest_form`, or None when the
        meta-model cannot take the input or no form could be fitted. ``budget``: the wall time
        left to the discovery's safety net [s].
        """
        inp = CandidateInput.of(cand.meta, cand.input, cand.attach.mode == "additive",
                                cand.amplitude, fit.window)
        if inp is None:
            return None
        sep = SeparableFit(cand.meta, cand.attach.name, inp.u, base_vals, r_base,
                           cand.amplitude * 1e-3, lambda vals: self._resid(fit, theta, vals))
        nl_best = self._search_nonlinear(sep, inp, fit, budget)
        fitted = [f for f in (self._fit_form(sep, cand, inp, nl_best, mask, fit.n_out)
                              for mask in sep.forms()) if f is not None]
        return self._simplest_form(fitted, fit.n_out) if fitted else None

    def _search_nonlinear(self, sep: SeparableFit, inp: CandidateInput, fit: WindowFit,
                          budget: float) -> FloatArray:
        """The best nonlinear parameters (normalised; empty for a kind without one): a PSO
        over them only (periodic: the frequency), seeded by the kind from the residual
        (periodic of time: the periodogram's peaks), up to ``max_generations``, within
        the safety net ``budget`` [s], stopping once the best cost has not moved for 8
        generations."""
        meta, cfg = sep.meta, self.config
        if not meta.nonlinear:
            return np.zeros(0)
        nl_lo, nl_hi = meta.nonlinear_bounds(inp.b_range)
        seeds = meta.seeds(sep.r_base.reshape(-1, fit.n_out), fit.window, inp.is_time,
                           inp.z_ref, min(4, cfg.pso.pop_size))
        full = np.ones(len(meta.columns), dtype=bool)
        sw = pso_minimize(lambda x: sep.project(x, full)[0], nl_lo, nl_hi, cfg.pso,
                          rng=self._rng, time_budget=max(budget, 1e-3),
                          seeds=np.array(seeds) if seeds else None, patience=8)
        return sw.x

    def _fit_form(self, sep: SeparableFit, cand: _Candidate, inp: CandidateInput,
                  nl_best: FloatArray, mask: np.ndarray, n_out: int) -> _Fitted | None:
        """One form of the candidate (its ``mask``-ed columns) at the nonlinear parameters
        ``nl_best``: coefficients by projection, then every active parameter polished; its
        BIC change, residual improvement and significance against the kept terms alone."""
        meta = sep.meta
        _, coef = sep.project(nl_best[None, :], mask)
        p0 = meta.from_separable(nl_best, coef[0])
        active = meta.active_from_mask(mask)
        p, r, sig = self._polish(sep.residuals, p0, active, inp.lower, inp.upper, meta,
                                 cand.amplitude)
        if r is None:
            return None
        r_base = sep.r_base
        dbic = delta_bic(r_base, r, sum(active), n_out)
        rms0 = math.sqrt(float(r_base @ r_base))
        rms1 = math.sqrt(float(r @ r))
        impr = 1.0 - rms1 / rms0 if rms0 > 0 else 0.0
        return _Fitted(cand, p, active, inp.z_ref, inp.t_ref, r, dbic, impr, sig)

    def _simplest_form(self, fitted: list[_Fitted], n_out: int) -> _Fitted:
        """The simplest form unless an optional parameter itself earns its place: the best
        of the fewest parameters, then a larger form only if its extra parameters lower the
        BIC by ``bic_threshold`` against the form chosen so far."""
        fitted.sort(key=lambda f: sum(f.active))
        size = sum(fitted[0].active)
        best = min((f for f in fitted if sum(f.active) == size), key=lambda f: f.dbic)
        for f in fitted:
            extra = sum(f.active) - sum(best.active)
            if extra > 0 and delta_bic(best.r, f.r, extra, n_out) <= -self.config.bic_threshold:
                best = f
        return best

    def _polish(self, resid: Callable[[FloatArray], FloatArray], p0: FloatArray,
                active: tuple[bool, ...],
                lo: FloatArray, hi: FloatArray, meta: MetaModel, amplitude: float
                ) -> tuple[FloatArray, FloatArray | None, float]:
        """Bounded least squares over the active parameters (the rest 0); returns
        (parameters, residuals, significance of the main coefficient); bounds from
        :meth:`MetaModel.polish_bounds`."""
        act = np.array(active)
        p = np.where(act, p0, 0.0)
        lo, hi = meta.polish_bounds(lo, hi, amplitude)
        lo_a, hi_a = lo[act], hi[act]

        def fun(x: FloatArray) -> FloatArray:
            q = p.copy()
            q[act] = x
            out: FloatArray = resid(q)[0]
            return out

        from scipy.optimize import least_squares  # loaded on first use

        x0 = np.clip(p[act], lo_a + 1e-12 * (hi_a - lo_a), hi_a - 1e-12 * (hi_a - lo_a))
        try:
            sol = least_squares(fun, x0, bounds=(lo_a, hi_a), method="trf", x_scale="jac",
                                diff_step=1e-7, xtol=1e-12, ftol=1e-12, gtol=1e-12,
                                max_nfev=60)
        except ValueError:
            return p, None, 0.0
        r = sol.fun
        if not np.all(np.isfinite(r)) or np.any(np.abs(r) >= 1e5):
            return p, None, 0.0
        p[act] = sol.x
        main = meta.main_index(active)
        col = int(np.cumsum(act)[main]) - 1
        sd = self.est.relative_std(np.asarray(sol.jac), r)[col]
        sig = abs(float(p[main])) / sd if sd > 0 and math.isfinite(sd) else 0.0
        return p, r, sig

    # -- re-validation --------------------------------------------------------------------
    def revalidate(self, window: WindowData | WindowFit, theta: FloatArray, terms: list[Term],
                   free: Sequence[str] = ()) -> DiscoveryReport:
        """Polish the kept terms on a new window and switch off those that no longer earn
        their place (``drop_after`` failures in a row). Updates ``terms`` in place."""
        t0 = time.perf_counter()
        fit = self._fit(window)
        win = fit.window
        self.evaluations = 0
        report = DiscoveryReport()
        if not terms:
            return report
        n_out = fit.n_out
        self.polish_terms(fit, theta, terms, free)
        r_all = self._resid(fit, theta, compose(terms, win))[0]
        for term in list(terms):
            others = [t for t in terms if t is not term]
            r_without = self._resid(fit, theta, compose(others, win))[0]
            dbic = delta_bic(r_without, r_all, sum(term.active), n_out)
            rms0 = math.sqrt(float(r_without @ r_without))
            impr = 1.0 - math.sqrt(float(r_all @ r_all)) / rms0 if rms0 > 0 else 0.0
            ok = dbic <= -self.config.bic_threshold and impr >= self.config.min_improvement
            term.failures = 0 if ok else term.failures + 1
            # by identity: ``==`` between two terms compares arrays (ValueError)
            at = next(i for i, t in enumerate(terms) if t is term)
            if term.failures >= self.config.drop_after:
                del terms[at]
                report.dropped.append(term)
                r_all = self._resid(fit, theta, compose(terms, win))[0]
                continue
            simple = self._simplify(fit, theta, terms, term, r_all)
            if simple is not None:
                terms[at] = simple
                report.dropped.append(term)
                report.kept.append(simple)
                r_all = self._resid(fit, theta, compose(terms, win))[0]
        report.elapsed_s = time.perf_counter() - t0
        report.evaluations = self.evaluations
        return report

    def _simplify(self, fit: WindowFit, theta: FloatArray, terms: list[Term], term: Term,
                  r_all: FloatArray) -> Term | None:
        """A constant in place of a kept term whose kind :attr:`simplifies_to_constant` and
        whose shape no longer earns its place (its nonlinear parameter has gone to the neutral
        value: a base of 1, a rate or an exponent of 0). Discovered during a transient, such a
        term can fit the transient; once it has settled, the constant is the honest reading.

        Returns the constant term (linear meta-model, slope switched off) if it fits within
        ``bic_threshold`` of the kept term, else None."""
        if not term.meta.simplifies_to_constant:
            return None
        win = fit.window
        level = float(np.mean(term.values(win)))
        const = Term(get_meta_model("linear"), term.attach, term.input,
                     np.array([0.0, level]), (False, True), t_ref=0.0,
                     since_window=term.since_window)
        trial = [const if t is term else t for t in terms]
        self.polish_terms(fit, theta, trial)
        r_const = self._resid(fit, theta, compose(trial, win))[0]
        extra = sum(term.active) - 1
        if delta_bic(r_const, r_all, extra, fit.n_out) > -self.config.bic_threshold:
            logger.info("meta-model term %s simplified to the constant %s: its shape no "
                        "longer earns its place", term.expression(), const.expression())
            return const
        return None

    def polish_terms(self, window: WindowData | WindowFit, theta: FloatArray,
                     terms: list[Term], free: Sequence[str] = ()) -> None:
        """Joint bounded least squares over every kept term's active parameters, from their
        refined values, then each term's window estimate joins its evidence
        (:meth:`Term.refine`; ``[discovery.refinement]``).

        Time terms are polished in the coordinates of the window's centre (where a periodic
        term's frequency and phase are nearly uncorrelated); the window's covariance of each
        term is its block of the joint covariance (each output weighted by its residual
        variance, floored by the estimator's ``model_error``, inflated for autocorrelation).

        ``free`` names physical parameters (the window's determined estimates, with
        ``[discovery.refinement] joint``, the default) that are free in the same least
        squares (their logarithms, ties applied), from ``theta``: the term's window evidence
        and its covariance are then *marginal* over them (conditional on the window's
        estimates, a parameter confounded with the term absorbs the term's error, and the
        refined term keeps it there). Parameters the window did not determine stay held:
        freeing them lets their valley absorb part of a periodic term. The physical values of
        the joint solution are not published: the estimator's window estimate is.
        """
        fit = self._fit(window)
        win = fit.window
        centre = 0.5 * float(win.t[0] + win.t[-1])
        origins = [centre if term.movable else None for term in terms]
        local = [term.at_origin(o) for term, o in zip(terms, origins, strict=True)]
        slices = [np.array(t.active, dtype=bool) for t in local]
        x = np.concatenate([t.params[act] for t, act in zip(local, slices, strict=True)])

        def set_params(xv: FloatArray) -> list[Term]:
            out, k = [], 0
            for term, act in zip(local, slices, strict=True):
                q = term.params.copy()
                q[act] = xv[k:k + int(act.sum())]
                k += int(act.sum())
                out.append(Term(term.meta, term.attach, term.input, q, term.active,
                                t_ref=term.t_ref))
            return out

        n_terms = x.size
        free = [n for n in free if n in self.est.pmap.estimate]
        joint = bool(free)
        pmap = ParameterMap(self.est.names, free, dict(self.est.config.tie or {}))
        theta = np.asarray(theta, dtype=float)
        if joint:
            x = np.concatenate([x, pmap.ln(theta)])

        def fun(xv: FloatArray) -> FloatArray:
            th = pmap.full(xv[None, n_terms:], theta)[0] if joint else theta
            out: FloatArray = self._resid(fit, th, compose(set_params(xv[:n_terms]), win))[0]
            return out

        from scipy.optimize import least_squares  # loaded on first use

        scale = np.maximum(np.abs(x), 1e-6)
        if joint:
            scale[n_terms:] = 1e-3  # ln-parameters: a 0.1 % step is the natural unit
        try:
            sol = least_squares(fun, x, method="lm", x_scale=scale, diff_step=1e-7,
                                xtol=1e-12, ftol=1e-12, max_nfev=30 * (x.size + 1))
        except ValueError:
            return
        if not np.all(np.isfinite(sol.fun)) or float(sol.fun @ sol.fun) > float(
                fun(x) @ fun(x)):
            return
        jac = np.asarray(sol.jac)
        cov = parameter_covariance(jac, sol.fun, fit.n_out, self.est.config.model_error)
        with np.errstate(invalid="ignore"):
            sd = np.sqrt(np.where(np.diag(cov) > 0, np.diag(cov), np.inf))
        ref = self.config.refinement
        k = 0
        for term, loc, act, origin in zip(terms, local, slices, origins, strict=True):
            n = int(act.sum())
            y = loc.params.copy()
            y[act] = sol.x[k:k + n]
            block = cov[k:k + n, k:k + n]
            term.refine(y, block, origin, centre, win.index,
                        memory=ref.memory if ref.enabled else 0.0,
                        jump_threshold=ref.jump_threshold)
            main = term.meta.main_index(term.active)
            col = k + int(np.cumsum(act)[main]) - 1
            term.significance = (abs(float(sol.x[col])) / sd[col]
                                 if sd[col] > 0 and math.isfinite(sd[col]) else 0.0)
            k += n


__all__ = [
    "CandidateConfig",
    "Discovery",
    "DiscoveryConfig",
    "DiscoveryReport",
    "RefinementConfig",
    "Term",
    "compose",
    "delta_bic",
    "format_terms",
    "noise_level",
    "term_input",
    "window_structure",
]
