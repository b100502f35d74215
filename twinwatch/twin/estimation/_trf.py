"""The local fit's bounded least squares: scipy's trust-region reflective loop, compiled around
scipy's own trust-region solver.

``scipy.optimize.least_squares(method="trf", tr_solver="exact")`` runs ``trf_bounds``
(Branch, Coleman and Li, SIAM J. Sci. Comput. 21(1), 1999): per iteration the Coleman-Li
scaling, an SVD of the scaled, augmented Jacobian, the trust-region subproblem
(``solve_lsq_trust_region``, More's iteration on the Levenberg-Marquardt parameter) and the
reflective choice of the step (``select_step``). Its iterations are some seventy numpy calls
on arrays of a few entries: about 0.2 ms of CPU each beyond the twin call, 10 of the 13 ms
a swarm window's polish costs through it (its 50 evaluations; the default motor with 0.5 %
noise in ``benchmarks/bench_window.py``). Through this module it costs 8.8 ms: the SVD, the
twin calls and scipy's subproblem.

:func:`trust_region_reflective` runs the same loop for our one case (dense Jacobian, linear
loss, unit ``x_scale``, ``tr_solver="exact"``): the scaling, the augmented SVD and the step's
selection in compiled code (numba, the same LAPACK ``gesdd`` and BLAS ``ddot``/``dgemv`` calls
numpy and scipy make, the same operations in the same order), scipy's
``solve_lsq_trust_region``, ``update_tr_radius`` and ``check_termination`` themselves, and the
two transposed products numpy's way (its ``dgemv`` kernel is not numba's). The iterates are
scipy's bit for bit: ``tests/test_trf.py`` holds the result to the public ``least_squares``
on real windows and on a step reflected at a bound, so a scipy or numpy release that changes
either fails there. The compiled parts are ported from scipy 1.17's
``scipy/optimize/_lsq/trf.py`` and ``common.py`` under scipy's BSD-3-Clause licence (below).
"""

# The compiled functions below are ported from SciPy (scipy/optimize/_lsq/trf.py, common.py),
# under its licence:
#
# Copyright (c) 2001-2002 Enthought, Inc. 2003, SciPy Developers.
# All rights reserved.
#
# Redistribution and use in source and binary forms, with or without modification, are
# permitted provided that the following conditions are met:
#
# 1. Redistributions of source code must retain the above copyright notice, this list of
#    conditions and the following disclaimer.
# 2. Redistributions in binary form must reproduce the above copyright notice, this list of
#    conditions and the following disclaimer in the documentation and/or other materials
#    provided with the distribution.
# 3. Neither the name of the copyright holder nor the names of its contributors may be used
#    to endorse or promote products derived from this software without specific prior
#    written permission.
#
# THIS SOFTWARE IS PROVIDED BY THE COPYRIGHT HOLDERS AND CONTRIBUTORS "AS IS" AND ANY EXPRESS
# OR IMPLIED WARRANTIES, INCLUDING, BUT NOT LIMITED TO, THE IMPLIED WARRANTIES OF
# MERCHANTABILITY AND FITNESS FOR A PARTICULAR PURPOSE ARE DISCLAIMED. IN NO EVENT SHALL THE
# COPYRIGHT OWNER OR CONTRIBUTORS BE LIABLE FOR ANY DIRECT, INDIRECT, INCIDENTAL, SPECIAL,
# EXEMPLARY, OR CONSEQUENTIAL DAMAGES (INCLUDING, BUT NOT LIMITED TO, PROCUREMENT OF
# SUBSTITUTE GOODS OR SERVICES; LOSS OF USE, DATA, OR PROFITS; OR BUSINESS INTERRUPTION)
# HOWEVER CAUSED AND ON ANY THEORY OF LIABILITY, WHETHER IN CONTRACT, STRICT LIABILITY, OR
# TORT (INCLUDING NEGLIGENCE OR OTHERWISE) ARISING IN ANY WAY OUT OF THE USE OF THIS
# SOFTWARE, EVEN IF ADVISED OF THE POSSIBILITY OF SUCH DAMAGE.

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numba import njit

from twinwatch.twin.model import FloatArray

#: The local fit's tolerances and evaluation budget (``least_squares``'s ``xtol``, ``ftol``,
#: ``gtol`` and ``max_nfev``).
XTOL, FTOL, GTOL, MAX_NFEV = 1e-10, 1e-12, 1e-12, 50


@njit(cache=True, nogil=True)
def _norm(x: FloatArray) -> float:  # pragma: no cover - compiled
    """``numpy.linalg.norm`` of a vector: the square root of its BLAS ``ddot``."""
    return math.sqrt(np.dot(x, x))


@njit(cache=True, nogil=True)
def _scaling(x: FloatArray, g: FloatArray, lb: FloatArray, ub: FloatArray
             ) -> tuple[FloatArray, FloatArray, float]:  # pragma: no cover - compiled
    """scipy's ``CL_scaling_vector`` (Coleman and Li's ``v`` (n,) and its derivative's sign
    ``dv`` (n,)) and ``norm(g * v, ord=inf)``."""
    n = x.size
    v = np.ones(n)
    dv = np.zeros(n)
    g_norm = 0.0
    nan = False
    for i in range(n):
        if g[i] < 0 and np.isfinite(ub[i]):
            v[i] = ub[i] - x[i]
            dv[i] = -1.0
        if g[i] > 0 and np.isfinite(lb[i]):
            v[i] = x[i] - lb[i]
            dv[i] = 1.0
        a = abs(g[i] * v[i])
        nan = nan or a != a
        g_norm = max(g_norm, a)
    return v, dv, np.nan if nan else g_norm      # numpy's max: a NaN wins


@njit(cache=True, nogil=True)
def _augmented_svd(jac: FloatArray, f: FloatArray, g: FloatArray, v: FloatArray,
                   dv: FloatArray, j_aug: FloatArray, f_aug: FloatArray
                   ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray,
                              FloatArray]:  # pragma: no cover - compiled
    """The "hat" space of one iteration: ``d`` (n,), ``diag_h`` (n,), ``g_h`` (n,); the
    augmented system ``[J d; diag(diag_h)^0.5]`` (M + n, n) and ``[f; 0]`` written to
    ``j_aug`` and ``f_aug``; its thin SVD ``U`` (M + n, n), ``s`` (n,), ``V`` (n, n) (``V``
    as scipy's ``Vt.T``)."""
    m, n = jac.shape
    d = np.sqrt(v)
    diag_h = g * dv
    g_h = d * g
    for k in range(m):
        f_aug[k] = f[k]
        for j in range(n):
            j_aug[k, j] = jac[k, j] * d[j]
    sq = np.sqrt(diag_h)
    for i in range(n):
        f_aug[m + i] = 0.0
        for j in range(n):
            j_aug[m + i, j] = sq[i] if i == j else 0.0
    u, s, vt = np.linalg.svd(j_aug, full_matrices=False)
    return d, diag_h, g_h, u, s, vt.T


@njit(cache=True, nogil=True)
def _to_bound(x: FloatArray, s: FloatArray, lb: FloatArray, ub: FloatArray
              ) -> tuple[float, FloatArray]:  # pragma: no cover - compiled
    """scipy's ``step_size_to_bound``: the step along ``s`` to the nearest bound and which
    variables reach it (the sign of their direction, 0 for the others)."""
    n = x.size
    steps = np.full(n, np.inf)
    for i in range(n):
        if s[i] != 0:
            a = (lb[i] - x[i]) / s[i]
            b = (ub[i] - x[i]) / s[i]
            steps[i] = a if (a >= b or a != a) else b     # numpy's maximum: a NaN wins
    min_step = steps.min()
    hits = np.zeros(n)
    for i in range(n):
        if steps[i] == min_step:
            hits[i] = np.sign(s[i])
    return min_step, hits


@njit(cache=True, nogil=True)
def _quadratic(j_h: FloatArray, g_h: FloatArray, s: FloatArray, diag_h: FloatArray
               ) -> float:  # pragma: no cover - compiled
    """scipy's ``evaluate_quadratic``: ``0.5 s^T (J^T J + diag) s + g^T s``."""
    js = np.dot(j_h, s)
    q = np.dot(js, js)
    q += np.dot(s * diag_h, s)
    value: float = 0.5 * q + np.dot(s, g_h)
    return value


@njit(cache=True, nogil=True)
def _minimize_1d(a: float, b: float, lo: float, hi: float, c: float
                 ) -> tuple[float, float]:  # pragma: no cover - compiled
    """scipy's ``minimize_quadratic_1d``: the minimum of ``a t^2 + b t + c`` on ``[lo, hi]``
    (the first of the ends and the extremum at the lowest value)."""
    t = np.empty(3)
    t[0], t[1] = lo, hi
    k = 2
    if a != 0:
        extremum = -0.5 * b / a
        if lo < extremum < hi:
            t[2] = extremum
            k = 3
    best, best_y = 0, t[0] * (a * t[0] + b) + c
    for i in range(1, k):
        if best_y != best_y:
            break               # numpy's argmin: the first NaN
        y = t[i] * (a * t[i] + b) + c
        if y < best_y or y != y:
            best, best_y = i, y
    return t[best], best_y


@njit(cache=True, nogil=True)
def _select_step(x: FloatArray, j_h: FloatArray, diag_h: FloatArray, g_h: FloatArray,
                 p_h: FloatArray, d: FloatArray, delta: float, lb: FloatArray, ub: FloatArray,
                 theta: float) -> tuple[FloatArray, FloatArray, float, FloatArray, float, float,
                                        float]:  # pragma: no cover - compiled
    """scipy's ``select_step`` from the trust-region solution ``p_h`` (hat space), then the
    trial point as ``make_strictly_feasible(x + step, lb, ub, rstep=0)``. Returns (step,
    step_h, predicted reduction, trial point, ``|step_h|``, ``|step|``, ``|x|``)."""
    n = x.size
    p_h = p_h.copy()
    p = d * p_h
    inside = True
    for i in range(n):
        xi = x[i] + p[i]
        if not (xi >= lb[i] and xi <= ub[i]):
            inside = False
    if inside:
        step, step_h = p, p_h
        predicted = -_quadratic(j_h, g_h, p_h, diag_h)
    else:
        p_stride, hits = _to_bound(x, p, lb, ub)
        r_h = p_h.copy()
        for i in range(n):
            if hits[i] != 0:
                r_h[i] *= -1
        r = d * r_h
        p *= p_stride
        p_h *= p_stride
        x_on_bound = x + p
        # intersect_trust_region(p_h, r_h, delta)'s larger root
        a = np.dot(r_h, r_h)
        if a == 0:
            raise ValueError("`s` is zero.")
        b = np.dot(p_h, r_h)
        c = np.dot(p_h, p_h) - delta * delta
        if c > 0:
            raise ValueError("`x` is not within the trust region.")
        dd = np.sqrt(b * b - a * c)
        q = -(b + math.copysign(dd, b))
        t1, t2 = q / a, c / q
        to_tr = t2 if t1 < t2 else t1
        to_bound = _to_bound(x_on_bound, r, lb, ub)[0]
        r_stride = to_tr if to_tr < to_bound else to_bound      # Python's min
        if r_stride > 0:
            r_stride_l = (1 - theta) * p_stride / r_stride
            r_stride_u = theta * to_bound if r_stride == to_bound else to_tr
        else:
            r_stride_l, r_stride_u = 0.0, -1.0
        if r_stride_l <= r_stride_u:
            # build_quadratic_1d(j_h, g_h, r_h, s0=p_h, diag=diag_h)
            vv = np.dot(j_h, r_h)
            qa = np.dot(vv, vv)
            qa += np.dot(r_h * diag_h, r_h)
            qa *= 0.5
            qb = np.dot(g_h, r_h)
            u = np.dot(j_h, p_h)
            qb += np.dot(u, vv)
            qc = 0.5 * np.dot(u, u) + np.dot(g_h, p_h)
            qb += np.dot(p_h * diag_h, r_h)
            qc += 0.5 * np.dot(p_h * diag_h, p_h)
            r_stride, r_value = _minimize_1d(qa, qb, r_stride_l, r_stride_u, qc)
            r_h *= r_stride
            r_h += p_h
            r = r_h * d
        else:
            r_value = np.inf
        p *= theta
        p_h *= theta
        p_value = _quadratic(j_h, g_h, p_h, diag_h)
        ag_h = -g_h
        ag = d * ag_h
        to_tr = delta / _norm(ag_h)
        to_bound = _to_bound(x, ag, lb, ub)[0]
        ag_stride = theta * to_bound if to_bound < to_tr else to_tr
        # build_quadratic_1d(j_h, g_h, ag_h, diag=diag_h)
        vv = np.dot(j_h, ag_h)
        qa = np.dot(vv, vv)
        qa += np.dot(ag_h * diag_h, ag_h)
        qa *= 0.5
        qb = np.dot(g_h, ag_h)
        ag_stride, ag_value = _minimize_1d(qa, qb, 0.0, ag_stride, 0.0)
        ag_h *= ag_stride
        ag *= ag_stride
        if p_value < r_value and p_value < ag_value:
            step, step_h, predicted = p, p_h, -p_value
        elif r_value < p_value and r_value < ag_value:
            step, step_h, predicted = r, r_h, -r_value
        else:
            step, step_h, predicted = ag, ag_h, -ag_value
    trial = x + step
    for i in range(n):          # make_strictly_feasible(..., rstep=0)
        if trial[i] >= ub[i]:
            trial[i] = np.nextafter(ub[i], lb[i])
        elif trial[i] <= lb[i]:
            trial[i] = np.nextafter(lb[i], ub[i])
        if trial[i] < lb[i] or trial[i] > ub[i]:
            trial[i] = 0.5 * (lb[i] + ub[i])
    return step, step_h, predicted, trial, _norm(step_h), _norm(step), _norm(x)


def trust_region_reflective(fun: Callable[[FloatArray], FloatArray],
                            jac: Callable[[FloatArray], FloatArray], x0: FloatArray,
                            lower: FloatArray, upper: FloatArray) -> FloatArray:
    """Minimise ``0.5 |fun(x)|^2`` within ``lower <= x <= upper``: the ``x`` that
    ``least_squares(fun, x0, jac=jac, bounds=(lower, upper), method="trf", x_scale=1.0,
    xtol=XTOL, ftol=FTOL, gtol=GTOL, max_nfev=MAX_NFEV).x`` returns.

    Args:
        fun: residuals (M,) at a point (n,).
        jac: their Jacobian (M, n) at a point ``fun`` was just called at.
        x0: the start (n,), inside the bounds.
        lower, upper: the bounds (n,), finite or not, ``lower < upper``.

    Returns:
        The solution (n,).

    Raises:
        ValueError: as ``least_squares``: a lower bound not below its upper one, ``x0``
            outside the bounds, or residuals not finite at the start.
    """
    from scipy.optimize._lsq.common import (
        check_termination,
        in_bounds,
        make_strictly_feasible,
        solve_lsq_trust_region,
        update_tr_radius,
    )
    from scipy.optimize._lsq.trf import trf_no_bounds

    x0 = np.atleast_1d(x0).astype(float)
    lb = np.asarray(lower, dtype=float)
    ub = np.asarray(upper, dtype=float)
    if (lb >= ub).any():
        raise ValueError("Each lower bound must be strictly less than each upper bound.")
    if not in_bounds(x0, lb, ub):
        raise ValueError("Initial guess is outside of provided bounds")
    x0 = make_strictly_feasible(x0, lb, ub)
    f = np.atleast_1d(fun(x0))
    jac_x = np.atleast_2d(jac(x0))
    if not np.isfinite(f).all():
        raise ValueError("Residuals are not finite in the initial point.")
    if (lb == -np.inf).all() and (ub == np.inf).all():
        sol = trf_no_bounds(fun, jac, x0, f, jac_x, FTOL, XTOL, GTOL, MAX_NFEV,
                            np.ones_like(x0), None, "exact", {}, 0)
        x_free: FloatArray = sol.x
        return x_free
    # scipy's trf_bounds with x_scale 1, a linear loss and the exact solver
    x = x0.copy()
    nfev = 1
    m, n = jac_x.shape
    cost = 0.5 * np.dot(f, f)
    g = jac_x.T.dot(f)
    v, _, _ = _scaling(x, g, lb, ub)
    delta = _norm(x0 / np.sqrt(v))
    if delta == 0:
        delta = 1.0
    f_aug = np.zeros(m + n)
    j_aug = np.empty((m + n, n))
    alpha = 0.0
    status = None
    while True:
        v, dv, g_norm = _scaling(x, g, lb, ub)
        if g_norm < GTOL:
            status = 1
        if status is not None or nfev == MAX_NFEV:
            break
        d, diag_h, g_h, u, s, vv = _augmented_svd(jac_x, f, g, v, dv, j_aug, f_aug)
        j_h = j_aug[:m]
        uf = u.T.dot(f_aug)
        theta = max(0.995, 1 - g_norm)
        actual = -1.0
        while actual <= 0 and nfev < MAX_NFEV:
            p_h, alpha, _ = solve_lsq_trust_region(n, m, uf, s, vv, delta,
                                                   initial_alpha=alpha)
            step, step_h, predicted, x_new, step_h_norm, step_norm, x_norm = _select_step(
                x, j_h, diag_h, g_h, p_h, d, delta, lb, ub, theta)
            f_new = fun(x_new)
            nfev += 1
            if not np.isfinite(f_new).all():
                delta = 0.25 * step_h_norm
                continue
            cost_new = 0.5 * np.dot(f_new, f_new)
            actual = cost - cost_new
            delta_new, ratio = update_tr_radius(delta, actual, predicted, step_h_norm,
                                                step_h_norm > 0.95 * delta)
            status = check_termination(actual, cost, step_norm, x_norm, ratio, FTOL, XTOL)
            if status is not None:
                break
            alpha *= delta / delta_new
            delta = delta_new
        if actual > 0:
            x, f, cost = x_new, f_new, cost_new
            jac_x = jac(x)
            g = jac_x.T.dot(f)
    return x
