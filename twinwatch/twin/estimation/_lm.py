"""The local path's polish of the admitted parameters: bounded Levenberg-Marquardt.

A local window (:func:`~twinwatch.twin.estimation.polish.polish_admitted`) moves only the
parameters the last window's gate found determined, and the initial-state offsets, from the
trusted values: a small, well-posed least-squares problem started near its optimum. scipy's
trust-region reflective loop (:mod:`~twinwatch.twin.estimation._trf`) spent about 0.8 ms of
CPU a window on it beyond the twin calls (an SVD and the reflective bookkeeping each step;
the default motor's windows from 400 s in ``benchmarks/bench_window.py``); this loop spends
about 0.06 ms: a step is one compiled call on the normal equations of a few columns.

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
from numba import njit

from twinwatch.twin.estimation._trf import FTOL, GTOL, MAX_NFEV, XTOL
from twinwatch.twin.model import FloatArray

#: The first damping, a share of each variable's curvature: Nielsen's tau for a start near
#: the optimum (IMM-REP-1999-05; Madsen, Nielsen and Tingleff 2004, Sec. 3.2: 1e-6 to 1e-3,
#: the larger for a start that is not known to be close; a local window starts from the
#: trusted values, which the last window may have left a few standard errors away).
MU_START = 1e-3
#: A damping beyond 1/eps of float64 (4.5e15): the damped step is below the rounding of the
#: undamped one, nothing can move, and a matrix that did not factor up to here never will
#: (a non-finite Jacobian entry): the loop stops.
MU_GIVE_UP = 1e16


@njit(cache=True, nogil=True)
def _step(jt: FloatArray, r: FloatArray, x: FloatArray, lo: FloatArray, hi: FloatArray,
          mu: float, out: FloatArray) -> tuple[float, float, bool]:  # pragma: no cover - compiled
    """One damped step from ``x`` (n,) with residuals ``r`` (M,) and Jacobian transposed
    ``jt`` (n, M), clipped into ``[lo, hi]``: written to ``out`` (n,). Returns (the largest
    bound-scaled gradient of the free variables, the predicted fall of ``|r|^2``, whether
    the damped normal matrix was positive definite)."""
    n, m = jt.shape
    a = np.zeros((n, n))
    g = np.zeros(n)
    for i in range(n):
        gi = 0.0
        for k in range(m):
            gi += jt[i, k] * r[k]
        g[i] = gi
        for j in range(i + 1):
            s = 0.0
            for k in range(m):
                s += jt[i, k] * jt[j, k]
            a[i, j] = s
            a[j, i] = s
    # a variable on its bound whose gradient points out of the box is held there; the
    # gradient scaled by the distance to the bound it points to (1 with none), as
    # ``least_squares``' trust-region reflective loop tests it (Coleman and Li's scaling)
    free = np.ones(n, dtype=np.bool_)
    gmax = 0.0
    for i in range(n):
        if (x[i] <= lo[i] and g[i] > 0) or (x[i] >= hi[i] and g[i] < 0):
            free[i] = False
            continue
        reach = hi[i] - x[i] if g[i] < 0 else x[i] - lo[i]
        if not np.isfinite(reach):
            reach = 1.0
        gmax = max(gmax, abs(g[i] * reach))
    # (A + mu diag A) s = -g over the free variables, by Cholesky
    c = np.zeros((n, n))
    for i in range(n):
        out[i] = 0.0
        if not free[i]:
            continue
        for j in range(i + 1):
            if not free[j]:
                continue
            s = a[i, j]
            if i == j:
                s += mu * (a[i, i] if a[i, i] > 0 else 1.0)
            for k in range(j):
                if free[k]:
                    s -= c[i, k] * c[j, k]
            if i == j:
                if not s > 0:
                    return gmax, 0.0, False
                c[i, i] = np.sqrt(s)
            else:
                c[i, j] = s / c[j, j]
    for i in range(n):          # forward: C y = -g
        if free[i]:
            s = -g[i]
            for k in range(i):
                if free[k]:
                    s -= c[i, k] * out[k]
            out[i] = s / c[i, i]
    for i in range(n - 1, -1, -1):  # back: C^T s = y
        if free[i]:
            s = out[i]
            for k in range(i + 1, n):
                if free[k]:
                    s -= c[k, i] * out[k]
            out[i] = s / c[i, i]
    for i in range(n):          # clipped into the box: the step actually taken
        out[i] = min(max(x[i] + out[i], lo[i]), hi[i]) - x[i]
    pred = 0.0
    for i in range(n):
        t = 2.0 * g[i]
        for j in range(n):
            t += a[i, j] * out[j]
        pred -= t * out[i]
    return gmax, pred, True


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
    step = np.empty_like(x)
    mu, nu = MU_START, 2.0
    while calls < MAX_NFEV:
        gmax, predicted, definite = _step(jt, r, x, lo, hi, mu, step)
        if not gmax > GTOL:
            break
        if not definite:          # a Jacobian with a non-finite entry never factors
            mu, nu = mu * nu, nu * 2.0
            if not mu < MU_GIVE_UP:
                break
            continue
        trial = x + step
        short = math.sqrt(float(step @ step)) < XTOL * (XTOL + math.sqrt(float(x @ x)))
        r_new, jt_new = fun_jac(trial)
        calls += 1
        cost_new = float(r_new @ r_new)
        actual = cost - cost_new if math.isfinite(cost_new) else -math.inf
        rho = actual / predicted if predicted > 0 else -math.inf
        if actual > 0:
            x, r, jt = trial, r_new, jt_new
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
