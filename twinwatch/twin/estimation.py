"""Per-window parameter estimation: the DT' step (paper Section 3.2).

Each acquisition window, the parameters that no sensor measures are re-estimated by minimising
the RMSE between measured and simulated outputs (paper Eq. 1-2) with particle swarm optimisation
(pymoo's PSO; paper Table 2: swarm 15, up to 1000 iterations, w 0.9, c1 = c2 = 2.0).

What twinwatch adds to the paper, and why (measured on this machine; see benchmarks/):

1. **Warm start and polish.** The swarm holds the last trusted estimate as one particle, and
   the PSO's best is polished with a bounded least-squares solver (scipy's trust-region
   reflective method) whose Jacobian is one batched twin call. pymoo's PSO alone stalls short
   of the best fit (Ra scattered by +-1 % on exact-model data, more iterations do not help);
   with the polish it reaches the best fit every time, in a few tens of milliseconds.
2. **Identifiability per window.** At the optimum the Jacobian ``S`` of the normalised
   residuals with respect to ln(p) gives each parameter's relative standard error,
   ``cov(ln p) = s^2 (S^T S)^-1`` with ``s`` the residual level (floored by ``model_error``
   so that noise-free data do not make a collinear set look determined). Parameters are
   admitted in the configured priority order while every admitted one keeps its relative
   standard error below ``max_rel_std``; the others are *held* at their last trusted value
   (with the reason) and the admitted ones are re-fitted with them held. A window without a
   transient thus estimates Ra and D with Ke held, instead of publishing noise along the
   Ra-Ke valley.
3. **Time budget.** The PSO stops at ``max_generations`` or ``time_budget`` seconds, whichever
   comes first; with the same seed and no time cap hit, results are bit-for-bit reproducible.

Fitness (paper Eq. 2, normalised): ``RMSE_n = sqrt(mean_j mean_k ((y_sim - y_meas)/s_j)^2)``
with ``s_j = max(rms(y_meas_j), floor_j)`` per output j, so that current [A], speed [rad/s] and
voltage [V] weigh alike.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator
from pymoo.algorithms.soo.nonconvex.pso import PSO
from pymoo.core.population import Population
from pymoo.core.problem import Problem
from pymoo.operators.sampling.lhs import LHS
from pymoo.optimize import minimize
from pymoo.termination.collection import TerminationCollection
from pymoo.termination.max_gen import MaximumGenerationTermination
from pymoo.termination.max_time import TimeBasedTermination
from scipy.optimize import least_squares

from twinwatch.twin.model import FloatArray, TwinModel, WindowData

logger = logging.getLogger(__name__)

_BAD_COST = 1e6  # fitness of a particle whose simulation blew up

#: What a published parameter value is: see :attr:`WindowEstimate.status`.
ParameterStatus = Literal["estimated", "held", "tied", "fixed"]


class PSOSettings(BaseModel):
    """PSO settings (paper Table 2 for the paper's method)."""

    model_config = ConfigDict(extra="forbid")

    pop_size: int = Field(15, ge=2, description="swarm size")
    max_generations: int = Field(20, ge=1, description="iteration limit")
    w: float = Field(0.9, description="inertia weight")
    c1: float = Field(2.0, description="cognitive parameter")
    c2: float = Field(2.0, description="social parameter")
    adaptive: bool = Field(False, description="pymoo's adaptive w/c1/c2 (off: the paper's)")


class EstimationConfig(BaseModel):
    """What to estimate and how (table ``[estimation]``)."""

    model_config = ConfigDict(extra="forbid")

    estimate: list[str] = Field(
        default_factory=lambda: ["Ra", "D", "Ke", "La", "J"],
        description="parameters to estimate, in priority order (first kept when not all "
        "can be determined)",
    )
    tie: dict[str, str] = Field(
        default_factory=lambda: {"Kt": "Ke"},
        description="parameter -> parameter it equals (Kt = Ke in SI units)",
    )
    bounds: dict[str, tuple[float, float]] = Field(
        default_factory=dict,
        description="parameter -> [low, high] in SI units; default [nominal/5, nominal*5]",
    )
    pso: PSOSettings = Field(default_factory=PSOSettings)
    polish: bool = Field(True, description="least-squares polish after the PSO")
    time_budget: float = Field(0.5, gt=0, description="PSO time cap per window [s]")
    max_rel_std: float = Field(
        0.01, gt=0, description="largest relative standard error of a published estimate"
    )
    model_error: float = Field(
        1e-4, ge=0, description="floor of the normalised residual level used for the "
        "standard errors (model and discretisation error of noise-free data)"
    )
    trust_rel_std: float = Field(
        0.01, gt=0, description="an estimate becomes the trusted value (held by later windows "
        "that cannot determine it) only if its relative standard error is below this; set it "
        "tighter than max_rel_std when a held value's error would propagate (D = Ke*ia/omega "
        "- c amplifies a Ke error about 5 times)"
    )
    trust_rmse: float = Field(
        0.05, gt=0, description="a window whose normalised RMSE exceeds this does not "
        "update the trusted parameters"
    )
    seed: int = 0

    @model_validator(mode="after")
    def _check(self) -> EstimationConfig:
        if len(set(self.estimate)) != len(self.estimate):
            raise ValueError("estimate: a parameter is listed twice")
        for name, (lo, hi) in self.bounds.items():
            if not (0 < lo < hi):
                raise ValueError(f"bounds.{name}: need 0 < low < high, got [{lo}, {hi}]")
        for dep, src in self.tie.items():
            if dep in self.estimate:
                raise ValueError(f"tie.{dep}: a tied parameter cannot also be estimated")
            if dep == src:
                raise ValueError(f"tie.{dep}: cannot be tied to itself")
        return self

    def check_against(self, model: TwinModel) -> None:
        """Raise ValueError naming the key if a parameter name is not the model's."""
        names = set(model.parameter_names)
        for key, group in (("estimate", self.estimate), ("bounds", list(self.bounds)),
                           ("tie", list(self.tie) + list(self.tie.values()))):
            for n in group:
                if n not in names:
                    raise ValueError(
                        f"estimation.{key}: unknown parameter {n!r}; the model has "
                        f"{sorted(names)}"
                    )


@dataclass
class WindowEstimate:
    """The result of one window's estimation.

    Attributes:
        values: every model parameter -> value [SI] (estimated, held, tied or fixed).
        estimated: parameters the data determined this window, with their values.
        held: parameter -> reason it is not an estimate this window.
        rel_std: estimated parameter -> relative standard error (1-sigma, fraction).
        rmse: output -> RMSE in the output's unit.
        nrmse: normalised RMSE (the fitness).
        simulated: twin outputs at ``values``, shape (N, n_outputs).
        elapsed_s: wall time of the estimation [s].
        generations: PSO iterations run; ``time_capped`` tells whether the time budget hit.
        evaluations: twin simulations of one parameter vector (particles + polish).
        trusted: whether this window updated the trusted parameters.
        status: every model parameter -> ``estimated`` (determined by this window),
            ``held`` (not determined: its last trusted value, reason in :attr:`held`),
            ``tied`` (equals another parameter) or ``fixed`` (nameplate, not estimated).
    """

    values: dict[str, float]
    estimated: dict[str, float]
    held: dict[str, str]
    rel_std: dict[str, float]
    rmse: dict[str, float]
    nrmse: float
    simulated: FloatArray
    elapsed_s: float
    generations: int
    time_capped: bool
    evaluations: int
    trusted: bool = False
    pso_nrmse: float = math.nan
    extra: dict[str, object] = field(default_factory=dict)
    status: dict[str, ParameterStatus] = field(default_factory=dict)


class _SwarmProblem(Problem):  # type: ignore[misc]
    """pymoo problem: the whole swarm is one vectorised twin call."""

    def __init__(self, cost_fn, xl: FloatArray, xu: FloatArray) -> None:  # type: ignore[no-untyped-def]
        super().__init__(n_var=xl.size, n_obj=1, xl=xl, xu=xu)
        self._cost_fn = cost_fn

    def _evaluate(self, x, out, *args, **kwargs):  # type: ignore[no-untyped-def]
        out["F"] = self._cost_fn(x)[:, None]


class Estimator:
    """Estimates a twin's parameters on one window at a time.

    Args:
        model: the twin.
        config: estimation settings.
        nominal: parameter -> nameplate value [SI] (defaults to the model's nominal values).

    Raises:
        ValueError: if the config names a parameter the model does not have.
    """

    def __init__(
        self,
        model: TwinModel,
        config: EstimationConfig,
        nominal: Mapping[str, float] | None = None,
    ) -> None:
        config.check_against(model)
        self.model = model
        self.config = config
        self.names = model.parameter_names
        self.nominal = model.nominal_vector(nominal)
        self.est_idx = np.array([self.names.index(n) for n in config.estimate], dtype=int)
        lo, hi = [], []
        for n in config.estimate:
            nom = self.nominal[self.names.index(n)]
            b = config.bounds.get(n, (nom / 5.0, nom * 5.0))
            if not 0 < b[0] < b[1]:
                raise ValueError(
                    f"estimation.bounds.{n}: the nominal value {nom:g} gives no positive default "
                    "range; parameters are estimated on a log scale, so set a positive "
                    f"[low, high] for {n} (or do not estimate it)")
            lo.append(b[0])
            hi.append(b[1])
        self.lower = np.array(lo)
        self.upper = np.array(hi)
        self._ties = [(self.names.index(d), self.names.index(s)) for d, s in config.tie.items()]
        #: The trusted parameter vector (full), updated by good windows.
        self.trusted = self.nominal.copy()
        self._rng = np.random.default_rng(config.seed)

    # -- parameter vectors ----------------------------------------------------------------
    def _full(self, q: FloatArray, idx: FloatArray, base: FloatArray) -> FloatArray:
        """Full parameter vectors (P, n_params) from ln-parameters q (P, len(idx))."""
        theta = np.repeat(base[None, :], q.shape[0], axis=0)
        theta[:, idx] = np.exp(q)
        for dep, src in self._ties:
            theta[:, dep] = theta[:, src]
        return theta

    # -- residuals ------------------------------------------------------------------------
    def _prepare(self, window: WindowData) -> tuple[FloatArray, FloatArray]:
        meas = np.column_stack([window[o] for o in self.model.output_names])
        floors = np.array([o.scale for o in self.model.outputs])
        scale = np.maximum(np.sqrt(np.mean(meas**2, axis=0)), floors)
        return meas, scale

    def _residuals(
        self, theta: FloatArray, window: WindowData, meas: FloatArray, scale: FloatArray,
        terms: Mapping[str, FloatArray] | None = None,
    ) -> FloatArray:
        """Normalised residuals (P, M) such that ||r||_2 = RMSE_n; rows that blew up are inf.

        ``terms``: meta-model terms composed into the twin (see :meth:`TwinModel.simulate`).
        """
        y = self.model.simulate(theta, window, terms)[:, 1:, :]
        r = (y - meas[None, 1:, :]) / scale
        r = r.reshape(r.shape[0], -1) / math.sqrt(r.shape[1] * r.shape[2])
        bad = ~np.all(np.isfinite(r), axis=1)
        r[bad] = _BAD_COST
        return r

    # -- main entry -----------------------------------------------------------------------
    def estimate(self, window: WindowData,
                 terms: Mapping[str, FloatArray] | None = None) -> WindowEstimate:
        """Estimate the parameters on one window.

        Args:
            window: N samples of every channel in ``model.required_channels()``, finite.
            terms: the accepted meta-model terms (DT'', paper Eq. 3), attach point -> values
                (N,), held fixed while the physical parameters are estimated.

        Returns:
            The window's estimate; :attr:`trusted` is updated if the fit is good.

        Raises:
            ValueError: if a channel is missing or holds non-finite values.
        """
        t_start = time.perf_counter()
        for ch in self.model.required_channels():
            if ch not in window.channels:
                raise ValueError(f"window lacks channel {ch!r}")
            if not np.all(np.isfinite(window.channels[ch])):
                raise ValueError(f"window channel {ch!r} holds NaN or inf")
        meas, scale = self._prepare(window)
        cfg = self.config
        evals = 0
        base = self.trusted.copy()
        idx = self.est_idx
        xl, xu = np.log(self.lower), np.log(self.upper)
        q0 = np.clip(np.log(base[idx]), xl, xu)

        def cost(q: FloatArray) -> FloatArray:
            nonlocal evals
            evals += q.shape[0]
            r = self._residuals(self._full(q, idx, base), window, meas, scale, terms)
            return np.sqrt(np.sum(r * r, axis=1))

        # 1. PSO, warm-started with the trusted estimate as one particle.
        gens, capped = 0, False
        if cfg.pso.max_generations > 0 and idx.size:
            problem = _SwarmProblem(cost, xl, xu)
            init = LHS()(problem, cfg.pso.pop_size, random_state=self._rng).get("X")
            init[0] = q0
            algo = PSO(pop_size=cfg.pso.pop_size, sampling=Population.new(X=init),
                       w=cfg.pso.w, c1=cfg.pso.c1, c2=cfg.pso.c2, adaptive=cfg.pso.adaptive)
            term = TerminationCollection(
                MaximumGenerationTermination(cfg.pso.max_generations),
                TimeBasedTermination(cfg.time_budget),
            )
            seed = int(self._rng.integers(2**31))
            res = minimize(problem, algo, term, seed=seed, verbose=False, copy_algorithm=False)
            q_best = np.asarray(res.X, dtype=float).reshape(-1)
            pso_cost = float(np.asarray(res.F).reshape(-1)[0])
            gens = int(res.algorithm.n_gen)
            capped = gens < cfg.pso.max_generations
        else:
            q_best, pso_cost = q0, float(cost(q0[None, :])[0])

        # 2. Least-squares polish of every estimated parameter, and
        # 3. identifiability: which of them does this window determine?
        fit = _Fit(self, window, meas, scale, idx, base, xl, xu, terms)
        q_best, r_best, jac = fit.refine(q_best, np.arange(idx.size), polish=cfg.polish)
        selected, rel_std, reasons = self._select(jac, r_best, self.model.excitation(window))
        held: dict[str, str] = {}
        names_est = [self.names[i] for i in idx]
        for k, name in enumerate(names_est):
            if k not in selected:
                held[name] = reasons[k]
        if len(selected) < idx.size:
            # Re-fit the determined ones with the others held at their trusted values.
            q_fit = q_best.copy()
            held_pos = [k for k in range(idx.size) if k not in selected]
            q_fit[held_pos] = np.log(base[idx[held_pos]])
            if selected:
                q_fit, r_fit, jac_s = fit.refine(q_fit, np.array(selected, dtype=int),
                                                 polish=True)
                rel_std = dict(zip(selected, self._rel_std(jac_s, r_fit), strict=True))
            q_best = q_fit
        evals += fit.evaluations

        theta = self._full(q_best[None, :], idx, base)
        y = self.model.simulate(theta, window, terms)[0]
        evals += 1
        err = y - meas
        rmse = {o: float(np.sqrt(np.mean(err[:, j] ** 2)))
                for j, o in enumerate(self.model.output_names)}
        nrmse = float(np.sqrt(np.mean((err[1:] / scale) ** 2)))
        values = dict(zip(self.names, (float(v) for v in theta[0]), strict=True))
        for n in self.names:
            if n in self.config.tie:
                held.setdefault(n, f"tied to {self.config.tie[n]}")
            elif n not in names_est:
                held.setdefault(n, "fixed (nameplate)")
        estimated = {names_est[k]: values[names_est[k]] for k in selected}
        status: dict[str, ParameterStatus] = {}
        for n in self.names:
            if n in estimated:
                status[n] = "estimated"
            elif n in self.config.tie:
                status[n] = "tied"
            elif n not in names_est:
                status[n] = "fixed"
            else:
                status[n] = "held"
        trusted = bool(np.isfinite(nrmse) and nrmse <= cfg.trust_rmse)
        if trusted:
            for k, n in zip(selected, (names_est[k] for k in selected), strict=True):
                if rel_std.get(k, math.inf) <= cfg.trust_rel_std:
                    self.trusted[self.names.index(n)] = values[n]
            for dep, src in self._ties:
                self.trusted[dep] = self.trusted[src]
        return WindowEstimate(
            values=values,
            estimated=estimated,
            held=held,
            rel_std={names_est[k]: float(v) for k, v in rel_std.items() if k in selected},
            rmse=rmse,
            nrmse=nrmse,
            simulated=y,
            elapsed_s=time.perf_counter() - t_start,
            generations=gens,
            time_capped=capped,
            evaluations=evals,
            trusted=trusted,
            pso_nrmse=pso_cost,
            status=status,
        )

    # -- helpers --------------------------------------------------------------------------
    def _rel_std(self, jac: FloatArray, r: FloatArray) -> FloatArray:
        """Relative 1-sigma standard errors of the columns of ``jac`` (ln-parameters).

        ``cov(ln p) = s^2 (J^T J)^-1`` with ``s^2`` the residual variance, floored by
        ``model_error`` and inflated by ``(1 + rho)/(1 - rho)``, rho being the residuals' lag-1
        autocorrelation (the AR(1) effective-sample-size correction): white noise leaves it
        alone, while smooth model error (a parameter drifting within the window) is not
        allowed to pass for hundreds of independent samples.
        """
        m, n = jac.shape
        s2 = max(float(r @ r) / max(m - n, 1) * m, self.config.model_error**2) / m
        n_out = len(self.model.outputs)
        res = r.reshape(-1, n_out)
        num = float(np.sum(res[1:] * res[:-1]))
        den = float(np.sum(res * res))
        rho = min(max(num / den, 0.0), 0.99) if den > 0 else 0.0
        s2 *= (1.0 + rho) / (1.0 - rho)
        # Equilibrate the columns before inverting: the hydraulic twin's J^T J has a condition
        # number ~1e15 in raw form (pressure in Pa against a piston area in m^2), where pinv
        # returns meaningless variances (D reported at 2e-7 relative instead of ~3).
        norms = np.linalg.norm(jac, axis=0)
        safe = np.where(norms > 0, norms, 1.0)
        js = jac / safe
        try:
            cov = np.linalg.pinv(js.T @ js, rcond=1e-15, hermitian=True) * s2
        except np.linalg.LinAlgError:
            return np.full(n, np.inf)
        d = np.diag(cov) / safe**2
        with np.errstate(invalid="ignore"):
            out = np.sqrt(np.where(d > 0, d, np.inf))
        # A column the outputs do not respond to at all is not determined.
        out[np.linalg.norm(jac, axis=0) == 0] = np.inf
        return out

    def _select(
        self, jac: FloatArray, r: FloatArray, unexcited: Mapping[str, str] | None = None
    ) -> tuple[list[int], dict[int, float], dict[int, str]]:
        """Admit parameters in priority order while all admitted stay determined.

        ``unexcited``: parameters the model says this window does not excite
        (:meth:`TwinModel.excitation`), with the reason; they are held like undetermined ones.

        The priority list is a hierarchy: once a parameter cannot be determined, it and every
        parameter after it are held. Otherwise a lower-priority parameter that trades off with
        a held one (Ke with D in a quasi-static window) would absorb the held one's drift.
        """
        limit = self.config.max_rel_std
        selected: list[int] = []
        rel: dict[int, float] = {}
        reasons: dict[int, str] = {}
        blocked: str | None = None
        for k in range(jac.shape[1]):
            name = self.names[self.est_idx[k]]
            if blocked is not None:
                reasons[k] = (f"held with {blocked} (lower priority): held at last trusted "
                              "value")
                continue
            if unexcited and name in unexcited:
                blocked = name
                reasons[k] = f"{unexcited[name]}: held at last trusted value"
                continue
            cand = [*selected, k]
            sd = self._rel_std(jac[:, cand], r)
            if np.all(sd <= limit):
                selected = cand
                rel = dict(zip(cand, sd, strict=True))
                continue
            blocked = name
            alone = float(self._rel_std(jac[:, [k]], r)[0])
            if alone > limit:
                reasons[k] = (f"not determined by this window (relative std {alone:.2g} > "
                              f"{limit:.2g}): held at last trusted value")
            else:
                worst = max(range(len(cand) - 1), key=lambda i: sd[i] / limit, default=None)
                other = self.names[self.est_idx[cand[worst]]] if worst is not None else "others"
                reasons[k] = (f"not separable from {other} in this window: held at last "
                              "trusted value")
        return selected, rel, reasons


class _Fit:
    """The local part of one window's estimation: polish over a subset of the ln-parameters
    (the rest held) and the residuals and Jacobian at the result, counting twin evaluations."""

    def __init__(self, est: Estimator, window: WindowData, meas: FloatArray, scale: FloatArray,
                 idx: np.ndarray, base: FloatArray, xl: FloatArray, xu: FloatArray,
                 terms: Mapping[str, FloatArray] | None = None) -> None:
        self.est, self.window, self.meas, self.scale = est, window, meas, scale
        self.idx, self.base, self.xl, self.xu = idx, base, xl, xu
        self.terms = terms
        self.evaluations = 0

    def residuals(self, q: FloatArray) -> FloatArray:
        """Normalised residuals (P, M) for ln-parameter rows q (P, n_est)."""
        self.evaluations += q.shape[0]
        theta = self.est._full(q, self.idx, self.base)
        return self.est._residuals(theta, self.window, self.meas, self.scale, self.terms)

    def jacobian(self, q: FloatArray, active: np.ndarray, r0: FloatArray) -> FloatArray:
        """Forward-difference d r / d ln p over the ``active`` columns: one twin call."""
        h = 1e-6
        qs = np.repeat(q[None, :], active.size, axis=0)
        qs[np.arange(active.size), active] += h
        return ((self.residuals(qs) - r0[None, :]) / h).T

    def refine(self, q: FloatArray, active: np.ndarray, *, polish: bool
               ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Polish the ``active`` entries of q (bounded least squares, trust-region reflective),
        then return (q, residuals (M,), Jacobian (M, len(active))) at the result."""
        q = q.copy()
        if polish and active.size:
            last: dict[str, FloatArray] = {}

            def fun(x: FloatArray) -> FloatArray:
                qq = q.copy()
                qq[active] = x
                r = self.residuals(qq[None, :])[0]
                last["x"], last["r"] = x.copy(), r
                return r

            def jac(x: FloatArray) -> FloatArray:
                # least_squares asks for the Jacobian where it just evaluated fun: reuse it.
                r0 = last["r"] if "x" in last and np.array_equal(last["x"], x) else fun(x)
                qq = q.copy()
                qq[active] = x
                return self.jacobian(qq, active, r0)

            lo, hi = self.xl[active], self.xu[active]
            x0 = np.clip(q[active], lo + 1e-12, hi - 1e-12)
            sol = least_squares(fun, x0, jac=jac, bounds=(lo, hi), method="trf", x_scale=1.0,
                                xtol=1e-10, ftol=1e-12, gtol=1e-12, max_nfev=50)
            q[active] = sol.x
        r = self.residuals(q[None, :])[0]
        return q, r, self.jacobian(q, active, r)
