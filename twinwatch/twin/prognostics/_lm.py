"""The degradation models' bounded Levenberg-Marquardt, compiled.

The same model and Jacobian as :mod:`~twinwatch.twin.prognostics.degradation`'s ``_curve``
and ``_jacobian`` (the reference in ``tests/test_prognostics_lm.py``), compiled because a
trend's polish runs a few times per parameter and window on at most ``max_points`` points,
where numpy's per-call overhead would dominate.

The free parameters are coded ``0: c``, ``1: m``, ``2: r``, ``3: t0`` (onset). The model is
``c + m * g(max(t, t0) - t_ref, r)`` with ``g(tau, r) = (exp(r tau) - 1)/r`` (``tau`` where
``|r tau| < 1e-8``), ``t0`` absent (no onset) when ``has_onset`` is false.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _g1(tau: float, r: float) -> float:
    x = r * tau
    if abs(x) < 1e-8:
        return tau * (1.0 + 0.5 * x)
    return math.expm1(min(max(x, -700.0), 700.0)) / r


@njit(cache=True, nogil=True)
def _unpack(x: np.ndarray, codes: np.ndarray, base: np.ndarray) -> np.ndarray:
    p = base.copy()
    for i in range(codes.size):
        p[codes[i]] = x[i]
    return p


@njit(cache=True, nogil=True)
def _resid(t: np.ndarray, y: np.ndarray, s: np.ndarray, t_ref: float, p: np.ndarray,
           has_onset: bool, out: np.ndarray) -> float:
    c, m, r, t0 = p[0], p[1], p[2], p[3]
    cost = 0.0
    for i in range(t.size):
        tt = max(t[i], t0) if has_onset else t[i]
        v = (c + m * _g1(tt - t_ref, r) - y[i]) / s[i]
        out[i] = v
        cost += v * v
    return cost


@njit(cache=True, nogil=True)
def _jac(t: np.ndarray, s: np.ndarray, t_ref: float, p: np.ndarray, has_onset: bool,
         codes: np.ndarray, out: np.ndarray) -> None:
    m, r, t0 = p[1], p[2], p[3]
    for i in range(t.size):
        tt = max(t[i], t0) if has_onset else t[i]
        tau = tt - t_ref
        for j in range(codes.size):
            k = codes[j]
            if k == 0:
                d = 1.0
            elif k == 1:
                d = _g1(tau, r)
            elif k == 2:
                if abs(r) < 1e-12:
                    d = m * (0.5 * tau * tau)
                else:
                    d = m * ((tau * math.exp(min(max(r * tau, -700.0), 700.0))
                              - _g1(tau, r)) / r)
            else:
                d = m * math.exp(r * (t0 - t_ref)) if t[i] < t0 else 0.0
            out[i, j] = d / s[i]


@njit(cache=True, nogil=True)
def _solve(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, bool]:
    """``a x = b`` by Gaussian elimination with partial pivoting (LAPACK ``gesv``'s method);
    False on an exactly singular pivot (where ``numpy.linalg.solve`` raises)."""
    n = b.size
    m = a.copy()
    x = b.copy()
    for k in range(n):
        piv = k
        big = abs(m[k, k])
        for i in range(k + 1, n):
            if abs(m[i, k]) > big:
                big = abs(m[i, k])
                piv = i
        if big == 0.0 or not math.isfinite(big):
            return x, False
        if piv != k:
            for j in range(n):
                m[k, j], m[piv, j] = m[piv, j], m[k, j]
            x[k], x[piv] = x[piv], x[k]
        for i in range(k + 1, n):
            f = m[i, k] / m[k, k]
            for j in range(k, n):
                m[i, j] -= f * m[k, j]
            x[i] -= f * x[k]
    for k in range(n - 1, -1, -1):
        acc = x[k]
        for j in range(k + 1, n):
            acc -= m[k, j] * x[j]
        x[k] = acc / m[k, k]
    return x, True


@njit(cache=True, nogil=True)
def levenberg_marquardt(t: np.ndarray, y: np.ndarray, s: np.ndarray, t_ref: float,
                        base: np.ndarray, has_onset: bool, codes: np.ndarray, x0: np.ndarray,
                        lo: np.ndarray, hi: np.ndarray, iterations: int = 40) -> np.ndarray:
    """Bounded Levenberg-Marquardt (steps clipped to the bounds) of the degradation model.

    Args:
        t, y, s: evidence times [s], values [SI], 1-sigma [SI] (N,).
        t_ref: the reference time [s].
        base: the model's ``(c, m, r, t0)`` (4,); the free ones are overwritten by ``x``.
        has_onset: whether the model has an onset (``t0``).
        codes: the free parameters' codes (k,) in ``x``'s order.
        x0, lo, hi: the start and the bounds (k,).
        iterations: outer iterations at most.

    Returns:
        The polished free parameters (k,).
    """
    n = t.size
    k = codes.size
    x = x0.copy()
    r = np.empty(n)
    rn = np.empty(n)
    jm = np.empty((n, k))
    cost = _resid(t, y, s, t_ref, _unpack(x, codes, base), has_onset, r)
    lam = 1e-3
    for _ in range(iterations):
        _jac(t, s, t_ref, _unpack(x, codes, base), has_onset, codes, jm)
        a = np.zeros((k, k))
        g = np.zeros(k)
        for i in range(n):
            for p in range(k):
                g[p] += jm[i, p] * r[i]
                for q in range(k):
                    a[p, q] += jm[i, p] * jm[i, q]
        d = np.empty(k)
        for i in range(k):
            d[i] = a[i, i] if a[i, i] > 0 else 1.0
        improved = False
        small = False
        for _ in range(10):
            step, ok = _solve(a + lam * np.diag(d), -g)
            if not ok:
                lam *= 10.0
                continue
            xn = np.minimum(np.maximum(x + step, lo), hi)
            cn = _resid(t, y, s, t_ref, _unpack(xn, codes, base), has_onset, rn)
            if math.isfinite(cn) and cn < cost:
                improved = True
                small = cost - cn <= 1e-10 * cost
                x = xn
                r, rn = rn, r
                cost = cn
                lam = max(lam / 3.0, 1e-9)
                break
            lam *= 10.0
        if not improved or small:
            break
    return x


@njit(cache=True, nogil=True)
def wls_grid(t: np.ndarray, y: np.ndarray, w: np.ndarray, t_ref: float, rs: np.ndarray,
             onsets: np.ndarray, has_onset: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed-form weighted least squares of ``y = c + m * g(max(t, t0) - t_ref, r)`` for
    every growth rate of ``rs`` (R,) and, with ``has_onset``, every onset of ``onsets`` (O,)
    (``g`` as :func:`levenberg_marquardt`'s model; ``r = 0``: the line), without building the
    (R*O, N) basis.

    Args:
        t, y, w: evidence times [s], values [SI], weights ``1/s^2`` (N,).
        t_ref: the reference time [s].
        rs: growth rates [1/s] (R,).
        onsets: onset times [s] (O,); ignored without ``has_onset``.
        has_onset: grid the onsets too.

    Returns:
        (chi2, c, m), each (R*O,) with ``has_onset`` (row ``ri * O + oi``), else (R,).
    """
    n = t.size
    n_r = rs.size
    n_o = onsets.size if has_onset else 1
    s0 = 0.0
    sy = 0.0
    syy = 0.0
    for i in range(n):
        s0 += w[i]
        sy += w[i] * y[i]
        syy += w[i] * y[i] * y[i]
    chi2 = np.empty(n_r * n_o)
    c = np.empty(n_r * n_o)
    m = np.empty(n_r * n_o)
    g_t = np.empty(n)
    t0 = 0.0
    g0 = 0.0
    for ri in range(n_r):
        r = rs[ri]
        for i in range(n):
            g_t[i] = _g1(t[i] - t_ref, r)
        for oi in range(n_o):
            s1 = 0.0
            s2 = 0.0
            sgy = 0.0
            if has_onset:
                t0 = onsets[oi]
                g0 = _g1(t0 - t_ref, r)
            for i in range(n):
                b = g0 if has_onset and t[i] < t0 else g_t[i]
                s1 += b * w[i]
                s2 += b * b * w[i]
                sgy += b * w[i] * y[i]
            det = s0 * s2 - s1 * s1
            j = ri * n_o + oi
            if det > 1e-12 * max(s0 * s2, 1e-300):
                c[j] = (s2 * sy - s1 * sgy) / det
                m[j] = (s0 * sgy - s1 * sy) / det
                chi2[j] = max(syy - c[j] * sy - m[j] * sgy, 0.0)
            else:
                c[j] = sy / s0
                m[j] = 0.0
                chi2[j] = math.inf
    return chi2, c, m


@njit(cache=True, nogil=True)
def long_run_factor(r: np.ndarray, lags: int = -1) -> float:
    """Long-run over short-run variance of a residual series ``r`` (N,) (>= 1, <= N): ``1 + 2
    sum_k w_k rho_k`` with Bartlett weights ``w_k = 1 - k/(L+1)`` (Newey-West), ``L = min(N/4,
    30)`` unless ``lags`` >= 0 gives it; 1 below 8 points or for zero residuals.
    :func:`~twinwatch.twin.prognostics.degradation.long_run_factor` is the same sum through
    the FFT; here the lag products are summed directly."""
    n = r.size
    if n < 8:
        return 1.0
    big_l = max(1, min(lags if lags >= 0 else min(n // 4, 30), n - 1))
    den = 0.0
    for i in range(n):
        den += r[i] * r[i]
    if den <= 0.0:
        return 1.0
    acc = 0.0
    for k in range(1, big_l + 1):
        a = 0.0
        for i in range(n - k):
            a += r[i] * r[i + k]
        acc += (1.0 - k / (big_l + 1.0)) * (a / den)
    return min(max(1.0 + 2.0 * acc, 1.0), float(n))


@njit(cache=True, nogil=True)
def fit_statistics(t: np.ndarray, y: np.ndarray, s: np.ndarray, t_ref: float,
                   base: np.ndarray, has_onset: bool, codes: np.ndarray, x: np.ndarray,
                   rounding: float) -> tuple[np.ndarray, float, np.ndarray, float, float]:
    """What a polished degradation model says of its evidence, in one pass over it (the model
    and Jacobian of :func:`levenberg_marquardt`).

    Args:
        t, y, s, t_ref, base, has_onset, codes: as for :func:`levenberg_marquardt`.
        x: the free parameters (k,).
        rounding: the values' relative rounding (the chi-square floor's residual).

    Returns:
        (normalised residuals ``(model - y)/s`` (N,), their chi-square, the information
        matrix ``J^T J`` of the normalised Jacobian (k, k), the residuals' long-run variance
        factor (:func:`long_run_factor`), the chi-square of residuals at ``rounding`` times
        the largest ``|y|``).
    """
    n = t.size
    k = codes.size
    p = _unpack(x, codes, base)
    res = np.empty(n)
    chi2 = _resid(t, y, s, t_ref, p, has_onset, res)
    jm = np.empty((n, k))
    _jac(t, s, t_ref, p, has_onset, codes, jm)
    info = np.zeros((k, k))
    for i in range(n):
        for a in range(k):
            for b in range(a, k):
                info[a, b] += jm[i, a] * jm[i, b]
    for a in range(k):
        for b in range(a):
            info[a, b] = info[b, a]
    y_max = 0.0
    for i in range(n):
        y_max = max(y_max, abs(y[i]))
    floor = 0.0
    for i in range(n):
        q = rounding * y_max / s[i]
        floor += q * q
    return res, chi2, info, long_run_factor(res), floor


@njit(cache=True, nogil=True)
def value_band(t: float, t_ref: float, base: np.ndarray, has_onset: bool, codes: np.ndarray,
               cov: np.ndarray) -> tuple[float, float]:
    """The model and its 1-sigma band at one time (the delta method on the parameters'
    covariance: ``sqrt(j^T cov j)``, ``j`` the Jacobian row of :func:`levenberg_marquardt`).

    Args:
        t: the time [s].
        t_ref, base, has_onset, codes: as for :func:`levenberg_marquardt`.
        cov: the free parameters' covariance (k, k), in ``codes``' order.

    Returns:
        (value [SI], band [SI]).
    """
    tt = np.array([t])
    one = np.ones(1)
    res = np.empty(1)
    _resid(tt, np.zeros(1), one, t_ref, base, has_onset, res)
    jm = np.empty((1, codes.size))
    _jac(tt, one, t_ref, base, has_onset, codes, jm)
    q = 0.0
    for a in range(codes.size):
        acc = 0.0
        for b in range(codes.size):
            acc += cov[a, b] * jm[0, b]
        q += jm[0, a] * acc
    return res[0], math.sqrt(max(q, 0.0))


@njit(cache=True, nogil=True)
def kalman_step(t_ref: float, base: np.ndarray, codes: np.ndarray, cov: np.ndarray, t: float,
                y: float, s: float
                ) -> tuple[np.ndarray, np.ndarray, float]:
    """One evidence point taken into a fitted degradation model: an extended Kalman filter
    (recursive least squares) step on the free parameters, ``O(k^2)``.

    The model's parameters are referred to the latest evidence (``c`` the level, ``m`` the
    drift rate there). The *time update* refers them to the new evidence's time ``t``, exactly
    for the curve (``g(a + b) = g(a) + exp(r a) g(b)``)::

        c' = c + m g(tau, r),   m' = m exp(r tau),   tau = t - t_ref   (t > t0)

    and linearised for the covariance, ``P' = F P F^T`` with ``F`` its Jacobian (the
    parameters do not change in time: no process noise). The *measurement update* reads the
    level ``c'`` (``h = e_c``)::

        e = y - c',   S = s^2 + max(P'_cc, 0),   K = P'_{.c} / S,   x += K e,   P -= K K^T S

    For the line (and ``none``) this is the recursive form of the weighted least squares fit
    to the evidence and the new point (``P`` the unscaled ``(J^T W J)^-1``); for the
    exponential and an onset, the fit linearised about its current optimum (the innovation
    ``e / sqrt(S)`` says how far the new point is from it).

    Args:
        t_ref: the model's reference time [s] (< ``t``).
        base: ``(c, m, r, t0)`` (4,); an onset ``t0`` is at most ``t_ref`` (a fit's onset
            lies within its evidence): the curve from ``t_ref`` on does not depend on it.
        codes: the free parameters' codes (k,), ``cov``'s order.
        cov: their covariance (k, k), unscaled (``(J^T W J)^-1``, ``W = 1/s^2``).
        t, y, s: the new evidence: time [s], value [SI], 1-sigma [SI].

    Returns:
        (the new ``(c, m, r, t0)`` (4,) at reference time ``t``, the new unscaled covariance
        (k, k), the point's chi-square ``e^2 / S``).
    """
    c, m, r = base[0], base[1], base[2]
    k = codes.size
    tau = t - t_ref
    ex = math.exp(min(max(r * tau, -700.0), 700.0))
    g = _g1(tau, r)
    if abs(r) < 1e-12:
        dg = 0.5 * tau * tau
    else:
        dg = (tau * ex - g) / r
    f = np.eye(k)
    ic = -1
    for a in range(k):
        code = codes[a]
        if code == 0:
            ic = a
            for b in range(k):
                if codes[b] == 1:
                    f[a, b] = g
                elif codes[b] == 2:
                    f[a, b] = m * dg
        elif code == 1:
            for b in range(k):
                if codes[b] == 1:
                    f[a, b] = ex
                elif codes[b] == 2:
                    f[a, b] = m * tau * ex
    p = f @ cov @ f.T
    out = base.copy()
    out[0] = c + m * g
    out[1] = m * ex
    e = y - out[0]
    # a predicted level's variance below 0 is the arithmetic's, not the model's: F P F^T of
    # a fit whose drift rate and growth rate are perfectly anti-correlated cancels (an
    # exponential of growth rate 6.5/s stepped 4 s ahead, exp(r tau) = 1.7e11, gave P'_cc
    # of about -1e6: a negative chi-square, and the window's processing raised)
    var = s * s + max(p[ic, ic], 0.0)
    gain = p[:, ic] / var
    for a in range(k):
        out[codes[a]] += gain[a] * e
    for a in range(k):
        for b in range(k):
            p[a, b] -= gain[a] * gain[b] * var
    for a in range(k):
        for b in range(a):
            v = 0.5 * (p[a, b] + p[b, a])
            p[a, b] = v
            p[b, a] = v
    return out, p, e * e / var
