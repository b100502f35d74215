"""A kept meta-model term of DT'' and the composition of terms into the twin (paper Eq. 3).

DT'' = DT(p, x) + sum_i U_i(z_i): each :class:`Term` is one meta-model (:mod:`.metamodels`) with
fitted parameters, its input (time or a measured channel) and the attach point of the model it
acts on. :func:`compose` sums the terms per attach point into the ``terms`` argument of
:meth:`TwinModel.simulate`.

Inputs are *measured* signals, so the terms do not depend on the simulated state: they are
computed once per particle and the composed twin still simulates a whole swarm in one call. An
additive term's value for sample k is taken at the middle of the step k -> k+1 (the twin holds
it over the step); a multiplicative one at sample k.

**Refinement across windows**. A kept term's parameters accumulate the evidence
of every window it has explained (:class:`Refinement`, :meth:`Term.refine`): each window's
least-squares polish of the term is a measurement of its active parameters with the
polish's covariance (the Jacobian of the window's residuals, each output weighted by its own
residual variance, :func:`~twinwatch.twin.estimation.fit.parameter_covariance`), and the term keeps
information-weighted combination, a Kalman filter whose only dynamics is the rewriting of a
time term to the current window's origin (:meth:`MetaModel.move_origin`):

    prediction:  x- = move(x, t_c' - t_c),  P- = F P F^T / lambda,  lambda = exp(-dt/memory)
    update:      K = P- (P- + R)^-1,  x = x- + K (y - x-),  P = (I - K) P-

with ``y`` the window's estimate (aligned to the prediction: a phase within pi of it) and ``R``
its covariance. The exponential forgetting (``memory`` [s]) lets the term follow a real
change; an innovation far outside ``P- + R`` (normalised square per parameter above
``jump_threshold``) is taken as a change and the old evidence is discounted at once.

A periodic term of time is refined in the coordinates of the window's centre, where amplitude,
frequency and phase are nearly uncorrelated, and published in absolute time: its frequency and
phase are refined *jointly*, so the frequency's precision grows with the time span the term has
explained. The published intervals (``params_std``) are the refined covariance carried to the
published coordinates.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from twinwatch.twin.discovery.metamodels import MetaModel, get_meta_model
from twinwatch.twin.model import AttachPoint, FloatArray, TwinModel, WindowData

logger = logging.getLogger(__name__)

#: The input name of a term of time.
TIME = "t"


@dataclass
class Refinement:
    """The evidence a kept term has accumulated on its active parameters.

    Attributes:
        mean: (n_active,) the refined active parameters, in the coordinates of ``origin``.
        cov: (n_active, n_active) their covariance.
        origin: time origin [s] of ``mean`` for a time term whose origin can move (the centre
            of the last window), or None: the term's own coordinates (its ``t_ref``).
        t: time of the last update (the window's centre) [s].
        windows: effective number of windows combined (each older one weighs ``lambda`` less).
        index: the last window whose evidence is in.
        prior: the state before that window's evidence (a second polish of the same window,
            after a discovery, replaces its evidence rather than counting it twice).
        pending: the last window's estimate if it was held out (it disagreed with the rest).
    """

    mean: FloatArray
    cov: FloatArray
    origin: float | None
    t: float
    windows: float = 1.0
    index: int = -1
    prior: Refinement | None = field(default=None, repr=False)
    pending: Refinement | None = field(default=None, repr=False)

    def as_dict(self) -> dict[str, Any]:
        return {"mean": [float(x) for x in self.mean],
                "cov": [[float(x) for x in row] for row in self.cov],
                "origin": self.origin, "t": self.t, "windows": self.windows,
                "index": self.index}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Refinement:
        origin = d.get("origin")
        return cls(np.array(d["mean"], dtype=float), np.array(d["cov"], dtype=float),
                   None if origin is None else float(origin), float(d["t"]),
                   float(d.get("windows", 1.0)), int(d.get("index", -1)))


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
        refinement: the evidence accumulated since (None before its first polish).
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
    refinement: Refinement | None = None

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
        out: FloatArray = self.meta.evaluate(self.params[None, :], self.z(window))[0]
        return out

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

    # -- refinement across windows ----------------------------------------------------------
    @property
    def movable(self) -> bool:
        """A time term whose origin can move (refined in the current window's coordinates)."""
        return self.input == TIME and self.meta.move_origin(self.params, 0.0) is not None

    def _act(self) -> FloatArray:
        return np.array(self.active, dtype=bool)

    def _full(self, x: FloatArray) -> FloatArray:
        q = np.zeros(len(self.meta.params))
        q[self._act()] = x
        return q

    def _moved(self, x: FloatArray, d: float) -> FloatArray:
        """Active parameters ``x`` rewritten from an origin ``d`` later."""
        q = self.meta.move_origin(self._full(x), d)
        if q is None:
            raise ValueError(f"a {self.meta.kind} term cannot move its origin")
        out: FloatArray = np.asarray(q)[self._act()]
        return out

    def _move_jacobian(self, x: FloatArray, d: float) -> FloatArray:
        """d(moved)/dx by central differences (exact for the affine rewritings)."""
        n = x.size
        jac = np.empty((n, n))
        for k in range(n):
            h = 1e-6 * max(abs(float(x[k])), 1.0)
            e = np.zeros(n)
            e[k] = h
            jac[:, k] = (self._moved(x + e, d) - self._moved(x - e, d)) / (2 * h)
        return jac

    def local_params(self, origin: float | None) -> FloatArray:
        """The parameters (len(meta.params),) written from ``origin`` (None: as published)."""
        if origin is None:
            return self.params.copy()
        return self._full(self._moved(self.params[self._act()], origin - self.t_ref))

    def at_origin(self, origin: float | None) -> Term:
        """This term written from ``origin`` (the same function of time), for a polish."""
        if origin is None:
            return replace(self, params=self.params.copy(), refinement=None)
        return replace(self, params=self.meta.canonical(self.local_params(origin)),
                       t_ref=origin, refinement=None)

    def _carry(self, mean: FloatArray, cov: FloatArray, src: float | None,
               dst: float | None) -> tuple[FloatArray, FloatArray]:
        """(mean, cov) of active parameters rewritten from origin ``src`` to ``dst``."""
        if src is None or dst is None or src == dst:
            return mean, cov
        f = self._move_jacobian(mean, dst - src)
        return self._moved(mean, dst - src), f @ cov @ f.T

    def predict(self, origin: float | None, t: float, memory: float) -> Refinement | None:
        """The refinement carried to ``origin`` and time ``t`` (forgetting over the time
        since its last update): the prior of a new window's evidence."""
        ref = self.refinement
        if ref is None:
            return None
        mean, cov = self._carry(ref.mean, ref.cov, ref.origin, origin)
        dt = t - ref.t if math.isfinite(ref.t) and t > ref.t else 0.0
        lam = math.exp(-dt / memory) if memory > 0 else 0.0
        cov = cov / lam if lam > 0 else np.full_like(cov, np.inf)
        return replace(ref, mean=mean, cov=cov,
                       origin=origin if ref.origin is not None else None, t=t,
                       windows=ref.windows * lam, prior=None)

    def refine(self, y: FloatArray, r_cov: FloatArray, origin: float | None, t: float,
               index: int, *, memory: float, jump_threshold: float) -> None:
        """Combine one window's estimate of the term with its accumulated evidence.

        Args:
            y: the window's estimate (len(meta.params),), written from ``origin``.
            r_cov: its covariance over the active parameters (n_active, n_active).
            origin: the time origin of ``y`` (None: the term's own coordinates).
            t: the window's centre [s].
            index: the window's index (a second call for the same window replaces the first).
            memory: time constant of the forgetting [s] (0: keep the last window only).
            jump_threshold: normalised squared innovation per parameter above which a window
                disagrees with the refined parameters. One such window is held out (a
                transient); a second in a row that agrees with the first is a change: the
                refinement restarts from the two.

        Sets :attr:`params` (as published: from ``t_ref``, canonical) and :attr:`refinement`.
        A window whose covariance is not finite leaves the term as it was.
        """
        act = self._act()
        r_cov = np.asarray(r_cov, dtype=float)
        if not np.all(np.isfinite(r_cov)) or not np.all(np.isfinite(y)):
            return
        if self.refinement is not None and self.refinement.index == index:
            self.refinement = self.refinement.prior
        before = self.refinement
        prior = self.predict(origin, t, memory)
        if prior is not None and (prior.origin is None) != (origin is None):
            prior = None  # the coordinates changed (a restored term): start again
        ref_p = self._full(prior.mean) if prior is not None else None
        y_act = np.asarray(self.meta.align(self.meta.canonical(y), ref_p)
                           if ref_p is not None else self.meta.canonical(y))[act]
        pending = None
        if prior is None or not np.all(np.isfinite(prior.cov)):
            mean, cov, windows = y_act, r_cov, 1.0
        else:
            d2 = _nis(y_act - prior.mean, prior.cov + r_cov)
            if d2 <= jump_threshold:
                mean, cov = _fuse(prior.mean, prior.cov, y_act, r_cov)
                windows = prior.windows + 1.0
            else:
                held = prior.pending
                p_mean = p_cov = None
                if held is not None and (held.origin is None) == (origin is None):
                    p_mean, p_cov = self._carry(held.mean, held.cov, held.origin, origin)
                    p_mean = np.asarray(self.meta.align(self._full(p_mean),
                                                        self._full(y_act)))[act]
                if p_mean is not None and p_cov is not None and _nis(
                        y_act - p_mean, p_cov + r_cov) <= jump_threshold:
                    logger.info("meta-model term %s changed: windows %d and %d agree with "
                                "each other, not with its refined parameters; refinement "
                                "restarts from them", self.expression(), index - 1, index)
                    mean, cov = _fuse(p_mean, p_cov, y_act, r_cov)
                    windows = 2.0
                else:
                    logger.debug("meta-model term %s: window %d lies %.1f standard deviations "
                                 "from its refined parameters: held out", self.expression(),
                                 index, math.sqrt(d2 * y_act.size))
                    mean, cov, windows = prior.mean, prior.cov, prior.windows
                    pending = Refinement(y_act, r_cov, origin, t, 1.0, index)
        # the representative nearest zero (a periodic term's phase wrapped: it grows by
        # b*dt from window to window in the moving coordinates)
        mean = np.asarray(self.meta.align(self._full(mean), np.zeros(act.size)))[act]
        self.refinement = Refinement(mean, cov, origin, t, windows, index, prior=before,
                                     pending=pending)
        published = mean if origin is None else self._moved(mean, self.t_ref - origin)
        self.params = self.meta.canonical(self._full(published))

    @property
    def params_std(self) -> FloatArray | None:
        """Standard errors of the published active parameters (n_active,) from the refined
        covariance (None before the first refinement)."""
        ref = self.refinement
        if ref is None:
            return None
        cov = ref.cov
        if ref.origin is not None and ref.origin != self.t_ref:
            g = self._move_jacobian(ref.mean, self.t_ref - ref.origin)
            cov = g @ cov @ g.T
        d = np.diag(cov)
        return np.sqrt(np.where(d >= 0, d, np.nan))

    def as_dict(self) -> dict[str, Any]:
        """The health message's ``terms`` entry (README: "The health message")."""
        std = self.params_std
        names = [n for n, a in zip(self.meta.params, self.active, strict=True) if a]
        return {
            "kind": self.meta.kind,
            "attach": self.attach.name,
            "mode": self.attach.mode,
            "input": self.input,
            "t_ref": self.t_ref,
            "params": {n: float(v) for n, v, a in
                       zip(self.meta.params, self.params, self.active, strict=True) if a},
            "params_std": ({n: _finite(float(v)) for n, v in zip(names, std, strict=True)}
                           if std is not None else {n: None for n in names}),
            "weight": self.weight,
            "significance": _finite(self.significance),
            "evidence_windows": self.refinement.windows if self.refinement else 0.0,
            "equation": self.equation(),
            "meaning": self.meaning(),
            "since_window": self.since_window,
        }

    def state_dict(self) -> dict[str, Any]:
        """:meth:`as_dict` plus the refinement's full state (its correlations), for
        persistence."""
        d = self.as_dict()
        if self.refinement is not None:
            d["refinement"] = self.refinement.as_dict()
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], model: TwinModel) -> Term:
        """Rebuild a term from :meth:`state_dict` or :meth:`as_dict` (persistence). From
        :meth:`as_dict` alone, the refinement restarts from the published intervals
        (``params_std``, correlations unknown)."""
        meta = get_meta_model(d["kind"])
        params = np.array([float(d["params"].get(n, 0.0)) for n in meta.params])
        active = tuple(n in d["params"] for n in meta.params)
        sig = d.get("significance")
        term = cls(meta=meta, attach=model.attach_point(d["attach"]), input=d["input"],
                   params=params, active=active, t_ref=float(d.get("t_ref", 0.0)),
                   significance=math.inf if sig is None else float(sig),
                   since_window=int(d.get("since_window", 0)))
        if d.get("refinement"):
            term.refinement = Refinement.from_dict(d["refinement"])
        else:
            std = d.get("params_std") or {}
            names = [n for n, a in zip(meta.params, active, strict=True) if a]
            sd = np.array([np.nan if std.get(n) is None else float(std[n]) for n in names])
            if names and np.all(np.isfinite(sd)):
                term.refinement = Refinement(
                    params[np.array(active)], np.diag(sd**2),
                    term.t_ref if term.movable else None, math.nan,
                    float(d.get("evidence_windows") or 1.0))
        return term


def _nis(nu: FloatArray, s_cov: FloatArray) -> float:
    """Normalised innovation squared per parameter, ``nu^T S^-1 nu / n``."""
    return float(nu @ np.linalg.lstsq(s_cov, nu, rcond=None)[0]) / max(nu.size, 1)


def _fuse(m1: FloatArray, c1: FloatArray, m2: FloatArray, c2: FloatArray
          ) -> tuple[FloatArray, FloatArray]:
    """The information-weighted combination of two estimates (the Kalman update of ``m1``
    by the measurement ``m2``): gain ``K = C1 (C1 + C2)^-1``."""
    gain = np.linalg.lstsq((c1 + c2).T, c1.T, rcond=None)[0].T
    mean = m1 + gain @ (m2 - m1)
    cov = c1 - gain @ c1
    return mean, 0.5 * (cov + cov.T)


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


__all__ = ["TIME", "Refinement", "Term", "compose", "format_terms", "term_input"]
