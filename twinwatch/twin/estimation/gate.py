"""Stage 3, the identifiability gate: which parameters does this window determine?

At the polished optimum the Jacobian ``S`` of the normalised residuals with respect to the
ln-parameters gives each parameter's relative standard error (the sandwich covariance of
:func:`~twinwatch.twin.estimation.fit.parameter_covariance`, with
:data:`~twinwatch.twin.estimation.fit.NUMERICAL_SHARE`; the window's initial state, and the
scale of each meta-model term the twin holds, always free beside them: a parameter whose effect
a term can take is not determined by the window). Parameters
are admitted in the configured priority order while every admitted one keeps its relative
standard error at most ``max_rel_std``; the first that fails and every one after it are *held*
at their last trusted value, with the reason, and the admitted ones are re-fitted with them
held. The priority list is a hierarchy: a lower-priority parameter that trades off with a held
one (Ke with D in a quasi-static window) would otherwise absorb the held one's drift.

The rule the gate keeps to the end: nothing is published ``estimated`` above ``max_rel_std``.
The re-fit with the others held, or a failed model check that widens the standard errors, can
push an admitted parameter over it; it is then held too (:meth:`IdentifiabilityGate.enforce`),
published at its trusted value, never at the window's estimate, and the others are re-fitted
with it held.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from twinwatch.twin.estimation import polish
from twinwatch.twin.estimation.fit import NUMERICAL_SHARE, relative_std
from twinwatch.twin.estimation.polish import Polished
from twinwatch.twin.estimation.problem import FitPoint, WindowProblem
from twinwatch.twin.estimation.statistics import ModelCheck
from twinwatch.twin.model import FloatArray


@dataclass
class GateDecision:
    """What the gate admitted.

    Attributes:
        selected: positions (in the priority list ``estimate``) of the parameters this window
            determines, in priority order.
        rel_std: position -> relative standard error (1-sigma, fraction) of the admitted
            parameters (after a gate's re-fit, also of parameters it then held).
        held: estimated parameter -> why this window does not determine it (prose).
        gain: admitted position -> {held position: d ln(estimate) / d ln(held value)}, the
            estimate's sensitivity to each value it was fitted with held
            (:meth:`IdentifiabilityGate.propagate_held`; empty before).
    """

    selected: list[int]
    rel_std: dict[int, float]
    held: dict[str, str]
    gain: dict[int, dict[int, float]] = dataclasses.field(default_factory=dict)

    def widened(self, factor: float) -> GateDecision:
        """The same decision with every standard error multiplied by ``factor``."""
        return dataclasses.replace(self, rel_std={k: v * factor
                                                  for k, v in self.rel_std.items()})


class IdentifiabilityGate:
    """The identifiability gate of one estimator.

    Args:
        estimate: the estimated parameters, in priority order.
        max_rel_std: largest relative standard error of a published estimate
            (``[estimation] max_rel_std``).
        model_error: floor of the normalised residual level (``[estimation] model_error``).
        n_out: outputs interleaved in the residuals.
    """

    def __init__(self, estimate: Sequence[str], max_rel_std: float, model_error: float,
                 n_out: int) -> None:
        self.names = tuple(estimate)
        self.limit = max_rel_std
        self.model_error = model_error
        self.n_out = n_out

    def relative_std(self, jac: FloatArray, r: FloatArray) -> FloatArray:
        """Relative standard errors (n,) of the ln-parameter columns of ``jac`` (M, n) at
        residuals ``r`` (M,) (:func:`~twinwatch.twin.estimation.fit.relative_std`)."""
        return relative_std(jac, r, self.n_out, self.model_error, NUMERICAL_SHARE)

    def select(self, jac: FloatArray, r: FloatArray,
               unexcited: Mapping[str, str] | None = None, n_nuisance: int = 0,
               unobservable: Mapping[str, str] | None = None
               ) -> tuple[list[int], dict[int, float], dict[int, str]]:
        """Admit parameters in priority order while all admitted stay determined.

        Args:
            jac: (M, n_est + n_nuisance), the parameters' columns then the nuisance ones (the
                window's initial state), which are always in the fit: a parameter is
                determined only if it is determined beside them.
            r: (M,) normalised residuals at the optimum.
            unexcited: parameters the model says this window does not excite
                (:meth:`TwinModel.excitation`), with the reason; held like undetermined ones.
            n_nuisance: nuisance columns at the end of ``jac``.
            unobservable: parameters not observable at this sample rate
                (:meth:`TwinModel.time_constants`), with the reason: held, and skipped without
                holding the ones after them (unlike an undetermined or unexcited one: the
                others' evidence does not trade off with a dynamic the samples do not see).

        Returns:
            (admitted positions, their relative standard errors, position -> reason for each
            parameter not admitted).
        """
        selected: list[int] = []
        rel: dict[int, float] = {}
        reasons: dict[int, str] = {}
        blocked: str | None = None
        n_par = jac.shape[1] - n_nuisance
        nuis = list(range(n_par, jac.shape[1]))
        for k in range(n_par):
            name = self.names[k]
            if unobservable and name in unobservable:
                reasons[k] = f"{unobservable[name]}: held at last trusted value"
                continue
            if blocked is not None:
                reasons[k] = (f"held with {blocked} (lower priority): held at last trusted "
                              "value")
                continue
            if unexcited and name in unexcited:
                blocked = name
                reasons[k] = f"{unexcited[name]}: held at last trusted value"
                continue
            cand = [*selected, k]
            sd = self.relative_std(jac[:, cand + nuis], r)[:len(cand)]
            if (sd <= self.limit).all():
                selected = cand
                rel = dict(zip(cand, sd, strict=True))
                continue
            blocked = name
            reasons[k] = self._why_not(jac, r, cand, sd, nuis)
        return selected, rel, reasons

    def _why_not(self, jac: FloatArray, r: FloatArray, cand: list[int], sd: FloatArray,
                 nuis: list[int]) -> str:
        """Why the last of ``cand`` is not admitted: undetermined even alone, or not separable
        from the admitted parameter whose standard error it spoils most."""
        limit = self.limit
        k = cand[-1]
        alone = float(self.relative_std(jac[:, [k, *nuis]], r)[0])
        if alone > limit:
            return (f"not determined by this window (relative std {alone:.2g} > "
                    f"{limit:.2g}): held at last trusted value")
        worst = max(range(len(cand) - 1), key=lambda i: sd[i] / limit, default=None)
        other = self.names[cand[worst]] if worst is not None else "others"
        return f"not separable from {other} in this window: held at last trusted value"

    @staticmethod
    def _with_terms(problem: WindowProblem, point: FitPoint) -> tuple[FloatArray, int]:
        """The Jacobian :meth:`select` reads: ``point``'s (the parameters, then the initial
        state) with a column per held meta-model term's scale appended
        (:meth:`~twinwatch.twin.estimation.fit.LocalFit.term_sensitivity`), and the number
        of nuisance columns (the initial state's and the terms')."""
        n_nuis = problem.nuisance.size
        if not problem.terms:
            return point.jac, n_nuis
        cols = problem.local.term_sensitivity(point.v)
        return np.hstack([point.jac, cols]), n_nuis + cols.shape[1]

    def admit(self, problem: WindowProblem, polished: Polished,
              unexcited: Mapping[str, str] | None = None,
              unobservable: Mapping[str, str] | None = None) -> tuple[GateDecision, FitPoint]:
        """Select the parameters the polished optimum determines and, if some are held,
        re-fit the admitted ones (and the initial state) with the held ones at their trusted
        values.

        Args:
            problem: the window's problem.
            polished: the optimum over every estimated parameter.
            unexcited, unobservable: see :meth:`select`.

        Returns:
            (the decision, the point the window's twin is simulated at: the re-fit's, with
            the admitted parameters' standard errors from its Jacobian).
        """
        point = polished.point
        jac, n_nuis = self._with_terms(problem, point)
        selected, rel_std, reasons = self.select(jac, point.r, unexcited, n_nuis, unobservable)
        held = {name: reasons[k] for k, name in enumerate(self.names) if k not in selected}
        if len(selected) < problem.n_est:
            held_pos = [k for k in range(problem.n_est) if k not in selected]
            point, refitted = self._refit_holding(problem, point, selected, held_pos)
            if refitted:
                sd = self.relative_std(point.jac, point.r)[:len(selected)]
                rel_std = dict(zip(selected, sd, strict=True))
        return GateDecision(selected, rel_std, held), point

    def confirm(self, problem: WindowProblem, polished: Polished, selected: list[int],
                unexcited: Mapping[str, str] | None = None,
                unobservable: Mapping[str, str] | None = None
                ) -> tuple[GateDecision, FitPoint] | None:
        """The gate on a :func:`~twinwatch.twin.estimation.polish.polish_admitted` point
        (only ``selected`` moved): when :meth:`select` admits the same set there, the
        decision and the point :meth:`admit` gives after its re-fit holding the others; None
        when it admits another set (the caller polishes every parameter and runs
        :meth:`admit`)."""
        point = polished.point
        jac, n_nuis = self._with_terms(problem, point)
        sel, rel_std, reasons = self.select(jac, point.r, unexcited, n_nuis, unobservable)
        if sel != list(selected):
            return None
        held = {name: reasons[k] for k, name in enumerate(self.names) if k not in sel}
        cols = np.concatenate([np.array(sel, dtype=int), problem.nuisance])
        return GateDecision(sel, rel_std, held), FitPoint(point.v, point.r, point.jac[:, cols])

    def propagate_held(self, problem: WindowProblem, decision: GateDecision, point: FitPoint,
                       held_std: FloatArray) -> GateDecision:
        """Add the held parameters' own uncertainty to the admitted ones' standard errors.

        The admitted parameters are fitted with the held ones at their trusted values, so
        their standard errors from the Jacobian are conditional on those values being exact.
        A trusted value is itself an earlier window's estimate, with that window's standard
        error; an admitted parameter that trades off with it moves with its error: ``dq_a =
        G dq_h``, ``G = -(S_a^T S_a)^-1 S_a^T S_h`` (the least-squares optimum's sensitivity
        to the held ln-parameters, the initial state free beside the admitted ones), so the
        marginal variance is the conditional one plus ``G diag(sigma_h^2) G^T``.

        Args:
            problem: the window's problem.
            decision: the gate's decision (standard errors conditional on the held values).
            point: the point the window's twin is simulated at, its Jacobian's columns the
                admitted parameters then the initial state.
            held_std: (n_est,) relative standard error of each estimated parameter's trusted
                value (0: exact, e.g. the nameplate); read at the held positions.

        Returns:
            The decision with the marginal standard errors and the gains (:attr:`GateDecision.
            gain`), by which the trusted values are kept consistent with one another.
        """
        held = [k for k in range(problem.n_est) if k not in decision.selected]
        if not held or not decision.selected:
            return decision
        s_held = problem.local.sensitivity(point.v, np.array(held, dtype=int))
        gain, *_ = np.linalg.lstsq(point.jac, -s_held, rcond=None)
        gain = gain[:len(decision.selected)]
        extra = (gain ** 2) @ (np.asarray(held_std, dtype=float)[held] ** 2)
        rel = dict(decision.rel_std)
        gains = {k: dict(decision.gain.get(k, {})) for k in decision.selected}
        for i, k in enumerate(decision.selected):
            rel[k] = math.sqrt(rel.get(k, math.inf) ** 2 + float(extra[i]))
            gains[k].update({h: float(gain[i, j]) for j, h in enumerate(held)})
        return dataclasses.replace(decision, rel_std=rel, gain=gains)

    def enforce(self, problem: WindowProblem, decision: GateDecision, point: FitPoint,
                check: ModelCheck | None) -> tuple[GateDecision, FitPoint, bool]:
        """The gate again, on the final standard errors: an admitted parameter now above
        ``max_rel_std`` (after the re-fit with the others held, or widened by a failed model
        check) is held, published at its trusted value, and the others are re-fitted with it
        held. Their standard errors stay those of the fit in which it was free (marginal over
        it): the re-fit's would be conditional on a held value that may be off, and narrower.

        Returns:
            (the decision, the point, whether anything was held here: the twin must then be
            simulated again at the new point).
        """
        gated = [k for k in decision.selected
                 if not decision.rel_std.get(k, math.inf) <= self.limit]
        if not gated:
            return decision, point, False
        why = ("after the model check failed and widened it"
               if check is not None and not check.passed
               else "after the re-fit with the others held")
        selected = [k for k in decision.selected if k not in gated]
        held = dict(decision.held)
        for k in gated:
            held[self.names[k]] = (f"not determined by this window (relative std "
                                   f"{decision.rel_std.get(k, math.inf):.2g} > "
                                   f"{self.limit:.2g} {why}): held at last trusted value")
        point, _ = self._refit_holding(problem, point, selected, gated)
        return GateDecision(selected, decision.rel_std, held), point, True

    def _refit_holding(self, problem: WindowProblem, point: FitPoint, selected: list[int],
                       held: list[int]) -> tuple[FitPoint, bool]:
        """Set the ``held`` positions to their trusted values and polish the ``selected``
        ones with the initial state. Returns the new point and whether it was re-fitted (when
        nothing is left to fit, the residuals and Jacobian of ``point`` are kept)."""
        v = point.v.copy()
        v[held] = problem.trusted_ln(held)
        active = np.concatenate([np.array(selected, dtype=int), problem.nuisance])
        if not active.size:
            return FitPoint(v, point.r, point.jac), False
        # every column's sensitivity in the one call: propagate_held reads the held ones next
        every = np.arange(problem.n_est + problem.nuisance.size)
        # the parameters the gate selects are determined, as the ones it admitted last
        # window: the same loop as their polish (polish.POLISH_METHOD)
        v, r, jac = problem.local.refine(v, active, stats=every, method=polish.POLISH_METHOD)
        return FitPoint(v, r, jac[:, active]), True
