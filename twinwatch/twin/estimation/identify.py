"""Commissioning: the baseline parameters of a machine, identified offline from a recording.

The monitor compares every window's estimates with a baseline (``[machine.parameters]``); on a
machine nobody has measured, that baseline must itself come from data, and from more of it than
one window: :func:`identify` fits the twin to a long training stretch (one free-run simulation
from the stretch's measured initial state, the output-error criterion of system identification),
with the daemon's global + local search (PSO over the logarithms of the estimated parameters
within their bounds, then bounded least squares with the initial state), gives every parameter
its interval (the least-squares covariance, each output's residual variance and autocorrelation
counted), and scores the result on a validation stretch it was not fitted to, per output::

    fit % = 100 * (1 - ||y - y_hat|| / ||y - mean(y)||)

(MATLAB ``compare``'s NRMSE fit; 100 % is a perfect fit, 0 % no better than the mean). The
residuals of both stretches go through the model check of the monitoring
(:func:`twinwatch.twin.estimation.statistics.check_model`).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from twinwatch.twin.estimation.estimator import EstimationConfig, Estimator, PSOSettings
from twinwatch.twin.estimation.fit import LocalFit, WindowFit, pso_minimize, relative_std
from twinwatch.twin.estimation.statistics import ModelCheck
from twinwatch.twin.model import FloatArray, TwinModel, WindowData

logger = logging.getLogger(__name__)


class IdentifyConfig(BaseModel):
    """The ``[identify]`` table: how ``twinwatch identify`` fits the baseline.

    Ranges are fractions of the recording's samples: ``[0.0, 0.5]`` is its first half.
    """

    train: tuple[float, float] = Field((0.0, 0.5), description="training range, fractions "
                                       "of the recording [start, end)")
    validate_: tuple[float, float] = Field(
        (0.5, 1.0), alias="validate", description="validation range, fractions of the "
        "recording [start, end); the fit is scored there, never fitted")
    weights: dict[str, float] = Field(default_factory=dict, description="output -> weight in "
                                      "the fitness (default 1)")
    estimate: list[str] | None = Field(
        None, description="parameters to identify (default: [estimation] estimate); a long "
        "recording determines more than one window (a warm-up law, the sensing's "
        "hypotheses), which the monitoring then holds at the identified values")
    bounds: dict[str, tuple[float, float]] = Field(
        default_factory=dict, description="parameter -> [low, high] in SI units for the "
        "identification, over [estimation] bounds (a cold start searches wider than a window)")
    pso: PSOSettings = Field(default_factory=lambda: PSOSettings(pop_size=30,
                                                                 max_generations=100))
    time_budget: float = Field(120.0, gt=0, allow_inf_nan=False,
                               description="wall-time cap of the global searches [s], shared "
                               "by the starts")
    starts: int = Field(1, ge=1, le=100, description="independent global searches, each "
                        "polished by least squares; the best training fit is kept (a long "
                        "free-run problem has local optima a single swarm may settle in)")
    seed: int = 0

    model_config = ConfigDict(extra="forbid", populate_by_name=True)

    @model_validator(mode="after")
    def _check(self) -> IdentifyConfig:
        for key, (a, b) in (("train", self.train), ("validate", self.validate_)):
            if not 0.0 <= a < b <= 1.0:
                raise ValueError(f"{key}: need 0 <= start < end <= 1 (fractions of the "
                                 f"recording), got [{a}, {b}]")
        for name, w in self.weights.items():
            if not (w >= 0 and math.isfinite(w)):
                raise ValueError(f"weights.{name}: must be a finite number >= 0")
        if self.estimate is not None and len(set(self.estimate)) != len(self.estimate):
            raise ValueError("estimate: a parameter is listed twice")
        for name, (lo, hi) in self.bounds.items():
            if not (0 < lo < hi and math.isfinite(hi)):
                raise ValueError(f"bounds.{name}: need 0 < low < high, got [{lo}, {hi}]")
        return self

    def check_against(self, model: TwinModel) -> None:
        """Raise ValueError naming the key (``identify.<key>``) if an output or a parameter
        is not the model's."""
        for name in self.weights:
            if name not in model.output_names:
                raise ValueError(f"identify.weights.{name}: not an output of the model "
                                 f"{list(model.output_names)}")
        names = model.parameter_names
        for key, group in (("estimate", self.estimate or []), ("bounds", list(self.bounds))):
            for name in group:
                if name not in names:
                    raise ValueError(f"identify.{key}: unknown parameter {name!r}; the model "
                                     f"has {sorted(names)}")

    def estimation(self, estimation: EstimationConfig) -> EstimationConfig:
        """The ``[estimation]`` table as the identification uses it: this table's
        ``estimate`` and ``bounds`` over it (a tie whose parameter is identified is dropped).
        """
        if self.estimate is None and not self.bounds:
            return estimation
        estimate = list(self.estimate) if self.estimate is not None else estimation.estimate
        tie = {d: s for d, s in (estimation.tie or {}).items() if d not in (estimate or [])}
        return estimation.model_copy(update={"estimate": estimate, "tie": tie,
                                             "bounds": {**estimation.bounds, **self.bounds}})


@dataclass
class StretchScore:
    """The identified twin on one stretch of the recording.

    Attributes:
        start, end: first and last time [s].
        samples: samples.
        fit_pct: output -> fit % (MATLAB ``compare``).
        rmse: output -> RMSE [output unit].
        check: the model check of the stretch's residual.
        simulated: the twin's outputs (N, n_out); measured: the measured ones.
        t: time stamps (N,).
    """

    start: float
    end: float
    samples: int
    fit_pct: dict[str, float]
    rmse: dict[str, float]
    check: ModelCheck
    t: FloatArray
    measured: FloatArray
    simulated: FloatArray


@dataclass
class Identification:
    """The result of :func:`identify`.

    Attributes:
        values: every model parameter -> identified value [SI] (estimated ones; the others
            as configured).
        rel_std: estimated parameter -> relative standard error (1 sigma).
        bounds: estimated parameter -> the [low, high] the search used [SI].
        estimated, tied, fixed: the parameters by role.
        train, validation: the scores on both stretches.
        elapsed_s: wall time [s]; evaluations: twin simulations of one parameter vector.
        nrmse: the training fitness (weighted normalised RMSE) at the result.
        starts: the training fitness each start reached (``[identify] starts``), in order.
    """

    values: dict[str, float]
    rel_std: dict[str, float]
    bounds: dict[str, tuple[float, float]]
    estimated: list[str]
    tied: dict[str, str]
    train: StretchScore
    validation: StretchScore
    elapsed_s: float
    evaluations: int
    units: dict[str, str] = field(default_factory=dict)
    nrmse: float = math.nan
    starts: list[float] = field(default_factory=list)


def fit_percent(measured: FloatArray, simulated: FloatArray) -> float:
    """``100 (1 - ||y - y_hat|| / ||y - mean(y)||)`` of one output (shapes (N,)); -inf for a
    constant measurement."""
    den = float(np.linalg.norm(measured - np.mean(measured)))
    if den == 0 or not np.all(np.isfinite(simulated)):
        return -math.inf
    return 100.0 * (1.0 - float(np.linalg.norm(measured - simulated)) / den)


def _score(model: TwinModel, est: Estimator, window: WindowData, theta: FloatArray,
           weights: Mapping[str, float], initial: FloatArray | None) -> StretchScore:
    fit = WindowFit(model, window, weights)
    fit.initial = initial
    y = fit.simulate(theta[None, :])[0]
    names = model.output_names
    check = est.check(fit, y)
    return StretchScore(
        start=float(window.t[0]), end=float(window.t[-1]), samples=window.n,
        fit_pct={o: fit_percent(fit.meas[1:, j], y[1:, j]) for j, o in enumerate(names)},
        rmse={o: float(np.sqrt(np.mean((y[1:, j] - fit.meas[1:, j]) ** 2)))
              for j, o in enumerate(names)},
        check=check, t=np.asarray(window.t), measured=fit.meas, simulated=y)


def identify(model: TwinModel, estimation: EstimationConfig, config: IdentifyConfig,
             train: WindowData, validation: WindowData,
             nominal: Mapping[str, float] | None = None) -> Identification:
    """Identify the estimated parameters on ``train`` and score them on ``validation``.

    Args:
        model: the twin (its structure and options as configured).
        estimation: the ``[estimation]`` table: which parameters, their bounds, ties, the
            ``model_error`` floor and the validation settings (``config.estimate`` and
            ``config.bounds`` override the first two).
        config: the ``[identify]`` table.
        train, validation: contiguous stretches of the recording, every channel the model
            needs, finite.
        nominal: the configured values [SI] of the parameters (starting point, and the value
            of those not estimated).

    Returns:
        The identification.

    Raises:
        ValueError: a stretch lacks a channel, holds non-finite values or is too short.
    """
    t_start = time.perf_counter()
    for w, what in ((train, "training"), (validation, "validation")):
        if w.n < 10:
            raise ValueError(f"the {what} range holds {w.n} samples: too few to identify "
                             "from (widen [identify] train / validate)")
        for ch in model.required_channels():
            if ch not in w.channels:
                raise ValueError(f"the recording has no channel {ch!r} ({what} range)")
            if not np.all(np.isfinite(w.channels[ch])):
                raise ValueError(f"channel {ch!r} holds NaN or inf in the {what} range")
    est = Estimator(model, config.estimation(estimation), nominal)
    cfg = est.config
    names_est = list(cfg.estimate or [])
    fit = WindowFit(model, train, config.weights)
    pmap = est.pmap
    base = est.trusted.copy()
    xl, xu = np.log(est.lower), np.log(est.upper)
    rng = np.random.default_rng(config.seed)

    def cost(q: FloatArray) -> FloatArray:
        return fit.cost(pmap.full(q, base))

    q0 = np.clip(pmap.ln(base), xl, xu)
    cost0 = float(cost(q0[None, :])[0])
    local = LocalFit(fit, pmap, base, xl, xu, None,
                     initial=cfg.initial_state and bool(model.initial_states))
    n_est = len(names_est)
    active = np.arange(n_est + local.n_init)
    best: tuple[float, FloatArray, FloatArray, FloatArray] | None = None
    reached: list[float] = []
    t_global = time.perf_counter()
    for start in range(config.starts):
        # Each start: a swarm of its own (the configured values one of its particles), then
        # the local polish; the best training fit of all starts is kept.
        left = config.time_budget - (time.perf_counter() - t_global)
        sw = pso_minimize(cost, xl, xu, config.pso, rng=rng,
                          time_budget=max(left / (config.starts - start), 1e-3),
                          seeds=q0[None, :])
        q_best = sw.x if sw.cost <= cost0 else q0
        v, r, jac = local.refine(local.start(q_best), active)
        # a second polish from the first: the long free-run problem is stiffer than a window's
        v, r, jac = local.refine(v, active)
        sse = float(r @ r)
        logger.info("identify start %d/%d: PSO %d generations, cost %.6g; polished %.6g",
                    start + 1, config.starts, sw.generations, sw.cost, math.sqrt(sse))
        reached.append(math.sqrt(sse))
        if best is None or sse < best[0]:
            best = (sse, v, r, jac)
    assert best is not None
    _, v, r, jac = best
    sd = relative_std(jac, r, fit.n_out, cfg.model_error)[:n_est]
    theta = pmap.full(v[None, :n_est], base)[0]
    values = dict(zip(model.parameter_names, (float(x) for x in theta), strict=True))
    init = local.initial(v)
    return Identification(
        values=values,
        rel_std={n: float(s) for n, s in zip(names_est, sd, strict=True)},
        bounds={n: (float(lo), float(hi)) for n, lo, hi in
                zip(names_est, est.lower, est.upper, strict=True)},
        estimated=names_est,
        tied=dict(cfg.tie or {}),
        train=_score(model, est, train, theta, config.weights, init),
        validation=_score(model, est, validation, theta, config.weights, None),
        elapsed_s=time.perf_counter() - t_start,
        evaluations=fit.evaluations,
        nrmse=math.sqrt(best[0]),
        starts=reached,
        units={p.name: p.unit for p in model.parameters},
    )


def parameters_block(result: Identification, source: str, *, nominal_header: str = ""
                     ) -> str:
    """The ``[machine.parameters]`` block (and the bounds the search used) to paste into a
    monitoring configuration, each value with its interval and the fit figures as comments."""
    lines = [f"# Identified by `twinwatch identify` from {source}",
             f"# training {result.train.start:g}-{result.train.end:g} s "
             f"({result.train.samples} samples), validation {result.validation.start:g}-"
             f"{result.validation.end:g} s ({result.validation.samples} samples)",
             "# fit % (100 (1 - |y - y_hat| / |y - mean(y)|)): "
             + "; ".join(f"{o} {result.train.fit_pct[o]:.1f} training, "
                         f"{result.validation.fit_pct[o]:.1f} validation"
                         for o in result.train.fit_pct)]
    if nominal_header:
        lines.append(f"# {nominal_header}")
    lines.append("[machine.parameters]")
    for name, value in result.values.items():
        unit = result.units.get(name, "")
        if name in result.rel_std:
            note = f"{unit}, identified +- {100 * result.rel_std[name]:.2g} % (1 sigma)"
        elif name in result.tied:
            note = f"{unit}, tied to {result.tied[name]}"
        else:
            note = f"{unit}, as configured (not identified)"
        lines.append(f"{name} = {value:.6g}".ljust(24) + f"# {note}")
    lines.append("")
    lines.append("# The search range the identification used; for the monitoring's [estimation]:")
    lines.append("# bounds = { " + ", ".join(f"{n} = [{lo:.4g}, {hi:.4g}]"
                                             for n, (lo, hi) in result.bounds.items()) + " }")
    return "\n".join(lines) + "\n"


__all__ = ["Identification", "IdentifyConfig", "StretchScore", "fit_percent", "identify",
           "parameters_block"]
