"""The local path's polish of the admitted parameters: bounded Levenberg-Marquardt.

A local window (:func:`~twinwatch.twin.estimation.polish.polish_admitted`) moves only the
parameters the last window's gate found determined, and the initial-state offsets, from the
trusted values: a small, well-posed least-squares problem started near its optimum. scipy's
trust-region reflective loop (:mod:`~twinwatch.twin.estimation._trf`) spends about 0.2 ms
of Python a call on it beyond the twin (an SVD and the reflective bookkeeping each step);
here a step is the normal equations of ``n <= 10`` columns, a few microseconds.

The method: Levenberg (1944), Marquardt (J. SIAM 11(2), 1963): the step ``s`` solves
``(J^T J + mu diag(J^T J)) s = -J^T r`` (Marquardt's scaling: the step is invariant to the
variables' units), ``mu`` updated by the gain ratio ``rho`` (the cost's fall over the fall the
linearisation predicts) as Nielsen's rule has it (IMM-REP-1999-05; Madsen, Nielsen and
Tingleff, *Methods for non-linear least squares problems*, 2004, Eq. 3.15): a step taken
multiplies ``mu`` by ``max(1/3, 1 - (2 rho - 1)^3)``, a step refused by ``nu`` (2, doubled at
each refusal in a row): no oscillation between a step taken and one refused. Bounds by
projection: a variable on a bound with the gradient pushing out of the box is held, the others
step, and the trial point is clipped into the box (Kanzow, Yamashita and Fukushima, J. Comput.
Appl. Math. 172, 2004: the projected LM keeps its local quadratic convergence). It stops as
``least_squares`` does, with the same tolerances (:data:`~twinwatch.twin.estimation._trf.XTOL`,
``FTOL``, ``GTOL``, ``MAX_NFEV``): a step shorter than ``XTOL (XTOL + |x|)``, a cost falling
by less than ``FTOL`` of itself in a step that did as predicted, or a projected gradient
below ``GTOL`` (scaled by the distance to the bounds, as there). Where the problem is
determined (the gate's test) both loops reach the same optimum to those tolerances;
``tests/test_trf.py`` holds them to each other on real windows.

Not used from the swarm's best (:func:`~twinwatch.twin.estimation.polish.polish`): that
polish moves every estimated parameter, some along a valley the data do not determine, where
the point a loop stops at depends on its path (docs/design-estimation.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from twinwatch.twin.estimation._trf import FTOL, GTOL, MAX_NFEV, XTOL
from twinwatch.twin.model import FloatArray

#: The first damping, a share of each variable's curvature (Nielsen, IMM-REP-1999-05, tau).
MU_START = 1e-3


def levenberg_marquardt(fun_jac: Callable[[FloatArray], tuple[FloatArray, FloatArray]],
                        x0: FloatArray, lower: FloatArray, upper: FloatArray
                        ) -> tuple[FloatArray, int]:
    """Minimise ``|r(x)|^2`` within ``lower <= x <= upper``.

    Args:
        fun_jac: at a point (n,), the residuals (M,) and their Jacobian transposed (n, M),
            from one call (one batched twin call: the point and its forward differences).
        x0: the start (n,), within the bounds.
        lower, upper: the bounds (n,), finite or not, ``lower < upper``.

    Returns:
        The solution (n,) and the calls of ``fun_jac`` made.

    Raises:
        ValueError: ``x0`` outside the bounds, or the residuals not finite at it.
    """
    x = np.array(x0, dtype=float)
    lo = np.asarray(lower, dtype=float)
    hi = np.asarray(upper, dtype=float)
    if not ((lo <= x) & (x <= hi)).all():
        raise ValueError("Initial guess is outside of provided bounds")
    r, jt = fun_jac(x)
    calls = 1
    cost = float(r @ r)
    if not math.isfinite(cost):
        raise ValueError("Residuals are not finite in the initial point.")
    a = jt @ jt.T
    g = jt @ r
    mu, nu = MU_START, 2.0
    while calls < MAX_NFEV:
        # a variable on its bound whose gradient points out of the box is held there
        held = ((x <= lo) & (g > 0)) | ((x >= hi) & (g < 0))
        free = ~held
        # the gradient scaled by the distance to the bound it points to (1 with none), as
        # ``least_squares``' trust-region reflective loop tests it (Coleman and Li's scaling)
        reach = np.where(g < 0, hi - x, x - lo)
        reach = np.where(np.isfinite(reach), reach, 1.0)
        if not np.abs(g * reach)[free].max(initial=0.0) > GTOL:
            break
        d = a.diagonal()
        af = a[np.ix_(free, free)] if held.any() else a.copy()
        df = d[free]
        af[np.diag_indices_from(af)] += mu * np.where(df > 0, df, 1.0)
        try:
            sf = np.linalg.solve(af, -g[free])
        except np.linalg.LinAlgError:
            mu, nu = mu * nu, nu * 2.0
            continue
        step = np.zeros_like(x)
        step[free] = sf
        trial = np.clip(x + step, lo, hi)
        step = trial - x
        short = math.sqrt(float(step @ step)) < XTOL * (XTOL + math.sqrt(float(x @ x)))
        predicted = -float(2.0 * g @ step + step @ a @ step)
        r_new, jt_new = fun_jac(trial)
        calls += 1
        cost_new = float(r_new @ r_new)
        actual = cost - cost_new if math.isfinite(cost_new) else -math.inf
        rho = actual / predicted if predicted > 0 else -math.inf
        if actual > 0:
            x, r, jt = trial, r_new, jt_new
            a, g = jt @ jt.T, jt @ r
            small_fall = actual < FTOL * cost and rho > 0.25
            cost = cost_new
            mu *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
            if short or small_fall:
                break
        elif short:
            break    # no shorter step helps: x is the optimum to the tolerance
        else:
            mu, nu = mu * nu, nu * 2.0
    return x, calls


__all__ = ["levenberg_marquardt"]
