"""When to search for a missing component: a test on the residual's structure, accumulated.

The paper runs discovery when the residual "stays too large" (Section 3.3). What gives a
missing component away is not the residual's size (a moderate fault leaves a residual only
about twice the noise level) but its *structure*: measurement noise is white, a missing term is
not (a periodic term is a spectral peak, a drift or an offset is correlated at every lag).

Per window, per output (:func:`residual_structure`):

* the output's white-noise level ``s`` is estimated from first differences
  (:func:`~twinwatch.twin.estimation.statistics.noise_level`: nearly blind to a smooth error);
* the portmanteau statistic of Ljung and Box (1978) on the residual ``e``
  (mean not removed: an offset is model error too)::

      Q = N (N + 2) sum_{k=1..h} rho_k^2 / (N - k)     ~ chi^2(h) when e is white

  gives the probability ``p`` of so much structure in white noise;
* the structure must also matter: its RMS ``sqrt(max(rms^2 - s^2, 0))`` (normalised by the
  output's scale) above ``min_nrmse``;
* an output without measurement noise (its white-noise level below ``min_nrmse / 10``: a
  controller's output computed from the noisy speed, a register at rest) cannot be tested for
  whiteness: its residual is smooth whatever the model. While another output is measured with
  noise, it is left to that output; when none is (a noise-free plant), its structure counts by
  its size alone (p-value 0 above ``min_nrmse``).

The window's p-value is the smallest over the outputs whose structure matters, times their
number (Bonferroni). A window is *structured* (the residual says the model lacks something; its
estimates are published ``suspect``) when that p-value is below ``window_alpha``.

Over windows (:class:`StructureEvidence`): Fisher's method combines the last
``trigger_windows`` windows' p-values, ``X = -2 sum ln p_i ~ chi^2(2K)``; discovery runs when
the combined p-value is below ``false_alarm``. With ``K > 1`` each window's p-value is floored
at ``false_alarm`` itself, so that no single window (a bus hiccup) decides alone. For white
residuals each test is a false alarm with probability at most ``false_alarm``. A search that
keeps nothing waits ``retry_after`` windows, so a coloured sensor noise the twin does not model
costs a search every ``retry_after`` windows, never a wrong term (a term must earn its place:
:class:`~twinwatch.twin.discovery.search.Discovery`).

References:
    G. M. Ljung, G. E. P. Box, "On a measure of lack of fit in time series models",
    Biometrika 65(2), 1978. R. A. Fisher, *Statistical Methods for Research Workers*, 1925
    (combining independent tests).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from scipy.special import chdtrc  # chi2.sf without scipy.stats (22 MB, 0.5 s of import)

from twinwatch.twin.estimation.statistics import noise_level
from twinwatch.twin.model import FloatArray

__all__ = ["OutputStructure", "StructureEvidence", "WindowStructure", "residual_structure"]


@dataclass(frozen=True)
class OutputStructure:
    """One output's residual in one window.

    Attributes:
        ratio: its normalised RMSE over its white-noise level (the former criterion).
        structured_nrmse: RMS of the part of the residual that is not white noise, over the
            output's scale.
        q: the Ljung-Box statistic over ``lags`` lags.
        p_value: probability of a ``q`` this large in white noise (chi^2 with ``lags`` degrees
            of freedom); 1.0 when the structure is too small to matter.
    """

    ratio: float
    structured_nrmse: float
    q: float
    p_value: float


@dataclass(frozen=True)
class WindowStructure:
    """The structure test of one window's residual (:func:`residual_structure`).

    Attributes:
        outputs: output name -> its :class:`OutputStructure`.
        p_value: the window's p-value: the smallest over the outputs whose structure matters,
            times their number (Bonferroni), at most 1.
        structured: ``p_value < window_alpha`` (and the residual is finite).
    """

    outputs: dict[str, OutputStructure]
    p_value: float
    structured: bool

    @property
    def worst(self) -> str | None:
        """The output with the strongest evidence of structure (None: no output counts)."""
        if not self.outputs:
            return None
        return min(self.outputs, key=lambda o: (self.outputs[o].p_value, -self.outputs[o].q))

    def describe(self) -> str:
        """One line for the log: which output, how structured, how unlikely in white noise."""
        o = self.worst
        if o is None:
            return "no output"
        s = self.outputs[o]
        p = f"p = {s.p_value:.1e}" if s.p_value >= 1e-16 else "p < 1e-16"
        return f"{o} residual {s.ratio:.1f} x its noise level, Ljung-Box Q = {s.q:.0f} ({p})"


def _p_chi2(x: float, dof: int) -> float:
    return float(chdtrc(dof, x)) if math.isfinite(x) else 0.0


def residual_structure(errors: FloatArray, names: list[str] | tuple[str, ...], *,
                       lags: int, min_nrmse: float, window_alpha: float) -> WindowStructure:
    """Test one window's residual for structure (see the module docstring).

    Args:
        errors: normalised residual (N, n_out): each output's error over its scale
            (:meth:`~twinwatch.twin.estimation.fit.WindowFit.error_matrix`).
        names: the outputs' names (n_out,).
        lags: ``h``, the number of autocorrelation lags in the Ljung-Box statistic.
        min_nrmse: the smallest structured RMS (normalised) that matters.
        window_alpha: the window is structured below this p-value.

    Returns:
        The window's :class:`WindowStructure`. A residual with a NaN or an infinity is
        structured (p-value 0): the twin did not follow the machine.
    """
    e = np.asarray(errors, dtype=float)
    if e.ndim != 2 or e.shape[1] != len(names):
        raise ValueError(f"errors: shape {e.shape} does not match {len(names)} outputs")
    if not np.all(np.isfinite(e)):
        return WindowStructure({}, 0.0, True)
    n = e.shape[0]
    h = max(1, min(lags, n - 2))
    noise = noise_level(e)
    rms = np.sqrt(np.mean(e * e, axis=0))
    den = np.sum(e * e, axis=0)
    weights = 1.0 / (n - np.arange(1, h + 1))
    noisy = noise > min_nrmse / 10.0
    outputs: dict[str, OutputStructure] = {}
    counted: list[float] = []
    for j, name in enumerate(names):
        x = e[:, j]
        if den[j] <= 0.0:
            outputs[name] = OutputStructure(0.0, 0.0, 0.0, 1.0)
            continue
        rho = np.array([float(x[k:] @ x[:n - k]) for k in range(1, h + 1)]) / den[j]
        q = float(n * (n + 2) * np.sum(weights * rho * rho))
        structured = math.sqrt(max(float(rms[j] ** 2 - noise[j] ** 2), 0.0))
        ratio = float(rms[j] / noise[j]) if noise[j] > 0 else math.inf
        matters = structured > min_nrmse and (noisy[j] or not noisy.any())
        p = (_p_chi2(q, h) if noisy[j] else 0.0) if matters else 1.0
        outputs[name] = OutputStructure(ratio, structured, q, p)
        if matters:
            counted.append(p)
    p_window = min(1.0, min(counted) * len(counted)) if counted else 1.0
    return WindowStructure(outputs, p_window, p_window < window_alpha)


@dataclass
class StructureEvidence:
    """The structure tests of the last windows, combined (Fisher's method; module docstring).

    Args:
        windows: ``K``, how many windows are combined (``[discovery] trigger_windows``).
        false_alarm: the combined test's level: discovery runs below it; with ``windows > 1``
            also the floor of each window's p-value.

    Attributes:
        p_values: the last ``K`` windows' floored p-values, oldest first.
    """

    windows: int
    false_alarm: float
    p_values: deque[float] = field(default_factory=deque)

    def __post_init__(self) -> None:
        self.p_values = deque(self.p_values, maxlen=self.windows)

    def add(self, test: WindowStructure) -> float:
        """Record one window's test; return the combined p-value of the last ``K`` windows
        (1.0 until ``K`` windows are recorded)."""
        floor = self.false_alarm if self.windows > 1 else 1e-300
        self.p_values.append(max(test.p_value, floor))
        return self.combined

    @property
    def combined(self) -> float:
        """Fisher's combined p-value of the last ``K`` windows (1.0 before ``K`` windows)."""
        if len(self.p_values) < self.windows:
            return 1.0
        x = -2.0 * sum(math.log(p) for p in self.p_values)
        return _p_chi2(x, 2 * self.windows)

    @property
    def triggered(self) -> bool:
        """The evidence of the last ``K`` windows is below the false-alarm level."""
        return self.combined < self.false_alarm

    def clear(self) -> None:
        """Forget the evidence (a discovery ran on it, or the twin changed)."""
        self.p_values.clear()
