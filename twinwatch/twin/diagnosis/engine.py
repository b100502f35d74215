"""The hypothesis bank: this machine's healthy baseline and every fault mode's twin, window after
window (:mod:`~twinwatch.twin.diagnosis.hypotheses` has the method and its sources).

1. **Baseline.** The first ``baseline_windows`` windows fit this machine's own parameters: the
   estimated parameters (with the estimation's ties) by Gauss-Newton over every window so far
   (their normal equations summed, each window linearised at the baseline of its time), the
   nameplate their weak prior. The residual left measures each output's variance and lag-1
   correlation: the weights of every later comparison. While nothing is detected the
   baseline goes on learning from windows old enough (``lag`` windows) that a change
   detected since would have stopped it; a change detected rolls it back to before the
   change point.
2. **Each window** the baseline twin and each direction's sensitivity are simulated once
   (:func:`~twinwatch.twin.diagnosis.hypotheses.columns`); every hypothesis's local quadratic
   is appended to its segment; the few best are linearised again at their fitted size.
3. **Evidence** per hypothesis: :func:`~twinwatch.twin.diagnosis.hypotheses.fit_segment`;
   the unknown change's from the window's own estimate (every estimated parameter free in
   every window, and the kept meta-model terms), penalised per window.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from twinwatch.twin.diagnosis.hypotheses import (
    LN_STEP,
    Change,
    Columns,
    Fitted,
    Hypothesis,
    Track,
    WindowTerms,
    bounded_solve,
    columns,
    evidence_each_many,
    evidence_many,
    window_basis,
)
from twinwatch.twin.estimation.fit import WindowFit
from twinwatch.twin.model import FloatArray

__all__ = ["RESOLUTION", "HypothesisBank", "WindowReading"]

#: The baseline's prior: each fitted parameter about its nameplate with this standard
#: deviation of its logarithm (10 %: the spread of a machine's constants about its maker's
#: rated values, of the order of the tolerances IEC 60034-1 sets on rated quantities). The
#: directions the baseline's windows do not determine (a regulated motor's Ke, D and J
#: trade off) stay near the nameplate instead of wandering with the noise.
NAMEPLATE_TOLERANCE = 0.1

#: A reading that repeats to this share of its size repeats exactly (one converter code, one
#: register value): a stuck reading does, a clipped one at its range's end does. 1e-9 lies
#: far below one code of a 24-bit converter (6e-8 of full scale) and far above float64's
#: rounding (1e-16), so it tells one code repeated from two neighbouring codes.
EXACT = 1e-9

#: The finest residual the comparison resolves by default, as a share of each output's scale
#: (its RMS): the estimation's default ``model_error`` (``[estimation] model_error``, the
#: twin-vs-machine floor the commissioning measures; the bank takes the machine's). Below it
#: two twins that both fit are equally good: a noise-free simulation's residual (1e-9 of the
#: scale) would otherwise make a rounding error a decisive difference.
RESOLUTION = 1e-4


@dataclass
class WindowReading:
    """What one window told the bank.

    Attributes:
        learning: the baseline is still being learned (windows so far, of how many).
        fits: hypothesis label -> its fit over the windows since its change point.
        unknown: the unknown change's log-evidence [nats].
        unknown_windows: the windows since the unknown change's most likely change point.
    """

    learning: tuple[int, int] | None
    fits: dict[str, Fitted] = field(default_factory=dict)
    unknown: float = -math.inf
    unknown_windows: int = 0


def _autocorr(r: FloatArray) -> float:
    d = float(np.dot(r[:-1], r[:-1]))
    if d <= 0:
        return 0.0
    return float(np.dot(r[1:], r[:-1]) / d)


class HypothesisBank:
    """This machine's baseline and its hypothesis twins (see the module docstring).

    Args:
        model_params: the twin's parameter names, in order.
        nominal: the nameplate vector (n_params,) [SI].
        hypotheses: the single fault modes' twins.
        estimate: the parameters the baseline fits (the estimation's).
        ties: dependent parameter -> its source (the estimation's ties).
        terms: what term bases need (the speed channel).
        baseline_windows: windows that set the baseline before any change is looked for.
        keep: windows kept per hypothesis (the change point is looked for among them).
        lag: windows a later window waits before the baseline learns from it.
        resolution: the finest residual the comparison resolves, a share of each output's
            scale (the machine's ``[estimation] model_error``).
    """

    def __init__(self, model_params: Sequence[str], nominal: FloatArray,
                 hypotheses: Sequence[Hypothesis], estimate: Sequence[str],
                 ties: Mapping[str, str], terms: WindowTerms, *,
                 baseline_windows: int = 10, keep: int = 150, lag: int = 10,
                 resolution: float = RESOLUTION,
                 attach_scales: Mapping[str, float] | None = None) -> None:
        self.resolution = float(resolution)
        self._attach_scale = dict(attach_scales or {})
        self.names = tuple(model_params)
        self.nominal = np.asarray(nominal, dtype=float).copy()
        self.theta = self.nominal.copy()
        self.hypotheses = list(hypotheses)
        self.terms = terms
        self.baseline_windows = baseline_windows
        self.keep = keep
        self.lag = lag
        self.ties = dict(ties)
        self.groups = [(p, [p, *[d for d, s in ties.items() if s == p]])
                       for p in estimate if p in self.names and p not in ties]
        #: each group's own parameter's index in the parameter vector
        self._group_index = [self.names.index(p) for p, _ in self.groups]
        dirs: dict[tuple[object, ...], None] = {}
        for _, members in self.groups:
            for m in members:
                dirs[("p", m)] = None
        for h in self.hypotheses:
            for c in h.changes:
                for d in c.directions():
                    dirs[d] = None
        self.directions = list(dirs)
        index = {d: i for i, d in enumerate(self.directions)}
        #: hypothesis label -> its columns as combinations of the directions (q, n_dir)
        self._combo: dict[str, FloatArray] = {}
        self._bounds: dict[str, tuple[FloatArray, FloatArray]] = {}
        #: label -> its sizes' plausible range squared, at most 1 (whether a window informs it)
        self._reach: dict[str, FloatArray] = {}
        for h in self.hypotheses:
            rows = []
            for c in h.changes:
                if c.kind == "scale":
                    row = np.zeros(len(self.directions))
                    for name, power in c.powers:
                        row[index[("p", name)]] += power
                    rows.append(row)
                else:
                    for d in c.directions():
                        row = np.zeros(len(self.directions))
                        row[index[d]] = 1.0
                        rows.append(row)
            self._combo[h.label] = np.array(rows).reshape(len(rows), len(self.directions))
            self._bounds[h.label] = h.bounds()
        #: label -> its one direction's index, for a hypothesis of one number that is one
        #: direction (not a combination of several)
        self._single: dict[str, int] = {
            lab: int(np.flatnonzero(c[0])[0]) for lab, c in self._combo.items()
            if c.shape[0] == 1 and np.count_nonzero(c[0]) == 1 and np.max(c[0]) == 1.0}
        #: the hypotheses fitted on the columns, each as (label, its single direction's index
        #: or -1, its combination's index among the distinct ones (twins of one change with
        #: other bounds share it), its bounds as numbers when it has one)
        distinct: dict[bytes, int] = {}
        self._linear = [(h.label, self._single.get(h.label, -1),
                         distinct.setdefault(self._combo[h.label].tobytes(), len(distinct)),
                         tuple(float(v) for v in self._bounds[h.label][0][:1]),
                         tuple(float(v) for v in self._bounds[h.label][1][:1]))
                        for h in self.hypotheses if h.closed_form is None]
        g = len(self.groups)
        self._prec = np.zeros((g, g))
        self._rhs = np.zeros(g)
        self._prior = np.eye(g) / NAMEPLATE_TOLERANCE**2
        self.learned = 0
        self.sigma2: FloatArray | None = None
        self.kappa: FloatArray | None = None
        self._stats: list[tuple[FloatArray, FloatArray]] = []
        self._kept: list[tuple[WindowFit, FloatArray | None]] = []
        self.tracks: dict[str, Track] = {h.label: Track(max(h.size, 1), keep)
                                         for h in self.hypotheses}
        self._pairs: dict[str, Hypothesis] = {}
        self._no_pair: set[str] = set()
        self._unknown: deque[float] = deque(maxlen=keep)
        #: per window kept: the power its log-likelihoods were tempered by (1: the library's
        #: best twin fitted it within the noise; the noise's chi-square bound over that
        #: twin's residual otherwise)
        self.fits_window: deque[float] = deque(maxlen=keep)
        #: the last ``lag`` windows' baseline normal equations (a, b, x0), waiting to be
        #: learned from once no change was seen during them (:meth:`settle`)
        self._pending: deque[tuple[FloatArray, FloatArray, FloatArray]] = deque()
        self.detected = False
        self.last: WindowReading | None = None

    # -- baseline ---------------------------------------------------------------------------
    def _group_columns(self, cols: Columns) -> FloatArray:
        out = np.zeros((len(self.groups), *cols.r0.shape))
        for acc, (_, members) in zip(out, self.groups, strict=True):
            for m in members:
                acc += cols.cols[("p", m)]
        return out

    def _ln_theta(self) -> FloatArray:
        out: FloatArray = np.log(self.theta[self._group_index])
        return out

    def _set_groups(self, x: FloatArray) -> None:
        for (_p, members), v in zip(self.groups, x, strict=True):
            for m in members:
                self.theta[self.names.index(m)] = math.exp(float(v))

    def _learn(self, a: FloatArray, b: FloatArray, x0: FloatArray) -> None:
        """Add a window's normal equations (linearised at ``x0``, the groups' ln values) and
        solve the baseline again."""
        self._prec += a
        self._rhs += b + a @ x0
        x_nom = np.log(np.array([self.nominal[self.names.index(p)] for p, _ in self.groups]))
        lhs = self._prec + self._prior
        rhs = self._rhs + self._prior @ x_nom
        try:
            x = np.linalg.solve(lhs, rhs)
        except np.linalg.LinAlgError:
            return
        self._set_groups(x)

    # -- one window -------------------------------------------------------------------------
    def update(self, fit: WindowFit, est_simulated: FloatArray | None, est_free: int,
               initial: FloatArray | None, t_mid: float) -> WindowReading | None:
        """Test every hypothesis on one window.

        Args:
            fit: the window's fit problem.
            est_simulated: the window's own estimate's outputs (N, n_out), None if none.
            est_free: numbers the estimate fitted in this window (parameters, offsets).
            initial: the estimate's initial-state offsets.
            t_mid: the window's middle time [s].

        Returns:
            The window's reading, or None when the baseline twin does not simulate it.
        """
        bases: dict[tuple[object, ...], FloatArray] = {}   # the window's term bases, once
        cols = columns(fit, self.theta, self.directions, self.terms, initial, bases)
        if cols is None:
            return None
        m_rows = cols.r0.shape[0]
        r_est = None
        if est_simulated is not None and np.isfinite(est_simulated).all():
            r_est = (fit.meas[1:] - est_simulated[1:]) / cols.scale
        sig2, kap = self._noise(cols, r_est)
        proj = _Projector(cols, kap, sig2)
        r0p = proj(cols.r0)
        if self.learned < self.baseline_windows:
            self._learn_window(cols, proj, r0p, fit, initial)
            return WindowReading((self.learned, self.baseline_windows))
        dp = proj.many(cols.mat)
        # the window's information, gradient and squared residual on the projected columns
        gram, grad, s0 = dp @ dp.T, dp @ r0p, float(r0p @ r0p)
        first = self._fit_linear(gram, grad, s0)
        n_eff = max(float(np.add.reduce(kap) * m_rows), 2.0)
        ln_n = math.log(n_eff)
        pairs = self._fit_pairs(gram, grad, s0, first)
        everyone = [*self.hypotheses, *pairs]
        exact = self._gauss_newton(everyone, first, dp, fit, initial, proj, bases)
        reading = WindowReading(None)
        fitted: dict[str, tuple[FloatArray, float, FloatArray]] = {}
        ranges: dict[int, tuple[float, float, float]] = {}
        for h in everyone:
            if h.closed_form is not None:
                fitted[h.label] = (np.zeros(1), self._closed_form(h, cols, fit, proj, s0, ranges),
                                   np.zeros((1, 1)))
            else:
                a, b, phi, s_h = first[h.label]
                fitted[h.label] = exact.get(h.label, (phi, s_h, a))
        # how well the window's best twin of the library fits it against the baseline's
        # noise: the chi-square bound of its effective samples (mean plus 3 standard
        # deviations) over its weighted squared residual, at most 1. Below 1 every twin of the
        # library misses something in this window (a drift within it, an operating point the
        # twin does not cover): its log-likelihoods are tempered by that power (a
        # misspecified model's likelihood: Grunwald and van Ommen, Bayesian Analysis 12(4),
        # 2017), so that how the twins rank in it counts for that much less
        bound = n_eff + 3.0 * math.sqrt(2.0 * n_eff)
        s_lib = min((v[1] for v in fitted.values()), default=s0)
        eta = min(1.0, bound / max(s_lib, 1e-300))
        self.fits_window.append(eta)
        self._append_tracks(everyone, fitted, eta, s0, ln_n, t_mid)
        self._read_evidence(everyone, reading)
        self._choose_pairs(reading)
        # the unknown change: the window's own estimate (every estimated parameter free in
        # every window, the kept meta-model terms in its twin), its numbers' penalty paid in
        # every window: it gains on a library twin only what that leaves unexplained
        if r_est is not None:
            rp = proj(r_est, profile=False)
            s_est = float(rp @ rp)
            eta_u = min(1.0, bound / max(s_est, 1e-300))
            self._unknown.append(0.5 * eta_u * (s0 - s_est) - 0.5 * max(est_free, 1) * ln_n)
        else:
            self._unknown.append(-0.5 * max(est_free, 1) * ln_n)
        reading.unknown, reading.unknown_windows = self._unknown_evidence()
        # this window's baseline normal equations: learned from once it is ``lag`` windows old
        # with no change seen since (:meth:`settle`)
        if self.groups:
            xg = proj.many(self._group_columns(cols))
            self._pending.append((xg @ xg.T, xg @ r0p, self._ln_theta()))
        self.last = reading
        return reading

    def _noise(self, cols: Any, r_est: FloatArray | None) -> tuple[FloatArray, FloatArray]:
        """The residual's variance (n_out,) and AR(1) factor (n_out,) per output: the
        baseline's once learned, else this window's (its own estimate's residual, or the
        baseline twin's), floored by the resolution."""
        if self.sigma2 is not None:
            assert self.kappa is not None
            return self.sigma2, self.kappa
        ref = r_est if r_est is not None else cols.r0
        sig2 = np.maximum(np.mean(ref * ref, axis=0), self.resolution**2)
        kap = np.array([_kappa(ref[:, j]) for j in range(ref.shape[1])])
        return sig2, kap

    def _fit_linear(self, gram: FloatArray, grad: FloatArray, s00: float
                    ) -> dict[str, tuple[FloatArray, FloatArray, FloatArray, float]]:
        """Each open hypothesis's size on the window, linearised at the baseline (bounded
        least squares on the projected columns: their information ``gram`` (D, D), gradient
        ``grad`` (D,) and the projected residual's squared norm ``s00``): label ->
        (information, gradient, size, squared residual)."""
        # a hypothesis of one direction picks its entry of the information and the gradient:
        # exactly what the products with its combination give (1 x the entry plus zeros),
        # unless an entry is not finite (0 x inf is NaN): then the products are taken
        pick = bool(np.isfinite(gram).all() and np.isfinite(grad).all())
        diag, gradl = gram.diagonal().tolist(), grad.tolist()
        ab: dict[int, tuple[FloatArray, FloatArray]] = {}    # each distinct combination's
        out = {}
        for label, i, ci, lo0, hi0 in self._linear:
            if i >= 0 and pick:
                a, b = gram[i:i + 1, i:i + 1], grad[i:i + 1]
                a0, b0 = diag[i], gradl[i]
            else:
                if ci not in ab:
                    cmb = self._combo[label]
                    ab[ci] = (cmb @ gram @ cmb.T, cmb @ grad)
                a, b = ab[ci]
                if a.shape != (1, 1):
                    lo, hi = self._bounds[label]
                    phi = bounded_solve(a, b, lo, hi)
                    out[label] = (a, b, phi, float(s00 - 2 * b @ phi + phi @ a @ phi))
                    continue
                a0, b0 = float(a[0, 0]), float(b[0])
            # bounded_solve of one number (its arithmetic), and the squared residual in the
            # same order, on the numbers themselves
            p0 = min(max(b0 / a0 if a0 > 0 else 0.0, lo0[0]), hi0[0])
            out[label] = (a, b, np.array([p0]), s00 - 2 * b0 * p0 + p0 * a0 * p0)
        return out

    def _fit_pairs(self, gram: FloatArray, grad: FloatArray, s0: float,
                   first: dict[str, tuple[FloatArray, FloatArray, FloatArray, float]]
                   ) -> list[Hypothesis]:
        """The pair twins of this window fitted linearised (into ``first``; ``gram``, ``grad``
        and ``s0`` as :meth:`_fit_linear`'s); a pair whose two
        twins change the window alike (correlation beyond PAIR_CORRELATION) is dropped for
        good. Returns the pairs kept."""
        pairs = self._pairs_now()
        for h in list(pairs):
            cmb = self._combo[h.label]
            a_, b_ = cmb @ gram @ cmb.T, cmb @ grad
            q1 = cmb.shape[0] // 2 or 1
            c11, c22 = np.diag(a_)[:q1].sum(), np.diag(a_)[q1:].sum()
            c12 = np.abs(a_[:q1, q1:]).sum()
            if c11 > 0 and c22 > 0 and c12 / math.sqrt(c11 * c22) > self.PAIR_CORRELATION:
                # the two twins change the window alike: together they are not two findings
                self._drop_pair(h.label, forever=True)
                pairs.remove(h)
                continue
            lo_, hi_ = self._bounds[h.label]
            phi_ = bounded_solve(a_, b_, lo_, hi_)
            first[h.label] = (a_, b_, phi_, float(s0 - 2 * b_ @ phi_ + phi_ @ a_ @ phi_))
        return pairs

    def _gauss_newton(self, everyone: list[Hypothesis],
                      first: Mapping[str, tuple[FloatArray, FloatArray, FloatArray, float]],
                      dp: FloatArray, fit: WindowFit, initial: FloatArray | None,
                      proj: _Projector, bases: dict[tuple[object, ...], FloatArray]
                      ) -> dict[str, tuple[FloatArray, float, FloatArray]]:
        """The scale and term hypotheses (the twin is not linear in them) linearised again at
        their size: up to GN_STEPS Gauss-Newton steps from the exact twin there, stopping once
        a size moves less than 1e-4. Returns label -> (size, squared residual, information)."""
        again = [h for h in everyone if h.label in first and h.nonlinear
                 and _largest(first[h.label][2]) > 1e-3]
        exact: dict[str, tuple[FloatArray, float, FloatArray]] = {}
        phis = {h.label: first[h.label][2] for h in again}
        lin = {h.label: self._combo[h.label] @ dp for h in again}
        for _ in range(self.GN_STEPS):
            if not again:
                break
            step = self._exact(again, phis, fit, initial, proj, lin, bases)
            moved = []
            for h in again:
                if h.label not in step:
                    continue
                exact[h.label] = step[h.label]
                if _largest(step[h.label][0] - phis[h.label]) > 1e-4:
                    moved.append(h)
                phis[h.label] = step[h.label][0]
            again = moved
        return exact

    def _append_tracks(self, everyone: list[Hypothesis],
                       fitted: Mapping[str, tuple[FloatArray, float, FloatArray]], eta: float,
                       s0: float, ln_n: float, t_mid: float) -> None:
        """Each hypothesis's window joins its track: the tempered log-likelihood ratio with
        the baseline less its sizes' penalty (Schwarz), its size, the size's standard error
        from the tempered information, and whether the window informs the size at all."""
        # the twins of two numbers or more: their tempered informations' pseudo-inverses, one
        # call for those of one shape (:func:`_pinv`), their rows appended after
        wide: dict[tuple[int, ...], list[tuple[Track, float, FloatArray, FloatArray, bool,
                                               float]]] = {}
        for h in everyone:
            track = self.tracks[h.label]
            phi, s_h, a = fitted[h.label]
            half = 0.5 * eta * (s0 - s_h) if math.isfinite(s_h) else -math.inf
            if h.closed_form is not None:
                track.append(half - 0.5 * ln_n, (0.0,), (1.0,), t_mid)
                continue
            reach = self._reach.get(h.label)
            if reach is None:
                lo, hi = self._bounds[h.label]
                span = np.where(np.isfinite(hi - lo), hi - lo, 1.0)
                reach = self._reach[h.label] = np.minimum(span, 1.0) ** 2
            # the tempered likelihood's information: eta times the window's
            if a.shape == (1, 1):
                a00 = eta * float(a[0, 0])
                std: Sequence[float] | FloatArray = (
                    (1.0 / math.sqrt(a00),) if a00 > 0 else
                    np.sqrt(np.maximum(np.diag(np.linalg.pinv(eta * a)), 0.0)))
                info = a00 * float(reach[0]) > 1.0
            else:
                a = eta * a
                info = bool(np.max(np.diag(a) * reach) > 1.0)
                wide.setdefault(a.shape, []).append(
                    (track, half - 0.5 * h.size * ln_n, phi, a, info, half))
                continue
            track.append(half - 0.5 * h.size * ln_n, phi, std, t_mid, info, half, ln_n)
        for rows in wide.values():
            inv = _pinv(np.array([row[3] for row in rows]))
            stds = np.sqrt(np.maximum(np.diagonal(inv, axis1=1, axis2=2), 0.0))
            for (track, gain, phi, _, info, half), std in zip(rows, stds, strict=True):
                track.append(gain, phi, std, t_mid, info, half, ln_n)

    def _read_evidence(self, everyone: list[Hypothesis], reading: WindowReading) -> None:
        """The evidence of each hypothesis since its change point (into ``reading.fits``): a
        line of sizes for a part's change (:func:`evidence_many`), each window's own size for
        the others (:func:`evidence_each_many`); the twins of one size at once."""
        groups: dict[tuple[bool, int, int], list[Hypothesis]] = {}
        others: list[str] = []
        for h in everyone:
            tr = self.tracks[h.label]
            consistent = h.consistent
            groups.setdefault((consistent, tr.q, tr.m), []).append(h)
            if not consistent:
                others.append(h.label)
        found: dict[str, Fitted | None] = {}
        for (consistent, _, _), hs in groups.items():
            many = evidence_many if consistent else evidence_each_many
            found.update(zip((h.label for h in hs), many([self.tracks[h.label] for h in hs]),
                             strict=True))
        # the others first, then the parts' changes by size (the order the fits are read in)
        order = others + [
            h.label for (consistent, _, _), hs in groups.items() if consistent for h in hs]
        for label in order:
            if (f := found[label]) is not None:
                reading.fits[label] = f

    #: Gauss-Newton steps at most per scale hypothesis and window (each from the exact twin at
    #: the last size; the steps stop once the size moves less than 1e-4).
    GN_STEPS = 3

    #: Partners the best single mode is paired with (the next modes by evidence, those whose
    #: twins change the windows alike skipped), and pair twins kept at most: two faults at
    #: once are tried when no single mode explains the change.
    PAIR_OF = 3
    PAIRS_KEPT = 6

    #: Two twins whose columns correlate beyond this (their information matrix's off-diagonal
    #: over the geometric mean of its diagonal) change a window alike: their pair would fit
    #: the noise with sizes that cancel (a winding's Ra down with a voltage reading's scale
    #: up), so it is not tried.
    PAIR_CORRELATION = 0.9

    def _pairs_now(self) -> list[Hypothesis]:
        return list(self._pairs.values())

    def _drop_pair(self, label: str, forever: bool = False) -> None:
        self._pairs.pop(label, None)
        self.tracks.pop(label, None)
        if forever:
            self._no_pair.add(label)

    def _choose_pairs(self, reading: WindowReading) -> None:
        """Start tracking the pairs of the best single fault modes (their best twins) that
        are not tracked yet; drop the least evident pairs beyond :data:`PAIRS_KEPT`."""
        singles: dict[str, tuple[float, str]] = {}
        for h in self.hypotheses:
            f = reading.fits.get(h.label)
            if f is None or h.closed_form is not None or f.evidence <= 0:
                continue
            fid = h.faults[0]
            if fid not in singles or f.evidence > singles[fid][0]:
                singles[fid] = (f.evidence, h.label)
        ranked = sorted(singles.values(), reverse=True)
        if not ranked or reading.unknown <= ranked[0][0]:
            return      # a single mode explains the change as well as anything: no pair
        by_label = {h.label: h for h in self.hypotheses}
        ha = by_label[ranked[0][1]]
        tried = 0
        for _, lab in ranked[1:]:
            if tried >= self.PAIR_OF:
                break
            hb = by_label[lab]
            label = "+".join(sorted((ha.label, hb.label)))
            if label in self._no_pair:
                continue            # the two change the windows alike: next partner
            tried += 1
            if label in self._pairs:
                continue
            pair = Hypothesis((ha.faults[0], hb.faults[0]), (*ha.changes, *hb.changes), label)
            self._pairs[label] = pair
            self._combo[label] = np.vstack([self._combo[ha.label], self._combo[hb.label]])
            lo_a, hi_a = self._bounds[ha.label]
            lo_b, hi_b = self._bounds[hb.label]
            self._bounds[label] = (np.concatenate([lo_a, lo_b]), np.concatenate([hi_a, hi_b]))
            self._reach.pop(label, None)    # its two modes' order is the best one's first
            self.tracks[label] = Track(pair.size, self.keep)
        if len(self._pairs) > self.PAIRS_KEPT:
            weakest = sorted(self._pairs, key=lambda key: reading.fits[key].evidence
                             if key in reading.fits else -math.inf)
            for key in weakest[:len(self._pairs) - self.PAIRS_KEPT]:
                self._drop_pair(key)
                reading.fits.pop(key, None)

    def _theta_at(self, h: Hypothesis, phi: FloatArray) -> FloatArray:
        th = self.theta.copy()
        k = 0
        for c in h.changes:
            if c.kind == "scale":
                for name, power in c.powers:
                    th[self.names.index(name)] *= math.exp(power * float(phi[k]))
            k += c.size
        return th

    def _exact(self, hyps: list[Hypothesis], phis: dict[str, FloatArray], fit: WindowFit,
               initial: FloatArray | None, proj: _Projector, lin: Mapping[str, FloatArray],
               bases: dict[tuple[object, ...], FloatArray]
               ) -> dict[str, tuple[FloatArray, float, FloatArray]]:
        """Each hypothesis's twin simulated at its size and a step beyond it in each scale and
        term change (one batch): its exact residual there and a Gauss-Newton step from it.
        A term enters the twin through its equations (the leak's pressure factor feeds the
        valve's square-root flow: not linear in it). The reading changes (the twin's outputs
        are linear in a reading's gain or offset) keep their columns at the baseline
        (``lin``: label -> columns (q, M), projected; ``bases``: the window's term bases,
        :func:`~twinwatch.twin.diagnosis.hypotheses.window_basis`)."""
        window = fit.window
        rows: list[FloatArray] = []
        row_terms: list[dict[str, FloatArray]] = []
        layout = []

        def terms_at(h: Hypothesis, phi: FloatArray) -> dict[str, FloatArray]:
            out_t: dict[str, FloatArray] = {}
            k = 0
            for c in h.changes:
                if c.kind == "term":
                    for i, d in enumerate(c.directions()):
                        values = window_basis(window, d, self.terms, bases)
                        out_t[c.target] = out_t.get(c.target, 0.0) + float(phi[k + i]) * values
                k += c.size
            return out_t

        for h in hyps:
            phi0 = phis[h.label]
            start = len(rows)
            rows.append(self._theta_at(h, phi0))
            row_terms.append(terms_at(h, phi0))
            k = 0
            for c in h.changes:
                if c.kind in ("scale", "term"):
                    for i in range(c.size):
                        e = np.zeros_like(phi0)
                        e[k + i] = self._fd_step(c)
                        at = phi0 + e
                        rows.append(self._theta_at(h, at))
                        row_terms.append(terms_at(h, at))
                k += c.size
            layout.append((h, start, len(rows) - start - 1))
        terms: dict[str, FloatArray] = {}
        for i, t in enumerate(row_terms):
            for point, values in t.items():
                if point not in terms:
                    terms[point] = np.zeros((len(rows), window.n))
                terms[point][i] = values
        init = None if initial is None else np.repeat(np.asarray(initial)[None], len(rows), 0)
        y = fit.simulate(np.vstack(rows), terms or None, init)
        finite = np.logical_and.reduce(np.isfinite(y).reshape(len(rows), -1), axis=1)
        # every twin's exact columns and residual, normalised, then projected in one call
        # (:meth:`_Projector.each`: each row as alone)
        raw: list[FloatArray] = []
        where: list[tuple[Hypothesis, list[tuple[int, int]], int]] = []
        for h, start, n_fd in layout:
            if not finite[start:start + 1 + n_fd].all():
                continue
            block = y[start:start + 1 + n_fd]
            y1 = block[0]
            k, j = 0, 1
            fd = []
            for c in h.changes:
                if c.kind in ("scale", "term"):
                    for i in range(c.size):
                        fd.append((k + i, len(raw)))
                        raw.append((block[j][1:] - y1[1:]) / (self._fd_step(c) * fit.scale))
                        j += 1
                k += c.size
            where.append((h, fd, len(raw)))
            raw.append((fit.meas[1:] - y1[1:]) / fit.scale)
        projected = proj.each(np.array(raw)) if raw else np.zeros((0, 0))
        out = {}
        for h, fd, last in where:
            phi0 = phis[h.label]
            base_cols = lin[h.label]
            cols = np.array(base_cols, copy=True)
            # the reading changes' own effect at their size (at the baseline's slope), then the
            # exact scale and term part
            for row, i in fd:
                cols[row] = projected[i]
            k = 0
            lin_shift = None
            for c in h.changes:
                if c.kind not in ("scale", "term"):
                    if lin_shift is None:
                        lin_shift = np.zeros(cols.shape[1])
                    for i in range(k, k + c.size):
                        lin_shift += base_cols[i] * float(phi0[i])
                k += c.size
            r = projected[last]
            if lin_shift is not None:
                r = r - lin_shift
            a = cols @ cols.T
            b = cols @ r
            lo, hi = self._bounds[h.label]
            if a.shape == (1, 1):
                # bounded_solve of one number (its arithmetic) and the squared residual in the
                # same order, on the numbers themselves
                a0, b0, p0 = float(a[0, 0]), float(b[0]), float(phi0[0])
                st = min(max(b0 / a0 if a0 > 0 else 0.0, float(lo[0]) - p0), float(hi[0]) - p0)
                out[h.label] = (np.array([p0 + st]),
                                float(r @ r) - 2 * b0 * st + st * a0 * st, a)
                continue
            step = bounded_solve(a, b, lo - phi0, hi - phi0)
            s_val = float(r @ r - 2 * b @ step + step @ a @ step)
            out[h.label] = (phi0 + step, s_val, a)
        return out

    def _fd_step(self, c: Change) -> float:
        """The finite-difference step of a change's free number: a parameter's logarithm's
        (:data:`LN_STEP`), a term amplitude's (1e-3 of its attach point's scale)."""
        if c.kind == "term":
            a = self._attach_scale.get(c.target, 1.0)
            return 1e-3 * a
        return LN_STEP

    def _closed_form(self, h: Hypothesis, cols: Columns, fit: WindowFit, proj: _Projector,
                     s0: float, ranges: dict[int, tuple[float, float, float]]) -> float:
        """A stuck or clipped reading's weighted squared residual.

        A stuck reading repeats one value (to the :data:`RESOLUTION` of its scale): its own
        residual is the twin's prediction against nothing (the reading carries none), the
        other outputs' the baseline's. A reading that moves is not stuck: its movement is
        counted at the resolution, so the hypothesis loses. A clipped reading repeats its
        extreme (two samples or more at it within the resolution): the samples at it are
        explained by the clip, the others are the baseline's. A settled, noise-free drive whose
        readings repeat exactly gains nothing from either: its twin predicts the same constant.
        ``s0`` is the baseline's weighted squared residual (what a reading that is not the
        twin's output leaves); ``ranges``: each output's tolerance, largest and smallest
        reading in this window, kept for the window's other closed forms.
        """
        c = h.closed_form
        assert c is not None
        names = fit.model.output_names
        if c.target not in names:
            return s0
        j = names.index(c.target)
        meas = fit.meas[1:, j]
        if j not in ranges:
            # a stuck register or a converter at its range's end repeats one code exactly
            ranges[j] = (EXACT * max(float(np.abs(meas).max()), float(cols.scale[j])),
                         float(meas.max()), float(meas.min()))
        tol, hi, lo = ranges[j]
        mask: slice | np.ndarray = slice(None)      # the samples the reading explains
        if c.kind == "stuck":
            if hi - lo > tol:
                return math.inf
        else:
            y = cols.y0[1:, j]
            at_hi = (np.abs(meas - hi) <= tol) & (y > hi)
            at_lo = (np.abs(meas - lo) <= tol) & (y < lo)
            n_hi, n_lo = at_hi.sum(), at_lo.sum()
            mask, n_at = (at_hi, n_hi) if n_hi >= n_lo else (at_lo, n_lo)
            if n_at < 2:
                # no sample at the range's end beyond the twin: the clip does not show in
                # this window, which is the baseline's (a clipping sensor reads true below
                # its range)
                return s0
        r = cols.r0.copy()
        r[mask, j] = 0.0
        rp = proj(r)
        return float(rp @ rp)

    #: Gauss-Newton passes over the baseline's windows once they are all in (each simulates
    #: every kept window again at the baseline of the pass before).
    BASELINE_PASSES = 3

    def _learn_window(self, cols: Columns, proj: _Projector, r0p: FloatArray,
                      fit: WindowFit, initial: FloatArray | None) -> None:
        """One baseline window: its normal equations join the running solution; the window is
        kept so that, once the baseline's windows are all in, Gauss-Newton passes over all of
        them together (each linearised at the same baseline) settle it, and the residual it
        leaves in them gives each output's variance and correlation."""
        x = self._group_columns(cols)
        xp = proj.many(x) if len(x) else np.zeros((0, r0p.size))
        self._learn(xp @ xp.T, xp @ r0p, self._ln_theta())
        self._kept.append((fit, None if initial is None else np.array(initial)))
        self.learned += 1
        if self.learned < self.baseline_windows:
            return
        x_nom = np.log(np.array([self.nominal[self.names.index(p)] for p, _ in self.groups]))
        for _ in range(self.BASELINE_PASSES if self.groups else 0):
            prec = self._prior.copy()
            x0 = self._ln_theta()
            rhs = self._prior @ x_nom
            for f, init in self._kept:
                c = columns(f, self.theta, [("p", m) for _, ms in self.groups for m in ms],
                            self.terms, init)
                if c is None:
                    continue
                pr = _Projector(c, proj.kappa, proj.s2)
                xg = pr.many(self._group_columns(c))
                a = xg @ xg.T
                prec += a
                rhs += xg @ pr(c.r0) + a @ x0
            try:
                self._set_groups(np.linalg.solve(prec, rhs))
            except np.linalg.LinAlgError:
                break
            self._prec, self._rhs = prec - self._prior, rhs - self._prior @ x_nom
        stats = []
        for f, init in self._kept:
            c = columns(f, self.theta, [], self.terms, init)
            if c is None:
                continue
            zr = c.nuisance.reshape(len(c.nuisance), -1)
            r = c.r0.reshape(-1)
            if zr.shape[0]:
                r = r - zr.T @ np.linalg.lstsq(zr @ zr.T, zr @ r, rcond=None)[0]
            res: FloatArray = r.reshape(c.r0.shape)
            stats.append((np.mean(res * res, axis=0),
                          np.array([_kappa(res[:, j]) for j in range(res.shape[1])])))
        self._stats = stats
        self._kept = []
        if stats:
            # each output's variance: the 90th percentile of the baseline's windows (the misfit
            # a healthy window of this machine reaches, its operating points varying: a
            # residual threshold set on healthy data, Isermann 2006, sec. 7.3), not their
            # median, which a later healthy window's model error exceeds half the time
            self.sigma2 = np.maximum(np.percentile(np.array([a for a, _ in stats]), 90,
                                                   axis=0), self.resolution**2)
            self.kappa = np.median(np.array([k for _, k in stats]), axis=0)
        else:
            self.sigma2 = np.asarray(proj.s2, dtype=float)
            self.kappa = np.asarray(proj.kappa, dtype=float)

    def settle(self, no_change: bool) -> None:
        """After the diagnosis of the last window: while no change is seen (``no_change``),
        the window ``lag`` windows back joins the baseline (this machine's parameters learned
        from every window without a change, not from the first ones alone: a baseline known
        from 10 windows drifts from the truth by its own error, which hundreds of later windows
        would read as a change); once a change is seen, the windows since wait, and those of
        the change are never learned from."""
        if not no_change:
            self._pending.clear()
            return
        while len(self._pending) > self.lag:
            a, b, x0 = self._pending.popleft()
            self._learn(a, b, x0)

    # -- state ----------------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        """The baseline, its statistics and every hypothesis's windows since the change, as
        JSON-able data (a restart resumes from it: :meth:`restore`)."""
        def arr(x: FloatArray | None) -> list[float] | None:
            return None if x is None else [float(v) for v in np.ravel(x)]

        return {
            "names": list(self.names), "labels": [h.label for h in self.hypotheses],
            "theta": arr(self.theta), "learned": self.learned, "sigma2": arr(self.sigma2),
            "kappa": arr(self.kappa), "prec": arr(self._prec), "rhs": arr(self._rhs),
            "stats": [[arr(a), arr(b)] for a, b in self._stats],
            "tracks": {lab: t.as_dict() for lab, t in self.tracks.items()
                       if lab in self._combo and "+" not in lab},
            "unknown": list(self._unknown),
            "fits_window": list(self.fits_window),
        }

    def restore(self, state: Mapping[str, Any]) -> None:
        """Resume from :meth:`state`; a state of another twin or library (other parameter
        names or hypotheses) is ignored: the baseline is learned again."""
        if list(state.get("names", [])) != list(self.names) or \
                list(state.get("labels", [])) != [h.label for h in self.hypotheses]:
            return
        self.theta = np.array(state["theta"], dtype=float)
        self.learned = int(state["learned"])
        self.sigma2 = None if state["sigma2"] is None else np.array(state["sigma2"])
        self.kappa = None if state["kappa"] is None else np.array(state["kappa"])
        g = len(self.groups)
        self._prec = np.array(state["prec"], dtype=float).reshape(g, g)
        self._rhs = np.array(state["rhs"], dtype=float)
        self._stats = [(np.array(a), np.array(b)) for a, b in state.get("stats", [])]
        for lab, tr in state.get("tracks", {}).items():
            if lab in self.tracks:
                self.tracks[lab] = Track.from_dict(tr, self.keep)
        self._unknown = deque((float(v) for v in state.get("unknown", [])), maxlen=self.keep)
        self.fits_window = deque((float(v) for v in state.get("fits_window", [])),
                                 maxlen=self.keep)

    def unknown_gains(self) -> FloatArray:
        """The unknown change's per-window gains (m,), oldest first (as a track's ``gain``)."""
        return np.fromiter(self._unknown, float, len(self._unknown))

    def _unknown_evidence(self) -> tuple[float, int]:
        if not self._unknown:
            return -math.inf, 0
        u = self.unknown_gains()
        # np.flip's, np.cumsum's, np.max's and np.mean's arithmetic without their wrappers
        suffix = u[::-1].cumsum()[::-1]
        top = float(np.maximum.reduce(suffix))
        start = int(suffix.argmax())
        ev = top + math.log(float(np.add.reduce(np.exp(suffix - top)) / len(u)))
        return ev, len(u) - start


class _Projector:
    """Weigh a normalised residual (N-1, n_out) by each output's ``sqrt(kappa_j/sigma_j^2)``
    and project out the initial-state offsets (nuisance: fitted with every hypothesis)."""

    def __init__(self, cols: Columns, kappa: FloatArray, sigma2: FloatArray) -> None:
        self.s2 = sigma2
        self.kappa = kappa
        self.sw = np.sqrt(kappa / sigma2)
        n_init = cols.nuisance.shape[0]
        self.zw = (cols.nuisance * self.sw).reshape(n_init, -1)
        self.zw_t = self.zw.T
        self.ginv = _pinv(self.zw @ self.zw.T) if n_init else np.zeros((0, 0))

    def many(self, v: FloatArray) -> FloatArray:
        """:meth:`__call__` for a stack of residual-shaped arrays (k, N-1, n_out) -> (k, M)."""
        vw: FloatArray = (v * self.sw).reshape(v.shape[0], -1)
        if self.zw.shape[0]:
            vw = vw - ((vw @ self.zw_t) @ self.ginv) @ self.zw
        return vw

    def each(self, v: FloatArray) -> FloatArray:
        """:meth:`__call__` of each of a stack (k, N-1, n_out) -> (k, M), in one call: numpy's
        stacked matmul of a matrix by a stack of vectors makes each element's ``gemv`` call as
        the single product does (the same numbers, ``tests/test_diagnosis.py``)."""
        vw: FloatArray = (v * self.sw).reshape(v.shape[0], -1)
        if self.zw.shape[0]:
            out: FloatArray = vw - np.matmul(
                self.zw_t, np.matmul(self.ginv, np.matmul(self.zw, vw[..., None])))[..., 0]
            return out
        return vw

    def __call__(self, v: FloatArray, profile: bool = True) -> FloatArray:
        vw: FloatArray = (v * self.sw).reshape(-1)
        if profile and self.zw.shape[0]:
            vw = vw - self.zw_t @ (self.ginv @ (self.zw @ vw))
        return vw


def _pinv(a: FloatArray) -> FloatArray:
    """``np.linalg.pinv(a)`` of a matrix (q, q) or a stack of them (k, q, q): its steps (the
    SVD; the singular values above 1e-15 of the largest inverted, the others 0; V S+ U')
    without its checks, each matrix of a stack as it would be alone: the same numbers."""
    u, s, vt = np.linalg.svd(a, full_matrices=False)
    large = s > 1e-15 * np.max(s, axis=-1, keepdims=True)
    s = np.divide(1, s, where=large, out=s)
    s[~large] = 0
    out: FloatArray = np.matmul(np.swapaxes(vt, -1, -2), s[..., None] * np.swapaxes(u, -1, -2))
    return out


def _largest(phi: FloatArray) -> float:
    """``max |phi|`` (NaN if one is NaN), one number without numpy's reduction."""
    return abs(float(phi[0])) if phi.shape == (1,) else float(np.max(np.abs(phi)))


def _kappa(r: FloatArray) -> float:
    """The share of independent samples in an AR(1) residual: (1 - rho)/(1 + rho), rho its
    lag-1 autocorrelation (negative rho counted as none), at least one sample in all."""
    rho = min(max(_autocorr(r - float(np.mean(r))), 0.0), 0.999999)
    return float(max((1.0 - rho) / (1.0 + rho), 1.0 / max(len(r), 1)))
