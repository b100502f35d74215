"""Unknown-component discovery: the DT'' step (paper Section 3.3, Table 1, Eq. 3).

When re-estimating the physical parameters cannot explain a window (the DT' residual stays
above the exit criterion), a second optimisation fits interpretable meta-model terms attached to
the twin's equations: DT'' = DT(p, x) + sum_i U_i(z_i). The specialist's configuration says which
meta-models are candidates, what each takes as input (time or a measured channel) and where it
attaches (an :class:`~twinwatch.twin.model.AttachPoint` of the model: additive to a state
equation such as ``d(omega)/dt``, multiplicative on an equation such as the pressure ``p``).

How the search is made reliable (our design; the paper runs one PSO over every meta-model with
on/off weights, which on this machine found the unbalanced shaft's periodic term in 2 runs of 10
and kept spurious terms):

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
3. **Re-validation.** Every later window polishes the kept terms from their last values and
   checks that each still earns its place (the same criterion, as a removal test); a term that
   fails ``drop_after`` windows in a row is switched off.

Meta-model inputs are *measured* signals (time, or a measured input, output or state): the terms
do not depend on the simulated state, so they are computed once per particle and the composed
twin still simulates the whole swarm in one call. An additive term's value for sample k is taken
at the middle of the step k -> k+1 (the twin holds it over the step); a multiplicative one at
sample k.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from pymoo.algorithms.soo.nonconvex.pso import PSO
from pymoo.core.population import Population
from pymoo.operators.sampling.lhs import LHS
from pymoo.optimize import minimize
from pymoo.termination.collection import TerminationCollection
from pymoo.termination.ftol import SingleObjectiveSpaceTermination
from pymoo.termination.max_gen import MaximumGenerationTermination
from pymoo.termination.max_time import TimeBasedTermination
from pymoo.termination.robust import RobustTermination
from scipy.optimize import least_squares

from twinwatch.twin.estimation import Estimator, PSOSettings, _SwarmProblem
from twinwatch.twin.metamodels import META_MODELS, MetaModel, get_meta_model
from twinwatch.twin.model import AttachPoint, FloatArray, TwinModel, WindowData

logger = logging.getLogger(__name__)

TIME = "t"


class CandidateConfig(BaseModel):
    """One ``[[discovery.candidates]]`` entry: meta-models to try at one attach point.

    Attributes:
        attach: the model's attach point (``d(omega)/dt``, ``p``, ...).
        input: ``t`` (time [s]) or a measured channel name (``omega``, ``Va``, ...).
        kinds: meta-model kinds of Table 1 to try (default: all six).
        amplitude: largest plausible magnitude of the term in the attach point's unit (bounds
            the main coefficient and offsets); default the attach point's own scale.
    """

    model_config = ConfigDict(extra="forbid")

    attach: str
    input: str = TIME
    kinds: list[str] = Field(default_factory=lambda: list(META_MODELS))
    amplitude: float | None = Field(None, gt=0)

    @field_validator("kinds")
    @classmethod
    def _kinds(cls, v: list[str]) -> list[str]:
        for k in v:
            get_meta_model(k)
        if not v:
            raise ValueError("list at least one meta-model kind")
        return v


class DiscoveryConfig(BaseModel):
    """The ``[discovery]`` table: when discovery runs and what it may add."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(False, description="run the DT'' step")
    candidates: list[CandidateConfig] = Field(default_factory=list)
    trigger_windows: int = Field(3, ge=1, description="consecutive windows whose residual is "
                                 "too large before discovery runs (K)")
    residual_ratio: float = Field(3.0, gt=1, description="a residual is too large when its "
                                  "normalised RMSE exceeds this many times the normalised noise "
                                  "level estimated from the residual")
    min_nrmse: float = Field(2e-3, ge=0, description="... and its normalised RMSE exceeds this")
    bic_threshold: float = Field(10.0, ge=0, description="BIC decrease a term must bring")
    min_improvement: float = Field(0.2, ge=0, lt=1, description="fraction of the residual RMSE "
                                   "a term must remove")
    min_significance: float = Field(5.0, ge=0, description="main coefficient over its "
                                    "standard error")
    max_terms: int = Field(3, ge=1)
    drop_after: int = Field(3, ge=1, description="windows in a row a kept term may fail "
                            "re-validation before it is switched off")
    retry_after: int = Field(10, ge=1, description="windows to wait after a discovery that "
                             "kept nothing")
    time_budget: float = Field(1.5, gt=0, description="wall-time cap of one discovery [s]")
    pso: PSOSettings = Field(default_factory=lambda: PSOSettings(max_generations=30))
    seed: int = 0

    @model_validator(mode="after")
    def _check(self) -> DiscoveryConfig:
        if self.enabled and not self.candidates:
            raise ValueError("candidates: discovery is enabled but no candidate is listed")
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


@dataclass
class Term:
    """A kept meta-model term of DT''.

    Attributes:
        meta: the meta-model.
        attach: where it attaches.
        input: ``t`` or a channel name.
        params: raw parameters (len(meta.params),) for the input ``z = input - t_ref``
            (``t_ref`` only for time; 0 when the term reads in absolute time).
        active: which parameters are on (switched-off offsets are 0).
        t_ref: time origin of a time input [s].
        significance: main coefficient over its standard error, last window.
        failures: consecutive windows it failed re-validation.
        since_window: window index it was discovered in.
    """

    meta: MetaModel
    attach: AttachPoint
    input: str
    params: FloatArray
    active: tuple[bool, ...]
    t_ref: float = 0.0
    significance: float = math.inf
    failures: int = 0
    since_window: int = 0

    @property
    def weight(self) -> float:
        """The main coefficient (paper: the weight linking the meta-model to the twin)."""
        return float(self.params[self.meta.main_index(self.active)])

    def z(self, window: WindowData) -> FloatArray:
        """The input samples the twin uses (additive: mid-step; multiplicative: at sample)."""
        additive = self.attach.mode == "additive"
        return term_input(window, self.input, self.t_ref, additive)

    def values(self, window: WindowData) -> FloatArray:
        """U(z) at each sample of the window, shape (N,)."""
        return self.meta.evaluate(self.params[None, :], self.z(window))[0]

    def input_text(self, precision: int = 2) -> str:
        if self.input != TIME:
            return self.input
        if self.t_ref == 0:
            return "t"
        return f"(t - {self.t_ref:.{precision}f})"

    def expression(self, precision: int = 2) -> str:
        return self.meta.render(self.params, self.input_text(precision), precision)

    def equation(self, precision: int = 2) -> str:
        """The term as an equation of DT'', e.g.
        ``d(omega)/dt += 4.98*sin(10.00*t + 2.12) rad/s^2``."""
        if self.attach.mode == "additive":
            return f"{self.attach.name} += {self.expression(precision)} {self.attach.unit}"
        return f"{self.attach.name} *= 1 + ({self.expression(precision)})"

    def meaning(self) -> str:
        """Interpretation: the kind and where it acts, with Table 1's working conditions.

        A linear term without slope is a constant: a steady offset (additive) or gain change
        (multiplicative) of the quantity, which the paper reads as a leak on the hydraulic
        pressure (Section 5.3.2); Table 1's linear conditions are named after it."""
        if self.meta.kind == "linear" and not self.active[0]:
            what = "gain" if self.attach.mode == "multiplicative" else "offset"
            return (f"constant on {self.attach.quantity}: a steady {what} (a leak, a constant "
                    f"load or loss; Table 1 linear: {self.meta.meaning})")
        kind = self.meta.kind.replace("_", " ")
        return f"{kind} on {self.attach.quantity}: {self.meta.meaning}"

    def describe(self, precision: int = 2) -> str:
        return f"{self.equation(precision)}  [{self.meaning()}]"

    def as_dict(self) -> dict[str, Any]:
        """The health message's ``terms`` entry (README: "The health message")."""
        return {
            "kind": self.meta.kind,
            "attach": self.attach.name,
            "mode": self.attach.mode,
            "input": self.input,
            "t_ref": self.t_ref,
            "params": {n: float(v) for n, v, a in
                       zip(self.meta.params, self.params, self.active, strict=True) if a},
            "weight": self.weight,
            "significance": _finite(self.significance),
            "equation": self.equation(),
            "meaning": self.meaning(),
            "since_window": self.since_window,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], model: TwinModel) -> Term:
        """Rebuild a term from :meth:`as_dict` (persistence)."""
        meta = get_meta_model(d["kind"])
        params = np.array([float(d["params"].get(n, 0.0)) for n in meta.params])
        active = tuple(n in d["params"] for n in meta.params)
        sig = d.get("significance")
        return cls(meta=meta, attach=model.attach_point(d["attach"]), input=d["input"],
                   params=params, active=active, t_ref=float(d.get("t_ref", 0.0)),
                   significance=math.inf if sig is None else float(sig),
                   since_window=int(d.get("since_window", 0)))


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def term_input(window: WindowData, name: str, t_ref: float, additive: bool) -> FloatArray:
    """Input samples of a term, shape (N,): time relative to ``t_ref`` or a channel; for an
    additive term, at the middle of each step (the last sample's step is extrapolated)."""
    if name == TIME:
        z = window.t - t_ref
        if additive:
            z = z + 0.5 * window.sample_period
        return np.asarray(z, dtype=float)
    z = np.asarray(window[name], dtype=float)
    if additive and z.size > 1:
        z = np.concatenate([0.5 * (z[:-1] + z[1:]), z[-1:]])
    return z


def compose(terms: Sequence[Term], window: WindowData) -> dict[str, FloatArray]:
    """Sum the terms per attach point: the ``terms`` argument of ``TwinModel.simulate``."""
    out: dict[str, FloatArray] = {}
    for term in terms:
        v = term.values(window)
        out[term.attach.name] = out.get(term.attach.name, 0.0) + v
    return out


def noise_level(residual: FloatArray) -> FloatArray:
    """Per-output white-noise level of residuals (N, n_out) from first differences:
    ``std(diff(e))/sqrt(2)`` is the noise's standard deviation for white noise and nearly
    blind to a smooth (model-error) residual."""
    d = np.diff(residual, axis=0)
    return np.sqrt(np.mean(d * d, axis=0) / 2.0)


def residual_too_large(r: FloatArray, n_out: int, config: DiscoveryConfig) -> bool:
    """The exit criterion on normalised residuals ``r`` (M,) with ``n_out`` interleaved
    outputs: a normalised RMSE above ``min_nrmse`` and above ``residual_ratio`` times the
    normalised white-noise level (:func:`noise_level`, pooled over the outputs). Pooling keeps
    a noise-free output with a small structured error (the closed-loop Va after a noisy
    initial state) from passing for a missing component."""
    if not np.all(np.isfinite(r)):
        return True
    res = r.reshape(-1, n_out) * math.sqrt(r.size)
    nrmse = float(np.sqrt(np.mean(res * res)))
    if nrmse <= config.min_nrmse:
        return False
    noise = float(np.sqrt(np.mean(noise_level(res) ** 2)))
    return nrmse > config.residual_ratio * noise


def _ar1(r: FloatArray, n_out: int) -> float:
    res = r.reshape(-1, n_out)
    den = float(np.sum(res * res))
    if den <= 0:
        return 0.0
    return min(max(float(np.sum(res[1:] * res[:-1])) / den, 0.0), 0.99)


def delta_bic(r_base: FloatArray, r_new: FloatArray, k: int, n_out: int) -> float:
    """BIC(new) - BIC(base) for ``k`` extra parameters, with the sample size corrected for
    the new residuals' lag-1 autocorrelation (effective n = n (1 - rho)/(1 + rho)).

    Args:
        r_base, r_new: normalised residuals (M,), ``M = (N - 1)*n_out``.
        k: parameters the new model adds.
        n_out: outputs interleaved in the residual vectors.
    """
    rho = _ar1(r_new, n_out)
    n_eff = max(r_new.size * (1.0 - rho) / (1.0 + rho), float(k + 2))
    rss0, rss1 = float(r_base @ r_base), float(r_new @ r_new)
    if rss1 <= 0:
        return -math.inf
    tiny = 1e-300
    return n_eff * math.log(max(rss1, tiny) / max(rss0, tiny)) + k * math.log(n_eff)


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
        raw = self.cand.meta.to_raw(self.p_norm, self.z_ref)
        raw = np.where(self.active, raw, 0.0)
        raw = self.cand.meta.canonical(raw)
        t_ref = self.t_ref
        if self.cand.input == TIME:
            raw, t_ref = self.cand.meta.shift_origin(raw, t_ref)
        return Term(self.cand.meta, self.cand.attach, self.cand.input, raw, self.active,
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


class Discovery:
    """Fits, selects and re-validates meta-model terms for one twin.

    Args:
        model: the twin (its attach points).
        config: the ``[discovery]`` table.
        estimator: the window estimator (its residual normalisation is reused, so DT' and DT''
            are scored alike).

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

    # -- residuals ------------------------------------------------------------------------
    def residuals(self, theta: FloatArray, window: WindowData,
                  terms: Mapping[str, FloatArray] | None) -> FloatArray:
        """Normalised residuals (P, M) of the twin at ``theta`` (n_params,) with per-particle
        term values (attach -> (P, N) or (N,))."""
        meas, scale = self.est._prepare(window)
        p = 1
        for v in (terms or {}).values():
            if np.ndim(v) == 2:
                p = max(p, v.shape[0])
        self.evaluations += p
        th = np.repeat(np.asarray(theta, dtype=float)[None, :], p, axis=0)
        return self.est._residuals(th, window, meas, scale, terms)

    # -- discovery ------------------------------------------------------------------------
    def discover(self, window: WindowData, theta: FloatArray, kept: Sequence[Term]
                 ) -> tuple[list[Term], DiscoveryReport]:
        """Search the candidates on one window and return the newly kept terms.

        Args:
            window: the window (every required channel, finite).
            theta: the physical parameters (n_params,) to hold while fitting.
            kept: terms already in DT'' (held while the new ones are fitted).

        Returns:
            (new terms, report). New terms are ordered by selection.
        """
        t0 = time.perf_counter()
        self.evaluations = 0
        cfg = self.config
        n_out = len(self.model.outputs)
        base_vals = compose(kept, window)
        r_base = self.residuals(theta, window, base_vals)[0]
        new: list[Term] = []
        report = DiscoveryReport(ran=True)
        deadline = t0 + cfg.time_budget
        pool = list(self.candidates)
        for _ in range(cfg.max_terms - len(kept)):
            fitted: list[_Fitted] = []
            for i, cand in enumerate(pool):
                left = deadline - time.perf_counter()
                if left <= 0:
                    logger.warning("discovery reached its time budget (%.2f s) after %d "
                                   "candidates", cfg.time_budget, report.tried)
                    break
                f = self._fit_candidate(cand, window, theta, base_vals, r_base, n_out,
                                        left / (len(pool) - i))
                report.tried += 1
                if f is not None:
                    fitted.append(f)
            best = self._select_term(fitted)
            if best is None:
                break
            term = best.to_term(window.index)
            new.append(term)
            pool = [c for c in pool if not (c.meta is best.cand.meta and
                                            c.attach is best.cand.attach and
                                            c.input == best.cand.input)]
            base_vals = compose([*kept, *new], window)
            r_base = self.residuals(theta, window, base_vals)[0]
            if not residual_too_large(r_base, n_out, cfg):
                break  # the residual is down to the noise: nothing left to explain
        report.kept = new
        report.elapsed_s = time.perf_counter() - t0
        report.evaluations = self.evaluations
        return new, report

    def _select_term(self, fitted: Sequence[_Fitted]) -> _Fitted | None:
        """The candidate to keep: among those that earn their place, the lowest BIC, unless a
        candidate with fewer parameters comes within ``bic_threshold`` of it (the extra
        parameters must earn their place too: a constant leak is a constant, not an
        exponential whose base fits to 1.0000)."""
        ok = [f for f in fitted if self._earns_place(f)]
        if not ok:
            if fitted:
                f = min(fitted, key=lambda f: f.dbic)
                logger.debug("best candidate %s on %s does not earn its place (dBIC %.1f, "
                             "improvement %.0f %%, significance %.1f)", f.cand.meta.kind,
                             f.cand.attach.name, f.dbic, 100 * f.improvement, f.significance)
            return None
        best = min(ok, key=lambda f: f.dbic)
        simpler = [f for f in ok if sum(f.active) < sum(best.active)
                   and f.dbic - best.dbic < self.config.bic_threshold]
        if simpler:
            best = min(simpler, key=lambda f: (sum(f.active), f.dbic))
        return best

    def _earns_place(self, f: _Fitted) -> bool:
        cfg = self.config
        return (f.dbic <= -cfg.bic_threshold and f.improvement >= cfg.min_improvement
                and f.significance >= cfg.min_significance)

    def _fit_candidate(self, cand: _Candidate, window: WindowData, theta: FloatArray,
                       base_vals: Mapping[str, FloatArray], r_base: FloatArray, n_out: int,
                       budget: float) -> _Fitted | None:
        meta, cfg = cand.meta, self.config
        additive = cand.attach.mode == "additive"
        t_ref = float(window.t[0]) if cand.input == TIME else 0.0
        if cand.input == TIME and meta.positive_input:
            t_ref = 0.0  # power and logarithm of time read in absolute time (t > 0)
        z = term_input(window, cand.input, t_ref, additive)
        if meta.positive_input and not np.all(z > 0):
            return None
        z_ref = float(np.max(np.abs(z)))
        if cand.input == TIME and not meta.positive_input:
            z_ref = float(window.t[-1] - window.t[0]) or 1.0
        if not (z_ref > 0 and math.isfinite(z_ref)):
            return None
        u = z / z_ref
        b_range = None
        if meta.kind == "periodic":
            # One period per window up to a quarter of the sampling rate, in units of z_ref
            # (time) or of the input's range (a channel).
            ts = window.sample_period
            b_range = ((2 * math.pi / (window.t[-1] - window.t[0])) * z_ref,
                       (math.pi / (2 * ts)) * z_ref) if cand.input == TIME else (0.5, 50.0)
        lo, hi = meta.bounds(cand.amplitude, b_range=b_range)
        name = cand.attach.name
        base_at = np.asarray(base_vals.get(name, 0.0))
        eps = cand.amplitude * 1e-3  # probe size for the linearised response

        def resid(p: FloatArray) -> FloatArray:
            v = meta.evaluate(np.atleast_2d(p), u)
            vals = dict(base_vals)
            vals[name] = base_at + v
            return self.residuals(theta, window, vals)

        def project(nl: FloatArray, mask: FloatArray) -> tuple[FloatArray, FloatArray]:
            """Separable least squares: for each row of nonlinear parameters, the basis
            coefficients minimising the linearised residual. Returns (cost (P,), coef
            (P, n_cols)); the response to each basis function is one batched twin call."""
            basis = meta.basis(nl, u)  # (P, n_cols, N)
            n_p, n_c, n = basis.shape
            cols = np.flatnonzero(mask)
            probe = base_at + eps * basis[:, cols].reshape(-1, n)
            vals = dict(base_vals)
            vals[name] = probe
            sens = ((self.residuals(theta, window, vals) - r_base) / eps).reshape(
                n_p, cols.size, -1)
            cost = np.full(n_p, np.inf)
            coef = np.zeros((n_p, n_c))
            for q in range(n_p):
                s_q = sens[q].T
                if not np.all(np.isfinite(s_q)):
                    continue
                c, *_ = np.linalg.lstsq(s_q, -r_base, rcond=None)
                coef[q, cols] = c
                r_lin = r_base + s_q @ c
                cost[q] = math.sqrt(float(r_lin @ r_lin))
            return cost, coef

        full = np.ones(len(meta.columns), dtype=bool)
        n_nl = len(meta.nonlinear)
        if n_nl:
            # 1. PSO over the nonlinear parameters only (periodic: the frequency), seeded with
            # the residual's periodogram peaks.
            nl_lo, nl_hi = meta.nonlinear_bounds(b_range)
            problem = _SwarmProblem(lambda x: project(x, full)[0], nl_lo, nl_hi)
            pop = cfg.pso.pop_size
            init = LHS()(problem, pop, random_state=self._rng).get("X")
            if meta.kind == "periodic" and cand.input == TIME:
                peaks = self._peak_frequencies(r_base, window, n_out, min(4, pop))
                for k, w in enumerate(peaks):
                    init[k, 0] = np.clip(w * z_ref, nl_lo[0], nl_hi[0])
            algo = PSO(pop_size=pop, sampling=Population.new(X=init), w=cfg.pso.w,
                       c1=cfg.pso.c1, c2=cfg.pso.c2, adaptive=cfg.pso.adaptive)
            # Up to max_generations, within this candidate's share of the time budget, and
            # stop once the best cost has not moved for 8 generations (the 1-D frequency
            # search converges in a few when a periodogram seed is right).
            term = TerminationCollection(
                MaximumGenerationTermination(cfg.pso.max_generations),
                TimeBasedTermination(max(budget * 0.6, 1e-3)),
                RobustTermination(SingleObjectiveSpaceTermination(tol=1e-9), period=8))
            res = minimize(problem, algo, term, seed=int(self._rng.integers(2**31)),
                           verbose=False, copy_algorithm=False)
            nl_best = np.asarray(res.X, dtype=float).reshape(-1)
        else:
            nl_best = np.zeros(0)

        # 2. Every form (the full one and each without an optional parameter): project,
        # polish all its parameters by nonlinear least squares, keep the best by BIC.
        forms = [full]
        for opt in meta.optional:
            m = full.copy()
            m[meta.column_of(opt)] = False
            forms.append(m)
        fitted: list[_Fitted] = []
        for mask in forms:
            _, coef = project(nl_best[None, :], mask)
            p0 = meta.from_separable(nl_best, coef[0])
            active = self._active_params(meta, mask)
            p, r, sig = self._polish(resid, p0, active, lo, hi, meta, cand.amplitude)
            if r is None:
                continue
            dbic = delta_bic(r_base, r, sum(active), n_out)
            rms0 = math.sqrt(float(r_base @ r_base))
            rms1 = math.sqrt(float(r @ r))
            impr = 1.0 - rms1 / rms0 if rms0 > 0 else 0.0
            fitted.append(_Fitted(cand, p, active, z_ref, t_ref, r, dbic, impr, sig))
        if not fitted:
            return None
        # The simplest form unless the optional parameter itself earns its place.
        reduced = [f for f in fitted if not all(f.active)]
        full_fit = [f for f in fitted if all(f.active)]
        if not reduced:
            return full_fit[0]
        simple = min(reduced, key=lambda f: f.dbic)
        if full_fit and delta_bic(simple.r, full_fit[0].r, 1, n_out) <= -cfg.bic_threshold:
            return full_fit[0]
        return simple

    @staticmethod
    def _active_params(meta: MetaModel, mask: FloatArray) -> tuple[bool, ...]:
        """Parameters switched on by a basis-column mask."""
        if meta.kind == "periodic":
            return (True, True, True, bool(mask[2]))
        on = dict(zip(meta.columns, (bool(x) for x in mask), strict=True))
        return tuple(on.get(n, True) for n in meta.params)

    def _polish(self, resid, p0: FloatArray, active: tuple[bool, ...],  # type: ignore[no-untyped-def]
                lo: FloatArray, hi: FloatArray, meta: MetaModel, amplitude: float
                ) -> tuple[FloatArray, FloatArray | None, float]:
        """Bounded least squares over the active parameters (the rest 0); returns
        (parameters, residuals, significance of the main coefficient). Linear coefficients
        are bounded by +-10 amplitudes, nonlinear ones by their search bounds."""
        act = np.array(active)
        p = np.where(act, p0, 0.0)
        lo, hi = lo.copy(), hi.copy()
        for k, n in enumerate(meta.params):
            if n not in meta.nonlinear:
                lo[k], hi[k] = -10 * amplitude, 10 * amplitude
        if meta.kind == "periodic":
            lo[2], hi[2] = -4 * math.pi, 4 * math.pi
        lo_a, hi_a = lo[act], hi[act]

        def fun(x: FloatArray) -> FloatArray:
            q = p.copy()
            q[act] = x
            return resid(q)[0]

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
        sd = self.est._rel_std(np.asarray(sol.jac), r)[col]
        sig = abs(float(p[main])) / sd if sd > 0 and math.isfinite(sd) else 0.0
        return p, r, sig

    def _peak_frequencies(self, r: FloatArray, window: WindowData, n_out: int,
                          count: int) -> list[float]:
        """Angular frequencies [rad/s] of the largest periodogram peaks of the residual,
        refined by parabolic interpolation, strongest first."""
        res = r.reshape(-1, n_out)
        n = res.shape[0]
        nfft = 8 * n
        spec = np.zeros(nfft // 2 + 1)
        for j in range(n_out):
            x = res[:, j] - np.mean(res[:, j])
            spec += np.abs(np.fft.rfft(x * np.hanning(n), nfft)) ** 2
        freqs = np.fft.rfftfreq(nfft, window.sample_period) * 2 * math.pi
        peaks = [k for k in range(2, spec.size - 1)
                 if spec[k] >= spec[k - 1] and spec[k] > spec[k + 1]]
        peaks.sort(key=lambda k: -spec[k])
        out = []
        for k in peaks[:count]:
            a, b, c = np.log(spec[k - 1:k + 2] + 1e-300)
            den = a - 2 * b + c
            shift = 0.5 * (a - c) / den if den != 0 else 0.0
            out.append(float(freqs[k] + shift * (freqs[1] - freqs[0])))
        return out

    # -- re-validation --------------------------------------------------------------------
    def revalidate(self, window: WindowData, theta: FloatArray, terms: list[Term]
                   ) -> DiscoveryReport:
        """Polish the kept terms on a new window and switch off those that no longer earn
        their place (``drop_after`` failures in a row). Updates ``terms`` in place."""
        t0 = time.perf_counter()
        self.evaluations = 0
        report = DiscoveryReport()
        if not terms:
            return report
        n_out = len(self.model.outputs)
        self.polish_terms(window, theta, terms)
        r_all = self.residuals(theta, window, compose(terms, window))[0]
        for term in list(terms):
            others = [t for t in terms if t is not term]
            r_without = self.residuals(theta, window, compose(others, window))[0]
            dbic = delta_bic(r_without, r_all, sum(term.active), n_out)
            rms0 = math.sqrt(float(r_without @ r_without))
            impr = 1.0 - math.sqrt(float(r_all @ r_all)) / rms0 if rms0 > 0 else 0.0
            ok = dbic <= -self.config.bic_threshold and impr >= self.config.min_improvement
            term.failures = 0 if ok else term.failures + 1
            if term.failures >= self.config.drop_after:
                terms.remove(term)
                report.dropped.append(term)
                r_all = self.residuals(theta, window, compose(terms, window))[0]
                continue
            simple = self._simplify(window, theta, terms, term, r_all, n_out)
            if simple is not None:
                terms[terms.index(term)] = simple
                report.dropped.append(term)
                report.kept.append(simple)
                r_all = self.residuals(theta, window, compose(terms, window))[0]
        report.elapsed_s = time.perf_counter() - t0
        report.evaluations = self.evaluations
        return report

    def _simplify(self, window: WindowData, theta: FloatArray, terms: list[Term], term: Term,
                  r_all: FloatArray, n_out: int) -> Term | None:
        """A constant in place of a kept exponential, negative exponential or power term
        whose shape no longer earns its place (its nonlinear parameter has gone to the neutral
        value: a base of 1, a rate or an exponent of 0). Discovered during a transient, such a
        term can fit the transient; once it has settled, the constant is the honest reading.

        Returns the constant term (linear meta-model, slope switched off) if it fits within
        ``bic_threshold`` of the kept term, else None."""
        if term.meta.kind not in ("exponential", "negative_exponential", "power"):
            return None
        level = float(np.mean(term.values(window)))
        const = Term(get_meta_model("linear"), term.attach, term.input,
                     np.array([0.0, level]), (False, True), t_ref=0.0,
                     since_window=term.since_window)
        trial = [const if t is term else t for t in terms]
        self.polish_terms(window, theta, trial)
        r_const = self.residuals(theta, window, compose(trial, window))[0]
        extra = sum(term.active) - 1
        if delta_bic(r_const, r_all, extra, n_out) > -self.config.bic_threshold:
            logger.info("meta-model term %s simplified to the constant %s: its shape no "
                        "longer earns its place", term.expression(), const.expression())
            return const
        return None

    def polish_terms(self, window: WindowData, theta: FloatArray, terms: list[Term]) -> None:
        """Joint bounded least squares over every kept term's active parameters, from their
        current values (a term's phase and frequency drift slowly between windows)."""
        slices, x0 = [], []
        for term in terms:
            act = np.array(term.active)
            slices.append(act)
            x0.append(term.params[act])
        x = np.concatenate(x0)

        def set_params(xv: FloatArray) -> list[Term]:
            out, k = [], 0
            for term, act in zip(terms, slices, strict=True):
                q = term.params.copy()
                q[act] = xv[k:k + int(act.sum())]
                k += int(act.sum())
                out.append(Term(term.meta, term.attach, term.input, q, term.active,
                                t_ref=term.t_ref))
            return out

        def fun(xv: FloatArray) -> FloatArray:
            return self.residuals(theta, window, compose(set_params(xv), window))[0]

        scale = np.maximum(np.abs(x), 1e-6)
        try:
            sol = least_squares(fun, x, method="lm", x_scale=scale, diff_step=1e-7,
                                xtol=1e-12, ftol=1e-12, max_nfev=30 * (x.size + 1))
        except ValueError:
            return
        if not np.all(np.isfinite(sol.fun)) or float(sol.fun @ sol.fun) > float(
                fun(x) @ fun(x)):
            return
        k = 0
        jac = np.asarray(sol.jac)
        sd = self.est._rel_std(jac, sol.fun)
        for term, act in zip(terms, slices, strict=True):
            n = int(act.sum())
            term.params[act] = sol.x[k:k + n]
            term.params = term.meta.canonical(term.params)
            main = term.meta.main_index(term.active)
            col = k + int(np.cumsum(act)[main]) - 1
            term.significance = (abs(term.weight) / sd[col]
                                 if sd[col] > 0 and math.isfinite(sd[col]) else 0.0)
            k += n


def format_terms(terms: Sequence[Term], precision: int = 2) -> str:
    """DT'' as plain text, one term per line (empty string without terms)."""
    return "\n".join(t.describe(precision) for t in terms)


__all__ = [
    "CandidateConfig",
    "Discovery",
    "DiscoveryConfig",
    "DiscoveryReport",
    "Term",
    "compose",
    "delta_bic",
    "format_terms",
    "noise_level",
    "term_input",
]
