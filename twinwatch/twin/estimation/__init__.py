"""Estimation: the parameters no sensor measures, re-estimated every window (paper Section 3.2).

Modules: ``estimator`` (the :class:`~twinwatch.twin.estimation.estimator.Estimator`, its
configuration and the window's result), ``fit`` (the one fitting core every variant of the twin
is scored by: residuals, the swarm, the least-squares polish, the standard errors),
``statistics`` (residual tests: white noise, AR(1), Ljung-Box, the residual-input test, BIC),
``fusion`` (a Kalman filter on the parameters across windows), ``identify`` (commissioning the
baseline from a recording).

May import: :mod:`twinwatch.twin.model` (the contract) and this room. Never a machine
(:mod:`twinwatch.twin.models`), the discovery, or anything outside the twin.
"""
