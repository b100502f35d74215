"""One window's estimation problem: what the stages search, within which bounds, scored how.

As pymoo separates the problem from the algorithm that solves it and the termination that
stops it, the estimator builds a :class:`WindowProblem` once per window and hands it to each
stage. It holds no decision of its own: the search variables are the natural logarithms of the
estimated parameters (paper Eq. 1's decision vector), then the window's initial-state offsets;
every parameter not searched comes from the trusted vector.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from twinwatch.twin.estimation.fit import LocalFit, ParameterMap, Residual, WindowFit
from twinwatch.twin.model import FloatArray, TwinModel, WindowData


def check_window(model: TwinModel, window: WindowData) -> None:
    """Refuse a window the twin cannot be fitted to.

    Raises:
        ValueError: naming the channel, if one of ``model.required_channels()`` is missing or
            holds a NaN or inf.
    """
    for ch in model.required_channels():
        if ch not in window.channels:
            raise ValueError(f"window lacks channel {ch!r}")
        if not np.isfinite(window.channels[ch]).all():
            raise ValueError(f"window channel {ch!r} holds NaN or inf")


@dataclass
class FitPoint:
    """A point of the local problem and what the polish returned there.

    Attributes:
        v: search vector ``[ln p (n_est), d (n_init)]`` (n_est + n_init,): ln-parameters, then
            the initial-state offsets in units of each output's scale.
        r: normalised residuals (M,), ``M = (N-1) * n_out`` (:meth:`WindowFit.residuals`).
        jac: their Jacobian (M, n_active) with respect to the variables the last polish moved
            (the admitted parameters' columns, then the initial state's).
    """

    v: FloatArray
    r: FloatArray
    jac: FloatArray


@dataclass
class TwinAt:
    """The twin simulated at a point of the problem.

    Attributes:
        q: the estimated ln-parameters (n_est,).
        theta: the full parameter vector (1, n_params) [SI], ties applied.
        initial: the initial-state offsets (n_init,) in the outputs' units, or None.
        y: simulated outputs (N, n_out).
        residual: RMSE per output, worst error and nRMSE of ``y`` (paper Eq. 2).
    """

    q: FloatArray
    theta: FloatArray
    initial: FloatArray | None
    y: FloatArray
    residual: Residual


class WindowProblem:
    """One window's estimation problem.

    Args:
        fit: the window's fit (measured outputs and their normalisation, paper Eq. 2).
        pmap: search variables <-> full parameter vectors, ties applied.
        base: the trusted parameter vector (n_params,) [SI]: the warm start, and the value of
            every parameter not searched (held ones included). Copied.
        lower, upper: bounds of the estimated parameters (n_est,) [SI], positive.
        terms: the kept meta-model terms (DT'', paper Eq. 3), attach point -> values (N,),
            held fixed while the physical parameters are estimated.
        initial: also fit the window's initial-state offsets (``model.initial_states``).

    Attributes:
        xl, xu: bounds of the ln-parameters (n_est,).
        local: the bounded least-squares problem over the search vector
            (:class:`~twinwatch.twin.estimation.fit.LocalFit`).
        nuisance: positions of the initial-state offsets in the search vector (n_init,).
    """

    def __init__(self, fit: WindowFit, pmap: ParameterMap, base: FloatArray,
                 lower: FloatArray, upper: FloatArray,
                 terms: Mapping[str, FloatArray] | None, *, initial: bool) -> None:
        self.fit = fit
        self.pmap = pmap
        self.base = np.array(base, dtype=float, copy=True)
        self.terms = terms
        self.xl, self.xu = np.log(lower), np.log(upper)
        self.local = LocalFit(fit, pmap, self.base, self.xl, self.xu, terms, initial=initial)
        self.nuisance = self.local.nuisance

    @property
    def n_est(self) -> int:
        """Estimated parameters."""
        return int(self.pmap.idx.size)

    @property
    def n_out(self) -> int:
        """Outputs compared."""
        return self.fit.n_out

    def start(self) -> FloatArray:
        """The warm start: the trusted values' ln-parameters (n_est,), clipped to the bounds."""
        return np.clip(self.pmap.ln(self.base), self.xl, self.xu)

    def cost(self, q: FloatArray) -> FloatArray:
        """The fitness (normalised RMSE, paper Eq. 2) of ln-parameter rows ``q`` (P, n_est),
        the window's measured first sample as initial state; shape (P,)."""
        return self.fit.cost(self.pmap.full(q, self.base), self.terms)

    def trusted_ln(self, positions: list[int] | np.ndarray) -> FloatArray:
        """The trusted ln-values of the estimated parameters at ``positions``."""
        out: FloatArray = np.log(self.base[self.pmap.idx[positions]])
        return out

    def twin_at(self, v: FloatArray) -> TwinAt:
        """Simulate the twin at search vector ``v``; the window's fit keeps its initial-state
        offsets (:attr:`WindowFit.initial`) for every later simulation of this window."""
        q = v[:self.n_est]
        initial = self.local.initial(v)
        self.fit.initial = initial
        theta = self.pmap.full(q[None, :], self.base)
        y = self.fit.simulate(theta, self.terms)[0]
        return TwinAt(q=q, theta=theta, initial=initial, y=y, residual=self.fit.residual(y))
