"""The local fit's bounded least squares: scipy's trust-region reflective loop, called directly.

``scipy.optimize.least_squares(method="trf")`` spends most of a window's polish in its generic
wrapper (argument checks, the ``VectorFunction`` that caches and counts, the result's
packaging), more than in the twin calls themselves. :func:`trust_region_reflective` prepares
what the wrapper prepares for our one case (dense Jacobian, linear loss, unit ``x_scale``,
``tr_solver="exact"``) and runs scipy's own ``trf_bounds`` (``trf_no_bounds`` when no bound is
finite; Branch, Coleman and Li, SIAM J. Sci. Comput. 21(1), 1999), so the iterates are
scipy's, bit for bit; ``tests/test_trf.py`` holds it to the public ``least_squares`` on real
windows, so a scipy release that changes either fails there.
"""

from __future__ import annotations

from collections.abc import Callable

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
    from scipy.optimize._lsq.trf import trf_bounds, trf_no_bounds

    x0 = np.atleast_1d(x0).astype(float)
    lb = np.asarray(lower, dtype=float)
    ub = np.asarray(upper, dtype=float)
    if (lb >= ub).any():
        raise ValueError("Each lower bound must be strictly less than each upper bound.")
    if not in_bounds(x0, lb, ub):
        raise ValueError("Initial guess is outside of provided bounds")
    x0 = make_strictly_feasible(x0, lb, ub)
    f0 = np.atleast_1d(fun(x0))
    j0 = np.atleast_2d(jac(x0))
    if not np.isfinite(f0).all():
        raise ValueError("Residuals are not finite in the initial point.")
    scale = np.ones_like(x0)
    if (lb == -np.inf).all() and (ub == np.inf).all():
        sol = trf_no_bounds(fun, jac, x0, f0, j0, FTOL, XTOL, GTOL, MAX_NFEV, scale, None,
                            "exact", {}, 0)
    else:
        sol = trf_bounds(fun, jac, x0, f0, j0, lb, ub, FTOL, XTOL, GTOL, MAX_NFEV, scale,
                         None, "exact", {}, 0)
    x: FloatArray = sol.x
    return x
