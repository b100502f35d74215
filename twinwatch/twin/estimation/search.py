"""Stage 1, the global search: particle swarm optimisation, warm-started (paper Section 3.2).

The paper minimises the RMSE between measured and simulated outputs (Eq. 1-2) with a particle
swarm (Table 2: swarm 15, up to 1000 iterations, w 0.9, c1 = c2 = 2.0). twinwatch keeps the
swarm as a global search (20 iterations by default: the first window, a sudden change) and puts
the last trusted estimate in it as one particle, so a window like the last one starts at its
answer; the local polish (:mod:`~twinwatch.twin.estimation.polish`) does the rest.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import Field, StrictFloat, StrictInt

from twinwatch._table import StrictTable
from twinwatch.twin.estimation.fit import pso_minimize
from twinwatch.twin.estimation.problem import WindowProblem
from twinwatch.twin.model import FloatArray


class PSOSettings(StrictTable):
    """PSO settings (paper Table 2 for the paper's method)."""

    pop_size: StrictInt = Field(15, ge=2, description="swarm size")
    max_generations: StrictInt = Field(20, ge=1, description="iteration limit")
    w: StrictFloat = Field(0.9, description="inertia weight")
    c1: StrictFloat = Field(2.0, description="cognitive parameter")
    c2: StrictFloat = Field(2.0, description="social parameter")
    adaptive: bool = Field(False, description="pymoo's adaptive w/c1/c2 (off: the paper's)")


@dataclass
class SearchResult:
    """What the global search found.

    Attributes:
        q: the best ln-parameters (n_est,).
        cost: their normalised RMSE (paper Eq. 2, the window's measured first sample as
            initial state): the health message's PSO fitness.
        generations: PSO iterations run (0 when nothing is searched).
        time_capped: the time budget, not the iteration limit, stopped the swarm.
    """

    q: FloatArray
    cost: float
    generations: int = 0
    time_capped: bool = False


def global_search(problem: WindowProblem, settings: PSOSettings, *, rng: np.random.Generator,
                  time_budget: float) -> SearchResult:
    """Search the estimated parameters' box with pymoo's PSO, the trusted values as one
    particle (:func:`~twinwatch.twin.estimation.fit.pso_minimize`; the whole swarm is one twin
    call per iteration).

    Args:
        problem: the window's problem (bounds, warm start, fitness).
        settings: the swarm (``[estimation.pso]``).
        rng: the estimator's generator; the same state and no time cap give the same result.
        time_budget: wall-time cap [s] (``[estimation] time_budget``).

    Returns:
        The best particle; with nothing to estimate, the warm start and its cost.
    """
    q0 = problem.start()
    if settings.max_generations > 0 and problem.n_est:
        sw = pso_minimize(problem.cost, problem.xl, problem.xu, settings, rng=rng,
                          time_budget=time_budget, seeds=q0[None, :])
        return SearchResult(sw.x, sw.cost, sw.generations, sw.time_capped)
    return warm_start(problem)


def warm_start(problem: WindowProblem) -> SearchResult:
    """No global search: the trusted values (clipped to the bounds) and their cost (one twin
    call), the local-first strategy's start when the trusted twin still fits
    (:class:`~twinwatch.twin.estimation.estimator.Estimator`). Not the last window's optimum:
    on a drive whose output clamps, the residual is not smooth, and from there the polish
    can stop in another basin."""
    q0 = problem.start()
    return SearchResult(q0, float(problem.cost(q0[None, :])[0]))
