"""Every estimated parameter's trend and remaining useful life, window after window.

:class:`Prognostics` is what the twin's adaptation (:class:`~twinwatch.twin.adaptation.
TwinAdapter`) calls once per window with the window's estimate: each parameter's evidence
(:mod:`~twinwatch.twin.prognostics.evidence`) goes to its trend
(:mod:`~twinwatch.twin.prognostics.trend`), which is refitted, and the parameters with an alarm
rule get the predicted crossing of its warning and alarm thresholds
(:mod:`~twinwatch.twin.prognostics.rul`). The result, :class:`Prognosis` per parameter, is
what the health message publishes (``parameters.<name>.trend`` and ``.rul``).
"""

from __future__ import annotations

import functools
import math
import zlib
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Literal, Protocol

import numpy as np
import numpy.typing as npt

from twinwatch.twin.model import FloatArray
from twinwatch.twin.prognostics.config import PrognosticsConfig, Thresholds
from twinwatch.twin.prognostics.rul import (
    Crossing,
    draw_trajectories,
    first_crossings,
    predict_crossing,
    sort_order,
)
from twinwatch.twin.prognostics.trend import (
    Evidence,
    ParameterTrend,
    Restart,
    TrendSettings,
)

__all__ = ["Prognosis", "Prognostics", "RulReport", "StoredHealth", "TrendReport"]


# What :meth:`Prognostics.replay` reads of a stored health message's typed view
# (:func:`twinwatch.twin.health.read_health`), stated here because this package cannot import
# the message's module; a field renamed there fails the type check in daemon/resume.py.
class StoredEvidence(Protocol):
    """``parameters.<name>.trend.window_evidence``: the window's evidence."""

    @property
    def t(self) -> float | None: ...
    @property
    def value(self) -> float | None: ...
    @property
    def std(self) -> float | None: ...
    @property
    def source(self) -> str | None: ...


class StoredRestart(Protocol):
    """``parameters.<name>.trend.restart``: the trend's last restart."""

    @property
    def t(self) -> float | None: ...
    @property
    def step(self) -> float | None: ...
    @property
    def reason(self) -> str | None: ...


class StoredTrend(Protocol):
    """``parameters.<name>.trend``."""

    @property
    def since_t(self) -> float | None: ...
    @property
    def restart(self) -> StoredRestart | None: ...
    @property
    def restarts(self) -> int | None: ...
    @property
    def window_evidence(self) -> StoredEvidence | None: ...


class StoredParameter(Protocol):
    """``parameters.<name>``."""

    @property
    def trend(self) -> StoredTrend | None: ...


class StoredHealth(Protocol):
    """A stored health message, as :meth:`Prognostics.replay` reads it."""

    @property
    def t_end(self) -> float | None: ...
    @property
    def parameters(self) -> Mapping[str, StoredParameter] | None: ...

RulStatus = Literal["insufficient", "not_degrading", "degrading"]


@dataclass
class TrendReport:
    """A parameter's trend after a window (``parameters.<name>.trend``).

    Attributes:
        model: ``none``, ``linear`` or ``exponential`` (None: too little evidence).
        onset: the onset of the degradation [s] (None: from the segment's start).
        since_t: the first evidence of the current segment [s] (after the last restart).
        evidence: evidence windows the trend is fitted to.
        level, level_std: the trend's value at the window's end [SI] and its 1-sigma.
        rate, rate_low, rate_high: drift rate at the latest evidence [SI/s] and its interval.
        rate_pct_per_h: the rate in percent of nominal per hour.
        growth: the exponential's growth rate [1/s] (None otherwise).
        degrading: the trend drifts beyond its uncertainty.
        model_weight: the chosen model's share of the model-averaging weight.
        monotonicity, trendability: the segment's history scores (0..1).
        restarted: this window restarted the trend (a step).
        restart: the last restart (time [s], step [SI], reason), or None.
        restarts: restarts so far.
        window_evidence: this window's evidence (value [SI], 1-sigma [SI], source), or None.
    """

    model: str | None
    onset: float | None
    since_t: float | None
    evidence: int
    level: float | None = None
    level_std: float | None = None
    rate: float | None = None
    rate_low: float | None = None
    rate_high: float | None = None
    rate_pct_per_h: float | None = None
    growth: float | None = None
    degrading: bool = False
    model_weight: float | None = None
    monotonicity: float | None = None
    trendability: float | None = None
    restarted: bool = False
    restart: Restart | None = None
    restarts: int = 0
    window_evidence: Evidence | None = None


@dataclass
class RulReport:
    """A parameter's remaining useful life (``parameters.<name>.rul``): the predicted crossing
    of its alarm rule's warning and alarm thresholds.

    Attributes:
        status: ``insufficient`` (too little evidence since the start or a restart),
            ``not_degrading`` (the trend is flat within its uncertainty), ``degrading``.
        warning, alarm: the crossings (None when the rule has no such level, or not
            degrading).
        method: how the distribution is computed (``monte_carlo``), with ``draws`` and the
            ``interval``'s central probability.
    """

    status: RulStatus
    warning: Crossing | None = None
    alarm: Crossing | None = None
    method: str = "monte_carlo"
    draws: int = 0
    interval: float = 0.95


@dataclass
class Prognosis:
    """One parameter's trend and, with an alarm rule, its RUL."""

    trend: TrendReport
    rul: RulReport | None = None


@dataclass
class _Pace:
    """Wall seconds per plant second over the recent windows."""

    points: deque[tuple[float, float]] = field(default_factory=lambda: deque(maxlen=30))

    def add(self, t: float, wall: float | None) -> None:
        if wall is not None and math.isfinite(wall):
            if self.points and t <= self.points[-1][0]:
                self.points.clear()  # the source's clock went back: start over
            self.points.append((t, wall))

    def value(self) -> float:
        if len(self.points) < 2:
            return 1.0
        (t0, w0), (t1, w1) = self.points[0], self.points[-1]
        return (w1 - w0) / (t1 - t0) if t1 > t0 and w1 >= w0 else 1.0


class Prognostics:
    """Trend and remaining useful life of every estimated parameter.

    Args:
        names: the estimated parameters.
        nominal: parameter -> nameplate value [SI] (for the rate in percent per hour).
        config: the ``[prognostics]`` table.
        thresholds: parameter -> its alarm rule's thresholds [SI] (parameters without one get
            a trend but no RUL).
    """

    def __init__(self, names: Sequence[str], nominal: Mapping[str, float],
                 config: PrognosticsConfig | None = None,
                 thresholds: Mapping[str, Thresholds] | None = None) -> None:
        self.config = config or PrognosticsConfig()
        c = self.config
        knobs = {f.name for f in fields(TrendSettings)}
        self.settings = TrendSettings(**c.model_dump(include=knobs))
        self.names = tuple(names)
        self.nominal = dict(nominal)
        self.thresholds = dict(thresholds or {})
        self.trends = {n: ParameterTrend(n, self.settings) for n in self.names}
        self._pace = _Pace()
        #: (parameter, level) -> the order of its last RUL draws (:func:`sort_order`'s hint)
        self._orders: dict[tuple[str, str], npt.NDArray[np.intp]] = {}
        #: The last window's prognosis per parameter.
        self.latest: dict[str, Prognosis] = {}

    # -- one window ---------------------------------------------------------------------------
    def update(self, evidence: Mapping[str, Evidence], *, t_end: float, jump: bool = False,
               wall: float | None = None) -> dict[str, Prognosis]:
        """Feed one window's evidence and predict.

        Args:
            evidence: parameter -> this window's evidence (parameters without any: absent).
            t_end: the window's last sample time [s] (the RUL counts from it).
            jump: the fusion flagged the window as a sudden change.
            wall: the wall-clock time at the window's end [s since the epoch].

        Returns:
            parameter -> its prognosis (also :attr:`latest`).
        """
        self._pace.add(t_end, wall)
        out: dict[str, Prognosis] = {}
        for name, trend in self.trends.items():
            ev = evidence.get(name)
            trend.add(ev, jump=jump)
            trend.refit(t_end)
            out[name] = self._prognosis(name, trend, ev, t_end, wall)
        self.latest = out
        return out

    def replay(self, messages: Sequence[StoredHealth]) -> int:
        """Rebuild the trends from stored health messages (oldest first, on one time line:
        :meth:`~twinwatch.sinks.store.StateStore.timeline` at a restart): the evidence each
        window published (``parameters.<name>.trend.window_evidence``) since the segment's
        start the latest message names (``trend.since_t``), and its restarts, each taken as
        :meth:`update` took it, so a restart of the daemon changes neither the trend nor the
        RUL.

        Returns:
            The evidence windows replayed.
        """
        n = 0
        for name, trend in self.trends.items():
            latest = _trend_of(messages[-1], name) if messages else None
            if latest is None:
                continue
            restart = latest.restart
            if restart is not None and restart.t is not None and not trend.restarts:
                # the count and the last one: what the health message reports of them
                trend.restarts = [Restart(float(restart.t), _number(restart.step),
                                          restart.reason or "")
                                  ] * max(latest.restarts or 1, 1)
            since = latest.since_t
            if since is None:
                continue
            for msg in messages:
                t = _trend_of(msg, name)
                ev = t.window_evidence if t is not None else None
                if (ev is not None and ev.t is not None and ev.value is not None and ev.std
                        and ev.t >= since and not (trend.t and ev.t <= trend.t[-1])):
                    e = Evidence(float(ev.t), float(ev.value), float(ev.std),
                                 ev.source or "estimated")
                    trend.take(e, trend.innovation(e))
                    n += 1
                if trend.t:
                    trend.refit(float(msg.t_end) if msg.t_end is not None else trend.t[-1])
        return n

    def predict(self, t_end: float) -> dict[str, Prognosis]:
        """Every parameter's prognosis at ``t_end`` [s] from its trend as it stands, without
        new evidence and without changing it (nor :attr:`latest`): what a restart resumed
        (:meth:`replay`) predicts before the next window."""
        return {name: self._prognosis(name, trend, None, t_end, None)
                for name, trend in self.trends.items()}

    # -- reports ------------------------------------------------------------------------------
    def _prognosis(self, name: str, trend: ParameterTrend, ev: Evidence | None, t_end: float,
                   wall: float | None) -> Prognosis:
        f = trend.fit
        mono, trd = trend.scores()
        report = TrendReport(
            model=f.kind if f is not None else None,
            onset=f.onset if f is not None else None,
            since_t=trend.since_t, evidence=trend.evidence,
            monotonicity=mono, trendability=trd, restarted=trend.restarted,
            restart=trend.restarts[-1] if trend.restarts else None,
            restarts=len(trend.restarts), window_evidence=ev)
        degrading = False
        if f is not None:
            degrading = trend.degrading()
            # at the latest evidence: the fit's reference time, unless the fit is kept from
            # an earlier window (ParameterTrend.refit)
            rate, sd = f.rate_at(trend.t[-1])
            z = 1.959963984540054
            nom = self.nominal.get(name) or 0.0
            report.level, report.level_std = f.value_band(t_end)
            report.rate = rate
            report.rate_low, report.rate_high = rate - z * sd, rate + z * sd
            report.rate_pct_per_h = rate / nom * 360000.0 if nom else None
            report.growth = f.r if f.kind == "exponential" else None
            report.degrading = degrading
            report.model_weight = trend.model_weight()
        th = self.thresholds.get(name)
        if th is None:
            return Prognosis(report)
        c = self.config
        rul = RulReport("insufficient", draws=c.draws, interval=c.interval)
        if f is not None:
            rul.status = "degrading" if degrading else "not_degrading"
        if f is not None and degrading:
            mixture = list(zip(trend.fits, trend.weights, strict=True))
            # one sample of the trajectories for both levels
            drawn = draw_trajectories(f, mixture, c.draws, normals=_normals(c.seed, name, c.draws))
            levels = [(level, *th.level(level)) for level in ("warning", "alarm")]
            levels = [(level, high, low) for level, high, low in levels
                      if high is not None or low is not None]
            times = first_crossings(drawn, t_end, [(high, low) for _, high, low in levels])
            for (level, high, low), samples in zip(levels, times, strict=True):
                order = self._orders[name, level] = sort_order(
                    samples, self._orders.get((name, level)))
                cr = predict_crossing(f, level, high, low, t_end=t_end, interval=c.interval,
                                      draws=c.draws, wall_end=wall, pace=self._pace.value(),
                                      trajectories=drawn, times=samples, order=order)
                setattr(rul, level, cr)
        return Prognosis(report, rul)


@functools.lru_cache(maxsize=256)
def _normals(seed: int, name: str, draws: int) -> FloatArray:
    """The standard normals (``draws``, 4) of a parameter's RUL draws, the same in every
    window (common random numbers from ``seed`` and the name: the same evidence gives the
    same RUL); read-only, shared by every machine of the process."""
    z = np.random.default_rng([seed, zlib.crc32(name.encode())]).standard_normal((draws, 4))
    z.flags.writeable = False
    return z


def _number(value: float | None) -> float:
    """A stored number (``null`` for a non-finite one: NaN)."""
    return math.nan if value is None else float(value)


def _trend_of(message: StoredHealth, name: str) -> StoredTrend | None:
    """``parameters.<name>.trend`` of a stored message, None where it has none."""
    parameter = (message.parameters or {}).get(name)
    return parameter.trend if parameter is not None else None
