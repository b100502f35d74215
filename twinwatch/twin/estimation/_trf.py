"""The local fit's bounded least squares: scipy's trust-region reflective loop, called directly.

``scipy.optimize.least_squares(method="trf")`` spends most of a window's polish in its generic
wrapper (argument checks, the ``VectorFunction`` that caches and counts, the result's
packaging), more than in the twin calls themselves. :func:`trust_region_reflective` prepares
what the wrapper prepares for our one case (dense Jacobian, linear loss, unit ``x_scale``,
``tr_solver="exact"``) and runs scipy's ``trf_bounds`` loop (Branch, Coleman and Li, SIAM J.
Sci. Comput. 21(1), 1999) as :func:`_trf_bounds`: the same operations in the same order,
calling scipy's own step functions (``solve_lsq_trust_region``, ``select_step``,
``update_tr_radius``, ``check_termination``), without what our case does not read (the unit
scale's multiplications by 1, the result's active-constraint mask, the counters). The iterates
are scipy's, bit for bit; ``tests/test_trf.py`` holds it to the public ``least_squares`` on
real windows, so a scipy release that changes either fails there.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from twinwatch.twin.model import FloatArray

#: The local fit's tolerances and evaluation budget (``least_squares``'s ``xtol``, ``ftol``,
#: ``gtol`` and ``max_nfev``).
XTOL, FTOL, GTOL, MAX_NFEV = 1e-10, 1e-12, 1e-12, 50


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
    from scipy.optimize._lsq.common import in_bounds, make_strictly_feasible
    from scipy.optimize._lsq.trf import trf_no_bounds

    x0 = np.atleast_1d(x0).astype(float)
    lb = np.asarray(lower, dtype=float)
    ub = np.asarray(upper, dtype=float)
    if np.any(lb >= ub):
        raise ValueError("Each lower bound must be strictly less than each upper bound.")
    if not in_bounds(x0, lb, ub):
        raise ValueError("Initial guess is outside of provided bounds")
    x0 = make_strictly_feasible(x0, lb, ub)
    f0 = np.atleast_1d(fun(x0))
    j0 = np.atleast_2d(jac(x0))
    if not np.isfinite(f0).all():
        raise ValueError("Residuals are not finite in the initial point.")
    if np.all(lb == -np.inf) and np.all(ub == np.inf):
        sol = trf_no_bounds(fun, jac, x0, f0, j0, FTOL, XTOL, GTOL, MAX_NFEV,
                            np.ones_like(x0), None, "exact", {}, 0)
        x: FloatArray = sol.x
        return x
    return _trf_bounds(fun, jac, x0, f0, j0, lb, ub)


def _trf_bounds(fun: Callable[[FloatArray], FloatArray], jac: Callable[[FloatArray], FloatArray],
                x0: FloatArray, f0: FloatArray, j0: FloatArray, lb: FloatArray,
                ub: FloatArray) -> FloatArray:
    """scipy's ``trf_bounds`` (scipy/optimize/_lsq/trf.py) with ``x_scale`` 1, no loss, the
    exact trust-region solver, no callback: its iterates, its solution ``x``."""
    from scipy.linalg import svd
    from scipy.optimize._lsq.common import (
        check_termination,
        make_strictly_feasible,
        solve_lsq_trust_region,
        update_tr_radius,
    )
    from scipy.optimize._lsq.trf import select_step

    x, f, jm = x0.copy(), f0, j0
    m, n = jm.shape
    cost = 0.5 * np.dot(f, f)
    g = jm.T.dot(f)
    up, low = np.isfinite(ub), np.isfinite(lb)

    def scaling(x: FloatArray, g: FloatArray) -> tuple[FloatArray, FloatArray]:
        # scipy's CL_scaling_vector: v the distance to the bound the gradient points at
        to_ub, to_lb = (g < 0) & up, (g > 0) & low
        v = np.where(to_lb, x - lb, np.where(to_ub, ub - x, 1.0))
        return v, np.where(to_lb, 1.0, np.where(to_ub, -1.0, 0.0))

    v, dv = scaling(x, g)
    delta = _norm(x0 / v**0.5)
    if delta == 0:
        delta = 1.0
    f_aug = np.zeros(m + n)
    j_aug = np.empty((m + n, n))
    alpha = 0.0
    nfev = 1
    status = None
    while True:
        v, dv = scaling(x, g)
        g_norm = np.abs(g * v).max(initial=0)  # norm(g * v, ord=inf)
        if g_norm < GTOL:
            status = 1
        if status is not None or nfev == MAX_NFEV:
            break
        d = v**0.5
        diag_h = g * dv
        g_h = d * g
        f_aug[:m] = f
        np.multiply(jm, d, out=j_aug[:m])
        j_h = j_aug[:m]
        j_aug[m:] = np.diag(diag_h**0.5)
        u, s, vt = svd(j_aug, full_matrices=False)
        vm = vt.T
        uf = u.T.dot(f_aug)
        theta = max(0.995, 1 - g_norm)
        reduction = -1.0
        while reduction <= 0 and nfev < MAX_NFEV:
            p_h, alpha, _ = solve_lsq_trust_region(n, m, uf, s, vm, delta, initial_alpha=alpha)
            p = d * p_h
            step, step_h, predicted = select_step(x, j_h, diag_h, g_h, p, p_h, d, delta, lb, ub,
                                                  theta)
            x_new = x + step
            if (x_new <= lb).any() or (x_new >= ub).any():
                x_new = make_strictly_feasible(x_new, lb, ub, rstep=0)
            f_new = fun(x_new)
            nfev += 1
            step_h_norm = _norm(step_h)
            if not np.isfinite(f_new).all():
                delta = 0.25 * step_h_norm
                continue
            cost_new = 0.5 * np.dot(f_new, f_new)
            reduction = cost - cost_new
            delta_new, ratio = update_tr_radius(delta, reduction, predicted, step_h_norm,
                                                step_h_norm > 0.95 * delta)
            status = check_termination(reduction, cost, _norm(step), _norm(x), ratio, FTOL,
                                       XTOL)
            if status is not None:
                break
            alpha *= delta / delta_new
            delta = delta_new
        if reduction > 0:
            x, f, cost = x_new, f_new, cost_new
            jm = jac(x)
            g = jm.T.dot(f)
    return x


def _norm(a: FloatArray) -> Any:
    """``numpy.linalg.norm`` of a vector: the same ``sqrt(a.dot(a))``."""
    return np.sqrt(a.dot(a))
