"""Hypothesis twins: every fault mode a change of the twin, fitted on the window's own data.

Multiple-model fault isolation (Willsky and Jones, "A generalized likelihood ratio approach to
the detection and estimation of jumps in linear systems", IEEE TAC 21(1), 1976; Basseville and
Nikiforov, *Detection of Abrupt Changes*, 1993, ch. 2 and 7; Isermann, *Fault-Diagnosis
Systems*, 2006, ch. 9-10): a fault mode of the library is a change of the twin (a parameter
scaled, several scaled together where the physics ties them, a reading's gain or offset, the
supply's ratio on an input, a meta-model term at an attach point, a reading stuck or clipped).
Each window the twin at this machine's healthy **baseline** is simulated once, and each change
once more as a sensitivity (a finite difference of a parameter's logarithm, a corrected input,
a term's basis function; the initial state's offsets are nuisance directions, exact because
the twin is linear in them). A change's effect on the window's residual is then a local
quadratic in its free size ``phi`` (one or two numbers):

    S_k(phi) = C_k - 2 B_k' phi + phi' A_k phi          (weighted squared residual, window k)

which sums over windows: the windows since a change point fit one size (a step) or a size and
its rate (a drift) by generalised least squares, and the generalised likelihood ratio against
the baseline is ``GLR = sum S0_k - min_phi sum S_k(phi)`` (Willsky and Jones' GLR with the
change time maximised over the windows kept, Basseville and Nikiforov Eq. 2.4.39). The few
best hypotheses are linearised again at their fitted size (Gauss-Newton), so a large change
(an inertia +50 %) is fitted as the twin would simulate it, not on the baseline's slope.

**The residual's statistics.** Each output's squared residual is weighed by ``kappa_j /
sigma_j^2``: ``sigma_j^2`` the larger of the baseline windows' residual variance and that left
by the window's best explanation (a Birge ratio: a window the library cannot explain weighs
less, Birge, Phys. Rev. 40, 1932), and ``kappa_j = (1 - rho_j)/(1 + rho_j)`` the share of
independent samples of an AR(1) residual with lag-1 correlation ``rho_j`` measured on the
baseline (the large-sample variance of a mean under AR(1) errors: Box, Jenkins and Reinsel,
*Time Series Analysis*, 4th ed., Eq. 2.1.13). A model error (the twin's integrator, a drive's
update between samples) leaves a residual correlated from sample to sample, so a twin that
misses the machine a little everywhere gains few effective samples and cannot make a
confident case for a change that merely reshapes it.

Nothing here is tuned: the weights come from this machine's baseline, the penalties are the
Bayesian information criterion's ``(q/2) ln n`` per freed number (Schwarz, Ann. Stat. 6(2),
1978) and the change point's uniform prior over the windows kept.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from functools import cached_property
from typing import Any

import numpy as np
from numba import njit

from twinwatch.twin.estimation.fit import WindowFit
from twinwatch.twin.model import FloatArray, TwinModel, WindowData

__all__ = ["LN_STEP", "Change", "Columns", "Fitted", "Hypothesis", "Track", "WindowTerms",
           "bounded_solve", "columns", "evidence_of", "periodic_angle", "window_basis"]

#: Finite-difference step of a parameter's (or a gain's, a supply ratio's) logarithm. The
#: twins are smooth in their parameters; 1e-4 keeps the truncation error (O(step)) far below
#: a 1 % noise's information while the simulation's rounding (1e-13 relative) stays negligible.
LN_STEP = 1e-4


@dataclass(frozen=True)
class Change:
    """One change of the twin (a fault mode's hypothesis is one change or a pair).

    Attributes:
        kind: ``scale`` (parameters scaled together: ``theta_i * exp(power_i * phi)``), ``gain``
            (a reading ``exp(phi)`` times the true value), ``offset`` (a reading plus ``phi``
            in the channel's unit), ``supply`` (the machine receives ``exp(phi)`` times the
            input it reports), ``term`` (a meta-model term at an attach point, its
            amplitude(s) free), ``stuck`` (a reading held constant), ``clipped`` (a reading
            limited at its extreme).
        target: the channel (gain, offset, supply, stuck, clipped) or attach point (term).
        powers: parameter -> power (scale).
        basis: the term's shape: ``constant``, ``coulomb`` (``-sign`` of the speed channel:
            a braking torque), ``periodic`` (``sin`` and ``cos`` of ``harmonic`` times the
            shaft angle: two amplitudes).
        harmonic: a periodic term's multiple of the shaft's rotation.
        low, high: the free size's plausible range (ln factor for scale and supply; ``g`` of a
            gain; a share of the reading's scale for an offset; the attach point's unit for a
            term; None: unbounded).
    """

    kind: str
    target: str = ""
    powers: tuple[tuple[str, float], ...] = ()
    basis: str = ""
    harmonic: float = 1.0
    low: float | None = None
    high: float | None = None

    @property
    def size(self) -> int:
        """Free numbers the change adds (0: stuck and clipped, fitted in closed form)."""
        if self.kind in ("stuck", "clipped"):
            return 0
        return 2 if self.kind == "term" and self.basis == "periodic" else 1

    def directions(self) -> list[tuple[object, ...]]:
        """The sensitivity directions this change is a combination of (see :func:`columns`)."""
        if self.kind == "scale":
            return [("p", name) for name, _ in self.powers]
        if self.kind == "term":
            if self.basis == "periodic":
                return [("term", self.target, "sin", self.harmonic),
                        ("term", self.target, "cos", self.harmonic)]
            return [("term", self.target, self.basis, 0.0)]
        if self.kind in ("gain", "offset", "supply"):
            return [(self.kind, self.target)]
        return []


@dataclass(frozen=True)
class Hypothesis:
    """One twin to test: the changes of one fault mode's alternative, or of a pair of modes.

    Attributes:
        faults: the fault ids it stands for (one, or two for a pair).
        changes: its changes (their free sizes concatenated in order).
        label: for a person (``Ra`` ``ia gain``).
    """

    faults: tuple[str, ...]
    changes: tuple[Change, ...]
    label: str

    # cached: a frozen hypothesis's size and closed form are read several times a window
    @cached_property
    def size(self) -> int:
        return sum(c.size for c in self.changes)

    @cached_property
    def nonlinear(self) -> bool:
        """A scale or term change is among its changes (the twin is not linear in it)."""
        return any(c.kind in ("scale", "term") for c in self.changes)

    @cached_property
    def consistent(self) -> bool:
        """A part's change (one size, or a steady drift, across the windows): every twin but
        a periodic term (its phase is each window's own) and a stuck or clipped reading."""
        return self.size > 0 and not any(c.kind == "term" and c.basis == "periodic"
                                         for c in self.changes)

    @cached_property
    def closed_form(self) -> Change | None:
        """The stuck or clipped reading this hypothesis is (fitted without sensitivities)."""
        for c in self.changes:
            if c.kind in ("stuck", "clipped"):
                return c
        return None

    def bounds(self) -> tuple[FloatArray, FloatArray]:
        lo, hi = [], []
        for c in self.changes:
            for _ in range(c.size):
                lo.append(-math.inf if c.low is None else c.low)
                hi.append(math.inf if c.high is None else c.high)
        return np.array(lo), np.array(hi)


def periodic_angle(window: WindowData, channel: str, harmonic: float) -> FloatArray:
    """``harmonic`` times the shaft angle [rad] over the window, shape (N,): the speed channel
    [rad/s] integrated by the trapezoid rule from 0 at the first sample (an unbalance turns with
    the shaft: its torque is ``a sin(angle) + b cos(angle)``, ISO 21940-11)."""
    w = np.asarray(window[channel], dtype=float)
    t = window.t
    ang = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t))])
    out: FloatArray = harmonic * ang
    return out


@dataclass
class WindowTerms:
    """What a term's basis needs from the window: the shaft speed channel (coulomb, periodic);
    empty: none."""

    speed_channel: str = ""


def window_basis(window: WindowData, direction: tuple[object, ...], terms: WindowTerms,
                 cache: dict[tuple[object, ...], FloatArray]) -> FloatArray:
    """A term direction's basis function over the window (N,): ``constant``, ``coulomb``
    (``-sign`` of the speed), ``sin`` or ``cos`` of the harmonic's shaft angle; kept in
    ``cache`` (direction -> its values over this window, ``("angle",)`` the shaft angle) for
    the window's other uses (its columns, each Gauss-Newton step's twins): computed once."""
    out = cache.get(direction)
    if out is not None:
        return out
    _, _, shape, harmonic = direction
    if shape == "constant":
        out = np.ones(window.n)
    elif not terms.speed_channel:
        raise ValueError(f"a {shape} term needs the library's speed_channel")
    elif shape == "coulomb":
        out = -np.sign(np.asarray(window[terms.speed_channel], dtype=float))
    else:
        ang = cache.get(("angle",))
        if ang is None:
            ang = cache[("angle",)] = periodic_angle(window, terms.speed_channel, 1.0)
        ang = float(harmonic) * ang  # type: ignore[arg-type]
        out = np.sin(ang) if shape == "sin" else np.cos(ang)
    cache[direction] = out
    return out


@dataclass
class Columns:
    """One window's baseline twin and its sensitivities, in normalised units (each output's
    error over its scale, samples 1..N-1: the first is the initial state).

    Attributes:
        y0: the baseline twin's outputs (N, n_out).
        r0: measured minus baseline, normalised (N-1, n_out).
        cols: direction -> the outputs' change per unit of the direction's number, normalised
            (N-1, n_out): the rows of ``mat``.
        mat: the directions' columns in the order asked for (n_dir, N-1, n_out).
        nuisance: the initial-state offsets' columns (n_init, N-1, n_out).
        scale: each output's scale (n_out,).
    """

    y0: FloatArray
    r0: FloatArray
    cols: dict[tuple[object, ...], FloatArray]
    mat: FloatArray
    nuisance: FloatArray
    scale: FloatArray


def _transformed(window: WindowData, channel: str, gain: float = 1.0, offset: float = 0.0
                 ) -> WindowData:
    ch = dict(window.channels)
    ch[channel] = (np.asarray(window[channel], dtype=float) - offset) * gain
    return replace(window, channels=ch)     # the same times (and their sample period, kept)


def columns(fit: WindowFit, theta: FloatArray, directions: Sequence[tuple[object, ...]],
            terms: WindowTerms, initial: FloatArray | None = None,
            bases: dict[tuple[object, ...], FloatArray] | None = None) -> Columns | None:
    """Simulate the baseline twin and each direction's sensitivity on one window.

    Directions: ``("p", name)`` the parameter's logarithm; ``("gain", channel)`` a reading's
    gain (measured = (1 + phi) x true); ``("offset", channel)`` a reading's offset [a share
    of the reading's scale: its RMS over the window, at least the output's floor];
    ``("supply", channel)`` the log-ratio of what the machine receives on an input to what
    it reports; ``("term", attach, shape, harmonic)`` a meta-model term's amplitude [the
    attach point's unit]. Parameter and term directions share one batched simulation; each
    channel correction of an input (the open-loop Va, the closed-loop Va that starts the
    controller's integrator) one more.

    Args:
        fit: the window's fit problem.
        theta: the baseline parameter vector (n_params,) [SI].
        directions: the directions wanted.
        terms: what the term bases need.
        initial: the initial-state offsets the baseline starts from (None: the fit's).
        bases: the window's term bases computed so far (:func:`window_basis`; None: none
            kept).

    Returns:
        The columns, or None when the baseline twin does not simulate the window.
    """
    model: TwinModel = fit.model
    window = fit.window
    names = model.parameter_names
    n_init = len(model.initial_states)
    init0 = np.zeros(n_init) if initial is None else np.asarray(initial, dtype=float)
    # the rows simulated: the baseline, each parameter and term direction, each initial state
    simulated = [i for i, d in enumerate(directions) if d[0] in ("p", "term")]
    p = 1 + len(simulated) + n_init
    th = np.repeat(np.asarray(theta, dtype=float)[None], p, axis=0)
    inits = np.repeat(init0[None], p, axis=0)
    steps = np.empty(len(simulated))
    tm: dict[str, FloatArray] = {}
    for row, i in enumerate(simulated, start=1):
        d = directions[i]
        if d[0] == "p":
            th[row, names.index(str(d[1]))] *= math.exp(LN_STEP)
            steps[row - 1] = LN_STEP
        else:
            attach = model.attach_point(str(d[1]))
            step = steps[row - 1] = 1e-3 * (attach.scale if attach.mode == "additive" else 1.0)
            arr = tm.get(attach.name)
            if arr is None:
                arr = tm[attach.name] = np.zeros((p, window.n))
            arr[row] = step * window_basis(window, d, terms, {} if bases is None else bases)
    for i in range(n_init):
        inits[p - n_init + i, i] += fit.initial_scale[i] * 1e-3
    y = fit.simulate(th, tm or None, inits if n_init else None)
    if not np.isfinite(y[0]).all():
        return None
    scale = fit.scale
    y0 = y[0]
    r0 = (fit.meas[1:] - y0[1:]) / scale
    mat = np.zeros((len(directions), *r0.shape))
    k = len(simulated)      # the simulated directions: usually the first k (a slice)
    mat[slice(0, k) if simulated == list(range(k)) else simulated] = (
        (y[1:1 + k, 1:] - y0[1:]) / (steps[:, None] * scale)[:, None])
    nuis = (y[p - n_init:, 1:] - y0[1:]) / ((fit.initial_scale * 1e-3)[:, None] * scale)[:, None]
    outputs = model.output_names
    for i, d in enumerate(directions):
        if d[0] not in ("gain", "offset", "supply"):
            continue
        ch = str(d[1])
        col = mat[i]
        if ch in outputs and d[0] != "supply":
            j = outputs.index(ch)
            # a gain per unit of (g - 1); an offset per unit of the output's scale (its RMS)
            col[:, j] = y0[1:, j] / scale[j] if d[0] == "gain" else 1.0
        if ch in model.inputs:
            if d[0] == "offset":     # per unit of the reading's RMS over the window
                rms = float(np.sqrt(np.mean(np.square(window[ch])))) + 1e-12
                w2 = _transformed(window, ch, offset=1e-3 * rms)
                step = 1e-3
            elif d[0] == "gain":      # the true input is the reading over exp(phi)
                w2 = _transformed(window, ch, gain=math.exp(-LN_STEP))
                step = LN_STEP
            else:                     # the machine receives exp(phi) x the input
                w2 = _transformed(window, ch, gain=math.exp(LN_STEP))
                step = LN_STEP
            y2 = model.simulate(th[:1], w2, None, inits[:1] if n_init else None)
            if np.isfinite(y2).all():
                col += (y2[0, 1:] - y0[1:]) / (step * scale)
    return Columns(y0=y0, r0=r0, cols=dict(zip(directions, mat, strict=True)), mat=mat,
                   nuisance=nuis, scale=scale)


def bounded_solve(a: FloatArray, b: FloatArray, lo: FloatArray, hi: FloatArray
                  ) -> FloatArray:
    """``argmin phi' a phi - 2 b' phi`` within ``lo <= phi <= hi`` (a few numbers: an active
    set, each out-of-range number fixed at its bound and the rest solved again)."""
    q = b.shape[0]
    if q == 1:
        a0 = float(a[0, 0])
        x1 = float(b[0]) / a0 if a0 > 0 else 0.0
        return np.array([min(max(x1, float(lo[0])), float(hi[0]))])
    # all free first (most solves end here)
    reg = 1e-12 * max(1.0, float(a.trace())) * np.eye(q)
    x = np.linalg.lstsq(a + reg, b, rcond=None)[0]
    fixed = (x < lo) | (x > hi)
    if fixed.any():
        x = np.clip(x, lo, hi)
        for _ in range(q):
            free = ~fixed
            if free.any():
                af = a[np.ix_(free, free)]
                bf = b[free] - a[np.ix_(free, fixed)] @ x[fixed]
                reg = 1e-12 * max(1.0, float(af.trace())) * np.eye(af.shape[0])
                x[free] = np.linalg.lstsq(af + reg, bf, rcond=None)[0]
            out = (x < lo) | (x > hi)
            if not (out & free).any():
                break
            x = np.clip(x, lo, hi)
            fixed |= out
    out_x: FloatArray = np.clip(x, lo, hi)
    return out_x


class Track:
    """One hypothesis's per-window fits over the windows kept (oldest first), in arrays.

    Attributes (views of length ``keep``, the first :attr:`m` rows filled; a window appended
    to a full track drops the oldest):
        gain: each window's log-likelihood gain over the baseline less its penalty [nats]:
            ``(S0_k - S_k)/2 - (q/2) ln n_k`` (the Bayesian information criterion's penalty for
            the window's own fitted size: Schwarz 1978).
        half: ``(S0_k - S_k)/2`` alone.
        ln_n: the window's effective samples' logarithm.
        phi: each window's fitted size (m, q); std: its standard error (m, q).
        t: the windows' middle times [s].
        info: the window could tell the change over its plausible range.
    """

    def __init__(self, q: int, keep: int) -> None:
        self.q, self.keep, self.m = q, keep, 0
        # one row a window (its fields side by side: :attr:`FIELDS`), a few rows beyond the
        # windows kept: a full track drops its oldest window by moving its start, and copies
        # its windows back to the front once the spare rows are used up
        self._start = 0
        self._buf = np.zeros((keep + self.SPARE, 5 + 2 * q))

    #: rows beyond ``keep``: the copy back to the front happens once per SPARE windows
    SPARE = 16

    #: each field's columns of a row
    FIELDS = {"gain": 0, "half": 1, "ln_n": 2, "t": 3, "info": 4, "phi": 5, "std": 6}

    def _cols(self, name: str) -> int | slice:
        i = self.FIELDS[name]
        return i if i < 5 else slice(5 + (i - 5) * self.q, 5 + (i - 4) * self.q)

    def _view(self, name: str) -> np.ndarray:
        return self._buf[self._start:self._start + self.keep, self._cols(name)]

    gain = property(lambda self: self._view("gain"))
    half = property(lambda self: self._view("half"))
    ln_n = property(lambda self: self._view("ln_n"))
    t = property(lambda self: self._view("t"))
    info = property(lambda self: self._view("info") != 0)
    phi = property(lambda self: self._view("phi"))
    std = property(lambda self: self._view("std"))

    def append(self, gain: float, phi: Sequence[float] | FloatArray,
               std: Sequence[float] | FloatArray, t: float, info: bool = True,
               half: float = 0.0, ln_n: float = 0.0) -> None:
        """One window's row: its gain [nats], size (q,), standard error (q,), middle time
        [s], whether it informs the size, its half log-likelihood ratio and ln n."""
        if self.m == self.keep:
            self._start += 1
            self.m -= 1
        k = self._start + self.m
        b = self._buf
        if k == b.shape[0]:
            b[:self.m] = b[self._start:k]
            self._start, k = 0, self.m
        row, q = b[k], self.q     # field by field (half the CPU of one tuple numpy converts)
        row[0], row[1], row[2], row[3], row[4] = gain, half, ln_n, t, info
        row[5:5 + q], row[5 + q:] = phi, std
        self.m += 1

    def __len__(self) -> int:
        return self.m

    def gains(self) -> FloatArray:
        """The windows' gains (m,) [nats], oldest first (a view)."""
        return self._buf[self._start:self._start + self.m, 0]

    def as_dict(self) -> dict[str, Any]:
        """The windows kept, as ``q`` and one array (a copy) per field, (m,) or (m, q):
        :func:`~twinwatch.io.encoding.to_json` writes them as lists, :meth:`from_dict` reads
        either."""
        out: dict[str, Any] = {"q": self.q}
        rows = self._buf[self._start:self._start + self.m]
        for name in self.FIELDS:
            out[name] = rows[:, self._cols(name)].copy()
        out["info"] = out["info"] != 0
        return out

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], keep: int) -> Track:
        tr = cls(int(d["q"]), keep)
        rows = zip(d["gain"], d["half"], d["ln_n"], d["t"], d["info"], d["phi"], d["std"],
                   strict=True)
        for g, h, ln, t, inf, p, sd in rows:
            tr.append(g, np.array(p, dtype=float), np.array(sd, dtype=float), t, bool(inf),
                      h, ln)
        return tr


def _stacked(tracks: Sequence[Track], first: int, end: int) -> np.ndarray:
    """The tracks' rows (every field, :attr:`Track.FIELDS`) over their windows ``first`` to
    ``end``, stacked: (H, end - first, 5 + 2q)."""
    return np.array([t._buf[t._start + first:t._start + end] for t in tracks])


def _field(rows: np.ndarray, name: str, q: int) -> np.ndarray:
    """One field of :func:`_stacked`'s rows as its own C-ordered array: (H, L) or (H, L, q)
    (what each field's own stack was: the arithmetic on it is the same)."""
    i = Track.FIELDS[name]
    return np.ascontiguousarray(rows[..., i] if i < 5 else
                                rows[..., 5 + (i - 5) * q:5 + (i - 4) * q])


@dataclass
class Fitted:
    """A hypothesis over the windows since its most likely change point.

    Attributes:
        evidence: its log-evidence against the baseline [nats]: the windows' gains summed
            since each change point, averaged over the change points (their uniform prior).
        start: index (into the windows kept) of the most likely change point.
        windows: windows since it.
        phi: the size fitted in the last windows since it (their inverse-variance mean, the
            last ``recent`` windows), shape (q,).
        std: its standard error (q,).
        share: the share of those windows whose gain is positive.
        informative: one of the last ``recent`` windows could tell: the change over its
            plausible range would have moved its weighted squared residual by more than 1.
        birge: the sizes' Birge ratio about their line since the change point.
        ended: the log-evidence that the change held from its change point to a later
            window and the machine is back at its baseline since (a repair) [nats]; -inf
            when not looked for.
    """

    evidence: float
    start: int
    windows: int
    phi: FloatArray
    std: FloatArray
    share: float
    informative: bool = True
    birge: float = 1.0
    ended: float = -math.inf


@njit(cache=True, nogil=True, error_model="numpy")
def _max_nan(x: float, floor: float) -> float:  # pragma: no cover - compiled
    """``np.maximum(x, floor)``: a NaN ``x`` stays NaN."""
    return x if (x >= floor or x != x) else floor


@njit(cache=True, nogil=True, error_model="numpy")
def _line_point(ra: float, rat: float, ratt: float, rap: float, rapt: float, rapp: float
                ) -> tuple[float, float, bool]:  # pragma: no cover - compiled
    """The weighted line of sizes in time through one point's sums (a size's information
    ``ra``, its times' moments ``rat``, ``ratt``, the sizes' ``rap``, ``rapt``, ``rapp``):
    its intercept ``alpha`` at the last window, the sizes' chi-square about it, and whether
    its slope is determined (otherwise the weighted mean, slope 0)."""
    det = ra * ratt - rat * rat
    good = det > 1e-12 * _max_nan(ra * ratt, 1e-300)
    if good:
        alpha = (ratt * rap - rat * rapt) / det
        beta = (ra * rapt - rat * rap) / det
    else:
        alpha = rap / _max_nan(ra, 1e-300)
        beta = 0.0
    return alpha, _max_nan(rapp - alpha * rap - beta * rapt, 0.0), good


@njit(cache=True, nogil=True, error_model="numpy")
def _suffix_lines(sds: FloatArray, tt: FloatArray, phis: FloatArray, half: FloatArray,
                  n_eff: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray,
                                              FloatArray, FloatArray]:  # pragma: no cover
    """:func:`evidence_many`'s sums since each window and their lines, for (H, m, q) sizes
    ``phis`` with standard errors ``sds`` at times ``tt`` (H, m) [s, 0 at the last window]:
    each window's information ``a = 1/sd^2`` (0 for a standard error 0 or not finite), the
    suffix sums of ``a``, ``a t``, ``a t^2``, ``a phi``, ``a phi t``, ``a phi^2`` (6, H, m,
    q), of ``half`` and ``n_eff`` (H, m), and each window's line since it: ``alpha`` (H, m,
    q), ``chi2`` and its numbers (H, m). Element by element the arithmetic of the numpy
    expressions it replaced, each sum from the last window back (``cumsum``'s order)."""
    h_n, m, q = phis.shape
    sums = np.empty((6, h_n, m, q))
    half_s = np.empty((h_n, m))
    n_s = np.empty((h_n, m))
    alpha = np.empty((h_n, m, q))
    # summed over the q sizes from 0.0 (0.0 + chi is chi: _line_point's chi is >= +0.0 or NaN)
    chi2 = np.zeros((h_n, m))
    params = np.zeros((h_n, m))
    for h in range(h_n):
        half_s[h, m - 1] = half[h, m - 1]
        n_s[h, m - 1] = n_eff[h, m - 1]
        for i in range(m - 2, -1, -1):
            half_s[h, i] = half_s[h, i + 1] + half[h, i]
            n_s[h, i] = n_s[h, i + 1] + n_eff[h, i]
        for j in range(q):
            for i in range(m - 1, -1, -1):
                sd = sds[h, i, j]
                a = 0.0
                if math.isfinite(sd) and sd > 0:
                    s = _max_nan(sd, 1e-300)
                    a = 1.0 / (s * s)
                t = tt[h, i]
                p = phis[h, i, j]
                terms = (a, a * t, a * t * t, a * p, a * p * t, a * (p * p))
                for k in range(6):
                    if i == m - 1:
                        sums[k, h, i, j] = terms[k]
                    else:
                        sums[k, h, i, j] = sums[k, h, i + 1, j] + terms[k]
        for i in range(m):
            for j in range(q):
                al, chi, good = _line_point(sums[0, h, i, j], sums[1, h, i, j],
                                            sums[2, h, i, j], sums[3, h, i, j],
                                            sums[4, h, i, j], sums[5, h, i, j])
                alpha[h, i, j] = al
                chi2[h, i] += chi
                params[h, i] += 2.0 if good else 1.0
    return sums, half_s, n_s, alpha, chi2, params


@njit(cache=True, nogil=True, error_model="numpy")
def _ended_lines(sums: FloatArray, ks: np.ndarray
                 ) -> tuple[FloatArray, FloatArray]:  # pragma: no cover - compiled
    """The line from each hypothesis's change point ``ks[h]`` to each window: the sums
    since ``ks[h]`` less those since the window (:func:`_suffix_lines`' sums), their
    chi-square and numbers (H, m); every window, those at or before ``ks[h]`` too (masked
    by the caller)."""
    _, h_n, m, q = sums.shape
    chi2 = np.zeros((h_n, m))
    params = np.zeros((h_n, m))
    for h in range(h_n):
        k0 = ks[h]
        for i in range(m):
            for j in range(q):
                _, chi, good = _line_point(
                    sums[0, h, k0, j] - sums[0, h, i, j], sums[1, h, k0, j] - sums[1, h, i, j],
                    sums[2, h, k0, j] - sums[2, h, i, j], sums[3, h, k0, j] - sums[3, h, i, j],
                    sums[4, h, k0, j] - sums[4, h, i, j], sums[5, h, k0, j] - sums[5, h, i, j])
                chi2[h, i] += chi
                params[h, i] += 2.0 if good else 1.0
    return chi2, params


def evidence_many(tracks: Sequence[Track], recent: int = 5) -> list[Fitted | None]:
    """:func:`evidence_of` (``consistent``) for many tracks of one size and length at once:
    the same arithmetic on (H, m, q) arrays (the sums since each window and their lines
    compiled, :func:`_suffix_lines`; the logarithms and exponentials numpy's).

    Args:
        tracks: H tracks, each of size ``q`` with ``m`` windows (the first one's; the others
            must match).
        recent: windows that say whether a track is informative now.

    Returns:
        H fits in ``tracks``' order (None each when ``m`` is 0): the log-evidence [nats] over
        the change points, Basseville and Nikiforov 1993 ch. 2 (the windows' gains summed
        since each one, averaged over them), the line of sizes since the most likely one,
        and whether the change ended.
    """
    if not tracks:
        return []
    m, q = tracks[0].m, tracks[0].q
    if m == 0:
        return [None] * len(tracks)
    rows_all = _stacked(tracks, 0, m)                                    # (H, m, 5 + 2q)
    half = _field(rows_all, "half", q)                                   # (H, m)
    tt = _field(rows_all, "t", q) - tracks[0].t[m - 1]
    phis = _field(rows_all, "phi", q)                                    # (H, m, q)
    sds = _field(rows_all, "std", q)
    n_eff = np.exp(_field(rows_all, "ln_n", q))
    # the weighted sums since each window (sa, sat, satt, sap, sapt, sapp: (6, H, m, q)) and
    # the line through them, in one compiled pass (numpy's arithmetic in numpy's order)
    sums, half_s, n_s, alpha, chi2, params = _suffix_lines(sds, tt, phis, half, n_eff)
    ev_c = half_s - 0.5 * chi2 - 0.5 * params * np.log(np.maximum(n_s, 2.0))   # (H, m)
    # (np.mean's, np.max's, np.sum's and np.any's reductions below without their wrappers)
    ks = ev_c.argmax(axis=1)
    rows = np.arange(len(tracks))
    top = ev_c[rows, ks]
    spread = np.add.reduce(np.exp(ev_c - top[:, None]), axis=1) / m
    # the change ended at a later window e > k: the line from k to e, the baseline since
    # (every e at once; those at or before k masked out)
    chi_e, par_e = _ended_lines(sums, ks)
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        ev_e = ((half_s[rows, ks][:, None] - half_s) - 0.5 * chi_e - 0.5 * par_e * np.log(
            np.maximum(n_s[rows, ks][:, None] - n_s, 2.0)))
    later = np.arange(m)[None, :] > ks[:, None]
    ended = np.maximum.reduce(np.where(later, ev_e, -np.inf), axis=1)
    since = np.arange(m)[None, :] >= ks[:, None]
    positive = np.add.reduce(since & (rows_all[:, :, 0] > 0), axis=1)
    informative = np.logical_or.reduce(rows_all[:, max(0, m - recent):, 4] != 0, axis=1)
    std = 1.0 / np.sqrt(np.maximum(sums[0][rows, ks], 1e-300))
    # as Python numbers once (the same values as float() of each)
    top_h, spread_h, ended_h = top.tolist(), spread.tolist(), ended.tolist()
    positive_h, informative_h = positive.tolist(), informative.tolist()
    chi2_k = chi2[rows, ks].tolist()
    out: list[Fitted | None] = []
    for h, k in enumerate(ks.tolist()):
        out.append(Fitted(top_h[h] + math.log(spread_h[h]), k, m - k, alpha[h, k], std[h],
                          positive_h[h] / (m - k), informative_h[h],
                          max(1.0, chi2_k[h] / max(q * (m - k - 2), 1)), ended_h[h]))
    return out


def evidence_of(track: Track, recent: int = 5, consistent: bool = True) -> Fitted | None:
    """The hypothesis's evidence over every change point of its windows (see :class:`Fitted`).

    ``consistent`` (a part that changes: one size, or a size drifting at a steady rate): the
    windows since a change point share one straight line of sizes in time. Each window's own
    fit gives its log-likelihood gain at its own size ``phi_k`` and that size's information
    ``a_k = 1/std_k^2``; near it the gain falls as ``a_k (phi - phi_k)^2 / 2``, so the line's
    evidence is ``sum_k (S0_k - S_k)/2 - chi2/2 - (p/2) ln N`` (``chi2`` the sizes' weighted
    scatter about the line, ``p`` its numbers, ``N`` the windows' effective samples). A twin
    that explains windows by sizes that jump from window to window (an intermittent load read
    as the bearings) loses what the jumps cost. The evidence that the change *ended* (the
    line held to a later window, the baseline since: a repair) is given too. Otherwise (a
    periodic term, whose phase is each window's own; a reading stuck): each window's gain less
    its own size's penalty.
    """
    if consistent:
        return evidence_many([track], recent)[0]
    return evidence_each_many([track], recent)[0]


def evidence_each_many(tracks: Sequence[Track], recent: int = 5) -> list[Fitted | None]:
    """:func:`evidence_of` (not ``consistent``: each window's own size) for many tracks of one
    size and length at once.

    Args:
        tracks: H tracks, each of size ``q`` with ``m`` windows (the first one's; the others
            must match).
        recent: the last windows whose sizes are averaged (inverse-variance) and that say
            whether a track is informative now.

    Returns:
        H fits in ``tracks``' order (None each when ``m`` is 0).
    """
    if not tracks:
        return []
    m = tracks[0].m
    if m == 0:
        return [None] * len(tracks)
    q = tracks[0].q
    rows_all = _stacked(tracks, 0, m)                                    # (H, m, 5 + 2q)
    g = _field(rows_all, "gain", q)                                      # (H, m)
    suffix_g = g[:, ::-1].cumsum(axis=1)[:, ::-1]
    # (np.mean's, np.sum's and np.any's reductions below without their wrappers)
    ks = suffix_g.argmax(axis=1)
    rows = np.arange(len(tracks))
    top = suffix_g[rows, ks]
    with np.errstate(invalid="ignore"):   # a row at -inf: its evidence is -inf, as alone
        spread = np.add.reduce(np.exp(suffix_g - top[:, None]), axis=1) / m
    since = np.arange(m)[None, :] >= ks[:, None]
    positive = np.add.reduce(since & (g > 0), axis=1)
    last = max(0, m - recent)
    recent_rows = rows_all[:, last:]
    informative = np.logical_or.reduce(recent_rows[:, :, 4] != 0, axis=1)
    # each one's size: the inverse-variance mean over its last windows since its change point
    lo = np.maximum(ks, last)
    use = (np.arange(last, m)[None, :] >= lo[:, None])[..., None]        # (H, L, 1)
    w = np.where(use, 1.0 / np.maximum(_field(recent_rows, "std", q), 1e-300) ** 2, 0.0)
    wsum = np.add.reduce(w, axis=1)
    phis = _field(recent_rows, "phi", q)
    phi = np.add.reduce(np.where(use, w * phis, 0.0), axis=1) / wsum
    std = 1.0 / np.sqrt(wsum)
    out: list[Fitted | None] = []
    for h in range(len(tracks)):
        k, t0 = int(ks[h]), float(top[h])
        ev = t0 + math.log(float(spread[h])) if math.isfinite(t0) else -math.inf
        out.append(Fitted(ev, k, m - k, phi[h], std[h], float(positive[h]) / (m - k),
                          bool(informative[h])))
    return out

