"""Stage 2, the polish: bounded least squares from the swarm's best (output-error fit).

pymoo's PSO alone stalls short of the best fit (more iterations do not help).
From its best particle, scipy's trust-region reflective least squares
(Jacobian from one batched twin call) reaches the optimum of the normalised residuals of paper
Eq. 2, jointly with the window's initial-state offsets (nuisance variables: a noisy first sample
otherwise leaves a transient in every residual and biases the estimates). Its Jacobian at the
optimum is what the identifiability gate and the fusion read.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from twinwatch.twin.estimation.fit import residual_variances
from twinwatch.twin.estimation.problem import FitPoint, WindowProblem
from twinwatch.twin.model import FloatArray

#: The admitted-only polish's loop (:meth:`~twinwatch.twin.estimation.fit.LocalFit.refine`'s
#: ``method``): Levenberg-Marquardt, the parameters it moves being the ones the gate found
#: determined (:mod:`~twinwatch.twin.estimation._lm`).
POLISH_METHOD: Literal["trf", "lm"] = "lm"


@dataclass
class Polished:
    """The polished optimum over every estimated parameter and the initial state.

    Attributes:
        point: the optimum (search vector, residuals (M,), Jacobian (M, n_est + n_init)).
        row_var: variance of each residual row (M,), per output (floored by ``model_error``,
            inflated by its AR(1) factor): the weights of the window's evidence in the fusion.
        nuisance: the fitted initial-state offsets (n_init,), normalised: the fusion
            linearises the window at them.
    """

    point: FitPoint
    row_var: FloatArray
    nuisance: FloatArray


def polish(problem: WindowProblem, q: FloatArray, *, enabled: bool, model_error: float
           ) -> Polished:
    """Polish ln-parameters ``q`` (n_est,) and the initial-state offsets (from 0) by bounded
    least squares (:meth:`~twinwatch.twin.estimation.fit.LocalFit.refine`).

    Args:
        problem: the window's problem.
        q: the global search's best (n_est,).
        enabled: ``[estimation] polish``; off, only the residuals and the Jacobian at ``q``
            are computed.
        model_error: the floor of the normalised residual level (``[estimation]
            model_error``).

    Returns:
        The optimum, its row variances and initial-state offsets.
    """
    local = problem.local
    n_free = problem.n_est + problem.nuisance.size
    v, r, jac = local.refine(local.start(q), np.arange(n_free), polish=enabled)
    row_var = residual_variances(r, problem.n_out, model_error, n_free)
    return Polished(FitPoint(v, r, jac), row_var, v[problem.n_est:].copy())


def polish_admitted(problem: WindowProblem, q: FloatArray, selected: list[int], *,
                    model_error: float) -> Polished:
    """Polish only ``selected`` (positions in the priority list: the parameters the last
    window's gate admitted) and the initial-state offsets, the other estimated parameters at
    their trusted values, from ln-parameters ``q`` (n_est,); the Jacobian at the result has
    every column (the estimated parameters', then the initial state's: one sensitivity call),
    so the gate can check that this window admits the same set
    (:meth:`~twinwatch.twin.estimation.gate.IdentifiabilityGate.confirm`).

    When it does, this is the point :func:`polish` and the gate's re-fit holding the others
    reach, without the first trust-region run moving the held parameters along the valley
    the gate then holds.

    Returns:
        As :func:`polish` (the row variances with the same count of fitted variables).
    """
    local = problem.local
    n_est = problem.n_est
    n_free = n_est + problem.nuisance.size
    v = local.start(q)
    held = [k for k in range(n_est) if k not in selected]
    if held:
        v[held] = problem.trusted_ln(held)
    active = np.concatenate([np.asarray(selected, dtype=int), problem.nuisance])
    v, r, jac = local.refine(v, active, stats=np.arange(n_free), method=POLISH_METHOD)
    row_var = residual_variances(r, problem.n_out, model_error, n_free)
    return Polished(FitPoint(v, r, jac), row_var, v[n_est:].copy())
