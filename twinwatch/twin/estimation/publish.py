"""The last step: what the window publishes for every parameter, and with which status.

A parameter is ``estimated`` when the gate admitted it (this window determines it), ``fused``
when no window alone determines it but the fused evidence of the windows so far does (relative
standard error at most ``max_rel_std``: the fused value is published), ``held`` otherwise (the
last trusted value), ``tied`` when it equals another parameter (Kt = Ke) and ``fixed`` when it is
not estimated (the nameplate). A fused value is published, never trusted: the twin keeps
holding the last value a window determined (a fused Ke 1.5 % off, well within its 0.9 %
interval, biased D by 8 % through D = Ke*ia/omega - c when it was held at it).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

from twinwatch.twin.estimation.fit import ParameterMap
from twinwatch.twin.estimation.gate import GateDecision
from twinwatch.twin.model import FloatArray

#: What a published parameter value is: see :attr:`Published.status`.
ParameterStatus = Literal["estimated", "fused", "held", "tied", "fixed"]


@dataclass
class Published:
    """The window's published parameters.

    Attributes:
        values: every model parameter -> published value [SI].
        estimated: parameters the window determined -> their values [SI].
        held: parameter -> why it is not this window's estimate (held, fused, tied, fixed).
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
            max_rel_std: float) -> Published:
    """The published parameters of one window.

    Args:
        theta: the final twin's parameter vector (1, n_params) [SI].
        pmap: the estimated parameters (in priority order) and the ties.
        tie: dependent parameter -> the parameter it equals (``[estimation] tie``).
        decision: the gate's final decision.
        fused: estimated parameter -> (fused value [SI], relative standard error); empty when
            fusion is off.
        max_rel_std: largest relative standard error of a published estimate or fused value.

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
    for n in names:
        status[n] = _status(n, estimated, tie, estimate, fused, max_rel_std)
        if status[n] == "fused":  # held[n] keeps why this window alone could not
            values[n], rel_std[n] = fused[n]
    for dep, src in pmap.ties:
        values[names[dep]] = values[names[src]]
    return Published(values, estimated, held, rel_std, status)


def _status(name: str, estimated: Mapping[str, float], tie: Mapping[str, str],
            estimate: Sequence[str], fused: Mapping[str, tuple[float, float]],
            max_rel_std: float) -> ParameterStatus:
    if name in estimated:
        return "estimated"
    if name in tie:
        return "tied"
    if name not in estimate:
        return "fixed"
    if name in fused and fused[name][1] <= max_rel_std:
        return "fused"
    return "held"
