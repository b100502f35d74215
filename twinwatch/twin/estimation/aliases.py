"""Aliases: how a change of a parameter the window does not estimate shows in the estimates.

A window estimates some parameters (Ra and D, say) and holds or fixes the others (Ke held at
its last trusted value, the PWM drive's tau_e fixed by the commissioning). A held parameter
still acts on the machine: when it changes, the estimates absorb what they can of its effect.
To first order this is least squares' omitted-variable bias (Seber and Wild, *Nonlinear
Regression*, 1989, sec. 2.1.3 and 12.3; Ljung, *System Identification*, 2nd ed., 1999,
sec. 8.5): with ``S_E`` the window's sensitivities of the normalised residual to the estimated
parameters' logarithms and ``s_p`` that of a not-estimated ``p``, a change ``dp`` [%] moves the
estimates by

    dE = (S_E^T S_E)^-1 S_E^T s_p dp  =  a_p dp,

and the share of ``p``'s effect the estimates mimic is ``1 - |s_p - S_E a_p|^2 / |s_p|^2``.
``a_p`` is ``p``'s *alias*: its direction in the estimates. Measured on the PWM drive's twin
(a recording of its own simulation, tau_e raised 50 %, 2026-11-25): tau_e's alias in a window
that estimated Ra, Ke, J and D was Ra +0.54, Ke -0.15, J -0.35, D -0.14 % per % of tau_e,
99.8 % of its effect absorbed; that window published Ra +28.4, Ke -5.8, J -11.7, D -5.8 %:
tau_e +43.8 % +- 10.1 % (2 sigma; the plant's +50 %) read through its alias, where the
fault library read worn brushes (Ra up) at 0.85.

The diagnosis (:mod:`twinwatch.twin.diagnosis`) reads the aliases of the parameters no fault
of its library names as the unknown fault's signature in that window: several estimates that
moved together along one alias are one change the library does not know, not two faults.

Cost: one batched simulation of ``2 (n_estimated + n_candidates)`` parameter vectors (central
differences at :data:`STEP`), run by :class:`~twinwatch.twin.adaptation.TwinAdapter` only in a
window where some estimate moved beyond twice its standard error from its nameplate.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from twinwatch.twin.estimation.fit import ParameterMap, WindowFit
from twinwatch.twin.model import FloatArray

__all__ = ["STEP", "Alias", "aliases"]

#: The central differences' step in ln-parameters (1 %: an alias is read per percent, and a
#: drive's residual is not smooth at the 1e-6 steps of the estimation's own Jacobian).
STEP = 0.01
#: A candidate whose effect on the residual is below this share of the largest estimated
#: parameter's is not seen in the window at all (a warm-up constant once warm): no alias.
MIN_EFFECT = 1e-3


@dataclass(frozen=True)
class Alias:
    """A not-estimated parameter's alias in one window.

    Attributes:
        absorbed: the share (0..1) of its effect on the window's residual that the estimated
            parameters mimic (1: a change of it is invisible but through the estimates).
        moves: estimated parameter -> its change [%] per 1 % change of this parameter.
        effect: the normalised RMSE a 1 % change of it makes, nothing re-estimated.
    """

    absorbed: float
    moves: dict[str, float] = field(default_factory=dict)
    effect: float = 0.0

    def as_dict(self) -> dict[str, object]:
        return {"absorbed": self.absorbed, "moves": dict(self.moves), "effect": self.effect}


def aliases(fit: WindowFit, theta: FloatArray, estimated: Sequence[str],
            candidates: Sequence[str], ties: Mapping[str, str] | None = None,
            terms: Mapping[str, FloatArray] | None = None,
            initial: FloatArray | None = None) -> dict[str, Alias]:
    """Each candidate's alias in the estimated parameters (the module's formula).

    Args:
        fit: the window's fit problem.
        theta: the parameter vector the window's twin ran with (n_params,) [SI], in
            ``fit.model.parameter_names`` order.
        estimated: the parameters the window estimated.
        candidates: the parameters it did not (held, fused, fixed; not tied ones).
        ties: dependent parameter -> the parameter it equals (moved with it).
        terms: the meta-model terms in the twin (attach point -> values), as in the fit.
        initial: the window's initial-state offsets, as in the fit.

    Returns:
        candidate -> its :class:`Alias`; empty when nothing was estimated, and without a
        candidate whose perturbed twin blew up or that does not act in the window.
    """
    names = tuple(fit.model.parameter_names)
    est = [n for n in estimated if n in names]
    cand = [n for n in candidates if n in names and n not in est]
    if not est or not cand:
        return {}
    pmap = ParameterMap(names, (), ties)
    base = np.asarray(theta, dtype=float)
    cols = est + cand
    rows = np.repeat(base[None, :], 2 * len(cols), axis=0)
    for k, n in enumerate(cols):
        j = names.index(n)
        rows[2 * k, j] *= np.exp(STEP)
        rows[2 * k + 1, j] *= np.exp(-STEP)
    pmap.apply_ties(rows)
    r = fit.residuals(rows, terms, initial)
    if not np.all(np.isfinite(r[:2 * len(est)])):
        return {}
    # d r / d (1 % of the parameter)
    sens = (r[0::2] - r[1::2]) / (2.0 * STEP * 100.0)
    s_e = sens[:len(est)].T
    size = float(np.max(np.linalg.norm(s_e, axis=0)))
    out: dict[str, Alias] = {}
    for k, n in enumerate(cand):
        s_p = sens[len(est) + k]
        norm = float(np.linalg.norm(s_p))
        if not np.all(np.isfinite(s_p)) or norm <= MIN_EFFECT * size or norm == 0.0:
            continue
        a, *_ = np.linalg.lstsq(s_e, s_p, rcond=None)
        res = s_p - s_e @ a
        absorbed = float(np.clip(1.0 - (res @ res) / (norm * norm), 0.0, 1.0))
        out[n] = Alias(absorbed, {e: float(x) for e, x in zip(est, a, strict=True)}, norm)
    return out
