"""The last step: what the window publishes for every parameter, and with which status.

* ``estimated``: the gate admitted it (this window determines it) and the window is sound (its
  model check passed, no sensor is frozen or saturated);
* ``fused``: no window alone determines it (or this one is not sound), but the fused evidence
  of the windows so far does, to ``[estimation.fusion] max_rel_std`` (the fusion's own gate,
  apart from the window's): the fused value and its standard error are published;
* ``suspect``: not to be used as a value of the machine, with the reason: the window's
  estimate of a window that is not sound (a failed model check, a frozen or saturated sensor),
  or a held value that the fused evidence contradicts (more than :data:`CONTRADICTION`
  standard errors away from it); alarms and programs treat it like ``held``;
* ``held``: the last trusted value, nothing contradicting it;
* ``tied``: equal to another parameter (Kt = Ke); ``fixed``: not estimated (the nameplate).

A fused value is published, never trusted: the twin keeps holding the last value a window
determined (a held value's error propagates: D = Ke*ia/omega - c amplifies Ke's).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

from twinwatch.twin.estimation.fit import ParameterMap
from twinwatch.twin.estimation.gate import GateDecision
from twinwatch.twin.model import FloatArray

#: What a published parameter value is: see :attr:`Published.status`.
ParameterStatus = Literal["estimated", "fused", "suspect", "held", "tied", "fixed"]

#: A held value further than this many standard errors from the fused evidence is contradicted.
CONTRADICTION = 3.0


@dataclass
class Published:
    """The window's published parameters.

    Attributes:
        values: every model parameter -> published value [SI].
        estimated: parameters the window determined -> their values [SI] (``suspect`` ones
            included: the window's estimates).
        held: parameter -> why it is not this window's sound estimate (held, fused, suspect,
            tied, fixed).
        rel_std: parameter -> relative standard error (1-sigma, fraction) of the published
            value (this window's estimate, or the fused value).
        status: every model parameter -> its :data:`ParameterStatus`.
    """

    values: dict[str, float]
    estimated: dict[str, float]
    held: dict[str, str]
    rel_std: dict[str, float]
    status: dict[str, ParameterStatus]


def publish(theta: FloatArray, pmap: ParameterMap, tie: Mapping[str, str],
            decision: GateDecision, fused: Mapping[str, tuple[float, float]],
            fused_max_rel_std: float, *, suspect: str | None = None,
            held_std: Mapping[str, float] | None = None) -> Published:
    """The published parameters of one window.

    Args:
        theta: the final twin's parameter vector (1, n_params) [SI].
        pmap: the estimated parameters (in priority order) and the ties.
        tie: dependent parameter -> the parameter it equals (``[estimation] tie``).
        decision: the gate's final decision.
        fused: estimated parameter -> (fused value [SI], relative standard error); empty when
            fusion is off.
        fused_max_rel_std: largest relative standard error of a published fused value
            (``[estimation.fusion] max_rel_std``).
        suspect: why the window is not sound (a failed model check, a sensor fault), or None.
        held_std: parameter -> relative standard error of its trusted (held) value (0 or
            absent: exact), for the contradiction test.

    Returns:
        Values, statuses, reasons and standard errors.
    """
    names: Sequence[str] = pmap.names
    estimate = pmap.estimate
    values = dict(zip(names, (float(v) for v in theta[0]), strict=True))
    held = dict(decision.held)
    for n in names:
        if n in tie:
            held.setdefault(n, f"tied to {tie[n]}")
        elif n not in estimate:
            held.setdefault(n, "fixed (nameplate)")
    estimated = {estimate[k]: values[estimate[k]] for k in decision.selected}
    rel_std = {estimate[k]: float(v) for k, v in decision.rel_std.items()
               if k in decision.selected}
    status: dict[str, ParameterStatus] = {}
    hs = held_std or {}
    for n in names:
        if n in tie:
            status[n] = "tied"
            continue
        if n not in estimate:
            status[n] = "fixed"
            continue
        f_val, f_std = fused.get(n, (math.nan, math.inf))
        precise = f_std <= fused_max_rel_std
        if n in estimated and suspect is None:
            status[n] = "estimated"
        elif precise:  # held[n] keeps why this window alone could not
            status[n] = "fused"
            if n in estimated:
                held[n] = f"{suspect}: the fused value is published"
            values[n], rel_std[n] = f_val, f_std
        elif n in estimated:
            status[n] = "suspect"
            held[n] = f"suspect: {suspect}"
        else:
            status[n] = "held"
            z = _contradiction(values[n], f_val, f_std, hs.get(n, 0.0))
            if z > CONTRADICTION:
                status[n] = "suspect"
                held[n] = (f"suspect: held at its last trusted value, which the fused evidence "
                           f"({f_val:.6g} +- {f_std * 100:.2g} %, 1 sigma) contradicts "
                           f"({z:.1f} standard errors)")
    for dep, src in pmap.ties:
        values[names[dep]] = values[names[src]]
    return Published(values, estimated, held, rel_std, status)


def _contradiction(held: float, fused: float, fused_std: float, held_std: float) -> float:
    """How many standard errors the held value is from the fused one (0 without evidence)."""
    if not (math.isfinite(fused) and fused > 0 and held > 0 and math.isfinite(fused_std)):
        return 0.0
    sd = math.hypot(fused_std, held_std)
    return abs(math.log(held / fused)) / sd if sd > 0 else 0.0
