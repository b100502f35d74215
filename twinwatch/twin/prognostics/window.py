"""The adaptive acquisition window (the paper's future work, Sections 5.2.2 and 6).

The paper's Ra error grows near the end of the degradation because a fixed 200-sample window
averages a parameter that changes quickly; it proposes a window that follows the variation.
A window of ``N`` samples trades two errors: the estimate's noise, whose standard error falls as
``N^-1/2``, and the drift of the parameter within the window (the window averages it and lags
behind it by half its length), which grows as ``N``. :class:`WindowController` keeps them
balanced, window after window:

* the length that balances them for the value *now* (the window's end): its error is the
  noise ``s(N) = s0 (N0/N)^1/2`` and the lag of half the drift within the window, ``d(N) / 2 =
  |rate| N Ts / 2``; ``s^2 + d^2/4`` is smallest where ``d / s = sqrt(2)`` (``drift_ratio``,
  1.4), i.e. at ``N * (drift_ratio / ratio)^(2/3)`` from a window of ``N`` samples whose drift is
  ``ratio`` of its standard error (the ratio grows as ``N^3/2``);
* **shorter** at once when that length is below 0.9 of the window (by at most ``shrink``), or
  when the residual grows with the window: its normalised RMSE above ``residual_ratio`` times
  its white-noise level (the twin's constant parameters no longer fit one window), by
  ``shrink``;
* **longer** (by at most ``grow``) after ``quiet_windows`` windows in a row in which that length
  is above 1.1 of the window (every drift is small against its standard error; none at all in
  a stretch without degradation);
* always within ``[min_window, max_window]``.

The rate is the parameter's trend's (:mod:`~twinwatch.twin.prognostics.trend`), or the fusion's
when the trend has none yet; the standard error is the window's stated one, or the scatter of
the evidence about its trend when that is smaller (the model-error floor overstates it for
noise-free estimates). The decision applies to the next window the acquisition starts; each
health message says which length its window had and why (``acquisition``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from twinwatch.twin.prognostics.config import AdaptiveWindowConfig

__all__ = ["WindowChoice", "WindowController"]


@dataclass(frozen=True)
class WindowChoice:
    """The controller's decision after a window.

    Attributes:
        used: samples of the window just estimated.
        used_reason: why it had that length (for a person).
        next: samples of the next window.
        reason: why ``next`` (for a person).
        drift_ratio: the largest drift within the window over its standard error (None: no
            parameter had both).
        parameter: the parameter with that ratio.
    """

    used: int
    used_reason: str
    next: int
    reason: str
    drift_ratio: float | None = None
    parameter: str | None = None


class WindowController:
    """Chooses each window's length (module docstring).

    Args:
        config: the ``[acquisition.adaptive]`` table.
        initial: the configured window [samples] (the first windows' length), clipped to the
            bounds.
        sample_period: [s].
    """

    def __init__(self, config: AdaptiveWindowConfig, initial: int, sample_period: float) -> None:
        self.config = config
        self.sample_period = sample_period
        self.current = int(min(max(initial, config.min_window), config.max_window))
        self._quiet = 0
        #: Why each length was chosen, for the windows that come with it.
        self.reasons: dict[int, str] = {self.current: "the configured window"}

    def decide(self, used: int, drift: Mapping[str, tuple[float, float]],
               residual_ratio: float | None) -> WindowChoice:
        """The next window's length after a window of ``used`` samples.

        Args:
            used: samples of the window just estimated.
            drift: parameter -> (drift rate [SI/s], the window's standard error of it [SI]),
                for the parameters the window estimated.
            residual_ratio: the window's normalised RMSE over its white-noise level (None:
                unknown).
        """
        c = self.config
        span = used * self.sample_period
        worst, who = None, None
        for name, (rate, std) in drift.items():
            if not (std > 0 and math.isfinite(rate) and math.isfinite(std)):
                continue
            ratio = abs(rate) * span / std
            if worst is None or ratio > worst:
                worst, who = ratio, name
        n = used
        # The length where the drift within the window is drift_ratio of its standard error
        # (module docstring).
        target = (used * (c.drift_ratio / worst) ** (2.0 / 3.0) if worst is not None
                  and worst > 0 else math.inf)
        if target < 0.9 * used:
            self._quiet = 0
            n = int(max(min(target, used * c.shrink), c.min_window))
            reason = (f"shortened: {who} drifts {worst:.1f} standard errors within a "
                      f"{span:g} s window")
        elif residual_ratio is not None and residual_ratio > c.residual_ratio:
            self._quiet = 0
            n = int(max(used * c.shrink, c.min_window))
            reason = (f"shortened: the residual is {residual_ratio:.1f} times its noise level "
                      f"(the parameters change within the window)")
        elif target > 1.1 * used:
            self._quiet += 1
            if self._quiet >= c.quiet_windows and used < c.max_window:
                self._quiet = 0
                n = int(min(math.ceil(min(target, used * c.grow)), c.max_window))
                reason = (f"lengthened: {c.quiet_windows} quiet windows (every drift below "
                          f"{c.drift_ratio:g} standard errors)")
            else:
                reason = self.reasons.get(used, "unchanged")
        else:
            self._quiet = 0
            reason = self.reasons.get(used, "unchanged")
        n = int(min(max(n, c.min_window), c.max_window))
        used_reason = self.reasons.get(used, "the configured window")
        if n != used:
            self.reasons[n] = reason
        else:
            reason = used_reason
        self.current = n
        return WindowChoice(used, used_reason, n, reason, worst, who)
