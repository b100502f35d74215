"""The health report: one message per window (paper Section 3.2: "the drift of the estimates
over time is the machine's health").

:class:`HealthMessage` owns the whole layout (every field typed, unknown fields refused), is
built in one place (:func:`build_health`, from the public results of the window's estimation
and adaptation) and serialised by one encoder (:meth:`HealthMessage.to_json`,
:func:`twinwatch.io.encoding.to_json`) for Zenoh, the state store and the Rerun recording:
non-finite numbers become ``null`` everywhere.

The README's table "The health message" documents every field; a test holds it against this
model. Layout version :data:`SCHEMA_VERSION`:

* 7: the window's ``source``: the jitter of its time stamps against the nominal grid the
  samples were placed on (RMS and maximum [us]), what the source waits for (a device absent,
  a gateway being reopened) and the bus messages that went silent; the counters of windows
  abandoned by cause (``windows_abandoned_gap``, ``_time_back``, ``_jitter``, ``_bad_value``,
  ``_missing_channel``).
* 6: every message carries its ``run`` id (one per start of the daemon, kept across a reload;
  a new run of a simulated plant or of a replayed recording is a new run): windows of different
  runs share window numbers and plant times, the run tells them apart (the history query
  filters by it).
* 5: each meta-model term carries the standard errors of its parameters (``params_std``) and
  the number of windows whose evidence they combine (``evidence_windows``): a kept term is
  refined across windows (:mod:`twinwatch.twin.discovery.terms`).
* 4: ``status`` may be ``fused`` (not determined by this window alone but by the evidence
  of the windows so far, :mod:`~twinwatch.twin.estimation.fusion`); each estimated parameter
  carries its fused value, interval and rate (``fused``); the window's model validation
  (``model_check``: residual whiteness and residual-input tests per output; a window that fails
  it is not trusted and its intervals are widened).
* 3: each parameter's ``status`` (``estimated`` / ``held`` / ``tied`` / ``fixed``) next to the
  human ``reason``; non-finite numbers are ``null`` in every copy (the state store kept a bare
  ``NaN`` token before); ``discovery.simplified`` documented.
* 2: adds ``terms``, ``residual``, ``discovery``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field

from twinwatch.io.encoding import to_json
from twinwatch.twin.estimation.estimator import ParameterStatus, WindowEstimate
from twinwatch.twin.model import TwinModel, WindowData

if TYPE_CHECKING:
    from twinwatch.twin.adaptation import AdaptationResult
    from twinwatch.twin.estimation.fit import Residual

__all__ = [
    "SCHEMA_VERSION",
    "AlarmStatus",
    "DiscoveryStatus",
    "FusedHealth",
    "ModelCheckHealth",
    "OutputCheckHealth",
    "HealthMessage",
    "ParameterHealth",
    "ResidualFit",
    "ResidualHealth",
    "SourceHealth",
    "TermHealth",
    "build_health",
    "summary_line",
]

SCHEMA_VERSION = 7


def _finite(x: Any) -> Any:
    """JSON has no NaN/inf: a non-finite number is reported as null."""
    if isinstance(x, int | float) and not isinstance(x, bool) and not math.isfinite(x):
        return None
    return x


#: A number that is null when not finite.
Num = Annotated[float | None, BeforeValidator(_finite)]


class _Part(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class FusedHealth(_Part):
    """``parameters.<name>.fused``: the evidence of every window so far on an estimated
    parameter (Kalman filter, :mod:`twinwatch.twin.estimation.fusion`)."""

    value: Num = Field(description="fused value [SI]")
    rel_std_pct: Num = Field(description="its 1-sigma relative standard error [%]")
    low: Num = Field(description="2-sigma interval, lower end [SI]")
    high: Num = Field(description="2-sigma interval, upper end [SI]")


class ParameterHealth(_Part):
    """``parameters.<name>``: one model parameter in this window."""

    value: Num = Field(description="published value [SI]: the estimate, or the last trusted "
                       "value when held")
    unit: str = Field(description="SI unit")
    nominal: float = Field(description="nameplate value [SI] the deviation is measured from")
    deviation_pct: Num = Field(description="value vs nominal [%]")
    status: ParameterStatus = Field(
        description="estimated (determined by this window), fused (by the windows so far), "
        "held (neither: the last trusted value), tied (equals another parameter), fixed "
        "(nameplate, not estimated)")
    fused: FusedHealth | None = Field(
        None, description="the fused evidence on an estimated parameter (null when fusion "
        "is off or the parameter is not estimated)")
    held: bool = Field(description="status is not 'estimated' (the v2 flag, kept for readers "
                       "of schema 2)")
    reason: str | None = Field(description="why this window does not estimate it, for a "
                               "person (null when estimated); never parse it: use status")
    rel_std_pct: Num = Field(description="1-sigma relative standard error of an estimate [%] "
                             "(null when not estimated)")


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
    too_large: bool = Field(description="the residual is above the exit criterion")
    consecutive: int = Field(description="such windows in a row")
    ran: bool = Field(description="a search ran in this window")
    elapsed_s: float = Field(description="search and re-validation time [s]")
    kept: list[str] = Field(description="equations added in this window")
    dropped: list[str] = Field(description="equations switched off in this window")
    simplified: list[str] = Field(description="equations a kept term was simplified to")
    changed: bool = Field(description="DT'' changed in this window")


class AlarmStatus(_Part):
    """``alarms.<name>``: the alarm state of a parameter with a rule."""

    level: Literal["normal", "warning", "alarm"]
    since_t: Num = Field(description="plant time the level was entered [s]")
    since_window: int | None = Field(description="window the level was entered")
    deviation_pct: Num = Field(description="last evidence [%]")
    pending: Literal["normal", "warning", "alarm"] | None = Field(
        description="level a running evidence run would move to")


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


class HealthMessage(_Part):
    """One window's health: the message on ``twinwatch/<machine>/health`` (README: "The health
    message"). Build it with :func:`build_health`; serialise it with :meth:`to_json`."""

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
    terms: list[TermHealth]
    residual: ResidualHealth
    discovery: DiscoveryStatus
    counters: dict[str, int]
    source: SourceHealth = Field(default_factory=SourceHealth)
    alarms: dict[str, AlarmStatus] = Field(default_factory=dict)

    model_config = ConfigDict(extra="forbid", validate_assignment=True, populate_by_name=True,
                              protected_namespaces=())

    def as_dict(self) -> dict[str, Any]:
        """The message as plain JSON types, exactly as subscribers read it."""
        return self.model_dump(by_alias=True)

    def to_json(self) -> str:
        """The message as compact, strict JSON (the one encoder, :mod:`twinwatch.io.encoding`)."""
        return to_json(self.as_dict())


def _nums(values: Mapping[str, float]) -> dict[str, float | None]:
    return dict(values)  # validated by Num: non-finite -> None


def _residual(r: Residual) -> ResidualFit:
    return ResidualFit(rmse=_nums(r.rmse), max_abs=_nums(r.max_abs), nrmse=r.nrmse)


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
) -> HealthMessage:
    """Build the health message of one window (its ``alarms`` are added by the daemon's alarm
    evaluator, which reads the rest).

    Args:
        machine: machine name (the Zenoh key segment).
        model_name: registry name of the twin model (``dc_motor``).
        run: the run id (:func:`twinwatch.daemon.runner.new_run_id`: one per start of the
            daemon, kept across a reload).
        model: the twin (for units).
        window: the estimated window (for its index and time span).
        adaptation: the window's adaptation: its estimate, meta-model terms, DT' and DT''
            residuals and discovery.
        nominal: parameter -> nominal (nameplate) value the deviation is measured from.
        counters: daemon and driver counters (windows, overruns, bad frames, ...).
        discovery_enabled: whether the machine's configuration enables discovery.
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
        model_check=(ModelCheckHealth.model_validate(est.model_check.as_dict())
                     if est.model_check is not None else None),
        terms=[TermHealth.model_validate(t.as_dict()) for t in adaptation.terms],
        residual=ResidualHealth(
            dt_prime=_residual(adaptation.dt_prime),
            dt_second=_residual(adaptation.dt_second) if adaptation.dt_second else None,
            noise=_nums(adaptation.noise),
        ),
        discovery=DiscoveryStatus(
            enabled=discovery_enabled,
            too_large=adaptation.too_large,
            consecutive=adaptation.consecutive,
            ran=bool(disc and disc.ran),
            elapsed_s=(disc.elapsed_s if disc else 0.0) + (reval.elapsed_s if reval else 0.0),
            kept=[t.equation() for t in disc.kept] if disc else [],
            dropped=[t.equation() for t in reval.dropped] if reval else [],
            simplified=[t.equation() for t in reval.kept] if reval else [],
            changed=adaptation.changed,
        ),
        counters=dict(counters or {}),
    )


def summary_line(health: HealthMessage) -> str:
    """One line for logs: the parameters the window could estimate (``=`` marks one held at
    its last trusted value; tied and fixed ones are left out), the terms, the fit."""
    parts = []
    for name, p in health.parameters.items():
        if p.status in ("tied", "fixed"):
            continue
        mark = "=" if p.status == "held" else ""
        dev = p.deviation_pct
        parts.append(f"{name}{mark}{p.value:.5g} ({dev:+.2f}%)" if dev is not None
                     and p.value is not None else f"{name}{mark}{p.value}")
    rm = f"{health.nrmse:.2e}" if health.nrmse is not None else "n/a"
    n = len(health.terms)
    extra = f" +{n} term{'s' if n > 1 else ''}" if n else ""
    return (f"window {health.window} [{health.t_start:.2f}-{health.t_end:.2f} s] "
            + " ".join(parts) + f"{extra} nRMSE {rm} in {health.elapsed_s * 1e3:.0f} ms")
