"""The fit of a twin to one window: residuals, RMSE, Jacobian and covariance, built once.

The estimation (DT', paper Section 3.2), the discovery (DT'', Section 3.3) and the adaptation
all score a twin on a window the same way, so they share this module:

* :class:`WindowFit` holds the window's measured outputs and their normalisation (built once per
  window) and turns a swarm's simulation into normalised residuals, with the paper's fitness
  (Eq. 2, normalised): ``RMSE_n = sqrt(mean_j mean_k (w_j (y_sim - y_meas)/s_j)^2)``, with
  ``s_j = max(rms(y_meas_j), floor_j)`` per output j so that current [A], speed [rad/s] and
  voltage [V] weigh alike, and optional per-output weights ``w_j`` (default 1).
* :class:`ParameterMap` maps the estimator's search variables (the natural logarithms of the
  estimated parameters: every parameter is positive, and a log scale makes a relative step the
  same for an ohm and a kg m^2) to full parameter vectors, with ties (Kt = Ke) applied.
* :class:`LocalFit` polishes a subset of them by bounded least squares and returns the residuals
  and the Jacobian at the result; :func:`relative_std` turns the Jacobian into relative standard
  errors.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numba import njit

from twinwatch.twin.estimation._lm import levenberg_marquardt
from twinwatch.twin.estimation._trf import trust_region_reflective
from twinwatch.twin.estimation.statistics import ar1, mean, norms, quantum
from twinwatch.twin.model import FloatArray, TwinModel, WindowData, as_rows

#: Residual given to every sample of a particle whose simulation blew up.
BAD_RESIDUAL = 1e6


@dataclass
class Residual:
    """Fit of one twin variant (DT' or DT'') on a window.

    Attributes:
        rmse: output -> RMSE [output unit].
        max_abs: output -> worst absolute error [output unit].
        nrmse: normalised RMSE (the estimator's fitness).
    """

    rmse: dict[str, float]
    max_abs: dict[str, float]
    nrmse: float


class WindowFit:
    """One window's fit problem.

    Args:
        model: the twin.
        window: the measured window (every channel in ``model.required_channels()``).
        weights: output name -> weight ``w_j`` in the fitness (default 1 for every output).

    Attributes:
        meas: measured outputs, shape (N, n_out), in ``model.outputs`` order.
        scale: per-output normalisation ``s_j`` (n_out,).
        evaluations: simulations of one parameter vector run through this fit.
    """

    def __init__(self, model: TwinModel, window: WindowData,
                 weights: Mapping[str, float] | None = None) -> None:
        self.model = model
        self.window = window
        self.names = model.output_names
        self.n_out = len(self.names)
        self.meas = np.column_stack([window[o] for o in self.names])
        floors = np.array([o.scale for o in model.outputs])
        self.scale = np.maximum(np.sqrt(mean(self.meas**2, axis=0)), floors)
        w = weights or {}
        self.weights = np.array([float(w.get(o, 1.0)) for o in self.names])
        self._norm = self.weights / self.scale
        self._den = math.sqrt(max(self.meas.shape[0] - 1, 1) * self.n_out)
        self.evaluations = 0
        #: Scale of each initial-state offset (the output's normalisation).
        self.initial_scale = np.array([self.scale[self.names.index(o)]
                                       for o in model.initial_states])
        #: The window's estimated initial-state offsets (n_init,) in the outputs' units, used by
        #: every simulation that does not pass its own (None: the measured first sample).
        self.initial: FloatArray | None = None

    @property
    def n(self) -> int:
        """Samples in the window."""
        return int(self.meas.shape[0])

    @functools.cached_property
    def quanta(self) -> FloatArray:
        """Per output (n_out,), the step of its readings in the window over the output's scale
        (:func:`~twinwatch.twin.estimation.statistics.quantum`; 0: continuous, or a single
        value the window cannot tell the step of)."""
        steps = np.array([quantum(self.meas[:, j]) for j in range(self.n_out)])
        out: FloatArray = np.where(np.isnan(steps), 0.0, steps) / self.scale
        return out

    @functools.cached_property
    def longest_runs(self) -> list[tuple[int, int]]:
        """Per output, (first sample, length) of the longest run of exactly equal
        consecutive readings (the sensor checks', :mod:`~twinwatch.twin.estimation.quality`)."""
        return [_longest_run(self.meas[:, j]) for j in range(self.n_out)]

    def simulate(self, theta: FloatArray, terms: Mapping[str, FloatArray] | None = None,
                 initial: FloatArray | None = None) -> FloatArray:
        """The twin's outputs (P, N, n_out) for parameter vectors ``theta`` (P, n_params);
        ``terms``: attach point -> values (N,) or (P, N) (DT'', paper Eq. 3); ``initial``:
        initial-state offsets (n_init,) or (P, n_init) (default :attr:`initial`)."""
        theta = as_rows(theta)
        p = theta.shape[0]
        for v in (terms or {}).values():
            if np.ndim(v) == 2:
                p = max(p, np.shape(v)[0])
        if initial is not None and np.ndim(initial) == 2:
            p = max(p, np.shape(initial)[0])
        if p > theta.shape[0]:
            theta = np.repeat(theta[:1], p, axis=0)
        self.evaluations += p
        init = self.initial if initial is None else initial
        if init is None or not self.model.initial_states:
            return self.model.simulate(theta, self.window, terms or None)
        return self.model.simulate(theta, self.window, terms or None, initial=init)

    def residuals(self, theta: FloatArray, terms: Mapping[str, FloatArray] | None = None,
                  initial: FloatArray | None = None) -> FloatArray:
        """Normalised residuals (P, M), ``M = (N-1)*n_out`` (the first sample is the initial
        state), such that ``||r||_2`` is the normalised RMSE; a row whose simulation blew up
        is :data:`BAD_RESIDUAL` everywhere."""
        return self.residuals_of(self.simulate(theta, terms, initial))

    def residuals_of(self, y: FloatArray) -> FloatArray:
        """Normalised residuals of simulated outputs ``y`` (P, N, n_out) or (N, n_out)."""
        y3 = y if y.ndim == 3 else y[None]
        r = np.empty((y3.shape[0], (y3.shape[1] - 1) * y3.shape[2]))
        _residuals_kernel(np.ascontiguousarray(y3), self.meas, self._norm, self._den, r)
        out: FloatArray = r if y.ndim == 3 else r[0]
        return out

    def cost(self, theta: FloatArray, terms: Mapping[str, FloatArray] | None = None
             ) -> FloatArray:
        """The fitness (normalised RMSE) of each row of ``theta``, shape (P,)."""
        r = self.residuals(theta, terms)
        out: FloatArray = np.sqrt(np.sum(r * r, axis=1))
        return out

    def error_matrix(self, y: FloatArray) -> FloatArray:
        """Normalised errors of one trajectory ``y`` (N, n_out) as a matrix (N-1, n_out), each
        column the output's error over its scale (weights left out)."""
        out: FloatArray = (y[1:] - self.meas[1:]) / self.scale
        return out

    def residual(self, y: FloatArray) -> Residual:
        """RMSE, worst error (per output, in its unit) and nRMSE of one trajectory (N, n_out)."""
        err = y - self.meas
        return Residual(
            rmse={o: float(np.sqrt(mean(err[:, j] ** 2))) for j, o in enumerate(self.names)},
            max_abs={o: float(np.abs(err[:, j]).max()) for j, o in enumerate(self.names)},
            nrmse=float(np.sqrt(mean(((err[1:]) * self._norm) ** 2))),
        )


@njit(cache=True, nogil=True)
def _residuals_kernel(y: FloatArray, meas: FloatArray, norm: FloatArray, den: float,
                      r: FloatArray) -> None:  # pragma: no cover - compiled
    """:meth:`WindowFit.residuals_of` into ``r`` (P, (N-1)*n_out): ``(y - meas)*norm/den``
    from the second sample on, each step rounded as numpy's; a row with a non-finite entry
    is :data:`BAD_RESIDUAL` everywhere."""
    p, nk, n_out = y.shape
    for q in range(p):
        finite = True
        for k in range(1, nk):
            for j in range(n_out):
                v = ((y[q, k, j] - meas[k, j]) * norm[j]) / den
                r[q, (k - 1) * n_out + j] = v
                finite = finite and np.isfinite(v)
        if not finite:
            r[q, :] = BAD_RESIDUAL


def _longest_run(x: FloatArray) -> tuple[int, int]:
    """(first index, length) of the longest run of exactly equal consecutive values."""
    if x.size == 0:
        return 0, 0
    change = (x[1:] != x[:-1]).nonzero()[0] + 1
    starts = np.concatenate([[0], change])
    ends = np.concatenate([change, [x.size]])
    lengths = ends - starts
    i = int(np.argmax(lengths))
    return int(starts[i]), int(lengths[i])


class ParameterMap:
    """Search variables (ln of the estimated parameters) <-> full parameter vectors.

    Args:
        names: every model parameter, in ``model.parameters`` order.
        estimate: the estimated parameters, in priority order.
        ties: dependent parameter -> the parameter it equals.

    Attributes:
        idx: positions of the estimated parameters in the full vector (n_est,).
    """

    def __init__(self, names: Sequence[str], estimate: Sequence[str],
                 ties: Mapping[str, str] | None = None) -> None:
        self.names = tuple(names)
        self.estimate = tuple(estimate)
        self.idx = np.array([self.names.index(n) for n in self.estimate], dtype=int)
        self.ties = [(self.names.index(d), self.names.index(s))
                     for d, s in (ties or {}).items()]

    def full(self, q: FloatArray, base: FloatArray) -> FloatArray:
        """Full parameter vectors (P, n_params) from ln-parameter rows ``q`` (P, n_est), the
        others taken from ``base`` (n_params,), ties applied."""
        q = as_rows(q)
        theta = np.empty((q.shape[0], len(self.names)))
        theta[:] = base
        theta[:, self.idx] = np.exp(q)
        self.apply_ties(theta)
        return theta

    def apply_ties(self, theta: FloatArray) -> None:
        """Set each tied parameter to its source, in place; ``theta`` (n_params,) or (P, ...)."""
        for dep, src in self.ties:
            theta[..., dep] = theta[..., src]

    def ln(self, theta: FloatArray) -> FloatArray:
        """The search variables of a full vector (n_params,) -> (n_est,)."""
        out: FloatArray = np.log(np.asarray(theta, dtype=float)[self.idx])
        return out


class LocalFit:
    """The local part of a window's estimation: bounded least-squares polish of some of the
    search variables (the others held) and the residuals and Jacobian at the result.

    The search vector is ``[ln p (n_est), d (n_init)]``: the estimated parameters' logarithms,
    then, with ``initial``, the window's initial-state offsets in units of each output's scale
    (bounded to +-0.5: an error of the first sample, not a new operating point).

    Args:
        fit: the window's fit.
        pmap: the parameter map.
        base: the full parameter vector supplying the parameters that are not searched.
        lower, upper: bounds of the ln-parameters (n_est,).
        terms: meta-model term values held fixed (attach point -> (N,)).
        initial: also fit the initial-state offsets of ``fit.model.initial_states``.
    """

    #: Bound of the normalised initial-state offsets.
    INITIAL_BOUND = 0.5

    def __init__(self, fit: WindowFit, pmap: ParameterMap, base: FloatArray,
                 lower: FloatArray, upper: FloatArray,
                 terms: Mapping[str, FloatArray] | None = None, initial: bool = False) -> None:
        self.fit, self.pmap, self.base = fit, pmap, base
        self.n_est = pmap.idx.size
        self.n_init = len(fit.model.initial_states) if initial else 0
        b = self.INITIAL_BOUND
        self.lower = np.concatenate([lower, np.full(self.n_init, -b)])
        self.upper = np.concatenate([upper, np.full(self.n_init, b)])
        self.terms = terms
        #: :meth:`sensitivity_and_residuals`'s columns at the last few points (the gate, its
        #: propagation of the held values and the fusion's first linearisation ask for
        #: columns at the same point: each is simulated once).
        self._sens: dict[bytes, dict[str, Any]] = {}

    @property
    def nuisance(self) -> np.ndarray:
        """Positions of the initial-state offsets in the search vector."""
        return np.arange(self.n_est, self.n_est + self.n_init)

    def start(self, q: FloatArray) -> FloatArray:
        """A search vector from ln-parameters ``q`` (n_est,), offsets 0."""
        return np.concatenate([np.asarray(q, dtype=float), np.zeros(self.n_init)])

    def initial(self, v: FloatArray) -> FloatArray | None:
        """The initial-state offsets of search vector(s) ``v`` in the outputs' units (None
        when not fitted)."""
        if not self.n_init:
            return None
        out: FloatArray = np.asarray(v)[..., self.n_est:] * self.fit.initial_scale
        return out

    def residuals(self, v: FloatArray) -> FloatArray:
        """Normalised residuals (P, M) for search-vector rows ``v`` (P, n_est + n_init)."""
        v = as_rows(v)
        theta = self.pmap.full(v[:, :self.n_est], self.base)
        return self.fit.residuals(theta, self.terms,
                                  self.initial(v) if self.n_init else None)

    def jacobian(self, v: FloatArray, active: np.ndarray, r0: FloatArray) -> FloatArray:
        """Forward-difference ``d r / d v`` over the ``active`` columns (M, n_active) at
        residuals ``r0``, step 1e-6: the polish's search direction (one twin call for all
        columns). The statistics read :meth:`sensitivity`."""
        h = 1e-6
        vs = np.repeat(v[None, :], active.size, axis=0)
        vs[np.arange(active.size), active] += h
        return ((self.residuals(vs) - r0[None, :]) / h).T

    #: Relative step of :meth:`term_sensitivity` (a term's scale).
    TERM_STEP = 1e-4

    def term_sensitivity(self, v: FloatArray) -> FloatArray:
        """``d r / d s`` (M, n_terms) at search vector ``v``, ``s`` each held meta-model
        term's relative scale (its values times ``1 + s``), by forward difference of
        :data:`TERM_STEP`; (M, 0) without terms. The identifiability gate takes these columns
        as nuisance (:mod:`~twinwatch.twin.estimation.gate`)."""
        v = np.atleast_2d(v)[-1:]
        theta = self.pmap.full(v[:, :self.n_est], self.base)
        initial = self.initial(v) if self.n_init else None
        r0 = self.fit.residuals(theta, self.terms, initial)[0]
        terms = self.terms or {}
        h = self.TERM_STEP
        cols = []
        for key in terms:
            scaled = {k: (a * (1.0 + h) if k == key else a) for k, a in terms.items()}
            cols.append((self.fit.residuals(theta, scaled, initial)[0] - r0) / h)
        return np.stack(cols, axis=1) if cols else np.zeros((r0.size, 0))

    #: Steps of :meth:`sensitivity`, smallest first (ln-parameters; initial-state offsets in
    #: units of their output's scale).
    SENSITIVITY_STEPS = (1e-6, 1e-5, 1e-4, 1e-3)
    #: Forward and backward differences agree when they differ by at most this share.
    SENSITIVITY_AGREEMENT = 0.02

    def sensitivity(self, v: FloatArray, active: np.ndarray,
                    steps: Sequence[float] | None = None) -> FloatArray:
        """``d r / d v`` over the ``active`` columns (M, n_active) for the statistics
        (standard errors, the gate, the model check, the fusion's evidence), robust to the
        residual's jumps: per column, the central difference at the smallest step whose
        forward and backward differences agree (to :data:`SENSITIVITY_AGREEMENT`), or at the
        largest step if none does; one twin call for all.

        The residual of a drive with a clamped output is not smooth: the clamping
        anti-windup switches on or off, a jump in the integrator. A difference whose step
        straddles a jump adds ``jump/step`` to the column, and the parameters look
        determined where they are not. A jump on one side shows as forward and backward
        differences that disagree; on a smooth residual they agree to the step's order.

        Args:
            v: the search vector.
            active: the columns.
            steps: the steps to try, smallest first (default :data:`SENSITIVITY_STEPS`).
        """
        return self.sensitivity_and_residuals(v, active, steps)[0]

    #: Points whose sensitivity columns are kept (:meth:`sensitivity_and_residuals`).
    SENSITIVITY_CACHE = 4

    def _point_key(self, v: FloatArray) -> bytes:
        """The residuals depend on ``v`` and, without fitted offsets, on the window's
        :attr:`WindowFit.initial` (set by :meth:`WindowProblem.twin_at`)."""
        key = np.ascontiguousarray(v, dtype=float).tobytes()
        if not self.n_init and self.fit.initial is not None:
            key += b"|" + np.ascontiguousarray(self.fit.initial, dtype=float).tobytes()
        return key

    def sensitivity_and_residuals(self, v: FloatArray, active: np.ndarray,
                     steps: Sequence[float] | None = None) -> tuple[FloatArray, FloatArray]:
        """:meth:`sensitivity`, and the residuals (M,) at ``v`` (the batch's last row).

        A column already computed at the same ``v`` is reused (the same numbers: every row is
        simulated on its own) when it was computed with the same steps, or settled at the
        first step and ``steps`` starts with it."""
        # Step by step, smallest first, only for the columns not settled yet (on a smooth
        # residual the first step settles every column: 2k + 1 rows, not 2 n_h k + 1).
        active = np.asarray(active, dtype=int)
        k = active.size
        hs = tuple(self.SENSITIVITY_STEPS if steps is None else steps)
        n_h = len(hs)
        key = self._point_key(v)
        entry = self._sens.get(key)
        r0: FloatArray | None = None if entry is None else entry["r0"]
        out: FloatArray | None = None if r0 is None else np.empty((k, r0.size))
        missing = []
        for j, c in enumerate(active):
            hit = None if entry is None else entry["cols"].get(int(c))
            if hit is not None and (hit[0] == hs or (hit[1] == 0 and hit[0][0] == hs[0])):
                assert out is not None
                out[j] = hit[2]
            else:
                missing.append(j)
        todo = np.array(missing, dtype=int)
        settled: list[tuple[int, int, FloatArray]] = []
        if not todo.size and r0 is None:
            r0 = self.residuals(v[None, :])[0]
            out = np.empty((k, r0.size))
        for i, h in enumerate(hs):
            if not todo.size:
                break
            m = todo.size
            cols = active[todo]
            vs = np.repeat(v[None, :], 2 * m + (1 if r0 is None else 0), axis=0)
            for d, c in enumerate(cols.tolist()):  # each the same IEEE sum as numpy's
                vs[d, c] += h
                vs[m + d, c] -= h
            r = self.residuals(vs)
            if r0 is None:
                r0 = r[-1]
                out = np.empty((k, r0.size))  # returned transposed (the layout BLAS sees)
            assert out is not None
            # -(x)/h is x/(-h) to the bit (a negated operand negates the rounded quotient)
            both = np.divide(r[:2 * m] - r0[None, :], np.repeat([h, -h], m)[:, None])
            fwd, bwd = both[:m], both[m:]
            central = 0.5 * (fwd + bwd)
            gap = norms(fwd - bwd, axis=1)
            size = norms(both, axis=1)
            size = np.maximum(size[:m], size[m:])
            agree = gap <= self.SENSITIVITY_AGREEMENT * np.maximum(size, 1e-300)
            done = agree if i < n_h - 1 else np.ones(m, dtype=bool)
            out[todo[done]] = central[done]
            # the cache keeps rows of ``central`` (never written after)
            settled.extend((int(active[j]), i, central[d]) for d, j in
                           zip(np.flatnonzero(done).tolist(), todo[done].tolist(), strict=True))
            todo = todo[~done]
        assert out is not None and r0 is not None
        if entry is None:
            if len(self._sens) >= self.SENSITIVITY_CACHE:
                self._sens.pop(next(iter(self._sens)))
            entry = self._sens[key] = {"r0": r0, "cols": {}}
        for c, i, col in settled:
            entry["cols"][c] = (hs, i, col)
        return out.T, r0

    def refine(self, v: FloatArray, active: np.ndarray, *, polish: bool = True,
               stats: np.ndarray | None = None, method: Literal["trf", "lm"] = "trf"
               ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Polish the ``active`` entries of ``v`` (bounded least squares, forward-difference
        Jacobian from one batched twin call), then return (v, residuals (M,), Jacobian
        (M, len(stats)) for the statistics, by :meth:`sensitivity`) at the result;
        ``stats``: the Jacobian's columns (default ``active``). ``method``: ``"trf"``
        scipy's trust-region reflective loop (:mod:`~twinwatch.twin.estimation._trf`),
        ``"lm"`` Levenberg-Marquardt (:mod:`~twinwatch.twin.estimation._lm`, for a
        determined problem started near its optimum)."""
        v = np.array(v, dtype=float, copy=True)
        if polish and active.size:
            k = active.size
            rows = np.repeat(v[None, :], k + 1, axis=0)
            stepped = 1 + np.arange(k)
            lo, hi = self.lower[active], self.upper[active]
            x0 = np.clip(v[active], lo + 1e-12, hi - 1e-12)

            def batch(x: FloatArray) -> FloatArray:
                """The point and its forward differences (:meth:`jacobian`'s rows), one twin
                call: residuals (k + 1, M), the point's first."""
                rows[:, active] = x
                rows[stepped, active] += 1e-6
                return self.residuals(rows)

            if method == "lm":
                def fun_jac(x: FloatArray) -> tuple[FloatArray, FloatArray]:
                    r_all = batch(x)
                    return r_all[0], (r_all[1:] - r_all[0]) / 1e-6

                v[active] = levenberg_marquardt(fun_jac, x0, lo, hi)[0]
            else:
                last: dict[str, FloatArray] = {}

                def fun(x: FloatArray) -> FloatArray:
                    # least_squares asks for the Jacobian where it just evaluated fun
                    r_all = batch(x)
                    last["x"], last["r"], last["d"] = x.copy(), r_all[0], r_all[1:]
                    r0: FloatArray = r_all[0]
                    return r0

                def jac(x: FloatArray) -> FloatArray:
                    seen = last.get("x")
                    if seen is None or seen.shape != x.shape or not (seen == x).all():
                        fun(x)
                    return ((last["d"] - last["r"][None, :]) / 1e-6).T

                v[active] = trust_region_reflective(fun, jac, x0, lo, hi)
        jac_s, r = self.sensitivity_and_residuals(v, active if stats is None else stats)
        return v, r, jac_s


#: Eigenvalues of the equilibrated ``J^T J`` below this share of the largest are directions the
#: data do not determine (:func:`covariance`).
RCOND = 1e-12
#: A residual whose mean square is below this share of the ``model_error`` floor's (a tenth of
#: its RMS) shows none of the error the floor stands for: it is the simulation's own
#: arithmetic; the identifiability gate takes the floor as white there
#: (:func:`residual_variances`'s ``numerical``). Above it the residual's autocorrelation is the
#: model error's.
NUMERICAL_SHARE = 0.01


def covariance(jac: FloatArray, weights: FloatArray) -> FloatArray:
    """The least-squares covariance ``A^-1 (J^T W J) A^-1`` with ``A = J^T J`` (the sandwich:
    the residual variance may differ from row to row, e.g. between outputs).

    The columns are equilibrated before the inverse: the hydraulic twin's ``J^T J`` has a
    condition number of ~1e15 in raw form (pressure in Pa against a piston area in m^2), where
    an unequilibrated inverse returns meaningless variances. A direction of the equilibrated
    ``A`` whose eigenvalue is below :data:`RCOND` of the largest is not determined: every
    variable that loads on it gets an infinite variance (a pseudo-inverse would give them a
    small, finite one). A column the outputs do not respond to at all is such a direction.

    Args:
        jac: (M, n) Jacobian of the residuals.
        weights: (M,) variance of each residual row.

    Returns:
        (n, n) covariance; ``inf`` on the rows and columns of undetermined variables.
    """
    n = jac.shape[1]
    if not np.isfinite(jac).all():
        return np.full((n, n), np.inf)
    col_norms = norms(jac, axis=0)
    safe = np.where(col_norms > 0, col_norms, 1.0)
    js = jac / safe
    # the two (M, n) products stay numpy's (its J^T J is BLAS syrk: numba's gemm differs in
    # the last bits); the small (n, n) rest is compiled, the same arithmetic to the bit
    try:
        cov: FloatArray = _sandwich(js.T @ js, (js * weights[:, None]).T @ js, safe,
                                    col_norms)
    except (np.linalg.LinAlgError, ValueError):  # numba's eigh: ValueError if not converged
        return np.full((n, n), np.inf)
    return cov


@njit(cache=True, nogil=True)
def _equilibrated_inverse(a: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The inverse of the equilibrated ``A = J^T J`` (n, n) on the directions it determines
    (eigenvalues above :data:`RCOND` of the largest), and per variable its load on the
    others: the sum of its squared components along them (n,)."""
    lam, vec = np.linalg.eigh(a)
    n = lam.size
    top = lam[0]
    for i in range(1, n):
        top = max(top, lam[i])
    keep = lam > RCOND * max(top, 1e-300)
    # (kept / lam[keep]) @ kept.T, the columns gathered and scaled by loops: the same
    # numbers, without compiling numba's boolean indexing and broadcasting for it
    r = 0
    for i in range(n):
        if keep[i]:
            r += 1
    kept = np.empty((n, r))
    scaled = np.empty((n, r))
    c = 0
    for i in range(n):
        if keep[i]:
            for k in range(n):
                kept[k, c] = vec[k, i]
                scaled[k, c] = vec[k, i] / lam[i]
            c += 1
    a_inv = scaled @ kept.T
    loads = np.zeros(lam.size)
    for k in range(lam.size):
        for i in range(lam.size):
            if not keep[i]:
                loads[k] += vec[k, i] ** 2
    return a_inv, loads


@njit(cache=True, nogil=True)
def _sandwich(a: FloatArray, b: FloatArray, safe: FloatArray, norms: FloatArray
              ) -> FloatArray:
    """:func:`covariance`'s ``A^-1 B A^-1`` from the equilibrated ``A`` and ``B = J^T W J``
    (n, n), scaled back by the column norms ``safe`` (n,), ``inf`` on the rows and columns
    of a zero column (``norms``) or one that loads on an undetermined direction."""
    a_inv, loads = _equilibrated_inverse(a)
    cov = a_inv @ b @ a_inv
    for i in range(safe.size):  # cov / np.outer(safe, safe), the same numbers
        for j in range(safe.size):
            cov[i, j] = cov[i, j] / (safe[i] * safe[j])
    for k in range(safe.size):
        if norms[k] == 0 or loads[k] > 1e-12:
            cov[k, :] = np.inf
            cov[:, k] = np.inf
    return cov


def relative_std(jac: FloatArray, r: FloatArray, n_out: int, floor: float,
                 numerical: float = 0.0) -> FloatArray:
    """Standard errors of the search variables at a least-squares optimum (relative for
    ln-parameters): the square roots of :func:`parameter_covariance`'s diagonal
    (``numerical``: :func:`residual_variances`')."""
    d = parameter_covariance(jac, r, n_out, floor, numerical=numerical).diagonal()
    with np.errstate(invalid="ignore"):
        return np.sqrt(np.where(d > 0, d, np.inf))


def explained_rms(jac: FloatArray, cov: FloatArray, n_out: int) -> FloatArray:
    """Per output, the RMS of the residual (in units of the residual entries times sqrt(M))
    that the search variables' uncertainty ``cov`` explains: ``sqrt(mean_k J_k cov J_k^T)``
    over each output's rows. An output measured without noise (a drive's voltage) is never
    white: its residual is what the other outputs' noise does to the estimates, and this is
    how large that is.

    Args:
        jac: (M, n) Jacobian of the normalised residuals, ``n_out`` outputs interleaved.
        cov: (n, n) covariance of the search variables.
        n_out: outputs.

    Returns:
        (n_out,).
    """
    m = jac.shape[0]
    finite = np.isfinite(cov).all(axis=0)
    if not finite.any():
        return np.zeros(n_out)
    j = jac[:, finite] * math.sqrt(m)
    c = cov[np.ix_(finite, finite)]
    var = np.einsum("ij,jk,ik->i", j, c, j).reshape(-1, n_out)
    out: FloatArray = np.sqrt(np.maximum(mean(var, axis=0), 0.0))
    return out


def explained_dof(jac: FloatArray, cov: FloatArray, n_out: int) -> FloatArray:
    """Per output, the degrees of freedom of the squared residual RMS that the search
    variables' uncertainty ``cov`` explains (:func:`explained_rms`, its mean).

    That share of an output's mean square is ``d^T A d`` over ``d ~ N(0, I)`` with
    ``A = C^(1/2) J_o^T J_o C^(1/2) / N_o``: a sum of chi-squares of one degree weighted by
    A's eigenvalues. Its Welch-Satterthwaite degrees, ``tr(A)^2 / tr(A^2)``, say how heavy
    its tail is: near 1 when one direction of the estimates dominates (a drive's voltage
    follows the one parameter combination the window determines least), up to the number of
    search variables when all weigh alike (Satterthwaite, Biometrics Bulletin 2(6), 1946).

    Args:
        jac: (M, n) Jacobian of the normalised residuals, ``n_out`` outputs interleaved.
        cov: (n, n) covariance of the search variables.
        n_out: outputs.

    Returns:
        (n_out,): the degrees, 0 for an output the uncertainty does not reach.
    """
    finite = np.isfinite(cov).all(axis=0)
    out = np.zeros(n_out)
    if not finite.any():
        return out
    j = jac[:, finite]
    c = cov[np.ix_(finite, finite)]
    for o in range(n_out):
        jo = j[o::n_out]
        bc = (jo.T @ jo) @ c          # tr(A) = tr(B C), tr(A^2) = tr(B C B C), B = J_o^T J_o
        tr1 = float(np.trace(bc))
        tr2 = float(np.add.reduce(bc * bc.T, axis=None))
        if tr1 > 0.0 and tr2 > 0.0:
            out[o] = tr1 * tr1 / tr2
    return out


def parameter_covariance(jac: FloatArray, r: FloatArray, n_out: int, floor: float,
                         levels: FloatArray | None = None, *, numerical: float = 0.0
                         ) -> FloatArray:
    """Covariance of the search variables at a least-squares optimum.

    Each output's residual variance is estimated on its own (an output measured without noise,
    such as a closed-loop drive's voltage, must not lower the noise of the others), floored by
    ``floor`` (the normalised model and discretisation error of noise-free data) and inflated
    by ``(1 + rho)/(1 - rho)``, rho being that output's lag-1 autocorrelation (the AR(1)
    effective-sample-size correction): white noise leaves it alone, while smooth model error
    (a parameter drifting within the window) is not allowed to pass for hundreds of
    independent samples. The covariance is the sandwich of :func:`covariance`.

    Args:
        jac: (M, n) Jacobian of the normalised residuals with respect to the search variables.
        r: (M,) normalised residuals at the optimum, ``n_out`` outputs interleaved.
        n_out: outputs interleaved in ``r``.
        floor: smallest normalised residual level assumed.
        levels: per output, a normalised noise level to use instead of the residual's (the
            white noise alone, e.g. to ask what noise does to the estimates); no AR(1)
            inflation then.
        numerical: :func:`residual_variances`'.

    Returns:
        (n, n) covariance (``inf`` for a variable the outputs do not respond to).
    """
    cached, key = _COVARIANCES.get((jac, r, n_out, floor, levels, numerical))
    if cached is not None:
        out: FloatArray = cached.copy()
        return out
    m, n = jac.shape
    res = r.reshape(-1, n_out)
    if levels is not None:
        var = np.maximum(np.asarray(levels, dtype=float) ** 2, floor**2)
        cov = covariance(jac, _rows(var / m, res.shape[0]))
    else:
        cov = covariance(jac, residual_variances(r, n_out, floor, n, numerical))
    _COVARIANCES.put(key, cov.copy())
    return cov


def long_run_factors(jac: FloatArray, r: FloatArray, n_out: int, floor: float,
                     numerical: float = 0.0, lags: int | None = None) -> FloatArray:
    """Per column of ``jac``, how much wider its standard error is when the residual's
    serial correlation with the sensitivities is counted: ``sqrt(max(1, V_hac / V))``, ``V``
    the variance :func:`parameter_covariance` gives (each output's residual variance with its
    AR(1) factor), ``V_hac`` the heteroskedasticity and autocorrelation consistent sandwich
    ``A^-1 S A^-1`` (White 1982, *Maximum likelihood estimation of misspecified models*,
    Econometrica 50; Newey and West 1987, Econometrica 55: ``S`` the
    long-run variance of the per-sample scores ``g_t = J_t^T r_t``, Bartlett weights
    ``1 - l/(L+1)`` over ``L = N // 4`` lags, as :func:`~.statistics.long_run_factor`).

    A twin that misses part of the machine leaves a residual that follows the inputs, and the
    parameters whose sensitivities follow them too take it up window after window: their
    scores stay of one sign for many samples, which the AR(1) factor alone does not see.
    White residuals give about 1.

    Args:
        jac: (M, n) Jacobian of the normalised residuals (``n_out`` outputs interleaved).
        r: (M,) the residuals.
        n_out: outputs.
        floor, numerical: :func:`parameter_covariance`'s.
        lags: L (default ``N // 4``).

    Returns:
        (n,) factors >= 1 (1 for a column without a finite variance).
    """
    m, n = jac.shape
    nt = m // n_out
    out = np.ones(n)
    if n == 0 or nt < 4 or not (np.isfinite(jac).all() and np.isfinite(r).all()):
        return out
    base = parameter_covariance(jac, r, n_out, floor, numerical=numerical).diagonal()
    g = (jac * r[:, None]).reshape(nt, n_out, n).sum(axis=1)
    big_l = max(1, min(lags if lags is not None else nt // 4, nt - 1))
    # s = g^T g + sum_l w_l (G_l + G_l^T), G_l = g[l:]^T g[:-l], summed lag after lag
    terms = np.empty((big_l + 1, n, n))
    g_t = g.T
    terms[0] = g_t @ g
    for lag in range(1, big_l + 1):  # g_t[:, lag:] is the view g[lag:].T: the same gemm
        np.matmul(g_t[:, lag:], g[:-lag], terms[lag])
    both = terms[1:] + terms[1:].transpose(0, 2, 1)
    both *= (1.0 - np.arange(1, big_l + 1) / (big_l + 1.0))[:, None, None]
    terms[1:] = both
    s = np.add.accumulate(terms, axis=0)[-1]
    col_norms = norms(jac, axis=0)
    safe = np.where(col_norms > 0, col_norms, 1.0)
    js = jac / safe
    try:
        a_inv, _ = _equilibrated_inverse(js.T @ js)
    except ValueError as exc:  # numba's eigh did not converge: numpy's error, as before
        raise np.linalg.LinAlgError(str(exc)) from exc
    hac = (a_inv @ (s / np.outer(safe, safe)) @ a_inv).diagonal() / (safe * safe)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = hac / base
    good = np.isfinite(ratio) & np.isfinite(base) & (base > 0)
    out[good] = np.sqrt(np.maximum(ratio[good], 1.0))
    return out


def residual_variances(r: FloatArray, n_out: int, floor: float, n_fitted: int,
                       numerical: float = 0.0) -> FloatArray:
    """Variance of each normalised residual row (M,), estimated per output: the mean square
    (corrected for ``n_fitted`` fitted variables), floored by ``floor`` (a normalised RMS) and
    inflated by the output's AR(1) factor ``(1 + rho)/(1 - rho)``
    (see :func:`parameter_covariance`).

    With ``numerical`` > 0 (the identifiability gate's :data:`NUMERICAL_SHARE`), an output
    whose mean square is below that share of ``floor**2`` gets the floor alone, not
    inflated: its lag-1 autocorrelation is the simulation's arithmetic's (near 1 on
    noise-free data), not the model error's. The fusion's weights and the model check keep
    the inflated floor."""
    m = r.size
    res = r.reshape(-1, n_out)
    moments, key = _MOMENTS.get((r, n_out))
    if moments is None:
        moments = (mean(res * res, axis=0), [None] * n_out)
        _MOMENTS.put(key, moments)
    mean_square, rhos = moments
    var = mean_square * m * m / max(m - n_fitted, 1)
    for j in range(n_out):
        if var[j] < numerical * floor**2:
            var[j] = floor**2
            continue
        rho = rhos[j]
        if rho is None:
            rho = rhos[j] = ar1(res[:, j], 1)
        var[j] = max(var[j], floor**2) * (1.0 + rho) / (1.0 - rho)
    return _rows(var / m, res.shape[0])


def _rows(per_output: FloatArray, nt: int) -> FloatArray:
    """``np.tile(per_output, nt)``: each output's value on its rows of the interleaved
    residual vector (nt * n_out,)."""
    out = np.empty((nt, per_output.size))
    out[:] = per_output
    return out.reshape(-1)


class _Recent:
    """The last few results of a pure function of arrays and numbers, found again when it is
    called with the same arguments: arrays of the same shape, strides, dtype and bytes (the
    layout too: it decides the BLAS call, and so the last bits), numbers of the same type and
    value (the gate, the model check and the long-run factor ask for the same covariance).

    Shared by every estimator of the process: the results depend on the arguments alone, an
    entry's value is never replaced (a value computed piecewise gets each piece once), and the
    list is replaced, not edited (a thread reads either list whole).

    Args:
        size: results kept.
    """

    def __init__(self, size: int) -> None:
        self.size = size
        self._entries: list[tuple[tuple[Any, ...], Any]] = []

    @staticmethod
    def _signature(args: tuple[Any, ...]) -> tuple[Any, ...]:
        return tuple((a.shape, a.strides, a.dtype.str, a.tobytes(order="A"))
                     if isinstance(a, np.ndarray) else (type(a), a) for a in args)

    def get(self, args: tuple[Any, ...]) -> tuple[Any, tuple[Any, ...]]:
        """The result stored for ``args`` (None: none) and their signature (for :meth:`put`)."""
        key = self._signature(args)
        for k, value in reversed(self._entries):
            if k == key:
                return value, key
        return None, key

    def put(self, key: tuple[Any, ...], value: Any) -> None:
        """Store ``value`` under ``key``, the signature :meth:`get` returned."""
        self._entries = [*self._entries[-(self.size - 1):], (key, value)]


#: :func:`parameter_covariance`'s last results.
_COVARIANCES = _Recent(8)
#: Per residual vector and output count, each output's mean square and its lag-1
#: autocorrelation (computed when first needed) (:func:`residual_variances`).
_MOMENTS = _Recent(4)


@functools.cache
def _swarm_problem_class() -> type:
    """pymoo's ``Problem`` subclass, built on first use (pymoo is imported then, not when a
    configuration is validated)."""
    from pymoo.core.problem import Problem

    class SwarmProblem(Problem):  # type: ignore[misc]  # pymoo is untyped: Problem is Any
        """pymoo problem whose ``_evaluate`` is one vectorised call for the whole swarm (as
        pymoo's ``problems/single``): ``cost_fn(X (P, n)) -> (P,)``."""

        def __init__(self, cost_fn: Callable[[FloatArray], FloatArray], xl: FloatArray,
                     xu: FloatArray) -> None:
            super().__init__(n_var=xl.size, n_obj=1, xl=xl, xu=xu)
            self._cost_fn = cost_fn

        def _evaluate(self, x: FloatArray, out: dict[str, Any], *args: Any,
                      **kwargs: Any) -> None:
            out["F"] = self._cost_fn(x)[:, None]

    return SwarmProblem


@dataclass
class SwarmResult:
    """Outcome of :func:`pso_minimize`: best point, its cost, iterations run, and whether the
    time cap (rather than the iteration limit or convergence) stopped it."""

    x: FloatArray
    cost: float
    generations: int
    time_capped: bool


def pso_minimize(cost_fn: Callable[[FloatArray], FloatArray], lower: FloatArray,
                 upper: FloatArray, settings: Any, *, rng: np.random.Generator,
                 time_budget: float, seeds: FloatArray | None = None,
                 patience: int | None = None) -> SwarmResult:
    """Particle swarm optimisation (paper Eq. 1-2, pymoo's PSO) within bounds.

    With the paper's fixed ``w``, ``c1``, ``c2`` (``adaptive`` off, the default) the swarm
    runs in :func:`_pso_loop`: pymoo's PSO step by step (its velocity equation, its
    out-of-bounds redraws and repair, its polynomial mutation of the best particle, the
    improvement replacement of the personal bests) on arrays, without pymoo's per-particle
    ``Individual`` bookkeeping, which costs most of a small swarm's CPU. pymoo's ``PSO`` class
    runs the adaptive variant (its fuzzy ``w``/``c1``/``c2`` updates).

    Args:
        cost_fn: vectorised cost, (P, n) -> (P,).
        lower, upper: bounds (n,).
        settings: swarm settings with ``pop_size``, ``max_generations``, ``w``, ``c1``, ``c2``,
            ``adaptive`` (:class:`~twinwatch.twin.estimation.PSOSettings`).
        rng: the random generator (the initial Latin hypercube and the swarm's seed come from
            it: same generator state, same result when the time cap is not hit).
        time_budget: wall-time cap [s].
        seeds: rows (k, n) placed as the first particles (a warm start, periodogram peaks).
        patience: also stop once the best cost has not moved (1e-9) for this many iterations.

    Returns:
        The best particle found; ``generations`` counts the initial swarm as the first.
    """
    from pymoo.operators.sampling.lhs import LHS

    problem = _swarm_problem_class()(cost_fn, lower, upper)
    init = LHS()(problem, settings.pop_size, random_state=rng).get("X")
    if seeds is not None:
        for k, row in enumerate(np.atleast_2d(seeds)[: settings.pop_size]):
            init[k] = np.clip(row, lower, upper)
    seed = int(rng.integers(2**31))
    if not settings.adaptive:
        return _pso_loop(cost_fn, np.asarray(lower, dtype=float),
                         np.asarray(upper, dtype=float), np.asarray(init, dtype=float),
                         settings, np.random.default_rng(seed), time_budget, patience)
    from pymoo.algorithms.soo.nonconvex.pso import PSO
    from pymoo.core.population import Population
    from pymoo.optimize import minimize
    from pymoo.termination.collection import TerminationCollection
    from pymoo.termination.ftol import SingleObjectiveSpaceTermination
    from pymoo.termination.max_gen import MaximumGenerationTermination
    from pymoo.termination.max_time import TimeBasedTermination
    from pymoo.termination.robust import RobustTermination

    algo = PSO(pop_size=settings.pop_size, sampling=Population.new(X=init), w=settings.w,
               c1=settings.c1, c2=settings.c2, adaptive=settings.adaptive)
    parts: list[Any] = [MaximumGenerationTermination(settings.max_generations),
                        TimeBasedTermination(time_budget)]
    if patience is not None:
        parts.append(RobustTermination(SingleObjectiveSpaceTermination(tol=1e-9),
                                       period=patience))
    res = minimize(problem, algo, TerminationCollection(*parts),
                   seed=seed, verbose=False, copy_algorithm=False)
    gens = int(res.algorithm.n_gen)
    return SwarmResult(x=np.asarray(res.X, dtype=float).reshape(-1),
                       cost=float(np.asarray(res.F).reshape(-1)[0]), generations=gens,
                       time_capped=gens < settings.max_generations and patience is None)


#: pymoo's PSO defaults that :func:`_pso_loop` keeps: the velocity cap as a share of each
#: variable's range, the out-of-bounds redraws before the repair, the best particle's
#: polynomial mutation (probability, its distribution index drawn from this range)
PSO_MAX_VELOCITY_RATE = 0.20
PSO_REDRAWS = 20
PSO_MUTATION_PROB = 0.9
PSO_MUTATION_ETA = (5.0, 30.0)


def _pso_loop(cost_fn: Callable[[FloatArray], FloatArray], xl: FloatArray, xu: FloatArray,
              init: FloatArray, settings: Any, gen: np.random.Generator, time_budget: float,
              patience: int | None) -> SwarmResult:
    """pymoo's ``PSO`` (``adaptive=False``, ``initial_velocity="random"``,
    ``pertube_best=True``) on arrays: the same steps, through pymoo's own operator functions
    (``pso_equation``, ``repair_random_init``, ``mut_pm``), one ``cost_fn`` call per
    iteration for the whole swarm.

    Args:
        cost_fn: vectorised cost, (P, n) -> (P,).
        xl, xu: bounds (n,).
        init: the initial particles (P, n), inside the bounds.
        settings: ``pop_size``, ``max_generations``, ``w``, ``c1``, ``c2``.
        gen: the swarm's generator.
        time_budget: wall-time cap [s] (checked after each iteration, as pymoo's).
        patience: stop once the best cost has moved by at most 1e-9 for this many
            iterations (None: never).
    """
    from pymoo.algorithms.soo.nonconvex.pso import pso_equation
    from pymoo.operators.mutation.pm import mut_pm
    from pymoo.operators.repair.bounds_repair import repair_random_init

    t0 = time.monotonic()
    n_var = xl.size
    v_max = PSO_MAX_VELOCITY_RATE * (xu - xl)
    x = init.copy()
    f = np.asarray(cost_fn(x), dtype=float).reshape(-1)
    v = gen.random(x.shape) * v_max[None, :]
    p_x, p_f = x.copy(), f.copy()   # the personal bests
    gens, still = 1, 0
    best = float(np.min(p_f))
    prob_var = np.array([min(0.5, 1.0 / n_var)])
    w, c1, c2 = settings.w, settings.c1, settings.c2
    while gens < settings.max_generations and time.monotonic() - t0 < time_budget:
        k = int(np.argmin(p_f))   # the social best: the best personal best
        s_x = np.repeat(p_x[k][None, :], x.shape[0], axis=0)
        xp, vp = pso_equation(x, p_x, s_x, v, v_max, w, c1, c2, random_state=gen)
        for _ in range(PSO_REDRAWS):
            m = np.where(np.any((xp < xl) | (xp > xu), axis=1))[0]
            if m.size == 0:
                break
            xp[m], vp[m] = pso_equation(x[m], p_x[m], s_x[m], v[m], v_max, w, c1, c2,
                                        random_state=gen)
        xp = repair_random_init(xp, x, xl, xu, random_state=gen)
        eta = np.array([gen.uniform(*PSO_MUTATION_ETA)])
        mutant = mut_pm(p_x[k][None, :].copy(), xl, xu, eta, prob_var, at_least_once=False,
                        random_state=gen)
        # pymoo sets the best particle's move to its personal best, mutated (or not)
        xp[k] = mutant[0] if gen.random() <= PSO_MUTATION_PROB else p_x[k]
        f = np.asarray(cost_fn(xp), dtype=float).reshape(-1)
        better = f < p_f
        p_x[better], p_f[better] = xp[better], f[better]
        x, v = xp, vp
        gens += 1
        now = float(np.min(p_f))
        still = still + 1 if abs(best - now) <= 1e-9 else 0
        best = now
        if patience is not None and still >= patience:
            break
    k = int(np.argmin(p_f))
    return SwarmResult(x=p_x[k].copy(), cost=float(p_f[k]), generations=gens,
                       time_capped=gens < settings.max_generations and patience is None)
