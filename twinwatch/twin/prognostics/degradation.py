"""Degradation models fitted to one parameter's evidence, and the choice among them.

A parameter's history (window times ``t`` [s], values ``y`` [SI] with their published 1-sigma
uncertainty ``s`` [SI]) is described by one of the models of MATLAB's Predictive Maintenance
Toolbox (``linearDegradationModel``, ``exponentialDegradationModel``), written so that they nest
and their parameters are what a planner reads, at the reference time ``t_ref`` (the latest
evidence, "now")::

    none          y(t) = c
    linear        y(t) = c + m * tau
    exponential   y(t) = c + m * (exp(r * tau) - 1) / r           tau = t - t_ref

``c`` is the level now [SI], ``m`` the drift rate now [SI/s], ``r`` the growth rate of the
drift [1/s] (the paper's degradation laws are exponentials with r = 0.003 /s; as r -> 0 the
exponential becomes the line). Each degrading model also has an *onset* ``t0``: flat before
it, ``tau = max(t, t0) - t_ref``. The onset is a parameter of the fit (not MATLAB's slope
test), so a flat-then-degrading history is one model, not a compromise between two.

**Fit.** Weighted least squares, weights ``1/s^2`` (the published uncertainty). For fixed
``(r, t0)`` the model is linear in ``(c, m)``: a grid over ``r * span`` and ``t0`` is solved in
closed form, then the best point is polished by a bounded Levenberg-Marquardt
(:mod:`~twinwatch.twin.prognostics._lm`). The
parameter covariance is ``(J^T W J)^-1`` scaled by the residuals: by the reduced chi-square when
the scatter exceeds the published uncertainty, and by the residuals' long-run variance factor
(Newey-West, :func:`~twinwatch.twin.estimation.statistics.long_run_factor`) when consecutive
windows' errors are correlated, so the interval is never narrower than the evidence supports.

**Choice** (:func:`select`). ``n_eff ln(chi^2 / n)`` plus a penalty, ``n_eff`` corrected for
the residuals' lag-1 autocorrelation as in
:func:`~twinwatch.twin.estimation.statistics.delta_bic`: the BIC (penalty ``k ln n_eff``)
decides whether the parameter degrades at all, the AICc (``2k + 2k(k+1)/(n_eff - k - 1)``)
which degradation model predicts it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt
from numba import njit

from twinwatch.twin.model import FloatArray
from twinwatch.twin.prognostics._lm import (
    fit_statistics,
    kalman_step,
    levenberg_marquardt,
    value_band,
    wls_grid,
)

__all__ = ["ModelKind", "DegradationFit", "bin_evidence", "fit_models", "long_run_factor",
           "pinv_sym", "refit_models", "select"]


def pinv_sym(a: FloatArray, rcond: float = 1e-15) -> FloatArray:
    """Pseudo-inverse of a small symmetric matrix ``a`` (k, k): ``numpy.linalg.pinv(a, rcond,
    hermitian=True)`` (the eigenvalues at most ``rcond`` times the largest dropped) without its
    general wrapper, compiled: the trends' fits and the fusion call it about ten times a window.
    Negative eigenvalues are inverted as numpy does (unlike the fusion's ``_safe_inverse``).
    A matrix with a non-finite entry goes through numpy's ``eigh`` (numba's refuses it).

    Args:
        a: symmetric matrix (k, k); only its lower triangle is read (``eigh``).
        rcond: relative cut-off of the eigenvalues' magnitudes.

    Returns:
        The pseudo-inverse (k, k).

    Raises:
        numpy.linalg.LinAlgError: the eigen-decomposition did not converge.
    """
    a = np.ascontiguousarray(a, dtype=float)
    if a.size and _finite(a):
        try:
            out: FloatArray = _pinv_sym(a, rcond)
        except ValueError as exc:  # numba's eigh did not converge: numpy's error
            raise np.linalg.LinAlgError(str(exc)) from exc
        return out
    w, v = np.linalg.eigh(a)
    aw = np.abs(w)
    keep = aw > rcond * (aw.max() if aw.size else 0.0)
    inv = np.zeros_like(w)
    inv[keep] = 1.0 / w[keep]
    out = (v * inv) @ v.T
    return out


@njit(cache=True, nogil=True)
def _finite(a: FloatArray) -> bool:
    for x in a.flat:
        if not math.isfinite(x):
            return False
    return True


@njit(cache=True, nogil=True)
def _pinv_sym(a: FloatArray, rcond: float) -> FloatArray:
    """:func:`pinv_sym`'s arithmetic on a finite matrix, compiled."""
    w, v = np.linalg.eigh(a)
    n = w.size
    top = abs(w[0])             # |w|.max() and v * inv by loops: the same numbers, without
    for i in range(1, n):       # compiling numba's array expressions (a cold start's seconds)
        top = max(top, abs(w[i]))
    cut = rcond * top
    inv = np.zeros(n)
    for i in range(n):
        if abs(w[i]) > cut:
            inv[i] = 1.0 / w[i]
    scaled = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            scaled[i, j] = v[i, j] * inv[j]
    out: FloatArray = scaled @ v.T
    return out


ModelKind = Literal["none", "linear", "exponential"]

#: Grid of r * span (span: the evidence's time span) searched for the exponential.
_RHO_GRID = np.concatenate([-np.geomspace(4.0, 0.05, 8), np.geomspace(0.05, 8.0, 18)])


@dataclass
class DegradationFit:
    """One degradation model fitted to a parameter's evidence.

    Attributes:
        kind: ``none``, ``linear`` or ``exponential``.
        t_ref: reference time [s] (the latest evidence): ``c`` and ``m`` are the level and
            the drift rate there.
        c, m, r: level [SI], drift rate [SI/s], growth rate of the drift [1/s] (0 unless
            exponential).
        onset: the onset time ``t0`` [s] (flat before it), None when the model degrades from
            the first evidence on.
        cov: covariance of the free parameters ``(c[, m][, r][, t0])`` [their units], scaled
            (see the module docstring).
        free: names of the free parameters, in ``cov``'s order.
        chi2: weighted residual sum of squares (published uncertainty).
        n: evidence points; ``k`` free parameters.
        scale: the factor the covariance was multiplied by (>= 1): ``max(chi2 / (n - k), 1)``
            times ``long_run``.
        long_run: the residuals' long-run variance factor (Newey-West, >= 1) of the last
            fit to the evidence (:meth:`advance` keeps it).
        bic: the Bayesian information criterion (smaller is better): degrading or not.
        aicc: the corrected Akaike criterion: which degradation model predicts best.
        rms_norm: RMS of the normalised residuals (1: the scatter the published
            uncertainty states).
        chi2_floor: the chi-square of residuals at the values' rounding (``1e-9`` of the
            largest): the criteria read ``max(chi2, chi2_floor)``.
        residuals: the normalised residuals of the evidence fitted (N,).

    ``bic``, ``aicc``, ``chi2_floor`` and ``residuals`` are those of the last fit to the
    evidence (:func:`fit_models`, :func:`refit_models`): :meth:`advance` updates the
    parameters, their covariance, ``chi2``, ``n`` and ``scale`` only.
    """

    kind: ModelKind
    t_ref: float
    c: float
    m: float = 0.0
    r: float = 0.0
    onset: float | None = None
    cov: FloatArray = field(default_factory=lambda: np.zeros((1, 1)))
    free: tuple[str, ...] = ("c",)
    chi2: float = 0.0
    n: int = 0
    scale: float = 1.0
    long_run: float = 1.0
    bic: float = math.inf
    aicc: float = math.inf
    rms_norm: float = math.nan
    chi2_floor: float = 0.0
    residuals: FloatArray = field(default_factory=lambda: np.zeros(0), repr=False)
    #: (cov, eigenvalues, eigenvectors) of :meth:`draws`, for the ``cov`` it was computed on
    _eigh: tuple[FloatArray, FloatArray, FloatArray] | None = field(
        default=None, init=False, repr=False, compare=False)
    #: the free parameters' codes (:meth:`_coded`)
    _codes: npt.NDArray[np.int64] | None = field(default=None, init=False, repr=False,
                                                  compare=False)

    @property
    def k(self) -> int:
        return len(self.free)

    @property
    def label(self) -> str:
        """The model's name, with its onset when it has one (``exponential from 160 s``)."""
        return self.kind if self.onset is None else f"{self.kind} from {self.onset:.0f} s"

    def std(self, name: str) -> float:
        """1-sigma standard error of a free parameter (0 for one the model does not have)."""
        if name not in self.free:
            return 0.0
        i = self.free.index(name)
        return float(math.sqrt(max(self.cov[i, i], 0.0)))

    def value(self, t: FloatArray | float) -> FloatArray:
        """The model at times ``t`` [s] (any shape)."""
        return _curve(np.asarray(t, dtype=float), self.t_ref, self.c, self.m, self.r, self.onset)

    def jacobian(self, t: FloatArray) -> FloatArray:
        """d value / d free parameters at times ``t`` (N,), shape (N, k)."""
        return _jacobian(np.asarray(t, dtype=float), self, self.free)

    def band(self, t: FloatArray) -> FloatArray:
        """1-sigma uncertainty of the model's value at times ``t`` (N,) (delta method on the
        parameter covariance)."""
        jac = self.jacobian(np.atleast_1d(np.asarray(t, dtype=float)))
        out: FloatArray = np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", jac, self.cov, jac),
                                             0.0))
        return out

    def value_band(self, t: float) -> tuple[float, float]:
        """:meth:`value` and :meth:`band` at one time ``t`` [s], compiled
        (:func:`~twinwatch.twin.prognostics._lm.value_band`)."""
        codes, base = self._coded()
        return value_band(float(t), self.t_ref, base, self.onset is not None, codes, self.cov)

    def advance(self, t: float, y: float, s: float) -> float:
        """Take one new evidence point into the fit, in place: the extended Kalman (recursive
        least squares) step of :func:`~twinwatch.twin.prognostics._lm.kalman_step` on the
        unscaled covariance (``cov / scale``), then ``chi2``, ``n``, ``scale`` (with
        ``long_run`` kept) and ``t_ref = t``. An onset stays at most ``t``.

        Args:
            t: the evidence's time [s], after ``t_ref``.
            y: its value [SI].
            s: its 1-sigma [SI] (> 0; at least the value's rounding, as in
                :func:`fit_models`).

        Returns:
            The point's chi-square against the prediction, ``e^2 / (s^2 + P_cc)``.
        """
        codes, base = self._coded()
        # a stated uncertainty below the value's rounding is not information (fit_models)
        s = max(float(s), _ROUNDING * abs(float(y)), 1e-300)
        x, cov, chi2 = kalman_step(self.t_ref, base, codes, self.cov / self.scale, float(t),
                                   float(y), s)
        self.t_ref = float(t)
        self.c, self.m = float(x[0]), float(x[1])
        if self.kind == "exponential":
            self.r = float(x[2])
        if self.onset is not None:
            self.onset = min(float(x[3]), self.t_ref)
        self.chi2 += chi2
        self.n += 1
        self.scale = max(self.chi2 / max(self.n - self.k, 1), 1.0) * self.long_run
        self.cov = cov * self.scale
        self.rms_norm = math.sqrt(max(self.chi2, 0.0) / self.n)
        return chi2

    def _coded(self) -> tuple[npt.NDArray[np.int64], FloatArray]:
        """The free parameters' codes (:mod:`._lm`) and ``(c, m, r, t0)``."""
        codes = self._codes
        if codes is None:
            codes = self._codes = np.array([_CODE[p] for p in self.free], dtype=np.int64)
        base = np.array([self.c, self.m, self.r,
                         self.onset if self.onset is not None else 0.0])
        return codes, base

    def rate_at(self, t: float) -> tuple[float, float]:
        """The drift rate at time ``t`` [s] and its 1-sigma [SI/s] (delta method):
        ``m exp(r (t - t_ref))`` after the onset, 0 before it."""
        if t == self.t_ref or self.kind == "none":
            return self.m, self.std("m")
        if self.onset is not None and t <= self.onset:
            return 0.0, 0.0
        tau = t - self.t_ref
        e = math.exp(min(self.r * tau, 700.0))
        grad = {"m": e, "r": self.m * tau * e}
        g = np.array([grad.get(p, 0.0) for p in self.free])
        var = float(g @ self.cov @ g)
        return self.m * e, math.sqrt(max(var, 0.0))

    def draws(self, n: int, rng: np.random.Generator | None = None, *,
              normals: FloatArray | None = None) -> dict[str, FloatArray]:
        """``n`` draws of ``c``, ``m``, ``r`` from the fit's Gaussian (the RUL's Monte Carlo):
        ``mean + (z sqrt(w)) V^T``, ``w, V`` the covariance's eigen-decomposition.

        Args:
            n: draws.
            rng: the generator of the standard normals ``z`` (n, k).
            normals: the standard normals themselves instead (n, >= k); the first ``k``
                columns are used.

        Raises:
            ValueError: neither ``rng`` nor ``normals``, or fewer than (n, k) normals.
        """
        mean = np.array([self._get(p) for p in self.free])
        if self._eigh is None or self._eigh[0] is not self.cov:
            # once per covariance: a window draws from each fit for each alarm level
            self._eigh = (self.cov, *np.linalg.eigh(0.5 * (self.cov + self.cov.T)))
        _, w, v = self._eigh
        if normals is not None:
            if normals.shape[0] < n or normals.shape[1] < mean.size:
                raise ValueError(f"{n} draws of {mean.size} parameters need that many normals,"
                                 f" not {normals.shape}")
            z = normals[:n, :mean.size]
        elif rng is not None:
            z = rng.standard_normal((n, len(mean)))
        else:
            raise ValueError("draws needs a generator (rng) or the normals")
        x = _gaussian_draws(mean, np.sqrt(np.maximum(w, 0.0)), v, z)
        return {p: x[self.free.index(p)] if p in self.free else np.full(n, self._get(p))
                for p in ("c", "m", "r")}

    def _get(self, name: str) -> float:
        if name == "t0":
            return float(self.onset if self.onset is not None else self.t_ref)
        return float(getattr(self, name))


@njit(cache=True, nogil=True, fastmath={"contract"})
def _gaussian_draws(mean: FloatArray, sw: FloatArray, v: FloatArray, z: FloatArray
                    ) -> FloatArray:
    """``mean + (z sw) V^T`` (:meth:`DegradationFit.draws`) transposed: (k, n), from z (n, k),
    sw (k,), V (k, k). Summed in order with fused multiply-adds (``contract``), as numpy's
    ``@`` (BLAS ``dgemm``) sums them on x86-64 with FMA: the same draws, bit for bit."""
    n, k = z.shape
    out = np.empty((k, n))
    for i in range(n):
        for a in range(k):
            acc = 0.0
            for j in range(k):
                acc += z[i, j] * sw[j] * v[a, j]
            out[a, i] = mean[a] + acc
    return out


#: Relative rounding of the evidence's values: a stated uncertainty or a residual below it
#: is not information.
_ROUNDING = 1e-9

_ZERO = np.zeros(1)
_NONE = np.zeros(0)

#: The compiled polish's codes of the free parameters (:mod:`._lm`).
_CODE = {"c": 0, "m": 1, "r": 2, "t0": 3}

#: The clip ufunc itself (``np.clip``'s wrapper costs more than the clip on a trend's points).
_CLIP = getattr(getattr(np, "_core", None), "umath", np).clip


def _g(tau: FloatArray, r: float | FloatArray) -> FloatArray:
    """(exp(r tau) - 1)/r, continuous at r = 0 (tau there)."""
    if isinstance(r, float) and isinstance(tau, np.ndarray):
        # hot path (a fit's scalar rate): the numbers below without the masks when possible
        x = r * tau
        small = np.abs(x) < 1e-8
        if not small.any():
            out: FloatArray = np.expm1(_CLIP(x, -700.0, 700.0)) / r
            return out
        if small.all():
            return tau * (1.0 + 0.5 * x)
    r = np.asarray(r, dtype=float)
    x = r * tau
    small = np.abs(x) < 1e-8
    safe = np.where(small, 1.0, r)
    return np.where(small, tau * (1.0 + 0.5 * x), np.expm1(np.clip(x, -700.0, 700.0)) / safe)


def _curve(t: FloatArray, t_ref: float, c: float, m: float, r: float,
           onset: float | None) -> FloatArray:
    tt = t if onset is None else np.maximum(t, onset)
    return c + m * _g(tt - t_ref, r)


def _jacobian(t: FloatArray, fit: DegradationFit, free: tuple[str, ...]) -> FloatArray:
    tt = t if fit.onset is None else np.maximum(t, fit.onset)
    tau = tt - fit.t_ref
    cols = []
    for p in free:
        if p == "c":
            cols.append(np.ones_like(t))
        elif p == "m":
            cols.append(_g(tau, fit.r))
        elif p == "r":
            x = fit.r * tau
            if abs(fit.r) < 1e-12:
                d = 0.5 * tau * tau
            else:
                d = (tau * np.exp(np.clip(x, -700, 700)) - _g(tau, fit.r)) / fit.r
            cols.append(fit.m * d)
        elif p == "t0":
            assert fit.onset is not None
            before = t < fit.onset
            cols.append(np.where(before, fit.m * np.exp(fit.r * (fit.onset - fit.t_ref)), 0.0))
    return np.column_stack(cols)


def _finish(kind: ModelKind, t: FloatArray, y: FloatArray, s: FloatArray, t_ref: float,
            c: float, m: float, r: float, onset: float | None, free: tuple[str, ...]
            ) -> DegradationFit:
    """Polish the grid's best by least squares (:mod:`._lm`), then the scaled covariance."""
    k = len(free)
    codes = np.array([_CODE[p] for p in free], dtype=np.int64)
    base = np.array([c, m, r, onset if onset is not None else 0.0])
    x = base[codes]
    if kind != "none" and k > 2:
        lo = np.full(k, -np.inf)
        hi = np.full(k, np.inf)
        span = max(float(t[-1] - t[0]), 1e-9)
        for i, p in enumerate(free):
            if p == "r":
                lo[i], hi[i] = -6.0 / span, 12.0 / span
            elif p == "t0":
                lo[i], hi[i] = float(t[0]), float(t[-1])
        pad = 1e-9 * np.where(np.isfinite(hi - lo), hi - lo, 0.0)
        x = np.clip(x, lo + pad, hi - pad)
        x = levenberg_marquardt(t, y, s, t_ref, base, onset is not None, codes, x, lo, hi)
    r_norm, chi2, info, lrf, floor = fit_statistics(t, y, s, t_ref, base, onset is not None,
                                                    codes, x, _ROUNDING)
    fit = DegradationFit(kind, t_ref, c, m, r, onset, free=free)
    for i, p in enumerate(free):
        if p == "t0":
            fit.onset = float(x[i])
        else:
            setattr(fit, p, float(x[i]))
    n = int(t.size)
    # Equilibrated before the pseudo-inverse: the level [SI], the drift rate [SI/s], the growth
    # rate [1/s] and the onset [s] differ by 10 orders of magnitude in the information, whose
    # raw eigenvalues then span more than 1/rcond; the cut would drop a direction that is
    # merely small in these units and give it zero variance (an onset "known" to 1e-4 s, a
    # growth rate to a third of its real error, and a RUL interval that misses the crossing).
    d = np.sqrt(np.abs(info.diagonal()))
    d = np.where((d > 0) & np.isfinite(d), d, 1.0)
    dd = np.outer(d, d)
    try:
        cov = pinv_sym(info / dd, rcond=1e-12) / dd
    except np.linalg.LinAlgError:
        cov = np.full((k, k), np.inf)
    dof = max(n - k, 1)
    red = chi2 / dof
    scale = max(red, 1.0) * lrf
    fit.cov = cov * scale
    fit.long_run = lrf
    fit.chi2 = chi2
    # residuals below the values' rounding are not information (see chi2_floor)
    fit.chi2_floor = floor
    fit.n = n
    fit.scale = scale
    fit.rms_norm = float(math.sqrt(chi2 / max(n, 1)))
    fit.residuals = r_norm
    return fit


def long_run_factor(r: FloatArray, lags: int | None = None) -> float:
    """Long-run over short-run variance of a residual series (>= 1): ``1 + 2 sum_k w_k
    rho_k`` with Bartlett weights ``w_k = 1 - k/(L+1)`` (Newey-West), ``L = min(n/4, 30)``
    by default (:func:`~twinwatch.twin.estimation.statistics.long_run_factor` for one series)."""
    r = np.asarray(r, dtype=float)
    n = r.size
    if n < 8:
        return 1.0
    big_l = max(1, min(lags if lags is not None else min(n // 4, 30), n - 1))
    den = float(r @ r)
    if den <= 0:
        return 1.0
    spec = np.fft.rfft(r, 2 * n)
    acov = np.fft.irfft(spec * np.conj(spec))[1:big_l + 1] / den
    w = 1.0 - np.arange(1, big_l + 1) / (big_l + 1.0)
    return float(min(max(1.0 + 2.0 * float(w @ acov), 1.0), float(n)))


def bin_evidence(t: FloatArray, y: FloatArray, s: FloatArray, most: int
                 ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """At most ``most`` points: consecutive evidence combined by inverse-variance weighting
    (time, value, and the combined 1-sigma ``1/sqrt(sum w)``), the bins counted back from the
    latest point so it stays one bin's end."""
    n = t.size
    if n <= most:
        return t, y, s
    b = -(-n // most)
    w = 1.0 / (s * s)
    edges = np.arange(n, 0, -b)[::-1]
    starts = np.concatenate([[0], edges[:-1]])
    sw = np.add.reduceat(w, starts)
    tb = np.add.reduceat(w * t, starts) / sw
    yb = np.add.reduceat(w * y, starts) / sw
    return tb, yb, 1.0 / np.sqrt(sw)


def _assign_bic(fits: list[DegradationFit]) -> None:
    """BIC of each fit with the weights known up to a common scale, on one effective sample
    size for all (a comparison needs the same one): ``n (1 - rho)/(1 + rho)``, ``rho`` the
    lag-1 autocorrelation of the residuals of the fit with the smallest chi-square (the
    richest: its residuals are the errors, not the others' misfit)."""
    if not fits:
        return
    best = min(fits, key=lambda f: f.chi2)
    r = best.residuals
    n = best.n
    den = float(r @ r)
    rho = float(np.sum(r[1:] * r[:-1])) / den if n > 2 and den > 0 else 0.0
    rho = min(max(rho, 0.0), 0.99)
    most = max(f.k for f in fits)
    n_eff = max(n * (1.0 - rho) / (1.0 + rho), float(most + 1))
    for f in fits:
        fit_term = n_eff * math.log(max(max(f.chi2, f.chi2_floor) / n, 1e-300))
        f.bic = fit_term + f.k * math.log(n_eff)
        f.aicc = fit_term + 2.0 * f.k + 2.0 * f.k * (f.k + 1) / max(n_eff - f.k - 1, 1.0)


def _onset_grid(t: FloatArray, most: int) -> FloatArray:
    """Candidate onsets: evidence times from the first to the one ``max(5, n/5)`` from the
    end (a degradation needs some evidence after its onset), at most ``most`` of them."""
    n = t.size
    last = n - max(5, n // 5)
    if last < 2:
        return np.empty(0)
    idx = np.unique(np.linspace(1, last, min(most, last), dtype=int))
    out: FloatArray = t[idx]
    return out


def fit_models(t: FloatArray, y: FloatArray, s: FloatArray, *, t_ref: float | None = None,
               kinds: tuple[ModelKind, ...] = ("none", "linear", "exponential"),
               onset: bool = True, min_points: int = 6,
               onsets: FloatArray | None = None) -> list[DegradationFit]:
    """Fit every model of ``kinds`` (and, with ``onset``, each degrading one with an onset)
    to the evidence.

    Args:
        t: evidence times [s] (N,), increasing.
        y: values [SI] (N,).
        s: their 1-sigma uncertainty [SI] (N,), positive.
        t_ref: reference time (default: ``t[-1]``).
        kinds: the candidate models.
        onset: also fit the degrading models with an onset.
        min_points: a model with ``k`` parameters needs ``k + min_points`` points.
        onsets: the candidate onsets (default: the evidence times but the last fifth).

    Returns:
        The fits (``none`` first when asked), each with its BIC.
    """
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    # A stated uncertainty below 1e-9 of the values is rounding, not information.
    floor = _ROUNDING * float(np.max(np.abs(y))) if y.size else 0.0
    s = np.maximum(np.asarray(s, dtype=float), max(floor, 1e-300))
    n = t.size
    t_ref = float(t[-1]) if t_ref is None else float(t_ref)
    w = 1.0 / (s * s)
    out: list[DegradationFit] = []
    if n == 0:
        return out
    c0 = float(w @ y / np.sum(w))
    if "none" in kinds:
        out.append(_finish("none", t, y, s, t_ref, c0, 0.0, 0.0, None, ("c",)))
    span = float(t[-1] - t[0])
    if span <= 0:
        _assign_bic(out)
        return out
    if not onset:
        onsets = np.empty(0)
    elif onsets is None:
        onsets = _onset_grid(t, 30)
    if "linear" in kinds and n >= 2 + min_points:
        chi2, c, m = wls_grid(t, y, w, t_ref, _ZERO, _NONE, False)
        out.append(_finish("linear", t, y, s, t_ref, float(c[0]), float(m[0]), 0.0, None,
                           ("c", "m")))
        if onsets.size and n >= 3 + min_points:
            chi2, c, m = wls_grid(t, y, w, t_ref, _ZERO, onsets, True)
            i = int(np.argmin(chi2))
            out.append(_finish("linear", t, y, s, t_ref, float(c[i]), float(m[i]), 0.0,
                               float(onsets[i]), ("c", "m", "t0")))
    if "exponential" in kinds and n >= 3 + min_points:
        rs = _RHO_GRID / span
        chi2, c, m = wls_grid(t, y, w, t_ref, rs, _NONE, False)
        i = int(np.argmin(chi2))
        out.append(_finish("exponential", t, y, s, t_ref, float(c[i]), float(m[i]),
                           float(rs[i]), None, ("c", "m", "r")))
        if onsets.size and n >= 4 + min_points:
            chi2, c, m = wls_grid(t, y, w, t_ref, rs, onsets, True)  # (R*O,)
            i = int(np.argmin(chi2))
            ri, oi = divmod(i, onsets.size)
            out.append(_finish("exponential", t, y, s, t_ref, float(c[i]), float(m[i]),
                               float(rs[ri]), float(onsets[oi]), ("c", "m", "r", "t0")))
    _assign_bic(out)
    return out


def refit_models(previous: list[DegradationFit], t: FloatArray, y: FloatArray, s: FloatArray,
                 *, t_ref: float | None = None) -> list[DegradationFit]:
    """The models of ``previous`` (a :func:`fit_models` answer on fewer evidence points)
    fitted again to the evidence, warm-started: each model's growth rate and onset from its
    previous fit, the level and drift rate solved in closed form at the new reference time,
    then the same polish, covariance and criteria as :func:`fit_models`, without a grid search.

    Args:
        previous: the fits to start from (their ``kind``, ``r``, ``onset``, ``free``).
        t, y, s: the evidence as for :func:`fit_models` [s], [SI], [SI] (N,).
        t_ref: reference time (default: ``t[-1]``).

    Returns:
        The fits in ``previous``'s order, each with its BIC.
    """
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    floor = _ROUNDING * float(np.max(np.abs(y))) if y.size else 0.0
    s = np.maximum(np.asarray(s, dtype=float), max(floor, 1e-300))
    t_ref = float(t[-1]) if t_ref is None else float(t_ref)
    w = 1.0 / (s * s)
    out: list[DegradationFit] = []
    for g in previous:
        if g.kind == "none":
            out.append(_finish("none", t, y, s, t_ref, float(w @ y / np.sum(w)), 0.0, 0.0,
                               None, g.free))
            continue
        onset = None if g.onset is None else min(max(g.onset, float(t[0])), float(t[-1]))
        r = float(g.r) if g.kind == "exponential" else 0.0
        _, c, m = wls_grid(t, y, w, t_ref, np.array([r]), np.array([onset or 0.0]),
                           onset is not None)
        out.append(_finish(g.kind, t, y, s, t_ref, float(c[0]), float(m[0]), float(g.r),
                           onset, g.free))
    _assign_bic(out)
    return out


def select(fits: list[DegradationFit], min_weight: float = 0.01
           ) -> tuple[DegradationFit | None, list[tuple[DegradationFit, float]]]:
    """The chosen model and the plausible ones with their weights.

    Two questions, two criteria: *is it degrading?* is a test, answered by the BIC (consistent:
    it does not see a trend in noise; the ``none`` model against the best degrading one);
    *how?* is a forecast, answered by the AICc among the degrading models (efficient: the
    BIC's heavier penalty would pick a line over an exponential just starting to curve).
    Weights: ``exp(-delta/2)`` of each criterion (Bayesian model averaging), the degrading
    models sharing what the BIC leaves them; below ``min_weight`` of the largest, dropped.

    Returns:
        (chosen fit or None without fits, [(fit, weight)] summing to 1).
    """
    good = [f for f in fits if math.isfinite(f.bic)]
    if not good:
        return None, []
    none = [f for f in good if f.kind == "none"]
    degrading = [f for f in good if f.kind != "none"]
    if not degrading:
        return none[0], [(none[0], 1.0)]
    best_bic = min(degrading, key=lambda f: f.bic)
    w_none = 0.0
    if none:
        d = none[0].bic - best_bic.bic
        w_none = 1.0 / (1.0 + math.exp(min(0.5 * d, 700.0)))
    a_min = min(f.aicc for f in degrading)
    w = np.array([math.exp(-0.5 * min(f.aicc - a_min, 1400.0)) for f in degrading])
    w = w / w.sum() * (1.0 - w_none)
    pairs = [(f, float(wi)) for f, wi in zip(degrading, w, strict=True)]
    if none:
        pairs.insert(0, (none[0], w_none))
    top = max(wi for _, wi in pairs)
    pairs = [(f, wi) for f, wi in pairs if wi >= min_weight * top]
    total = sum(wi for _, wi in pairs)
    pairs = [(f, wi / total) for f, wi in pairs]
    chosen = none[0] if none and w_none >= 0.5 else min(degrading, key=lambda f: f.aicc)
    return chosen, pairs
