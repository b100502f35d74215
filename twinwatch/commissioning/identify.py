"""Commissioning: the baseline parameters of a machine, identified offline from a recording,
and what the recording can and cannot tell about them (docs/drives.md, "Commissioning").

:func:`identify` fits the twin to a training stretch in one free run (output error; PSO over
the ln-parameters, then bounded least squares with the initial state), analyses
identifiability at the optimum (Ljung, *System Identification*, 2nd ed., ch. 4.6 and 9;
MATLAB's ``getcov``/``getpvec``), holds the undetermined parameters at stated values
(``[identify.fixed]``, else ``[machine.parameters]``) and re-fits the rest, scores both fits
on a validation stretch (:func:`fit_percent`, MATLAB ``compare``), and gives AIC/BIC (MATLAB
``aic``) by which :func:`compare_structures` ranks ``[identify.candidates]``.
:func:`parameters_block` writes the ``[machine.parameters]`` lines to paste.

The covariance is the monitoring's sandwich (:func:`least_squares_covariance`); the
information matrix analysed is its inverse over the parameters (the initial-state offsets
profiled out).
"""

from __future__ import annotations

import itertools
import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from twinwatch.config.identify import AS_CONFIGURED, IdentifyConfig
from twinwatch.plugins import toml_value
from twinwatch.twin.estimation.estimator import EstimationConfig, Estimator
from twinwatch.twin.estimation.fit import (
    LocalFit,
    ParameterMap,
    WindowFit,
    explained_dof,
    explained_rms,
    parameter_covariance,
    pso_minimize,
    residual_variances,
)
from twinwatch.twin.estimation.statistics import ModelCheck, OutputCheck, noise_level
from twinwatch.twin.model import BoolArray, FloatArray, TwinModel, WindowData

logger = logging.getLogger(__name__)

#: A parameter within this relative distance (in ln) of a bound is "at the bound".
AT_BOUND = 0.01
#: Components of a combination below this fraction of its largest are left out of its label.
LABEL_CUT = 0.2
#: A parameter with a stated value can resolve a combination when its weight is at least
#: this fraction of the largest (a smaller one leaves the others' error amplified by 1/w).
HOLD_SHARE = 0.1
#: The partners named when no stated value resolves a combination: weights from this fraction.
MAIN_SHARE = 0.3


@dataclass
class StretchScore:
    """The identified twin on one stretch of the recording.

    Attributes:
        start, end: first and last time [s].
        samples: samples.
        fit_pct: output -> fit % (MATLAB ``compare``).
        rmse: output -> RMSE [output unit].
        check: the model check of the stretch's residual; an output whose fit % is negative
            fails it (reason given), whatever the residual tests say.
        simulated: the twin's outputs (N, n_out); measured: the measured ones.
        t: time stamps (N,).
        inputs: the model's exogenous inputs on the stretch, name -> (N,).
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
    inputs: dict[str, FloatArray] = field(default_factory=dict)

    @property
    def worse_than_mean(self) -> list[str]:
        """Outputs fitted worse than their mean (negative fit %)."""
        return [o for o, f in self.fit_pct.items() if not f >= 0]


@dataclass
class Combination:
    """A combination of relative parameter changes: ``sum_i w_i d(ln p_i)``.

    Attributes:
        weights: parameter -> weight w_i, the largest |w_i| 1.
        std: 1-sigma of the combination (a relative change: 1.0 is 100 %).
    """

    weights: dict[str, float]
    std: float

    def label(self, cut: float = LABEL_CUT) -> str:
        """``a_adc - 0.41 Ra + 0.41 J``: the weights from the largest, those below ``cut``
        left out (relative changes: ``Ra + 0.8 Ke`` is a 1 % change of Ra with a 0.8 % one
        of Ke)."""
        parts: list[str] = []
        for name, w in sorted(self.weights.items(), key=lambda kv: -abs(kv[1])):
            if abs(w) < cut:
                continue
            mag = "" if abs(abs(w) - 1.0) < 5e-3 else f"{abs(w):.2g} "
            sign = "-" if w < 0 else "+"
            parts.append(f"{sign} {mag}{name}" if parts else
                         f"{'-' if w < 0 else ''}{mag}{name}")
        return " ".join(parts)


@dataclass
class Identifiability:
    """What the recording determines, at a least-squares optimum (ln-parameters).

    Attributes:
        names: the parameters analysed (free in that fit), in ``estimate`` order.
        information: (n, n) information matrix of the ln-parameters (the initial state
            profiled out; zero rows for the parameters in an exact null direction).
        eigenvalues: its eigenvalues, ascending (n,).
        rank: the Jacobian's numerical rank over the parameters: n less the exact null
            directions (:data:`NULL_TOL`).
        determined_rank: combinations the data determine to within ``max_rel_std``.
        condition: largest over smallest eigenvalue (inf when singular).
        rel_std: parameter -> relative standard error (1 sigma), the others free.
        correlation: (n, n) correlation matrix.
        strong_pairs: (a, b, rho) with |rho| >= the configured threshold, strongest first.
        undetermined: the combinations whose 1-sigma exceeds ``max_rel_std``, weakest first.
        at_bound: parameter -> ``"lower"`` or ``"upper"``: left at a bound by the search.
        max_rel_std: the threshold used.
    """

    names: list[str]
    information: FloatArray
    eigenvalues: FloatArray
    rank: int
    determined_rank: int
    condition: float
    rel_std: dict[str, float]
    correlation: FloatArray
    strong_pairs: list[tuple[str, str, float]]
    undetermined: list[Combination]
    at_bound: dict[str, str]
    max_rel_std: float


@dataclass
class HeldParameter:
    """A parameter the recording does not determine, held at a stated value in the re-fit.

    Attributes:
        value: the value held [SI].
        source: ``[identify.fixed]``, ``[machine.parameters]`` or ``best fit`` (no stated
            value: the full fit's, which the data do not support).
        stated: what the source says about the value (the configured reason).
        why: why the parameter is not determined (the combination it is in, its 1-sigma;
            or the bound it sits at).
        full_value: the value the fit with every parameter free gave.
        rel_std: the stated value's relative 1-sigma (``[identify.fixed]``), propagated to
            the re-fitted parameters; 0 for a value taken as exact.
    """

    value: float
    source: str
    stated: str
    why: str
    full_value: float
    rel_std: float = 0.0


@dataclass
class InformationCriteria:
    """Akaike's and the Bayesian information criterion of a fit on its training residual
    (MATLAB ``aic``: ``N ln det(E^T E / N) + 2 n_p + N n_y (ln 2 pi + 1)``; BIC with
    ``n_p ln N`` for ``2 n_p``), E the residual (N, n_y) in the outputs' units.

    Attributes:
        aic, bic: the criteria (lower is better; only differences between structures on the
            same data mean anything).
        samples: N; parameters: n_p (estimated parameters and initial-state offsets).
    """

    aic: float
    bic: float
    samples: int
    parameters: int


@dataclass
class FullFit:
    """The fit with every parameter of ``estimate`` free.

    Attributes:
        values: every model parameter -> value [SI].
        rel_std: estimated parameter -> relative standard error (1 sigma, all free).
        train, validation: its scores.
        nrmse: training fitness.
        criteria: AIC and BIC on the training residual.
    """

    values: dict[str, float]
    rel_std: dict[str, float]
    train: StretchScore
    validation: StretchScore
    nrmse: float
    criteria: InformationCriteria


@dataclass
class Identification:
    """The result of :func:`identify`.

    Attributes:
        values: every model parameter -> value [SI]: the determined ones as re-fitted, the
            held ones at their held value, the others as configured.
        rel_std: free parameter -> relative standard error (1 sigma), given the held values
            (the determined ones within ``max_rel_std``).
        bounds: estimated parameter -> the [low, high] the search used [SI].
        estimated: the parameters identify was asked for (``estimate``), in order.
        determined: those the recording determines (each within ``max_rel_std``).
        held: parameters held in the re-fit -> the value, its source and why.
        undetermined: parameters left free but not determined (nobody stated a value of
            any parameter of their weak combination) -> why; never pasted.
        tied: tied parameter -> its source.
        train, validation: the scores of the fit with the held values (what is pasted).
        full: the fit with every estimated parameter free, and its scores.
        identifiability: the analysis at the full fit.
        max_rel_std: the threshold (``[identify] max_rel_std``).
        structure: the candidate's name (``as configured`` for the configured options);
            options: its model options over ``[machine.options]``.
        elapsed_s: wall time [s]; evaluations: twin simulations of one parameter vector.
        units: parameter -> unit; output_units: output -> unit.
        nrmse: the training fitness of the fit with the held values.
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
    determined: list[str] = field(default_factory=list)
    held: dict[str, HeldParameter] = field(default_factory=dict)
    undetermined: dict[str, str] = field(default_factory=dict)
    full: FullFit | None = None
    identifiability: Identifiability | None = None
    max_rel_std: float = 0.1
    structure: str = AS_CONFIGURED
    options: dict[str, Any] = field(default_factory=dict)
    units: dict[str, str] = field(default_factory=dict)
    output_units: dict[str, str] = field(default_factory=dict)
    nrmse: float = math.nan
    starts: list[float] = field(default_factory=list)

    @property
    def pasted(self) -> list[str]:
        """The parameters :func:`parameters_block` pastes: the determined ones, none when the
        validation range fails the model check (a twin that does not describe the machine
        gives biased values)."""
        return list(self.determined) if self.validation.check.passed else []

    @property
    def at_bound(self) -> dict[str, str]:
        """Parameters the full fit left at a bound -> ``lower``/``upper``."""
        return self.identifiability.at_bound if self.identifiability else {}


def fit_percent(measured: FloatArray, simulated: FloatArray) -> float:
    """``100 (1 - ||y - y_hat|| / ||y - mean(y)||)`` of one output (shapes (N,)); -inf for a
    constant measurement."""
    den = float(np.linalg.norm(measured - np.mean(measured)))
    if den == 0 or not np.all(np.isfinite(simulated)):
        return -math.inf
    return 100.0 * (1.0 - float(np.linalg.norm(measured - simulated)) / den)


def information_criteria(measured: FloatArray, simulated: FloatArray, n_params: int
                         ) -> InformationCriteria:
    """AIC and BIC of a fit (:class:`InformationCriteria`) from the measured and simulated
    outputs (N, n_y) (the first sample, the initial state, left out)."""
    e = np.asarray(simulated[1:] - measured[1:], dtype=float)
    n, ny = e.shape
    with np.errstate(all="ignore"):
        sign, logdet = np.linalg.slogdet(e.T @ e / max(n, 1))
    if not (sign > 0 and math.isfinite(logdet)):
        logdet = -math.inf if np.all(np.isfinite(e)) else math.inf
    const = n * ny * (math.log(2 * math.pi) + 1.0)
    base = n * logdet + const
    return InformationCriteria(aic=base + 2.0 * n_params, bic=base + n_params * math.log(n),
                               samples=n, parameters=n_params)


def _honest_check(check: ModelCheck, fit_pct: Mapping[str, float]) -> ModelCheck:
    """The model check with every output fitted worse than its mean failed (reason given)."""
    bad = [o for o, f in fit_pct.items() if not f >= 0]
    if not bad:
        return check
    outputs = dict(check.outputs)
    reasons = list(check.reasons)
    for o in bad:
        oc = outputs.get(o)
        if oc is not None:
            outputs[o] = OutputCheck(oc.rms, oc.noise, oc.whiteness_p, oc.cross_p, False)
        reasons.append(f"{o} fitted worse than its mean (fit {fit_pct[o]:.1f} %): the twin "
                       "does not explain its variation")
    return ModelCheck(passed=False, reasons=reasons, outputs=outputs, widen=check.widen)


def _score(model: TwinModel, est: Estimator, window: WindowData, theta: FloatArray,
           weights: Mapping[str, float], initial: FloatArray | None,
           explained: FloatArray | None = None, explained_dof: FloatArray | None = None
           ) -> StretchScore:
    """The twin with parameters ``theta`` on a stretch; ``initial`` None: the initial-state
    offsets are estimated on the stretch with the parameters held (MATLAB ``compare``'s
    default: a noisy first sample must not count as model error); ``explained``,
    ``explained_dof``: the model check's (:meth:`Estimator.check`)."""
    fit = WindowFit(model, window, weights)
    if initial is None and est.config.initial_state and model.initial_states:
        pmap = est.pmap
        local = LocalFit(fit, pmap, theta, np.log(est.lower), np.log(est.upper), None,
                         initial=True)
        v, _, _ = local.refine(local.start(pmap.ln(theta)), local.nuisance)
        initial = local.initial(v)
    fit.initial = initial
    y = fit.simulate(theta[None, :])[0]
    names = model.output_names
    fit_pct = {o: fit_percent(fit.meas[1:, j], y[1:, j]) for j, o in enumerate(names)}
    check = _honest_check(est.check(fit, y, explained, explained_dof=explained_dof), fit_pct)
    return StretchScore(
        start=float(window.t[0]), end=float(window.t[-1]), samples=window.n,
        fit_pct=fit_pct,
        rmse={o: float(np.sqrt(np.mean((y[1:, j] - fit.meas[1:, j]) ** 2)))
              for j, o in enumerate(names)},
        check=check, t=np.asarray(window.t), measured=fit.meas, simulated=y,
        inputs={c: np.asarray(window[c]) for c in model.exogenous if c in window.channels})


def analyse(names: Sequence[str], cov: FloatArray, values: Mapping[str, float],
            bounds: Mapping[str, tuple[float, float]], max_rel_std: float,
            strong: float = 0.9, null: FloatArray | None = None) -> Identifiability:
    """Identifiability at an optimum from the covariance of the ln-parameters.

    Args:
        names: the free parameters (n), the covariance's order.
        cov: (n, n) covariance of their logarithms (``inf`` rows: not determined at all).
        values: parameter -> value at the optimum [SI].
        bounds: parameter -> [low, high] searched [SI].
        max_rel_std: the 1-sigma (relative) a determined combination may have.
        strong: |correlation| from which a pair is listed.
        null: (n, q) directions the outputs do not respond to at all
            (:func:`least_squares_covariance`), each an undetermined combination of infinite
            1-sigma.
    """
    n = len(names)
    names = list(names)
    null = np.zeros((n, 0)) if null is None else np.asarray(null)[:n]
    finite = np.isfinite(np.diag(cov)) if n else np.zeros(0, dtype=bool)
    c = np.where(np.isfinite(cov), cov, 0.0)
    d = np.diag(c).copy()
    d[~finite] = np.inf
    sd = np.sqrt(np.maximum(d, 0.0))
    undetermined = _null_combinations(names, null)
    # the determined block: eigen-decomposition of its covariance (the largest variances are
    # the information matrix's smallest eigenvalues, the same eigenvectors)
    blk = c[np.ix_(finite, finite)]
    w, vecs = np.linalg.eigh(blk) if finite.any() else (np.zeros(0), np.zeros((0, 0)))
    w = np.maximum(w, 1e-300)
    info = np.zeros((n, n))
    if finite.any():
        info[np.ix_(finite, finite)] = vecs @ np.diag(1.0 / w) @ vecs.T
    # every parameter in an exact null direction has no information of its own (a zero row)
    eig = np.sort(np.concatenate([np.zeros(n - int(finite.sum())), 1.0 / w]))
    q = sum(1 for comb in undetermined if math.isinf(comb.std))
    top = float(eig.max()) if eig.size else 0.0
    small = float(eig.min()) if eig.size else 0.0
    fin_names = [nm for nm, f in zip(names, finite, strict=True) if f]
    weak = _weak_combinations(fin_names, w, vecs, max_rel_std)
    undetermined += weak
    undetermined.sort(key=lambda comb: -comb.std)
    corr = _correlation(c, sd, finite)
    return Identifiability(
        names=names, information=info, eigenvalues=eig,
        rank=n - q,  # the Jacobian's numerical rank over the parameters
        determined_rank=w.size - len(weak),
        condition=top / small if small > 0 and q == 0 else math.inf,
        rel_std={nm: float(s) for nm, s in zip(names, sd, strict=True)},
        correlation=corr, strong_pairs=_strong_pairs(names, corr, strong),
        undetermined=undetermined, at_bound=_at_bound(names, values, bounds),
        max_rel_std=max_rel_std)


def _at_bound(names: Sequence[str], values: Mapping[str, float],
              bounds: Mapping[str, tuple[float, float]]) -> dict[str, str]:
    """The parameters the search left at a bound (within :data:`AT_BOUND` in ln): name ->
    ``"lower"`` or ``"upper"``."""
    at_bound = {}
    for name in names:
        lo, hi = bounds[name]
        v = values[name]
        if abs(math.log(v / lo)) < AT_BOUND:
            at_bound[name] = "lower"
        elif abs(math.log(hi / v)) < AT_BOUND:
            at_bound[name] = "upper"
    return at_bound


def _null_combinations(names: Sequence[str], null: FloatArray) -> list[Combination]:
    """Each exact null direction (a column of ``null`` (n, q)) as a combination of infinite
    1-sigma: its largest component +1, components below :data:`NULL_COMPONENT` left out."""
    out: list[Combination] = []
    for k in range(null.shape[1]):
        vec = null[:, k]
        if vec.size and float(np.max(np.abs(vec))) > 0:
            out.append(_combination(names, vec, math.inf, NULL_COMPONENT))
    return out


def _weak_combinations(names: Sequence[str], w: FloatArray, vecs: FloatArray,
                       max_rel_std: float) -> list[Combination]:
    """The eigen-directions of the determined block's covariance (variances ``w`` (k,),
    vectors ``vecs`` (k, k) over ``names``) whose 1-sigma, the largest component +1, exceeds
    ``max_rel_std``, in eigenvalue order; the others are determined."""
    out: list[Combination] = []
    for k in range(w.size):
        vec = vecs[:, k]
        m = float(np.max(np.abs(vec)))
        std = math.sqrt(w[k]) / m if m > 0 else math.inf
        if std <= max_rel_std:
            continue
        out.append(_combination(names, vec, std))
    return out


def _combination(names: Sequence[str], vec: FloatArray, std: float,
                 cut: float = -1.0) -> Combination:
    """The direction ``vec`` (n,) over ``names`` scaled so that its largest component is +1,
    components of magnitude ``cut`` or less left out."""
    m = float(np.max(np.abs(vec)))
    sign = 1.0 if vec[int(np.argmax(np.abs(vec)))] > 0 else -1.0
    return Combination({nm: float(sign * x / m) for nm, x in zip(names, vec, strict=True)
                        if abs(x) > cut}, std)


def _correlation(c: FloatArray, sd: FloatArray, finite: BoolArray) -> FloatArray:
    """The correlation matrix of the covariance ``c`` (n, n) with standard deviations ``sd``
    (n,); ``nan`` rows and columns for the parameters not ``finite`` (not determined)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        corr: FloatArray = c / np.outer(np.where(sd > 0, sd, 1.0), np.where(sd > 0, sd, 1.0))
    corr[~finite, :] = np.nan
    corr[:, ~finite] = np.nan
    return corr


def _strong_pairs(names: Sequence[str], corr: FloatArray,
                  strong: float) -> list[tuple[str, str, float]]:
    """The pairs whose |correlation| is ``strong`` or more, strongest first."""
    pairs = [(names[i], names[j], float(corr[i, j]))
             for i, j in itertools.combinations(range(len(names)), 2)
             if math.isfinite(corr[i, j]) and abs(corr[i, j]) >= strong]
    return sorted(pairs, key=lambda p: -abs(p[2]))


#: Singular values of the column-scaled Jacobian below this fraction of the largest are
#: exact null directions: a forward difference of 1e-6 in ln p carries the simulation's
#: round-off at about 1e-6 of a column, so no finer direction is real.
NULL_TOL = 1e-5
#: A parameter whose component in an exact null direction exceeds this is not determined
#: at all (infinite variance).
NULL_COMPONENT = 1e-3


def least_squares_covariance(jac: FloatArray, r: FloatArray, n_out: int, floor: float
                             ) -> tuple[FloatArray, FloatArray]:
    """The least-squares covariance of the search variables at an optimum, in the sandwich
    form ``A^+ (J^T W J) A^+`` (``A = J^T J``; W each output's residual variance:
    :func:`~twinwatch.twin.estimation.fit.residual_variances`, as the monitoring), on the
    Jacobian's numerical range: directions the outputs do not respond to at all (singular
    values below :data:`NULL_TOL` of the largest, columns equilibrated) are returned apart,
    and every variable with a component in them gets an infinite variance (a pseudo-inverse
    would spread their enormous variance over the others).

    Args:
        jac: (M, n) Jacobian of the normalised residuals.
        r: (M,) residuals, ``n_out`` outputs interleaved.
        n_out: outputs.
        floor: smallest normalised residual level.

    Returns:
        (covariance (n, n) with ``inf`` rows/columns for the undetermined variables,
        null directions (n, q) as unit vectors of the variables).
    """
    m, n = jac.shape
    if n == 0:
        return np.zeros((0, 0)), np.zeros((0, 0))
    var = residual_variances(r, n_out, floor, n)
    norms = np.linalg.norm(jac, axis=0)
    safe = np.where(norms > 0, norms, 1.0)
    js = jac / safe
    u, sv, vt = np.linalg.svd(js, full_matrices=False)
    top = float(sv.max()) if sv.size else 0.0
    keep = sv > NULL_TOL * top if top > 0 else np.zeros(sv.size, dtype=bool)
    ur, sr, vr = u[:, keep], sv[keep], vt[keep].T
    meat = (ur * var[:, None]).T @ ur
    cov = (vr @ (meat / np.outer(sr, sr)) @ vr.T) / np.outer(safe, safe)
    # the null space over the scaled variables, completed to n dimensions
    _, _, vfull = np.linalg.svd(js, full_matrices=True)
    null_s = vfull[int(keep.sum()):].T
    dead = norms == 0
    if null_s.size:
        dead |= np.any(np.abs(null_s) > NULL_COMPONENT, axis=1)
    cov[dead, :] = np.inf
    cov[:, dead] = np.inf
    null = null_s / safe[:, None]
    null = null / np.maximum(np.linalg.norm(null, axis=0), 1e-300)
    return cov, null


class _Problem:
    """The training problem of :func:`identify`: the fit on the training stretch, the
    parameter map, the local polish over any subset of the estimated parameters, and the
    analysis and the scores at a search vector."""

    def __init__(self, model: TwinModel, est: Estimator, config: IdentifyConfig,
                 stretches: tuple[WindowData, WindowData]) -> None:
        cfg = est.config
        self.model = model
        self.est = est
        self.config = config
        self.stretches = stretches
        self.names = list(cfg.estimate or [])
        self.n_est = len(self.names)
        self.fit = WindowFit(model, stretches[0], config.weights)
        self.pmap: ParameterMap = est.pmap
        self.base = est.trusted.copy()
        self.xl, self.xu = np.log(est.lower), np.log(est.upper)
        self.bounds = {n: (float(lo), float(hi)) for n, lo, hi in
                       zip(self.names, est.lower, est.upper, strict=True)}
        self.local = LocalFit(self.fit, self.pmap, self.base, self.xl, self.xu, None,
                              initial=cfg.initial_state and bool(model.initial_states))
        self.floor = cfg.model_error

    def polish(self, v: FloatArray, free: Sequence[int], rounds: int = 2
               ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Least-squares polish of the ``free`` ln-parameters (and the initial state) from
        ``v``; returns (v, residuals, Jacobian over ``free`` then the initial state)."""
        active = np.concatenate([np.asarray(free, dtype=int),
                                 np.arange(self.n_est, self.n_est + self.local.n_init)])
        r = jac = np.zeros(0)
        for _ in range(rounds):
            v, r, jac = self.local.refine(v, active)
        return v, r, jac

    def covariance(self, r: FloatArray, jac: FloatArray, k: int,
                   v: FloatArray | None = None, held: Mapping[int, float] | None = None
                   ) -> tuple[FloatArray, FloatArray]:
        """Covariance of the first ``k`` search variables of ``jac``'s columns (the free
        ln-parameters; the initial-state offsets after them marginalised) at residuals ``r``
        (:func:`least_squares_covariance`), and the exact null directions over them.

        ``held``: position of a held ln-parameter in ``v`` -> the 1-sigma of its stated value
        (relative); each moves the free ones as the least-squares optimum follows it
        (``S = -(J^T J)^-1 J^T J_h``), which adds ``S diag(sigma^2) S^T``.
        """
        cov, null = least_squares_covariance(jac, r, self.fit.n_out, self.floor)
        held = {i: sd for i, sd in (held or {}).items() if sd > 0}
        if held and v is not None and jac.shape[1]:
            cols = np.array(sorted(held), dtype=int)
            jh = self.local.jacobian(v, cols, r)
            sens = -np.linalg.lstsq(jac, jh, rcond=None)[0]
            sig = np.array([held[i] for i in cols])
            with np.errstate(invalid="ignore"):
                cov = cov + (sens * sig**2) @ sens.T
        return cov[:k, :k], null[:k]

    def theta(self, v: FloatArray) -> FloatArray:
        out: FloatArray = self.pmap.full(v[None, :self.n_est], self.base)[0]
        return out

    def analyse(self, v: FloatArray, r: FloatArray, jac: FloatArray, free: Sequence[int],
                held: Mapping[int, float] | None = None
                ) -> tuple[FloatArray, dict[str, float], Identifiability]:
        """The parameters at ``v`` (``theta``; name -> value) and what the data determine of
        the ``free`` ones there (:func:`analyse`; ``r``, ``jac``, ``held``: :meth:`covariance`)."""
        theta = self.theta(v)
        values = dict(zip(self.model.parameter_names, (float(x) for x in theta), strict=True))
        cov, null = self.covariance(r, jac, len(free), v, held)
        return theta, values, analyse([self.names[i] for i in free], cov, values, self.bounds,
                                      self.config.max_rel_std, self.config.correlation, null)

    def scores(self, theta: FloatArray, v: FloatArray, r: FloatArray, jac: FloatArray
               ) -> tuple[StretchScore, StretchScore]:
        """The twin with ``theta`` on the training stretch (from ``v``'s initial state) and
        on the validation stretch; ``r``, ``jac``: the fit's residuals and Jacobian."""
        # per output, the residual RMS the noise's effect on the estimates explains (as the
        # monitoring's model check: a noise-free output carries the others' noise's trace)
        n_out = self.fit.n_out
        white = noise_level(r.reshape(-1, n_out)) * math.sqrt(r.size)
        cov = parameter_covariance(jac, r, n_out, self.floor, white)
        spread = explained_rms(jac, cov, n_out), explained_dof(jac, cov, n_out)
        train, validation = self.stretches
        weights = self.config.weights
        return (_score(self.model, self.est, train, theta, weights, self.local.initial(v),
                       *spread),
                _score(self.model, self.est, validation, theta, weights, None, *spread))


def identify(model: TwinModel, estimation: EstimationConfig, config: IdentifyConfig,
             train: WindowData, validation: WindowData,
             nominal: Mapping[str, float] | None = None, *,
             start: Mapping[str, float] | None = None, structure: str = AS_CONFIGURED,
             options: Mapping[str, Any] | None = None) -> Identification:
    """Identify the estimated parameters on ``train``, say which the recording determines,
    re-fit with the others held at stated values, and score both fits on ``validation``
    (see the module docstring; the steps: :func:`_check_stretches`, :func:`_search`,
    :func:`_full_fit`, :func:`_hold_and_refit`).

    Args:
        model: the twin (its structure and options as configured).
        estimation: the ``[estimation]`` table: which parameters, their bounds, ties, the
            ``model_error`` floor and the validation settings (``config.estimate`` and
            ``config.bounds`` override the first two).
        config: the ``[identify]`` table (for this structure: :meth:`IdentifyConfig.
            for_structure`).
        train, validation: contiguous stretches of the recording, every channel the model
            needs, finite.
        nominal: the configured values [SI] of the parameters (starting point, the value of
            those not estimated, and the stated value of an undetermined one that
            ``[identify.fixed]`` does not state).
        start: parameter values [SI] to place as one more particle of every swarm (another
            structure's result: a warm start).
        structure, options: the structure's name and its options, for the report.

    Raises:
        ValueError: a stretch lacks a channel, holds non-finite values or is too short.
    """
    t_start = time.perf_counter()
    _check_stretches(model, train, validation)
    # a stated value of a parameter that is not identified is its value in the fit
    estimated = set(config.estimation(estimation).resolved(model).estimate or [])
    nominal = {**(nominal or {}), **{k: f.value for k, f in config.fixed.items()
                                     if k not in estimated}}
    est = Estimator(model, config.estimation(estimation), nominal)
    prob = _Problem(model, est, config, (train, validation))
    best, reached = _search(prob, start, structure)
    full, analysis = _full_fit(prob, best)
    holds = _Holds(prob.names, prob.bounds, config, dict(nominal), full.values, best[1].copy(),
                   list(range(prob.n_est)))
    r, jac = _hold_and_refit(prob, holds, analysis, best[2], best[3])
    theta, values, final = prob.analyse(holds.v, r, jac, holds.free, holds.rel_sd())
    sub = final.names
    determined = [n for n in sub if final.rel_std[n] <= config.max_rel_std]
    undetermined = {n: _unresolved(n, final) for n in sub if n not in determined}
    train_score, validation_score = prob.scores(theta, holds.v, r, jac)
    return Identification(
        values=values,
        rel_std={n: final.rel_std[n] for n in sub},
        bounds=prob.bounds,
        estimated=prob.names,
        tied=dict(est.config.tie or {}),
        train=train_score,
        validation=validation_score,
        elapsed_s=time.perf_counter() - t_start,
        evaluations=prob.fit.evaluations,
        determined=determined,
        held=holds.held,
        undetermined=undetermined,
        full=full,
        identifiability=analysis,
        max_rel_std=config.max_rel_std,
        structure=structure,
        options=dict(options or {}),
        nrmse=float(np.linalg.norm(r)),
        starts=reached,
        units={p.name: p.unit for p in model.parameters},
        output_units={o.name: o.unit for o in model.outputs},
    )


def _check_stretches(model: TwinModel, train: WindowData, validation: WindowData) -> None:
    """:func:`identify`'s first step; ValueError naming the stretch and what it lacks."""
    for w, what in ((train, "training"), (validation, "validation")):
        if w.n < 10:
            raise ValueError(f"the {what} range holds {w.n} samples: too few to identify "
                             "from (widen [identify] train / validate)")
        for ch in model.required_channels():
            if ch not in w.channels:
                raise ValueError(f"the recording has no channel {ch!r} ({what} range)")
            if not np.all(np.isfinite(w.channels[ch])):
                raise ValueError(f"channel {ch!r} holds NaN or inf in the {what} range")


#: The best training fit of :func:`_search`: (sum of squared residuals, search vector (n_est +
#: n_init,), residuals (M,), Jacobian (M, n_est + n_init)).
_Best = tuple[float, FloatArray, FloatArray, FloatArray]


def _search(prob: _Problem, start: Mapping[str, float] | None, structure: str
            ) -> tuple[_Best, list[float]]:
    """:func:`identify`'s search over every estimated parameter: ``config.starts`` swarms of
    their own (the configured values, and ``start`` when given, particles of each), each
    followed by the local polish; the time budget shared out over the starts left.

    Returns:
        The best polished fit of all starts, and each start's polished nRMSE.
    """
    fit, config, parameter_names = prob.fit, prob.config, prob.model.parameter_names
    rng = np.random.default_rng(config.seed)

    def cost(q: FloatArray) -> FloatArray:
        return fit.cost(prob.pmap.full(q, prob.base))

    q0 = np.clip(prob.pmap.ln(prob.base), prob.xl, prob.xu)
    seeds = [q0]
    if start:
        alt = prob.base.copy()
        for name, value in start.items():
            if name in parameter_names and value > 0:
                alt[list(parameter_names).index(name)] = value
        seeds.append(np.clip(prob.pmap.ln(alt), prob.xl, prob.xu))
    seed_rows = np.array(seeds)
    seed_cost = fit.cost(prob.pmap.full(seed_rows, prob.base))
    best_seed = seed_rows[int(np.argmin(seed_cost))]
    cost0 = float(np.min(seed_cost))
    best: _Best | None = None
    reached: list[float] = []
    t_global = time.perf_counter()
    every = list(range(prob.n_est))
    for k in range(config.starts):
        left = config.time_budget - (time.perf_counter() - t_global)
        sw = pso_minimize(cost, prob.xl, prob.xu, config.pso, rng=rng,
                          time_budget=max(left / (config.starts - k), 1e-3),
                          seeds=seed_rows)
        q_best = sw.x if sw.cost <= cost0 else best_seed
        # two polishes: the long free-run problem is stiffer than a window's
        v, r, jac = prob.polish(prob.local.start(q_best), every)
        sse = float(r @ r)
        logger.info("identify %s, start %d/%d: PSO %d generations, cost %.6g; polished "
                    "%.6g", structure, k + 1, config.starts, sw.generations, sw.cost,
                    math.sqrt(sse))
        reached.append(math.sqrt(sse))
        if best is None or sse < best[0]:
            best = (sse, v, r, jac)
    assert best is not None  # IdentifyConfig.starts >= 1
    return best, reached


def _full_fit(prob: _Problem, best: _Best) -> tuple[FullFit, Identifiability]:
    """:func:`identify`'s fit of every estimated parameter (``best``, from :func:`_search`)
    scored on both stretches, and what the recording determines of it (:func:`analyse`)."""
    sse, v, r, jac = best
    theta, values, analysis = prob.analyse(v, r, jac, range(prob.n_est))
    train, validation = prob.scores(theta, v, r, jac)
    full = FullFit(
        values=values, rel_std=dict(analysis.rel_std), train=train, validation=validation,
        nrmse=math.sqrt(sse),
        criteria=information_criteria(train.measured, train.simulated,
                                      prob.n_est + prob.local.n_init))
    return full, analysis


@dataclass
class _Holds:
    """The estimated parameters :func:`identify` holds, and the search vector they are held
    in (:func:`_hold_and_refit`).

    Attributes:
        names: the estimated parameters, in the search vector's order.
        bounds: each one's search range [SI].
        config: the ``[identify]`` table (its ``fixed`` values, stated first).
        configured: the configured values [SI] (stated when ``[identify.fixed]`` does not).
        full_values: the full fit's values [SI] (reported beside a held one).
        v: the search vector (ln-parameters, then the initial state); a held parameter's
            entry is its held value's logarithm.
        free: the positions in ``names`` not held, in order.
        held: the held parameters, in the order they were held.
    """

    names: list[str]
    bounds: Mapping[str, tuple[float, float]]
    config: IdentifyConfig
    configured: dict[str, float]
    full_values: Mapping[str, float]
    v: FloatArray
    free: list[int]
    held: dict[str, HeldParameter] = field(default_factory=dict)

    def stated(self, name: str) -> tuple[float, str, str] | None:
        """The value a person stated for ``name`` [SI], where, and why; None when nobody
        did."""
        if name in self.config.fixed:
            f = self.config.fixed[name]
            return f.value, "[identify.fixed]", f.reason
        if name in self.configured:
            return float(self.configured[name]), "[machine.parameters]", "the configured value"
        return None

    def hold(self, i: int, why: str, at: float | None = None) -> None:
        """Hold the ``i``-th estimated parameter at ``at`` (where the search left it, at a
        bound), else at its stated value (clipped to its bounds)."""
        name = self.names[i]
        lo, hi = self.bounds[name]
        sd = 0.0
        if at is not None:
            value, source, note = at, "bound", "where the search left it"
        else:
            found = self.stated(name)
            assert found is not None  # only a parameter with a stated value is held there
            value, source, note = found
            if source == "[identify.fixed]":
                sd = self.config.fixed[name].rel_std
        self.held[name] = HeldParameter(value=float(min(max(value, lo), hi)), source=source,
                                        stated=note, why=why, full_value=self.full_values[name],
                                        rel_std=sd)
        self.v[i] = math.log(self.held[name].value)
        self.free.remove(i)

    def rel_sd(self) -> dict[int, float]:
        """Position -> relative standard error of each held value that states one."""
        return {self.names.index(n): h.rel_std for n, h in self.held.items() if h.rel_std > 0}


def _hold_and_refit(prob: _Problem, holds: _Holds, analysis: Identifiability, r: FloatArray,
                    jac: FloatArray) -> tuple[FloatArray, FloatArray]:
    """:func:`identify`'s hold-and-re-fit: the parameters the full fit left at a bound held
    there; then, until every free one is determined or none can be held, the weakest
    combination's main parameter with a stated value held at it (:func:`_weakest_stated`) and
    the rest re-fitted (a re-fit that pushes one to a bound holds it there too). ``holds`` is
    updated in place; returns the last re-fit's residuals and Jacobian (the full fit's
    ``r``, ``jac`` when nothing was held).
    """
    config, names_est, bounds = holds.config, holds.names, holds.bounds
    for name, side in analysis.at_bound.items():
        i = names_est.index(name)
        holds.hold(i, f"at its {side} bound {bounds[name][0 if side == 'lower' else 1]:.4g}: "
                   "the data push it beyond the range searched (widen [identify] bounds, or "
                   "the structure does not describe it)", at=holds.full_values[name])
    changed = bool(holds.held)
    while holds.free:
        if changed:
            holds.v, r, jac = prob.polish(holds.v, holds.free)
            changed = False
        _, vals, a = prob.analyse(holds.v, r, jac, holds.free, holds.rel_sd())
        newly = [n for n in a.at_bound if n not in analysis.at_bound]
        if newly:
            for name in newly:
                holds.hold(names_est.index(name), f"the re-fit with the held values pushed "
                           f"it to its {a.at_bound[name]} bound", at=vals[name])
            changed = True
            continue
        if all(a.rel_std[n] <= config.max_rel_std for n in a.names):
            break
        choice = _weakest_stated(a, holds)
        if choice is None:
            break
        name, why = choice
        holds.hold(names_est.index(name), why)
        changed = True
    if changed:
        holds.v, r, jac = prob.polish(holds.v, holds.free)
    return r, jac


def _weakest_stated(a: Identifiability, holds: _Holds) -> tuple[str, str] | None:
    """The parameter to hold next and why: the weakest combination that a stated value can
    resolve, its main parameter with a stated value (``[identify.fixed]`` before the
    configured values, then the largest share, then the lowest priority); None when
    every undetermined combination is of parameters nobody stated (they stay free, and
    undetermined)."""
    names_est = holds.names
    for comb in a.undetermined:
        top = max(abs(w) for w in comb.weights.values())
        cands = [n for n, w in comb.weights.items()
                 if abs(w) >= HOLD_SHARE * top and holds.stated(n) is not None]
        if not cands:
            continue
        weights = comb.weights
        name = min(cands, key=lambda n: (
            0 if n in holds.config.fixed else 1, -abs(weights[n]), -names_est.index(n)))
        others = [n for n in comb.weights if n != name and abs(comb.weights[n]) >= LABEL_CUT]
        if others:
            return name, f"in {comb.label()} (+-{percent(comb.std)})"
        return name, f"the outputs barely respond to it (+-{percent(comb.std)} alone)"
    return None


def _unresolved(name: str, analysis: Identifiability) -> str:
    """Why a free parameter is not determined: the undetermined combination it weighs most
    in, and which parameters a stated value would resolve it with."""
    best: tuple[float, Combination] | None = None
    for comb in analysis.undetermined:
        top = max(abs(x) for x in comb.weights.values())
        share = abs(comb.weights.get(name, 0.0)) / top if top > 0 else 0.0
        if share >= LABEL_CUT and (best is None or share > best[0]):
            best = (share, comb)
    if best is None:
        return f"the outputs barely respond to it (above the {percent(analysis.max_rel_std)} " \
            "allowed)"
    comb = best[1]
    top = max(abs(x) for x in comb.weights.values())
    partners = [n for n, x in comb.weights.items() if abs(x) >= MAIN_SHARE * top]
    if name not in partners:
        partners.append(name)
    return (f"in {comb.label()} (+-{percent(comb.std)}); state a value of "
            f"{' or '.join(partners)} to determine it")


def percent(x: float) -> str:
    """A relative error as a percentage for reports: ``8.1 %``, ``118 %``, ``4e+06 %``."""
    if not math.isfinite(x):
        return "inf %"
    p = 100.0 * x
    return f"{p:.3g} %" if p < 1e3 else f"{p:.0f} %" if p < 1e5 else f"{p:.1e} %"


@dataclass
class Comparison:
    """Candidate structures ranked (:func:`compare_structures`).

    Attributes:
        results: every candidate's identification, in the order given.
        winner: index of the winner in ``results``.
        rule: how it was chosen, in words.
        criteria: each result's AIC/BIC as compared (on the outputs every structure has:
            a structure that adds an output, such as a closed loop's voltage, is scored on
            the same data as the others).
        outputs: those outputs.
    """

    results: list[Identification]
    winner: int
    rule: str
    criteria: list[InformationCriteria] = field(default_factory=list)
    outputs: list[str] = field(default_factory=list)

    @property
    def best(self) -> Identification:
        return self.results[self.winner]


def compare_structures(results: Sequence[Identification]) -> Comparison:
    """Rank candidate structures identified on the same recording.

    A structure that fits an output worse than its mean on the validation range is out; of
    the others, those whose validation residual passes the model check come first, and among
    them the lowest BIC on the training residual wins (the information criterion pays for
    every parameter; ties keep the order given, the configured structure first).

    Args:
        results: one :class:`Identification` per structure (its ``full`` fit is compared).

    Raises:
        ValueError: no results.
    """
    if not results:
        raise ValueError("no structure to compare")

    fulls = [r.full for r in results]
    if any(f is None for f in fulls):
        raise ValueError("a structure has no full fit to compare")
    names = [list(r.train.fit_pct) for r in results]
    common = [o for o in names[0] if all(o in n for n in names)]
    if not common:
        raise ValueError("the structures share no output to compare on")
    criteria = []
    for r, f in zip(results, fulls, strict=True):
        assert f is not None
        if list(r.train.fit_pct) == common:
            criteria.append(f.criteria)
            continue
        cols = [list(r.train.fit_pct).index(o) for o in common]
        criteria.append(information_criteria(f.train.measured[:, cols],
                                             f.train.simulated[:, cols],
                                             f.criteria.parameters))

    def key(k: int) -> tuple[int, int, float, int]:
        f = fulls[k]
        assert f is not None
        negative = 1 if f.validation.worse_than_mean else 0
        failed = 0 if f.validation.check.passed else 1
        bic = criteria[k].bic if math.isfinite(criteria[k].bic) else math.inf
        return negative, failed, bic, k

    winner = min(range(len(results)), key=key)
    rule = ("no output fitted worse than its mean on the validation range, then the "
            "validation model check passed, then the lowest BIC on the training residual"
            + ("" if all(n == common for n in names) else
               f" of the outputs all have ({', '.join(common)})"))
    return Comparison(list(results), winner, rule, criteria, common)


def parameters_block(result: Identification, source: str, *, nominal_header: str = ""
                     ) -> str:
    """The ``[machine.parameters]`` block to paste into a monitoring configuration: only the
    determined parameters (each with its interval); the held ones commented out with the
    reason; the bounds the search used; the structure's options when a candidate won.

    Args:
        result: the identification.
        source: what was identified from, for the header.
        nominal_header: one more header line.
    """
    fits = "; ".join(f"{o} {result.train.fit_pct[o]:.1f} training, "
                     f"{result.validation.fit_pct[o]:.1f} validation"
                     for o in result.train.fit_pct)
    lines = [f"# Identified by `twinwatch identify` from {source}",
             f"# training {result.train.start:g}-{result.train.end:g} s "
             f"({result.train.samples} samples), validation {result.validation.start:g}-"
             f"{result.validation.end:g} s ({result.validation.samples} samples)",
             f"# fit % (100 (1 - |y - y_hat| / |y - mean(y)|)): {fits}"]
    for what, score in (("training", result.train), ("validation", result.validation)):
        if not score.check.passed:
            lines.append(f"# model check ({what}) FAILED: " + "; ".join(score.check.reasons))
    if nominal_header:
        lines.append(f"# {nominal_header}")
    if result.structure != AS_CONFIGURED:
        lines.append(f"# structure: {result.structure}; in [machine.options] set:")
        for key, value in (result.options or {}).items():
            lines.append(f"#   {key} = {toml_value(value)}")
    pasted = result.pasted
    if not result.validation.check.passed:
        lines.append("# NOTHING TO PASTE: the twin fails the model check on the validation "
                     "range, so its values are biased by what it misses: fix the structure "
                     "([identify.candidates]), or accept that error ([estimation] model_error)")
    elif result.held or result.undetermined:
        lines.append(f"# Pasted: the parameters the recording determines within "
                     f"{percent(result.max_rel_std)} (1 sigma)"
                     + (", given the held values below." if result.held else "."))
    lines.append("[machine.parameters]")
    for name in result.determined:
        value = result.values[name]
        unit = result.units.get(name, "")
        note = f"{unit}, identified +- {percent(result.rel_std[name])} (1 sigma)"
        if name not in pasted:
            note += ", NOT PASTED: the model check failed"
        lines.append(("" if name in pasted else "# ") + f"{name} = {value:.6g}".ljust(24)
                     + f"# {note}")
    for dep, src in result.tied.items():
        if src in pasted:
            lines.append(f"{dep} = {result.values[dep]:.6g}".ljust(24)
                         + f"# {result.units.get(dep, '')}, tied to {src}")
    if result.held or result.undetermined:
        lines.append("# Not determined by this recording (not pasted):")
        for name, h in result.held.items():
            unit = result.units.get(name, "")
            lines.append(f"# {name} = {h.value:.6g}".ljust(24) + f"# {unit}, held "
                         f"({h.source}: {h.stated}); not determined: {h.why}")
        for name, why in result.undetermined.items():
            unit = result.units.get(name, "")
            lines.append(f"# {name} = {result.values[name]:.6g}".ljust(24)
                         + f"# {unit}, not determined (+-{percent(result.rel_std[name])}): {why}")
        for dep, src in result.tied.items():
            if src not in pasted:
                lines.append(f"# {dep} = {result.values[dep]:.6g}".ljust(24)
                             + f"# {result.units.get(dep, '')}, tied to {src} (not pasted)")
    lines.append("")
    lines.append("# The search range the identification used; for the monitoring's [estimation]:")
    lines.append("# bounds = { " + ", ".join(f"{n} = [{lo:.4g}, {hi:.4g}]"
                                             for n, (lo, hi) in result.bounds.items()) + " }")
    return "\n".join(lines) + "\n"


__all__ = ["Combination", "Comparison", "FullFit", "HeldParameter", "Identifiability",
           "Identification", "InformationCriteria", "StretchScore", "analyse",
           "compare_structures", "fit_percent", "identify", "information_criteria",
           "parameters_block", "percent"]
