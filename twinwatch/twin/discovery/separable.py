"""One candidate meta-model on one window, as a separable least-squares problem.

Paper Section 3.3 fits every meta-model's parameters by PSO. Written as linear coefficients
times basis functions with at most one nonlinear parameter (:meth:`MetaModel.basis`: a periodic
term is ``alpha*sin(b z) + beta*cos(b z) + d``), a candidate needs a search over the nonlinear
parameter only: for each value the coefficients come from linear least squares on the twin's
response to each basis function (variable projection; Golub and Pereyra, SIAM J. Numer. Anal.
10(2), 1973), one batched twin call for all of them, exact for the linear DC motor twin and a
linearisation otherwise. :class:`CandidateInput` is the candidate's input normalised for that
search; :class:`SeparableFit` is the problem the discovery's PSO and polish solve.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from twinwatch.twin.discovery.metamodels import MetaModel
from twinwatch.twin.discovery.terms import TIME, term_input
from twinwatch.twin.model import FloatArray, WindowData

#: The twin's normalised residuals (P, M) with the given term values per attach point.
Residuals = Callable[[Mapping[str, FloatArray]], FloatArray]


@dataclass
class CandidateInput:
    """A candidate's input on a window, normalised for the search.

    Attributes:
        u: the input over its reference, ``z / z_ref`` (N,): the search works on it, so the
            bounds do not depend on the input's unit (:attr:`MetaModel.z_powers`).
        z_ref: the reference [input unit]: the largest |z|, or a time term's window length [s].
        t_ref: a time term's origin [s] (0 for a channel).
        is_time: the input is time.
        b_range: the range of the nonlinear parameter the data allow (a knee or band inside
            the window's data), in normalised units.
        lower, upper: bounds of the normalised parameters (n_params,).
    """

    u: FloatArray
    z_ref: float
    t_ref: float
    is_time: bool
    b_range: tuple[float, float] | None
    lower: FloatArray
    upper: FloatArray

    @classmethod
    def of(cls, meta: MetaModel, input_name: str, additive: bool, amplitude: float,
           window: WindowData) -> CandidateInput | None:
        """The normalised input of meta-model ``meta`` on ``input_name`` (``t`` or a channel)
        over ``window`` (an additive term is evaluated at mid-step), or None when the
        meta-model cannot take it: a non-positive value for a kind that needs a positive input
        (power, logarithm), an input that is zero or not finite throughout, or one the window
        cannot tell from a simpler kind (:meth:`MetaModel.identifiable`)."""
        is_time = input_name == TIME
        t_ref = meta.time_origin(window) if is_time else 0.0
        z = term_input(window, input_name, t_ref, additive)
        z_ref = _reference(meta, z, window, is_time)
        if z_ref is None:
            return None
        u = z / z_ref
        if not meta.identifiable(u):
            return None
        b_range = meta.data_range(u) or meta.search_range(window, is_time, z_ref)
        lo, hi = meta.bounds(amplitude, b_range=b_range)
        return cls(u, z_ref, t_ref, is_time, b_range, lo, hi)


def _reference(meta: MetaModel, z: FloatArray, window: WindowData, is_time: bool
               ) -> float | None:
    """The input's reference ``z_ref``: the largest |z| (a time term of ``t - t0``: the
    window's length [s]); None when the kind needs a positive input and ``z`` is not, or the
    reference is zero or not finite."""
    if meta.positive_input and not np.all(z > 0):
        return None
    z_ref = float(np.max(np.abs(z)))
    if is_time and not meta.positive_input:
        z_ref = float(window.t[-1] - window.t[0]) or 1.0
    return z_ref if z_ref > 0 and math.isfinite(z_ref) else None


class SeparableFit:
    """A candidate term's fit on one window, the physical parameters and the other terms held.

    Args:
        meta: the meta-model.
        attach: its attach point's name.
        u: the normalised input (N,) (:attr:`CandidateInput.u`).
        base_vals: the kept terms' values, attach point -> (N,).
        r_base: the twin's normalised residuals (M,) with the kept terms only.
        eps: probe size of the linearised response [attach point's unit].
        residuals: the twin's residuals for term values (counts its simulations).
    """

    def __init__(self, meta: MetaModel, attach: str, u: FloatArray,
                 base_vals: Mapping[str, FloatArray], r_base: FloatArray, eps: float,
                 residuals: Residuals) -> None:
        self.meta = meta
        self.attach = attach
        self.u = u
        self.base_vals = base_vals
        self.base_at = np.asarray(base_vals.get(attach, 0.0))
        self.r_base = r_base
        self.eps = eps
        self._residuals = residuals

    def forms(self) -> list[np.ndarray]:
        """Column masks of every form of the meta-model: the full one and each without some
        of its optional parameters (offsets, a slope), none empty."""
        meta = self.meta
        full = np.ones(len(meta.columns), dtype=bool)
        forms = []
        for drop in itertools.chain.from_iterable(
                itertools.combinations(meta.optional, k) for k in range(len(meta.optional) + 1)):
            m = full.copy()
            for opt in drop:
                m[meta.column_of(opt)] = False
            if m.any():
                forms.append(m)
        return forms

    def residuals(self, p: FloatArray) -> FloatArray:
        """The twin's normalised residuals (P, M) with the term at normalised parameter rows
        ``p`` (P, n_params) added to the kept terms."""
        v = self.meta.evaluate(np.atleast_2d(p), self.u)
        vals = dict(self.base_vals)
        vals[self.attach] = self.base_at + v
        return self._residuals(vals)

    def project(self, nl: FloatArray, mask: np.ndarray) -> tuple[FloatArray, FloatArray]:
        """Separable least squares: for each row of nonlinear parameters ``nl`` (P, n_nl), the
        coefficients of the ``mask``-ed basis columns minimising the linearised residual
        ``r_base + S c`` (S: the twin's response to each basis function, one batched twin
        call).

        Returns:
            (cost (P,): the linearised residual's norm, inf where the response is not finite;
            coef (P, n_cols): the coefficients, 0 outside ``mask``).
        """
        basis = self.meta.basis(nl, self.u)  # (P, n_cols, N)
        n_p, n_c, n = basis.shape
        cols = np.flatnonzero(mask)
        vals = dict(self.base_vals)
        vals[self.attach] = self.base_at + self.eps * basis[:, cols].reshape(-1, n)
        r_base = self.r_base
        sens = ((self._residuals(vals) - r_base) / self.eps).reshape(n_p, cols.size, -1)
        cost = np.full(n_p, np.inf)
        coef = np.zeros((n_p, n_c))
        for q in range(n_p):
            s_q = sens[q].T
            if not np.all(np.isfinite(s_q)):
                continue
            c, *_ = np.linalg.lstsq(s_q, -r_base, rcond=None)
            coef[q, cols] = c
            r_lin = r_base + s_q @ c
            cost[q] = math.sqrt(float(r_lin @ r_lin))
        return cost, coef
