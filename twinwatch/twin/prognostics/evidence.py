"""What one window says about each parameter, for its trend.

A trend is fitted to *independent* evidence, one point per window, with its published
uncertainty:

* a parameter the window **estimated** (status ``estimated``, the window trusted): its value and
  standard error (``value * rel_std``);
* a parameter this window does not determine (status ``fused`` or ``held``) but on which it
  still carries information for the fusion: the fused value of the Kalman filter
  (:mod:`~twinwatch.twin.estimation.fusion`) cannot be used point by point (each one carries
  all the windows before it: a fit would count them again and again), so the window's *own*
  share of that evidence is recovered from the filter's prediction and update,
  in information form (the filter's measurement is the window's least-squares problem)::

      I_w     = [P_post^-1 - P_pred^-1]_levels            the window's information
      I_w z_w = [P_post^-1 x_post - P_pred^-1 x_pred]_levels

  on the logarithms of the parameters, ``z_w`` the window's estimate and ``I_w^+`` its
  covariance. A window the filter treated as a jump (its prediction inflated) has no such share
  and gives no evidence; nor does a window that was not trusted, or one that carries almost no
  information (relative standard error above ``max_rel_std``).

A held value itself is never evidence (it is the last trusted one, not new information), nor are
tied and fixed parameters.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from twinwatch.twin.estimation.estimator import WindowEstimate
from twinwatch.twin.model import FloatArray
from twinwatch.twin.prognostics.degradation import pinv_sym
from twinwatch.twin.prognostics.trend import Evidence

__all__ = ["fused_share", "window_evidence"]


def fused_share(names: Sequence[str], prior: tuple[FloatArray, FloatArray],
                posterior: tuple[FloatArray, FloatArray]) -> dict[str, tuple[float, float]]:
    """The window's own estimate of each parameter from the fusion's prediction and update
    (module docstring).

    Args:
        names: the fused parameters, in the filter's order (``n`` of them; the state holds
            their logarithms first, then, for the trend model, their rates).
        prior: the filter's prediction at the window (mean (n_state,), covariance).
        posterior: its state after the window.

    Returns:
        parameter -> (value [SI], relative standard error) for the parameters the window
        informed.
    """
    n = len(names)
    x0, p0 = (np.asarray(a, dtype=float) for a in prior)
    x1, p1 = (np.asarray(a, dtype=float) for a in posterior)
    if x0.shape != x1.shape or p0.shape != p1.shape or x0.size < n:
        return {}
    try:
        y0 = pinv_sym(p0)
        y1 = pinv_sym(p1)
    except np.linalg.LinAlgError:
        return {}
    info = (y1 - y0)[:n, :n]
    info = 0.5 * (info + info.T)
    # Below rounding of the posterior's own information: the window told it nothing.
    told = np.diag(info) > 1e-9 * np.abs(np.diag(y1)[:n])
    idx = np.flatnonzero(told)
    if not idx.size:
        return {}
    info = info[np.ix_(idx, idx)]
    names = [names[int(i)] for i in idx]
    b_full = (y1 @ x1 - y0 @ x0)[:n]
    b = b_full[idx]
    w, v = np.linalg.eigh(info)
    big = max(float(np.max(np.abs(w))), 1e-300)
    keep = w > 1e-12 * big
    if not np.any(keep):
        return {}
    inv = (v[:, keep] / w[keep]) @ v[:, keep].T
    # A parameter with a share in a direction the window does not inform has no estimate
    # of its own (infinite variance, not the minimum-norm solution's).
    blind = np.sum(v[:, ~keep] ** 2, axis=1) > 1e-8
    z = inv @ b
    out: dict[str, tuple[float, float]] = {}
    for i, name in enumerate(names):
        var = float(inv[i, i])
        if blind[i] or not (var > 0 and math.isfinite(var)) or not math.isfinite(z[i]):
            continue
        out[name] = (float(math.exp(z[i])), math.sqrt(var))
    return out


def window_evidence(estimate: WindowEstimate, t: float, *,
                    fused: Mapping[str, tuple[float, float]] | None = None,
                    max_rel_std: float = 0.5) -> dict[str, Evidence]:
    """Each parameter's evidence from one window (module docstring).

    Args:
        estimate: the window's estimate.
        t: the window's middle [s].
        fused: :func:`fused_share` of the window (None: no fusion, or a jump).
        max_rel_std: largest relative standard error of evidence worth a point.

    Returns:
        parameter -> evidence, for the parameters the window informs.
    """
    out: dict[str, Evidence] = {}
    if not estimate.trusted:
        return out
    for name, status in estimate.status.items():
        if status == "estimated":
            value = estimate.values[name]
            rel = estimate.rel_std.get(name)
            if rel is None or not (rel > 0) or rel > max_rel_std or not value:
                continue
            out[name] = Evidence(t, float(value), abs(float(value)) * float(rel), "estimated")
        elif status in ("fused", "held", "suspect") and fused and name in fused:
            value, rel = fused[name]
            if 0 < rel <= max_rel_std:
                out[name] = Evidence(t, value, abs(value) * rel, "fused")
    return out
