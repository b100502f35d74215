"""The interval's floor: what the twin's own error adds to a window's standard errors.

A window's standard errors (stages 3 and 4) hold what the noise does to its estimates. A twin
that does not describe the drive exactly (a speed PI integrating by another rule than the
firmware's, a sub-step or integrator of another order) leaves part of its error in the
residual, where the model check sees it, and absorbs the rest into the parameters, where no
statistic of the window's residual can: five parameters free can mimic a tick of integral
action.

That error differs from window to window (it follows the window's excitation), so it shows
as a scatter of the windows' estimates beyond what their standard errors explain. Per
estimated parameter, the between-window variance ``tau^2`` is the DerSimonian-Laird moment
estimate (the random-effects meta-analysis of the windows): over pairs of consecutive sound
windows that both determined the parameter, at most ``within_s`` apart,

    nu = ln p_k - ln p_j - rate * (t_k - t_j)        (the fused rate's drift removed)
    tau^2 = max(0, mean(nu^2 - sigma_k^2 - sigma_j^2) / 2)

(each window's structural error independent with variance ``tau^2``: ``E nu^2 = sigma_k^2 +
sigma_j^2 + 2 tau^2``). A window's estimate of parameter ``a`` carries its own structural error
and, through the values it was fitted with held (``d ln a / d ln h = g_ah``,
:attr:`~twinwatch.twin.estimation.gate.GateDecision.gain`), theirs:

    floor_a^2 = tau_a^2 + sum_h g_ah^2 tau_h^2
    published sigma_a = sqrt(sigma_a^2 + floor_a^2)

Only the published interval: the estimates, the gate, the trusted values and the fusion read
the window's own standard errors. Comparing estimates with estimates (not with the
nameplate) keeps a machine that is simply off its nameplate from looking structurally wrong; a
twin whose error biases every window alike does not scatter and is not seen here (the model
check's business). Cost: a few operations per admitted parameter and window, no twin call.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from twinwatch.twin.model import FloatArray

#: Two estimates further apart than this [s] are not paired (the trusted values' confirmation
#: window, :data:`~twinwatch.twin.estimation.estimator.CONFIRM_WITHIN_S`).
WITHIN_S = 10.0


@dataclass
class FloorState:
    """What :class:`StructuralFloor` carries between windows.

    Attributes:
        last: per estimated parameter, the last sound window's (ln value, variance of it,
            the window's middle [s]) or None.
        excess: per estimated parameter, the sum of ``nu^2 - sigma_k^2 - sigma_j^2`` (n_est,).
        pairs: per estimated parameter, the pairs summed (n_est,).
    """

    last: list[tuple[float, float, float] | None]
    excess: FloatArray
    pairs: FloatArray = field(default_factory=lambda: np.zeros(0))

    def copy(self) -> FloorState:
        return FloorState(list(self.last), self.excess.copy(), self.pairs.copy())

    def as_dict(self, names: Sequence[str]) -> dict[str, list[float | None] | None]:
        """JSON-serialisable, by parameter name (``names``: the estimated parameters, in
        order): ``[ln value, its variance, t, excess, pairs]`` (the first three None before
        the parameter's first sound window); None for a parameter with neither."""
        out: dict[str, list[float | None] | None] = {}
        for k, name in enumerate(names):
            last = self.last[k]
            if last is None and not self.pairs[k]:
                out[name] = None
                continue
            head: list[float | None] = list(last) if last is not None else [None, None, None]
            out[name] = [*head, float(self.excess[k]), float(self.pairs[k])]
        return out

    @classmethod
    def from_dict(cls, state: Mapping[str, Any], names: Sequence[str]) -> FloorState:
        """:meth:`as_dict` read back; a parameter it does not name starts without pairs.

        Raises:
            TypeError, ValueError: an entry is not five numbers.
        """
        n = len(names)
        out = cls([None] * n, np.zeros(n), np.zeros(n))
        for k, name in enumerate(names):
            entry = state.get(name)
            if entry is None:
                continue
            x, var, t, excess, pairs = entry
            if x is not None and var is not None and t is not None:
                out.last[k] = (float(x), float(var), float(t))
            out.excess[k], out.pairs[k] = float(excess), float(pairs)
        return out


class StructuralFloor:
    """The between-window structural variance of each estimated parameter (module docstring).

    Args:
        n_est: estimated parameters (ln-parameters, in priority order).
        within_s: the longest time between two paired estimates [s].
    """

    def __init__(self, n_est: int, within_s: float = WITHIN_S) -> None:
        self.n_est = n_est
        self.within_s = within_s
        self.state = FloorState([None] * n_est, np.zeros(n_est), np.zeros(n_est))

    def observe(self, selected: Sequence[int], ln_values: FloatArray,
                rel_std: Mapping[int, float], t: float,
                rates: Mapping[int, float] | None = None) -> None:
        """Add a sound window's estimates (the model check passed, the fit and the sensors good).

        Args:
            selected: positions of the parameters the window determined.
            ln_values: (n_est,) the window's ln-parameters (the twin's).
            rel_std: position -> the window's relative standard error (1 sigma, the gate's).
            t: the window's middle [s].
            rates: position -> the fused relative rate of change [1/s] (none: 0).
        """
        s = self.state
        for k in selected:
            sd = float(rel_std.get(k, math.inf))
            x = float(ln_values[k])
            if not (math.isfinite(sd) and math.isfinite(x)):
                continue
            prev = s.last[k]
            if prev is not None and t - prev[2] <= self.within_s:
                nu = x - prev[0] - (rates or {}).get(k, 0.0) * (t - prev[2])
                s.excess[k] += nu * nu - sd * sd - prev[1]
                s.pairs[k] += 1
            s.last[k] = (x, sd * sd, t)

    def restart_pairs(self) -> None:
        """Pair no estimate with one before now: the fusion found a sudden change (a step of
        the machine, which the pairs' model, a stationary parameter with the fused rate's
        drift, does not describe). The pairs summed so far stay."""
        self.state.last = [None] * self.n_est

    def tau(self) -> FloatArray:
        """(n_est,) each parameter's between-window standard deviation of ln p (0 without a
        pair, or when the pairs scatter no more than their standard errors say)."""
        s = self.state
        with np.errstate(invalid="ignore", divide="ignore"):
            var = np.where(s.pairs > 0, s.excess / np.maximum(s.pairs, 1) / 2.0, 0.0)
        return np.sqrt(np.maximum(var, 0.0))

    def floors(self, selected: Sequence[int], gain: Mapping[int, Mapping[int, float]]
               ) -> dict[int, float]:
        """Position -> ``floor_a`` (relative, 1 sigma) of each determined parameter:
        ``sqrt(tau_a^2 + sum_h g_ah^2 tau_h^2)`` over the values it was fitted with held."""
        tau2 = self.tau() ** 2
        out = {}
        for a in selected:
            f2 = float(tau2[a])
            for h, g in gain.get(a, {}).items():
                f2 += g * g * float(tau2[h])
            out[a] = math.sqrt(f2)
        return out


__all__ = ["FloorState", "StructuralFloor", "WITHIN_S"]
