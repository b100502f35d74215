"""How a sequence of predictions is judged (the prognostics benchmark and tests).

A *profile* is the time-of-event prediction made at each window ``t_p``: the predicted crossing
time (median) with its interval, or the Monte Carlo draws. Against the true crossing ``t_eol``:

* **alpha-lambda** (Saxena et al., "Metrics for offline evaluation of prognostic performance",
  IJPHM 2010; ProgPy's ``metrics.alpha_lambda``): at a prediction time ``t_p`` the prediction
  passes when at least ``beta`` of its distribution lies within ``alpha`` of the true remaining
  life, ``t_eol +- alpha (t_eol - t_p)``. ProgPy evaluates it at the first prediction at or
  after a time ``lambda``; here ``lambda`` is a fraction of the way from the degradation's
  onset to the crossing (Saxena's ``t_lambda = t_P + lambda (t_EoL - t_P)``), and the *pass
  rate* is the share of all windows from ``t_lambda`` to the crossing that pass;
* **coverage**: the share of those windows whose interval contains ``t_eol``;
* **relative error** of the median crossing, against the remaining life (``|t_hat - t_eol| /
  (t_eol - t_p)``) and against the crossing time itself (``|t_hat - t_eol| / t_eol``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from twinwatch.twin.model import FloatArray

__all__ = ["ProfileScore", "alpha_lambda_pass", "score_profile"]


def alpha_lambda_pass(t_pred: float, samples: FloatArray | None, median: float | None,
                      t_eol: float, alpha: float = 0.2, beta: float = 0.5) -> bool:
    """One prediction against the alpha cone: ``beta`` of its time-of-event draws
    (``samples``, plant times; inf: never) within ``t_eol +- alpha (t_eol - t_pred)``; without
    draws, the median inside the cone."""
    lo = t_eol - alpha * (t_eol - t_pred)
    hi = t_eol + alpha * (t_eol - t_pred)
    if samples is not None and np.size(samples):
        s = np.asarray(samples, dtype=float)
        return float(np.mean((s >= lo) & (s <= hi))) >= beta
    return median is not None and lo <= median <= hi


@dataclass
class ProfileScore:
    """A profile's scores over the windows from ``t_lambda`` to the true crossing.

    Attributes:
        windows: windows scored.
        alpha_lambda: share passing the alpha-lambda test.
        coverage: share whose interval contains the true crossing.
        within: share whose median is within ``tolerance`` of the true crossing time.
        error_rul_median, error_rul_max: relative error of the median against the remaining
            life (median and worst over the windows).
        error_time_max: worst relative error against the crossing time.
        predicted: share of the windows with a finite median.
    """

    windows: int
    alpha_lambda: float
    coverage: float
    within: float
    error_rul_median: float
    error_rul_max: float
    error_time_max: float
    predicted: float


def score_profile(times: Sequence[float], medians: Sequence[float | None],
                  lows: Sequence[float | None], highs: Sequence[float | None],
                  samples: Sequence[FloatArray | None], *, t_eol: float, t_onset: float,
                  lam: float = 0.5, alpha: float = 0.2, beta: float = 0.5,
                  tolerance: float = 0.1) -> ProfileScore:
    """Score the predictions made at ``times`` (plant time of each window's end) of the
    crossing whose true time is ``t_eol``; only those from ``t_onset + lam (t_eol - t_onset)``
    to ``t_eol`` count. ``lows``/``highs`` None: an open interval (never / at once)."""
    t_lam = t_onset + lam * (t_eol - t_onset)
    n = passed = covered = within = finite = 0
    err_rul: list[float] = []
    err_t: list[float] = []
    for t, med, lo, hi, smp in zip(times, medians, lows, highs, samples, strict=True):
        if t < t_lam or t >= t_eol:
            continue
        n += 1
        passed += alpha_lambda_pass(t, smp, med, t_eol, alpha, beta)
        lo_ok = lo is not None and lo <= t_eol
        hi_ok = hi is None or hi >= t_eol
        covered += lo_ok and hi_ok
        if med is not None and math.isfinite(med):
            finite += 1
            within += abs(med - t_eol) <= tolerance * t_eol
            err_rul.append(abs(med - t_eol) / max(t_eol - t, 1e-9))
            err_t.append(abs(med - t_eol) / t_eol)
        else:
            err_rul.append(math.inf)
            err_t.append(math.inf)
    if n == 0:
        return ProfileScore(0, math.nan, math.nan, math.nan, math.nan, math.nan, math.nan,
                            math.nan)
    return ProfileScore(n, passed / n, covered / n, within / n, float(np.median(err_rul)),
                        float(np.max(err_rul)), float(np.max(err_t)), finite / n)
