"""The health report: one message per window (paper Section 3.2: "the drift of the estimates
over time is the machine's health").

:class:`HealthMessage` owns the whole layout (every field typed, unknown fields refused), is
built in one place (:func:`build_health`) and serialised by one encoder
(:meth:`HealthMessage.to_json`): non-finite numbers become ``null`` everywhere. Every reader
of a published message reads it through one typed view derived from the model,
:func:`read_health` (:data:`HealthView`), never by the decoded JSON's keys.

The table of docs/health-message.md documents every field; a test holds it against this
model. Layout version :data:`SCHEMA_VERSION`; what each version added is listed on that page.
"""

from __future__ import annotations

import copy
import functools
import json
import math
import operator
import types
import typing
from collections.abc import Mapping
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    StrictFloat,
    StrictInt,
    ValidationError,
    create_model,
)

if TYPE_CHECKING:  # the builder's inputs: a reader of the message (the watcher) loads none
    from twinwatch.twin.adaptation import AdaptationResult
    from twinwatch.twin.estimation.estimator import WindowEstimate
    from twinwatch.twin.model import TwinModel, WindowData
    from twinwatch.twin.prognostics.window import WindowChoice

__all__ = [
    "SCHEMA_VERSION",
    "AcquisitionHealth",
    "AlarmStatus",
    "CrossingHealth",
    "DiagnosisHealth",
    "DiscoveryStatus",
    "FaultHealth",
    "FusedHealth",
    "ModelCheckHealth",
    "OutputCheckHealth",
    "HealthMessage",
    "ParameterHealth",
    "ResidualFit",
    "ResidualHealth",
    "RulAlarmStatus",
    "RulHealth",
    "SensorHealth",
    "SourceHealth",
    "TermHealth",
    "TrendHealth",
    "HealthView",
    "build_health",
    "check_function_line",
    "developing_line",
    "diagnosis_line",
    "read_health",
    "sent",
    "view_of",
    "summary_line",
    "trend_line",
]

SCHEMA_VERSION = 14

ParameterStatus = Literal["estimated", "fused", "suspect", "held", "tied", "fixed"]
"""The estimation's :data:`~twinwatch.twin.estimation.publish.ParameterStatus`, restated so
that this module (the message and its readers' view) imports no estimation: a reader such as
``twinwatch watch`` loads pydantic and this module only (tests/test_health_readers.py holds the
two equal)."""


def _finite(x: Any) -> Any:
    """JSON has no NaN/inf: a non-finite number is reported as null."""
    if isinstance(x, int | float) and not isinstance(x, bool) and not math.isfinite(x):
        return None
    return x


#: A number that is null when not finite.
Num = Annotated[float | None, BeforeValidator(_finite)]


class _Part(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True,
                              ser_json_inf_nan="null")


class FusedHealth(_Part):
    """``parameters.<name>.fused``: the evidence of every window so far on an estimated
    parameter (Kalman filter, :mod:`twinwatch.twin.estimation.fusion`)."""

    value: Num = Field(description="fused value [SI]")
    rel_std_pct: Num = Field(description="its 1-sigma relative standard error [%]")
    low: Num = Field(description="2-sigma interval, lower end [SI]")
    high: Num = Field(description="2-sigma interval, upper end [SI]")


class EvidenceHealth(_Part):
    """``parameters.<name>.trend.window_evidence``: what this window told the trend."""

    t: float = Field(description="the window's middle [s]")
    value: Num = Field(description="the parameter [SI]")
    std: Num = Field(description="its 1-sigma uncertainty [SI]")
    source: Literal["estimated", "fused"] = Field(
        description="estimated: this window's estimate; fused: the window's own share of the "
        "fused evidence")


class RestartHealth(_Part):
    """``parameters.<name>.trend.restart``: the last step that restarted the trend."""

    t: float = Field(description="the first window beyond the old trend [s]")
    step: Num = Field(description="size of the step [SI] (the new value minus the old "
                      "trend's prediction)")
    reason: str


class TrendHealth(_Part):
    """``parameters.<name>.trend``: where an estimated parameter is going
    (:mod:`twinwatch.twin.prognostics`)."""

    model: Literal["none", "linear", "exponential"] | None = Field(
        description="the degradation model the evidence follows (chosen by the BIC); null: "
        "too little evidence since the start or a restart")
    onset: Num = Field(description="the degradation's onset [s] (flat before); null: from "
                       "since_t")
    since_t: Num = Field(description="first evidence of the current trend [s] (after the "
                         "last restart)")
    evidence: int = Field(description="evidence windows the trend is fitted to")
    level: Num = Field(description="the trend's value at the window's end [SI]")
    level_std: Num = Field(description="its 1-sigma uncertainty [SI]")
    rate: Num = Field(description="drift rate now [SI/s]")
    rate_low: Num = Field(description="95 % interval of the drift rate, lower end [SI/s]")
    rate_high: Num = Field(description="95 % interval of the drift rate, upper end [SI/s]")
    rate_pct_per_h: Num = Field(description="drift rate in percent of nominal per hour")
    growth: Num = Field(description="the exponential's growth rate of the drift [1/s]")
    degrading: bool = Field(description="the drift rate is beyond its uncertainty (not flat)")
    model_weight: Num = Field(description="the chosen model's share of the model-averaging "
                              "weight (how sure the choice is)")
    monotonicity: Num = Field(description="MATLAB's monotonicity of the trend's history "
                              "(0..1)")
    trendability: Num = Field(description="|corr(history, time)| (0..1)")
    restarted: bool = Field(description="this window restarted the trend (a step: a repair, "
                            "a part replaced, a sudden fault)")
    restart: RestartHealth | None = Field(description="the last restart")
    restarts: int = Field(description="restarts so far")
    window_evidence: EvidenceHealth | None = Field(
        description="this window's evidence on the parameter (null: none)")


class CrossingHealth(_Part):
    """``parameters.<name>.rul.warning`` / ``.alarm``: when the trend crosses the threshold."""

    threshold: Num = Field(description="the threshold [SI] the trend heads to")
    status: Literal["crossed", "predicted", "not_reached"] = Field(
        description="crossed: the trend is beyond it; predicted: the median crossing is "
        "finite; not_reached: most draws never reach it")
    t: Num = Field(description="median crossing [s, plant time]")
    t_low: Num = Field(description="interval, earliest [s, plant time]")
    t_high: Num = Field(description="interval, latest [s, plant time] (null: some draws "
                        "never reach it)")
    rul_s: Num = Field(description="median time from the window's end [s]")
    low_s: Num = Field(description="interval, earliest [s from the window's end]")
    high_s: Num = Field(description="interval, latest [s from the window's end]")
    wall: Num = Field(description="median crossing on the wall clock [s since the epoch]")
    wall_low: Num = Field(description="interval, earliest [s since the epoch]")
    wall_high: Num = Field(description="interval, latest [s since the epoch]")
    probability: Num = Field(description="share of the draws that reach it")


class RulHealth(_Part):
    """``parameters.<name>.rul``: remaining useful life to the alarm rule's thresholds."""

    status: Literal["insufficient", "not_degrading", "degrading"]
    warning: CrossingHealth | None = Field(description="crossing of the warning threshold")
    alarm: CrossingHealth | None = Field(description="crossing of the alarm threshold")
    method: str = Field(description="how the distribution is computed (monte_carlo)")
    draws: int
    interval: float = Field(description="central probability of the intervals")


class ParameterHealth(_Part):
    """``parameters.<name>``: one model parameter in this window."""

    value: Num = Field(description="published value [SI]: the estimate, or the last trusted "
                       "value when held")
    unit: str = Field(description="SI unit")
    nominal: float = Field(description="nameplate value [SI] the deviation is measured from")
    deviation_pct: Num = Field(description="value vs nominal [%]")
    status: ParameterStatus = Field(
        description="estimated (determined by this sound window), fused (by the windows so "
        "far), suspect (a window that is not sound, or a held value the fused evidence "
        "contradicts: treat like held), held (the last trusted value), tied (equals another "
        "parameter), fixed (nameplate, not estimated)")
    fused: FusedHealth | None = Field(
        None, description="the fused evidence on an estimated parameter (null when fusion "
        "is off or the parameter is not estimated)")
    held: bool = Field(description="status is not 'estimated' (the v2 flag, kept for readers "
                       "of schema 2; true for a suspect value)")
    reason: str | None = Field(description="why this window does not estimate it, for a "
                               "person (null when estimated); never parse it: use status")
    rel_std_pct: Num = Field(description="1-sigma relative standard error of an estimate [%] "
                             "(null when not estimated)")
    trend: TrendHealth | None = Field(
        None, description="where it is going (null when not estimated, or prognostics off)")
    rul: RulHealth | None = Field(
        None, description="remaining useful life to its alarm rule's thresholds (null "
        "without a rule)")


class ResidualFit(_Part):
    """``residual.dt_prime`` / ``residual.dt_second``: the fit of one twin variant."""

    rmse: dict[str, Num] = Field(description="output -> RMSE [output unit]")
    max_abs: dict[str, Num] = Field(description="output -> worst absolute error [output unit]")
    nrmse: Num = Field(description="normalised RMSE")


class ResidualHealth(_Part):
    """``residual``: the twin without and with its meta-model terms."""

    dt_prime: ResidualFit = Field(description="the physical twin alone (DT')")
    dt_second: ResidualFit | None = Field(description="with the terms (DT''); null without "
                                          "terms")
    noise: dict[str, Num] = Field(description="output -> white-noise level estimated from the "
                                  "final residual [output unit]")


class TermHealth(_Part):
    """``terms[]``: one meta-model term of DT'' (as persisted by ``Term.as_dict``)."""

    kind: str = Field(description="meta-model kind (periodic, exponential, ...)")
    attach: str = Field(description="attach point, e.g. d(omega)/dt")
    mode: Literal["additive", "multiplicative"]
    input: str = Field(description="t or a channel")
    t_ref: float = Field(description="time origin of a time input [s]")
    params: dict[str, float] = Field(description="the term's parameters (switched-off offsets "
                                     "absent)")
    params_std: dict[str, Num] = Field(description="1-sigma standard error of each parameter "
                                       "(same units), from the evidence of every window the "
                                       "term has explained; null before its first polish")
    weight: Num = Field(description="the main coefficient")
    significance: Num = Field(description="weight / its standard error (this window)")
    evidence_windows: float = Field(description="effective number of windows the parameters "
                                    "combine (older ones forgotten, [discovery.refinement])")
    equation: str = Field(description="plain-text equation")
    meaning: str = Field(description="Table 1's working conditions where it attaches")
    since_window: int = Field(description="window it was found in")


class DiscoveryStatus(_Part):
    """``discovery``: the unknown-component search (DT'') in this window."""

    enabled: bool
    too_large: bool = Field(description="the residual is structured: the model lacks "
                            "something (whiteness test below window_alpha)")
    consecutive: int = Field(description="such windows in a row")
    p_value: Num = Field(None, description="probability of the residual's structure "
                                "in white noise (Ljung-Box, the most structured output)")
    evidence_p: Num = Field(None, description="the last trigger_windows windows' "
                                   "tests combined (Fisher): discovery runs below false_alarm")
    ran: bool = Field(description="a search ran in this window")
    elapsed_s: float = Field(description="search and re-validation time [s]")
    kept: list[str] = Field(description="equations added in this window")
    dropped: list[str] = Field(description="equations switched off in this window")
    simplified: list[str] = Field(description="equations a kept term was simplified to")
    changed: bool = Field(description="DT'' changed in this window")


class RulAlarmStatus(_Part):
    """``alarms.<name>.rul``: the alarm state on a parameter's remaining useful life."""

    level: Literal["normal", "warning", "alarm"]
    since_t: Num = Field(description="plant time the level was entered [s]")
    since_window: int | None = Field(description="window the level was entered")
    rul_s: Num = Field(description="last RUL evidence [s] (null: not degrading)")
    pending: Literal["normal", "warning", "alarm"] | None = Field(
        description="level a running evidence run would move to")
    pending_since_t: Num = Field(None, description="plant time that evidence run began [s] "
                                 "(restored at a restart: the raise is not delayed)")
    pending_windows: int | None = Field(None, description="its windows so far")


class AlarmStatus(_Part):
    """``alarms.<name>``: the alarm state of a parameter with a rule."""

    level: Literal["normal", "warning", "alarm"]
    since_t: Num = Field(description="plant time the level was entered [s]")
    since_window: int | None = Field(description="window the level was entered")
    deviation_pct: Num = Field(description="last evidence [%]")
    pending: Literal["normal", "warning", "alarm"] | None = Field(
        description="level a running evidence run would move to")
    pending_since_t: Num = Field(None, description="plant time that evidence run began [s] "
                                 "(restored at a restart: the raise is not delayed)")
    pending_windows: int | None = Field(None, description="its windows so far")
    rul: RulAlarmStatus | None = Field(
        None, description="the alarm state on the remaining useful life (rules with "
        "rul_warning / rul_alarm)")


class OutputCheckHealth(_Part):
    """``model_check.outputs.<output>``: one output's residual tests."""

    rms: Num = Field(description="residual RMS, relative to the output's scale")
    noise: Num = Field(description="its white-noise level, same unit")
    whiteness_p: Num = Field(description="Ljung-Box p-value (small: not white)")
    cross_p: Num = Field(description="residual-input test p-value (small: depends on the "
                         "input)")
    passed: bool


class ModelCheckHealth(_Part):
    """``model_check``: does the twin describe this window (Ljung, System Identification,
    ch. 16)?"""

    passed: bool = Field(description="every output's residual is white and independent of the "
                         "inputs (or below the model-error floor)")
    reasons: list[str] = Field(description="why not, one line per failing output")
    widen: Num = Field(description="factor the window's standard errors were multiplied by")
    outputs: dict[str, OutputCheckHealth]


class SensorHealth(_Part):
    """``sensors[]``: a measured output stuck at one value while the twin moves
    (:mod:`twinwatch.twin.estimation.quality`): a data-quality fact about that channel."""

    channel: str = Field(description="the output's channel")
    kind: Literal["frozen", "saturated"] = Field(
        description="frozen (stuck), or saturated (stuck at the window's extreme while the "
        "twin goes beyond it: the sensor clips)")
    value: Num = Field(description="the stuck reading [the channel's unit]")
    t_start: Num = Field(description="time of its first stuck sample [s]")
    duration_s: Num = Field(description="how long it stayed [s]")
    samples: int = Field(description="stuck samples in the window")


class SourceHealth(_Part):
    """``source``: how the window's samples came (:mod:`twinwatch.daemon.ringbuffer`) and what
    the source lacks right now."""

    jitter_rms_us: Num = Field(0.0, description="RMS of the time stamps' distance from the "
                               "nominal grid the samples were placed on [us] (0: on the grid)")
    jitter_max_us: Num = Field(0.0, description="largest distance of a stamp from its grid "
                               "slot [us]")
    waiting: str | None = Field(None, description="what the source is waiting for (a device "
                                "absent, a gateway being reopened), null when it delivers")
    silent: list[str] = Field(default_factory=list, description="bus messages (and the "
                              "channels they carry) not received for longer than the "
                              "driver's silence limit")
    device_faults: list[str] = Field(default_factory=list, description="what the device "
                                     "reports wrong with itself while it delivers: a drive "
                                     "in fault (its EMCY, the CiA 402 statusword's fault "
                                     "bit), an NMT state other than operational")


class AcquisitionHealth(_Part):
    """``acquisition``: the window this message is about."""

    window: int = Field(description="samples in the window")
    window_s: float = Field(description="its length [s]")
    adaptive: bool = Field(description="the adaptive window is on")
    reason: str | None = Field(description="why this length (adaptive window)")
    next_window: int | None = Field(description="samples of the next window the adaptive "
                                    "window asks for")
    next_reason: str | None = Field(description="why that length")


class FaultHealth(_Part):
    """``diagnosis.faults[]``: one fault mode of the library, ranked
    (:mod:`twinwatch.twin.diagnosis`)."""

    id: str = Field(description="the fault mode's id in the library")
    component: str = Field(description="the part it concerns")
    probability: float = Field(description="posterior probability the fault is present (0..1)")
    action: str = Field(description="the maintenance action")
    urgency: Literal["low", "medium", "high"]
    source: str = Field(description="the reference its signature comes from")
    evidence_for: list[str] = Field(description="the evidence that supports it, strongest "
                                    "first, as sentences with the numbers")
    evidence_against: list[str] = Field(description="the evidence against it (what it would "
                                        "show and the window does not)")
    changes: list[str] = Field(default_factory=list, description="what its twin changes: "
                               "parameters by name, readings as '<channel> reading', terms "
                               "by their attach point")


class DiagnosisHealth(_Part):
    """``diagnosis``: from the windows' data to the failing part (:mod:`twinwatch.twin.
    diagnosis`: each fault mode of the machine's library a change of the twin, fitted on the
    windows since its change point against this machine's healthy baseline)."""

    status: Literal["no_fault", "fault", "unknown", "check_function"] = Field(
        description="the most probable outcome: no fault, a fault of the library (top), a "
        "fault the library does not know, or check_function: the twin has not described the "
        "machine for [diagnosis] check_function_after_s (its model check failing), so its "
        "estimates are held and no outcome is claimed (NAMUR NE 107 'check function')")
    top: str | None = Field(description="the most probable fault's id (status fault), else "
                            "null")
    probability: float = Field(description="the outcome's probability (0..1)")
    no_fault: float = Field(description="probability that no fault is present")
    unknown: float = Field(description="probability of a fault the library does not know")
    unknown_terms: list[str] = Field(description="discovered terms no fault mode explains")
    faults: list[FaultHealth] = Field(description="the most probable fault modes, ranked")
    shaft_speed: Num = Field(description="the window's mean absolute shaft speed [rad/s] a "
                             "periodic term's frequency is compared with (null: none)")
    library: str = Field(description="the fault library (model, shipped or configured)")
    evidence: int = Field(description="evidence variables that told something (strength "
                          "away from 0.5)")
    alarms: list[str] = Field(default_factory=list, description="the faults whose probability "
                              "alarm is raised ([diagnosis] alarm, with hysteresis)")
    check_function_since: Num = Field(None, description="plant time [s] of the first failed "
                                      "model check of the run that put the diagnosis in "
                                      "check_function (null: the twin fits)")
    check_failed: str | None = Field(None, description="the model check's record over the "
                                     "last check_function_after_s, for a person (null: every "
                                     "window passed)")
    unexplained: list[str] = Field(default_factory=list, description="deviations and trends "
                                   "no fault mode of the library explains, as sentences (the "
                                   "unknown fault's evidence)")
    ruled_out: list[str] = Field(default_factory=list, description="fault modes with evidence "
                                 "for them that the diagnosis ruled out, and why")
    unobserved: list[str] = Field(default_factory=list, description="fault modes the "
                                  "diagnosis cannot see now, and why: every parameter their "
                                  "signature moves is without evidence from a recent window "
                                  "(held or not estimated), and nothing else shows them; "
                                  "their probability is their prior, not a finding")
    split: list[str] = Field(default_factory=list, description="fault modes whose twins fit "
                             "the windows alike (each at least 0.1, none at the alarm): the "
                             "data cannot tell them apart; the check on the machine that does "
                             "is in separate")
    separate: str | None = Field(None, description="the checks on the machine that tell the "
                                 "split modes apart (null: no split)")


class HealthMessage(_Part):
    """One window's health: the message on ``twinwatch/<machine>/health`` (its reference:
    docs/health-message.md). Build it with :func:`build_health`, once, from everything it
    carries; serialise it with :meth:`to_json`. Frozen: assigning a field raises a
    :class:`pydantic.ValidationError` (a message is never edited after it is built; a variant
    is :meth:`~pydantic.BaseModel.model_copy` with ``update``, a new message)."""

    schema_: int = Field(SCHEMA_VERSION, alias="schema", description="layout version")
    machine: str = Field(description="machine name from the config")
    model: str = Field(description="twin model (registry name)")
    run: str = Field(description="run id: one per start of the daemon, kept across a reload")
    window: int = Field(description="window index since start")
    t_start: float = Field(description="first sample time [s, source time]")
    t_end: float = Field(description="last sample time [s, source time]")
    samples: int = Field(description="samples in the window")
    parameters: dict[str, ParameterHealth]
    rmse: dict[str, Num] = Field(description="output -> RMSE [output unit]")
    nrmse: Num = Field(description="the normalised RMSE the estimation minimises")
    trusted: bool = Field(description="the window updated the trusted values")
    elapsed_s: float = Field(description="adaptation time [s]")
    generations: int = Field(description="PSO iterations")
    time_capped: bool = Field(description="the time budget stopped the PSO")
    evaluations: int = Field(description="twin simulations of one parameter vector")
    model_check: ModelCheckHealth | None = Field(
        None, description="the window's model validation (null when disabled)")
    sensors: list[SensorHealth] = Field(
        default_factory=list, description="frozen or saturated sensors in this window (its "
        "estimates are then suspect)")
    terms: list[TermHealth]
    residual: ResidualHealth
    discovery: DiscoveryStatus
    counters: dict[str, int]
    source: SourceHealth = Field(default_factory=SourceHealth)
    alarms: dict[str, AlarmStatus] = Field(default_factory=dict)
    acquisition: AcquisitionHealth | None = Field(None, description="the window's length "
                                                  "and why")
    diagnosis: DiagnosisHealth | None = Field(None, description="the ranked fault modes "
                                              "(null: [diagnosis] off or no library)")

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True,
                              protected_namespaces=(), ser_json_inf_nan="null")

    def as_dict(self) -> dict[str, Any]:
        """The message as plain JSON types, exactly as subscribers read it."""
        return self.model_dump(by_alias=True)

    def to_json(self) -> str:
        """The message as compact, strict JSON: what :func:`twinwatch.io.encoding.to_json`
        makes of :meth:`as_dict` (NaN and infinities ``null``, no spaces), written by
        pydantic's compiled serialiser (the same document, tested)."""
        return self.model_dump_json(by_alias=True)


def _nums(values: Mapping[str, float]) -> dict[str, float | None]:
    return dict(values)  # validated by Num: non-finite -> None


def build_health(
    *,
    machine: str,
    model_name: str,
    run: str,
    model: TwinModel,
    window: WindowData,
    adaptation: AdaptationResult,
    nominal: Mapping[str, float],
    counters: Mapping[str, int] | None = None,
    discovery_enabled: bool = False,
    source: SourceHealth | None = None,
    diagnosis: DiagnosisHealth | None = None,
    alarms: Mapping[str, AlarmStatus] | None = None,
) -> HealthMessage:
    """Build the health message of one window, from everything it carries.

    The message is built without the diagnosis and the alarms first (what the diagnoser and
    the alarm evaluator read), then completed by :func:`complete_health`.

    Args:
        machine: machine name (the Zenoh key segment).
        model_name: registry name of the twin model (``dc_motor``).
        run: the run id (:func:`twinwatch.daemon.runner.new_run_id`).
        model: the twin (for units).
        window: the estimated window (for its index and time span).
        adaptation: the window's adaptation: its estimate, meta-model terms, DT' and DT''
            residuals and discovery.
        nominal: parameter -> nominal (nameplate) value the deviation is measured from.
        counters: daemon and driver counters (windows, overruns, bad frames, ...).
        discovery_enabled: whether the machine's configuration enables discovery.
        source: the window's time stamps' jitter and what the source waits for or lacks
            (None: a source that reports neither, all zero).
        diagnosis: the ranked fault modes (None: ``[diagnosis]`` off, no library, or not
            derived yet).
        alarms: each alarm rule's state after this window (None: none yet).
    """
    est: WindowEstimate = adaptation.estimate
    params: dict[str, ParameterHealth] = {}
    for spec in model.parameters:
        value = est.values[spec.name]
        nom = float(nominal.get(spec.name, spec.nominal))
        status = est.status[spec.name]
        rel = est.rel_std.get(spec.name)
        fused = None
        if spec.name in est.fused:
            f_val, f_std = est.fused[spec.name]
            fused = FusedHealth(value=f_val, rel_std_pct=f_std * 100.0,
                                low=f_val * math.exp(-2.0 * f_std),
                                high=f_val * math.exp(2.0 * f_std))
        progn = adaptation.prognosis.get(spec.name)
        params[spec.name] = ParameterHealth(
            value=value,
            unit=spec.unit,
            nominal=nom,
            deviation_pct=(value / nom - 1.0) * 100.0 if nom else None,
            status=status,
            fused=fused,
            held=status != "estimated",
            reason=est.held.get(spec.name),
            rel_std_pct=rel * 100.0 if rel is not None else None,
            trend=(TrendHealth.model_validate(progn.trend, from_attributes=True)
                   if progn is not None else None),
            rul=(RulHealth.model_validate(progn.rul, from_attributes=True)
                 if progn is not None and progn.rul is not None else None),
        )
    disc = adaptation.discovery
    reval = adaptation.revalidation
    return HealthMessage(
        machine=machine,
        model=model_name,
        run=run,
        window=int(window.index),
        t_start=float(window.t[0]),
        t_end=float(window.t[-1]),
        samples=int(window.n),
        parameters=params,
        rmse=_nums(est.rmse),
        nrmse=est.nrmse,
        trusted=est.trusted,
        elapsed_s=est.elapsed_s,
        generations=est.generations,
        time_capped=est.time_capped,
        evaluations=est.evaluations,
        model_check=(ModelCheckHealth.model_validate(est.model_check, from_attributes=True)
                     if est.model_check is not None else None),
        sensors=[SensorHealth.model_validate(f, from_attributes=True) for f in est.sensors],
        terms=[TermHealth.model_validate(t.as_dict()) for t in adaptation.terms],
        residual=ResidualHealth(
            dt_prime=ResidualFit.model_validate(adaptation.dt_prime, from_attributes=True),
            dt_second=(ResidualFit.model_validate(adaptation.dt_second, from_attributes=True)
                       if adaptation.dt_second else None),
            noise=_nums(adaptation.noise),
        ),
        discovery=DiscoveryStatus(
            enabled=discovery_enabled,
            too_large=adaptation.too_large,
            consecutive=adaptation.consecutive,
            p_value=(adaptation.structure.p_value if adaptation.structure is not None
                     else None),
            evidence_p=adaptation.evidence_p,
            ran=bool(disc and disc.ran),
            elapsed_s=(disc.elapsed_s if disc else 0.0) + (reval.elapsed_s if reval else 0.0),
            kept=[t.equation() for t in disc.kept] if disc else [],
            dropped=[t.equation() for t in reval.dropped] if reval else [],
            simplified=[t.equation() for t in reval.kept] if reval else [],
            changed=adaptation.changed,
        ),
        counters=dict(counters or {}),
        source=source if source is not None else SourceHealth(),
        alarms=dict(alarms or {}),
        acquisition=_acquisition(window, adaptation.window_choice),
        diagnosis=diagnosis,
    )


def complete_health(reading: HealthMessage, *, diagnosis: DiagnosisHealth | None,
                    alarms: Mapping[str, AlarmStatus]) -> HealthMessage:
    """The window's message: ``reading`` (:func:`build_health`) with the diagnosis and the
    alarms derived from it.

    Args:
        reading: the window's message as :func:`build_health` made it without them.
        diagnosis: the ranked fault modes (None: ``[diagnosis]`` off, or it failed).
        alarms: each alarm rule's state after this window.

    Returns:
        A new message (``reading`` is left as it was). Its parts are ``reading``'s, not
        validated again.
    """
    fields = {name: getattr(reading, name) for name in HealthMessage.model_fields}
    return HealthMessage(**fields | {"diagnosis": diagnosis, "alarms": dict(alarms)})


def _acquisition(window: WindowData, choice: WindowChoice | None) -> AcquisitionHealth:
    n = int(window.n)
    span = float(window.t[-1] - window.t[0]) * n / (n - 1) if n > 1 else 0.0
    return AcquisitionHealth(window=n, window_s=span, adaptive=choice is not None,
                             reason=choice.used_reason if choice is not None else None,
                             next_window=choice.next if choice is not None else None,
                             next_reason=choice.reason if choice is not None else None)


def summary_line(health: HealthMessage) -> str:
    """One line for logs: the parameters the window could estimate (``=`` marks one held at
    its last trusted value, ``?`` a suspect one; tied and fixed ones are left out), the terms,
    the fit."""
    parts = []
    for name, p in health.parameters.items():
        if p.status in ("tied", "fixed"):
            continue
        mark = {"held": "=", "suspect": "?"}.get(p.status, "")
        dev = p.deviation_pct
        parts.append(f"{name}{mark}{p.value:.5g} ({dev:+.2f}%)" if dev is not None
                     and p.value is not None else f"{name}{mark}{p.value}")
    rm = f"{health.nrmse:.2e}" if health.nrmse is not None else "n/a"
    n = len(health.terms)
    extra = f" +{n} term{'s' if n > 1 else ''}" if n else ""
    return (f"window {health.window} [{health.t_start:.2f}-{health.t_end:.2f} s] "
            + " ".join(parts) + f"{extra} nRMSE {rm} in {health.elapsed_s * 1e3:.0f} ms"
            + _diagnosis_tag(health.diagnosis))


def _diagnosis_tag(d: DiagnosisHealth | None) -> str:
    if d is None or d.status == "no_fault":
        return ""
    if d.status == "unknown":
        return f"; unknown fault {d.probability:.2f}"
    if d.status == "check_function":
        return "; CHECK FUNCTION: the twin does not fit"
    return f"; {d.top} {d.probability:.2f}"


def check_function_line(d: DiagnosisHealth, label: str = "check function") -> str:
    """The check-function state for a person (NAMUR NE 107): since when the twin does not
    describe the machine, the model check's record, and what to check."""
    since = (f" since plant time {d.check_function_since:.0f} s"
             if d.check_function_since is not None else "")
    why = f" ({d.check_failed})" if d.check_failed else ""
    return (f"{label}: the twin does not describe this machine{since}{why}: its "
            f"estimates are held and no fault is named; check the sensors (wiring, scaling, "
            f"offsets) and the model's configuration")


def diagnosis_line(d: DiagnosisHealth | None) -> str | None:
    """One line for a person about the diagnosis (the run's summary), e.g. ``diagnosis:
    internal_leak (piston seal (internal leakage)) 0.97, urgency high: run an internal-leakage
    ...``; None without a diagnosis."""
    if d is None:
        return None
    if d.status == "no_fault":
        return f"diagnosis: no fault ({d.no_fault:.2f})"
    if d.status == "check_function":
        return f"diagnosis: {check_function_line(d)}"
    if d.status == "unknown":
        what = "; ".join(d.unknown_terms + d.unexplained) or "no term yet"
        return (f"diagnosis: a fault the library does not know ({d.unknown:.2f}): {what}")
    f = d.faults[0]
    if d.split:
        named = " or ".join(f"{x.id} {x.probability:.2f}" for x in d.faults if x.id in d.split)
        return (f"diagnosis: {named}: the data cannot tell them apart; to tell: "
                f"{d.separate or f.action}")
    return (f"diagnosis: {f.id} ({f.component}) {f.probability:.2f}, urgency {f.urgency}: "
            f"{f.action}")


def developing_line(d: DiagnosisHealth | None,
                    parameters: Mapping[str, ParameterHealth]) -> str | None:
    """When the diagnosis finds no fault yet but a parameter's trend heads to its warning,
    one line naming it, when it gets there and the faults whose evidence is that trend, e.g.
    ``developing: Ra -0.71 % vs nominal, degrading -15 %/h, its warning in 7.8 min
    (7.5-8.2 min); if it goes on: winding_short (armature winding)``: the diagnosis stays
    "no fault" while a deviation is inside the faults' signature size. None when the
    diagnosis names a fault or nothing is heading to a warning."""
    from twinwatch.twin.prognostics.rul import format_crossing

    if d is None or d.status != "no_fault":
        return None
    out = []
    for name, p in parameters.items():
        rul, t = p.rul, p.trend
        if rul is None or rul.status != "degrading" or t is None or not t.degrading:
            continue
        w = rul.warning
        if w is None or w.status != "predicted":
            continue
        # the faults whose twin changes this parameter
        causes = [f"{f.id} ({f.component})" for f in d.faults if name in f.changes]
        dev = f" {p.deviation_pct:+.2f} % vs nominal," if p.deviation_pct is not None else ""
        rate = (f" degrading {t.rate_pct_per_h:+.3g} %/h," if t.rate_pct_per_h is not None
                else " degrading,")
        out.append(f"{name}{dev}{rate} its warning in "
                   f"{format_crossing(w.rul_s, w.low_s, w.high_s)}"
                   + (f"; if it goes on: {', '.join(causes[:2])}" if causes else ""))
    return "developing: " + "; ".join(out) if out else None


def trend_line(name: str, p: ParameterHealth) -> str | None:
    """One line for a person about a parameter's trend and RUL (the run's summary), e.g.
    ``Ra  exponential from 160 s, -0.00264 ohm/s (-0.0027 .. -0.0026), -146 %/h; warning
    crossed, alarm in 6 min (4-9 min); monotonicity 0.98, trendability 0.97``; None without a
    trend."""
    from twinwatch.twin.prognostics.rul import format_crossing

    t = p.trend
    if t is None:
        return None
    unit = p.unit
    head = f"{name:<3} "
    if t.model is None:
        rs = (f"; restarted at {t.restart.t:.0f} s ({t.restart.reason})" if t.restart
              else "")
        plural = "" if t.evidence == 1 else "s"
        span = (f" over {t.window_evidence.t - t.since_t:.0f} s"
                if t.evidence > 1 and t.window_evidence is not None and t.since_t is not None
                else "")
        return head + f"no trend yet ({t.evidence} evidence window{plural}{span}{rs})"
    model = t.model if t.onset is None else f"{t.model} from {t.onset:.0f} s"
    if t.degrading and t.rate is not None:
        pct = f", {t.rate_pct_per_h:+.3g} %/h" if t.rate_pct_per_h is not None else ""
        body = (f"{model}: {t.rate:+.3g} {unit}/s ({t.rate_low:+.3g} .. {t.rate_high:+.3g})"
                f"{pct}")
    else:
        body = f"not degrading ({model}, {t.evidence} windows: flat within its uncertainty)"
    rul = p.rul
    if rul is not None and rul.status == "degrading":
        parts = []
        for level, c in (("warning", rul.warning), ("alarm", rul.alarm)):
            if c is None:
                continue
            if c.status == "crossed":
                parts.append(f"{level} threshold crossed")
            else:
                parts.append(f"{level} ({c.threshold:.6g} {unit}) in "
                             + format_crossing(c.rul_s, c.low_s, c.high_s))
        if parts:
            body += "; " + ", ".join(parts)
    scores = []
    if t.monotonicity is not None:
        scores.append(f"monotonicity {t.monotonicity:.2f}")
    if t.trendability is not None:
        scores.append(f"trendability {t.trendability:.2f}")
    if t.restarts and t.restart is not None:
        scores.append(f"restarted at {t.restart.t:.0f} s (step {t.restart.step:+.4g} {unit})")
    return head + body + ("; " + ", ".join(scores) if scores else "")


# -- the readers' view ---------------------------------------------------------------------------
# Every reader of a published or stored message reads it through one typed view derived from
# the model above, never by indexing the decoded JSON with strings. The view is lenient where
# the model is strict, because a reader meets messages the model would refuse: an older
# schema's (the state database keeps them), a newer one's, a partial one in a test.
# So in a view every field is None when the message does not carry it (absent or null: also a
# field the model defaults, e.g. ``schema``), a part of the wrong shape reads as absent, unknown
# fields are kept (not read), a status is any string, and numbers stay as they were sent.

_VIEW_CONFIG = ConfigDict(extra="allow", frozen=True, populate_by_name=True,
                          protected_namespaces=())
_views: dict[type[BaseModel], type[BaseModel]] = {}


def _lenient(tp: Any) -> Any:
    """The view's annotation for the model's ``tp``."""
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        return view_of(tp)
    if tp is float or tp is int:  # as sent: an int stays an int, a bool or a text is no number
        return StrictInt | StrictFloat
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin is Annotated:
        return Annotated[(_lenient(args[0]), *tp.__metadata__)]
    if origin is Literal:
        return str
    if origin in (typing.Union, types.UnionType):
        return functools.reduce(operator.or_, [_lenient(a) for a in args])
    if origin is dict:
        # a type built at run time (the lenient view's): no static type to check
        return dict[_lenient(args[0]), _lenient(args[1])]  # type: ignore[misc]
    if origin is list:
        return list[_lenient(args[0])]  # type: ignore[misc]  # built at run time, as above
    return tp


def view_of(model: type[BaseModel]) -> type[BaseModel]:
    """The readers' view of a part of the message (:class:`HealthView` for
    :class:`HealthMessage`, ``ParameterView`` for :class:`ParameterHealth`, ...): the same
    fields, each None when not sent, unknown fields kept, statuses as strings."""
    if model in _views:
        return _views[model]
    fields: dict[str, Any] = {}
    for name, f in model.model_fields.items():
        ann = _lenient(f.annotation) | None
        if f.metadata:  # a Num's validator (non-finite -> None)
            ann = Annotated[(ann, *f.metadata)]
        fields[name] = (ann, Field(None, alias=f.alias))
    base = model.__name__.removesuffix("Health").removesuffix("Message") or "Health"
    view = create_model(f"{base}View", __config__=_VIEW_CONFIG, __doc__=(
        f"The readers' view of :class:`{model.__name__}` (:func:`view_of`)."), **fields)
    _views[model] = view
    return view


if TYPE_CHECKING:
    # A static checker reads a view as its model (the same attribute names: a misspelt field
    # is caught); at run time each attribute may also be None (an older daemon).
    HealthView = HealthMessage
    ParameterView = ParameterHealth
    RulView = RulHealth
    AlarmView = AlarmStatus
    DiagnosisView = DiagnosisHealth
else:
    HealthView = view_of(HealthMessage)
    ParameterView = view_of(ParameterHealth)
    RulView = view_of(RulHealth)
    AlarmView = view_of(AlarmStatus)
    DiagnosisView = view_of(DiagnosisHealth)


def sent(part: BaseModel, field: str) -> bool:
    """Whether the message carried ``field`` in ``part`` (null or not), e.g. whether a
    parameter has a ``rul`` entry at all (schema 7 on) as opposed to one that is null.

    Raises:
        AttributeError: ``field`` is not a field of ``part``'s model (a misspelt name).
    """
    if field not in type(part).model_fields:
        raise AttributeError(f"{type(part).__name__} has no field {field!r}")
    return field in part.model_fields_set


def read_health(doc: str | bytes | Mapping[str, Any] | HealthMessage) -> HealthView:
    """The readers' typed view of one health message, parsed once.

    A part of the wrong shape (a number where an object belongs, an entry of a list or a map
    that is not one) reads as absent, as if the message did not carry it: what a reader
    shows of the rest is unchanged.

    Args:
        doc: the message as published (JSON text or bytes), decoded (a mapping), or the
            daemon's own :class:`HealthMessage`.

    Returns:
        The :data:`HealthView`: attribute access, every field optional (see :func:`view_of`).

    Raises:
        ValueError: not JSON, or not a JSON object.
    """
    if isinstance(doc, HealthMessage):
        doc = doc.as_dict()
    try:
        if isinstance(doc, str | bytes):
            return HealthView.model_validate_json(doc)
        return HealthView.model_validate(doc)
    except ValidationError as exc:
        if isinstance(doc, str | bytes):
            data = json.loads(doc)  # ValueError when not JSON
        else:
            data = copy.deepcopy(doc)
        if not isinstance(data, dict):
            raise ValueError("a health message is a JSON object") from exc
        errors = exc.errors()
    for _ in range(1000):
        if not _prune(data, errors):
            break
        try:
            return HealthView.model_validate(data)
        except ValidationError as exc:
            errors = exc.errors()
    raise ValueError("not a health message")


_DROPPED = object()


def _prune(data: dict[str, Any], errors: list[Any]) -> bool:
    """Remove from ``data`` the parts ``errors`` (a ValidationError's) point at: a key of an
    object, an entry of a list. False when there is nothing to remove."""
    paths: set[tuple[Any, ...]] = set()
    for e in errors:
        node: Any = data
        path: list[Any] = []
        for key in e["loc"]:
            if isinstance(node, dict) and key in node:
                node = node[key]
            elif isinstance(node, list) and isinstance(key, int) and 0 <= key < len(node):
                node = node[key]
            else:
                break
            path.append(key)
        if path:
            paths.add(tuple(path))
    if not paths:
        return False
    lists: list[list[Any]] = []
    for loc in paths:
        if any(loc[:i] in paths for i in range(1, len(loc))):
            continue  # its container goes
        parent: Any = data
        for key in loc[:-1]:
            parent = parent[key]
        if isinstance(parent, list):
            parent[loc[-1]] = _DROPPED  # indices stay until every error is placed
            lists.append(parent)
        else:
            del parent[loc[-1]]
    for entries in lists:
        entries[:] = [x for x in entries if x is not _DROPPED]
    return True
