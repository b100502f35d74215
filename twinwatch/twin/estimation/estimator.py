"""Per-window parameter estimation: the DT' step (paper Section 3.2), as stages.

Each acquisition window, the parameters that no sensor measures are re-estimated by minimising
the normalised RMSE between measured and simulated outputs (paper Eq. 1-2,
:class:`~twinwatch.twin.estimation.fit.WindowFit`). :meth:`Estimator.estimate` builds the
window's problem (:class:`~twinwatch.twin.estimation.problem.WindowProblem`) and runs small
stages on it, each a module of this room that says what it implements and why:

1. **global search** (:mod:`~twinwatch.twin.estimation.search`): warm-started PSO;
2. **polish** (:mod:`~twinwatch.twin.estimation.polish`): bounded least squares, jointly with
   the window's initial state;
3. **identifiability gate** (:mod:`~twinwatch.twin.estimation.gate`): parameters admitted in
   priority order, the others held at their last trusted value;
4. **model check** (:mod:`~twinwatch.twin.estimation.check`) and sensors
   (:mod:`~twinwatch.twin.estimation.quality`): a window that fails either is not sound: its
   estimates are published ``suspect``;
5. **fusion** (:mod:`~twinwatch.twin.estimation.fusion`): a Kalman filter on the parameters
   across windows;

then :mod:`~twinwatch.twin.estimation.publish` gives each parameter's published value and
status, and a sound window updates the trusted values later windows hold (once the next
estimate agrees: :meth:`Estimator._trust`). With the same seed and no time cap hit, results
are bit-for-bit reproducible.

**Local first** (``[estimation] strategy = "local_first"``, the default). A machine's parameters
drift slowly, so the global search is skipped and stage 2 polishes from the trusted values,
unless the swarm is due (:meth:`Estimator._swarm_due`). A local fit is *rejected*, and the
same window estimated again from the start with the swarm, when its residual is beyond what the
window's noise explains (:meth:`Estimator._residual_too_large`) or it fails its model check.
``strategy = "swarm"`` runs the swarm every window; the paper's method is ``strategy = "swarm"``
with Table 2's swarm (``[estimation.pso] max_generations = 1000``) and ``polish = false``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from pydantic import (
    Field,
    StrictFloat,
    StrictInt,
    field_validator,
    model_validator,
)

from twinwatch._table import StrictTable
from twinwatch.twin.estimation.check import ValidationConfig, check_twin, model_check
from twinwatch.twin.estimation.fit import (
    NUMERICAL_SHARE,
    ParameterMap,
    WindowFit,
    long_run_factors,
    relative_std,
)
from twinwatch.twin.estimation.floor import FloorState, StructuralFloor
from twinwatch.twin.estimation.fusion import (
    FusionConfig,
    FusionState,
    ParameterFusion,
    fuse_window,
)
from twinwatch.twin.estimation.gate import GateDecision, IdentifiabilityGate
from twinwatch.twin.estimation.polish import Polished, polish, polish_admitted
from twinwatch.twin.estimation.problem import FitPoint, TwinAt, WindowProblem, check_window
from twinwatch.twin.estimation.publish import ParameterStatus, publish
from twinwatch.twin.estimation.quality import SensorFault, live_outputs, sensor_faults
from twinwatch.twin.estimation.search import PSOSettings, SearchResult, global_search, warm_start
from twinwatch.twin.estimation.statistics import ModelCheck, mean, noise_level
from twinwatch.twin.model import FloatArray, TwinModel, WindowData

logger = logging.getLogger(__name__)

#: Two estimates of a parameter agree when they are within this many combined standard errors
#: (after the change the fused rate explains) and at most :data:`CONFIRM_WITHIN_S` apart: the
#: second makes it trusted (:meth:`Estimator._trust`).
CONFIRM = 2.0
CONFIRM_WITHIN_S = 10.0
#: A local-first window's fusion stops iterating once no level moves by more than this share
#: of its posterior standard error (:meth:`ParameterFusion.update`'s ``step_tol``).
LOCAL_FUSION_STEP_TOL = 0.01
#: A local-first window polishes only the parameters the last window's gate admitted (the
#: others at their trusted values, the set confirmed by the gate on one sensitivity call of
#: every column; another set: the polish of every parameter): 8 twin calls a window instead of
#: 50. It relies on :data:`~twinwatch.twin.estimation.fusion.OWN_INFORMATION` and on
#: :meth:`Estimator._keep_consistent` propagating only values trusted anew. False: the full
#: polish.
POLISH_ADMITTED = True
#: A window re-tried with the unconfirmed estimates (:meth:`Estimator._unconfirmed`) keeps
#: the retry when its nRMSE is below this share of the first fit's.
RETRY_GAIN = 0.5

__all__ = [
    "EstimationConfig",
    "Estimator",
    "EstimatorState",
    "PSOSettings",
    "ParameterStatus",
    "ValidationConfig",
    "WindowEstimate",
]


class EstimationConfig(StrictTable):
    """What to estimate and how (table ``[estimation]``).

    ``estimate`` and ``tie`` left out mean "the model's" (:attr:`TwinModel.estimation_defaults`:
    the DC motor estimates Ra, D, Ke, La, J with Kt tied to Ke; the hydraulic actuator q_pump
    and D); :meth:`resolved` fills them in.
    """

    estimate: list[str] | None = Field(
        None,
        description="parameters to estimate, in priority order (first kept when not all "
        "can be determined); default: the model's",
    )
    tie: dict[str, str] | None = Field(
        None,
        description="parameter -> parameter it equals (Kt = Ke in SI units); default: the "
        "model's",
    )
    bounds: dict[str, tuple[StrictFloat, StrictFloat]] = Field(
        default_factory=dict,
        description="parameter -> [low, high] in SI units; default [nominal/5, nominal*5]",
    )
    pso: PSOSettings = Field(default_factory=PSOSettings)
    strategy: Literal["local_first", "swarm"] = Field(
        "local_first", description="local_first: polish from the trusted values and run the "
        "swarm only at start, after a rejected local fit, after a sudden change and every "
        "swarm_every windows; swarm: the swarm every window (the paper's method with "
        "[estimation.pso] max_generations = 1000 and polish = false)")
    swarm_every: StrictInt = Field(
        30, ge=0, description="local_first: run the swarm at least every this many windows "
        "as a guard against a local optimum (0: only at start, after a rejected fit or a "
        "sudden change)")
    local_residual_ratio: StrictFloat = Field(
        3.0, gt=1.0, allow_inf_nan=False, description="local_first: a local fit whose "
        "nRMSE exceeds this many times what the window's noise explains (or the last swarm "
        "window's nRMSE, if larger) is rejected and the window estimated with the swarm")
    polish: bool = Field(True, description="least-squares polish after the PSO")
    time_budget: StrictFloat = Field(0.5, gt=0, description="PSO time cap per window [s]")
    max_rel_std: StrictFloat = Field(
        0.01, gt=0, description="largest relative standard error of a published estimate"
    )
    model_error: StrictFloat = Field(
        1e-4, ge=0, description="floor of the normalised residual level used for the "
        "standard errors (model and discretisation error of noise-free data)"
    )
    trust_rel_std: StrictFloat = Field(
        0.01, gt=0, description="an estimate becomes the trusted value (held by later windows "
        "that cannot determine it) only if its relative standard error is below this; set it "
        "tighter than max_rel_std when a held value's error would propagate (D = Ke*ia/omega "
        "- c amplifies a Ke error about 5 times)"
    )
    trust_rmse: StrictFloat = Field(
        0.05, gt=0, description="a window whose normalised RMSE exceeds this does not "
        "update the trusted parameters"
    )
    validation: ValidationConfig = Field(default_factory=ValidationConfig)
    fusion: FusionConfig = Field(default_factory=FusionConfig)
    initial_state: bool = Field(
        True, description="estimate each window's initial state (offsets to the first "
        "sample's measured outputs) with the parameters: a noisy first sample otherwise leaves "
        "a transient in the residual and biases the estimates")
    seed: StrictInt = 0

    @field_validator("estimate")
    @classmethod
    def _not_empty(cls, value: list[str] | None) -> list[str] | None:
        if value is not None and not value:
            raise ValueError("no parameter listed: name at least one to estimate, or leave "
                             "the key out for the model's default")
        return value

    @model_validator(mode="after")
    def _check(self) -> EstimationConfig:
        if self.estimate is not None and len(set(self.estimate)) != len(self.estimate):
            raise ValueError("estimate: a parameter is listed twice")
        for name, (lo, hi) in self.bounds.items():
            if not (0 < lo < hi):
                raise ValueError(f"bounds.{name}: need 0 < low < high, got [{lo}, {hi}]")
        for dep, src in (self.tie or {}).items():
            if self.estimate is not None and dep in self.estimate:
                raise ValueError(f"tie.{dep}: a tied parameter cannot also be estimated")
            if dep == src:
                raise ValueError(f"tie.{dep}: cannot be tied to itself")
        return self

    def resolved(self, model: TwinModel) -> EstimationConfig:
        """This table with ``estimate`` and ``tie`` filled in from the model's defaults where
        left out (a tie whose parameter the configuration estimates is dropped).

        Raises:
            ValueError: naming the key, if a parameter name is not the model's.
        """
        defaults = model.estimation_defaults
        estimate = list(self.estimate) if self.estimate is not None else list(defaults.estimate)
        if self.tie is not None:
            tie = dict(self.tie)
        else:
            tie = {d: s for d, s in defaults.tie.items() if d not in estimate}
        out = self.model_copy(update={"estimate": estimate, "tie": tie})
        out.check_against(model)
        for dep in tie:
            if dep in estimate:
                raise ValueError(f"estimation.tie.{dep}: a tied parameter cannot also be "
                                 "estimated")
        return out

    def check_against(self, model: TwinModel) -> None:
        """Raise ValueError naming the key if a parameter name is not the model's."""
        names = set(model.parameter_names)
        tie = self.tie or {}
        for key, group in (("estimate", self.estimate or []), ("bounds", list(self.bounds)),
                           ("tie", list(tie) + list(tie.values()))):
            for n in group:
                if n not in names:
                    raise ValueError(
                        f"estimation.{key}: unknown parameter {n!r}; the model has "
                        f"{sorted(names)}"
                    )


@dataclass
class WindowEstimate:
    """The result of one window's estimation.

    Attributes:
        values: every model parameter -> value [SI] (estimated, held, tied or fixed).
        estimated: parameters the data determined this window, with their values.
        held: parameter -> reason it is not an estimate of this window (also for a fused one).
        rel_std: estimated parameter -> relative standard error (1-sigma, fraction).
        rmse: output -> RMSE in the output's unit.
        nrmse: normalised RMSE (the fitness).
        simulated: twin outputs at ``values``, shape (N, n_outputs).
        elapsed_s: wall time of the estimation [s].
        generations: PSO iterations run; ``time_capped`` tells whether the time budget hit.
        evaluations: twin simulations of one parameter vector (particles + polish).
        trusted: whether this window updated the trusted parameters.
        initial: the window's estimated initial-state offsets (``model.initial_states``, in
            their units), or None.
        model_check: the window's model validation (None when disabled); a window that fails
            it does not update the trusted values and its standard errors are widened.
        status: every model parameter -> ``estimated`` (determined by this window, whose
            model check passed and whose sensors are sound), ``fused`` (not by this window
            alone, but by the evidence of the windows so far: the fused value, :attr:`fused`),
            ``suspect`` (the estimate of a window that is not sound, or a held value the fused
            evidence contradicts: treat like held), ``held`` (its last trusted value, reason
            in :attr:`held`), ``tied`` (equals another parameter) or ``fixed`` (nameplate,
            not estimated); :mod:`~twinwatch.twin.estimation.publish`.
        fused: estimated parameter -> (fused value [SI], relative standard error) after this
            window (:mod:`twinwatch.twin.estimation.fusion`); empty when fusion is off.
        fusion_jump: the window's estimate was a sudden change for the fusion (it followed).
        fitted: every model parameter -> the value the window's twin ran with [SI] (the
            estimates and the held values it was fitted with; ``values`` may publish a fused
            value instead): what ``simulated`` is, and what meta-models are fitted beside.
        sensors: the window's frozen or saturated sensors
            (:mod:`~twinwatch.twin.estimation.quality`); such a window is not sound.
        search: ``swarm`` (the global search ran: ``generations`` > 0) or ``local`` (polished
            from the trusted values, ``[estimation] strategy = "local_first"``).
        search_reason: why the swarm ran (``start``, ``guard``, ``sudden change``,
            ``rolled back``, ``rejected: ...`` when the local fit was rejected first,
            ``every window`` with ``strategy = "swarm"``); empty for a local window.
        floor: parameter the window determined -> the structural term added to its published
            relative standard error (1 sigma, fraction; :mod:`~twinwatch.twin.estimation.floor`):
            ``rel_std = sqrt(sigma^2 + floor^2)``, ``sigma`` the window's own.
        long_run: parameter the window determined -> the factor its published standard error
            was multiplied by for the residual's serial correlation with its sensitivity
            (:func:`~twinwatch.twin.estimation.fit.long_run_factors`; >= 1), before the floor.
    """

    values: dict[str, float]
    estimated: dict[str, float]
    held: dict[str, str]
    rel_std: dict[str, float]
    rmse: dict[str, float]
    nrmse: float
    simulated: FloatArray
    elapsed_s: float
    generations: int
    time_capped: bool
    evaluations: int
    trusted: bool = False
    status: dict[str, ParameterStatus] = field(default_factory=dict)
    initial: FloatArray | None = None
    model_check: ModelCheck | None = None
    fused: dict[str, tuple[float, float]] = field(default_factory=dict)
    fusion_jump: bool = False
    sensors: list[SensorFault] = field(default_factory=list)
    fitted: dict[str, float] = field(default_factory=dict)
    search: Literal["swarm", "local"] = "swarm"
    search_reason: str = ""
    floor: dict[str, float] = field(default_factory=dict)
    long_run: dict[str, float] = field(default_factory=dict)


@dataclass
class _Fitted:
    """Stages 1-4 on one window: what the rest of :meth:`Estimator.estimate` reads (the
    problem: the window's, or the retry's holding never-confirmed estimates)."""

    problem: WindowProblem
    found: SearchResult
    polished: Polished
    decision: GateDecision
    point: FitPoint
    twin: TwinAt
    check: ModelCheck | None
    rejected: str = ""


@dataclass(frozen=True)
class EstimatorState:
    """What an :class:`Estimator` carries from one window to the next (its trusted parameter
    vector and the fusion's state), for :meth:`Estimator.snapshot` /
    :meth:`Estimator.rollback`."""

    trusted: FloatArray
    fusion: FusionState | None
    trusted_std: FloatArray
    candidates: dict[str, tuple[float, float, float]]
    depends: dict[str, dict[str, tuple[float, float, int]]]
    provisional: frozenset[str]
    anew: dict[str, tuple[float, int]]
    floor: FloorState


class Estimator:
    """Estimates a twin's parameters on one window at a time.

    Args:
        model: the twin.
        config: estimation settings (``estimate``/``tie`` left out: the model's defaults).
        nominal: parameter -> nameplate value [SI] (defaults to the model's nominal values).

    Raises:
        ValueError: if the config names a parameter the model does not have, or a default
            search range is not positive.
    """

    def __init__(
        self,
        model: TwinModel,
        config: EstimationConfig,
        nominal: Mapping[str, float] | None = None,
    ) -> None:
        config = config.resolved(model)
        assert config.estimate is not None and config.tie is not None
        self.model = model
        self.config = config
        self.names = model.parameter_names
        self.nominal = model.nominal_vector(nominal)
        self.pmap = ParameterMap(self.names, config.estimate, config.tie)
        lo, hi = [], []
        for n in config.estimate:
            nom = self.nominal[self.names.index(n)]
            b = config.bounds.get(n, (nom / 5.0, nom * 5.0))
            if not 0 < b[0] < b[1]:
                raise ValueError(
                    f"estimation.bounds.{n}: the nominal value {nom:g} gives no positive default "
                    "range; parameters are estimated on a log scale, so set a positive "
                    f"[low, high] for {n} (or do not estimate it)")
            lo.append(b[0])
            hi.append(b[1])
        self.lower = np.array(lo)
        self.upper = np.array(hi)
        #: The trusted parameter vector (full), updated by good windows.
        self.trusted = self.nominal.copy()
        #: Relative standard error of each trusted value (full; 0 for a nameplate value).
        self.trusted_std = np.zeros(len(self.names))
        #: The last estimate eligible for trust of each parameter (value [SI], relative
        #: standard error, the window's middle [s]): the next one must agree with it
        #: (:meth:`_trust`).
        self._candidates: dict[str, tuple[float, float, float]] = {}
        #: Parameters whose trusted value is one unconfirmed estimate (:meth:`_trust`).
        self._provisional: set[str] = set()
        #: Per output, whether its readings were live in a window without a sensor fault
        #: (:func:`~twinwatch.twin.estimation.quality.live_outputs`).
        self._live: dict[str, bool] = {}
        #: Per output, the level it was last found saturated at.
        self._clips: dict[str, float] = {}
        #: :meth:`unobservable`'s last answer and the (sample period, trusted vector) it is for
        self._unobservable: tuple[Any, dict[str, str]] = (None, {})
        #: Per trusted parameter, the values it was fitted with held: name -> (d ln p / d ln q,
        #: q's trusted value then, q's :attr:`_anew` count then) (:meth:`_keep_consistent`).
        self._depends: dict[str, dict[str, tuple[float, float, int]]] = {}
        #: parameter -> (the value it was last trusted at from its own estimate, a count of
        #: such trusts): what :meth:`_keep_consistent` propagates (not its own shifts)
        self._anew: dict[str, tuple[float, int]] = {}
        self._rng = np.random.default_rng(config.seed)
        #: Evidence across windows (None when ``[estimation.fusion] enabled = false``).
        self.fusion = (ParameterFusion(tuple(config.estimate), self.trusted[self.pmap.idx],
                                       config.fusion) if config.fusion.enabled else None)
        #: Stage 3: the identifiability gate.
        self.gate = IdentifiabilityGate(config.estimate, config.max_rel_std, config.model_error,
                                        len(model.outputs))
        #: Local first: windows since the last swarm (None before the first), why the next
        #: window must run it (empty: it need not), and the nRMSE the last swarm reached.
        self._since_swarm: int | None = None
        #: windows the first guard swarm comes early (:meth:`stagger_guard`; 0: none)
        self.guard_phase = 0
        self._swarm_next = ""
        self._swarm_nrmse = 0.0
        #: The last window's admitted set (the gate's, before the model check): a local-first
        #: window polishes only these, and the gate confirms the set (:meth:`_fit`).
        self._admitted: list[int] | None = None
        #: Whether the last window was trusted (fit, check passed, sensors sound): only then
        #: does a window hold a :meth:`_stale` parameter at its fused value.
        self._fits = False
        #: The interval's floor (:mod:`~twinwatch.twin.estimation.floor`).
        self.floor = StructuralFloor(len(config.estimate))

    # -- state ----------------------------------------------------------------------------
    def snapshot(self) -> EstimatorState:
        """The state carried between windows, to :meth:`rollback` to."""
        return EstimatorState(self.trusted.copy(),
                              self.fusion.state.copy() if self.fusion else None,
                              self.trusted_std.copy(), dict(self._candidates),
                              {n: dict(d) for n, d in self._depends.items()},
                              frozenset(self._provisional), dict(self._anew),
                              self.floor.state.copy())

    def rollback(self, state: EstimatorState) -> None:
        """Forget what windows since :meth:`snapshot` taught (windows the adaptation found
        biased by a missing component)."""
        self.trusted[:] = state.trusted
        self.trusted_std[:] = state.trusted_std
        self._candidates = dict(state.candidates)
        self._depends = {n: dict(d) for n, d in state.depends.items()}
        self._provisional = set(state.provisional)
        self._anew = dict(state.anew)
        self.floor.state = state.floor.copy()
        if self.fusion is not None and state.fusion is not None:
            self.fusion.state = state.fusion.copy()
        # search globally again
        self._swarm_next = "rolled back"

    def withdraw(self, est: WindowEstimate) -> WindowEstimate:
        """The window's estimate once :meth:`rollback` has taken its evidence back: a
        parameter published ``fused`` keeps the rolled-back filter's value where it still meets
        the fusion's gate, else it is held at its trusted value."""
        if self.fusion is None or not est.fused:
            return est
        f_val, f_std, ratio = self.fusion.values(), self.fusion.rel_std(), self.fusion.birge()
        fused = {n: (f_val[n], f_std[n] * ratio[n]) for n in est.fused}
        status, values = dict(est.status), dict(est.values)
        rel_std, held = dict(est.rel_std), dict(est.held)
        for n, st in est.status.items():
            if st != "fused" or n not in fused:
                continue
            value, sd = fused[n]
            if sd <= self.config.fusion.max_rel_std:
                values[n], rel_std[n] = value, sd
                continue
            status[n] = "held"
            values[n] = float(self.trusted[self.names.index(n)])
            rel_std.pop(n, None)
            held[n] = ("the fused evidence without this window (rolled back: its residual is "
                       "too large for the model) does not determine it: held at last trusted "
                       "value")
        for dep, src in self.pmap.ties:
            values[self.names[dep]] = values[self.names[src]]
        return dataclasses.replace(est, fused=fused, status=status, values=values,
                                   rel_std=rel_std, held=held)

    def fusion_state(self) -> dict[str, Any] | None:
        """The fusion's state (JSON-serialisable), for persistence."""
        return self.fusion.state.as_dict() if self.fusion else None

    def set_fusion_state(self, state: Mapping[str, Any] | None) -> bool:
        """Resume the fusion from :meth:`fusion_state`; False (and a fresh start from the
        trusted values) when it does not fit this configuration."""
        if self.fusion is None:
            return state is None
        if state is not None:
            try:
                fs = FusionState.from_dict(state)
            except (KeyError, TypeError, ValueError):
                fs = None
            if fs is not None and fs.mean.shape == (self.fusion.n_state,) and \
                    fs.cov.shape == (self.fusion.n_state, self.fusion.n_state):
                self.fusion.state = fs
                return True
        self.fusion.reset(self.trusted[self.pmap.idx])
        return False

    def floor_state(self) -> dict[str, Any]:
        """The interval floor's state (JSON-serialisable), for persistence: a restart goes on
        with the scatter seen so far (its published intervals those of an uninterrupted run)."""
        return self.floor.state.as_dict(self.pmap.estimate)

    def set_floor_state(self, state: Mapping[str, Any] | None) -> bool:
        """Resume the interval's floor from :meth:`floor_state`; False (a fresh start: no
        pairs yet) when there is none or it cannot be read."""
        if not state:
            return False
        try:
            self.floor.state = FloorState.from_dict(state, self.pmap.estimate)
        except (TypeError, ValueError):
            return False
        return True

    def trusted_values(self) -> dict[str, float]:
        """Every parameter's trusted value [SI]."""
        return dict(zip(self.names, (float(v) for v in self.trusted), strict=True))

    def set_trusted(self, values: Mapping[str, float]) -> list[str]:
        """Resume from saved trusted values (ties re-applied; their standard errors are not
        saved: taken as exact, as a nameplate). Returns the names that are not the model's
        (ignored)."""
        unknown = []
        for name, value in values.items():
            if name in self.names:
                self.trusted[self.names.index(name)] = float(value)
            else:
                unknown.append(name)
        self.pmap.apply_ties(self.trusted)
        return unknown

    def window_fit(self, window: WindowData) -> WindowFit:
        """The window's fit problem, scored as the estimator scores it."""
        return WindowFit(self.model, window)

    # -- main entry -----------------------------------------------------------------------
    def problem(self, window: WindowData, terms: Mapping[str, FloatArray] | None = None,
                fit: WindowFit | None = None) -> WindowProblem:
        """The window's estimation problem, from the trusted values (the stages' input).

        Raises:
            ValueError: if a channel is missing or holds non-finite values.
        """
        check_window(self.model, window)
        # held at the fused value only while the twin fits without a term: a term's fit or a
        # failing check moves the fusion with the model's error
        held = self.trusted if terms or not self._fits else self._held_values()
        return WindowProblem(fit or self.window_fit(window), self.pmap, held,
                             self.lower, self.upper, terms,
                             initial=self.config.initial_state and bool(self.model.initial_states))

    def estimate(self, window: WindowData,
                 terms: Mapping[str, FloatArray] | None = None,
                 fit: WindowFit | None = None) -> WindowEstimate:
        """Estimate the parameters on one window (the module docstring's stages).

        Args:
            window: N samples of every channel in ``model.required_channels()``, finite.
            terms: the accepted meta-model terms (DT'', paper Eq. 3), attach point -> values
                (N,), held fixed while the physical parameters are estimated.
            fit: the window's :class:`WindowFit` if the caller has built it already.

        Returns:
            The window's estimate; :attr:`trusted` is updated if the window is sound and its
            estimate confirmed (:meth:`_trust`).

        Raises:
            ValueError: if a channel is missing or holds non-finite values.
        """
        t_start = time.perf_counter()
        cfg = self.config
        problem = self.problem(window, terms, fit)
        rates = self._fused_rates()  # before this window joins the fusion (the floor's drift)
        evals0 = problem.fit.evaluations
        initial0 = problem.fit.initial
        why = self._swarm_due()
        fitted = None
        if not why:
            # local first: the trusted values polished; rejected -> the swarm, same window
            fitted = self._fit(problem, window, warm_start(problem), terms, local=True)
            if fitted.rejected:
                why = f"rejected: {fitted.rejected}"
                logger.debug("window %d: local fit %s; the swarm runs", window.index, why)
                problem.fit.initial = initial0  # the swarm scores from the measured start
                fitted = None
        if fitted is None:
            found = global_search(problem, cfg.pso, rng=self._rng, time_budget=cfg.time_budget)
            fitted = self._fit(problem, window, found, terms, local=False)
            # the first guard comes `guard_phase` windows early (:meth:`stagger_guard`)
            self._since_swarm = self.guard_phase if self._since_swarm is None else 0
            r_sw = fitted.polished.point.r
            self._swarm_nrmse = float(np.sqrt(np.sum(r_sw * r_sw)))
        else:
            assert self._since_swarm is not None
            self._since_swarm += 1
        self._swarm_next = ""
        problem, found, polished = fitted.problem, fitted.found, fitted.polished
        decision = fitted.decision
        twin, check = fitted.twin, fitted.check
        # ... and a sensor that is frozen or saturated is named: the window is not sound
        run = cfg.validation.sensor_run if cfg.validation.enabled else 0
        faults = sensor_faults(problem.fit, twin.y, run, self._live, self._clips)
        self._clips.update({f.channel: f.value for f in faults if f.kind == "saturated"})
        nrmse = twin.residual.nrmse
        good = bool(np.isfinite(nrmse) and nrmse <= cfg.trust_rmse)
        trusted = good and (check is None or check.passed) and not faults
        # 5. fusion: a trusted window's evidence joins the filter; then what is published
        outliers = self.fusion.outliers if self.fusion is not None else 0
        fused, jump = self._fuse(problem, polished, decision, window, trusted,
                                 step_tol=0.0 if why else LOCAL_FUSION_STEP_TOL)
        if jump:
            self._swarm_next = "sudden change"
        suspect = self._suspect(check, faults, nrmse)
        outlier = None if suspect is not None else self._outlier(outliers)
        if outlier is not None:
            suspect, trusted = outlier, False
        out = publish(twin.theta, self.pmap, cfg.tie or {}, decision, fused,
                      cfg.fusion.max_rel_std, suspect=suspect,
                      held_std=self.trusted_std_values())
        t_mid = float(0.5 * (window.t[0] + window.t[-1]))
        long_run = self._long_run(decision, fitted.point, check, out)
        self._fits = trusted
        if trusted:
            self._trust(decision, out.values, t_mid)
        if jump or (self.fusion is not None and self.fusion.outliers > outliers):
            self.floor.restart_pairs()  # a change of the machine is no scatter of the twin
        floors = self._floor(decision, twin.theta, t_mid, trusted, rates, out, fused)
        if run and not faults:  # an output once seen live stays known to be live
            for name, live in live_outputs(problem.fit, run).items():
                self._live[name] = self._live.get(name, False) or live
        return WindowEstimate(
            values=out.values,
            estimated=out.estimated,
            held=out.held,
            rel_std=out.rel_std,
            rmse=twin.residual.rmse,
            nrmse=nrmse,
            simulated=twin.y,
            elapsed_s=time.perf_counter() - t_start,
            generations=found.generations,
            time_capped=found.time_capped,
            evaluations=problem.fit.evaluations - evals0,
            trusted=trusted,
            status=out.status,
            initial=twin.initial,
            model_check=check,
            fused=fused,
            fusion_jump=jump,
            sensors=faults,
            fitted={n: float(v) for n, v in zip(self.names, np.ravel(twin.theta), strict=True)},
            search="swarm" if why else "local",
            search_reason=why,
            floor=floors,
            long_run=long_run,
        )

    def _outlier(self, before: int) -> str | None:
        """Why the window is suspect when the fusion did not take it (its outlier count went up
        from ``before``: a move beyond JUMP_LIMIT at once), else None. Its estimates are not
        the machine's either."""
        fusion = self.fusion
        if fusion is None or fusion.outliers <= before or fusion.last_outlier is None:
            return None
        name, factor = fusion.last_outlier
        return (f"{name} would move by a factor {factor:.3g} in one window (beyond 2): "
                f"an outlier of the model, not fused")

    def _long_run(self, decision: GateDecision, point: FitPoint, check: ModelCheck | None,
                  out: Any) -> dict[str, float]:
        """The long-run factor (:func:`~twinwatch.twin.estimation.fit.long_run_factors`)
        of each parameter the window determined, applied to its published relative standard
        error (``out``, in place) where the model check passed (a failed one widened them
        already, :attr:`ModelCheck.widen`)."""
        if not decision.selected or (check is not None and not check.passed):
            return {}
        n_sel = len(decision.selected)
        if point.jac.shape[1] < n_sel:
            return {}
        factors = long_run_factors(point.jac, point.r, len(self.model.outputs),
                                   self.config.model_error, NUMERICAL_SHARE)
        estimate = self.pmap.estimate
        used = {}
        for i, k in enumerate(decision.selected):
            n = estimate[k]
            f = float(factors[i])
            used[n] = f
            if n in out.rel_std and out.status.get(n) in ("estimated", "suspect"):
                out.rel_std[n] *= f
        return used

    def _floor(self, decision: GateDecision, theta: FloatArray, t_mid: float, sound: bool,
               rates: Mapping[str, tuple[float, float]], out: Any,
               fused: Mapping[str, tuple[float, float]] | None = None) -> dict[str, float]:
        """The interval's floor (:mod:`~twinwatch.twin.estimation.floor`): a sound window's
        estimates join the between-window scatter, then each parameter the window determined
        has its published relative standard error ``sigma`` made ``sqrt(sigma^2 + floor^2)``
        (``out``, the :class:`~twinwatch.twin.estimation.publish.Published`, in place; a fused
        value keeps the fusion's). A parameter whose published error is then above
        ``max_rel_std`` is not published ``estimated`` (:meth:`_beyond_floor`).

        Returns:
            Parameter -> its floor (relative, 1 sigma), for the parameters the window
            determined.
        """
        estimate = self.pmap.estimate
        if sound:
            ln = np.log(np.ravel(theta)[self.pmap.idx])
            self.floor.observe(decision.selected, ln, decision.rel_std, t_mid,
                               {k: rates[n][0] for k, n in enumerate(estimate) if n in rates})
        floors = {}
        for k, f in self.floor.floors(decision.selected, decision.gain).items():
            n = estimate[k]
            floors[n] = f
            if out.status.get(n) not in ("estimated", "suspect") or n not in out.rel_std:
                continue
            if f > 0.0:
                out.rel_std[n] = math.hypot(out.rel_std[n], f)
            if out.status[n] == "estimated" and out.rel_std[n] > self.config.max_rel_std:
                self._beyond_floor(out, n, f, (fused or {}).get(n))
        return floors

    def _beyond_floor(self, out: Any, name: str, floor: float,
                      fused: tuple[float, float] | None) -> None:
        """Publish ``name`` (``out``, in place) as what it is when the twin's scatter makes
        its error exceed ``max_rel_std``: the fused value where that meets the fusion's gate,
        else held at its trusted value, with the reason."""
        why = (f"its published error, the twin's own added, is {out.rel_std[name] * 100:.2g} "
               f"% > max_rel_std {self.config.max_rel_std * 100:.2g} % (the windows' scatter "
               f"{floor * 100:.2g} %, 1 sigma, and the residual's correlation with its "
               "sensitivity): the twin does not determine it on this machine")
        if fused is not None and fused[1] <= self.config.fusion.max_rel_std:
            out.status[name] = "fused"
            out.values[name], out.rel_std[name] = fused
            out.held[name] = f"{why}; the fused value is published"
        else:
            out.status[name] = "held"
            out.values[name] = float(self.trusted[self.names.index(name)])
            out.rel_std.pop(name, None)
            out.held[name] = f"{why}: held at last trusted value"
        for dep, src in self.pmap.ties:
            out.values[self.names[dep]] = out.values[self.names[src]]

    def stagger_guard(self, name: str) -> int:
        """Bring the first guard swarm forward by a phase of 0 to ``swarm_every - 1`` windows
        from ``name`` (CRC-32, as the acquisition's stagger), so machines started together run
        their guards spread over ``swarm_every`` windows instead of in the same one.
        Returns the phase [windows]; 0 when the guard is off."""
        every = self.config.swarm_every
        self.guard_phase = zlib.crc32(name.encode()) % every if every else 0
        return self.guard_phase

    def _swarm_due(self) -> str:
        """Why this window runs the global search (empty: polish locally from the trusted
        values): ``strategy = "swarm"``, the first window, a sudden change or a roll-back
        before it, or ``swarm_every`` windows since the last swarm."""
        cfg = self.config
        if cfg.strategy == "swarm":
            return "every window"
        if self._since_swarm is None:
            return "start"
        if self._swarm_next:
            return self._swarm_next
        if cfg.swarm_every and self._since_swarm + 1 >= cfg.swarm_every:
            return "guard"
        return ""

    def _fit(self, problem: WindowProblem, window: WindowData, found: SearchResult,
             terms: Mapping[str, FloatArray] | None, *, local: bool) -> _Fitted:
        """Stages 2-4 from the search's best: polish, then :meth:`_gate_and_check`, retried
        once with :meth:`_unconfirmed` when the model check fails. ``local``: a local-first
        window, which stops as soon as it is rejected (:attr:`_Fitted.rejected` says why)."""
        cfg = self.config
        admitted = None
        if (POLISH_ADMITTED and local and cfg.polish and self._admitted is not None
                and not self._stale_held(self._admitted)):
            # only what the last window's gate admitted moves (POLISH_ADMITTED)
            polished = polish_admitted(problem, found.q, self._admitted,
                                       model_error=cfg.model_error)
            if not self._residual_too_large(problem, polished.point.r):
                admitted = self.gate.confirm(problem, polished, self._admitted,
                                             self.model.excitation(window),
                                             self.unobservable(window))
        if admitted is None:
            polished = polish(problem, found.q, enabled=cfg.polish,
                              model_error=cfg.model_error)
        if local:
            # a confirmed point passed this test above
            rejected = "" if admitted else self._residual_too_large(problem, polished.point.r)
            if rejected:
                return _Fitted(problem, found, polished, GateDecision([], {}, {}),
                               polished.point, problem.twin_at(polished.point.v), None,
                               rejected)
        # 3. identifiability gate, 4. model check (see _gate_and_check) ...
        decision, point, twin, check = self._gate_and_check(problem, polished, window,
                                                            admitted)
        if check is not None and not check.passed:
            if local:
                first = check.reasons[0] if check.reasons else "failed"
                return _Fitted(problem, found, polished, decision, point, twin, check,
                               f"the model check failed ({first})")
            # ... and once more holding the latest sound estimates (_unconfirmed)
            retry = self._unconfirmed()
            if retry is not None:
                saved = self.trusted.copy(), self.trusted_std.copy()
                self.trusted[:], self.trusted_std[:] = retry
                try:
                    other = self.problem(window, terms, problem.fit)
                    second = self._gate_and_check(other, polished, window)
                except BaseException:  # the window fails; the trusted values stay the machine's
                    self.trusted[:], self.trusted_std[:] = saved
                    raise
                # accepted only where the data contradict the nameplate plainly: the check
                # passes and the fit explains the window at least twice as well (a check
                # fails now and then by chance)
                if (second[3] is not None and second[3].passed
                        and second[2].residual.nrmse < RETRY_GAIN * twin.residual.nrmse):
                    problem = other
                    decision, point, twin, check = second
                    self._provisional.update(
                        n for i, n in enumerate(self.names) if self.trusted[i] != saved[0][i])
                else:
                    self.trusted[:], self.trusted_std[:] = saved
        return _Fitted(problem, found, polished, decision, point, twin, check)

    def _stale(self) -> list[int]:
        """The estimated parameters (positions) whose trusted value the fusion contradicts:
        never trusted from an estimate of their own, and the fused value determined (within
        the fusion's ``max_rel_std``) and beyond 2 fused standard errors from it."""
        f = self.fusion
        if f is None:
            return []
        mean, cov = f.state.mean, f.state.cov
        limit = self.config.fusion.max_rel_std
        out = []
        for k in range(len(self.pmap.idx)):
            if self.pmap.estimate[k] in self._anew:
                continue
            sd = math.sqrt(max(float(cov[k, k]), 0.0))
            trusted = float(self.trusted[self.pmap.idx[k]])
            if (sd <= limit and trusted > 0
                    and abs(math.log(trusted) - float(mean[k])) > 2.0 * sd):
                out.append(k)
        return out

    def _held_values(self) -> FloatArray:
        """The values a window holds the parameters it does not estimate at (full): the
        trusted values, except a :meth:`_stale` one, held at its fused value. A parameter the
        windows determine only now and then, each time too loosely to be trusted, keeps its
        nameplate as trusted value while the fusion follows it; held there, the other
        parameters would absorb the difference."""
        stale = self._stale()
        if not stale or self.fusion is None:
            return self.trusted
        base = self.trusted.copy()
        for k in stale:
            base[self.pmap.idx[k]] = math.exp(float(self.fusion.state.mean[k]))
        self.pmap.apply_ties(base)
        return base

    def _stale_held(self, admitted: list[int]) -> bool:
        """Whether a parameter the admitted-only polish would hold is :meth:`_stale`: such a
        window polishes every parameter (held at a stale value, the others absorb its error)."""
        return any(k not in admitted for k in self._stale())

    def _residual_too_large(self, problem: WindowProblem, r: FloatArray) -> str:
        """Why a local fit's normalised residuals ``r`` (M,) are beyond what the window's
        noise explains (empty: they are not): nRMSE above ``local_residual_ratio`` times the
        larger of the white-noise nRMSE (per output from first differences,
        :func:`~twinwatch.twin.estimation.statistics.noise_level`, floored by
        ``model_error``) and the last swarm window's nRMSE."""
        n_out = problem.n_out
        nrmse = float(np.sqrt((r * r).sum()))
        white = noise_level(r.reshape(-1, n_out)) * math.sqrt(r.size)
        explained = float(np.sqrt(mean(np.maximum(white, self.config.model_error) ** 2)))
        limit = self.config.local_residual_ratio * max(explained, self._swarm_nrmse)
        if np.isfinite(nrmse) and nrmse <= limit:
            return ""
        return f"nRMSE {nrmse:.3g} > {limit:.3g}"

    def _gate_and_check(self, problem: WindowProblem, polished: Polished,
                        window: WindowData,
                        admitted: tuple[GateDecision, FitPoint] | None = None
                        ) -> tuple[GateDecision, Any, Any, ModelCheck | None]:
        """Stages 3 and 4 on ``problem``: the identifiability gate (standard errors marginal
        over the held values' own uncertainty), the model check (a failing window's standard
        errors widened) and the gate again (:meth:`IdentifiabilityGate.enforce`).

        ``admitted``: the gate's decision and point already confirmed
        (:meth:`IdentifiabilityGate.confirm`), instead of :meth:`IdentifiabilityGate.admit`.

        Returns:
            The gate's decision, the re-fitted point, the twin at it and the model check
            (None when validation is off).
        """
        cfg = self.config
        if admitted is None:
            admitted = self.gate.admit(problem, polished, self.model.excitation(window),
                                       self.unobservable(window))
        decision, point = admitted
        self._admitted = list(decision.selected)
        decision = self.gate.propagate_held(problem, decision, point,
                                            self.trusted_std[self.pmap.idx])
        twin = problem.twin_at(point.v)
        # 4. model check: a failing window's standard errors are widened ...
        check = None
        if cfg.validation.enabled:
            check = model_check(problem, point, twin.y, self.model.exogenous, cfg.validation,
                                cfg.model_error)
            if not check.passed:
                decision = decision.widened(check.widen)
        before = set(decision.selected)
        decision, point, held_more = self.gate.enforce(problem, decision, point, check)
        if held_more:
            twin = problem.twin_at(point.v)
            # the re-fit holds them at their trusted values: their own uncertainty too
            gated = np.array([self.trusted_std[i] if k in before else 0.0
                              for k, i in enumerate(self.pmap.idx)])
            decision = self.gate.propagate_held(problem, decision, point, gated)
        return decision, point, twin, check

    def _unconfirmed(self) -> tuple[FloatArray, FloatArray] | None:
        """The trusted vector and its standard errors with every parameter that was never
        confirmed (still at its nameplate, or held at one unconfirmed estimate) set to its
        latest sound estimate (:meth:`_trust`'s candidates), or None when there is none.

        A window whose model check fails while it holds such a parameter at its nameplate
        is tried once more with these: otherwise a machine far off its nameplate can fail
        every check and have nothing ever confirmed. Only on a failed check: a window that
        fits holding the nameplate keeps it."""
        base, std = self.trusted.copy(), self.trusted_std.copy()
        changed = False
        for n, (value, sd, _t) in self._candidates.items():
            i = self.names.index(n)
            if (self.trusted_std[i] == 0.0 or n in self._provisional) and base[i] != value:
                base[i], std[i] = value, sd
                changed = True
        if not changed:
            return None
        self.pmap.apply_ties(base)
        self.pmap.apply_ties(std)
        return base, std

    def _keep_consistent(self) -> None:
        """Move each trusted value by what its estimate's sensitivity to the values it was
        fitted with held says, where those have been trusted anew since from their own
        estimates: ``ln p += g (ln q' - ln q)``. A trusted value is an estimate conditional on
        the others' trusted values then; two that trade off (D = Ke*ia/omega - c: d ln D /
        d ln Ke ~ 5) and were trusted at different times are otherwise inconsistent, and a
        window holding both biases what it estimates.

        A shift made here is not passed on: D and Ke, each fitted holding the other, would
        otherwise shift each other every window and walk."""
        for n, deps in self._depends.items():
            i = self.names.index(n)
            shift = 0.0
            for q, (g, then, seen) in deps.items():
                now, count = self._anew.get(q, (0.0, seen))
                if count != seen and then > 0 and now > 0:
                    shift += g * math.log(now / then)
                    deps[q] = (g, now, count)
            if shift:
                self.trusted[i] *= math.exp(shift)
        self.pmap.apply_ties(self.trusted)

    def _fused_rates(self) -> dict[str, tuple[float, float]]:
        """Estimated parameter -> the fused relative rate of change [1/s] and its standard
        error (none without fusion or with a random walk)."""
        if self.fusion is None or not self.fusion.trend:
            return {}
        f = self.fusion
        sd = np.sqrt(np.maximum(f.state.cov.diagonal()[f.n:], 0.0))
        return {n: (float(f.state.mean[f.n + i]), float(sd[i]))
                for i, n in enumerate(f.names)}

    def _suspect(self, check: ModelCheck | None, faults: list[SensorFault],
                 nrmse: float) -> str | None:
        """Why the window's estimates are not sound, or None: its sensor faults (named), else
        a fit that does not explain the window (nRMSE above ``trust_rmse``: a swarm stuck
        far from the machine), else its failed model check."""
        if faults:
            units = {o.name: o.unit for o in self.model.outputs}
            return "; ".join(f.describe(units.get(f.channel, "")) for f in faults)
        if not (np.isfinite(nrmse) and nrmse <= self.config.trust_rmse):
            return (f"the fit does not explain the window (nRMSE {nrmse:.3g} > trust_rmse "
                    f"{self.config.trust_rmse:g})")
        if check is not None and not check.passed:
            first = check.reasons[0] if check.reasons else "failed"
            return f"the model check failed ({first})"
        return None

    def unobservable(self, window: WindowData) -> dict[str, str]:
        """The estimated parameters this window's sample rate cannot observe, with the reason:
        those whose time constant (:meth:`TwinModel.time_constants`, at the trusted values) is
        below the window's sample period. The gate holds them at their trusted value (without
        holding the parameters after them) and the fusion never informs them: published
        ``held`` with that reason, never a number with an interval."""
        period = window.sample_period
        if not (period > 0):
            return {}
        key = (period, self.trusted.tobytes())
        if self._unobservable[0] != key:  # asked by each stage of a window: answered once
            out = {}
            for name, (tau, what) in self.model.time_constants(self.trusted_values()).items():
                if name in self.pmap.estimate and 0 < tau < period:
                    out[name] = (f"not observable at this sample rate ({what} = "
                                 f"{tau * 1e3:.3g} ms, below the {period * 1e3:.3g} ms "
                                 "sample period)")
            self._unobservable = (key, out)
        return dict(self._unobservable[1])

    def trusted_std_values(self) -> dict[str, float]:
        """Every parameter's trusted value's relative standard error (0: a nameplate or a
        resumed value)."""
        return dict(zip(self.names, (float(v) for v in self.trusted_std), strict=True))

    def _fuse(self, problem: WindowProblem, polished: Polished, decision: GateDecision,
              window: WindowData, informative: bool, step_tol: float = 0.0
              ) -> tuple[dict[str, tuple[float, float]], bool]:
        """Stage 5 (:func:`~twinwatch.twin.estimation.fusion.fuse_window`); nothing when
        fusion is off."""
        if self.fusion is None:
            return {}, False
        t_mid = float(0.5 * (window.t[0] + window.t[-1]))
        before = self.fusion.outliers
        skip = [k for k, n in enumerate(self.pmap.estimate) if n in self.unobservable(window)]
        out = fuse_window(self.fusion, problem, polished, decision.selected, t_mid,
                          informative, step_tol=step_tol, skip=skip)
        if self.fusion.outliers > before:
            name, factor = self.fusion.last_outlier or ("a parameter", float("nan"))
            logger.log(logging.INFO if before == 0 else logging.DEBUG,
                       "window %d: its evidence would move %s by a factor %.3g at once "
                       "(more than 2): an outlier of the model, not fused (%d so far)",
                       window.index, name, factor, self.fusion.outliers)
        return out

    def _trust(self, decision: GateDecision, values: Mapping[str, float], t: float) -> None:
        """Make the window's estimates the trusted values where their standard error is at
        most ``trust_rel_std`` and the previous such estimate of the parameter agrees with it
        (within :data:`CONFIRM` combined standard errors, after the change the fused rate
        explains over the time between them, at most :data:`CONFIRM_WITHIN_S` before; ties
        re-applied). A fused value is never trusted
        (:mod:`~twinwatch.twin.estimation.publish`).

        Why two: a trusted value is what every later window holds, and one window's estimate
        can be far off with a small standard error when the twin does not describe the drive
        exactly and the error is absorbed by the parameters rather than left in the residual.
        Such estimates do not repeat from window to window; a drift does.

        Args:
            decision: the gate's final decision.
            values: the published values.
            t: the window's middle [s].
        """
        estimate = self.pmap.estimate
        rates = self._fused_rates()
        for k in decision.selected:
            n = estimate[k]
            sd = decision.rel_std.get(k, math.inf)
            if not sd <= self.config.trust_rel_std:
                continue
            value = values[n]
            i = self.names.index(n)
            last = self._candidates.get(n)
            self._candidates[n] = (value, sd, t)
            if last is None:
                continue
            dt = t - last[2]
            change = math.log(value / last[0]) - rates.get(n, (0.0, 0.0))[0] * dt
            if dt > CONFIRM_WITHIN_S or abs(change) > CONFIRM * math.hypot(sd, last[1]):
                continue
            self._provisional.discard(n)
            self.trusted[i] = value
            self.trusted_std[i] = sd
            self._anew[n] = (value, self._anew.get(n, (0.0, 0))[1] + 1)
            self._depends[n] = {
                estimate[h]: (g, float(self.trusted[self.names.index(estimate[h])]),
                              self._anew.get(estimate[h], (0.0, 0))[1])
                for h, g in decision.gain.get(k, {}).items()}
        self._keep_consistent()
        self.pmap.apply_ties(self.trusted)
        self.pmap.apply_ties(self.trusted_std)

    def check(self, fit: WindowFit, y: FloatArray, explained: FloatArray | None = None,
              drift: FloatArray | None = None, *, explained_dof: FloatArray | None = None
              ) -> ModelCheck:
        """Validate the twin on a window from its simulated outputs ``y`` (N, n_out) with
        this estimator's settings (:func:`~twinwatch.twin.estimation.check.check_twin`, whose
        ``explained``, ``drift`` and ``explained_dof`` these are)."""
        return check_twin(fit, y, self.model.exogenous, self.config.validation,
                          self.config.model_error, explained, drift, explained_dof)

    def relative_std(self, jac: FloatArray, r: FloatArray) -> FloatArray:
        """Relative standard errors of ln-parameter columns of ``jac`` at residuals ``r``, as
        the estimator computes them (:func:`twinwatch.twin.estimation.fit.relative_std` with this
        configuration's ``model_error`` floor)."""
        return relative_std(jac, r, len(self.model.outputs), self.config.model_error)
