"""The prognostics' tables: ``[prognostics]`` (trend and remaining useful life) and
``[acquisition.adaptive]`` (the adaptive window), and the thresholds a RUL is computed to."""

from __future__ import annotations

from dataclasses import dataclass

from pydantic import BaseModel, ConfigDict, Field, StrictFloat, StrictInt, model_validator

__all__ = ["AdaptiveWindowConfig", "PrognosticsConfig", "Thresholds"]


class PrognosticsConfig(BaseModel):
    """``[prognostics]``: each estimated parameter's trend and remaining useful life
    (:mod:`twinwatch.twin.prognostics`)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    enabled: bool = Field(True, description="fit a trend to every estimated parameter and "
                          "predict when it crosses its alarm rule's thresholds")
    horizon: StrictFloat = Field(
        3600.0, gt=0, description="s of evidence a trend is fitted to (the "
        "latest; a restart begins a new one)")
    min_evidence: StrictInt = Field(10, ge=4, le=10_000, description="evidence windows since the "
                                    "start or a restart before a trend is fitted")
    min_span: StrictFloat = Field(
        60.0, ge=0, allow_inf_nan=False, description="s of plant time the evidence since the "
        "start or a restart must span before a trend (its rate, degrading or not, and the RUL) "
        "is fitted: a minute of noisy windows extrapolated to an hour is not a trend (a 60 s "
        "replay of a real drive read D -4.03e+03 %/h)")
    max_points: StrictInt = Field(120, ge=20, le=10_000, description="evidence is binned to at "
                                  "most this many points for the fit (cost; a slow trend loses "
                                  "nothing)")
    onset: bool = Field(True, description="the degrading models may start at an onset (flat "
                        "before it)")

    interval: StrictFloat = Field(0.95, gt=0.5, lt=1.0, description="central probability of the "
                                  "published RUL interval")
    draws: StrictInt = Field(2000, ge=100, le=100_000, description="Monte Carlo draws of the RUL")
    step_threshold: StrictFloat = Field(5.0, gt=1.0, description="a window this many standard "
                                        "errors off the trend may be a step (a repair, a part "
                                        "replaced)")
    step_confirm: StrictInt = Field(2, ge=1, le=20, description="consecutive such windows on one "
                                    "side before the trend restarts (one, when the fusion saw the "
                                    "jump too)")
    flat_z: StrictFloat = Field(2.0, gt=0, description="a drift rate within this many standard "
                                "errors of zero is flat: not degrading")
    detection: StrictFloat = Field(0.9, gt=0.5, lt=1.0, description="degrading only when the "
                                   "evidence favours a degrading model over none with at least "
                                   "this probability (BIC weights)")
    max_rel_std: StrictFloat = Field(0.5, gt=0, description="evidence with a larger relative "
                                     "standard error is not worth a point")
    seed: StrictInt = Field(0, description="seed of the Monte Carlo draws (the same evidence gives "
                            "the same RUL)")


class AdaptiveWindowConfig(BaseModel):
    """``[acquisition.adaptive]``: the window follows the change (paper Sections 5.2.2 and 6:
    a fixed window averages a parameter that changes quickly).

    Off by default. When on, the window's length aims at a drift within it of ``drift_ratio``
    standard errors: it shortens (by at most ``shrink``) when a parameter's drift within a
    window exceeds that or the residual grows with the window (its normalised RMSE above
    ``residual_ratio`` times its white-noise level), and lengthens back (by at most ``grow``)
    after ``quiet_windows`` quiet windows in a row, within ``[min_window, max_window]``
    samples (:class:`~twinwatch.twin.prognostics.window.WindowController`).
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    enabled: bool = Field(False, description="let the window follow the change")
    min_window: StrictInt = Field(100, ge=10, description="shortest window [samples]")
    max_window: StrictInt = Field(800, ge=10, description="longest window [samples]")
    drift_ratio: StrictFloat = Field(1.4, gt=0, description="the drift within a window, in its "
                                     "standard errors, the window's length aims at (1.4 = sqrt(2): "
                                     "the error of the value now, noise and the lag of half the "
                                     "drift, is smallest there)")
    residual_ratio: StrictFloat = Field(3.0, gt=1, description="shorten when the window's residual "
                                        "exceeds this many times its white-noise level")
    quiet_windows: StrictInt = Field(
        3, ge=1, description="quiet windows in a row before the window "
        "lengthens")
    shrink: StrictFloat = Field(0.5, gt=0, lt=1, description="factor a window shortens by")
    grow: StrictFloat = Field(1.5, gt=1, description="factor a window lengthens by")

    @model_validator(mode="after")
    def _bounds(self) -> AdaptiveWindowConfig:
        if self.max_window < self.min_window:
            raise ValueError(f"max_window ({self.max_window}) must be at least min_window "
                             f"({self.min_window})")
        return self


@dataclass(frozen=True)
class Thresholds:
    """A parameter's alarm thresholds [SI] (from its ``[alarms.parameters.<name>]`` rule):
    crossed upwards (``*_high``) or downwards (``*_low``); None where the rule has none."""

    warning_high: float | None = None
    warning_low: float | None = None
    alarm_high: float | None = None
    alarm_low: float | None = None

    def level(self, level: str) -> tuple[float | None, float | None]:
        """(high, low) of ``warning`` or ``alarm``."""
        return getattr(self, f"{level}_high"), getattr(self, f"{level}_low")
