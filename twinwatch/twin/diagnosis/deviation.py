"""Graded evidence of a parameter's deviation from its nameplate (issue 34).

A fault mode's signature says a parameter moves ``up`` or ``down`` by at least ``min_pct``
percent (:class:`~twinwatch.twin.diagnosis.library.DeviationSign`). The window publishes the
parameter's deviation ``x`` [% of nameplate] with its standard error ``sd``. This module gives
the likelihood of ``x`` under a hypothesis (a set of faults present), one factor per parameter:

* no fault moves it: ``x ~ N(0, sd^2 + tau^2)``, ``tau`` the healthy machine's spread about its
  nameplate (:data:`NOMINAL_SPREAD_PCT`), mixed with a small leak ``lam``: something outside the
  model moved it by at least :data:`BROAD_MIN_PCT` in either direction;
* a fault moves it in ``direction`` by a magnitude ``m`` at least ``a`` (its ``min_pct``), ``m``
  log-uniform on ``[a, b]`` with ``b`` its ``max_pct`` (:data:`HI_PCT` unless the library says
  less; scale-free: a 2 % and a 20 % change are equally plausible a priori), observed through
  ``N(m, sd^2)``; each fault of the hypothesis acts with its ``link`` (noisy-OR), the smallest
  size and the largest ``max_pct`` of the acting faults in a direction standing for them, and
  a hypothesis moving it both ways splits the two.

One factor per parameter, whatever the sizes the faults name: a current sensor's Ra -0.8 %
(its size 0.5 %) and a winding's (1 %) are read from the same number, never counted twice, and
a tight Ra -0.8 % is evidence against a fault that leaves Ra where it is (bearing wear), which a
binary "beyond 1 %" variable cannot say.

The log-uniform density convolved with the Gaussian is taken in closed form with ``1/m``
evaluated at ``max(|x|, a)`` (exact to a few percent while ``sd`` is small against ``|x|``, and
the right tail beyond the size otherwise):
``p(x) = [Phi((x - a)/sd) - Phi((x - b)/sd)] / (clip(x, a, b) ln(b/a))`` for ``up``.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import ndtr

__all__ = ["BROAD_MIN_PCT", "HI_PCT", "NOMINAL_SPREAD_PCT", "likelihood", "moved_density"]

#: Largest deviation a fault is thought to make [% of nameplate].
HI_PCT = 300.0
#: A healthy machine's parameters scatter about their nameplate by this much [%, 1 sigma]
#: beyond their estimates' own error: the twin's model error at an operating point.
NOMINAL_SPREAD_PCT = 0.25
#: The leak's deviation (something outside the library moved the parameter): at least this.
BROAD_MIN_PCT = 1.0


def moved_density(x: float, sd: float, size: np.ndarray | float, up: bool,
                  hi: np.ndarray | float = HI_PCT) -> np.ndarray:
    """Density of an observed deviation ``x`` [%] with standard error ``sd`` [%] when the
    parameter moved ``up`` (else down) by a log-uniform magnitude in ``[size, hi]``.

    Args:
        x: the observed deviation [% of nameplate], signed.
        sd: its 1-sigma standard error [%] (> 0).
        size: the smallest magnitude [%], scalar or an array (one per hypothesis).
        hi: the largest magnitude [%] (a fault's ``max_pct``; :data:`HI_PCT` by default),
            scalar or an array like ``size``.
    Returns:
        the density [1/%], the shape of ``size``.
    """
    b = np.minimum(np.asarray(hi, dtype=float), HI_PCT)
    a = np.minimum(np.asarray(size, dtype=float), b / 2)
    y = x if up else -x
    mass = ndtr((y - a) / sd) - ndtr((y - b) / sd)
    return np.asarray(mass / (np.clip(y, a, b) * np.log(b / a)))


def likelihood(x: float, sd: float, p_up: np.ndarray, size_up: np.ndarray, p_down: np.ndarray,
               size_down: np.ndarray, leak: float, hi_up: np.ndarray | float = HI_PCT,
               hi_down: np.ndarray | float = HI_PCT) -> np.ndarray:
    """Likelihood of the observed deviation under each hypothesis (the module's model).

    Args:
        x, sd: the observed deviation and its standard error [%].
        p_up, p_down: probability that the hypothesis' faults move the parameter up / down
            (noisy-OR of their links), shape (n_hypotheses,).
        size_up, size_down: the smallest size among those faults [%] (any value where the
            probability is 0), shape (n_hypotheses,).
        leak: probability that something outside the library moved it.
        hi_up, hi_down: the largest size those faults make [%] (their ``max_pct``).
    Returns:
        p(x | hypothesis) [1/%], shape (n_hypotheses,).
    """
    spread = math.hypot(sd, NOMINAL_SPREAD_PCT)
    nominal = math.exp(-0.5 * (x / spread) ** 2) / (spread * math.sqrt(2.0 * math.pi))
    broad = 0.5 * float(moved_density(x, sd, BROAD_MIN_PCT, True)
                        + moved_density(x, sd, BROAD_MIN_PCT, False))
    base = (1.0 - leak) * nominal + leak * broad
    both = p_up * p_down
    w_up = p_up - 0.5 * both
    w_down = p_down - 0.5 * both
    none = (1.0 - p_up) * (1.0 - p_down)
    out: np.ndarray = (none * base + w_up * moved_density(x, sd, size_up, True, hi_up)
                       + w_down * moved_density(x, sd, size_down, False, hi_down))
    return out
