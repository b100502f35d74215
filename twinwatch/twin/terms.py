"""A kept meta-model term of DT'' and the composition of terms into the twin (paper Eq. 3).

DT'' = DT(p, x) + sum_i U_i(z_i): each :class:`Term` is one meta-model (:mod:`.metamodels`) with
fitted parameters, its input (time or a measured channel) and the attach point of the model it
acts on. :func:`compose` sums the terms per attach point into the ``terms`` argument of
:meth:`TwinModel.simulate`.

Inputs are *measured* signals, so the terms do not depend on the simulated state: they are
computed once per particle and the composed twin still simulates a whole swarm in one call. An
additive term's value for sample k is taken at the middle of the step k -> k+1 (the twin holds
it over the step); a multiplicative one at sample k.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from twinwatch.twin.metamodels import MetaModel, get_meta_model
from twinwatch.twin.model import AttachPoint, FloatArray, TwinModel, WindowData

#: The input name of a term of time.
TIME = "t"


@dataclass
class Term:
    """A kept meta-model term of DT''.

    Attributes:
        meta: the meta-model.
        attach: where it attaches.
        input: ``t`` or a channel name.
        params: raw parameters (len(meta.params),) for the input ``z = input - t_ref``
            (``t_ref`` only for time; 0 when the term reads in absolute time).
        active: which parameters are on (switched-off offsets are 0).
        t_ref: time origin of a time input [s].
        significance: main coefficient over its standard error, last window.
        failures: consecutive windows it failed re-validation.
        since_window: window index it was discovered in.
    """

    meta: MetaModel
    attach: AttachPoint
    input: str
    params: FloatArray
    active: tuple[bool, ...]
    t_ref: float = 0.0
    significance: float = math.inf
    failures: int = 0
    since_window: int = 0

    @property
    def weight(self) -> float:
        """The main coefficient (paper: the weight linking the meta-model to the twin)."""
        return float(self.params[self.meta.main_index(self.active)])

    def z(self, window: WindowData) -> FloatArray:
        """The input samples the twin uses (additive: mid-step; multiplicative: at sample)."""
        additive = self.attach.mode == "additive"
        return term_input(window, self.input, self.t_ref, additive)

    def values(self, window: WindowData) -> FloatArray:
        """U(z) at each sample of the window, shape (N,)."""
        return self.meta.evaluate(self.params[None, :], self.z(window))[0]

    def input_text(self, precision: int = 2) -> str:
        if self.input != TIME:
            return self.input
        if self.t_ref == 0:
            return "t"
        return f"(t - {self.t_ref:.{precision}f})"

    def expression(self, precision: int = 2) -> str:
        return self.meta.render(self.params, self.input_text(precision), precision)

    def equation(self, precision: int = 2) -> str:
        """The term as an equation of DT'', e.g.
        ``d(omega)/dt += 4.98*sin(10.00*t + 2.12) rad/s^2``."""
        if self.attach.mode == "additive":
            return f"{self.attach.name} += {self.expression(precision)} {self.attach.unit}"
        return f"{self.attach.name} *= 1 + ({self.expression(precision)})"

    def meaning(self) -> str:
        """Interpretation: the kind and where it acts, with its working conditions
        (:meth:`MetaModel.interpret`)."""
        return self.meta.interpret(self.attach, self.active)

    def describe(self, precision: int = 2) -> str:
        return f"{self.equation(precision)}  [{self.meaning()}]"

    def as_dict(self) -> dict[str, Any]:
        """The health message's ``terms`` entry (README: "The health message")."""
        return {
            "kind": self.meta.kind,
            "attach": self.attach.name,
            "mode": self.attach.mode,
            "input": self.input,
            "t_ref": self.t_ref,
            "params": {n: float(v) for n, v, a in
                       zip(self.meta.params, self.params, self.active, strict=True) if a},
            "weight": self.weight,
            "significance": _finite(self.significance),
            "equation": self.equation(),
            "meaning": self.meaning(),
            "since_window": self.since_window,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], model: TwinModel) -> Term:
        """Rebuild a term from :meth:`as_dict` (persistence)."""
        meta = get_meta_model(d["kind"])
        params = np.array([float(d["params"].get(n, 0.0)) for n in meta.params])
        active = tuple(n in d["params"] for n in meta.params)
        sig = d.get("significance")
        return cls(meta=meta, attach=model.attach_point(d["attach"]), input=d["input"],
                   params=params, active=active, t_ref=float(d.get("t_ref", 0.0)),
                   significance=math.inf if sig is None else float(sig),
                   since_window=int(d.get("since_window", 0)))


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def term_input(window: WindowData, name: str, t_ref: float, additive: bool) -> FloatArray:
    """Input samples of a term, shape (N,): time relative to ``t_ref`` or a channel; for an
    additive term, at the middle of each step (the last sample's step is extrapolated)."""
    if name == TIME:
        z = window.t - t_ref
        if additive:
            z = z + 0.5 * window.sample_period
        return np.asarray(z, dtype=float)
    z = np.asarray(window[name], dtype=float)
    if additive and z.size > 1:
        z = np.concatenate([0.5 * (z[:-1] + z[1:]), z[-1:]])
    return z


def compose(terms: Sequence[Term], window: WindowData) -> dict[str, FloatArray]:
    """Sum the terms per attach point: the ``terms`` argument of ``TwinModel.simulate``."""
    out: dict[str, FloatArray] = {}
    for term in terms:
        v = term.values(window)
        out[term.attach.name] = out.get(term.attach.name, 0.0) + v
    return out


def format_terms(terms: Sequence[Term], precision: int = 2) -> str:
    """DT'' as plain text, one term per line (empty string without terms)."""
    return "\n".join(t.describe(precision) for t in terms)


__all__ = ["TIME", "Term", "compose", "format_terms", "term_input"]
