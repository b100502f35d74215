"""Residual statistics shared by estimation, discovery and adaptation.

Every function here works on *normalised* residuals: the output errors of one window divided by
each output's scale (see :class:`~.fit.WindowFit`), either as a matrix ``(N, n_out)``
(one column per output) or as the flat vector ``(N*n_out,)`` the optimisers minimise, with the
outputs interleaved (``r.reshape(-1, n_out)`` gives the matrix back).

What is here: :func:`noise_level`, :func:`ar1` and :func:`long_run_factor` (how many samples
one independent piece of evidence is worth), :func:`delta_bic` (discovery's test), and the
residual tests of model validation, :func:`ljung_box` and :func:`cross_correlation_test`
(Ljung, *System Identification*, 2nd ed., Section 16.6; MATLAB ``resid``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def mean(x: FloatArray, axis: int | None = None) -> Any:
    """``np.mean(x, axis)`` of a float array: the same sum (``np.add.reduce``) divided by the
    same count, without ``np.mean``'s dispatch (most of its time on a window's arrays, called
    tens of times a window)."""
    return np.add.reduce(x, axis=axis) / (x.size if axis is None else x.shape[axis])


def norms(x: FloatArray, axis: int) -> FloatArray:
    """``np.linalg.norm(x, axis=axis)`` of a real 2-D array: the same
    ``sqrt(add.reduce(x * x, axis))`` without its dispatch."""
    out: FloatArray = np.sqrt(np.add.reduce(x * x, axis=axis))
    return out


def _matrix(r: FloatArray, n_out: int) -> FloatArray:
    a = np.asarray(r, dtype=float)
    return a.reshape(-1, n_out) if a.ndim == 1 else a


def noise_level(residual: FloatArray) -> FloatArray:
    """Per-output white-noise level from first differences.

    ``std(diff(e))/sqrt(2)`` is the standard deviation of white noise and nearly blind to a
    smooth (model-error) residual.

    Args:
        residual: shape (N, n_out).

    Returns:
        Shape (n_out,), in the residual's unit.
    """
    res = np.asarray(residual, dtype=float)
    d = res[1:] - res[:-1]  # np.diff(res, axis=0) without its dispatch
    out: FloatArray = np.sqrt(mean(d * d, axis=0) / 2.0)
    return out


#: Largest span of a window's readings, in steps, for :func:`quantum` to call them quantised:
#: above a 16-bit register's or converter's 65,536 codes, so every such reading is found;
#: a float32 signal (24-bit mantissa, e.g. a DBC's float) spans more and is taken as
#: continuous, its rounding (6e-8 of the value) far below any sensor's noise.
QUANTUM_MAX_STEPS = 1e5
#: How far a gap between two readings may be from a whole number of steps (share of a step):
#: float64's rounding of a grid value leaves at most 1e-16 x QUANTUM_MAX_STEPS = 1e-11 of a
#: step, while each gap of a continuous reading lands within it by chance with probability
#: 2e-3, so the 199 gaps of a 200-sample window all do with probability 2e-3 ** 199.
QUANTUM_TOLERANCE = 1e-3


def quantum(values: FloatArray) -> float:
    """The step of a reading that takes values on a grid only, in the reading's unit, or 0.

    A drive's current in per mille of its rated current, an ADC's count, an encoder's count
    per sample period: the reading is the quantity rounded to the grid, and the rounding
    error, up to half a step, is part of every residual a correct twin leaves. Where the
    quantity moves slowly against the step the error is not white (it follows the quantity
    between two levels), so the model check must not count it as model error.

    The step is the smallest gap between two distinct readings of the window when every gap
    is a whole multiple of it (within :data:`QUANTUM_TOLERANCE` of a step) and the readings
    span at most :data:`QUANTUM_MAX_STEPS` steps. A continuous reading fails that test (its
    gaps are not multiples of its smallest); a reading with a single value cannot be told.

    Args:
        values: one channel's readings in a window (N,), finite.

    Returns:
        The step (> 0); 0 when the readings are not on a grid; NaN when they hold a single
        value (on a grid or not: the window cannot tell).
    """
    v = np.sort(values)
    gaps = v[1:] - v[:-1]
    gaps = gaps[gaps > 0]
    if not gaps.size:
        return math.nan
    step = float(gaps.min())
    ratio = gaps / step
    span = float(ratio.sum())
    if not span <= QUANTUM_MAX_STEPS:
        return 0.0
    ratio -= np.rint(ratio)
    if float(np.abs(ratio).max()) > QUANTUM_TOLERANCE:
        return 0.0
    return step


def ar1(r: FloatArray, n_out: int) -> float:
    """Pooled lag-1 autocorrelation of residuals, clipped to [0, 0.99].

    Args:
        r: normalised residuals, (M,) interleaved or (N, n_out).
        n_out: number of outputs.
    """
    res = _matrix(r, n_out)
    den = float((res * res).sum())
    if den <= 0:
        return 0.0
    return min(max(float((res[1:] * res[:-1]).sum()) / den, 0.0), 0.99)


def autocorrelation(x: FloatArray, lags: int) -> FloatArray:
    """Sample autocorrelation ``rho[0..lags]`` of a series (not mean-removed: a residual's
    offset is model error too), ``rho[0] = 1``; zeros for an all-zero series."""
    x = np.asarray(x, dtype=float)
    n = x.size
    den = float(x.dot(x))
    out = np.zeros(lags + 1)
    if den <= 0:
        return out
    top = min(lags, n - 1) + 1
    out[:top] = [x[k:].dot(x[:n - k]) for k in range(top)]  # ddot, as @, without matmul's dispatch
    out[:top] /= den
    return out


def long_run_factor(r: FloatArray, n_out: int, lags: int | None = None) -> float:
    """Long-run over short-run variance of the residuals (>= 1).

    ``1 + 2 sum_k w_k rho_k`` with Bartlett weights ``w_k = 1 - k/(L+1)`` (the Newey-West
    estimator of the long-run variance, normalised), pooled over the outputs. White residuals
    give about 1; a residual that is one smooth excursion over the window gives up to about
    ``L``. The parameter covariance computed as if the residuals were white is multiplied by it.

    Args:
        r: normalised residuals, (M,) interleaved or (N, n_out).
        n_out: number of outputs.
        lags: L; default ``N // 4``.
    """
    res = _matrix(r, n_out)
    n = res.shape[0]
    if n < 4:
        return 1.0
    big_l = max(1, min(lags if lags is not None else n // 4, n - 1))
    den = float(np.sum(res * res))
    if den <= 0:
        return 1.0
    total = 0.0
    for k in range(1, big_l + 1):
        rho = float(np.sum(res[k:] * res[:-k])) / den
        total += (1.0 - k / (big_l + 1.0)) * rho
    return float(min(max(1.0 + 2.0 * total, 1.0), float(n)))


def delta_bic(r_base: FloatArray, r_new: FloatArray, k: int, n_out: int) -> float:
    """BIC(new) - BIC(base) for ``k`` extra parameters, with the sample size corrected for
    the new residuals' lag-1 autocorrelation (effective n = n (1 - rho)/(1 + rho)).

    Args:
        r_base, r_new: normalised residuals (M,), ``M = (N - 1)*n_out``.
        k: parameters the new model adds.
        n_out: outputs interleaved in the residual vectors.

    Returns:
        Negative when the new model is better; ``-inf`` for a perfect new fit.
    """
    rho = ar1(r_new, n_out)
    n_eff = max(r_new.size * (1.0 - rho) / (1.0 + rho), float(k + 2))
    rss0, rss1 = float(r_base @ r_base), float(r_new @ r_new)
    if rss1 <= 0:
        return -math.inf
    tiny = 1e-300
    return n_eff * math.log(max(rss1, tiny) / max(rss0, tiny)) + k * math.log(n_eff)


def _chi2_sf(x: float, dof: int) -> float:
    from scipy.special import chdtrc  # chi2.sf, without importing scipy.stats

    return float(chdtrc(dof, x))


def _uncertainty_quantile(dof: float, alpha: float) -> float:
    """The factor on ``explained^2`` of :func:`check_model`'s bound: the ``1 - alpha``
    quantile of a chi-square of ``dof`` degrees over its mean, at least 4 (the bound of many
    degrees: twice the RMS); 4 when ``dof`` is 0 (no uncertainty reaches the output)."""
    if not dof > 0.0:
        return 4.0
    from scipy.special import chdtri  # chi2.isf, without importing scipy.stats

    return max(4.0, float(chdtri(dof, alpha)) / dof)


def ljung_box(e: FloatArray, lags: int) -> tuple[float, float]:
    """Ljung-Box whiteness test of one residual series.

    ``Q = N (N + 2) sum_{k=1..m} rho_k^2 / (N - k)``, chi-square with m degrees of freedom
    for white residuals (Ljung, System Identification, eq. 16.63).

    Args:
        e: residual series (N,).
        lags: m.

    Returns:
        (Q, p-value); a small p-value means the residual is not white (the model misses
        dynamics, or the noise is coloured). An all-zero series gives (0, 1).
    """
    e = np.asarray(e, dtype=float)
    n = e.size
    m = max(1, min(lags, n - 2))
    rho = autocorrelation(e, m)
    if rho[0] == 0:
        return 0.0, 1.0
    k = np.arange(1, m + 1)
    q = float(n * (n + 2) * np.add.reduce(rho[1:] ** 2 / (n - k)))
    return q, _chi2_sf(q, m)


def cross_correlation_test(e: FloatArray, u: FloatArray, lags: int) -> tuple[float, float]:
    """Residual-input independence test (Ljung, System Identification, eq. 16.67; MATLAB
    ``resid``): the cross-correlations of the residual with the input at lags 0..m.

    ``S = N r^T R_u^-1 r``, with ``r_tau`` the normalised cross-covariance of ``e(t)`` and
    ``u(t - tau)`` (means removed) and ``R_u`` the input's autocorrelation matrix (so a slowly
    varying input, whose cross-correlations at neighbouring lags are not independent, is not
    counted m + 1 times); chi-square with m + 1 degrees of freedom when the residual is white
    and independent of the input.

    Args:
        e: residual series (N,).
        u: input series (N,) (an exogenous input: the set-point of a closed loop, the voltage
            of an open loop).
        lags: m.

    Returns:
        (S, p-value); (0, 1) when either series is constant.
    """
    return _cross_correlation(e, _input_correlation(u, lags))


def _input_correlation(u: FloatArray, lags: int
                       ) -> tuple[FloatArray, float, FloatArray, FloatArray]:
    """:func:`cross_correlation_test`'s part that depends on the input alone (the same for
    every output's residual): the input with its mean removed, its RMS, and the eigenvalues
    (k,) and eigenvectors (k, m + 1) of its autocorrelation matrix that are kept."""
    u = np.asarray(u, dtype=float)
    u = u - float(mean(u))
    n = u.size
    m = max(0, min(lags, n - 2))
    su = float(np.sqrt(u.dot(u) / n))
    if su == 0:
        return u, su, np.zeros(0), np.zeros((0, m + 1))
    ru = autocorrelation(u, m)
    toe = ru[np.abs(np.subtract.outer(np.arange(m + 1), np.arange(m + 1)))]
    # The input's correlation matrix is nearly singular for a step set-point; its pseudo-inverse
    # counts only the independent directions, and so do the degrees of freedom.
    w, v = np.linalg.eigh(toe)
    keep = w > 1e-6 * max(float(w.max()), 1e-300)
    return u, su, w[keep], v[:, keep].T


def _cross_correlation(e: FloatArray, prepared: tuple[FloatArray, float, FloatArray,
                                                      FloatArray]) -> tuple[float, float]:
    """:func:`cross_correlation_test` of ``e`` against the input :func:`_input_correlation`
    prepared."""
    u, su, w, vt = prepared
    e = np.asarray(e, dtype=float)
    e = e - float(mean(e))
    n = e.size
    m = vt.shape[1] - 1
    se = float(np.sqrt(e.dot(e) / n))
    if se == 0 or su == 0:
        return 0.0, 1.0
    r = np.array([e[k:].dot(u[:n - k]) for k in range(m + 1)]) / (n * se * su)
    proj = vt @ r
    s = float(n * np.add.reduce(proj**2 / w))
    return s, _chi2_sf(s, int(w.size))


__all__ = [
    "ModelCheck",
    "OutputCheck",
    "ar1",
    "autocorrelation",
    "check_model",
    "cross_correlation_test",
    "delta_bic",
    "ljung_box",
    "long_run_factor",
    "noise_level",
    "quantum",
]


@dataclass
class OutputCheck:
    """Model validation of one output's residual (normalised by the output's scale).

    Attributes:
        rms: residual RMS.
        noise: white-noise level (:func:`noise_level`).
        whiteness_p: Ljung-Box p-value (small: the residual is not white).
        cross_p: residual-input test p-value (small: the residual depends on the input), the
            smallest over the exogenous inputs; 1 without inputs.
        passed: the output's residual is white and independent of the inputs, or below the
            floor (numerical and accepted model error).
    """

    rms: float
    noise: float
    whiteness_p: float
    cross_p: float
    passed: bool


@dataclass
class ModelCheck:
    """Per-window model validation (Ljung, System Identification, ch. 16; MATLAB ``resid``).

    Attributes:
        passed: every output passed.
        reasons: why it failed, one line per failing output (empty when passed).
        outputs: output name -> its :class:`OutputCheck`.
        widen: factor the window's standard errors were multiplied by (1 when passed).
    """

    passed: bool
    reasons: list[str] = field(default_factory=list)
    outputs: dict[str, OutputCheck] = field(default_factory=dict)
    widen: float = 1.0


def check_model(res: FloatArray, names: tuple[str, ...], inputs: FloatArray | None, *,
                alpha: float, lags: int, floor: float,
                explained: FloatArray | None = None,
                quanta: FloatArray | None = None,
                explained_dof: FloatArray | None = None) -> ModelCheck:
    """Validate a twin on one window from its residuals.

    An output fails when its residual is not white (Ljung-Box) or depends on an exogenous
    input (cross-correlation test), each at level ``alpha``, and its RMS is material: above
    ``floor`` (the model and discretisation error accepted in noise-free data: below it,
    rounding and a parameter drifting within the window are not evidence against the model)
    and above twice what the white noise and the estimates' own uncertainty explain
    (``sqrt(noise^2 + explained^2)``: a noise-free output, such as a closed-loop drive's
    voltage, carries the smooth trace of the other outputs' noise on the estimates). The
    uncertainty's share is a chi-square of ``explained_dof`` degrees scaled to its mean, not a
    sum of many: where its ``1 - alpha`` quantile lies beyond four times the mean (one or two
    degrees: one direction of the estimates dominates that output), the bound is that
    quantile, ``rms^2 > 4 noise^2 + max(4, q) explained^2`` (:func:`_uncertainty_quantile`);
    else the rule is twice ``sqrt(noise^2 + explained^2)``. The noise
    is at least a quantised reading's rounding error, ``step / sqrt(12)`` (:func:`quantum`):
    a drive that reports its current in per mille of the rated current leaves a residual of
    that size that follows the current, not white, where the twin is right. A failing
    window's standard errors are widened by ``sqrt(L) * rms / sqrt(noise^2 + explained^2)``
    of its worst output: ``L`` the long-run variance factor of the structured residual.

    Args:
        res: normalised residuals (N, n_out).
        names: output names (n_out).
        inputs: exogenous inputs (N, n_u), or None.
        alpha: test level (e.g. 0.01).
        lags: lags of both tests (e.g. 20).
        floor: normalised RMS below which an output passes.
        explained: per output, the residual RMS the estimates' uncertainty explains
            (:func:`twinwatch.twin.estimation.fit.explained_rms`); None: 0.
        quanta: per output, the reading's step (:func:`quantum`) in the residual's unit
            (over the output's scale); None or 0: a continuous reading.
        explained_dof: per output, the degrees of freedom of ``explained``'s square
            (:func:`twinwatch.twin.estimation.fit.explained_dof`); None: many (the bound is
            twice ``sqrt(noise^2 + explained^2)``).

    Returns:
        The window's check.
    """
    res = np.asarray(res, dtype=float)
    n = res.shape[0]
    lvl = noise_level(res)
    exog = [] if inputs is None else [_input_correlation(inputs[:, col], lags)
                                      for col in range(inputs.shape[1])]
    check = ModelCheck(passed=True)
    widen = 1.0
    for j, name in enumerate(names):
        e = res[:, j]
        rms = float(np.sqrt(mean(e * e)))
        _, p_white = ljung_box(e, lags)
        p_cross = 1.0
        for prepared in exog:
            p_cross = min(p_cross, _cross_correlation(e, prepared)[1])
        noise = float(lvl[j])
        rounding = 0.0 if quanta is None else float(quanta[j]) / math.sqrt(12.0)
        rounded = rounding > noise  # the reading's step, not its noise, sets the level
        if rounded:
            noise = rounding
        spread = float(explained[j]) if explained is not None else 0.0
        expected = math.hypot(noise, spread)
        q = 4.0 if explained_dof is None else _uncertainty_quantile(float(explained_dof[j]),
                                                                     alpha)
        material = rms > floor and (rms > 2.0 * expected if q == 4.0 else
                                    rms * rms > 4.0 * noise * noise + q * spread * spread)
        ok = not material or (p_white >= alpha and p_cross >= alpha)
        check.outputs[name] = OutputCheck(rms, float(lvl[j]), p_white, p_cross, ok)
        if ok:
            continue
        check.passed = False
        what = []
        if p_white < alpha:
            what.append(f"not white (Ljung-Box p = {p_white:.2g})")
        if p_cross < alpha:
            what.append(f"correlated with the input (p = {p_cross:.2g})")
        by = ("the reading's step and the estimates' uncertainty" if rounded
              else "noise and the estimates' uncertainty")
        check.reasons.append(f"residual of {name} {' and '.join(what)}, RMS {rms:.2g} of "
                             f"its scale, {rms / max(expected, 1e-300):.3g} times what {by} "
                             "explain")
        big_l = long_run_factor(e, 1, lags=max(1, n // 4))
        widen = max(widen, math.sqrt(big_l) * max(1.0, rms / max(expected, floor)))
    check.widen = widen
    return check
