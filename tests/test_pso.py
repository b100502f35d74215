"""The swarm on arrays (:func:`twinwatch.twin.estimation.fit._pso_loop`, issue 22) is pymoo's PSO:
the same particles, the same best, to the bit, as pymoo's ``PSO`` class (``adaptive=False``)
run on the same initial swarm and seed, with and without the patience stop, with a warm start
among the particles; only pymoo's per-particle bookkeeping is gone."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from twinwatch.twin.estimation.fit import _swarm_problem_class, pso_minimize


def rosenbrock(x: np.ndarray) -> np.ndarray:
    return np.sum(100.0 * (x[:, 1:] - x[:, :-1] ** 2) ** 2 + (1.0 - x[:, :-1]) ** 2, axis=1)


def coarse_bowl(x: np.ndarray) -> np.ndarray:
    """Flat steps: the best cost stops moving, so the patience stop ends the run."""
    return np.round(np.sum((x - 0.3) ** 2, axis=1), 2)


def pymoo_pso(cost, lo, hi, settings, rng, seeds=None, patience=None):
    """The swarm as twinwatch ran it through pymoo's ``PSO`` class and ``minimize``."""
    from pymoo.algorithms.soo.nonconvex.pso import PSO
    from pymoo.core.population import Population
    from pymoo.operators.sampling.lhs import LHS
    from pymoo.optimize import minimize
    from pymoo.termination.collection import TerminationCollection
    from pymoo.termination.ftol import SingleObjectiveSpaceTermination
    from pymoo.termination.max_gen import MaximumGenerationTermination
    from pymoo.termination.robust import RobustTermination

    calls = [0]

    def counted(x):
        calls[0] += 1
        return cost(x)

    problem = _swarm_problem_class()(counted, lo, hi)
    init = LHS()(problem, settings.pop_size, random_state=rng).get("X")
    if seeds is not None:
        init[0] = np.clip(seeds[0], lo, hi)
    algo = PSO(pop_size=settings.pop_size, sampling=Population.new(X=init), w=settings.w,
               c1=settings.c1, c2=settings.c2, adaptive=False)
    parts = [MaximumGenerationTermination(settings.max_generations)]
    if patience is not None:
        parts.append(RobustTermination(SingleObjectiveSpaceTermination(tol=1e-9),
                                       period=patience))
    res = minimize(problem, algo, TerminationCollection(*parts),
                   seed=int(rng.integers(2**31)), verbose=False, copy_algorithm=False)
    return np.asarray(res.X, dtype=float).reshape(-1), float(res.F[0]), calls[0]


@pytest.mark.parametrize("cost, n, patience, seed", [
    (rosenbrock, 4, None, 3), (rosenbrock, 2, None, 11), (coarse_bowl, 3, 8, 0),
    (coarse_bowl, 3, 8, 4), (rosenbrock, 5, 8, 7)])
def test_the_array_swarm_is_pymoos_pso_to_the_bit(cost, n, patience, seed):
    lo, hi = np.full(n, -2.0), np.full(n, 2.0)
    s = SimpleNamespace(pop_size=15, max_generations=40, w=0.9, c1=2.0, c2=2.0,
                        adaptive=False)
    warm = np.full((1, n), 0.5)
    calls = [0]

    def counted(x):
        calls[0] += 1
        return cost(x)

    ours = pso_minimize(counted, lo, hi, s, rng=np.random.default_rng(seed),
                        time_budget=100.0, seeds=warm, patience=patience)
    x, f, pymoo_calls = pymoo_pso(cost, lo, hi, s, np.random.default_rng(seed), seeds=warm,
                                  patience=patience)
    assert np.array_equal(ours.x, x) and ours.cost == f
    # the same swarm evaluations; each one counted as a generation, the initial swarm first
    assert calls[0] == pymoo_calls == ours.generations
    assert (ours.generations < s.max_generations) == (patience is not None)
    assert not ours.time_capped


def test_a_time_capped_swarm_says_so():
    lo, hi = np.full(2, -2.0), np.full(2, 2.0)
    s = SimpleNamespace(pop_size=15, max_generations=10**6, w=0.9, c1=2.0, c2=2.0,
                        adaptive=False)
    r = pso_minimize(rosenbrock, lo, hi, s, rng=np.random.default_rng(1), time_budget=0.05)
    assert r.time_capped and 1 <= r.generations < s.max_generations
    assert r.cost == pytest.approx(float(rosenbrock(r.x[None, :])[0]))
