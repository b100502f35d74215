"""The diagnosis: each fault mode's twin against this machine's healthy baseline, as posterior
probabilities with the evidence for and against each (:class:`Diagnoser`).

Each window the :class:`~twinwatch.twin.diagnosis.engine.HypothesisBank` fits every fault
mode's twin (:mod:`~twinwatch.twin.diagnosis.hypotheses`) on the window's data. A mode's
log-evidence against the healthy baseline is the log-likelihood it gains in the windows since
its most likely change point, less the information criterion's penalty for each window's
fitted size, averaged over the change points; with the library's priors it gives the
posterior over: no change, each fault mode (its twins' evidence averaged), and a change the
library does not know (the window's own estimate, every estimated parameter and the kept
meta-model terms free in every window, penalised alike). Modes whose twins fit alike stay
split: neither is named with confidence, and the message says which check on the machine
tells them apart (:attr:`~twinwatch.twin.health.DiagnosisHealth.split`).

The twin that no longer describes the machine (its model check failing over
``check_function_after_s``) reads **check function** (NAMUR NE 107) unless a fault's twin
explains the windows: the estimates are then held and no outcome is claimed.
"""

from __future__ import annotations

import functools
import math
from collections import deque
from collections.abc import Mapping, Sequence
from typing import Any, Literal

import numpy as np

from twinwatch.twin.diagnosis.engine import RESOLUTION, HypothesisBank, WindowReading
from twinwatch.twin.diagnosis.hypotheses import Change, Fitted, Hypothesis, WindowTerms
from twinwatch.twin.diagnosis.library import DiagnosisConfig, FaultLibrary, FaultMode
from twinwatch.twin.estimation.fit import WindowFit
from twinwatch.twin.health import DiagnosisHealth, FaultHealth, HealthMessage
from twinwatch.twin.model import FloatArray, TwinModel, WindowData

__all__ = ["Diagnoser", "shaft_speed"]

#: The two-sided level at which one twin fits better than another in Vuong's test (5 %: the
#: conventional level; the statistic is compared with a critical value at it, Vuong,
#: Econometrica 57(2), 1989).
VUONG_LEVEL = 0.05


@functools.cache
def _t_crit(n: int) -> float:
    """Student's t quantile for the mean of ``n`` per-window differences at
    :data:`VUONG_LEVEL` (two-sided): Vuong's statistic is a mean over windows whose variance
    is estimated from the same few windows (1.96 for many; 12.7 for two). ``scipy.special``'s
    inverse of the t distribution, what ``scipy.stats.t.ppf`` calls, without importing
    ``scipy.stats`` (46 MB of resident memory in each daemon process)."""
    from scipy.special import stdtrit

    return float(stdtrit(max(n - 1, 1), 1.0 - VUONG_LEVEL / 2.0))
#: The share of the posterior under which two modes are one answer: above it for both and
#: with the top below the alarm, the message names both and the checks that tell them apart.
SPLIT = 0.1


def _fold_pairs(best_twin: dict[str, tuple[str, Fitted]]) -> None:
    """A pair's twin stands for each of its modes that has no better twin of its own; the
    pairs' keys are then removed (in place)."""
    for k in list(best_twin):
        if "+" in k:
            for f in k.split("+"):
                lab, fitted = best_twin[k]
                if f not in best_twin or fitted.evidence > best_twin[f][1].evidence:
                    best_twin.setdefault(f, best_twin[k])
            del best_twin[k]


def _log_sum_exp(values: list[float]) -> float:
    top = max(values)
    if not math.isfinite(top):
        return top
    return top + math.log(sum(math.exp(v - top) for v in values))


def _vuong(evidence: Mapping[str, float], gains: Mapping[str, np.ndarray]) -> dict[str, float]:
    """Each candidate's evidence against the best one, less what the windows do not agree on.

    Two fault modes' twins are not nested (neither is the other with a size set to zero), so
    the likelihood ratio between them has no chi-square law: Vuong's closeness test reads
    the per-window differences of their log-likelihood gains instead (Econometrica 57(2),
    1989). A candidate below the best by ``D`` is raised to within ``max(0, D - 2 sd
    sqrt(n))`` of it, ``sd`` the standard deviation of those differences over the ``n``
    windows since the best one's change point: a better fit that is not better window after
    window is no evidence, and the two stay split by their priors. Against the baseline each
    twin is nested (its size zero is the baseline): that comparison stays the likelihood
    ratio's, with its information-criterion penalty.

    Returns:
        candidate -> its evidence.
    """
    out = dict(evidence)
    if not out:
        return out
    best = max(out, key=lambda k: out[k])
    ref = gains.get(best)
    if ref is None or ref.size == 0:
        return out
    suffix = ref[::-1].cumsum()[::-1]       # np.flip, np.cumsum, np.argmax without wrappers
    start = int(suffix.argmax())
    # the candidates by the windows they share with the best one (n): each group's
    # differences as the rows of one array, each row reduced as it would be alone
    shared: dict[int, list[str]] = {}
    for k in out:
        other = gains.get(k)
        if k == best or other is None or other.size == 0 or not math.isfinite(out[k]):
            continue
        shared.setdefault(min(ref.size, other.size), []).append(k)
    for n, keys in shared.items():
        d = ref[-n:] - np.array([gains[k][-n:] for k in keys])
        # a twin impossible in a window (a moving reading is no stuck one): left as it is
        finite = np.logical_and.reduce(np.isfinite(d), axis=1)
        d = d[:, max(0, start - (ref.size - n)):]
        size = d.shape[1]
        # one window is no sample of the differences: no twin is preferred on it alone
        # (np.mean's and np.std's arithmetic, without their wrappers)
        means = np.add.reduce(d, axis=1) / size if size else np.zeros(len(keys))
        dev = d - means[:, None]
        squares = np.add.reduce(dev * dev, axis=1)
        crit = _t_crit(size)
        for row, k in enumerate(keys):
            if not finite[row]:
                continue
            gap = out[best] - out[k]
            mean = float(means[row])
            sd = math.sqrt(float(squares[row]) / (size - 1)) if size > 1 else 0.0
            z = (0.0 if size < 2 or mean <= 0 else math.inf if sd == 0
                 else mean / sd * math.sqrt(size))
            out[k] = out[best] - gap * min(1.0, max(0.0, z / crit) ** 2)
    return out


def shaft_speed(window: WindowData, channel: str) -> tuple[float, float] | None:
    """The window's mean absolute shaft speed and its spread [rad/s], None without a speed
    channel (the library's ``speed_channel``)."""
    if not channel or channel not in window.channels:
        return None
    w = np.abs(np.asarray(window[channel], dtype=float))
    if w.size == 0 or not np.isfinite(w).all():
        return None
    # np.mean's and np.std's arithmetic, without their wrappers
    mean = float(w.sum()) / w.size
    dev = w - mean
    return mean, math.sqrt(float((dev * dev).sum()) / w.size)


class Diagnoser:
    """Ranks a library's fault modes each window by fitting each as a change of the twin.

    Args:
        library: the machine's fault library (:meth:`DiagnosisConfig.resolve`).
        model: the twin.
        nominal: parameter -> nameplate value [SI].
        estimate: the parameters the estimation fits (the baseline fits them too).
        ties: dependent parameter -> its source (the estimation's ties).
        config: the ``[diagnosis]`` table (its defaults when None).
        source: where the library comes from, as it reads in the message.
        resolution: the finest residual the comparison resolves, a share of each output's
            scale (the machine's ``[estimation] model_error``).
    """

    def __init__(self, library: FaultLibrary, model: TwinModel, nominal: Mapping[str, float],
                 *, estimate: Sequence[str] = (), ties: Mapping[str, str] | None = None,
                 config: DiagnosisConfig | None = None, source: str = "shipped",
                 resolution: float = RESOLUTION) -> None:
        cfg = config or DiagnosisConfig()
        self.library = library
        self.model = model
        self.config = cfg
        self.source = source
        self.faults: dict[str, FaultMode] = {f.id: f for f in library.faults}
        #: each mode's log prior, and the priors' sum with the unknown change's (the library
        #: and the config are fixed for the diagnoser's life)
        self._ln_prior = {fid: math.log(f.prior) for fid, f in self.faults.items()}
        #: the log prior of each answer a window's posterior weighs: a mode, a pair of modes
        #: (``a+b``: the sum of theirs), the unknown change
        self._log_prior = {key: sum(self._ln_prior[f] for f in key.split("+")) for key in [
            *self.faults, *(f"{a}+{b}" for a in self.faults for b in self.faults)]}
        self._log_prior["unknown"] = math.log(cfg.unknown_prior)
        self._prior_sum = sum(f.prior for f in self.faults.values()) + cfg.unknown_prior
        #: twin label -> the mode (or the pair of modes) it stands for
        self._mode_of: dict[str, str] = {}
        channels = [*model.output_names, *model.inputs]
        attach = [a.name for a in model.attach_points]
        self.hypotheses: list[Hypothesis] = []
        for f in library.faults:
            self.hypotheses += f.hypotheses(model.parameter_names, channels, attach)
        names = model.parameter_names
        nom = np.array([float(nominal.get(n, model.parameter(n).nominal)) for n in names])
        self.bank = HypothesisBank(names, nom, self.hypotheses,
                                   list(estimate) or list(model.estimation_defaults.estimate),
                                   dict(ties if ties is not None
                                        else model.estimation_defaults.tie),
                                   WindowTerms(library.speed_channel),
                                   baseline_windows=cfg.baseline_windows, keep=cfg.keep_windows,
                                   resolution=resolution,
                                   attach_scales={a.name: a.scale for a in model.attach_points})
        self._checks: deque[tuple[float, float, bool]] = deque()
        self._passed_run = 0
        self._cf_since: float | None = None
        self._last: DiagnosisHealth | None = None
        self._twins: dict[str, list[tuple[Change, str, list[str]]]] = {}

    # -- one window ---------------------------------------------------------------------------
    def update(self, health: HealthMessage, fit: WindowFit | None = None,
               simulated: FloatArray | None = None, free: int = 0,
               initial: FloatArray | None = None) -> DiagnosisHealth:
        """The ranked fault modes after this window.

        Args:
            health: the window's health message (the estimation's: model check, terms).
            fit: the window's fit problem (its data and the twin); None: the window is not
                diagnosed (the last diagnosis stands, its check-function state updated).
            simulated: the window's own estimate's outputs (N, n_out), for the change the
                library does not know.
            free: numbers that estimate fitted in the window (parameters and offsets).
            initial: its initial-state offsets.
        """
        reading = None
        if fit is not None:
            t_mid = 0.5 * (health.t_start + health.t_end)
            reading = self.bank.update(fit, simulated, free, initial, t_mid)
        since, record, share = self._check_function(health)
        speed = shaft_speed(fit.window, self.library.speed_channel) if fit is not None else None
        if reading is None or reading.learning is not None:
            out = self._learning(health, reading, speed, since, record)
        else:
            out = self._decide(health, reading, speed, since, record, share)
            self.bank.settle(out.no_fault >= 0.5 and out.status != "check_function")
        self._last = out
        return out

    def _learning(self, health: HealthMessage, reading: WindowReading | None,
                  speed: tuple[float, float] | None, since: float | None,
                  record: str | None) -> DiagnosisHealth:
        if reading is None:
            note = "the twin did not simulate this window: no diagnosis"
        else:
            assert reading.learning is not None
            k, n = reading.learning
            note = (f"learning this machine's healthy baseline: window {k} of {n} (no change "
                    f"is looked for before it is learned)")
        status: Literal["no_fault", "check_function"] = (
            "check_function" if since is not None else "no_fault")
        return DiagnosisHealth(
            status=status, top=None, probability=1.0, no_fault=1.0, unknown=0.0,
            unknown_terms=[], faults=[], shaft_speed=speed[0] if speed else None,
            library=f"{self.library.model} ({self.source})", evidence=0,
            check_function_since=since, check_failed=record, unexplained=[], ruled_out=[],
            unobserved=[note])

    def _decide(self, health: HealthMessage, reading: WindowReading,
                speed: tuple[float, float] | None, since: float | None, record: str | None,
                share: float) -> DiagnosisHealth:
        """The window's diagnosis from the bank's reading: the posterior
        (:meth:`_posterior`), the status (:meth:`_status`), the modes the data cannot tell
        apart (:meth:`_split`) and the sentences."""
        cfg = self.config
        best_twin, evidence, gains = self._by_fault(reading)
        p_none, p_unknown, post = self._posterior(best_twin, evidence, gains)
        _fold_pairs(best_twin)
        order = sorted(post, key=lambda k: -post[k])
        # the top mode's best twin's evidence (what each other listed mode is compared with)
        best_top = max((v.evidence for k, v in reading.fits.items()
                        if k.startswith(order[0] + "#")), default=0.0) if order else 0.0
        texts: dict[str, str] = {}    # each mode's twin's fitted change for a person, once

        def text(fid: str) -> str:
            if fid not in texts:
                texts[fid] = self._size_text(fid, *best_twin[fid])
            return texts[fid]

        listed = [self._fault(fid, post[fid], best_twin[fid], text(fid), best_top, order[0])
                  for fid in order[:cfg.listed]]
        p_top = post[order[0]] if order else 0.0
        status, best = self._status(order, p_top, post, p_none, p_unknown, since, share)
        split, separate = self._split(order, post, p_top)
        unexplained: list[str] = []
        terms = [t.equation for t in health.terms]
        if p_unknown >= SPLIT:
            unexplained.append(
                f"the window's own estimate (every estimated parameter free"
                f"{', the kept meta-model terms' if terms else ''}) fits the "
                f"{reading.unknown_windows} windows since the change better than any fault "
                f"mode's twin: a change the library does not know")
        ruled_out = [f"{fid} ({post[fid]:.2f}): its twin ({text(fid)}) explains the windows "
                     f"less well than {order[0]}'s"
                     for fid in order[1:] if post[fid] < 0.05
                     and best_twin[fid][1].evidence > 0][:cfg.listed]
        unobserved = [f"{fid}: its twin would not change these windows' data measurably "
                      f"(not observable in them): its probability is its prior"
                      for fid, (_, f) in best_twin.items() if not f.informative]
        return DiagnosisHealth(
            status=status,
            top=order[0] if status == "fault" else None,
            probability=best,
            no_fault=p_none,
            unknown=p_unknown,
            unknown_terms=terms if p_unknown >= SPLIT else [],
            faults=listed,
            shaft_speed=speed[0] if speed else None,
            library=f"{self.library.model} ({self.source})",
            evidence=sum(1 for f in reading.fits.values() if f.evidence > 0),
            check_function_since=since,
            check_failed=record,
            unexplained=unexplained,
            ruled_out=ruled_out,
            unobserved=unobserved,
            split=split,
            separate=separate,
        )

    def _by_fault(self, reading: WindowReading) -> tuple[
            dict[str, tuple[str, Fitted]], dict[str, float], dict[str, np.ndarray]]:
        """Each mode's (or pair's) twins gathered: its best twin (label, fit), its evidence
        (the log of the mean likelihood ratio over its twins: the alternatives of a mode are
        equally likely a priori) and the per-window gains of its best twin; the window's own
        estimate as ``unknown``."""
        by_fault: dict[str, list[tuple[str, Fitted]]] = {}
        for lab, f in reading.fits.items():
            key = self._mode_of.get(lab)
            if key is None:
                key = self._mode_of[lab] = "+".join(x.split("#")[0] for x in lab.split("+"))
            by_fault.setdefault(key, []).append((lab, f))
        evidence: dict[str, float] = {}
        gains: dict[str, np.ndarray] = {}
        best_twin = {fid: max(fits, key=lambda lf: lf[1].evidence)
                     for fid, fits in by_fault.items()}
        for fid, fits in by_fault.items():
            evs = [f.evidence for _, f in fits]
            top = max(evs)
            evidence[fid] = (top + math.log(sum(math.exp(e - top) for e in evs) / len(evs))
                             if math.isfinite(top) else -math.inf)
            gains[fid] = self.bank.tracks[best_twin[fid][0]].gains()
        evidence["unknown"] = reading.unknown
        gains["unknown"] = self.bank.unknown_gains()
        return best_twin, evidence, gains

    def _posterior(self, best_twin: Mapping[str, tuple[str, Fitted]],
                   evidence: Mapping[str, float], gains: Mapping[str, np.ndarray]
                   ) -> tuple[float, float, dict[str, float]]:
        """P(no change), P(a change the library does not know) and each mode's probability
        (alone or in a pair). A change against none: each twin's likelihood ratio with the
        baseline (nested: its size zero is the baseline) with its prior; which change: the
        twins against each other (not nested: Vuong's comparison, :func:`_vuong`)."""
        ln_prior, log_prior = self._ln_prior, self._log_prior
        # no change now: none ever, or one that ended (a repair: a second change, as likely as
        # the fault itself) and the windows since are the baseline's
        terms_none = [math.log(max(1.0 - self._prior_sum, 1e-6))]
        for key, (_, fitted) in best_twin.items():
            if "+" not in key and fitted.ended > -math.inf:
                terms_none.append(2.0 * ln_prior[key] + fitted.ended)
        log_none = _log_sum_exp(terms_none)
        log_change = _log_sum_exp([log_prior[k] + ev for k, ev in evidence.items()])
        p_change = 1.0 / (1.0 + math.exp(min(log_none - log_change, 700.0)))
        between = _vuong(evidence, gains)
        logs = {k: log_prior[k] + ev for k, ev in between.items() if math.isfinite(ev)}
        top_l = max(logs.values()) if logs else 0.0
        zz = sum(math.exp(v - top_l) for v in logs.values()) or 1.0
        joint = {k: p_change * math.exp(v - top_l) / zz for k, v in logs.items()}
        joint.setdefault("unknown", 0.0)
        p_none, p_unknown = 1.0 - p_change, joint.pop("unknown")
        # each fault's probability: alone, or with another (a pair's twin)
        post = {k: v for k, v in joint.items() if "+" not in k}
        for k, v in joint.items():
            if "+" in k:
                for f in k.split("+"):
                    post[f] = post.get(f, 0.0) + v
        return p_none, p_unknown, post

    def _status(self, order: list[str], p_top: float, post: Mapping[str, float],
                p_none: float, p_unknown: float, since: float | None, share: float
                ) -> tuple[Literal["no_fault", "fault", "unknown", "check_function"], float]:
        """The status and its probability: a fault when the top mode is the likeliest answer
        and holds half the mass (or the modes the data cannot tell apart do together); a
        change no mode stands out for: unknown; the twin no longer fitting: check function,
        unless a fault is named at the alarm level."""
        cfg = self.config
        status: Literal["no_fault", "fault", "unknown", "check_function"]
        best = max(p_none, p_unknown, p_top)
        split_mass = sum(post[f] for f in order[:3] if post[f] >= SPLIT)
        if order and best == p_top and (p_top >= 0.5 or split_mass >= 0.5):
            status = "fault"
        elif 1.0 - p_none > p_none:
            # a change, but no mode of the library (nor two) stands out among those that fit:
            # not a finding about a part
            status, best = "unknown", 1.0 - p_none
        else:
            status = "no_fault"
        if since is not None and not (status == "fault" and p_top >= (cfg.alarm or 0.8)):
            status = "check_function"
            best = share
        return status, best

    def _split(self, order: list[str], post: Mapping[str, float], p_top: float
               ) -> tuple[list[str], str | None]:
        """The modes the data cannot tell apart (each at SPLIT or more, the top below the
        alarm) and the checks on the machine that separate them."""
        if len(order) > 1 and post[order[1]] >= SPLIT and p_top < (self.config.alarm or 0.8):
            split = [fid for fid in order if post[fid] >= SPLIT][:3]
            return split, "; ".join(
                f"{fid}: {self.faults[fid].confirm or self.faults[fid].action}"
                for fid in split)
        return [], None

    def _twin(self, sub: str) -> list[tuple[Change, str, list[str]]]:
        """One twin's changes (``mode#i``): each its hypothesis change, its description for a
        person and the names it changes (parameters, ``<channel> reading``, attach points);
        built once per twin (the library is fixed for the diagnoser's life)."""
        got = self._twins.get(sub)
        if got is None:
            mode_id, twin_no = sub.split("#")
            got = []
            for spec in self.faults[mode_id].twins()[int(twin_no)]:
                params, chans, attach = spec.names()
                got.append((spec.change(), spec.describe(),
                            params + [f"{c} reading" for c in chans] + attach))
            self._twins[sub] = got
        return got

    def _size_text(self, fid: str, lab: str, f: Fitted) -> str:
        """The fitted change(s) of a twin (one mode's, or a pair's) for a person."""
        parts = []
        k = 0
        for sub in lab.split("+"):
            for c, what, _ in self._twin(sub):
                if c.size == 0:
                    parts.append(what)
                    continue
                phi = f.phi[k:k + c.size]
                sd = f.std[k:k + c.size]
                if c.kind in ("scale", "gain", "supply", "offset"):
                    v = 100.0 * (float(phi[0]) if c.kind in ("gain", "offset")
                                 else math.expm1(float(phi[0])))
                    s2 = 200.0 * float(sd[0])
                    of = " of its RMS" if c.kind == "offset" else ""
                    parts.append(f"{what} {v:+.2f} %{of} +- {s2:.2f} %")
                elif c.kind == "term" and c.size == 2:
                    amp = float(np.hypot(phi[0], phi[1]))
                    parts.append(f"{what}, amplitude {amp:.3g}")
                else:
                    parts.append(f"{what} {float(phi[0]):+.3g} +- "
                                 f"{2 * float(sd[0]):.2g}")
                k += c.size
        return ", ".join(parts)

    def _fault(self, fid: str, p: float, twin: tuple[str, Fitted], text: str,
               best_top: float, top: str) -> FaultHealth:
        mode = self.faults[fid]
        lab, f = twin
        pro: list[str] = []
        con: list[str] = []
        since = f"the {f.windows} windows since its change point"
        if f.evidence > 0:
            pro.append(f"its twin ({text}, 2 sigma) fits {since} "
                       f"better than the healthy baseline (log-evidence {f.evidence:.3g}; "
                       f"better in {100 * f.share:.0f} % of them)")
        else:
            con.append(f"its twin ({text}) fits the recent windows no "
                       f"better than the healthy baseline")
        if fid != top:
            if best_top - f.evidence > 1.0:
                con.append(f"{top}'s twin fits the same windows better (log-evidence "
                           f"{best_top - f.evidence:.3g} more)")
        changed: list[str] = []
        for sub in lab.split("+"):
            if sub.split("#")[0] != fid:
                continue
            for _, _, names in self._twin(sub):
                changed += names
        return FaultHealth(id=fid, component=mode.component, probability=p,
                           action=mode.action, urgency=mode.urgency, source=mode.source,
                           evidence_for=pro, evidence_against=con,
                           changes=list(dict.fromkeys(changed)))

    # -- state (a restart resumes the baseline and the evidence since the change) -------------
    def state(self) -> dict[str, Any]:
        """The bank's state as JSON-able data (:meth:`restore` reads it)."""
        return self.bank.state()

    def restore(self, state: Mapping[str, Any]) -> None:
        """Resume from :meth:`state` (a state of another library or twin is ignored)."""
        self.bank.restore(state)

    # -- check function -----------------------------------------------------------------------
    def _check_function(self, health: HealthMessage
                        ) -> tuple[float | None, str | None, float]:
        """The twin-no-longer-fits state (NAMUR NE 107 *check function*): entered when at
        least ``check_function_share`` of the windows of the last ``check_function_after_s``
        of plant time failed their model check; left after ``check_function_clear_windows``
        windows in a row that passed. Returns the plant time it started (None: not in it),
        the record of the horizon for a person (None: no failed check in it) and the share of
        its windows that failed."""
        cfg = self.config
        mc = health.model_check
        if mc is None:
            return self._cf_since, None, 0.0
        self._checks.append((health.t_start, health.t_end, mc.passed))
        while self._checks and self._checks[0][0] < (health.t_end - cfg.check_function_after_s
                                                     - 1e-6):
            self._checks.popleft()
        self._passed_run = self._passed_run + 1 if mc.passed else 0
        failed = [c for c in self._checks if not c[2]]
        covered = health.t_end - self._checks[0][0]
        share = len(failed) / len(self._checks)
        if self._cf_since is None:
            if covered >= 0.95 * cfg.check_function_after_s and share >= \
                    cfg.check_function_share:
                self._cf_since = failed[0][0]
        elif self._passed_run >= cfg.check_function_clear_windows:
            self._cf_since = None
            self._checks = deque(list(self._checks)[-cfg.check_function_clear_windows:])
        if not failed:
            return self._cf_since, None, 0.0
        record = (f"the model check failed in {len(failed)} of the last {len(self._checks)} "
                  f"windows ({covered:.0f} s)")
        return self._cf_since, record, share
