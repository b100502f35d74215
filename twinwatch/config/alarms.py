"""``[alarms]``: the rules an operator sets on parameter drift and on the remaining useful life
to the rule's alarm threshold (its warning one without it), evaluated by
:class:`twinwatch.daemon.alarms.AlarmEvaluator` (its module docstring says how).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING, Literal

from pydantic import Field, StrictFloat, StrictInt, model_validator

from twinwatch._table import StrictTable

if TYPE_CHECKING:
    from twinwatch.twin.prognostics.config import Thresholds

__all__ = ["LEVELS", "AlarmConfig", "AlarmRule", "Level"]

Level = Literal["normal", "warning", "alarm"]
LEVELS: tuple[Level, ...] = ("normal", "warning", "alarm")


class AlarmRule(StrictTable):
    """``[alarms.parameters.<name>]``: thresholds on one parameter's deviation from nominal.

    All thresholds and the hysteresis are in percent of the nominal value (``deviation_pct`` of
    the health message). Give ``warning``/``alarm`` (symmetric on the magnitude) or the
    one-sided ``*_high`` (> 0) / ``*_low`` (< 0) keys, not both for the same level.
    """

    warning: StrictFloat | None = Field(
        None, gt=0, description="warning when |deviation| >= this [%]")
    alarm: StrictFloat | None = Field(None, gt=0, description="alarm when |deviation| >= this [%]")
    warning_high: StrictFloat | None = Field(
        None, gt=0, description="warning when deviation >= this")
    alarm_high: StrictFloat | None = Field(
        None, gt=0, description="alarm when deviation >= this [%]")
    warning_low: StrictFloat | None = Field(
        None, lt=0, description="warning when deviation <= this")
    alarm_low: StrictFloat | None = Field(
        None, lt=0, description="alarm when deviation <= this [%]")
    hysteresis: StrictFloat = Field(1.0, ge=0, description="percentage points inside a threshold "
                                    "before its level may clear")
    raise_after_s: StrictFloat = Field(10.0, ge=0, description="plant seconds beyond a threshold "
                                       "before the level is raised")
    raise_after_windows: StrictInt = Field(
        3, ge=1, description="consecutive evidence windows beyond "
        "a threshold before the level is raised")
    clear_after_s: StrictFloat = Field(
        30.0, ge=0, description="plant seconds back inside before the "
        "level is lowered")
    clear_after_windows: StrictInt = Field(3, ge=1, description="consecutive evidence windows back "
                                           "inside before the level is lowered")
    action: str | None = Field(None, description="what the operator should do on warning/alarm "
                               "(default: a generic instruction)")
    rul_warning: StrictFloat | None = Field(None, gt=0, description="warning when the remaining "
                                            "useful life to the alarm threshold is below this [s]")
    rul_alarm: StrictFloat | None = Field(None, gt=0, description="alarm when the remaining useful "
                                          "life to the alarm threshold is below this [s]")
    rul_hysteresis: StrictFloat = Field(
        0.25, ge=0, le=10, description="a RUL level clears once the "
        "RUL is back above its threshold times 1 + this")
    rul_basis: Literal["median", "low"] = Field(
        "median", description="the RUL the rules read: the median, or the interval's "
        "earliest end (the earliest plausible crossing)")

    @model_validator(mode="after")
    def _consistent(self) -> AlarmRule:
        for lvl in ("warning", "alarm"):
            if getattr(self, lvl) is not None and (getattr(self, f"{lvl}_high") is not None
                                                   or getattr(self, f"{lvl}_low") is not None):
                raise ValueError(f"{lvl}: give either {lvl} (symmetric) or {lvl}_high/"
                                 f"{lvl}_low, not both")
        if all(getattr(self, k) is None for k in ("warning", "alarm", "warning_high",
                                                  "alarm_high", "warning_low", "alarm_low")):
            raise ValueError("no threshold: set warning and/or alarm (percent of nominal)")
        hi_w = self.warning if self.warning is not None else self.warning_high
        hi_a = self.alarm if self.alarm is not None else self.alarm_high
        if hi_w is not None and hi_a is not None and hi_w >= hi_a:
            raise ValueError(f"alarm: the alarm threshold ({hi_a} %) must be beyond the "
                             f"warning threshold ({hi_w} %)")
        lo_w = -self.warning if self.warning is not None else self.warning_low
        lo_a = -self.alarm if self.alarm is not None else self.alarm_low
        if lo_w is not None and lo_a is not None and lo_w <= lo_a:
            raise ValueError(f"alarm_low: the alarm threshold ({lo_a} %) must be beyond the "
                             f"warning threshold ({lo_w} %)")
        if (self.rul_warning is not None and self.rul_alarm is not None
                and self.rul_warning <= self.rul_alarm):
            raise ValueError(f"rul_warning: a RUL warning ({self.rul_warning} s) must come "
                             f"before the RUL alarm ({self.rul_alarm} s): make it larger")
        smallest = min(abs(v) for v in (hi_w, hi_a, lo_w, lo_a) if v is not None)
        if self.hysteresis >= smallest:
            raise ValueError(f"hysteresis: {self.hysteresis} percentage points is not smaller "
                             f"than the smallest threshold ({smallest} %): the level could "
                             "never clear")
        return self

    def thresholds(self, level: Level) -> tuple[float | None, float | None]:
        """(high, low) signed thresholds [%] of ``level`` (``warning`` or ``alarm``)."""
        sym = getattr(self, level)
        if sym is not None:
            return float(sym), -float(sym)
        return getattr(self, f"{level}_high"), getattr(self, f"{level}_low")

    @property
    def has_rul(self) -> bool:
        """The rule alarms on the remaining useful life."""
        return self.rul_warning is not None or self.rul_alarm is not None

    def rul_threshold(self, level: Level) -> float | None:
        """The RUL [s] below which ``level`` (``warning`` or ``alarm``) is raised."""
        return self.rul_warning if level == "warning" else self.rul_alarm

    def thresholds_si(self, nominal: float) -> Thresholds:
        """The rule's thresholds as values of the parameter [SI] (``nominal * (1 + pct/100)``),
        the targets of its remaining useful life."""
        from twinwatch.twin.prognostics.config import Thresholds

        def si(pct: float | None) -> float | None:
            return None if pct is None else nominal * (1.0 + pct / 100.0)

        wh, wl = self.thresholds("warning")
        ah, al = self.thresholds("alarm")
        return Thresholds(si(wh), si(wl), si(ah), si(al))

    def beyond(self, level: Level, deviation: float, margin: float = 0.0) -> float | None:
        """The (signed) threshold of ``level`` that ``deviation`` is beyond, moved inwards by
        ``margin`` percentage points (the hysteresis when the level is already active), or
        None."""
        high, low = self.thresholds(level)
        if high is not None and deviation >= high - margin:
            return high
        if low is not None and deviation <= low + margin:
            return low
        return None


class AlarmConfig(StrictTable):
    """``[alarms]``: per-parameter alarm rules; published on ``twinwatch/<machine>/alarm``."""

    enabled: bool = Field(True, description="evaluate alarms and publish their changes")
    parameters: dict[str, AlarmRule] = Field(default_factory=dict,
                                             description="parameter name -> rule")

    def rul_targets(self, nominal: Mapping[str, float]) -> dict[str, Thresholds]:
        """Parameter -> its rule's thresholds [SI] for the prognostics (``nominal``: the
        nameplate values the percentages are of); empty when alarms are off."""
        if not self.enabled:
            return {}
        return {name: rule.thresholds_si(float(nominal[name]))
                for name, rule in self.parameters.items() if name in nominal}

    def check_against(self, parameter_names: Iterable[str],
                      estimated: Iterable[str] | None = None) -> None:
        """Cross-check against the twin model (call from the config's model validator).

        Raises:
            ValueError: naming ``alarms.parameters.<name>`` for a parameter the model does not
                have, or one that is never estimated (fixed or tied: its deviation cannot move).
        """
        names = list(parameter_names)
        est = None if estimated is None else set(estimated)
        for name in self.parameters:
            if name not in names:
                raise ValueError(f"alarms.parameters.{name}: unknown parameter; the model has "
                                 f"{names}")
            if est is not None and name not in est:
                raise ValueError(f"alarms.parameters.{name}: {name} is not estimated (fixed or "
                                 f"tied), its deviation never changes; estimate it or put the "
                                 f"rule on the parameter it is tied to")
