"""Fault libraries: each machine model's fault modes as data (TOML), validated with pydantic.

A fault mode names the part it concerns, its signature over the evidence the health message
publishes, the maintenance action, its urgency and its source (the paper's Table 1 and
Sections 5.2-5.3, standard references). One library is shipped per twin model
(``twinwatch/twin/diagnosis/library/<model>.toml``); a machine's ``[diagnosis]`` table extends or
overrides it (``library = "path.toml"``, inline ``[[diagnosis.faults]]``: a fault with a
shipped id replaces it). Format and meaning: docs/diagnosis.md.

Signature items (each with ``link``, the noisy-OR probability that the fault shows it):

* ``deviations``: a parameter beyond ``min_pct`` percent of its nameplate, ``up`` or ``down``;
* ``trends``: a parameter's trend degrading ``up`` or ``down`` (``parameters.<name>.trend``);
* ``terms``: a discovered meta-model term of one of ``kinds`` (``*``: any) at one of ``attach``
  (``mode`` optional); ``harmonic``: a periodic term whose angular frequency ``b`` [rad/s] is
  ``harmonic`` times the shaft speed (the library's ``speed_channel``) within ``tolerance``;
* ``model_check``: the window's model validation failed;
* ``sensors``: a frozen or saturated sensor (``channel``: one, or ``*``);
* ``readings``: one output read too ``high`` or ``low`` (a gain or an offset) on the healthy
  twin explains the window (the reading check).
"""

from __future__ import annotations

import tomllib
from collections.abc import Sequence
from functools import cache
from importlib import resources
from pathlib import Path
from typing import Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictFloat,
    ValidationError,
    field_validator,
    model_validator,
)

from twinwatch.twin.diagnosis.evidence import EVIDENCE_KINDS, ModelNames, closest

__all__ = [
    "CheckSign",
    "DeviationSign",
    "DiagnosisConfig",
    "FaultLibrary",
    "FaultMode",
    "ReadingSign",
    "SensorSign",
    "TermSign",
    "TrendSign",
    "load_library",
    "shipped_library",
]

Link = Field(0.9, gt=0, le=1, description="probability the fault shows this evidence "
             "(noisy-OR link)")


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class DeviationSign(_Strict):
    """A parameter beyond ``min_pct`` % of its nameplate in ``direction``."""

    parameter: str = Field(description="the twin's parameter (Ra, D, q_pump, ...)")
    direction: Literal["up", "down"] = Field(description="above (up) or below (down) its "
                                             "nameplate")
    min_pct: StrictFloat = Field(gt=0, description="size of the deviation the fault makes [%]")
    max_pct: StrictFloat | None = Field(None, gt=0, le=300.0, description="the largest "
                                        "deviation the fault can make [%] (default 300): "
                                        "beyond it the deviation is evidence of a fault the "
                                        "library does not know, not of this one")
    link: float = Link
    when_held: list[str] = Field(default_factory=list, description="expected only in windows "
                                 "that hold these parameters (a fault seen through a held "
                                 "parameter: a weaker magnet reads as D up while Ke is held)")
    when_estimated: list[str] = Field(default_factory=list, description="expected only in "
                                      "windows that estimate these parameters (a supply sag "
                                      "moves D through Kt = Ke only while Ke is estimated)")

    def applies(self, estimated: frozenset[str]) -> bool:
        """Whether the expectation holds in a window estimating ``estimated``."""
        return (not any(p in estimated for p in self.when_held)
                and all(p in estimated for p in self.when_estimated))

    @model_validator(mode="after")
    def _sizes(self) -> DeviationSign:
        if self.max_pct is not None and self.max_pct <= self.min_pct:
            raise ValueError(f"{self.parameter} {self.direction}: max_pct {self.max_pct:g} must "
                             f"exceed min_pct {self.min_pct:g}")
        return self


class TrendSign(_Strict):
    """A parameter's trend degrading in ``direction``."""

    parameter: str = Field(description="the twin's parameter")
    direction: Literal["up", "down"] = Field(description="the trend's direction")
    link: float = Field(0.5, gt=0, le=1, description="probability the fault shows this "
                        "evidence (a wear trends; a sudden fault steps)")
    when_held: list[str] = Field(default_factory=list, description="as a deviation's")
    when_estimated: list[str] = Field(default_factory=list, description="as a deviation's")

    def applies(self, estimated: frozenset[str]) -> bool:
        """Whether the expectation holds in a window estimating ``estimated``."""
        return (not any(p in estimated for p in self.when_held)
                and all(p in estimated for p in self.when_estimated))


class TermSign(_Strict):
    """A discovered meta-model term."""

    kinds: list[str] = Field(min_length=1, description="meta-model kinds, '*' for any")
    attach: list[str] = Field(min_length=1, description="attach points, '*' for any")
    mode: Literal["additive", "multiplicative"] | None = Field(
        None, description="the term's mode (none: either)")
    harmonic: StrictFloat | None = Field(None, gt=0, description="a periodic term's angular "
                                         "frequency over the shaft speed (1: once per turn)")
    tolerance: StrictFloat = Field(0.15, gt=0, le=1, description="relative tolerance of the "
                                   "harmonic")
    link: float = Link
    missing_link: float | None = Field(
        None, gt=0, le=1, description="probability the term is found while the fault acts, "
        "for the term's absence as evidence against the fault (none: the link). A coulomb "
        "term at a speed of one sign is a constant braking torque discovery cannot tell "
        "from a sensor's offset or from D: its absence says little")

    @property
    def absence_link(self) -> float:
        """How strongly the term's absence speaks against the fault (its link unless said)."""
        return self.link if self.missing_link is None else self.missing_link


class ScalingSign(_Strict):
    """A parameter's deviation that scales as the shaft speed to ``power`` across operating
    points: -1 for a Coulomb friction torque ``Tc`` absorbed into the viscous friction (``D``
    then reads ``D + Tc/omega``: +25 % at 5.5 rad/s, +8 % at 17.7 for Tc 0.002 N m on the DC
    motor), where a worn bearing's D stays put (power 0)."""

    parameter: str = Field(description="the twin's parameter whose deviation scales")
    power: StrictFloat = Field(-1.0, description="the power of the shaft speed it scales as")
    link: float = Link


class SensorSign(_Strict):
    """A frozen or saturated sensor."""

    kind: Literal["frozen", "saturated"] = Field(description="the stuck sensor's kind")
    channel: str = Field("*", description="its channel ('*': any)")
    link: float = Link


class CheckSign(_Strict):
    """One output's model check failing persistently (a share of the recent windows): a
    reading the twin cannot reproduce while the others fit (a voltage reading's gain)."""

    output: str = Field(description="the twin's output (Va, omega, p, ...)")
    link: float = Link
    may_pass: bool = Field(False, description="the fault may as well leave the check passing "
                           "(an unbalance whose term fits): a failing check is its evidence, "
                           "a passing one is none against it")


class ReadingSign(_Strict):
    """One wrong reading on a healthy machine explaining the window (the health message's
    reading check, :mod:`twinwatch.twin.estimation.readings`): the output read too high (a
    gain above 1 or an offset with the reading's sign) or too low."""

    output: str = Field(description="the twin's measured output (ia, omega, x, p, ...)")
    direction: Literal["high", "low"] = Field(description="the reading is too high or too "
                                              "low")
    link: float = Link


class FaultMode(_Strict):
    """One fault mode of a machine model."""

    id: str = Field(pattern=r"^[a-z0-9_]+$", max_length=48, description="the fault mode's id "
                    "(lower case, digits, _): published as diagnosis.top")
    component: str = Field(min_length=1, description="the part it concerns")
    description: str = Field("", description="what fails, for a person")
    deviations: list[DeviationSign] = Field(default_factory=list)
    trends: list[TrendSign] = Field(default_factory=list)
    terms: list[TermSign] = Field(default_factory=list)
    model_check: float | None = Field(None, gt=0, le=1, description="link to a failed model "
                                      "check")
    sensors: list[SensorSign] = Field(default_factory=list)
    scaling: list[ScalingSign] = Field(default_factory=list, description="parameters whose "
                                       "deviation scales with the shaft speed")
    checks: list[CheckSign] = Field(default_factory=list, description="outputs whose model "
                                    "check the fault makes fail persistently")
    readings: list[ReadingSign] = Field(default_factory=list, description="the reading whose "
                                        "error explains the window on the healthy twin")
    action: str = Field(min_length=1, description="the maintenance action")
    urgency: Literal["low", "medium", "high"] = Field("medium", description="how soon to act")
    prior: float = Field(0.01, gt=0, lt=0.5, description="probability the fault is present at "
                         "any window")
    source: str = Field(min_length=1, description="the reference the signature comes from")

    @model_validator(mode="after")
    def _has_signature(self) -> FaultMode:
        if not any(kind.present(self) for kind in EVIDENCE_KINDS.values()):
            raise ValueError(f"fault {self.id!r}: its signature is empty (give deviations, "
                             f"trends, terms, sensors, readings or model_check)")
        return self

    def parameters(self) -> set[str]:
        """The parameters its signature names."""
        return {d.parameter for d in self.deviations} | {t.parameter for t in self.trends}


class FaultLibrary(_Strict):
    """A model's fault library (one TOML file)."""

    model: str = Field(description="the twin model it is for (registry name)")
    speed_channel: str = Field("", description="the shaft speed channel [rad/s] a periodic "
                               "term's frequency is compared with ('' : none)")
    equations: dict[str, list[str]] = Field(
        default_factory=dict, description="attach point -> the parameters of the equation it "
        "adds to: while a term there is one no fault explains, their deviations and trends "
        "may be its model error (the estimates absorb part of what the twin lacks)")
    read_across: list[str] = Field(
        default_factory=list, description="parameters the windows hold that the diagnosis "
        "reads across windows, from how the estimates moved with each window's alias of it "
        "(docs/diagnosis.md, 'A parameter the windows hold'); each one measured on the fault "
        "matrix before it is listed (the default motor's La read -33 % to +37 % on a nominal "
        "winding's run and named a voltage reading low at 0.88)")
    faults: list[FaultMode]

    @field_validator("faults")
    @classmethod
    def _unique(cls, v: list[FaultMode]) -> list[FaultMode]:
        seen: set[str] = set()
        for f in v:
            if f.id in seen:
                raise ValueError(f"fault id {f.id!r} appears twice")
            seen.add(f.id)
        return v


def load_library(path: str | Path) -> FaultLibrary:
    """Read and validate a fault library TOML file.

    Raises:
        OSError: the file cannot be read (IsADirectoryError: a directory). ValueError: a bad
        key, in one line naming each bad key with its location (``faults.0.deviations.0.
        direction: Input should be 'up' or 'down'``), no pydantic link;
        tomllib.TOMLDecodeError: not TOML.
    """
    with open(path, "rb") as fh:
        data = tomllib.load(fh)
    try:
        return FaultLibrary.model_validate(data)
    except ValidationError as exc:
        raise ValueError(one_line(exc)) from None


def one_line(exc: ValidationError) -> str:
    """A validation error in one line: ``key: message; key: message`` (each key dotted, a
    fault named by its id where it has one), without pydantic's links."""
    parts = []
    for err in exc.errors(include_url=False):
        loc = ".".join(str(p) for p in err["loc"])
        msg = str(err["msg"]).removeprefix("Value error, ")
        if err["type"] == "extra_forbidden":
            msg = "unknown key (misspelt, or not valid here)"
        elif err["type"] == "missing":
            msg = "required key is missing"
        parts.append(f"{loc}: {msg}" if loc else msg)
    return "; ".join(parts)


@cache
def shipped_library(model: str) -> FaultLibrary | None:
    """The library shipped for a twin model (``dc_motor``, ``dc_motor_pwm``,
    ``hydraulic_actuator``), or None."""
    ref = resources.files("twinwatch.twin.diagnosis").joinpath("library", f"{model}.toml")
    if not ref.is_file():
        return None
    return FaultLibrary.model_validate(tomllib.loads(ref.read_text(encoding="utf-8")))


class DiagnosisConfig(_Strict):
    """``[diagnosis]``: which fault library the diagnosis reads (docs/diagnosis.md)."""

    enabled: bool = Field(True, description="rank the fault modes every window (the health "
                          "message's diagnosis)")
    library: str | None = Field(None, description="a fault library TOML file (relative to the "
                                "working directory) extending the shipped one; a fault with a "
                                "shipped id replaces it")
    replace: bool = Field(False, description="use only the configured faults, not the "
                          "shipped library")
    faults: list[FaultMode] = Field(default_factory=list, description="[[diagnosis.faults]]: "
                                    "fault modes extending or replacing the library's")
    unknown_prior: float = Field(0.01, gt=0, lt=0.5, description="prior of a fault the "
                                 "library does not know (a term no fault mode explains)")
    listed: int = Field(5, ge=1, le=50, description="most fault modes listed in the message")
    alarm: float | None = Field(0.8, gt=0, le=1, description="a fault whose probability "
                                "reaches this raises an alarm event (twinwatch/<name>/alarm, "
                                "kind 'diagnosis'); none: no fault alarm")
    clear: float = Field(0.5, gt=0, lt=1, description="... cleared once its probability is "
                         "back below this (hysteresis)")
    raise_after_windows: int = Field(3, ge=1, le=1000, description="windows in a row at or "
                                     "above alarm before it is raised")
    clear_after_windows: int = Field(3, ge=1, le=1000, description="windows in a row below "
                                     "clear before it is cleared")
    check_function_after_s: float = Field(
        60.0, gt=0, le=86400, description="plant time [s] over which failed model checks "
        "put the diagnosis in check_function (NAMUR NE 107): the twin does not describe the "
        "machine, its estimates are held and no outcome is claimed")
    check_function_share: float = Field(0.8, gt=0, le=1, description="... the share of that "
                                        "time's windows whose model check failed")
    check_function_clear_windows: int = Field(3, ge=1, le=1000, description="windows in a row "
                                              "whose model check passed that end it")

    @model_validator(mode="after")
    def _hysteresis(self) -> DiagnosisConfig:
        if self.alarm is not None and self.clear >= self.alarm:
            raise ValueError(f"clear ({self.clear:g}) must be below alarm ({self.alarm:g}): "
                             f"the hysteresis")
        return self

    @field_validator("library")
    @classmethod
    def _readable(cls, v: str | None) -> str | None:
        if v is not None:
            try:
                load_library(v)
            except OSError as exc:
                raise ValueError(f"cannot read the fault library {v!r}: {exc.strerror}") from None
            except tomllib.TOMLDecodeError as exc:
                raise ValueError(f"the fault library {v!r} is not TOML: {exc}") from None
            except ValueError as exc:
                raise ValueError(f"the fault library {v!r}: {exc}") from None
        return v

    def resolve(self, model: str) -> FaultLibrary:
        """The library in force for a twin model: shipped, then the file's, then the inline
        faults (a later fault with the same id replaces the earlier)."""
        shipped = shipped_library(model)
        base = None if self.replace else shipped
        faults = {f.id: f for f in (base.faults if base else [])}
        speed = shipped.speed_channel if shipped else ""  # the model's, whatever the faults
        equations = dict(shipped.equations) if shipped else {}
        across = list(shipped.read_across) if shipped else []
        if self.library is not None:
            extra = load_library(self.library)
            speed = extra.speed_channel or speed
            equations.update(extra.equations)
            across += [p for p in extra.read_across if p not in across]
            faults.update({f.id: f for f in extra.faults})
        faults.update({f.id: f for f in self.faults})
        return FaultLibrary(model=model, speed_channel=speed, equations=equations,
                            read_across=across, faults=list(faults.values()))

    def check_against(self, model: str, parameter_names: tuple[str, ...] | list[str],
                      attach_names: list[str], channels: Sequence[str] = (),
                      outputs: Sequence[str] = ()) -> None:
        """Every name the faults and the library use exists: the parameters and attach points
        in the twin, the terms' kinds in the meta-model registry
        (:func:`~twinwatch.twin.discovery.metamodels.available_kinds`), the speed channel
        among the twin's ``channels``, a sensor's channel among its measured ``outputs`` (empty:
        not checked), and the library file is the machine's ``model``'s. A name that does not
        exist makes a fault that can never match, silently: refused instead.

        Raises:
            ValueError: one line naming the key (``diagnosis.library``, ``diagnosis.faults``),
                the fault and the name, with the known names.
        """
        if not self.enabled:
            return
        from twinwatch.twin.discovery.metamodels import available_kinds

        where = "diagnosis"
        if self.library is not None:
            extra = load_library(self.library)
            where = f"diagnosis.library ({self.library})"
            if extra.model != model:
                raise ValueError(f"{where}: the library is for the {extra.model!r} model; this "
                                 f"machine's model is {model!r}: set its model = {model!r} or "
                                 f"give the {model} library")
            if extra.speed_channel and channels and extra.speed_channel not in channels:
                raise ValueError(f"{where}: speed_channel {extra.speed_channel!r} is not a "
                                 f"channel of the {model} twin; "
                                 f"{closest(extra.speed_channel, channels)}")
        lib = self.resolve(model)
        inline = {f.id for f in self.faults}
        known = ModelNames(model, tuple(parameter_names), tuple(attach_names), tuple(channels),
                           tuple(outputs), tuple(available_kinds()))
        for f in lib.faults:
            key = "diagnosis.faults" if f.id in inline else where
            for kind in EVIDENCE_KINDS.values():
                problem = kind.problem(f, known)
                if problem is not None:
                    raise ValueError(f"{key}: fault {f.id!r} {problem}")
        for name in lib.read_across:
            if name not in parameter_names:
                raise ValueError(f"{where}: read_across names {name!r}, not a parameter of the "
                                 f"{model} twin; {closest(name, parameter_names)}")
        for a, names in lib.equations.items():
            if a not in attach_names:
                raise ValueError(f"diagnosis: equations names the attach point {a!r}; the "
                                 f"{model} model has {attach_names}")
            for name in names:
                if name not in parameter_names:
                    raise ValueError(f"diagnosis: equations.{a} names the parameter {name!r}; "
                                     f"the {model} model has {list(parameter_names)}")
