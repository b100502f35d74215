"""When to act: each estimated parameter's trend and remaining useful life (issue 17).

The twin publishes where each parameter is; the prognostics say where it is going. Per
estimated parameter, every window:

* :mod:`~twinwatch.twin.prognostics.evidence`: the window's independent evidence (an estimate
  with its standard error, or the window's share of the fused evidence);
* :mod:`~twinwatch.twin.prognostics.trend`: the evidence since the last restart, a step test
  (a repair or a part replaced restarts the trend), the history's monotonicity and
  trendability;
* :mod:`~twinwatch.twin.prognostics.degradation`: the degradation models (none, linear,
  exponential, each with an onset; MATLAB's ``linearDegradationModel`` and
  ``exponentialDegradationModel``), fitted by weighted least squares and chosen by the BIC;
* :mod:`~twinwatch.twin.prognostics.rul`: the time to the alarm rule's warning and alarm
  thresholds as a distribution (Monte Carlo on the fit's covariance, averaged over the
  plausible models), in plant time and wall time;
* :mod:`~twinwatch.twin.prognostics.window`: the adaptive acquisition window (paper Sections
  5.2.2 and 6);
* :mod:`~twinwatch.twin.prognostics.metrics`: the scores a prediction is judged by (ProgPy's
  alpha-lambda, the interval's coverage, the relative error).

The room imports the ground floor, ``twin/model.py`` and ``twin/estimation``; the twin's top
(adaptation, health) imports it.
"""

from twinwatch.twin.prognostics.config import AdaptiveWindowConfig, PrognosticsConfig, Thresholds
from twinwatch.twin.prognostics.engine import Prognosis, Prognostics, RulReport, TrendReport
from twinwatch.twin.prognostics.evidence import fused_share, window_evidence
from twinwatch.twin.prognostics.rul import Crossing
from twinwatch.twin.prognostics.trend import Evidence, Restart

__all__ = [
    "AdaptiveWindowConfig",
    "Crossing",
    "Evidence",
    "Prognosis",
    "Prognostics",
    "PrognosticsConfig",
    "Restart",
    "RulReport",
    "Thresholds",
    "TrendReport",
    "fused_share",
    "window_evidence",
]
