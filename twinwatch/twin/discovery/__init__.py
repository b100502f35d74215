"""Discovery: what the model lacks, found as interpretable meta-models (paper Section 3.3).

Modules: ``search`` (:class:`~twinwatch.twin.discovery.search.Discovery`, the forward
selection over candidate meta-models and its configuration), ``trigger`` (when to search: the
residual's whiteness test, combined over windows), ``separable`` (one candidate on
one window as a separable least-squares problem: its normalised input, the projection of the
coefficients, the forms without optional parameters), ``terms`` (a meta-model attached
to a model equation, its refinement across windows), ``metamodels/`` (one class per kind, paper
Table 1 and the non-smooth terms of real drives, with their registry).

May import: :mod:`twinwatch.twin.model`, :mod:`twinwatch.twin.estimation` and this room. Never
a machine (:mod:`twinwatch.twin.models`) or anything outside the twin.
"""
