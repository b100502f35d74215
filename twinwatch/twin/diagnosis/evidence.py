"""The evidence kinds a fault's signature may list, behind one registry (:data:`EVIDENCE_KINDS`).

Each kind is a small class: the signature key it reads in a fault mode (``deviations``,
``trends``, ``terms``, ``model_check``, ``checks``, ``sensors``, ``readings``:
docs/diagnosis.md), the
*validation* of its names against the machine (:meth:`EvidenceKind.problem`: a name that does
not exist makes a fault that can never match, refused by ``check-config``) and its
*likelihood* in the noisy-OR network (:mod:`twinwatch.twin.diagnosis.inference`): the evidence
variables a fault of the library shares with the others (:meth:`EvidenceKind.add_variables`,
each a :class:`Variable`: a soft observation, its leak, each fault's link), or, for the two
kinds whose likelihood is not one variable per signature item, where it is computed:

* ``deviations``: a graded likelihood per parameter over every hypothesis
  (:func:`twinwatch.twin.diagnosis.deviation.likelihood`, read by ``Diagnoser._dev_factors``);
* ``terms``: one variable per *discovered* term, each fault's link scaled by how well the term
  matches its signature (``Diagnoser._term_vars``), and one against each fault whose expected
  term the window lacks (``Diagnoser._missing_term_vars``).

A new evidence kind is one :class:`EvidenceKind` subclass here, one line in
:data:`EVIDENCE_KINDS` and its signature model in :mod:`twinwatch.twin.diagnosis.library`
(a field of ``FaultMode``); the order of :data:`EVIDENCE_KINDS` is the order a fault's
variables are built in (the posterior sums their log likelihoods in that order).
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, ClassVar, Protocol

from twinwatch.twin.health import HealthMessage, SensorHealth

if TYPE_CHECKING:
    from twinwatch.twin.diagnosis.library import DeviationSign, FaultMode, ScalingSign, TrendSign

__all__ = ["EVIDENCE_KINDS", "LEAK", "S_MIN", "EvidenceKind", "EvidenceSource", "ModelNames",
           "Variable", "clip", "closest", "estimated_parameters", "explains_check",
           "model_check_variable", "reading_variable"]

#: Probability of each kind of evidence variable with no fault in the library (model error, an
#: operating point the twin does not cover): a deviation beyond its size, a degrading trend,
#: a kept term, a failed model check, a stuck sensor, one reading's error explaining a window
#: (a process fault that moves the outputs as a wrong reading would).
LEAK = {"deviation": 0.002, "trend": 0.05, "term": 0.001, "model_check": 0.05,
        "sensor": 0.001, "reading": 0.02, "scaling": 0.01}
#: Strengths are kept in [S_MIN, 1 - S_MIN]: no single reading is certain.
S_MIN = 1e-4


def clip(s: float) -> float:
    """A strength kept in [:data:`S_MIN`, 1 - :data:`S_MIN`]."""
    return min(max(s, S_MIN), 1.0 - S_MIN)


def closest(name: str, known: Sequence[str]) -> str:
    """``did you mean 'omega'? known: ia, omega`` (the closest known name, if any)."""
    close = difflib.get_close_matches(name, list(known), n=1)
    return (f"did you mean {close[0]!r}? " if close else "") + f"known: {', '.join(known)}"


@dataclass
class Variable:
    """One evidence variable: its strength, leak, each fault's link and the words.

    Attributes:
        key: its name, shared by the faults that expect it (``trend:Ra:up``, ``model_check``,
            ``check:Va``, ``sensor:frozen:*``, ``term:0``, ``noterm:<fault>:<j>``).
        kind: its leak's key in :data:`LEAK`.
        s: the soft observation's strength in (0, 1): the probability the evidence is there.
        present, absent: the sentences when it is there and when it is not.
        links: fault id -> the probability that fault shows it (noisy-OR link).
        what: fault id -> what the fault expects, for a person.
        leak: its leak when raised above :data:`LEAK` (None: ``LEAK[kind]``).
        may: faults whose link explains the evidence when present, its absence no evidence
            against them (a check an unbalance may leave failing or passing).
        unexplained: a deviation or trend no library fault expects.
    """

    key: str
    kind: str
    s: float
    present: str
    absent: str
    links: dict[str, float] = field(default_factory=dict)
    what: dict[str, str] = field(default_factory=dict)
    leak: float | None = None
    may: set[str] = field(default_factory=set)
    unexplained: bool = False


@dataclass(frozen=True)
class ModelNames:
    """What a fault library's names are checked against: the machine's model (registry name),
    its parameters and attach points, its channels (empty: not checked), its measured outputs
    (empty: not checked) and the meta-model kinds the registry knows."""

    model: str
    parameters: Sequence[str]
    attach: Sequence[str]
    channels: Sequence[str]
    outputs: Sequence[str]
    kinds: Sequence[str]


class EvidenceSource(Protocol):
    """What a kind's variables read beyond the window's message: the diagnoser's memory (the
    last sound evidence on a parameter, the recent windows' model checks)."""

    def trend_variable(self, health: HealthMessage, key: str, name: str,
                       direction: str) -> Variable:
        """A parameter's trend degrading in ``direction`` (``key``: the variable's name)."""
        ...

    def check_rate_variable(self, output: str) -> Variable:
        """An output failing its model check persistently over the recent windows."""
        ...

    def scaling_variable(self, health: HealthMessage, key: str, name: str,
                         power: float) -> Variable | None:
        """``name``'s deviation scaling as the shaft speed to ``power`` across the recent
        windows (None: not decided yet)."""
        ...

    def recent_sensors(self, health: HealthMessage) -> list[tuple[int, SensorHealth]]:
        """The stuck sensors found in this window or the recent ones, with the window each
        was last found in (a clipping sensor shows only while its reading crosses the
        range; a stuck one stays stuck)."""
        ...


def model_check_variable(health: HealthMessage) -> Variable:
    """The window's model check failing (strength 1 when it failed, 0 when it passed, 0.5
    without a check)."""
    mc = health.model_check
    if mc is None:
        return Variable("model_check", "model_check", 0.5, "", "model check disabled")
    why = "; ".join(mc.reasons) if mc.reasons else ""
    return Variable("model_check", "model_check", clip(0.0 if mc.passed else 1.0),
                    f"the model check failed ({why})" if why else "the model check failed",
                    "the model check passed (the residual is white)")


#: A held value this far from its nameplate [%] carries a change in the window's twin.
CARRIED_PCT = 0.5


def estimated_parameters(health: HealthMessage) -> frozenset[str]:
    """The parameters whose change the window's twin carries, for a sign's ``when_held`` and
    ``when_estimated``: those it estimated, and those it held at a value more than
    :data:`CARRIED_PCT` from the nameplate (the trusted value the twin ran with already has
    the change in; a ``fused`` value is not the twin's). A weakened field estimated once at
    Ke -3.00 % and held there since leaves D at its nameplate: "D up while Ke is held" no
    longer applies (it argued against the weakened field: no fault 0.79)."""
    out = set()
    for n, p in health.parameters.items():
        if p.status == "estimated":
            out.add(n)
        elif (p.status == "held" and p.value is not None and p.nominal
              and abs(p.value / p.nominal - 1.0) * 100.0 > CARRIED_PCT):
            out.add(n)
    return frozenset(out)


def _chan(channel: str) -> str:
    return "a sensor" if channel == "*" else f"the {channel} sensor"


class EvidenceKind:
    """One kind of evidence a fault's signature lists (the base: no names to check, no
    per-fault variable).

    Attributes:
        name: the signature's key in a fault mode (``FaultMode.<name>``).
        variable: the kind of its evidence variables (their leak in :data:`LEAK`).
        prefix: how its variables' keys begin.
        explains_check: its evidence for a fault explains failed model checks (what the twin
            lacks, a sensor it cannot follow), not a twin that no longer fits.
    """

    name: ClassVar[str]
    variable: ClassVar[str]
    prefix: ClassVar[str]
    explains_check: ClassVar[bool] = False

    def present(self, fault: FaultMode) -> bool:
        """Whether ``fault``'s signature lists this kind of evidence."""
        return bool(getattr(fault, self.name))

    def problem(self, fault: FaultMode, names: ModelNames) -> str | None:
        """The first name of ``fault``'s items of this kind the machine does not have, as
        ``names the parameter 'Rx'; the dc_motor model has [...]`` (None: every name
        exists)."""
        return None

    def add_variables(self, source: EvidenceSource, health: HealthMessage, fault: FaultMode,
                      out: dict[str, Variable]) -> None:
        """Add ``fault``'s links to this kind's variables of the window in ``out`` (a variable
        shared by key with the faults before it, created by the first)."""
        return None


def _not_measured(label: str, name: str, where: str, names: ModelNames) -> str | None:
    """``names <label> '<name>'<where>, which the <model> twin does not measure; did you mean
    ...`` when the machine's measured outputs are known and ``name`` is not one (None:
    it is, or they are not known)."""
    if names.outputs and name not in names.outputs:
        return (f"names {label} {name!r}{where}, which the {names.model} twin does not "
                f"measure; {closest(name, names.outputs)}")
    return None


def _unknown_parameter(signs: Sequence[DeviationSign | TrendSign | ScalingSign],
                       names: ModelNames) -> str | None:
    """The first parameter a sign names that the model does not have, as ``names the
    parameter 'Rx'; the dc_motor model has [...]``."""
    for sign in signs:
        if sign.parameter not in names.parameters:
            return (f"names the parameter {sign.parameter!r}; the {names.model} model has "
                    f"{list(names.parameters)}")
    return None


def _unknown_condition(signs: Sequence[DeviationSign | TrendSign], names: ModelNames
                       ) -> str | None:
    """The first parameter a sign's ``when_held``/``when_estimated`` names that the model
    does not have."""
    for sign in signs:
        for name in (*sign.when_held, *sign.when_estimated):
            if name not in names.parameters:
                return (f"names the parameter {name!r} in when_held/when_estimated; the "
                        f"{names.model} model has {list(names.parameters)}")
    return None


class Deviations(EvidenceKind):
    """A parameter beyond ``min_pct`` % of its nameplate (``DeviationSign``); its likelihood is
    graded per parameter over the hypotheses (:mod:`twinwatch.twin.diagnosis.deviation`)."""

    name = "deviations"
    variable = "deviation"
    prefix = "dev:"

    def problem(self, fault: FaultMode, names: ModelNames) -> str | None:
        return (_unknown_parameter(fault.deviations, names)
                or _unknown_condition(fault.deviations, names))


class Trends(EvidenceKind):
    """A parameter's trend degrading ``up`` or ``down`` (``TrendSign``): one variable per
    parameter and direction, its strength from the window's trend."""

    name = "trends"
    variable = "trend"
    prefix = "trend:"

    def problem(self, fault: FaultMode, names: ModelNames) -> str | None:
        return _unknown_parameter(fault.trends, names) or _unknown_condition(fault.trends, names)

    def add_variables(self, source: EvidenceSource, health: HealthMessage, fault: FaultMode,
                      out: dict[str, Variable]) -> None:
        estimated = estimated_parameters(health)
        for t in fault.trends:
            if not t.applies(estimated):
                continue
            key = f"{self.prefix}{t.parameter}:{t.direction}"
            if key not in out:
                out[key] = source.trend_variable(health, key, t.parameter, t.direction)
            out[key].links[fault.id] = t.link
            out[key].what[fault.id] = f"{t.parameter} drifting {t.direction}"


class Terms(EvidenceKind):
    """A discovered meta-model term (``TermSign``): its variables are per discovered term and
    per expected term missing (``Diagnoser._term_vars``, ``_missing_term_vars``)."""

    name = "terms"
    variable = "term"
    prefix = "term:"
    explains_check = True

    def problem(self, fault: FaultMode, names: ModelNames) -> str | None:
        for t in fault.terms:
            for a in t.attach:
                if a != "*" and a not in names.attach:
                    return (f"names the attach point {a!r}; the {names.model} model has "
                            f"{list(names.attach)}")
            for k in t.kinds:
                if k != "*" and k not in names.kinds:
                    return (f"names the meta-model kind {k!r}, which the registry does not "
                            f"know; {closest(k, names.kinds)}")
        return None


class ModelCheck(EvidenceKind):
    """The window's model validation failed (``model_check``: the link)."""

    name = "model_check"
    variable = "model_check"
    prefix = "model_check"
    explains_check = True

    def add_variables(self, source: EvidenceSource, health: HealthMessage, fault: FaultMode,
                      out: dict[str, Variable]) -> None:
        if fault.model_check:
            key = self.prefix
            if key not in out:
                out[key] = model_check_variable(health)
            out[key].links[fault.id] = fault.model_check
            out[key].what[fault.id] = "the model check failing"


class Checks(EvidenceKind):
    """One output's model check failing persistently (``CheckSign``)."""

    name = "checks"
    variable = "model_check"
    prefix = "check:"
    explains_check = True

    def problem(self, fault: FaultMode, names: ModelNames) -> str | None:
        for cs in fault.checks:
            # a channel the twin reads (an output in one structure may be an input in
            # another: Va in closed loop and open loop; a check that is not compared in
            # this configuration never fails, it is not a mistake)
            if names.channels and cs.output not in names.channels:
                return (f"names the output {cs.output!r} in checks, which is not a channel "
                        f"of the {names.model} twin; {closest(cs.output, names.channels)}")
        return None

    def add_variables(self, source: EvidenceSource, health: HealthMessage, fault: FaultMode,
                      out: dict[str, Variable]) -> None:
        for cs in fault.checks:
            key = f"{self.prefix}{cs.output}"
            if key not in out:
                out[key] = source.check_rate_variable(cs.output)
            out[key].links[fault.id] = cs.link
            if cs.may_pass:
                out[key].may.add(fault.id)
            out[key].what[fault.id] = f"{cs.output}'s model check failing in most windows"


class Sensors(EvidenceKind):
    """A frozen or saturated sensor (``SensorSign``): present when the window's quality, or
    that of one of the recent windows (:meth:`EvidenceSource.recent_sensors`), names one of
    the fault's kinds on its channel. A fault's signs are one variable, "any of them": a
    stuck reading is frozen *or* saturated, and the kind it does not show is no evidence
    against it (two variables counted the missing kind against the fault at 1 - link: a
    frozen position reading read ``sensor_fault`` 0.54)."""

    name = "sensors"
    variable = "sensor"
    prefix = "sensor:"
    explains_check = True

    def problem(self, fault: FaultMode, names: ModelNames) -> str | None:
        for ss in fault.sensors:
            if ss.channel != "*" and (why := _not_measured("the sensor channel", ss.channel,
                                                           "", names)):
                return why
        return None

    def add_variables(self, source: EvidenceSource, health: HealthMessage, fault: FaultMode,
                      out: dict[str, Variable]) -> None:
        if not fault.sensors:
            return
        signs = sorted({(ss.kind, ss.channel) for ss in fault.sensors})
        key = self.prefix + "|".join(f"{kind}:{channel}" for kind, channel in signs)
        kinds = " or ".join(dict.fromkeys(kind for kind, _ in signs))
        channels = {channel for _, channel in signs}
        where = _chan(next(iter(channels))) if len(channels) == 1 else "a sensor"
        if key not in out:
            hit = [(w, s) for w, s in source.recent_sensors(health)
                   if any(s.kind == kind and channel in ("*", s.channel)
                          for kind, channel in signs)]
            names = ", ".join(
                f"{s.channel} {s.kind} at {s.value:.4g} for {s.duration_s:.1f} s"
                + ("" if w == health.window else f" (window {w})") for w, s in hit)
            out[key] = Variable(key, self.variable, clip(1.0 if hit else 0.0),
                                names or f"{where} {kinds}",
                                f"no {kinds} sensor in this window or the recent ones")
        link = max(ss.link for ss in fault.sensors)
        out[key].links[fault.id] = max(link, out[key].links.get(fault.id, 0.0))
        out[key].what[fault.id] = f"{where} {kinds}"


#: The healthy twin's nRMSE over the fit's (floored at :data:`READING_FLOOR`) from which a
#: reading check speaks at all, and from which at full strength: below, the window has
#: nothing a reading could explain.
READING_ANOMALY = (1.1, 1.5)
#: A fit's nRMSE below this is read as this (a noise-free fit reaches 1e-6, 2e-4 in the
#: windows of a growing fault; the reading check's ``NRMSE_FLOOR``).
READING_FLOOR = 2e-4
#: A reading explains the window when the healthy twin with it corrected leaves at most this
#: much more mean squared error than the process fit (relative), with this spread: measured
#: on the default motor at 1 % noise, the current reading's gain of 1.1 left 0.001 more,
#: bearing wear read as a speed reading 0.96 x left 0.15 more, a shorted winding with worn
#: bearings read as a current reading 1.11 x left 8 times more.
READING_EXCESS = (0.05, 0.02)


def _phi(z: float) -> float:
    return 0.5 * math.erfc(-z / math.sqrt(2.0))


class Readings(EvidenceKind):
    """One wrong reading on a healthy machine explaining the window (``ReadingSign``; the
    health message's ``readings``, :mod:`twinwatch.twin.estimation.readings`): one variable
    per output and direction, strong when the healthy twin with that reading corrected (its
    gain or its offset, the better) fits as well as the process fit, weak when it leaves
    more; neutral (no variable) while the window has nothing to explain."""

    name = "readings"
    variable = "reading"
    prefix = "reading:"
    explains_check = True

    def problem(self, fault: FaultMode, names: ModelNames) -> str | None:
        for rs in fault.readings:
            if why := _not_measured("the output", rs.output, " in readings", names):
                return why
        return None

    def add_variables(self, source: EvidenceSource, health: HealthMessage, fault: FaultMode,
                      out: dict[str, Variable]) -> None:
        for rs in fault.readings:
            key = f"{self.prefix}{rs.output}:{rs.direction}"
            if key not in out:
                var = reading_variable(health, key, rs.output, rs.direction)
                if var is None:
                    continue
                out[key] = var
            out[key].links[fault.id] = rs.link
            out[key].what[fault.id] = f"the {rs.output} reading too {rs.direction}"


def reading_variable(health: HealthMessage, key: str, output: str, direction: str
                     ) -> Variable | None:
    """The window's evidence that ``output`` reads too ``direction`` on a healthy machine
    (None: no reading check, or nothing to explain)."""
    r = health.readings
    x = r.outputs.get(output) if r is not None else None
    if r is None or x is None or r.nominal_nrmse is None or r.fit_nrmse is None:
        return None
    fit = max(r.fit_nrmse, READING_FLOOR)
    lo, hi = READING_ANOMALY
    weight = min(max((r.nominal_nrmse / fit - lo) / (hi - lo), 0.0), 1.0)
    if weight <= 0.0:
        return None
    cands = []
    if x.gain is not None and x.gain_nrmse is not None:
        cands.append((x.gain_nrmse, "gain", x.gain))
    if x.offset is not None and x.offset_nrmse is not None:
        cands.append((x.offset_nrmse, "offset", x.offset))
    if not cands:
        return None
    best, how, value = min(cands)
    sign = 1.0 if (x.mean or 0.0) >= 0.0 else -1.0
    high = (value > 1.0) if how == "gain" else (value * sign > 0.0)
    excess = (best * best - fit * fit) / (fit * fit)
    mid, sd = READING_EXCESS
    explains = _phi((mid - excess) / sd) if high == (direction == "high") else 0.0
    s = 0.5 + weight * (clip(explains) - 0.5)
    said = (f"{value:.4g} x" if how == "gain" else f"{value:+.4g}") + f" ({how})"
    numbers = (f"the healthy twin with the {output} reading corrected by {said} leaves nRMSE "
               f"{best:.4g} against the fit's {r.fit_nrmse:.4g} (the nameplate twin "
               f"{r.nominal_nrmse:.4g})")
    return Variable(key, "reading", s, f"the {output} reading too {direction} explains the "
                    f"window: {numbers}",
                    f"no {output} reading too {direction} explains the window: {numbers}")


class Scaling(EvidenceKind):
    """A parameter's deviation scaling with the shaft speed across operating points
    (``ScalingSign``): one variable per parameter and power, undecided (none) until the
    windows since the change span enough speeds (``Diagnoser.scaling_variable``)."""

    name = "scaling"
    variable = "scaling"
    prefix = "scaling:"

    def problem(self, fault: FaultMode, names: ModelNames) -> str | None:
        return _unknown_parameter(fault.scaling, names)

    def add_variables(self, source: EvidenceSource, health: HealthMessage, fault: FaultMode,
                      out: dict[str, Variable]) -> None:
        for sg in fault.scaling:
            key = f"{self.prefix}{sg.parameter}:{sg.power:g}"
            if key not in out:
                var = source.scaling_variable(health, key, sg.parameter, sg.power)
                if var is None:
                    continue
                out[key] = var
            out[key].links[fault.id] = sg.link
            # a deviation that does not scale is no evidence against: a term found for the
            # fault takes the change out of the parameter (Coulomb friction's constant term:
            # D back within a few % at every speed)
            out[key].may.add(fault.id)
            out[key].what[fault.id] = (f"{sg.parameter}'s deviation scaling as the shaft "
                                       f"speed to the power {sg.power:g}")


#: The evidence kinds: the signature's key -> its kind. Their order is the order a fault's
#: variables are built in and its names checked.
EVIDENCE_KINDS: dict[str, EvidenceKind] = {
    kind.name: kind for kind in (Deviations(), Trends(), Terms(), ModelCheck(), Checks(),
                                 Sensors(), Readings(), Scaling())}

#: How the keys of the variables that explain failed model checks begin.
_EXPLAINS_CHECK = tuple(k.prefix for k in EVIDENCE_KINDS.values() if k.explains_check)


def explains_check(key: str) -> bool:
    """Whether evidence about ``key`` (a variable's key) explains failed model checks."""
    return key.startswith(_EXPLAINS_CHECK)
