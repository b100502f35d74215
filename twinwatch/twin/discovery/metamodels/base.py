"""The meta-model contract: one class per kind (paper Section 3.3, Table 1).

A meta-model is a small interpretable function ``U(z)`` of one input ``z`` (time, a measured
input, output or state) that the discovery attaches to the twin when re-estimating the physical
parameters cannot explain the data (DT'' = DT + sum_i U_i(z_i), paper Eq. 3). Each kind knows
its own basis, bounds, rendering, canonical form and search hooks, so the discovery never
branches on a kind: a new meta-model is one subclass in one file, registered in
:mod:`twinwatch.twin.discovery.metamodels` (or through the ``twinwatch.metamodels`` entry points).

Numerics (docs/architecture.md): the search runs in *normalised* coordinates
``u = z / z_ref`` (``z_ref`` the input's largest magnitude over the window, or the window length
for time), so that the same bounds suit every input; :meth:`MetaModel.to_raw` converts the fitted
values back to the input's own units before they are reported or evaluated.

Separable form: every kind is written as linear coefficients times basis functions with at most
one nonlinear parameter (:meth:`MetaModel.basis`). The discovery's swarm searches only the
nonlinear parameters; for each particle the coefficients come from linear least squares.
"""

from __future__ import annotations

import abc
import math
from typing import ClassVar

import numpy as np

from twinwatch.twin.model import AttachPoint, FloatArray, WindowData


def fmt(x: float, precision: int) -> str:
    """A coefficient for an equation: fixed point when readable, else scientific."""
    if x != 0 and (abs(x) >= 1e5 or abs(x) < 10.0 ** -(precision)):
        return f"{x:.{precision}e}"
    return f"{x:.{precision}f}"


def plus(x: float, precision: int) -> str:
    """An addend in fixed point: ``" + 0.00"``, ``" - 1.25"`` (never ``+ 6.5e-07``)."""
    text = f"{abs(x):.{precision}f}"
    return f" - {text}" if x < 0 and float(text) != 0 else f" + {text}"


class MetaModel(abc.ABC):
    """One meta-model kind.

    Class attributes (each subclass sets them):
        kind: the name in configurations and health messages (``periodic``).
        equation: the form as Table 1 prints it (``a*sin(b*z + c) + d``).
        conditions: the working conditions it indicates (Table 1's third column).
        params: parameter names in order; ``params[0]`` is the main coefficient (the term's
            weight in the paper's sense) unless :meth:`main_index` says otherwise.
        optional: parameters the discovery may switch off (fixed at zero) when they do not
            earn their place (offsets, a linear slope).
        positive_input: the input must be > 0 over the window (power, logarithm).
        nonlinear: parameters the term is nonlinear in; the others are the linear
            coefficients of :meth:`basis`.
        simplifies_to_constant: once its nonlinear parameter has gone to the neutral value
            (a base of 1, a rate or an exponent of 0), the kept term is re-tested as a
            constant (discovery's re-validation).
    """

    kind: ClassVar[str]
    equation: ClassVar[str]
    conditions: ClassVar[str]
    params: ClassVar[tuple[str, ...]]
    optional: ClassVar[tuple[str, ...]] = ()
    positive_input: ClassVar[bool] = False
    nonlinear: ClassVar[tuple[str, ...]] = ()
    simplifies_to_constant: ClassVar[bool] = False

    # -- identity -------------------------------------------------------------------------
    @property
    def meaning(self) -> str:
        """The working conditions (paper Table 1)."""
        return self.conditions

    def main_index(self, active: tuple[bool, ...] | None = None) -> int:
        """Index of the main coefficient (the term's weight) among :attr:`params`."""
        return 0

    def interpret(self, attach: AttachPoint, active: tuple[bool, ...]) -> str:
        """The term's interpretation: the kind, where it acts, Table 1's working conditions."""
        return f"{self.kind.replace('_', ' ')} on {attach.quantity}: {self.meaning}"

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"

    # -- evaluation -----------------------------------------------------------------------
    @abc.abstractmethod
    def evaluate(self, p: FloatArray, z: FloatArray) -> FloatArray:
        """Evaluate ``U(z)`` for a swarm.

        Args:
            p: parameters, shape (P, len(params)), in :attr:`params` order.
            z: input samples, shape (N,).

        Returns:
            Shape (P, N). Overflow or an input outside the domain gives inf/nan (never
            raises): the caller scores it as a bad particle.
        """

    # -- separable form: U = sum_j coef_j * basis_j(u; nonlinear) ---------------------------
    @property
    def columns(self) -> tuple[str, ...]:
        """Names of the basis functions' linear coefficients."""
        return tuple(p for p in self.params if p not in self.nonlinear)

    @abc.abstractmethod
    def basis(self, nl: FloatArray, u: FloatArray) -> FloatArray:
        """Basis functions for a swarm of nonlinear parameters.

        Args:
            nl: shape (P, len(nonlinear)).
            u: input, shape (N,).

        Returns:
            Shape (P, len(columns), N).
        """

    def from_separable(self, nl: FloatArray, coef: FloatArray) -> FloatArray:
        """Parameters (len(params),) from nonlinear values and basis coefficients."""
        out = np.zeros(len(self.params))
        it = iter(coef)
        jt = iter(nl)
        for k, name in enumerate(self.params):
            out[k] = next(jt) if name in self.nonlinear else next(it)
        return out

    def column_of(self, param: str) -> int:
        """Basis column an optional parameter switches."""
        return self.columns.index(param)

    def active_from_mask(self, mask: FloatArray) -> tuple[bool, ...]:
        """Parameters switched on by a basis-column mask (nonlinear ones are always on)."""
        on = dict(zip(self.columns, (bool(x) for x in mask), strict=True))
        return tuple(on.get(n, True) for n in self.params)

    # -- search space (normalised input u = z / z_ref) ------------------------------------
    def bounds(self, amplitude: float, *, b_range: tuple[float, float] | None = None
               ) -> tuple[FloatArray, FloatArray]:
        """Search bounds in normalised coordinates (default: every parameter within
        +-``amplitude``).

        Args:
            amplitude: the largest plausible magnitude of the term, in the attach point's
                unit (bounds the main coefficient and offsets).
            b_range: the nonlinear parameter's range where the window decides it
                (:meth:`search_range`).

        Returns:
            (lower, upper), each of shape (len(params),).
        """
        a = float(amplitude)
        return np.full(len(self.params), -a), np.full(len(self.params), a)

    def nonlinear_bounds(self, b_range: tuple[float, float] | None = None
                         ) -> tuple[FloatArray, FloatArray]:
        """Search bounds of the nonlinear parameters (normalised coordinates)."""
        lo, hi = self.bounds(1.0, b_range=b_range)
        idx = [self.params.index(n) for n in self.nonlinear]
        return lo[idx], hi[idx]

    def polish_bounds(self, lo: FloatArray, hi: FloatArray, amplitude: float
                      ) -> tuple[FloatArray, FloatArray]:
        """Bounds for the final least-squares polish: linear coefficients within +-10
        amplitudes, nonlinear ones within their search bounds."""
        lo, hi = lo.copy(), hi.copy()
        for k, n in enumerate(self.params):
            if n not in self.nonlinear:
                lo[k], hi[k] = -10 * amplitude, 10 * amplitude
        return lo, hi

    def search_range(self, window: WindowData, input_is_time: bool, z_ref: float
                     ) -> tuple[float, float] | None:
        """The nonlinear parameter's range this window can resolve (normalised), or None for
        the kind's fixed bounds."""
        return None

    def data_range(self, u: FloatArray) -> tuple[float, float] | None:
        """The nonlinear parameter's range the input samples ``u`` (normalised, (N,)) decide,
        overriding :meth:`search_range`; None: no such constraint. A knee or a threshold must
        lie inside the data with samples on both sides, else the term is a line or a constant
        that a simpler kind states better."""
        return None

    def identifiable(self, u: FloatArray) -> bool:
        """Whether this window's input (normalised, (N,)) can tell the kind from a simpler one
        (a sign of a speed that never changes sign is a constant); the discovery skips the
        candidate otherwise."""
        return True

    def seeds(self, residual: FloatArray, window: WindowData, input_is_time: bool,
              z_ref: float, count: int) -> list[FloatArray]:
        """Nonlinear-parameter seeds (normalised) read off the residual (N, n_out); none by
        default."""
        return []

    def time_origin(self, window: WindowData) -> float:
        """Origin of a time input during the search [s]: the window's start (a term of
        ``t - t0`` is well conditioned), or 0 for kinds that need ``t > 0`` as such."""
        return 0.0 if self.positive_input else float(window.t[0])

    # -- units and equivalent forms -------------------------------------------------------
    #: How each parameter scales with the input's unit: the raw parameter i is the normalised
    #: one times ``z_ref ** z_powers[i]`` (a slope per unit of z: -1; a knee, a band or a
    #: scale in z's unit: +1; an amplitude or offset: 0). Empty: every parameter as it is.
    #: Kinds whose parameters do not scale as a power (exponential, logarithmic, power)
    #: override :meth:`to_raw` and :meth:`from_raw` instead.
    z_powers: tuple[int, ...] = ()

    def to_raw(self, p: FloatArray, z_ref: float) -> FloatArray:
        """Normalised-coordinate parameters (input ``z/z_ref``) -> raw ones (input ``z``).
        Shape (..., len(params)) in and out; by :attr:`z_powers`."""
        q = np.array(p, dtype=float, copy=True)
        for i, k in enumerate(self.z_powers):
            if k > 0:
                q[..., i] = q[..., i] * z_ref**k
            elif k < 0:
                q[..., i] = q[..., i] / z_ref**-k
        return q

    def from_raw(self, p: FloatArray, z_ref: float) -> FloatArray:
        """Inverse of :meth:`to_raw`."""
        q = np.array(p, dtype=float, copy=True)
        for i, k in enumerate(self.z_powers):
            if k > 0:
                q[..., i] = q[..., i] / z_ref**k
            elif k < 0:
                q[..., i] = q[..., i] * z_ref**-k
        return q

    def canonical(self, p: FloatArray) -> FloatArray:
        """One representative of equivalent parameter sets (raw, (len(params),))."""
        return np.array(p, dtype=float, copy=True)

    def shift_origin(self, p: FloatArray, t_ref: float) -> tuple[FloatArray, float]:
        """Rewrite a time term ``U(t - t_ref)`` as ``U'(t - t_ref')`` with the simplest
        ``t_ref'`` the kind allows (0: the term reads in absolute time).

        Returns:
            (parameters, new t_ref).
        """
        return np.array(p, dtype=float, copy=True), t_ref

    def move_origin(self, p: FloatArray, d: float) -> FloatArray | None:
        """The same function of time written from an origin ``d`` later: ``q`` with
        ``U_q(z - d) = U_p(z)`` for every z (raw parameters (len(params),), no wrapping), or
        None if the kind cannot be rewritten so (:mod:`~twinwatch.twin.discovery.terms` refines
        a time term at each window's centre)."""
        return None

    def align(self, p: FloatArray, ref: FloatArray) -> FloatArray:
        """``p`` (raw, canonical) in the equivalent form nearest to ``ref`` (a periodic term's
        phase unwrapped to within pi of ``ref``'s), so estimates can be averaged."""
        return np.array(p, dtype=float, copy=True)

    # -- rendering ------------------------------------------------------------------------
    @abc.abstractmethod
    def render(self, p: FloatArray, z: str, precision: int = 2) -> str:
        """The term as text with its fitted values, e.g. ``4.98*sin(10.00*t + 2.12)``.

        Args:
            p: raw parameters (len(params),).
            z: the input as it should read (``t``, ``omega``, ``(t - 160.00)``).
            precision: decimals.
        """


class ScaledShape(MetaModel):
    """A kind ``U(z) = a*g(z, b)``: one linear coefficient ``a`` times a shape ``g`` of the
    input with one nonlinear parameter ``b`` (exponential, negative exponential, power,
    saturation, dead zone). A subclass states :meth:`shape`; the evaluation and the separable
    basis (one column) follow from it.
    """

    params = ("a", "b")
    nonlinear = ("b",)
    #: The range of ``b`` the search keeps to where the window does not decide it (normalised).
    b_bounds: ClassVar[tuple[float, float]]

    def bounds(self, amplitude: float, *, b_range: tuple[float, float] | None = None
               ) -> tuple[FloatArray, FloatArray]:
        """``|a|`` up to the amplitude, ``b`` in ``b_range`` or :attr:`b_bounds`."""
        a = float(amplitude)
        b_lo, b_hi = b_range or self.b_bounds
        return np.array([-a, b_lo]), np.array([a, b_hi])

    @staticmethod
    @abc.abstractmethod
    def shape(z: FloatArray, b: FloatArray) -> FloatArray:
        """The shape ``g(z, b)``, broadcasting ``z`` of shape (1, N) against ``b`` of shape
        (P, 1) to (P, N); an input outside its domain or an overflow gives inf/nan (it is
        called with floating-point errors ignored)."""

    def evaluate(self, p: FloatArray, z: FloatArray) -> FloatArray:
        p = np.atleast_2d(np.asarray(p, dtype=float))
        z = np.asarray(z, dtype=float)[None, :]
        with np.errstate(all="ignore"):
            return p[:, 0, None] * self.shape(z, p[:, 1, None])

    def basis(self, nl: FloatArray, u: FloatArray) -> FloatArray:
        nl = np.atleast_2d(np.asarray(nl, dtype=float))
        u = np.asarray(u, dtype=float)[None, :]
        with np.errstate(all="ignore"):
            return self.shape(u, nl[:, :1])[:, None, :]


def wrap_phase(c: float) -> float:
    """An angle in (-pi, pi]."""
    return math.remainder(c, 2 * math.pi)
