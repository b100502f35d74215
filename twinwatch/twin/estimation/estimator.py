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
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from twinwatch.twin.estimation.fit import (
    LocalFit,
    ParameterMap,
    WindowFit,
    explained_rms,
    parameter_covariance,
    pso_minimize,
    relative_std,
    residual_variances,
)
from twinwatch.twin.estimation.fusion import FusionConfig, FusionState, ParameterFusion
from twinwatch.twin.estimation.statistics import ModelCheck, check_model, noise_level
from twinwatch.twin.model import FloatArray, TwinModel, WindowData

logger = logging.getLogger(__name__)

#: What a published parameter value is: see :attr:`WindowEstimate.status`.
ParameterStatus = Literal["estimated", "fused", "held", "tied", "fixed"]


class PSOSettings(BaseModel):
    """PSO settings (paper Table 2 for the paper's method)."""

    model_config = ConfigDict(extra="forbid")

    pop_size: int = Field(15, ge=2, description="swarm size")
    max_generations: int = Field(20, ge=1, description="iteration limit")
    w: float = Field(0.9, description="inertia weight")
    c1: float = Field(2.0, description="cognitive parameter")
    c2: float = Field(2.0, description="social parameter")
    adaptive: bool = Field(False, description="pymoo's adaptive w/c1/c2 (off: the paper's)")


class ValidationConfig(BaseModel):
    """Per-window model validation (table ``[estimation.validation]``; Ljung, System
    Identification, ch. 16): the residual of a twin that describes the machine is white and
    independent of the inputs."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(True, description="check every window's residuals")
    alpha: float = Field(0.01, gt=0, lt=0.5, description="level of the whiteness and "
                         "residual-input tests")
    lags: int = Field(20, ge=1, le=1000, description="lags of both tests (samples)")


class EstimationConfig(BaseModel):
    """What to estimate and how (table ``[estimation]``).

    ``estimate`` and ``tie`` left out mean "the model's" (:attr:`TwinModel.estimation_defaults`:
    the DC motor estimates Ra, D, Ke, La, J with Kt tied to Ke; the hydraulic actuator q_pump
    and D); :meth:`resolved` fills them in.
    """

    model_config = ConfigDict(extra="forbid")

    estimate: list[str] | None = Field(
        None,
        description="parameters to estimate, in priority order (first kept when not all "
        "can be determined); default: the model's",
    )
    tie: dict[str, str] | None = Field(
        None,
        description="parameter -> parameter it equals (Kt = Ke in SI units); default: the "
        "model's",
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
    validation: ValidationConfig = Field(default_factory=ValidationConfig)
    fusion: FusionConfig = Field(default_factory=FusionConfig)
    initial_state: bool = Field(
        True, description="estimate each window's initial state (offsets to the first "
        "sample's measured outputs) with the parameters: a noisy first sample otherwise leaves "
        "a transient in the residual and biases the estimates")
    seed: int = 0

    @model_validator(mode="after")
    def _check(self) -> EstimationConfig:
        if self.estimate is not None and len(set(self.estimate)) != len(self.estimate):
            raise ValueError("estimate: a parameter is listed twice")
        for name, (lo, hi) in self.bounds.items():
            if not (0 < lo < hi):
                raise ValueError(f"bounds.{name}: need 0 < low < high, got [{lo}, {hi}]")
        for dep, src in (self.tie or {}).items():
            if self.estimate is not None and dep in self.estimate:
                raise ValueError(f"tie.{dep}: a tied parameter cannot also be estimated")
            if dep == src:
                raise ValueError(f"tie.{dep}: cannot be tied to itself")
        return self

    def resolved(self, model: TwinModel) -> EstimationConfig:
        """This table with ``estimate`` and ``tie`` filled in from the model's defaults where
        left out (a tie whose parameter the configuration estimates is dropped).

        Raises:
            ValueError: naming the key, if a parameter name is not the model's.
        """
        defaults = model.estimation_defaults
        estimate = list(self.estimate) if self.estimate is not None else list(defaults.estimate)
        if self.tie is not None:
            tie = dict(self.tie)
        else:
            tie = {d: s for d, s in defaults.tie.items() if d not in estimate}
        out = self.model_copy(update={"estimate": estimate, "tie": tie})
        out.check_against(model)
        for dep in tie:
            if dep in estimate:
                raise ValueError(f"estimation.tie.{dep}: a tied parameter cannot also be "
                                 "estimated")
        return out

    def check_against(self, model: TwinModel) -> None:
        """Raise ValueError naming the key if a parameter name is not the model's."""
        names = set(model.parameter_names)
        tie = self.tie or {}
        for key, group in (("estimate", self.estimate or []), ("bounds", list(self.bounds)),
                           ("tie", list(tie) + list(tie.values()))):
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
        held: parameter -> reason it is not an estimate of this window (also for a fused one).
        rel_std: estimated parameter -> relative standard error (1-sigma, fraction).
        rmse: output -> RMSE in the output's unit.
        nrmse: normalised RMSE (the fitness).
        simulated: twin outputs at ``values``, shape (N, n_outputs).
        elapsed_s: wall time of the estimation [s].
        generations: PSO iterations run; ``time_capped`` tells whether the time budget hit.
        evaluations: twin simulations of one parameter vector (particles + polish).
        trusted: whether this window updated the trusted parameters.
        initial: the window's estimated initial-state offsets (``model.initial_states``, in
            their units), or None.
        model_check: the window's model validation (None when disabled); a window that fails
            it does not update the trusted values and its standard errors are widened.
        status: every model parameter -> ``estimated`` (determined by this window),
            ``fused`` (not by this window alone, but by the evidence of the windows so far:
            the fused value, :attr:`fused`), ``held`` (neither: its last trusted value,
            reason in :attr:`held`), ``tied`` (equals another parameter) or ``fixed``
            (nameplate, not estimated).
        fused: estimated parameter -> (fused value [SI], relative standard error) after this
            window (:mod:`twinwatch.twin.estimation.fusion`); empty when fusion is off.
        fusion_jump: the window's estimate was a sudden change for the fusion (it followed).
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
    initial: FloatArray | None = None
    model_check: ModelCheck | None = None
    fused: dict[str, tuple[float, float]] = field(default_factory=dict)
    fusion_jump: bool = False


@dataclass(frozen=True)
class EstimatorState:
    """What an :class:`Estimator` carries from one window to the next (its trusted parameter
    vector and the fusion's state), for :meth:`Estimator.snapshot` /
    :meth:`Estimator.rollback`."""

    trusted: FloatArray
    fusion: FusionState | None = None


class Estimator:
    """Estimates a twin's parameters on one window at a time.

    Args:
        model: the twin.
        config: estimation settings (``estimate``/``tie`` left out: the model's defaults).
        nominal: parameter -> nameplate value [SI] (defaults to the model's nominal values).

    Raises:
        ValueError: if the config names a parameter the model does not have, or a default
            search range is not positive.
    """

    def __init__(
        self,
        model: TwinModel,
        config: EstimationConfig,
        nominal: Mapping[str, float] | None = None,
    ) -> None:
        config = config.resolved(model)
        assert config.estimate is not None and config.tie is not None
        self.model = model
        self.config = config
        self.names = model.parameter_names
        self.nominal = model.nominal_vector(nominal)
        self.pmap = ParameterMap(self.names, config.estimate, config.tie)
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
        #: The trusted parameter vector (full), updated by good windows.
        self.trusted = self.nominal.copy()
        self._rng = np.random.default_rng(config.seed)
        #: Evidence across windows (None when ``[estimation.fusion] enabled = false``).
        self.fusion = (ParameterFusion(tuple(config.estimate), self.trusted[self.pmap.idx],
                                       config.fusion) if config.fusion.enabled else None)

    # -- state ----------------------------------------------------------------------------
    def snapshot(self) -> EstimatorState:
        """The state carried between windows, to :meth:`rollback` to."""
        return EstimatorState(self.trusted.copy(),
                              self.fusion.state.copy() if self.fusion else None)

    def rollback(self, state: EstimatorState) -> None:
        """Forget what windows since :meth:`snapshot` taught (a window the adaptation finds
        biased by a missing component must not update the trusted values or the fusion)."""
        self.trusted[:] = state.trusted
        if self.fusion is not None and state.fusion is not None:
            self.fusion.state = state.fusion.copy()

    def fusion_state(self) -> dict[str, Any] | None:
        """The fusion's state (JSON-serialisable), for persistence."""
        return self.fusion.state.as_dict() if self.fusion else None

    def set_fusion_state(self, state: Mapping[str, Any] | None) -> bool:
        """Resume the fusion from :meth:`fusion_state`; False (and a fresh start from the
        trusted values) when it does not fit this configuration."""
        if self.fusion is None:
            return state is None
        if state is not None:
            try:
                fs = FusionState.from_dict(state)
            except (KeyError, TypeError, ValueError):
                fs = None
            if fs is not None and fs.mean.shape == (self.fusion.n_state,) and \
                    fs.cov.shape == (self.fusion.n_state, self.fusion.n_state):
                self.fusion.state = fs
                return True
        self.fusion.reset(self.trusted[self.pmap.idx])
        return False

    def trusted_values(self) -> dict[str, float]:
        """Every parameter's trusted value [SI]."""
        return dict(zip(self.names, (float(v) for v in self.trusted), strict=True))

    def set_trusted(self, values: Mapping[str, float]) -> list[str]:
        """Resume from saved trusted values (ties re-applied). Returns the names that are not
        the model's (ignored)."""
        unknown = []
        for name, value in values.items():
            if name in self.names:
                self.trusted[self.names.index(name)] = float(value)
            else:
                unknown.append(name)
        self.pmap.apply_ties(self.trusted)
        return unknown

    def window_fit(self, window: WindowData) -> WindowFit:
        """The window's fit problem, scored as the estimator scores it."""
        return WindowFit(self.model, window)

    # -- main entry -----------------------------------------------------------------------
    def estimate(self, window: WindowData,
                 terms: Mapping[str, FloatArray] | None = None,
                 fit: WindowFit | None = None) -> WindowEstimate:
        """Estimate the parameters on one window.

        Args:
            window: N samples of every channel in ``model.required_channels()``, finite.
            terms: the accepted meta-model terms (DT'', paper Eq. 3), attach point -> values
                (N,), held fixed while the physical parameters are estimated.
            fit: the window's :class:`WindowFit` if the caller has built it already.

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
        wfit = fit or self.window_fit(window)
        evals0 = wfit.evaluations
        cfg = self.config
        base = self.trusted.copy()
        pmap = self.pmap
        n_est = pmap.idx.size
        xl, xu = np.log(self.lower), np.log(self.upper)
        q0 = np.clip(pmap.ln(base), xl, xu)

        def cost(q: FloatArray) -> FloatArray:
            return wfit.cost(pmap.full(q, base), terms)

        # 1. PSO, warm-started with the trusted estimate as one particle.
        gens, capped = 0, False
        if cfg.pso.max_generations > 0 and n_est:
            sw = pso_minimize(cost, xl, xu, cfg.pso, rng=self._rng,
                              time_budget=cfg.time_budget, seeds=q0[None, :])
            q_best, pso_cost, gens, capped = sw.x, sw.cost, sw.generations, sw.time_capped
        else:
            q_best, pso_cost = q0, float(cost(q0[None, :])[0])

        # 2. Least-squares polish of every estimated parameter (and the window's initial
        # state), and 3. identifiability: which of them does this window determine?
        local = LocalFit(wfit, pmap, base, xl, xu, terms,
                         initial=cfg.initial_state and bool(self.model.initial_states))
        nuis = local.nuisance
        v_best, r_best, jac = local.refine(local.start(q_best),
                                           np.arange(n_est + nuis.size), polish=cfg.polish)
        jac_final, r_final = jac, r_best
        # The residual variance of each row (per output), for the fusion's weights.
        row_var = residual_variances(r_best, len(self.model.outputs), cfg.model_error,
                                     n_est + nuis.size)
        nuisance_fit = v_best[n_est:].copy()
        selected, rel_std, reasons = self._select(jac, r_best, self.model.excitation(window),
                                                  nuis.size)
        held: dict[str, str] = {}
        names_est = list(cfg.estimate or [])
        for k, name in enumerate(names_est):
            if k not in selected:
                held[name] = reasons[k]
        if len(selected) < n_est:
            # Re-fit the determined ones with the others held at their trusted values.
            v_fit = v_best.copy()
            held_pos = [k for k in range(n_est) if k not in selected]
            v_fit[held_pos] = np.log(base[pmap.idx[held_pos]])
            active = np.concatenate([np.array(selected, dtype=int), nuis])
            if active.size:
                v_fit, r_fit, jac_s = local.refine(v_fit, active)
                sd = self._rel_std(jac_s, r_fit)[:len(selected)]
                rel_std = dict(zip(selected, sd, strict=True))
                jac_final, r_final = jac_s, r_fit
            v_best = v_fit
        q_best = v_best[:n_est]
        initial = local.initial(v_best)
        wfit.initial = initial
        theta = pmap.full(q_best[None, :], base)
        y = wfit.simulate(theta, terms)[0]
        res = wfit.residual(y)
        # 4. Model validation: is the residual what a twin that describes the machine leaves?
        check = None
        if cfg.validation.enabled:
            # What the white noise alone does to the estimates, and so to a noise-free
            # output's residual (the residual's own level would count model error as noise).
            n_out = len(self.model.outputs)
            white = noise_level(r_final.reshape(-1, n_out)) * math.sqrt(r_final.size)
            cov = parameter_covariance(jac_final, r_final, n_out, cfg.model_error, white)
            n_par = jac_final.shape[1] - nuis.size
            check = self.check(wfit, y, explained_rms(jac_final, cov, n_out),
                               drift=self._drift_residual(wfit, r_final, jac_final[:, :n_par]))
        if check is not None and not check.passed:
            rel_std = {k: v * check.widen for k, v in rel_std.items()}
        # The gate holds: nothing is published as an estimate above max_rel_std (the re-fit
        # with the others held, or a failed model check, can leave one above it).
        gated = [k for k in selected if not rel_std.get(k, math.inf) <= cfg.max_rel_std]
        for k in gated:
            selected.remove(k)
            why = ("after the model check failed and widened it"
                   if check is not None and not check.passed
                   else "after the re-fit with the others held")
            held[names_est[k]] = (f"not determined by this window (relative std "
                                  f"{rel_std.get(k, math.inf):.2g} > {cfg.max_rel_std:.2g} "
                                  f"{why}): held at last trusted value")
        if gated:
            # Held means held: the others are re-fitted with these at their trusted values,
            # so the published values and the simulation are the held twin's. Their standard
            # errors stay those of the fit in which the held ones were free (marginal over
            # them): the re-fit's would be conditional on a held value that may be off, and
            # narrower (on MotoShield a re-fitted D at -3.2 % got 1.5 %, against the 1.6 % its
            # 2-sigma interval needs to cover the commissioned value).
            v_best = v_best.copy()
            v_best[gated] = np.log(base[pmap.idx[gated]])
            active = np.concatenate([np.array(selected, dtype=int), nuis])
            if active.size:
                v_best, r_final, jac_final = local.refine(v_best, active)
            q_best = v_best[:n_est]
            initial = local.initial(v_best)
            wfit.initial = initial
            theta = pmap.full(q_best[None, :], base)
            y = wfit.simulate(theta, terms)[0]
            res = wfit.residual(y)

        values = dict(zip(self.names, (float(v) for v in theta[0]), strict=True))
        tie = cfg.tie or {}
        for n in self.names:
            if n in tie:
                held.setdefault(n, f"tied to {tie[n]}")
            elif n not in names_est:
                held.setdefault(n, "fixed (nameplate)")
        estimated = {names_est[k]: values[names_est[k]] for k in selected}
        nrmse = res.nrmse
        good = bool(np.isfinite(nrmse) and nrmse <= cfg.trust_rmse)
        passed = check is None or check.passed
        # 5. Evidence across windows: fuse the window (if its model check passed).
        fused: dict[str, tuple[float, float]] = {}
        jump = False
        if self.fusion is not None:
            t_mid = float(0.5 * (window.t[0] + window.t[-1]))
            if good and passed:
                # The window informs the parameters it determined and the first it could not
                # (weakly: noise, not structure, may be why); the ones after it are held at
                # their trusted values, as the window's estimate held them (with a viscous
                # load J, Ke and D trade off exactly: jointly, no window determines D).
                cols = np.arange(min(len(selected) + 1, n_est))
                base_ln = np.log(base[pmap.idx])

                def linearize(q: FloatArray) -> tuple[FloatArray, FloatArray]:
                    """The window's residuals and Jacobian (columns ``cols``, then the
                    initial state) at ln-parameters q."""
                    qq = base_ln.copy()
                    qq[cols] = q[cols]
                    v_f = np.concatenate([np.clip(qq, xl, xu), nuisance_fit])
                    r_f = local.residuals(v_f[None, :])[0]
                    active = np.concatenate([cols, nuis])
                    return local.jacobian(v_f, active, r_f), r_f

                jump = self.fusion.update(t_mid, linearize, row_var, nuis.size, cols=cols)
            else:
                self.fusion.update(t_mid)
            f_val, f_std = self.fusion.values(), self.fusion.rel_std()
            fused = {n: (f_val[n], f_std[n]) for n in names_est}
        out_std = {names_est[k]: float(v) for k, v in rel_std.items() if k in selected}
        status: dict[str, ParameterStatus] = {}
        for n in self.names:
            if n in estimated:
                status[n] = "estimated"
            elif n in tie:
                status[n] = "tied"
            elif n not in names_est:
                status[n] = "fixed"
            elif n in fused and fused[n][1] <= cfg.max_rel_std:
                status[n] = "fused"  # held[n] keeps why this window alone could not
                values[n] = fused[n][0]
                out_std[n] = fused[n][1]
            else:
                status[n] = "held"
        for dep, src in pmap.ties:
            values[self.names[dep]] = values[self.names[src]]
        trusted = good and passed
        if trusted:
            for k in selected:
                n = names_est[k]
                if rel_std.get(k, math.inf) <= cfg.trust_rel_std:
                    self.trusted[self.names.index(n)] = values[n]
            # A fused value is published, never trusted: the twin keeps holding the last value
            # a window determined (a fused Ke 1.5 % off, well within its 0.9 % interval, biased
            # D by 8 % through D = Ke*ia/omega - c when it was held at it).
            pmap.apply_ties(self.trusted)
        return WindowEstimate(
            values=values,
            estimated=estimated,
            held=held,
            rel_std=out_std,
            rmse=res.rmse,
            nrmse=nrmse,
            simulated=y,
            elapsed_s=time.perf_counter() - t_start,
            generations=gens,
            time_capped=capped,
            evaluations=wfit.evaluations - evals0,
            trusted=trusted,
            pso_nrmse=pso_cost,
            status=status,
            initial=initial,
            model_check=check,
            fused=fused,
            fusion_jump=jump,
        )

    def check(self, fit: WindowFit, y: FloatArray, explained: FloatArray | None = None,
              drift: FloatArray | None = None) -> ModelCheck:
        """Validate the twin on a window from its simulated outputs ``y`` (N, n_out)
        (:func:`~twinwatch.twin.estimation.statistics.check_model`, the ``[estimation.validation]``
        settings, the ``model_error`` floor, the model's exogenous inputs); ``explained``:
        per output, the residual RMS the estimates' uncertainty explains; ``drift``: the
        residual matrix to test instead, with what a drift of the estimated parameters within
        the window explains removed (:meth:`_drift_residual`)."""
        v = self.config.validation
        win = fit.window
        exog = [c for c in self.model.exogenous if c in win.channels]
        inputs = np.column_stack([win[c][1:] for c in exog]) if exog else None
        res = fit.error_matrix(y) if drift is None else drift
        return check_model(res, fit.names, inputs, alpha=v.alpha,
                           lags=min(v.lags, max(1, win.n // 4)),
                           floor=self.config.model_error, explained=explained)

    @staticmethod
    def _drift_residual(fit: WindowFit, r: FloatArray, jac: FloatArray) -> FloatArray | None:
        """The residual (N-1, n_out), normalised per output, with what a linear drift of the
        estimated parameters within the window explains removed.

        The paper's faults are slow degradations: a parameter that moves within the window
        leaves a smooth residual although the model is right. Its effect at sample k is about
        ``J_k (t_k - t_mid) rate`` (exact where the output follows the parameter without memory,
        as the hydraulic pressure follows D; close where the memory is short against the
        window); the rates come from linear least squares on the residual, and the model check
        tests what is left.

        Args:
            fit: the window's fit.
            r: (M,) normalised residuals at the estimate.
            jac: (M, n) their Jacobian with respect to the estimated ln-parameters.

        Returns:
            The residual matrix, or None without estimated parameters.
        """
        if jac.shape[1] == 0:
            return None
        n_out = fit.n_out
        t = fit.window.t[1:]
        tau = np.repeat((t - 0.5 * (t[0] + t[-1])) / max(float(t[-1] - t[0]), 1e-12), n_out)
        ramp = jac * tau[:, None]
        rates, *_ = np.linalg.lstsq(ramp, r, rcond=None)
        left = (r - ramp @ rates).reshape(-1, n_out)
        # back to the per-output normalisation of WindowFit.error_matrix (no weights, no 1/sqrt(M))
        return left * math.sqrt(r.size) / np.where(fit.weights != 0, fit.weights, 1.0)

    # -- helpers --------------------------------------------------------------------------
    def _rel_std(self, jac: FloatArray, r: FloatArray) -> FloatArray:
        return relative_std(jac, r, len(self.model.outputs), self.config.model_error)

    def relative_std(self, jac: FloatArray, r: FloatArray) -> FloatArray:
        """Relative standard errors of ln-parameter columns of ``jac`` at residuals ``r``, as
        the estimator computes them (:func:`twinwatch.twin.estimation.fit.relative_std` with this
        configuration's ``model_error`` floor)."""
        return self._rel_std(jac, r)

    def _select(
        self, jac: FloatArray, r: FloatArray, unexcited: Mapping[str, str] | None = None,
        n_nuisance: int = 0,
    ) -> tuple[list[int], dict[int, float], dict[int, str]]:
        """Admit parameters in priority order while all admitted stay determined.

        ``jac``: (M, n_est + n_nuisance), the parameters' columns then the nuisance ones (the
        window's initial state), which are always in the fit: a parameter is determined only
        if it is determined beside them.
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
        n_par = jac.shape[1] - n_nuisance
        nuis = list(range(n_par, jac.shape[1]))
        for k in range(n_par):
            name = self.names[self.pmap.idx[k]]
            if blocked is not None:
                reasons[k] = (f"held with {blocked} (lower priority): held at last trusted "
                              "value")
                continue
            if unexcited and name in unexcited:
                blocked = name
                reasons[k] = f"{unexcited[name]}: held at last trusted value"
                continue
            cand = [*selected, k]
            sd = self._rel_std(jac[:, cand + nuis], r)[:len(cand)]
            if np.all(sd <= limit):
                selected = cand
                rel = dict(zip(cand, sd, strict=True))
                continue
            blocked = name
            alone = float(self._rel_std(jac[:, [k, *nuis]], r)[0])
            if alone > limit:
                reasons[k] = (f"not determined by this window (relative std {alone:.2g} > "
                              f"{limit:.2g}): held at last trusted value")
            else:
                worst = max(range(len(cand) - 1), key=lambda i: sd[i] / limit, default=None)
                other = (self.names[self.pmap.idx[cand[worst]]] if worst is not None
                         else "others")
                reasons[k] = (f"not separable from {other} in this window: held at last "
                              "trusted value")
        return selected, rel, reasons
