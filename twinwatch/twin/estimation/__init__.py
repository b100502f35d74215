"""Estimation: the parameters no sensor measures, re-estimated every window (paper Section 3.2).

The estimator is small stages composed by a short
:meth:`~twinwatch.twin.estimation.estimator.Estimator.estimate`, as pymoo separates the problem,
the algorithm and the termination:

* ``estimator``: the :class:`~twinwatch.twin.estimation.estimator.Estimator` (state carried
  between windows, the composition), its configuration and the window's result;
* ``problem``: one window's problem (search variables, bounds, warm start, fitness);
* ``search``: stage 1, the global search (warm-started PSO, paper Eq. 1-2, Table 2);
* ``polish``: stage 2, bounded least squares with the window's initial state;
* ``gate``: stage 3, the identifiability gate (priority hierarchy, hold and re-fit; nothing
  published ``estimated`` above ``max_rel_std``);
* ``check``: stage 4, the model check (white, input-independent residuals; the widening);
* ``quality``: frozen and saturated sensors, named by channel (a window with one is not sound);
* ``fusion``: stage 5, a Kalman filter on the parameters across windows;
* ``publish``: each parameter's published value and status (``suspect`` for a window that is
  not sound, ``fused`` where the fused evidence meets its own gate);

and the shared core: ``fit`` (the one fitting core every variant of the twin is scored by:
residuals, the swarm, the least-squares polish, the standard errors), ``statistics`` (residual
tests: white noise, AR(1), Ljung-Box, the residual-input test, BIC). Commissioning the
baseline from a recording uses them from its own room (:mod:`twinwatch.commissioning`).

May import: :mod:`twinwatch.twin.model` (the contract) and this room. Never a machine
(:mod:`twinwatch.twin.models`), the discovery, or anything outside the twin.
"""
