"""Evidence across windows: a Kalman filter on the estimated parameters.

One window of a noisy or weakly excited machine often cannot pin a parameter down (the hydraulic
damping D is 7 Pa of 50 kPa of pressure), yet every window carries some information about it.
As MATLAB's recursive estimators do (``recursiveARX`` with a Kalman-filter adaptation; Ljung,
System Identification, Section 11.2), the parameters are tracked across windows by a Kalman
filter whose measurement is each window's least-squares estimate with its covariance.

**Model.** The state is the natural logarithm of each estimated parameter and, with
``model = "trend"``, its rate of change [1/s]: a local linear trend, so a slow degradation
(the paper's exponential laws) is followed without the lag a random walk has::

    ln p(t + dt) = ln p(t) + dt * rate(t) + w_level,   var(w_level) = q_level^2 dt (+ trend terms)
    rate(t + dt) = rate(t) + w_rate,                   var(w_rate)  = q_rate^2 dt

**Measurement.** A window's least-squares problem, linearised at the prediction (the extended
Kalman filter): its residuals and their Jacobian with respect to every estimated parameter (the
window's initial state marginalised), each output weighted by its residual variance (so model
error weakens the evidence). Its information is nearly zero along directions the window does not
determine, so such a window moves the fused value only where it knows something. Windows that
fail the model check are not fused. A window whose evidence is far beyond the prediction's
uncertainty (a sudden change, not a drift) inflates the prediction so the filter follows at
once.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numba import njit
from pydantic import Field, StrictFloat

from twinwatch._table import StrictTable
from twinwatch.twin.estimation.polish import Polished
from twinwatch.twin.estimation.problem import WindowProblem
from twinwatch.twin.model import FloatArray

#: Largest change of a level (ln-parameter) in one Gauss-Newton step of :meth:`update`.
MAX_STEP = 0.5
#: The steps of the window's Jacobian at each iteration
#: (:meth:`~twinwatch.twin.estimation.fit.LocalFit.sensitivity`): the smallest and the largest
#: of the gate's, half the twin calls at each of the iterations.
FUSION_STEPS = (1e-6, 1e-3)
#: The first parameter a window could not determine is fused only when at least this share of
#: its information in the window is its own (1 - R^2 against the parameters the gate admitted
#: and the initial state: its conditional over its marginal variance). Along a valley the
#: window's evidence on it is a combination with an admitted one, and the filter, fed that
#: every window, walks along the valley (Ke beside an admitted D has 1e-7 of its own).
OWN_INFORMATION = 0.01
#: Largest change of a level (ln-parameter) one window's sudden change may make: a window
#: whose evidence, after the jump test inflated the prediction, moves a parameter it
#: determines by more than a factor 2 is an outlier of the model, not wear, and is not fused.
JUMP_LIMIT = math.log(2.0)
#: Windows in a row whose evidence moves the same parameter beyond :data:`JUMP_LIMIT` by
#: about the same factor (within :data:`OUTLIER_AGREE`, ln) after which the move is the
#: machine's and is fused: one odd window is the model's outlier, a step the windows keep
#: telling is not (a seized bearing's D x4 at once).
OUTLIER_RUN = 3
OUTLIER_AGREE = 0.1
#: Windows over which a parameter's innovations are summed to test for a level shift the
#: single-window jump test misses (:meth:`ParameterFusion.update`): a step whose innovations
#: are a few standard errors per window, never the jump test's threshold.
SHIFT_WINDOWS = 6


class FusionConfig(StrictTable):
    """The ``[estimation.fusion]`` table: tracking parameters across windows."""

    enabled: bool = Field(True, description="fuse the windows' estimates (Kalman filter)")
    max_rel_std: StrictFloat = Field(
        0.02, gt=0, allow_inf_nan=False,
        description="publish the fused value of a parameter this window does not determine "
        "(status fused) when its relative standard error is at most this: the fusion's own "
        "gate, apart from the window's [estimation] max_rel_std")
    model: Literal["trend", "random_walk"] = Field(
        "trend", description="trend: level and rate of change (follows slow degradations "
        "without lag); random_walk: level only")
    level_noise: StrictFloat = Field(
        2e-4, ge=0, allow_inf_nan=False,
        description="random-walk intensity of a parameter's logarithm [1/sqrt(s)]: how fast "
        "it may wander unexplained")
    rate_noise: StrictFloat = Field(
        1e-4, ge=0, allow_inf_nan=False,
        description="trend model: random-walk intensity of the rate of change [1/s^1.5]: how "
        "fast a degradation may speed up")
    initial_std: StrictFloat = Field(
        0.5, gt=0, allow_inf_nan=False,
        description="relative standard deviation of the starting value (the nameplate)")
    initial_rate_std: StrictFloat = Field(
        1e-3, gt=0, allow_inf_nan=False,
        description="trend model: standard deviation of the starting rate [1/s]")
    jump_threshold: StrictFloat = Field(
        25.0, gt=0, allow_inf_nan=False,
        description="an innovation whose normalised square per parameter exceeds this is a "
        "sudden change: the prediction is inflated so the filter follows it")


@dataclass
class FusionState:
    """The filter's state: mean (n_state,) and covariance (n_state, n_state), the time of
    the last update [s] (None before the first window), and per parameter the sum of the
    fused windows' squared normalised innovations and their count (2, n) (the Birge ratio's,
    :meth:`ParameterFusion.birge`; None: none yet)."""

    mean: FloatArray
    cov: FloatArray
    t: float | None
    scatter: FloatArray | None = None

    def copy(self) -> FusionState:
        return FusionState(self.mean.copy(), self.cov.copy(), self.t,
                           None if self.scatter is None else self.scatter.copy())

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"mean": [float(v) for v in self.mean],
                               "cov": [[float(v) for v in row] for row in self.cov],
                               "t": self.t}
        if self.scatter is not None:
            out["scatter"] = [[float(v) for v in row] for row in self.scatter]
        return out

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> FusionState:
        """:meth:`as_dict` read back (a state saved before the scatter: none yet)."""
        sc = d.get("scatter")
        return cls(np.asarray(d["mean"], dtype=float), np.asarray(d["cov"], dtype=float),
                   None if d.get("t") is None else float(d["t"]),
                   None if sc is None else np.asarray(sc, dtype=float))


class ParameterFusion:
    """Kalman filter over the logarithms of the estimated parameters.

    Args:
        names: the estimated parameters.
        start: their starting values [SI] (the nameplate or the trusted values), (n,).
        config: the ``[estimation.fusion]`` table.
    """

    def __init__(self, names: tuple[str, ...], start: FloatArray, config: FusionConfig) -> None:
        self.names = names
        self.config = config
        self.n = len(names)
        self.trend = config.model == "trend"
        self.outliers = 0   # windows not fused: a sudden change beyond JUMP_LIMIT
        #: the last such window's parameter moved most and its factor (new / predicted)
        self.last_outlier: tuple[str, float] | None = None
        # per parameter, its last windows' normalised innovations and innovations (ln)
        self._shift: dict[int, deque[tuple[float, float]]] = {}
        #: the trend model's transition F and process noise Q of the last (dt, level_noise,
        #: rate_noise) (:meth:`_predict`)
        self._transition: tuple[Any, FloatArray, FloatArray] = (None, np.eye(0), np.eye(0))
        self.reset(start)

    @property
    def n_state(self) -> int:
        return 2 * self.n if self.trend else self.n

    def reset(self, start: FloatArray) -> None:
        """Start over from ``start`` [SI] with the configured prior."""
        n, c = self.n, self.config
        mean = np.zeros(self.n_state)
        mean[:n] = np.log(np.asarray(start, dtype=float))
        var = np.full(self.n_state, c.initial_std**2)
        if self.trend:
            var[n:] = c.initial_rate_std**2
        self.state = FusionState(mean, np.diag(var), None, np.zeros((2, n)))
        self._shift = {}
        self._outlier_run: list[tuple[int, float]] = []   # (parameter, ln move) in a row

    # -- the filter -------------------------------------------------------------------------
    def _predict(self, dt: float) -> tuple[FloatArray, FloatArray]:
        n, c = self.n, self.config
        s = self.state
        if dt <= 0:
            return s.mean.copy(), s.cov.copy()
        if not self.trend:
            return s.mean.copy(), s.cov + np.eye(n) * c.level_noise**2 * dt
        key = (dt, c.level_noise, c.rate_noise)
        if self._transition[0] != key:  # the windows come at one spacing: built once
            f = np.eye(2 * n)
            f[:n, n:] = np.eye(n) * dt
            ql, qr = c.level_noise**2, c.rate_noise**2
            q = np.zeros((2 * n, 2 * n))
            q[:n, :n] = np.eye(n) * (ql * dt + qr * dt**3 / 3.0)
            q[:n, n:] = q[n:, :n] = np.eye(n) * (qr * dt**2 / 2.0)
            q[n:, n:] = np.eye(n) * (qr * dt)
            self._transition = (key, f, q)
        _, f, q = self._transition
        return f @ s.mean, f @ s.cov @ f.T + q

    def predict(self, t: float) -> tuple[FloatArray, FloatArray]:
        """The prediction (mean, covariance) at time ``t`` [s] (not stored)."""
        dt = 0.0 if self.state.t is None else t - self.state.t
        return self._predict(dt)

    def update(self, t: float,
               linearize: Callable[[FloatArray], tuple[FloatArray, FloatArray]] | None = None,
               row_var: FloatArray | None = None, n_nuisance: int = 0,
               iterations: int = 8, cols: np.ndarray | None = None,
               bounds: tuple[FloatArray, FloatArray] | None = None,
               start: FloatArray | None = None, step_tol: float = 0.0,
               firm: np.ndarray | None = None) -> bool:
        """Advance to time ``t`` [s] and fuse one window.

        The window's least-squares problem and the prediction are combined as the iterated
        extended Kalman filter does: Gauss-Newton on ``||r(p)||^2_W + ||p - p_pred||^2_{P^-1}``,
        re-linearised at each iterate (a single linearisation at the prediction is not
        enough on a window that determines the parameters).

        Args:
            t: the window's middle [s].
            linearize: ln-parameters (n,) -> (Jacobian (M, len(cols) + n_nuisance) of the
                window's residuals with respect to the ``cols`` ln-parameters then the window's
                nuisance variables, residuals (M,)) there; None: advance without a measurement
                (a window that failed its model check).
            row_var: (M,) the variance of each residual row.
            n_nuisance: trailing nuisance columns of the Jacobian (no prior: marginalised).
            iterations: most Gauss-Newton iterations.
            cols: the parameters (positions) the window informs; the others carry no
                evidence from it (default: all).
            bounds: (lower, upper) ln-parameter bounds (n,): the levels are kept within them
                and each Gauss-Newton step moves a level by at most :data:`MAX_STEP` (after
                a jump, its prior inflated, a step can overflow the next prediction).
            start: ln-parameters (n,) to start the iterations from at ``cols`` (the window's
                own least-squares optimum: the posterior's mode lies between it and the
                prediction); default the prediction.
            step_tol: also stop once no level moves by more than this share of its posterior
                standard error (0: only at 1e-9; the numerical Jacobian's steps of ~1e-5
                never reach 1e-9).
            firm: the parameters (positions) the window determines (default: ``cols``): a
                jump inflates their levels' variances only.

        Returns:
            Whether the window's evidence was a jump (the prediction was inflated). A jump
            that would move a level of ``firm`` by more than :data:`JUMP_LIMIT` is an outlier:
            the filter only advances (counted in ``outliers``) and False is returned.
        """
        mean, cov = self.predict(t)
        scatter = self._scatter()
        predicted = FusionState(mean.copy(), cov.copy(), t, scatter.copy())
        jump = False
        if linearize is not None and row_var is not None:
            n = self.n
            sel = np.arange(n) if cols is None else np.asarray(cols, dtype=int)
            k = sel.size
            w = 1.0 / np.maximum(row_var, 1e-300)
            h = np.zeros((n, self.n_state))
            h[:, :n] = np.eye(n)
            sel_ix = np.ix_(sel, sel)

            def evidence(x: FloatArray) -> tuple[FloatArray, FloatArray]:
                """The window's information (n, n) and gradient (n,) at ln-parameters x, its
                nuisance variables marginalised."""
                jac, r0 = linearize(x)
                big = jac.T @ (jac * w[:, None])
                g = jac.T @ (w * r0)
                sub, gsub = big[:k, :k], g[:k]
                if n_nuisance:
                    inn = _safe_inverse(big[k:, k:])
                    sub = sub - big[:k, k:] @ inn @ big[k:, :k]
                    gsub = gsub - big[:k, k:] @ inn @ g[k:]
                info = np.zeros((n, n))
                grad = np.zeros(n)
                info[sel_ix] = 0.5 * (sub + sub.T)
                grad[sel] = gsub
                return info, grad

            info, grad = evidence(mean[:n])
            # The window's own Gauss-Newton step against the prediction's uncertainty:
            # (P + R)^-1 = I - I (P^-1 + I)^-1 I with I = R^-1 (Woodbury), so directions the
            # window does not determine (zero information) add nothing.
            step = -_safe_inverse(info) @ grad
            p_inv = _safe_inverse(cov[:n, :n])
            s_inv = info - info @ _safe_inverse(p_inv + info) @ info
            rank = int(np.count_nonzero(np.linalg.eigvalsh(info)
                                        > 1e-12 * max(float(np.abs(info).max()), 1e-300)))
            nis = float(step @ s_inv @ step) / max(rank, 1)
            # the window's own (marginal) covariance on the parameters it informs
            r_sel = _safe_inverse(info[sel_ix]) if sel.size else np.zeros((0, 0))
            if math.isfinite(nis) and nis > self.config.jump_threshold:
                # a sudden change is a step of the levels, not of their rates: each level's
                # variance grows, the rates' and the cross terms stay; only the levels the
                # window determines (the first parameter it could not determine is fused from
                # weak evidence, which an inflated prior places anywhere along its valley)
                cov = cov.copy()
                levels = sel if firm is None else np.asarray(firm, dtype=int)
                cov[levels, levels] *= nis / self.config.jump_threshold
                jump = True
                self._shift = {}
            else:
                jump = self._level_shift(step, r_sel, cov, sel)
            z2 = self._normalised_innovations(step, r_sel, cov, sel)
            y_prior = _safe_inverse(cov)
            x = mean.copy()
            if start is not None:
                x[sel] = np.asarray(start, dtype=float)[sel]
                if bounds is not None:
                    x[:n] = np.clip(x[:n], bounds[0], bounds[1])
                info, grad = evidence(x[:n])
            hess_inv = None
            for it in range(iterations):
                if it:
                    info, grad = evidence(x[:n])
                hess = y_prior + h.T @ info @ h
                gx = y_prior @ (x - mean) + h.T @ grad
                hess_inv = _safe_inverse(hess)
                dx = -hess_inv @ gx
                if not np.isfinite(dx).all():
                    break
                big_step = float(np.abs(dx[:n]).max())
                if big_step > MAX_STEP:
                    dx = dx * (MAX_STEP / big_step)
                x = x + dx
                if bounds is not None:
                    x[:n] = np.clip(x[:n], bounds[0], bounds[1])
                if float(np.abs(dx[:n]).max()) < 1e-9:
                    break
                if step_tol > 0 and (np.abs(dx[:n]) <= step_tol * np.sqrt(
                        np.maximum(hess_inv.diagonal()[:n], 0.0))).all():
                    break
            if jump:
                at = np.asarray(sel if firm is None else firm, dtype=int)
                moved = np.abs(x[:n] - mean[:n])[at]
                if moved.size and float(np.max(moved)) > JUMP_LIMIT:
                    worst = int(at[int(np.argmax(moved))])
                    ln_move = float(x[worst] - mean[worst])
                    run = self._outlier_run
                    if run and (run[-1][0] != worst
                                or abs(run[-1][1] - ln_move) > OUTLIER_AGREE):
                        run.clear()
                    run.append((worst, ln_move))
                    if len(run) < OUTLIER_RUN:   # else: the windows keep telling it: fused
                        self.outliers += 1
                        self.last_outlier = (self.names[worst], math.exp(ln_move))
                        self.state = predicted
                        return False
            self._outlier_run = []
            # the last iteration's inverse Hessian is the posterior's (the same information)
            cov_post = (_safe_inverse(y_prior + h.T @ info @ h) if hess_inv is None
                        else hess_inv)
            mean = x
            cov = 0.5 * (cov_post + cov_post.T)
            for i, v in z2.items():
                scatter[0, i] += v
                scatter[1, i] += 1.0
        self.state = FusionState(mean, cov, t, scatter)
        return jump

    def _scatter(self) -> FloatArray:
        """The state's Birge sums (2, n), zeros when it has none (or of another size)."""
        sc = self.state.scatter
        if sc is None or sc.shape != (2, self.n):
            return np.zeros((2, self.n))
        return sc.copy()

    @staticmethod
    def _normalised_innovations(step: FloatArray, r: FloatArray, cov: FloatArray,
                                sel: np.ndarray) -> dict[int, float]:
        """Per parameter the window informs, its squared normalised innovation: the window's
        own estimate against the prediction (``step``, ln), over the sum of the prediction's
        variance (after a jump's or a level shift's inflation) and the window's marginal one
        (the diagonal of ``r``, the inverse of its information on ``sel``); about 1 on average
        when the windows' standard errors and the filter are right."""
        if sel.size == 0:
            return {}
        out = {}
        for j, i in enumerate(sel):
            var = float(cov[i, i]) + float(r[j, j])
            d = float(step[i])
            if float(r[j, j]) > 0 and math.isfinite(var) and math.isfinite(d):
                out[int(i)] = d * d / var
        return out

    def _level_shift(self, step: FloatArray, r: FloatArray, cov: FloatArray,
                     sel: np.ndarray) -> bool:
        """The windowed test for a level shift (a generalised likelihood ratio over the last
        :data:`SHIFT_WINDOWS` windows; Basseville and Nikiforov, *Detection of Abrupt
        Changes*, 1993, Section 2.4): per parameter the window informs, its innovation ``d``
        (the window's own estimate against the prediction, ln) over its standard deviation
        (the prediction's and the window's marginal variances, ``r``'s diagonal as in
        :meth:`_normalised_innovations`) is kept; when, for the last m
        windows, ``(sum z)^2 / m`` exceeds ``jump_threshold`` the level has moved by about the
        innovations' mean and the prediction's variance of that parameter (``cov``, changed in
        place) grows by its square, so the filter follows. Returns whether one did."""
        if sel.size == 0:
            return False
        shifted = False
        for j, i in enumerate(sel):
            r_ii = float(r[j, j])
            var = float(cov[i, i]) + r_ii
            if not (r_ii > 0 and math.isfinite(var) and math.isfinite(float(step[i]))):
                continue
            d = float(step[i])
            hist = self._shift.setdefault(int(i), deque(maxlen=SHIFT_WINDOWS))
            hist.append((d / math.sqrt(var), d))
            z_sum = d_sum = 0.0
            for m, (z, di) in enumerate(reversed(hist), start=1):
                z_sum += z
                d_sum += di
                if m >= 2 and z_sum * z_sum / m > self.config.jump_threshold:
                    cov[i, i] += (d_sum / m) ** 2
                    hist.clear()
                    shifted = True
                    break
        return shifted

    # -- results ----------------------------------------------------------------------------
    def values(self) -> dict[str, float]:
        """Fused value of each parameter [SI]."""
        return {n: float(math.exp(self.state.mean[i])) for i, n in enumerate(self.names)}

    def rel_std(self) -> dict[str, float]:
        """Fused relative (ln) standard error of each parameter."""
        d = self.state.cov.diagonal()[:self.n]
        return {n: float(math.sqrt(max(d[i], 0.0))) for i, n in enumerate(self.names)}

    def birge(self) -> dict[str, float]:
        """Each parameter's Birge ratio across the fused windows (>= 1): the root mean square
        of their normalised innovations (the window's own estimate against the filter's
        prediction, over their combined standard error), 1 without any or when the windows
        scatter no more than their standard errors say.

        Birge (1932), *The calculation of errors by the method of least squares*, Phys. Rev.
        40, 207: when independent determinations of a quantity scatter about their weighted
        mean by more than their stated errors explain, the ratio ``R = sqrt(chi^2 / dof)``
        measures the error they share unstated, and the mean's standard error is multiplied
        by it. Here the determinations are the windows, the mean the filter's prediction, and
        ``chi^2 / dof`` the mean normalised innovation squared (Bar-Shalom, Li and
        Kirubarajan, *Estimation with Applications to Tracking and Navigation*, 2001, Section
        5.4). Read by the published interval only (:func:`fuse_window`); the filter's state
        keeps its own covariance."""
        sc = self._scatter()
        out = {}
        for i, n in enumerate(self.names):
            cnt = float(sc[1, i])
            out[n] = math.sqrt(max(1.0, float(sc[0, i]) / cnt)) if cnt > 0 else 1.0
        return out

    def rates(self) -> dict[str, float]:
        """Fused relative rate of change of each parameter [1/s] (0 for a random walk)."""
        if not self.trend:
            return dict.fromkeys(self.names, 0.0)
        return {n: float(self.state.mean[self.n + i]) for i, n in enumerate(self.names)}


def _first_held_step(problem: WindowProblem, polished: Polished, cols: np.ndarray,
                     base_ln: FloatArray) -> FloatArray | None:
    """Whether the window's last column of ``cols`` (the first parameter it could not
    determine) is fused, and from where.

    None when less than :data:`OWN_INFORMATION` of its information in the window is its own
    (1 - R^2 against the other columns and the initial state, at the polished point: the
    valley case). Else the Gauss-Newton step (len(cols),) on ``cols`` (the initial state
    free) from the polished point towards the window's own optimum with that parameter free:
    the filter's iterations start there (:meth:`ParameterFusion.update`'s ``start``): after
    the admitted-only polish the held parameter sits at its trusted value, which a degrading
    one has left. The sensitivity is the one the filter starts from (cached: no twin call
    more)."""
    nuis = problem.nuisance
    qq = base_ln.copy()
    qq[cols] = polished.point.v[:problem.n_est][cols]
    v_f = np.concatenate([np.clip(qq, problem.xl, problem.xu), polished.nuisance])
    jac, r0 = problem.local.sensitivity_and_residuals(v_f, np.concatenate([cols, nuis]),
                                                      steps=FUSION_STEPS)
    w = 1.0 / np.maximum(polished.row_var, 1e-300)
    big = jac.T @ (jac * w[:, None])
    e = cols.size - 1
    inv = _safe_inverse(big)
    own = float(big[e, e]) * float(inv[e, e])
    # 1 - R^2 = 1 / (I_ee (I^-1)_ee); a column with no information at all has none of its own
    if not (own > 0 and math.isfinite(own) and 1.0 / own >= OWN_INFORMATION):
        return None
    step = -(inv @ (jac.T @ (w * r0)))[:cols.size]
    # a step beyond MAX_STEP is no Gauss-Newton step of a valid linearisation: the polish
    # moved a parameter outside ``cols`` that the filter holds at its trusted value
    if not (np.isfinite(step).all() and float(np.abs(step).max()) <= MAX_STEP):
        return None
    return step


def _safe_inverse(a: FloatArray) -> FloatArray:
    """Inverse of a symmetric positive semi-definite matrix through its eigenvalues
    (near-zero ones treated as zero; non-finite entries as 0). Raises
    numpy.linalg.LinAlgError only if the eigen-decomposition does not converge."""
    a = np.asarray(a, dtype=float)
    if not np.isfinite(a).all():
        a = np.where(np.isfinite(a), a, 0.0)
    try:
        out: FloatArray = _safe_inverse_finite(np.ascontiguousarray(a))
    except ValueError as exc:  # numba's eigh did not converge: numpy's error, as before
        raise np.linalg.LinAlgError(str(exc)) from exc
    return out


@njit(cache=True, nogil=True)
def _safe_inverse_finite(a: FloatArray) -> FloatArray:
    """:func:`_safe_inverse` of a finite matrix, compiled (the same LAPACK ``syevd`` as
    numpy's, the same result to the bit)."""
    n = a.shape[0]
    sym = np.empty((n, n))      # 0.5 * (a + a.T), element by element (the same numbers:
    for i in range(n):          # numba's array expressions cost seconds of a cold start)
        for j in range(n):
            sym[i, j] = 0.5 * (a[i, j] + a[j, i])
    w, v = np.linalg.eigh(sym)
    big = 1e-300
    for i in range(n):
        big = max(big, abs(w[i]))
    inv = np.zeros(n)
    for i in range(n):
        if w[i] > 1e-12 * big:
            inv[i] = 1.0 / w[i]
    scaled = np.empty((n, n))   # v * inv
    for i in range(n):
        for j in range(n):
            scaled[i, j] = v[i, j] * inv[j]
    out: FloatArray = scaled @ v.T
    return out


def fuse_window(fusion: ParameterFusion, problem: WindowProblem, polished: Polished,
                selected: Sequence[int], t_mid: float, informative: bool, step_tol: float = 0.0,
                skip: Sequence[int] = ()) -> tuple[dict[str, tuple[float, float]], bool]:
    """Stage 5, the evidence across windows: fuse one window into the filter.

    A window that is ``informative`` (its fit good enough to trust and its model check
    passed) informs the parameters it determined and the first it could not (weakly: noise,
    not structure, may be why); the ones after it are held at their trusted values, as the
    window's estimate held them; one in ``skip`` is never informed. Its least-squares problem
    is re-linearised at each iterate of the filter (:meth:`ParameterFusion.update`) around the
    polished initial state, with the polish's row variances as weights. Any other window only
    advances the filter to its time.

    Args:
        fusion: the filter (its state is updated).
        problem: the window's problem.
        polished: the polish over every estimated parameter (initial state, row variances).
        selected: the positions the gate admitted, in priority order.
        t_mid: the window's middle [s].
        informative: fuse the window's evidence (else advance only).
        step_tol: :meth:`ParameterFusion.update`'s ``step_tol``.
        skip: positions never fused (the gate held them as not observable at this sample
            rate: :meth:`~twinwatch.twin.estimation.gate.IdentifiabilityGate.select`).

    Returns:
        (estimated parameter -> (fused value [SI], relative standard error: the filter's
        times its Birge ratio, :meth:`ParameterFusion.birge`), whether the window was a
        jump for the filter).
    """
    jump = False
    if informative:
        n_est = problem.n_est
        base_ln = np.log(problem.base[problem.pmap.idx])
        nuis = problem.nuisance
        local = problem.local
        firm = np.asarray(list(selected), dtype=int)
        held = [k for k in range(n_est) if k not in set(selected) and k not in set(skip)]
        # the admitted ones, then the first held one (the priority's next)
        cols = np.concatenate([firm, np.asarray(held[:1], dtype=int)])
        start = polished.point.v[:n_est]
        if held:
            step = _first_held_step(problem, polished, cols, base_ln)
            if step is None:
                cols = cols[:-1]
            else:
                start = start.copy()
                start[cols] = np.clip(start[cols] + step, problem.xl[cols], problem.xu[cols])

        def linearize(q: FloatArray) -> tuple[FloatArray, FloatArray]:
            """The window's residuals and Jacobian (columns ``cols``, then the initial state)
            at ln-parameters q."""
            qq = base_ln.copy()
            qq[cols] = q[cols]
            v_f = np.concatenate([np.clip(qq, problem.xl, problem.xu), polished.nuisance])
            active = np.concatenate([cols, nuis])
            # the residuals at v_f are the sensitivity batch's last row
            return local.sensitivity_and_residuals(v_f, active, steps=FUSION_STEPS)

        jump = fusion.update(t_mid, linearize, polished.row_var, nuis.size, cols=cols,
                             bounds=(problem.xl, problem.xu),
                             start=start, step_tol=step_tol, firm=firm)
    else:
        fusion.update(t_mid)
    f_val, f_std, ratio = fusion.values(), fusion.rel_std(), fusion.birge()
    return {n: (f_val[n], f_std[n] * ratio[n]) for n in problem.pmap.estimate}, jump


__all__ = ["FusionConfig", "FusionState", "ParameterFusion", "fuse_window"]
