"""Estimation: the parameters no sensor measures, re-estimated every window (paper Section 3.2).

The :class:`~twinwatch.twin.estimation.estimator.Estimator` runs small stages, one module
each, on one window's ``problem`` (its module docstring lists them in order). The shared core:
``fit`` (the one fitting core every variant of the twin is scored by: residuals, the swarm, the
least-squares polish, the standard errors) and ``statistics`` (residual tests). Commissioning the
baseline from a recording uses them from its own room (:mod:`twinwatch.commissioning`).

May import: :mod:`twinwatch.twin.model` (the contract) and this room. Never a machine
(:mod:`twinwatch.twin.models`), the discovery, or anything outside the twin.
"""
