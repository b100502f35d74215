"""One window of twin adaptation: DT' (estimation) then, when needed, DT'' (discovery).

:class:`TwinAdapter` is what the daemon's adaptation worker calls for each window (paper Fig. 2):

1. the physical parameters are re-estimated with the kept meta-model terms in place
   (:class:`~twinwatch.twin.estimation.Estimator`);
2. the kept terms are polished and re-validated (:meth:`Discovery.revalidate`); a term that no
   longer earns its place is switched off;
3. the residual's structure is tested (:mod:`twinwatch.twin.discovery.trigger`): a window whose
   residual is structured does not update the trusted parameters and publishes its estimates
   ``suspect`` (they are biased by the missing component);
4. when the tests of the last ``trigger_windows`` windows, combined, are below ``false_alarm``,
   discovery searches the candidates (:meth:`Discovery.discover`); new terms join DT'', the
   window is re-estimated with them, and the change is reported. A discovery that keeps nothing
   waits ``retry_after`` windows, unless a term is switched off meanwhile (the twin changed:
   the next structured windows are searched again).

Without a ``[discovery]`` table (or with ``enabled = false``) only step 1 runs.

Then, every window, the prognostics (:mod:`twinwatch.twin.prognostics`): each estimated
parameter's evidence from the window (its estimate, or its share of the fused evidence) joins
its trend, which gives the drift and, for a parameter with an alarm rule, the remaining useful
life; with ``[acquisition.adaptive]`` the next window's length is chosen
(:class:`~twinwatch.twin.prognostics.window.WindowController`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from twinwatch.twin.discovery.search import (
    Discovery,
    DiscoveryConfig,
    DiscoveryReport,
    window_structure,
)
from twinwatch.twin.discovery.terms import Term, compose, format_terms
from twinwatch.twin.discovery.trigger import StructureEvidence, WindowStructure
from twinwatch.twin.estimation.estimator import EstimationConfig, Estimator, WindowEstimate
from twinwatch.twin.estimation.fit import Residual, WindowFit
from twinwatch.twin.estimation.statistics import noise_level
from twinwatch.twin.model import FloatArray, TwinModel, WindowData
from twinwatch.twin.prognostics import (
    AdaptiveWindowConfig,
    Prognosis,
    Prognostics,
    PrognosticsConfig,
    Thresholds,
    fused_share,
    window_evidence,
)
from twinwatch.twin.prognostics.window import WindowChoice, WindowController

logger = logging.getLogger(__name__)


class _Labelled(logging.LoggerAdapter[logging.Logger]):
    """A logger whose lines start with ``label: `` (the machine's name)."""

    def process(self, msg: object, kwargs: Any) -> tuple[object, Any]:
        return f"{(self.extra or {}).get('label')}: {msg}", kwargs

__all__ = ["AdaptationResult", "Residual", "TwinAdapter", "TwinState"]


@dataclass
class AdaptationResult:
    """What one window did to the twin.

    Attributes:
        estimate: the window's parameter estimate; ``simulated``, ``rmse`` and ``nrmse`` are
            those of the final twin (DT'' when terms are kept).
        terms: the kept terms after this window (DT'' = DT + their sum).
        dt_prime: residual of the twin without terms, at the same parameters.
        dt_second: residual with the terms (None without terms).
        noise: output -> estimated white-noise level of the final residual.
        too_large: the final residual is structured: the model lacks something (the trigger's
            window test, :mod:`twinwatch.twin.discovery.trigger`).
        consecutive: windows in a row with a structured residual.
        discovery: the discovery run in this window, if any.
        revalidation: the re-validation of the kept terms, if any.
        changed: terms were added or dropped in this window.
        prognosis: estimated parameter -> its trend and remaining useful life after this
            window (empty when ``[prognostics]`` is off).
        window_choice: the adaptive window's decision (None when it is off).
        structure: the final residual's structure test (None without discovery).
        evidence_p: the combined p-value of the last ``trigger_windows`` windows' tests,
            before a discovery this window ran on them (None without discovery).
    """

    estimate: WindowEstimate
    terms: list[Term]
    dt_prime: Residual
    dt_second: Residual | None
    noise: dict[str, float]
    too_large: bool
    consecutive: int
    discovery: DiscoveryReport | None = None
    revalidation: DiscoveryReport | None = None
    changed: bool = False
    events: list[str] = field(default_factory=list)
    prognosis: dict[str, Prognosis] = field(default_factory=dict)
    window_choice: WindowChoice | None = None
    structure: WindowStructure | None = None
    evidence_p: float | None = None
    #: the window's fit problem (its data and the twin): what the diagnosis fits its
    #: hypothesis twins on (:mod:`twinwatch.twin.diagnosis`)
    fit: WindowFit | None = field(default=None, repr=False)


@dataclass(frozen=True)
class TwinState:
    """The accepted twin a restart resumes from, as the state database keeps it (JSON).

    Attributes:
        trusted: parameter -> its trusted value [SI].
        terms: the kept meta-model terms (:meth:`Term.state_dict
            <twinwatch.twin.discovery.terms.Term.state_dict>` each).
        fusion: the fusion's state (None without fusion).
        floor: the interval floor's state (None: measured again from the windows).
        diagnosis: the diagnosis' baseline and evidence (``Diagnoser.state()``; None without
            a diagnoser: the key is then not written).
    """

    trusted: dict[str, float] = field(default_factory=dict)
    terms: list[dict[str, Any]] = field(default_factory=list)
    fusion: dict[str, Any] | None = None
    floor: dict[str, Any] | None = None
    diagnosis: dict[str, Any] | None = None

    def as_dict(self) -> dict[str, Any]:
        """The JSON object saved: ``trusted``, ``terms``, ``fusion``, ``floor`` and, with a
        diagnoser, ``diagnosis``."""
        out = {"trusted": self.trusted, "terms": self.terms, "fusion": self.fusion,
               "floor": self.floor}
        return out if self.diagnosis is None else {**out, "diagnosis": self.diagnosis}

    @classmethod
    def from_dict(cls, state: Mapping[str, Any]) -> TwinState:
        """Read :meth:`as_dict`'s object (a key missing, as in an older file: its default).

        Raises:
            TypeError, ValueError: ``trusted`` or ``terms`` is not a mapping or a list.
        """
        return cls(dict(state.get("trusted") or {}), list(state.get("terms") or []),
                   state.get("fusion"), state.get("floor"), state.get("diagnosis"))


class TwinAdapter:
    """Estimation and discovery for one twin, window after window.

    Args:
        model: the twin.
        estimation: the ``[estimation]`` table.
        discovery: the ``[discovery]`` table (None: estimation only).
        nominal: parameter -> nameplate value [SI].
        prognostics: the ``[prognostics]`` table (None: its defaults).
        thresholds: parameter -> its alarm rule's thresholds [SI] (the RUL's targets).
        adaptive: the ``[acquisition.adaptive]`` table (None or disabled: a fixed window).
        label: the machine's name, leading each log line.

    Raises:
        ValueError: a configuration names a parameter, attach point or input the model lacks.
    """

    def __init__(self, model: TwinModel, estimation: EstimationConfig,
                 discovery: DiscoveryConfig | None = None,
                 nominal: Mapping[str, float] | None = None,
                 prognostics: PrognosticsConfig | None = None,
                 thresholds: Mapping[str, Thresholds] | None = None,
                 adaptive: AdaptiveWindowConfig | None = None, label: str = "") -> None:
        self.model = model
        #: The log, each line led by ``label`` (the machine's name).
        self._log: logging.Logger | logging.LoggerAdapter[logging.Logger] = (
            _Labelled(logger, {"label": label}) if label else logger)
        self.estimator = Estimator(model, estimation, nominal)
        prog = prognostics or PrognosticsConfig()
        nom = dict(zip(model.parameter_names, (float(v) for v in self.estimator.nominal),
                       strict=True))
        #: Trend and RUL of every estimated parameter (None when ``[prognostics]`` is off).
        self.prognostics = (Prognostics(self.estimator.pmap.estimate, nom, prog, thresholds)
                            if prog.enabled else None)
        self.adaptive = adaptive if adaptive is not None and adaptive.enabled else None
        #: The adaptive window's controller (created with the first window).
        self.window_controller: WindowController | None = None
        self.config = discovery or DiscoveryConfig()
        self.discovery = (Discovery(model, self.config, self.estimator)
                          if self.config.enabled else None)
        self.terms: list[Term] = []
        self.consecutive = 0
        self._cooldown = 0
        #: The last windows' structure tests, combined (the trigger).
        self.evidence = StructureEvidence(self.config.trigger_windows, self.config.false_alarm)

    @property
    def enabled(self) -> bool:
        return self.discovery is not None

    # -- one window -----------------------------------------------------------------------
    def process(self, window: WindowData) -> AdaptationResult:
        """Adapt the twin to one window (see the module docstring).

        Raises:
            ValueError: a required channel is missing or not finite.
        """
        t0 = time.perf_counter()
        est_ = self.estimator
        fit = est_.window_fit(window)
        snapshot = est_.snapshot()
        t_mid = float(0.5 * (window.t[0] + window.t[-1]))
        prior = (est_.fusion.predict(t_mid) if est_.fusion is not None
                 and self.prognostics is not None else None)
        est = est_.estimate(window, compose(self.terms, window) if self.terms else None,
                            fit=fit)
        if self.discovery is None:
            noise = self._noise(fit, est.simulated)
            return self._finish(window, AdaptationResult(
                est, [], fit.residual(est.simulated), None, noise, False, 0), prior, fit)
        theta = self._theta(est)
        reval = None
        changed = False
        events: list[str] = []
        if self.terms:
            used = [(t, t.params.copy()) for t in self.terms]
            reval = self.discovery.revalidate(fit, theta, self.terms, self._free(est))
            if self._terms_moved(used):
                # The terms' polish on this window moved them beyond their refined
                # uncertainty (typical right after a discovery): estimate it again with the
                # refined terms, forgetting what the first estimate taught the fusion.
                self._log.debug("window %d: the kept terms moved in their polish: estimated "
                                  "again with them", window.index)
                est_.rollback(snapshot)
                est = est_.estimate(window, compose(self.terms, window), fit=fit)
                theta = self._theta(est)
            if reval.dropped:
                # DT'' lost a term: a wait left by an earlier fruitless search no longer
                # holds (e.g. a shaft-following term dropped at a speed change is searched
                # for again at the new speed)
                self._cooldown = 0
            for t in reval.dropped:
                changed = True
                events.append(f"dropped: {t.describe()}")
                self._log.warning("window %d: meta-model term switched off (no longer earns its "
                                    "place): %s", window.index, t.describe())
            for t in reval.kept:
                events.append(f"simplified to: {t.describe()}")
                self._log.warning("window %d: meta-model term simplified to %s", window.index,
                                    t.describe())
            est = self._resimulate(est, fit, theta)
        structure = self._structure(fit, est)
        too_large = structure.structured
        self.consecutive = self.consecutive + 1 if too_large else 0
        evidence_p = self.evidence.add(structure)
        if too_large and est.trusted:
            # The window misses a component: its estimates are biased, do not trust them, and
            # publish no fused value that took its evidence (the filter is rolled back)
            est_.rollback(snapshot)
            est = est_.withdraw(dataclasses.replace(est, trusted=False))
        disc = None
        if self._cooldown > 0:
            self._cooldown -= 1
        elif self.evidence.triggered and len(self.terms) < self.config.max_terms:
            self._log.info("window %d: the residual is structured (%s; the last %d windows "
                             "together p = %.1e < false_alarm %.0e): discovery runs", window.index,
                             structure.describe(), self.config.trigger_windows, evidence_p,
                             self.config.false_alarm)
            self.evidence.clear()
            disc = self.discovery.discover(fit, theta, self.terms)[1]
            if disc.kept:
                self.terms.extend(disc.kept)
                changed = True
                for t in disc.kept:
                    events.append(f"discovered: {t.describe()}")
                    self._log.warning("window %d: unknown component discovered in %.2f s "
                                        "(%d twin evaluations): %s", window.index, disc.elapsed_s,
                                        disc.evaluations, t.describe())
                est = est_.estimate(window, compose(self.terms, window), fit=fit)
                prior = None  # the fusion took this window twice: no share of its own
                theta = self._theta(est)
                self.discovery.polish_terms(fit, theta, self.terms, self._free(est))
                est = self._resimulate(est, fit, theta)
                structure = self._structure(fit, est)
                too_large = structure.structured
                self.consecutive = 0
            else:
                self._cooldown = self.config.retry_after
                self._log.info("window %d: discovery ran (%.2f s, %d candidates) and no "
                                 "meta-model earned its place; next try in %d windows",
                                 window.index, disc.elapsed_s, disc.tried, self._cooldown)
        if too_large:
            est = self._suspect(est, disc)
        if changed:
            self._log.info("DT'' is now:\n%s", format_terms(self.terms) or "(no terms)")
        y_dt = fit.simulate(theta[None, :])[0] if self.terms else est.simulated
        est = dataclasses.replace(est, elapsed_s=time.perf_counter() - t0)
        return self._finish(window, AdaptationResult(
            estimate=est,
            terms=list(self.terms),
            dt_prime=fit.residual(y_dt),
            dt_second=fit.residual(est.simulated) if self.terms else None,
            noise=self._noise(fit, est.simulated),
            too_large=too_large,
            consecutive=self.consecutive,
            discovery=disc,
            revalidation=reval,
            changed=changed,
            events=events,
            structure=structure,
            evidence_p=evidence_p,
        ), prior, fit)

    # -- prognostics ----------------------------------------------------------------------
    def _finish(self, window: WindowData, result: AdaptationResult,
                prior: tuple[FloatArray, FloatArray] | None, fit: WindowFit
                ) -> AdaptationResult:
        """After the twin's fit: keep the fit problem for the diagnosis, feed the window's
        evidence to the trends (:mod:`twinwatch.twin.prognostics`) and choose the next
        window's length (``[acquisition.adaptive]``)."""
        result.fit = fit
        t0 = time.perf_counter()
        est = result.estimate
        t_mid = float(0.5 * (window.t[0] + window.t[-1]))
        evidence = {}
        if self.prognostics is not None:
            shares = None
            fusion = self.estimator.fusion
            if prior is not None and fusion is not None and est.trusted \
                    and not est.fusion_jump:
                shares = fused_share(fusion.names, prior,
                                     (fusion.state.mean, fusion.state.cov))
            evidence = window_evidence(est, t_mid, fused=shares,
                                       max_rel_std=self.prognostics.config.max_rel_std)
            result.prognosis = self.prognostics.update(
                evidence, t_end=float(window.t[-1]), jump=est.fusion_jump, wall=time.time())
        if self.adaptive is not None:
            result.window_choice = self._choose_window(window, result, evidence, fit)
        result.estimate = dataclasses.replace(
            est, elapsed_s=est.elapsed_s + time.perf_counter() - t0)
        return result

    def _choose_window(self, window: WindowData, result: AdaptationResult,
                       evidence: Mapping[str, Any], fit: WindowFit) -> WindowChoice:
        assert self.adaptive is not None
        n = int(window.n)
        if self.window_controller is None:
            period = float(np.median(np.diff(window.t))) if n > 1 else 1.0
            self.window_controller = WindowController(self.adaptive, n, period)
        est = result.estimate
        rates = self.estimator.fusion.rates() if self.estimator.fusion is not None else {}
        drift: dict[str, tuple[float, float]] = {}
        for name, ev in evidence.items():
            if ev.source != "estimated":
                continue
            p = result.prognosis.get(name)
            rate = p.trend.rate if p is not None and p.trend.rate is not None else None
            if rate is None:
                rate = rates.get(name, 0.0) * ev.value
            # The window's uncertainty as the evidence scatters about its trend when that is
            # less than stated (noise-free, the model-error floor overstates it, and a window
            # lengthened on it lags a drift it cannot see).
            trend = self.prognostics.trends.get(name) if self.prognostics else None
            fit_ = trend.fit if trend is not None else None
            scale = min(1.0, fit_.rms_norm) if fit_ is not None and fit_.rms_norm > 0 else 1.0
            drift[name] = (float(rate), float(ev.std) * scale)
        # The residual against its white-noise level, both normalised and pooled over the
        # outputs as the exit criterion pools them (a noise-free output, the closed loop's
        # Va, would otherwise always look structured); not below a 0.1 % nRMSE.
        ratio = None
        res = fit.error_matrix(est.simulated)
        if np.all(np.isfinite(res)):
            nrmse = float(np.sqrt(np.mean(res * res)))
            noise = float(np.sqrt(np.mean(noise_level(res) ** 2)))
            if nrmse > 1e-3 and noise > 0:
                ratio = nrmse / noise
        return self.window_controller.decide(n, drift, ratio)

    # -- persistence ----------------------------------------------------------------------
    def state(self) -> TwinState:
        """The accepted twin: trusted parameters and kept terms (without ``diagnosis``)."""
        return TwinState(self.estimator.trusted_values(), [t.state_dict() for t in self.terms],
                         self.estimator.fusion_state(), self.estimator.floor_state())

    def restore(self, state: TwinState) -> None:
        """Resume from :meth:`state` (unknown parameters are ignored with a warning).

        Raises:
            KeyError, TypeError, ValueError: a saved term does not fit the model.
        """
        for name in self.estimator.set_trusted(state.trusted):
            self._log.warning("saved state names unknown parameter %r: ignored", name)
        if not self.estimator.set_fusion_state(state.fusion) and state.fusion:
            self._log.warning("saved fusion state does not fit the estimated parameters: the "
                                "fusion starts again from the trusted values")
        if not self.estimator.set_floor_state(state.floor) and state.floor:
            self._log.warning("the saved structural term of the intervals (the floor) cannot be "
                                "read: it is measured again from this run's windows, the published "
                                "intervals narrower until it is")
        self.terms = [Term.from_dict(d, self.model) for d in state.terms]

    # -- helpers --------------------------------------------------------------------------
    def _theta(self, est: WindowEstimate) -> FloatArray:
        """The parameters the window's twin ran with (its fit), for the meta-models: not the
        published values, which may be a fused value the window was not fitted with (a term
        refined beside it would drift away)."""
        vals = est.fitted or est.values
        return np.array([vals[n] for n in self.model.parameter_names])

    @staticmethod
    def _suspect(est: WindowEstimate, disc: DiscoveryReport | None) -> WindowEstimate:
        """The window's residual says the model lacks a component: what it estimated is
        published ``suspect`` with the reason, so it moves no alarm (the alarms read
        ``estimated`` and ``fused`` values only)."""
        why = ("suspect: the residual is too large for the model (a component is missing; "
               + ("discovery found none that earns its place yet)" if disc is not None
                  else "discovery pending)"))
        status = dict(est.status)
        held = dict(est.held)
        for n, st in est.status.items():
            if st == "estimated":
                status[n] = "suspect"
                held[n] = why
        return dataclasses.replace(est, status=status, held=held)

    def _free(self, est: WindowEstimate) -> list[str]:
        """The physical parameters a kept term is polished jointly with: those this window
        determined (``[discovery.refinement] joint``; none when it is off)."""
        if not self.config.refinement.joint:
            return []
        return list(est.estimated)

    @staticmethod
    def _terms_moved(used: list[tuple[Term, FloatArray]], k: float = 3.0) -> bool:
        """Whether a kept term's parameters moved in this window's polish by more than ``k``
        of their refined standard errors (or by more than 1e-9 relative without one)."""
        for term, before in used:
            act = np.array(term.active, dtype=bool)
            d = np.abs(term.params[act] - before[act])
            std = term.params_std
            tol = (k * std if std is not None and std.shape == d.shape
                   and np.all(np.isfinite(std)) else 1e-9 * np.maximum(np.abs(before[act]), 1e-12))
            if np.any(d > tol):
                return True
        return False

    def _noise(self, fit: WindowFit, y: FloatArray) -> dict[str, float]:
        lvl = noise_level(y - fit.meas)
        return dict(zip(fit.names, (float(v) for v in lvl), strict=True))

    def _structure(self, fit: WindowFit, est: WindowEstimate) -> WindowStructure:
        """The structure test (:mod:`twinwatch.twin.discovery.trigger`) of the final twin's
        residual; a non-finite fit is structured."""
        if not math.isfinite(est.nrmse):
            return WindowStructure({}, 0.0, True)
        r = fit.error_matrix(est.simulated).reshape(-1)
        return window_structure(r / math.sqrt(r.size), fit.n_out, self.config, fit.names)

    def _resimulate(self, est: WindowEstimate, fit: WindowFit, theta: FloatArray
                    ) -> WindowEstimate:
        """The estimate with the (re-polished) terms' simulation and fit."""
        y = fit.simulate(theta[None, :],
                         compose(self.terms, fit.window) if self.terms else None)[0]
        res = fit.residual(y)
        return dataclasses.replace(est, simulated=y, rmse=res.rmse, nrmse=res.nrmse)
