"""Fault libraries: each machine model's fault modes as changes of its twin (TOML), validated
with pydantic.

A fault mode names the part it concerns and **what changes in the twin** when it is present,
never which estimates move or by how much: that follows from the twin on each window's data
(:mod:`~twinwatch.twin.diagnosis.hypotheses`). One library is shipped per twin model
(``twinwatch/twin/diagnosis/library/<model>.toml``); a machine's ``[diagnosis]`` table extends
or overrides it (``library = "path.toml"``, inline ``[[diagnosis.faults]]``: a fault with a
shipped id replaces it). Format and meaning: docs/diagnosis.md.

A change (one of):

* ``parameter = "Ra"``: the parameter scaled; ``range = [low, high]`` its plausible change [%];
* ``scale = { Ra = 1, La = 1, Ke = 1 }``: parameters scaled together, each by the common
  factor to its power (a supply delivering ``r`` times the voltage the drive reports divides
  Eq. 4's Ra, La and Ke by ``r``); ``range`` the factor's change [%];
* ``gain = "ia"``: a reading is ``(1 + g)`` times the true value; ``range`` g [%];
* ``offset = "omega"``: a reading is the true value plus an offset; ``range`` in % of the
  reading's scale (its RMS over the window; one side: its sign);
* ``supply = "Va"``: the machine receives ``(1 + r)`` times the input it reports; ``range``
  r [%];
* ``term = "d(omega)/dt"`` with ``shape``: a meta-model term at the attach point (paper
  Eq. 3): ``constant``, ``coulomb`` (a braking ``-sign(speed)``), ``periodic`` (the shaft's
  ``harmonic``: 1 an unbalance, 2 a misalignment, ISO 21940-11); ``range`` its amplitude in the
  attach point's unit (``coulomb``: ``[0, ...]``);
* ``stuck = "omega"``: the reading constant while the twin predicts it changing;
  ``clipped = "ia"``: the reading limited at its extreme.

``alternatives`` lists the twins a fault may be (each one change); ``together`` one twin of
several changes at once (where the physics ties them). A fault's ``prior`` is the probability
it is present at any window; ``confirm`` the check that tells it apart on the machine (said
when the data cannot).
"""

from __future__ import annotations

import math
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

from twinwatch.twin.diagnosis.hypotheses import Change, Hypothesis

__all__ = ["ChangeSpec", "DiagnosisConfig", "FaultLibrary", "FaultMode", "closest",
           "load_library", "shipped_library"]

_KINDS = ("parameter", "scale", "gain", "offset", "supply", "term", "stuck", "clipped")


def closest(name: str, known: Sequence[str]) -> str:
    """``did you mean 'omega'? known: ia, omega`` (the closest known name, if any)."""
    import difflib

    close = difflib.get_close_matches(name, list(known), n=1)
    return (f"did you mean {close[0]!r}? " if close else "") + f"known: {', '.join(known)}"


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class ChangeSpec(_Strict):
    """One change of the twin (exactly one of the kinds; see the module docstring)."""

    parameter: str | None = None
    scale: dict[str, StrictFloat] | None = None
    gain: str | None = None
    offset: str | None = None
    supply: str | None = None
    term: str | None = None
    stuck: str | None = None
    clipped: str | None = None
    shape: Literal["constant", "coulomb", "periodic"] = Field(
        "constant", description="a term's shape")
    harmonic: StrictFloat = Field(1.0, gt=0, description="a periodic term's multiple of the "
                                  "shaft's rotation")
    range: tuple[StrictFloat, StrictFloat] | None = Field(
        None, description="the change's plausible size: [%] for parameter, scale, gain and "
        "supply; [% of the reading's RMS] for offset; the attach point's unit for a term")

    @model_validator(mode="after")
    def _one(self) -> ChangeSpec:
        given = [k for k in _KINDS if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError(f"a change names exactly one of {', '.join(_KINDS)} (got "
                             f"{', '.join(given) or 'none'})")
        if self.range is not None and self.range[0] >= self.range[1]:
            raise ValueError(f"range {list(self.range)}: low must be below high")
        pct = self.kind in ("parameter", "scale", "gain", "supply")
        if self.kind == "offset" and self.range is not None and (
                self.range[0] < -1000.0 or self.range[1] > 1000.0):
            raise ValueError(f"range {list(self.range)}: an offset's range is in % of the "
                             f"reading's scale (-1000 to 1000)")
        if pct and self.range is not None and self.range[0] <= -100.0:
            raise ValueError(f"range {list(self.range)}: a change in % must stay above -100")
        return self

    @property
    def kind(self) -> str:
        return next(k for k in _KINDS if getattr(self, k) is not None)

    @property
    def target(self) -> str:
        v = getattr(self, self.kind)
        return "" if isinstance(v, dict) else str(v)

    def names(self) -> tuple[list[str], list[str], list[str]]:
        """(parameters, channels, attach points) it names."""
        if self.kind == "parameter":
            return [str(self.parameter)], [], []
        if self.kind == "scale":
            return list(self.scale or {}), [], []
        if self.kind == "term":
            return [], [], [str(self.term)]
        return [], [self.target], []

    def change(self) -> Change:
        """The hypothesis module's :class:`~twinwatch.twin.diagnosis.hypotheses.Change`."""
        lo, hi = self.range if self.range is not None else (None, None)

        def ln(v: float | None) -> float | None:
            return None if v is None else math.log1p(v / 100.0)

        if self.kind in ("parameter", "scale"):
            powers = ((str(self.parameter), 1.0),) if self.kind == "parameter" else tuple(
                (k, float(v)) for k, v in (self.scale or {}).items())
            return Change("scale", powers=powers, low=ln(lo), high=ln(hi))
        if self.kind == "supply":
            return Change(self.kind, self.target, low=ln(lo), high=ln(hi))
        if self.kind in ("gain", "offset"):      # g, and an offset's share of the scale
            return Change(self.kind, self.target,
                          low=None if lo is None else lo / 100.0,
                          high=None if hi is None else hi / 100.0)
        if self.kind == "term":
            return Change("term", self.target, basis=self.shape, harmonic=self.harmonic,
                          low=lo, high=hi)
        return Change(self.kind, self.target, low=lo, high=hi)

    def describe(self) -> str:
        """For a person: ``Ra``, ``Ke and Kt together``, ``ia reading's gain``."""
        k = self.kind
        if k == "parameter":
            return str(self.parameter)
        if k == "scale":
            return " and ".join(self.scale or {}) + " together"
        if k == "term":
            extra = f" at {self.harmonic:g}x the shaft speed" if self.shape == "periodic" else ""
            return f"a {self.shape} term on {self.term}{extra}"
        return {"gain": f"{self.target} reading's gain", "offset": f"{self.target} reading's "
                "offset", "supply": f"the supply's ratio on {self.target}",
                "stuck": f"{self.target} reading stuck", "clipped": f"{self.target} reading "
                "clipped"}[k]


class FaultMode(_Strict):
    """One fault mode of a machine model: a change of the twin."""

    id: str = Field(pattern=r"^[a-z0-9_]+$", max_length=48, description="the fault mode's id "
                    "(lower case, digits, _): published as diagnosis.top")
    component: str = Field(min_length=1, description="the part it concerns")
    description: str = Field("", description="what fails, for a person")
    change: ChangeSpec | None = Field(None, description="the twin's one change")
    alternatives: list[ChangeSpec] = Field(default_factory=list, description="the twins the "
                                           "fault may be, one change each")
    together: list[ChangeSpec] = Field(default_factory=list, description="changes made at "
                                       "once (one twin)")
    action: str = Field(min_length=1, description="the maintenance action")
    confirm: str = Field("", description="the check on the machine that confirms it (said "
                         "when the data cannot tell it from another mode; default: action)")
    urgency: Literal["low", "medium", "high"] = Field("medium", description="how soon to act")
    prior: float = Field(0.01, gt=0, lt=0.5, description="probability the fault is present at "
                         "any window")
    source: str = Field(min_length=1, description="the reference its physics comes from")

    @model_validator(mode="after")
    def _has_change(self) -> FaultMode:
        if not (self.change or self.alternatives or self.together):
            raise ValueError(f"fault {self.id!r}: give its change (change, alternatives or "
                             f"together)")
        return self

    def twins(self) -> list[list[ChangeSpec]]:
        """Its twins: each a list of changes made at once."""
        out: list[list[ChangeSpec]] = []
        if self.change is not None:
            out.append([self.change])
        out += [[c] for c in self.alternatives]
        if self.together:
            out.append(list(self.together))
        return out

    def hypotheses(self, parameters: Sequence[str], channels: Sequence[str],
                   attach: Sequence[str]) -> list[Hypothesis]:
        """Its twins as hypotheses, those a twin without the names they need left out (a
        library shared by twin variants: the PWM drive has no Va channel)."""
        out = []
        for i, twin in enumerate(self.twins()):
            usable = True
            for c in twin:
                p, ch, a = c.names()
                if (any(n not in parameters for n in p) or any(n not in channels for n in ch)
                        or any(n not in attach for n in a)):
                    usable = False
            if usable:
                out.append(Hypothesis((self.id,), tuple(c.change() for c in twin),
                                      f"{self.id}#{i}"))
        return out

    def explained(self, twin: int) -> str:
        tw = self.twins()[twin]
        return ", ".join(c.describe() for c in tw)


class FaultLibrary(_Strict):
    """A model's fault library (one TOML file)."""

    model: str = Field(description="the twin model it is for (registry name)")
    speed_channel: str = Field("", description="the shaft speed channel [rad/s] a periodic "
                               "or Coulomb term is built from ('' : none)")
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
        key, in one line naming each bad key with its location (``faults.0.change.range:
        ...``), no pydantic link; tomllib.TOMLDecodeError: not TOML.
    """
    with open(path, "rb") as fh:
        data = tomllib.load(fh)
    try:
        return FaultLibrary.model_validate(data)
    except ValidationError as exc:
        raise ValueError(one_line(exc)) from None


def one_line(exc: ValidationError) -> str:
    """A validation error in one line: ``key: message; key: message`` (each key dotted),
    without pydantic's links."""
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
    """``[diagnosis]``: the fault library and how the diagnosis reads it (docs/diagnosis.md)."""

    enabled: bool = Field(True, description="rank the fault modes every window (the health "
                          "message's diagnosis)")
    library: str | None = Field(None, description="a fault library TOML file (relative to the "
                                "working directory) extending the shipped one; a fault with a "
                                "shipped id replaces it")
    replace: bool = Field(False, description="use only the configured faults, not the "
                          "shipped library")
    faults: list[FaultMode] = Field(default_factory=list, description="[[diagnosis.faults]]: "
                                    "fault modes extending or replacing the library's")
    unknown_prior: float = Field(0.01, gt=0, lt=0.5, description="prior of a change the "
                                 "library does not know")
    baseline_windows: int = Field(10, ge=2, le=10000, description="windows that learn this "
                                  "machine's healthy baseline before a change is looked for "
                                  "(the machine is taken as healthy then)")
    keep_windows: int = Field(150, ge=10, le=10000, description="windows kept per hypothesis: "
                              "a change point is looked for among them")
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
        speed = shipped.speed_channel if shipped else ""
        if self.library is not None:
            extra = load_library(self.library)
            speed = extra.speed_channel or speed
            faults.update({f.id: f for f in extra.faults})
        faults.update({f.id: f for f in self.faults})
        return FaultLibrary(model=model, speed_channel=speed, faults=list(faults.values()))

    def check_against(self, model: str, parameter_names: Sequence[str],
                      attach_names: Sequence[str], channels: Sequence[str] = (),
                      outputs: Sequence[str] = ()) -> None:
        """Every name the faults use exists in the twin: a change's parameters, its channel
        among the twin's ``channels`` (empty: not checked), its attach point; the speed
        channel; the library file is the machine's ``model``'s. A configured fault (the
        library file's, an inline one) naming something the machine lacks is refused; a
        shipped one only when none of its twins is usable (a library shared by the twin's
        variants: a Coulomb friction parameter exists only with ``coulomb_friction``).

        Raises:
            ValueError: one line naming the key (``diagnosis.library``, ``diagnosis.faults``),
                the fault and the name, with the known names.
        """
        if not self.enabled:
            return
        where = "diagnosis"
        if self.library is not None:
            extra = load_library(self.library)
            where = f"diagnosis.library ({self.library})"
            if extra.model != model:
                raise ValueError(f"{where}: the library is for the {extra.model!r} model; this "
                                 f"machine's model is {model!r}: set its model = {model!r} or "
                                 f"give the {model} library")
        lib = self.resolve(model)
        if lib.speed_channel and channels and lib.speed_channel not in channels:
            raise ValueError(f"{where}: speed_channel {lib.speed_channel!r} is not a channel "
                             f"of the {model} twin; {closest(lib.speed_channel, channels)}")
        inline = {f.id for f in self.faults}
        configured = inline | ({f.id for f in load_library(self.library).faults}
                               if self.library is not None else set())
        chans = list(channels) or None
        for f in lib.faults:
            key = "diagnosis.faults" if f.id in inline else where
            problems = []
            for twin in f.twins():
                for c in twin:
                    p, ch, a = c.names()
                    for n in p:
                        if n not in parameter_names:
                            problems.append(f"names the parameter {n!r}; "
                                            f"{closest(n, parameter_names)}")
                    for n in a:
                        if n not in attach_names:
                            problems.append(f"names the attach point {n!r}; "
                                            f"{closest(n, attach_names)}")
                    for n in ch:
                        if chans is not None and n not in chans:
                            problems.append(f"names the channel {n!r}; {closest(n, chans)}")
                    if c.kind == "term" and c.shape != "constant" and not lib.speed_channel:
                        problems.append(f"has a {c.shape} term, which needs the library's "
                                        f"speed_channel")
            usable = len(f.hypotheses(parameter_names, chans or [], attach_names)) \
                if chans is not None else 1
            # a configured fault is the user's: every name must exist; a shipped one may hold
            # twins a variant of the model lacks (a Coulomb friction parameter, a Va reading)
            if problems and (f.id in configured or usable == 0):
                raise ValueError(f"{key}: fault {f.id!r} {problems[0]}")
