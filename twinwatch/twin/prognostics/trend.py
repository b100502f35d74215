"""The trend of one parameter: its evidence, the degradation model it follows, its restarts.

:class:`ParameterTrend` keeps one parameter's evidence since the last restart (within the
configured horizon) and, every window:

1. **Step test.** New evidence is compared with the current trend's prediction at its time: the
   normalised innovation ``z = (y - y_hat) / sqrt(k s^2 + band^2)`` (``s`` the evidence's
   published uncertainty, ``k`` the fit's reduced chi-square when above 1, ``band`` the
   prediction's own uncertainty). ``|z|`` above ``step_threshold`` in ``step_confirm``
   consecutive evidence windows on the same side is a *step* (a repair, a part replaced, a
   sudden fault): the trend restarts from the first of them, the evidence before it is
   dropped, and the restart is reported (time, size). One such window alone is an outlier and
   is dropped. When the fusion flagged the window as a sudden change (``fusion_jump``), one
   window confirms it.
2. **Fit.** The degradation models (:mod:`~twinwatch.twin.prognostics.degradation`) are fitted
   to the segment's evidence (binned to ``max_points``), the information criteria choose one
   (:func:`~twinwatch.twin.prognostics.degradation.select`), and the others keep their weight
   (Bayesian model averaging: the remaining useful life is drawn from every plausible model,
   so an undecided choice widens the interval). Between fits, evidence the fits predict is
   taken in by an extended Kalman update (:meth:`ParameterTrend.refit`).
3. **Degrading?** Only when the evidence favours a degrading model over ``none`` with odds of
   at least ``detection`` (0.9: the BIC's weights) and the chosen model's drift rate now is
   beyond ``flat_z`` standard errors of zero; otherwise "not degrading" (flat within its
   uncertainty).

The history's fitness for prediction is reported as MATLAB's Predictive Maintenance Toolbox
scores it: **monotonicity** (its ``sign`` method) on the evidence smoothed by a moving mean of
``smooth`` points (its ``WindowSize``; noisy evidence is otherwise never monotonic), and
**trendability** in its single-trajectory form ``|corr(x, t)|`` (Javed et al., 2015), since a
machine has one trajectory (MATLAB's compares run-to-failure members, Coble and Hines).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from twinwatch.twin.model import FloatArray
from twinwatch.twin.prognostics.degradation import (
    DegradationFit,
    _finite,
    bin_evidence,
    fit_models,
    refit_models,
    select,
)

__all__ = ["Evidence", "ParameterTrend", "Restart", "TrendSettings", "monotonicity",
           "trendability"]


@dataclass(frozen=True)
class Evidence:
    """One window's evidence on a parameter.

    Attributes:
        t: the window's middle [s, plant time].
        value: the parameter [SI].
        std: its 1-sigma uncertainty [SI] (> 0).
        source: ``estimated`` (this window's estimate) or ``fused`` (the window's share of the
            fusion's evidence, :func:`~twinwatch.twin.prognostics.evidence.window_evidence`).
    """

    t: float
    value: float
    std: float
    source: str = "estimated"


@dataclass(frozen=True)
class Restart:
    """A step that restarted the trend: when, how large [SI], and why."""

    t: float
    step: float
    reason: str


@dataclass(frozen=True)
class TrendSettings:
    """The knobs of a trend (the ``[prognostics]`` table's, see
    :class:`~twinwatch.twin.prognostics.config.PrognosticsConfig`)."""

    horizon: float = 3600.0
    min_evidence: int = 10
    min_span: float = 0.0
    max_points: int = 120
    onset: bool = True
    step_threshold: float = 5.0
    step_confirm: int = 2
    flat_z: float = 2.0
    smooth: int = 5
    min_weight: float = 0.01
    detection: float = 0.9
    #: The refit schedule (:meth:`ParameterTrend.refit` says how each is used).
    refit_every: int = 2
    skip_z: float = 1.0
    regrid_every: int = 10
    regrid_z: float = 3.0


def monotonicity(x: FloatArray, smooth: int = 1) -> float | None:
    """MATLAB's ``monotonicity`` (``sign`` method) of one history: ``|sum sign(diff x)| /
    (n - 1)`` after a moving mean of ``smooth`` points; None below 3 points."""
    value = _monotonicity(np.ascontiguousarray(x, dtype=float), int(smooth))
    return None if math.isnan(value) else value


def trendability(t: FloatArray, x: FloatArray) -> float | None:
    """``|corr(x, t)|`` (Pearson) of one history against time; None below 3 points or for a
    constant history."""
    value = _trendability(np.ascontiguousarray(t, dtype=float),
                          np.ascontiguousarray(x, dtype=float))
    return None if math.isnan(value) else value


@njit(cache=True, nogil=True)
def _monotonicity(x: FloatArray, smooth: int) -> float:
    """:func:`monotonicity` compiled (NaN for None): the moving mean's differences' signs
    summed in one pass."""
    n = x.size
    if smooth > 1 and n >= smooth + 2:
        w = 1.0 / smooth
        m = n - smooth + 1
        prev = 0.0
        total = 0.0
        for i in range(m):
            acc = 0.0
            for j in range(smooth):
                acc += x[i + j] * w
            if i:
                total += np.sign(acc - prev)
            prev = acc
        return abs(total) / (m - 1)
    if n < 3:
        return math.nan
    total = 0.0
    for i in range(1, n):
        total += np.sign(x[i] - x[i - 1])
    return abs(total) / (n - 1)


@njit(cache=True, nogil=True)
def _trendability(t: FloatArray, x: FloatArray) -> float:
    """:func:`trendability` compiled (NaN for None): Pearson's r from the centred series."""
    n = x.size
    if n < 3:
        return math.nan
    tm = t.mean()
    xm = x.mean()
    stt = 0.0
    sxx = 0.0
    stx = 0.0
    for i in range(n):
        tc = t[i] - tm
        xc = x[i] - xm
        stt += tc * tc
        sxx += xc * xc
        stx += tc * xc
    if stt <= 0 or sxx <= 0:
        return math.nan
    return min(abs(stx) / math.sqrt(stt * sxx), 1.0)


@njit(cache=True, nogil=True)
def _scores(t: FloatArray, x: FloatArray, smooth: int) -> tuple[float, float]:
    """:func:`monotonicity` and :func:`trendability` compiled, in one call (NaN for None)."""
    return _monotonicity(x, smooth), _trendability(t, x)


@dataclass
class ParameterTrend:
    """One parameter's trend, updated window after window.

    Args:
        name: the parameter.
        settings: the trend's knobs.

    Attributes:
        fits: the models fitted on the last evidence, with their weights (:attr:`weights`).
        fit: the chosen one (None: too little evidence).
        restarts: every restart so far; :attr:`restarted` whether the last update made one.
    """

    name: str
    settings: TrendSettings = field(default_factory=TrendSettings)
    t: list[float] = field(default_factory=list)
    y: list[float] = field(default_factory=list)
    s: list[float] = field(default_factory=list)
    src: list[str] = field(default_factory=list)
    since_t: float | None = None
    pending: list[tuple[Evidence, float]] = field(default_factory=list)
    fits: list[DegradationFit] = field(default_factory=list)
    weights: list[float] = field(default_factory=list)
    fit: DegradationFit | None = None
    restarts: list[Restart] = field(default_factory=list)
    restarted: bool = False
    outliers: int = 0
    _dirty: bool = False
    #: every model of the last fit (``fits`` keeps the plausible ones): the warm start.
    _all: list[DegradationFit] = field(default_factory=list)
    #: largest |innovation| of the evidence taken since the last fit (inf: search the grid).
    _z: float = math.inf
    #: evidence of the segment the horizon dropped (the refit schedule counts it)
    _dropped: int = 0
    #: evidence appended since the fits last took evidence (a fit or an update)
    _new: int = 0
    #: points (binned) the models were last fitted to
    _points: int = 0
    #: the horizon dropped evidence the fits still hold
    _stale: bool = False
    #: :meth:`scores` of the evidence as it stands (None: to compute)
    _scores: tuple[float | None, float | None] | None = None

    # -- intake -----------------------------------------------------------------------------
    def add(self, ev: Evidence | None, *, jump: bool = False) -> None:
        """Take one window's evidence (None: the window has none on this parameter) through
        the step test; ``jump``: the fusion flagged the window as a sudden change."""
        self.restarted = False
        if ev is None or not (math.isfinite(ev.value) and math.isfinite(ev.std)
                              and ev.std > 0):
            return
        if self.t and ev.t <= self.t[-1]:
            # The source's clock went back (a recording replayed again): the evidence before
            # belongs to another time line.
            self.pending = [(ev, 0.0)]
            self._restart("the source's clock went back")
            return
        z = self.innovation(ev)
        cfg = self.settings
        if abs(z) > cfg.step_threshold:
            if self.pending and math.copysign(1.0, self.pending[-1][1]) != math.copysign(1.0, z):
                self.outliers += len(self.pending)
                self.pending = []
            self.pending.append((ev, z))
            if len(self.pending) >= (1 if jump else cfg.step_confirm):
                if not jump and self._bend():
                    for e, _ in self.pending:  # the onset of a drift: the trend bends
                        self._append(e)
                    self.pending = []
                    self._z = math.inf
                    return
                self._restart(f"step of {z:+.1f} standard errors"
                              + (" (the fusion saw a sudden change)" if jump else ""))
            return
        if self.pending:  # one window beyond the trend, then back on it: an outlier
            self.outliers += len(self.pending)
            self.pending = []
            z = math.inf
        self.take(ev, z)

    def take(self, ev: Evidence, z: float) -> None:
        """Append evidence that passed the step test (:meth:`add`; :meth:`Prognostics.replay`
        takes the stored evidence this way), ``z`` its :meth:`innovation` (inf: search the
        grid at the next fit)."""
        self._append(ev)
        self._z = max(self._z, abs(z)) if self.fit is not None else math.inf

    def _bend(self) -> bool:
        """Do the windows beyond the trend start a drift rather than a step? They do when a
        degrading model with an onset up to the last evidence before them (a kink, not a
        jump) explains them within ``step_threshold`` standard errors."""
        if len(self.t) < self.settings.min_evidence:
            return False
        t = np.asarray(self.t + [e.t for e, _ in self.pending])
        y = np.asarray(self.y + [e.value for e, _ in self.pending])
        s = np.asarray(self.s + [e.std for e, _ in self.pending])
        n_old = len(self.t)
        recent = np.asarray(self.t[max(0, n_old - 20):])
        fits = [f for f in fit_models(t, y, s, onset=True, onsets=recent, min_points=0)
                if f.onset is not None]
        if not fits:
            return False
        best = min(fits, key=lambda f: f.chi2)
        red = max(best.chi2 / max(best.n - best.k, 1), 1.0)
        z = (y[n_old:] - best.value(t[n_old:])) / (s[n_old:] * math.sqrt(red))
        return bool(np.all(np.abs(z) < self.settings.step_threshold))

    def _append(self, ev: Evidence) -> None:
        if self.since_t is None:
            self.since_t = ev.t
        self.t.append(ev.t)
        self.y.append(ev.value)
        self.s.append(ev.std)
        self.src.append(ev.source)
        self._dirty = True
        self._new += 1
        self._scores = None

    def _restart(self, reason: str) -> None:
        first = self.pending[0][0]
        pred = float(self.fit.value(first.t)) if self.fit is not None else float("nan")
        step = float(np.mean([e.value for e, _ in self.pending])) - pred
        self.restarts.append(Restart(first.t, step, reason))
        self.t, self.y, self.s, self.src = [], [], [], []
        self._scores = None
        self._dropped = 0
        self.since_t = None
        for ev, _ in self.pending:
            self._append(ev)
        self.pending = []
        self.fit = None
        self.fits, self.weights, self._all = [], [], []
        self._z = math.inf
        self._points = 0
        self._stale = False
        self.restarted = True

    def innovation(self, ev: Evidence) -> float:
        """Normalised distance of ``ev`` from the current trend's prediction (0 without a
        trend)."""
        f = self.fit
        if f is None:
            return 0.0
        value, band = f.value_band(ev.t)
        red = max(f.chi2 / max(f.n - f.k, 1), 1.0)
        sig = math.sqrt(red * ev.std * ev.std + band * band)
        if not (sig > 0 and math.isfinite(sig)):
            return 0.0
        return (ev.value - value) / sig

    # -- fit ----------------------------------------------------------------------------------
    def refit(self, t_now: float, *, full: bool = False) -> None:
        """Bring the models up to the segment's evidence within the horizon (only when it
        changed or the horizon dropped some).

        What changed decides how (``full``: the grid search and the polish, always):

        * **update** (the steady state): one new evidence within ``skip_z`` of the
          prediction is taken into each plausible model (with a finite covariance) by an
          extended Kalman (recursive least squares) step about its current optimum
          (:meth:`~twinwatch.twin.prognostics.degradation.DegradationFit.advance`, ``O(k^2)``);
          the model comparison (the weights, the choice) stands;
        * **polish** from the last optimum
          (:func:`~twinwatch.twin.prognostics.degradation.refit_models`, the comparison
          refreshed) when the new evidence lies beyond ``skip_z`` (the linearisation no
          longer predicts it), when more than one evidence came at once (a bend), and, while
          the horizon drops evidence, at every ``refit_every``-th evidence (an update does
          not remove dropped evidence);
        * **grid search** (:func:`~twinwatch.twin.prognostics.degradation.fit_models`) every
          ``regrid_every``-th evidence, beyond ``regrid_z``, and after a restart, a bend or
          an outlier.
        """
        cfg = self.settings
        if self.t and self.t[0] < t_now - cfg.horizon:
            keep = [i for i, tt in enumerate(self.t) if tt >= t_now - cfg.horizon]
            self._dropped += len(self.t) - len(keep)
            self.t = [self.t[i] for i in keep]
            self.y = [self.y[i] for i in keep]
            self.s = [self.s[i] for i in keep]
            self.src = [self.src[i] for i in keep]
            self._dirty = True
            self._stale = True
            self._scores = None
        if not self._dirty:
            return
        if len(self.t) < cfg.min_evidence or self.t[-1] - self.t[0] < cfg.min_span:
            self._dirty = False
            self.fit, self.fits, self.weights, self._all = None, [], [], []
            return
        # The schedule counts the segment's evidence, not windows, so a replayed trend
        # takes each evidence as the uninterrupted one did.
        n = len(self.t) + self._dropped
        warm = not full and len(self._all) == (5 if cfg.onset else 3) \
            and self._z <= cfg.regrid_z
        regrid = not n % cfg.regrid_every
        if warm and not regrid and self._z <= cfg.skip_z and self._new == 1 \
                and self.fit is not None and not (self._stale and not n % cfg.refit_every) \
                and all(_finite(f.cov) for f in self.fits):
            self._dirty = False
            self._new = 0
            for f in self.fits:
                f.advance(self.t[-1], self.y[-1], self.s[-1])
            return
        self._dirty = False
        self._new = 0
        self._stale = False
        t, y, s = bin_evidence(np.asarray(self.t), np.asarray(self.y), np.asarray(self.s),
                               cfg.max_points)
        if warm and not regrid and t.size >= self._points:
            fits = refit_models(self._all, t, y, s, t_ref=self.t[-1])
        else:
            fits = fit_models(t, y, s, t_ref=self.t[-1], onset=cfg.onset)
        self._points = int(t.size)
        self._z = 0.0
        self._all = fits
        best, pairs = select(fits, cfg.min_weight)
        self.fit = best
        self.fits = [f for f, _ in pairs]
        self.weights = [w for _, w in pairs]

    # -- what it says -----------------------------------------------------------------------
    @property
    def evidence(self) -> int:
        return len(self.t)

    def degrading(self) -> bool:
        """Step 3 of the module docstring: ``detection`` odds against ``none`` and a drift
        rate beyond ``flat_z`` standard errors."""
        f = self.fit
        if f is None or f.kind == "none":
            return False
        if 1.0 - self._p_none() < self.settings.detection:
            return False
        return abs(f.m) > self.settings.flat_z * f.std("m")

    def _p_none(self) -> float:
        """The ``none`` model's share of the weight (the odds of no degradation)."""
        return sum(w for g, w in zip(self.fits, self.weights, strict=True) if g.kind == "none")

    def scores(self) -> tuple[float | None, float | None]:
        """(monotonicity, trendability) of the segment's evidence (computed again only when
        the evidence changed)."""
        if self._scores is None:
            n = len(self.t)  # fromiter with a count: a list's floats at half asarray's cost
            mono, trd = _scores(np.fromiter(self.t, float, n), np.fromiter(self.y, float, n),
                                self.settings.smooth)
            self._scores = (None if math.isnan(mono) else mono,
                            None if math.isnan(trd) else trd)
        return self._scores

    def model_weight(self) -> float | None:
        """The chosen model's share of the model-averaging weight."""
        if self.fit is None or not self.fits:
            return None
        for f, w in zip(self.fits, self.weights, strict=True):
            if f is self.fit:
                return w
        return None
