"""The meta-model library (paper Section 3.3, Table 1).

A meta-model is a small interpretable function ``U(z)`` of one input ``z`` (time, a measured
input, output or state) that the discovery step attaches to the twin when parameter
re-estimation alone cannot explain the data (DT'' = DT + sum_i U_i(z_i), paper Eq. 3).

=====================  ======================  ===================================================
kind                   U(z)                    working conditions (paper Table 1)
=====================  ======================  ===================================================
``linear``             m*z + b                 friction, misalignment, backlash
``exponential``        a*b^z                   current leaking, deterioration, wear and tear,
                                               corrosion
``negative_exponential`` a*exp(-b*z)           ageing, degradation, fatigue, crack growth
``power``              a*z^b                   hard stops, overloading, mechanical shock
``logarithmic``        a*ln(z) + b             saturation, memory effects, hysteresis
``periodic``           a*sin(b*z + c) + d      unbalanced shaft, shaft misalignment, machine
                                               unsteadiness
=====================  ======================  ===================================================

The first parameter of every kind is its *main coefficient* (its weight in the paper's sense:
``m`` for the linear model, ``a`` for the others; ``b`` for a linear term whose slope was
switched off, i.e. a constant): the term vanishes when it is zero, and its significance decides
whether the term earns its place.

Numerics (our choice, documented in docs/architecture.md): the search runs in *normalised*
coordinates ``u = z / z_ref`` (``z_ref`` the input's largest magnitude over the discovery
window, or the window length for time), so that the same bounds suit every input; the fitted
values are converted back to the input's own units (:meth:`MetaModel.to_raw`) before they are
reported or evaluated. Offsets (``b`` of the linear and logarithmic models, ``d`` of the
periodic one) and the linear slope are *optional*: the discovery also tries the form without
them and keeps the simpler one unless the offset earns its place.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from twinwatch.twin.model import FloatArray

#: Working conditions of each kind (paper Table 1), for the interpretation.
WORKING_CONDITIONS: dict[str, str] = {
    "linear": "friction, misalignment, backlash",
    "exponential": "current leaking, deterioration, wear and tear, corrosion",
    "negative_exponential": "ageing, degradation, fatigue, crack growth",
    "power": "hard stops, overloading, mechanical shock",
    "logarithmic": "saturation, memory effects, hysteresis",
    "periodic": "unbalanced shaft, shaft misalignment, machine unsteadiness",
}


def _fmt(x: float, precision: int) -> str:
    """A coefficient for an equation: fixed point when readable, else scientific."""
    if x != 0 and (abs(x) >= 1e5 or abs(x) < 10.0 ** -(precision)):
        return f"{x:.{precision}e}"
    return f"{x:.{precision}f}"


@dataclass(frozen=True)
class MetaModel:
    """One meta-model kind of Table 1.

    Attributes:
        kind: ``linear``, ``exponential``, ``negative_exponential``, ``power``,
            ``logarithmic`` or ``periodic``.
        params: parameter names in order; ``params[0]`` is the main coefficient.
        optional: parameters the discovery may fix at zero (offsets).
        positive_input: the input must be > 0 over the window (power, logarithmic).
        nonlinear: parameters the term is nonlinear in; the others are linear coefficients
            of basis functions (:meth:`basis`), which the search solves for by least squares
            (separable least squares: the swarm searches only the nonlinear ones).
    """

    kind: str
    params: tuple[str, ...]
    optional: tuple[str, ...] = ()
    positive_input: bool = False
    nonlinear: tuple[str, ...] = ()

    def main_index(self, active: tuple[bool, ...] | None = None) -> int:
        """Index of the main coefficient (the term's weight): the first parameter, or for a
        linear term without slope (``m`` switched off) its constant ``b``."""
        if active is not None and self.kind == "linear" and not active[0]:
            return 1
        return 0

    @property
    def meaning(self) -> str:
        return WORKING_CONDITIONS[self.kind]

    # -- evaluation -----------------------------------------------------------------------
    def evaluate(self, p: FloatArray, z: FloatArray) -> FloatArray:
        """Evaluate ``U(z)`` for a swarm.

        Args:
            p: parameters, shape (P, len(params)), in :attr:`params` order.
            z: input samples, shape (N,).

        Returns:
            Shape (P, N). Overflow gives inf/nan (never raises): the caller scores it as a bad
            particle.
        """
        p = np.atleast_2d(np.asarray(p, dtype=float))
        z = np.asarray(z, dtype=float)[None, :]
        c = [p[:, k, None] for k in range(p.shape[1])]
        with np.errstate(all="ignore"):
            if self.kind == "linear":
                return c[0] * z + c[1]
            if self.kind == "exponential":
                return c[0] * np.exp(z * np.log(np.abs(c[1])))
            if self.kind == "negative_exponential":
                return c[0] * np.exp(-c[1] * z)
            if self.kind == "power":
                return c[0] * np.where(z > 0, z, np.nan) ** c[1]
            if self.kind == "logarithmic":
                return c[0] * np.log(np.where(z > 0, z, np.nan)) + c[1]
            if self.kind == "periodic":
                return c[0] * np.sin(c[1] * z + c[2]) + c[3]
        raise ValueError(f"unknown meta-model kind {self.kind!r}")  # pragma: no cover

    # -- separable form: U = sum_j coef_j * basis_j(u; nonlinear) ----------------------------
    @property
    def columns(self) -> tuple[str, ...]:
        """The basis functions' linear coefficients, by the parameter they become (periodic:
        ``alpha`` and ``beta`` of ``alpha*sin(b u) + beta*cos(b u)``, then ``d``)."""
        if self.kind == "periodic":
            return ("alpha", "beta", "d")
        return tuple(p for p in self.params if p not in self.nonlinear)

    def basis(self, nl: FloatArray, u: FloatArray) -> FloatArray:
        """Basis functions for a swarm of nonlinear parameters.

        Args:
            nl: shape (P, len(nonlinear)).
            u: input, shape (N,).

        Returns:
            Shape (P, len(columns), N).
        """
        nl = np.atleast_2d(np.asarray(nl, dtype=float))
        p = nl.shape[0]
        u = np.asarray(u, dtype=float)[None, :]
        one = np.ones((p, u.shape[1]))
        with np.errstate(all="ignore"):
            if self.kind == "linear":
                cols = [np.repeat(u, p, axis=0), one]
            elif self.kind == "logarithmic":
                cols = [np.repeat(np.log(np.where(u > 0, u, np.nan)), p, axis=0), one]
            elif self.kind == "exponential":
                cols = [np.exp(u * np.log(np.abs(nl[:, :1])))]
            elif self.kind == "negative_exponential":
                cols = [np.exp(-nl[:, :1] * u)]
            elif self.kind == "power":
                cols = [np.where(u > 0, u, np.nan) ** nl[:, :1]]
            else:
                cols = [np.sin(nl[:, :1] * u), np.cos(nl[:, :1] * u), one]
        return np.stack(cols, axis=1)

    def from_separable(self, nl: FloatArray, coef: FloatArray) -> FloatArray:
        """Parameters (len(params),) from nonlinear values and basis coefficients."""
        if self.kind == "periodic":
            alpha, beta, d = coef
            return np.array([math.hypot(alpha, beta), nl[0], math.atan2(beta, alpha), d])
        out = np.zeros(len(self.params))
        it = iter(coef)
        jt = iter(nl)
        for k, name in enumerate(self.params):
            out[k] = next(jt) if name in self.nonlinear else next(it)
        return out

    def column_of(self, param: str) -> int:
        """Basis column an optional parameter switches."""
        return self.columns.index(param)

    def nonlinear_bounds(self, b_range: tuple[float, float] | None = None
                         ) -> tuple[FloatArray, FloatArray]:
        """Search bounds of the nonlinear parameters (normalised coordinates)."""
        lo, hi = self.bounds(1.0, b_range=b_range)
        idx = [self.params.index(n) for n in self.nonlinear]
        return lo[idx], hi[idx]

    # -- search space (normalised input u = z / z_ref) ------------------------------------
    def bounds(self, amplitude: float, *, b_range: tuple[float, float] | None = None
               ) -> tuple[FloatArray, FloatArray]:
        """Search bounds in normalised coordinates.

        Args:
            amplitude: the largest plausible magnitude of the term, in the attach point's
                unit (bounds the main coefficient and offsets).
            b_range: for ``periodic``, the normalised angular frequency range
                (rad per ``z_ref``); defaults to one to 50 periods per ``z_ref``.

        Returns:
            (lower, upper), each of shape (len(params),).
        """
        A = float(amplitude)
        if self.kind == "linear":
            lo, hi = [-A, -A], [A, A]
        elif self.kind == "exponential":
            lo, hi = [-A, math.exp(-3.0)], [A, math.exp(3.0)]
        elif self.kind == "negative_exponential":
            lo, hi = [-A, 0.0], [A, 5.0]
        elif self.kind == "power":
            lo, hi = [-A, 0.0], [A, 3.0]
        elif self.kind == "logarithmic":
            lo, hi = [-A, -A], [A, A]
        else:  # periodic: a >= 0 (the sign is the phase's), c in [-pi, pi]
            b_lo, b_hi = b_range or (2 * math.pi, 100 * math.pi)
            lo, hi = [0.0, b_lo, -math.pi, -A], [A, b_hi, math.pi, A]
        return np.array(lo, dtype=float), np.array(hi, dtype=float)

    def to_raw(self, p: FloatArray, z_ref: float) -> FloatArray:
        """Convert normalised-coordinate parameters (input ``z/z_ref``) to raw ones (input
        ``z``). Shape (..., len(params)) in and out."""
        q = np.array(p, dtype=float, copy=True)
        if self.kind == "linear":
            q[..., 0] = q[..., 0] / z_ref
        elif self.kind == "exponential":
            q[..., 1] = np.abs(q[..., 1]) ** (1.0 / z_ref)
        elif self.kind in ("negative_exponential", "periodic"):
            q[..., 1] = q[..., 1] / z_ref
        elif self.kind == "power":
            q[..., 0] = q[..., 0] / z_ref ** q[..., 1]
        elif self.kind == "logarithmic":
            q[..., 1] = q[..., 1] - q[..., 0] * math.log(z_ref)
        return q

    def from_raw(self, p: FloatArray, z_ref: float) -> FloatArray:
        """Inverse of :meth:`to_raw`."""
        q = np.array(p, dtype=float, copy=True)
        if self.kind == "linear":
            q[..., 0] = q[..., 0] * z_ref
        elif self.kind == "exponential":
            q[..., 1] = np.abs(q[..., 1]) ** z_ref
        elif self.kind in ("negative_exponential", "periodic"):
            q[..., 1] = q[..., 1] * z_ref
        elif self.kind == "power":
            q[..., 0] = q[..., 0] * z_ref ** q[..., 1]
        elif self.kind == "logarithmic":
            q[..., 1] = q[..., 1] + q[..., 0] * math.log(z_ref)
        return q

    def canonical(self, p: FloatArray) -> FloatArray:
        """One representative of equivalent parameter sets: periodic ``a >= 0``, ``b > 0``
        and ``c`` in (-pi, pi] (``a sin(bz + c) = -a sin(bz + c + pi) = a sin(-bz - c + pi)``)."""
        q = np.array(p, dtype=float, copy=True)
        if self.kind == "periodic":
            if q[1] < 0:
                q[1], q[2] = -q[1], math.pi - q[2]
            if q[0] < 0:
                q[0], q[2] = -q[0], q[2] + math.pi
            q[2] = math.remainder(q[2], 2 * math.pi)
        return q

    def shift_origin(self, p: FloatArray, t_ref: float) -> tuple[FloatArray, float]:
        """Rewrite a time term ``U(t - t_ref)`` as ``U'(t - t_ref')`` with the simplest
        ``t_ref'`` the kind allows (0 for linear and periodic: the term reads in absolute time).

        Returns:
            (parameters, new t_ref).
        """
        q = np.array(p, dtype=float, copy=True)
        if self.kind == "periodic":
            q[2] = math.remainder(q[2] - q[1] * t_ref, 2 * math.pi)
            return q, 0.0
        if self.kind == "linear":
            q[1] = q[1] - q[0] * t_ref
            return q, 0.0
        return q, t_ref

    # -- rendering ------------------------------------------------------------------------
    def render(self, p: FloatArray, z: str, precision: int = 2) -> str:
        """The term as text with its fitted values, e.g. ``4.98*sin(10.00*t + 2.12)``.

        Args:
            p: raw parameters (len(params),).
            z: the input as it should read (``t``, ``omega``, ``(t - 160.00)``).
            precision: decimals.
        """
        f = lambda x: _fmt(float(x), precision)  # noqa: E731

        def plus(x: float) -> str:  # an addend reads in fixed point: "+ 0.00", not "+ 6.5e-07"
            text = f"{abs(x):.{precision}f}"
            return f" - {text}" if x < 0 and float(text) != 0 else f" + {text}"

        if self.kind == "linear":
            if p[0] == 0:
                return f(p[1])
            out = f"{f(p[0])}*{z}"
            return out + plus(p[1]) if p[1] != 0 else out
        if self.kind == "exponential":
            return f"{f(p[0])}*{_fmt(float(p[1]), max(precision, 4))}^{z}"
        if self.kind == "negative_exponential":
            return f"{f(p[0])}*exp(-{_fmt(float(p[1]), max(precision, 4))}*{z})"
        if self.kind == "power":
            return f"{f(p[0])}*{z}^{f(p[1])}"
        if self.kind == "logarithmic":
            out = f"{f(p[0])}*ln({z})"
            return out + plus(p[1]) if p[1] != 0 else out
        out = f"{f(p[0])}*sin({f(p[1])}*{z}{plus(p[2])})"
        return out + plus(p[3]) if p[3] != 0 else out


#: The library, by kind (paper Table 1).
META_MODELS: dict[str, MetaModel] = {
    m.kind: m
    for m in (
        MetaModel("linear", ("m", "b"), optional=("m", "b")),
        MetaModel("exponential", ("a", "b"), nonlinear=("b",)),
        MetaModel("negative_exponential", ("a", "b"), nonlinear=("b",)),
        MetaModel("power", ("a", "b"), positive_input=True, nonlinear=("b",)),
        MetaModel("logarithmic", ("a", "b"), optional=("b",), positive_input=True),
        MetaModel("periodic", ("a", "b", "c", "d"), optional=("d",), nonlinear=("b",)),
    )
}


def get_meta_model(kind: str) -> MetaModel:
    """The meta-model of a kind; raises ValueError listing the kinds for an unknown one."""
    try:
        return META_MODELS[kind]
    except KeyError:
        raise ValueError(f"unknown meta-model {kind!r}; choose from {sorted(META_MODELS)}"
                         ) from None
