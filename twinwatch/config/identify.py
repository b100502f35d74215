"""The ``[identify]`` table: how ``twinwatch identify`` fits a machine's baseline from a
recording (:mod:`twinwatch.commissioning`): the training and validation ranges, the output
weights, what to identify within which bounds, the stated values to hold an undetermined
parameter at, the candidate model structures and the global search's settings.

It imports the estimation's table and the model contract (the estimation's numerics):
:mod:`twinwatch.config.schema` imports this module when a configuration is validated.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictFloat,
    StrictInt,
    field_validator,
    model_validator,
)

from twinwatch._table import StrictTable
from twinwatch.twin.estimation.estimator import EstimationConfig, PSOSettings
from twinwatch.twin.model import TwinModel


class FixedValue(StrictTable):
    """A stated value of one parameter (``[identify.fixed]``): held there when the recording
    does not determine the parameter."""

    value: StrictFloat = Field(gt=0, allow_inf_nan=False, description="the value [SI]")
    rel_std: StrictFloat = Field(0.0, ge=0, allow_inf_nan=False, description="its relative "
                                 "standard error (1 sigma), propagated to the parameters re-fitted "
                                 "with it held (0: taken as exact)")
    reason: str = Field("", description="where the value comes from (a nameplate, a "
                        "datasheet, another experiment)")


class Candidate(StrictTable):
    """A candidate model structure (``[[identify.candidates]]``): model options over
    ``[machine.options]`` (tables merged key by key: ``drive = { period = 0.002 }`` changes only
    the period)."""

    name: str = Field(min_length=1, description="how the report names it")
    options: dict[str, Any] = Field(description="model options that differ from "
                                    "[machine.options] (integrator method, controller period, "
                                    "input hold, filters, power stage, ...)")


class IdentifyConfig(StrictTable):
    """The ``[identify]`` table: how ``twinwatch identify`` fits the baseline.

    Ranges are fractions of the recording's samples: ``[0.0, 0.5]`` is its first half.
    """

    train: tuple[StrictFloat, StrictFloat] = Field(
        (0.0, 0.5), description="training range, fractions "
        "of the recording [start, end)")
    validate_: tuple[StrictFloat, StrictFloat] = Field(
        (0.5, 1.0), alias="validate", description="validation range, fractions of the "
        "recording [start, end); the fit is scored there, never fitted")
    weights: dict[str, StrictFloat] = Field(default_factory=dict, description="output -> weight in "
                                            "the fitness (default 1)")
    estimate: list[str] | None = Field(
        None, description="parameters to identify, in priority order (default: [estimation] "
        "estimate); a long recording determines more than one window (a warm-up law, the "
        "sensing's hypotheses), which the monitoring then holds at the identified values")
    bounds: dict[str, tuple[StrictFloat, StrictFloat]] = Field(
        default_factory=dict, description="parameter -> [low, high] in SI units for the "
        "identification, over [estimation] bounds (a cold start searches wider than a window)")
    max_rel_std: StrictFloat = Field(
        0.1, gt=0, allow_inf_nan=False, description="a parameter is determined when its "
        "relative standard error (1 sigma) is at most this; the others are held at their "
        "stated values and the rest re-fitted")
    fixed: dict[str, FixedValue] = Field(
        default_factory=dict, description="parameter -> { value, rel_std, reason }: the "
        "stated value to hold an identified parameter at when the recording does not "
        "determine it (default: its [machine.parameters] value); the value of a parameter "
        "that is not identified")
    correlation: StrictFloat = Field(0.9, gt=0, lt=1, description="|correlation| from which a "
                                     "pair of parameters is reported as strongly correlated")
    candidates: list[Candidate] = Field(
        default_factory=list, description="other model structures to identify and compare "
        "with the configured one by validation fit, model check and BIC")
    pso: PSOSettings = Field(default_factory=lambda: PSOSettings(pop_size=30,
                                                                 max_generations=100))
    time_budget: StrictFloat = Field(120.0, gt=0, allow_inf_nan=False,
                                     description="wall-time cap of the global searches [s], shared "
                                     "by the starts (per structure)")
    starts: StrictInt = Field(1, ge=1, le=100, description="independent global searches, each "
                              "polished by least squares; the best training fit is kept (a long "
                              "free-run problem has local optima a single swarm may settle in)")
    seed: StrictInt = 0

    model_config = ConfigDict(populate_by_name=True)

    @field_validator("fixed", mode="before")
    @classmethod
    def _bare_values(cls, value: Any) -> Any:
        # ``Ra = 29.6`` is short for ``Ra = { value = 29.6 }``
        if isinstance(value, Mapping):
            return {k: ({"value": v} if isinstance(v, (int, float)) else v)
                    for k, v in value.items()}
        return value

    @model_validator(mode="after")
    def _check(self) -> IdentifyConfig:
        for key, (a, b) in (("train", self.train), ("validate", self.validate_)):
            if not 0.0 <= a < b <= 1.0:
                raise ValueError(f"{key}: need 0 <= start < end <= 1 (fractions of the "
                                 f"recording), got [{a}, {b}]")
        for name, w in self.weights.items():
            if not (w >= 0 and math.isfinite(w)):
                raise ValueError(f"weights.{name}: must be a finite number >= 0")
        if self.estimate is not None and len(set(self.estimate)) != len(self.estimate):
            raise ValueError("estimate: a parameter is listed twice")
        for name, (lo, hi) in self.bounds.items():
            if not (0 < lo < hi and math.isfinite(hi)):
                raise ValueError(f"bounds.{name}: need 0 < low < high, got [{lo}, {hi}]")
        names = [c.name for c in self.candidates]
        for k, name in enumerate(names):
            if name in names[:k] or name == AS_CONFIGURED:
                raise ValueError(f"candidates[{k}].name: {name!r} is taken (each candidate "
                                 f"needs its own name; {AS_CONFIGURED!r} is the configured "
                                 "structure)")
        return self

    def check_against(self, model: TwinModel) -> None:
        """Raise ValueError naming the key (``identify.<key>``) if an output, a parameter or a
        candidate's option is not the model's."""
        for name in self.weights:
            if name not in model.output_names:
                raise ValueError(f"identify.weights.{name}: not an output of the model "
                                 f"{list(model.output_names)}")
        names = model.parameter_names
        for key, group in (("estimate", self.estimate or []), ("bounds", list(self.bounds)),
                           ("fixed", list(self.fixed))):
            for name in group:
                if name not in names:
                    raise ValueError(f"identify.{key}: unknown parameter {name!r}; the model "
                                     f"has {sorted(names)}")
        for k, cand in enumerate(self.candidates):
            if not dataclasses.is_dataclass(model):
                break  # a plug-in model: its candidates are checked when commissioned
            fields = {f.name: getattr(model, f.name) for f in dataclasses.fields(model)
                      if f.init}
            try:
                dataclasses.replace(model, **merge_options(fields, cand.options, known=fields))
            except (TypeError, ValueError, ArithmeticError) as exc:
                raise ValueError(f"identify.candidates[{k}] ({cand.name}).options: {exc}"
                                 ) from exc

    def estimation(self, estimation: EstimationConfig) -> EstimationConfig:
        """The ``[estimation]`` table as the identification uses it: this table's
        ``estimate`` and ``bounds`` over it (a tie whose parameter is identified is dropped).
        """
        if self.estimate is None and not self.bounds:
            return estimation
        estimate = list(self.estimate) if self.estimate is not None else estimation.estimate
        tie = {d: s for d, s in (estimation.tie or {}).items() if d not in (estimate or [])}
        return estimation.model_copy(update={"estimate": estimate, "tie": tie,
                                             "bounds": {**estimation.bounds, **self.bounds}})

    def for_structure(self, model: TwinModel) -> IdentifyConfig:
        """This table for a candidate structure whose model may lack some parameters (an
        option that removes one): those are dropped from ``estimate``, ``bounds``, ``fixed``."""
        names = set(model.parameter_names)
        update: dict[str, Any] = {
            "bounds": {k: v for k, v in self.bounds.items() if k in names},
            "fixed": {k: v for k, v in self.fixed.items() if k in names}}
        if self.estimate is not None:
            update["estimate"] = [n for n in self.estimate if n in names]
        return self.model_copy(update=update)


#: The name of the configured structure in a comparison.
AS_CONFIGURED = "as configured"


def merge_options(base: Mapping[str, Any], override: Mapping[str, Any], *,
                  known: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """``base`` with ``override`` over it, tables merged key by key (a candidate's options over
    ``[machine.options]``).

    Raises:
        ValueError: ``known`` given and an override key is not in it (a misspelt option).
    """
    out = dict(base)
    for key, value in override.items():
        if known is not None and key not in known:
            raise ValueError(f"unknown option {key!r}")
        old = out.get(key)
        if isinstance(value, Mapping) and isinstance(old, Mapping):
            out[key] = merge_options(old, value)
        elif isinstance(value, Mapping) and dataclasses.is_dataclass(old) \
                and not isinstance(old, type):
            out[key] = dataclasses.replace(old, **dict(value))
        elif isinstance(value, Mapping) and isinstance(old, BaseModel):
            out[key] = old.model_copy(update=dict(value))
        else:
            out[key] = value
    return out


__all__ = ["AS_CONFIGURED", "Candidate", "FixedValue", "IdentifyConfig", "merge_options"]
