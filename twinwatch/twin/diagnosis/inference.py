"""From the evidence to the failing part: a noisy-OR network over the fault library.

The paper leaves its last step, the maintenance decision, to the specialist (Section 6: "it
requires the specialist to decide"). This module takes the evidence each health message
publishes, with its uncertainty, and ranks the fault modes of the machine's library
(:mod:`twinwatch.twin.diagnosis.library`) by their posterior probability.

The model (a two-layer Bayesian network, noisy-OR; Pearl, *Probabilistic Reasoning in
Intelligent Systems*, 1988, Section 4.3.2; Henrion, "Practical issues in constructing a Bayes'
belief network", 1987, for the leak):

* faults ``f`` (the library's, plus ``unknown``: a fault the library does not know) are present
  independently with their ``prior``;
* an evidence variable ``e`` is present with ``P(e | F) = 1 - (1 - leak_e) prod_{f in F}
  (1 - link_{f,e})``: each present fault shows it with its link, ``leak_e`` with no fault at all;
* each variable is observed softly (Pearl's virtual evidence): a strength ``s`` in (0, 1) is the
  probability the evidence is really there given what the health message says, e.g. for "Ra is
  at least 1 % below nameplate" ``s = Phi((-dev - 1 %) / sd)`` with ``sd`` the published
  standard error: a deviation inside its interval is weak evidence, a tight one far beyond the
  size is strong, one tightly within the size is evidence against;
* the posterior is computed exactly over every hypothesis of at most two faults (no fault, each
  fault alone, each pair: 1 + n + n(n-1)/2 hypotheses; with priors of 1 % the mass of three or
  more faults is below 1e-4), and each fault's probability is the mass of the hypotheses that
  contain it.

A window whose parameter is ``suspect`` (its model check failed, a sensor is frozen or
saturated) or ``held`` gives no new deviation evidence: the last sound evidence (``estimated``
or ``fused``) on that parameter stands. A term the library's faults do not explain is the
``unknown`` fault's evidence (link 0.9).

Cost: a few hundred microseconds per window with numpy (benchmarks/bench_diagnosis.py).
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from itertools import combinations
from typing import Any, Literal

import numpy as np
from scipy.special import betainc, chdtrc

from twinwatch.twin.diagnosis.deviation import HI_PCT, likelihood
from twinwatch.twin.diagnosis.evidence import (
    EVIDENCE_KINDS,
    LEAK,
    S_MIN,
    Variable,
    clip,
    estimated_parameters,
    explains_check,
    model_check_variable,
)
from twinwatch.twin.diagnosis.library import FaultLibrary, FaultMode, TermSign
from twinwatch.twin.health import (
    AcrossRead,
    DiagnosisHealth,
    FaultHealth,
    HealthMessage,
    SensorHealth,
    TermHealth,
)
from twinwatch.twin.model import WindowData

__all__ = ["LEAK", "Diagnoser", "shaft_speed"]

#: The leak of a deviation (or a trend) of a parameter in the equation of a term no fault
#: explains (the library's ``equations``), at full strength of that term: the twin lacks a
#: component there and the estimate absorbs part of it (measured: a drive's 2 V dead zone at 1 %
#: noise published Ra +1.1 to +2.8 % in its sound windows, with the clip term in place).
LEAK_UNEXPLAINED = 0.3
#: The unknown fault's link to a term no library fault explains, and to a failed model check.
UNKNOWN_TERM_LINK = 0.9
UNKNOWN_CHECK_LINK = 0.3
#: The unknown fault's link to an output failing its model check persistently (in most of
#: the last :data:`CHECK_RATE_WINDOWS` windows): the twin, with every term it has found,
#: still cannot reproduce that output, so something it lacks is acting (a fault whose
#: ``checks`` names the output explains it instead).
UNKNOWN_CHECK_RATE_LINK = 0.3
#: A discovered term a library fault explains, while some output still fails its check
#: persistently with the term in the twin, is explained only in part (the twin lacks more
#: than the term, or the term stands in for something else: a pressure reading's gain and a
#: leak give the same term on p): the fault's match is discounted by this share of the
#: failure's strength, and the rest left to the unknown fault.
TERM_MISFIT_DISCOUNT = 0.5
#: An evidence variable is said for or against a fault when it moves the fault's odds by more
#: than this (log likelihood ratio against no fault; 0.3: a factor 1.35).
LLR_SAID = 0.3
#: A periodic term's harmonic is decided on its frequency against the shaft speed in at least
#: this many windows in a row (10 s at 2 s windows), each within the signature's tolerance.
HARMONIC_WINDOWS = 5
#: A periodic term's frequency over the shaft speed may change by this much (relative) from
#: one window to the next and still be the same term's track: a term re-found at each new
#: speed (an unbalance following the shaft) keeps its track; a fixed-frequency term against a
#: shaft speeding up moves along it and matches no harmonic until the speed settles.
RATIO_STEP = 0.15
#: A parameter's deviation against the shaft speed (:meth:`Diagnoser.scaling_variable`): the
#: windows kept, the fewest moved windows and the speed span that decide, and the tolerance
#: of the power (ln-ln slope).
SCALING_WINDOWS = 30
SCALING_MIN_WINDOWS = 6
SCALING_SPAN = 1.5
SCALING_TOL = 0.35
#: Windows after its last decided window over which a harmonic stays a fault's evidence while
#: its term is not found and the twin fails its check (:meth:`Diagnoser._remembered_term`).
TERM_MEMORY_WINDOWS = 60
#: The strength of such a remembered term (a decided harmonic: nearly as strong as found).
TERM_MEMORY_STRENGTH = 0.99
#: How well an undecided periodic term matches the harmonic its attach point's last decided
#: track had (:meth:`Diagnoser._harmonic_recall`); the other harmonics match at 1 minus it.
HARMONIC_RECALL = 0.8
#: Floor of a deviation's standard error [% of nameplate] (the twin's own model error).
SD_FLOOR_PCT = 0.05
#: The unknown fault's link to a parameter's deviation (or trend) in a direction no fault of
#: the library expects: a change the library does not know (a drifting current sensor's D
#: -52 % when the library had no fault that lowers D). A deviation some fault expects is left
#: to the library's faults and the leak.
UNKNOWN_DEV_LINK = 0.2
#: Size [% of nameplate] beyond which a deviation no fault expects counts as the unknown
#: fault's evidence.
UNEXPLAINED_PCT = 3.0
#: The unknown fault's link to each estimate its alias pattern moves (:meth:`Diagnoser._alias`:
#: the estimates moved together as a change of a parameter the window does not estimate and
#: no fault of the library names would move them).
ALIAS_LINK = 0.9
#: An alias is read only when the estimates mimic at least this share of the parameter's
#: effect (a change of it shows through them alone).
ALIAS_ABSORBED = 0.9
#: The alias pattern's size must be this many of its standard errors from 0.
ALIAS_Z = 3.0
#: ... and it must move at least two estimates, each by this much [% of nameplate] and twice
#: its standard error: one estimate moving alone is the library's (a deviation some fault
#: expects), a pattern across several is one change, not several faults.
ALIAS_MIN_PCT = 1.0
#: The pattern must fit the estimates: the chi-square p-value of what it leaves at least this.
ALIAS_FIT_P = 0.01
#: An alias read in one of this many recent windows (a minute at 2 s windows) is read again
#: in a window whose estimates still fit it with a change of the same sign, even if it moves
#: only one of them beyond twice its standard error now: a change of a parameter the twin
#: does not estimate does not come and go between two windows (the PWM drive's tau_e +50 %
#: read as the alias in most windows, and in those between, whose Ke, J and D sat within
#: their wider intervals, as worn brushes at 0.93).
ALIAS_MEMORY_WINDOWS = 30
#: Growth of a held parameter's last sound evidence's standard error with its age [% of
#: nameplate per square root of a window]: a random walk, so that evidence from before a fault
#: (La held at its nameplate since window 20) does not speak against it forever (1.5 % after
#: 100 windows, 3 % after 400).
STALE_SD_PCT = 0.15
#: A parameter's deviation evidence pools its sound estimates from the last this many windows
#: (after the change's onset; not while the estimates are read along an alias; not when,
#: widened, the pool tells less than the last window: a change under way, whose mean lags it)
#: when each comes from a window that estimated every parameter of the twin (nothing held or
#: fused: its estimates' errors are that window's noise alone, independent of the other
#: windows'; an estimate fitted beside a held value carries that value's lag, the same in every
#: such window). The weighted mean, its standard error inflated by the Birge ratio (the windows'
#: scatter beyond their stated errors) and shrunk at most :data:`POOL_SHRINK` times below the
#: last pooled window's. Measured on the fault matrix (benchmarks/bench_diagnosis.py, replayed,
#: 2026-11-26): the PWM drive at 1 % noise reads Ke -3 % +- 1.3 % (1 sigma) a window, and the
#: field weakened 3 % read "no fault" 0.92; pooled, magnet weakening 0.92 (top-1 60 -> 65 of 82,
#: confident-wrong 0, Brier 0.035 -> 0.030; the hydraulic fluid rising +42 to +46 % over ten
#: windows read +44.4 % +- 0.92 % pooled before the last-window rule, beside a published +46.3 %
#: +- 0.08 %). Pooling every sound window instead (the twin held Ra at a fused value lagging the
#: apparent -10 % of a current reading 1.1 times too high, and Ke absorbed it, -2 % in each such
#: window) named dry friction 0.88 on that sensor: 5 of 121 cases confident-wrong.
POOL_WINDOWS = 10
#: Fewest windows pooled (else the last window's estimate alone).
POOL_MIN = 3
#: Largest factor by which pooling shrinks the last pooled window's standard error: the
#: windows still share the fixed parameters' misstatement and the twin's own error, which
#: no pooling averages away (at 3 the PWM drive's slower current loop, tau_e +50 %, read as
#: an encoder reading high at 0.85 in one window; at 2.5 at most 0.75).
POOL_SHRINK = 2.5
#: A trend flat within its uncertainty, as evidence of a fault that drifts it: its rate
#: leaning the other way (or none) and leaning the fault's way.
TREND_FLAT = 0.2
TREND_FLAT_LEANING = 0.4
#: A parameter the windows hold (J on the default motor: never determined beside D in one
#: window; the library's ``read_across``) is read across the last this many windows after
#: the onset, from how the estimates moved with each window's alias of it
#: (:meth:`Diagnoser._across`): from one sound window to the next, each estimate moves by
#: ``c`` times the change of the held parameter's alias (its change ``c`` [%]) plus the two
#: windows' noise, and its own change (a step or a drift) cancels in the difference. A
#: set-point step makes the alias change sign (the inertia's torque accelerates, then
#: brakes), where a change of D itself moves every window alike.
ACROSS_WINDOWS = 30
#: Fewest windows with an alias (and sound estimates) for a read across windows.
ACROSS_MIN = 6
#: A read across windows with a standard error above this [%] says nothing.
ACROSS_MAX_SD = 20.0
#: Least share of the change's information that is its own, not shared with the estimates'
#: own changes (``1 / (I_cc (I^-1)_cc)``): an alias the same in every window (Ke's on the
#: default motor, D -5.15 to -5.25 % per % in every window) reads any slow drift of D's
#: error with the operating point as a change of Ke (a nominal run at 1 % noise read Ke
#: +20 % +- 4.6 %, and a speed reading low at 0.91).
ACROSS_OWN = 0.3
#: A read across windows is evidence once this many windows in a row read it alike (within
#: three combined standard errors): the paper's bearing wear at 1 % noise read J -18.5 % +-
#: 0.6 % in one window at 690 s (D's rise across a step's gap) and named a load inertia
#: change at 0.88; the inertia's own reads hold for tens of windows.
ACROSS_CONFIRM = 3
#: Largest reduced chi-square of the differences about the alias' line: beyond it the
#: estimates moved with something else between windows (a drifting D, whose rise across the
#: gap of a set-point step read as J -190 % +- 19 % under bearing wear at 1 % noise).
ACROSS_FIT = 4.0
#: A read across windows this many standard errors from 0 explains the estimates it moves:
#: each is read net of it (its alias times the change) in the window's evidence.
ACROSS_Z = 3.0
#: Evidence on a parameter older than this many windows (2 min at 2 s windows) says nothing
#: about it now: a parameter the windows have not estimated since (Ke held since the start
#: on a motor at a steady set-point) neither supports nor rules out the faults that move it.
STALE_MAX_WINDOWS = 60
#: A frozen or saturated sensor found in one of this many recent windows (10 min at 2 s
#: windows) is still evidence (a fault's ``sensors``): a reading that clips at 50 400 Pa does
#: so only in the windows whose pressure crosses it (8 of the 70 windows after its onset; the
#: twin meanwhile fits a gain term on p to the clipped readings, read ``internal_leak`` 0.86
#: between them), and a sensor does not mend itself between two such windows. With 60
#: windows (2 min, :data:`STALE_MAX_WINDOWS`) the fault matrix's clipped pressure readings,
#: last flagged 62 and 64 windows before their end, ended on "no fault" 0.91 and 0.98.
SENSOR_WINDOWS = 300
#: A term on a channel a recent stuck sensor reads (or on its derivative) is what the twin
#: fits to that sensor's readings: the faults naming such a sensor explain it with this link.
SENSOR_TERM_LINK = 0.9
#: A sound estimate this many standard errors from its nameplate, and at least
#: :data:`MOVED_PCT` percent, has moved (the change's onset until the trends date it).
MOVED_SD = 3.0
MOVED_PCT = 0.5
#: Windows over which an output's model-check failures are counted (a fault's ``checks``).
CHECK_RATE_WINDOWS = 10
#: An output whose check fails in more than this share of those windows fails persistently
#: (a healthy machine at 1 % noise: Va failed 4 to 10 % of its windows; a Va reading's error 27
#: to 31 of 40, a speed reading's 39 to 40 of 40). At 0.3, a rising Coulomb friction whose
#: term the twin holds (D held beside it) failed Va in 4 of 10 windows and read as a speed
#: reading low at 0.84 (bench_diagnosis dc/off/coulomb_rising; 0.75 at 0.4).
CHECK_RATE = 0.4


#: Windows over which a change that comes and goes is read (2 min at 2 s windows).
INTERMITTENT_WINDOWS = STALE_MAX_WINDOWS
#: A sound estimate this far from its nameplate [%], and :data:`INTERMITTENT_AWAY_SD`
#: standard errors, is away; back within :data:`INTERMITTENT_HOME_PCT` (or
#: :data:`INTERMITTENT_HOME_SD` standard errors) and below a quarter of how far it was, it
#: is home again. A wear fault does not
#: come back by itself; a load or a fault that comes and goes does (the fault matrix's
#: intermittent load, +40 % on 10 s of every 20 s, published D +168 % and its nameplate by
#: turns with every check passing, and ended on "no fault" 0.98). 20 %: beyond the PWM
#: drive's per-window scatter (standard errors of 5-9 %), whose repaired D +25 % step
#: crosses a 3 % threshold back and forth (the intermittent rule tried in the seventh round).
INTERMITTENT_AWAY_PCT = 20.0
INTERMITTENT_AWAY_SD = 2.0
INTERMITTENT_HOME_PCT = 2.0
INTERMITTENT_HOME_SD = 3.0
#: Returns home after being away, within :data:`INTERMITTENT_WINDOWS`, that make a change
#: intermittent (a repaired fault returns once).
INTERMITTENT_RETURNS = 2
#: The twin failing its model check in bursts: at least this share of the last
#: :data:`INTERMITTENT_WINDOWS` windows (at least half of them recorded) failed, in at least
#: :data:`INTERMITTENT_RUNS` separate runs, and at least this share passed (a twin failing
#: throughout is check function, not this).
INTERMITTENT_FAIL_SHARE = 0.3
INTERMITTENT_RUNS = 3
#: The unknown fault's link to a change that comes and goes, and the pattern's leak (a
#: healthy machine's estimates swinging 20 % and back twice in 2 min, or its twin failing
#: in bursts, with no fault present).
INTERMITTENT_LINK = 0.9
INTERMITTENT_LEAK = 5e-4


def _phi(z: float) -> float:
    return 0.5 * math.erfc(-z / math.sqrt(2.0))


def shaft_speed(window: WindowData, channel: str) -> tuple[float, float] | None:
    """The window's mean absolute shaft speed and its standard deviation [rad/s] from
    ``channel`` (None without the channel or with the shaft at rest)."""
    if not channel or channel not in window.channels:
        return None
    w = np.abs(np.asarray(window.channels[channel], dtype=float))
    w = w[np.isfinite(w)]
    if w.size == 0:
        return None
    mean = float(w.mean())
    if mean < 1e-6:
        return None
    return mean, float(w.std())


@dataclass
class _Dev:
    """The last sound evidence on a parameter: deviation and its standard error [%]."""

    dev: float
    sd: float
    value: float
    nominal: float
    unit: str
    window: int
    status: str
    estimated: frozenset[str] = frozenset()   # the parameters its window estimated
    t_end: float = 0.0                        # its window's end [s]
    full: bool = False                        # its window estimated every parameter
    pooled: int = 1                           # the windows' estimates it pools
    across: str = ""                          # read across windows: how (for a person)


@dataclass
class _Ratio:
    """A periodic term's frequency against the shaft speed in one window [rad/s]."""

    window: int
    b: float          # |b|, the term's angular frequency
    b_std: float      # its standard error
    speed: float      # the window's mean absolute shaft speed
    spread: float     # the speed's spread within the window


@dataclass
class _Comps:
    """The faults that move one parameter, per hypothesis (:mod:`.deviation`'s model)."""

    p_up: np.ndarray          # (n_hyp,) probability the hypothesis moves it up
    size_up: np.ndarray       # (n_hyp,) the smallest size of those faults [%]
    p_down: np.ndarray
    size_down: np.ndarray
    sizes: dict[tuple[int, str], float]  # (fault index, direction) -> its size [%]
    unexplained: tuple[str, ...]         # directions no library fault moves it in
    hi_up: np.ndarray | float = HI_PCT   # (n_hyp,) the largest size of the faults moving it
    hi_down: np.ndarray | float = HI_PCT
    reach: dict[str, float] = field(default_factory=dict)  # direction -> largest of any fault


@dataclass
class _AliasFit:
    """The estimates read as one change of a not-estimated parameter (:meth:`Diagnoser._alias`)."""

    parameter: str
    change: float               # its change [%] the estimates read
    change_sd: float            # the change's standard error [%]
    absorbed: float
    signs: dict[str, tuple[str, float, tuple[int, ...]]]  # estimate -> (direction, smallest
    #                                     size [%], the hypothesis columns of the faults moving it)
    text: str
    named: bool = False         # a library fault names the parameter (else the unknown fault's)


@dataclass
class _DevFactor:
    """One parameter's deviation evidence: its log-likelihood under every hypothesis."""

    name: str
    ev: _Dev
    text: str                 # the numbers, for a person
    log_lik: np.ndarray       # (n_hyp,)
    comps: _Comps
    sd: float                 # the standard error used [%] (grown with the evidence's age)
    leak_note: str = ""


class Diagnoser:
    """Ranks a library's fault modes from each window's health message (stateful: it keeps the
    last sound evidence on each parameter).

    Args:
        library: the machine's fault library (:meth:`DiagnosisConfig.resolve`).
        unknown_prior: prior of a fault the library does not know.
        listed: most fault modes listed in the result.
        source: where the library comes from, as it reads in the message.
        check_function_after_s: plant time [s] over which failed model checks put the
            diagnosis in ``check_function``: the twin does not describe the machine.
        check_function_share: share of that time's windows whose check failed.
        check_function_clear: windows in a row whose check passed that end it.
        pool_windows: windows a deviation's evidence pools (:data:`POOL_WINDOWS`; 1: the
            last sound window's estimate alone).
    """

    def __init__(self, library: FaultLibrary, *, unknown_prior: float = 0.01,
                 listed: int = 5, source: str = "shipped",
                 check_function_after_s: float = 60.0, check_function_share: float = 0.8,
                 check_function_clear: int = 3, pool_windows: int = POOL_WINDOWS) -> None:
        self.library = library
        self.unknown_prior = unknown_prior
        self.listed = listed
        self.source = source
        self.check_after_s = check_function_after_s
        self.check_share = check_function_share
        self.check_clear = check_function_clear
        self.pool_windows = pool_windows
        self._checks: deque[tuple[float, float, bool]] = deque()  # (t_start, t_end, passed)
        self._passed_run = 0
        self._cf_since: float | None = None
        self.faults: list[FaultMode] = list(library.faults)
        self._last: dict[str, _Dev] = {}
        self._pool: dict[str, deque[_Dev]] = {}  # each parameter's recent sound evidence
        self._prev: dict[str, _Dev] = {}  # the sound evidence before the last (a jump's check)
        # the change's onset [s]: evidence from before it is not used (:meth:`_observe`)
        self._onset: float | None = None
        # the last change point the trends dated [s] (kept when a trend's model drops it)
        self._trend_onset: float | None = None
        # parameter -> the last change point its own trend dated [s] (kept likewise)
        self._own_onset: dict[str, float] = {}
        # parameter -> the end [s] of its last sound window within its nameplate's interval
        self._quiet: dict[str, float] = {}
        self._tracks: list[tuple[str, list[_Ratio]]] = []  # (attach, ratios in a row)
        # attach point -> the harmonic its last decided track had, and that window
        self._harmonic: dict[str, tuple[float, int]] = {}
        ids = [f.id for f in self.faults] + ["unknown"]
        self._ids = ids
        n = len(ids)
        hyps: list[tuple[int, ...]] = [()] + [(i,) for i in range(n)] + list(
            combinations(range(n), 2))
        self._hyp = np.zeros((len(hyps), n))
        for h, members in enumerate(hyps):
            self._hyp[h, list(members)] = 1.0
        priors = np.array([f.prior for f in self.faults] + [unknown_prior])
        self._log_prior = (self._hyp @ np.log(priors)
                           + (1.0 - self._hyp) @ np.log1p(-priors))
        self._comps: dict[tuple[str, frozenset[str], tuple[str, float, tuple[int, ...]] | None],
                          _Comps] = {}
        self._alias_fit: _AliasFit | None = None  # the last one read (:meth:`_alias`)
        # parameter -> (the window its alias was last read in, the sign of its change)
        self._alias_seen: dict[str, tuple[int, float]] = {}
        # the parameters some fault's deviation sign names (not the unknown fault's aliases)
        self._named = frozenset(d.parameter for f in self.faults for d in f.deviations)
        # parameter -> (the window of the evidence its alias sign was read from, the sign)
        self._alias_signs: dict[str, tuple[int, tuple[str, float, tuple[int, ...]]]] = {}
        # parameter -> the faults a change of it in that direction is seen through the
        # estimates for while it is not estimated (a deviation sign on it, and signs that
        # hold when it is held: dry friction's Tc)
        self._through: dict[tuple[str, str], tuple[int, ...]] = {
            (q, direction): tuple(
                i for i, f in enumerate(self.faults)
                if any(d.parameter == q and d.direction == direction for d in f.deviations)
                and any(q in d.when_held for d in f.deviations))
            for q in self._named for direction in ("up", "down")}
        # per window: (window, output -> its check passed), for the faults' ``checks``
        self._outputs: deque[tuple[int, dict[str, bool]]] = deque(maxlen=CHECK_RATE_WINDOWS)
        self._dev_leak: dict[str, tuple[float, str]] = {}  # this window's raised leaks
        # (kind, channel) -> (the window it was last found stuck in, what was found)
        self._stuck: dict[tuple[str, str], tuple[int, SensorHealth]] = {}
        self._stuck_window = -1
        # per window: (window, parameter -> (deviation, standard error) [%] of its sound
        # estimates), and whether its model check passed: a change that comes and goes
        self._sound: deque[tuple[int, dict[str, tuple[float, float]]]] = deque(
            maxlen=INTERMITTENT_WINDOWS)
        self._passed: deque[bool] = deque(maxlen=INTERMITTENT_WINDOWS)
        # parameter -> (window, its end [s], shaft speed, deviation, standard error [%])
        self._speed_devs: dict[str, deque[tuple[int, float, float, float, float]]] = {}
        # per window: (window, its end [s], its sound estimates (deviation, standard error
        # [%]), read_across parameter -> its alias (estimate -> % per %)): the read across
        # windows
        self._aliased: deque[tuple[int, float, dict[str, tuple[float, float]],
                                   dict[str, dict[str, float]]]] = deque(maxlen=ACROSS_WINDOWS)
        # parameter -> its last reads across windows (change, standard error) or None
        self._across_hist: dict[str, deque[tuple[float, float] | None]] = {}
        # the recent windows whose twin held a meta-model term
        self._with_terms: deque[int] = deque(maxlen=ACROSS_WINDOWS)
        # parameter -> this window's read across windows (:meth:`_across`)
        self._across_fit: dict[str, tuple[float, float, dict[str, float]]] = {}
        self._across_windows: dict[str, int] = {}
        # fixed parameter a library fault names -> its last change read along its alias
        self._fixed_read: dict[str, tuple[_Dev, dict[str, float]]] = {}

    # -- evidence -----------------------------------------------------------------------------
    def _observe(self, health: HealthMessage, speed: tuple[float, float] | None) -> None:
        """Read the window's sound estimates (once per window, before any evidence): each
        becomes its parameter's last sound evidence, kept with the window's shaft speed
        ``speed`` (mean, spread [rad/s]; :meth:`scaling_variable`), and the change onset is
        dated.

        Only a window that estimated a parameter is new evidence: a fused value in a window
        that did not (held, or its check failed) is the fusion's prediction from the
        estimates already read, not a new observation. The onset is the trends' change point
        (:func:`_change_onset`, kept once a trend's model drops it); until a trend dates one
        (they need a few windows), the last window in which a parameter that has moved since
        was still within :data:`MOVED_SD` standard errors (and :data:`MOVED_PCT`) of its
        nameplate. Evidence older than the onset is from before the change: a held Ke read
        in window 0 counted against a sagging supply while its Ra rose, until Ra's trend
        dated the change (brushes 0.81 for two windows)."""
        sound: dict[str, tuple[float, float]] = {}
        self._sound.append((health.window, sound))
        if health.model_check is not None:
            self._passed.append(bool(health.model_check.passed))
        carried = estimated_parameters(health)
        full = all(p.status == "estimated" for p in health.parameters.values()
                   if p.status not in ("fixed", "tied"))
        for name, p in health.parameters.items():
            if (p.status == "estimated" and p.value is not None and p.nominal
                    and p.rel_std_pct is not None):
                dev = (p.value / p.nominal - 1.0) * 100.0
                sd = max(abs(p.rel_std_pct) * abs(p.value / p.nominal), SD_FLOOR_PCT)
                sound[name] = (dev, sd)
                if name in self._last:
                    self._prev[name] = self._last[name]
                self._last[name] = _Dev(dev, sd, p.value, p.nominal, p.unit, health.window,
                                        p.status, carried, float(health.t_end), full)
                self._pool.setdefault(name, deque(maxlen=max(self.pool_windows, 1))).append(
                    self._last[name])
                if speed is not None and speed[0] > 0:
                    self._speed_devs.setdefault(name, deque(maxlen=SCALING_WINDOWS)).append(
                        (health.window, float(health.t_end), float(speed[0]), dev, sd))
                if not _moved(dev, sd):
                    self._quiet[name] = float(health.t_end)
            elif p.status == "held" and p.value is not None and p.nominal:
                self._confirm_by_estimator(name, (p.value / p.nominal - 1.0) * 100.0)
        if health.terms:
            self._with_terms.append(health.window)
        self._aliased.append((health.window, float(health.t_end), sound, {
            p: {e: float(m) for e, m in a.moves.items() if m is not None}
            for p, a in health.aliases.items() if p in self.library.read_across}))
        dated = _change_onset(health)
        if dated is not None:
            self._trend_onset = dated
        for name, p in health.parameters.items():
            if p.trend is not None and p.trend.onset is not None:
                self._own_onset[name] = float(p.trend.onset)
        if self._trend_onset is not None:
            self._onset = self._trend_onset
            return
        moved = [self._quiet[n] for n, ev in self._last.items()
                 if n in self._quiet and _moved(ev.dev, ev.sd)
                 and health.window - ev.window <= STALE_MAX_WINDOWS]
        self._onset = max(moved, default=None)

    def _confirm_by_estimator(self, name: str, dev: float) -> None:
        """A window that held ``name`` publishes the estimator's trusted value of it at ``dev``
        [%]: when that is the last sound estimate, a jump not yet confirmed by a sound window
        of its own (:func:`_confirmed`) is confirmed by it (a ``fused`` value does not
        confirm: the filter took in the intermittent hydraulic load's one odd window too). A
        parameter that a window seldom determines (the DC motor's Ke: once in 40 windows,
        after a set-point step) has no next sound window to confirm a jump: a field weakened
        3 % was estimated -3.00 % +- 0.02 % once, fused at -2.95 % for 8 windows and trusted
        at -3.00 %, and the diagnosis kept reading the estimate before the jump (no fault
        0.98)."""
        ev, prev = self._last.get(name), self._prev.get(name)
        if ev is None or prev is None or _confirmed(ev, prev):
            return
        if abs(dev - ev.dev) <= max(JUMP_SD * ev.sd, MOVED_PCT) \
                and abs(dev - prev.dev) > abs(dev - ev.dev):
            self._prev[name] = ev

    def _deviation(self, health: HealthMessage, name: str) -> _Dev | None:
        """The last sound evidence on ``name`` (read by :meth:`_observe`), unless it is too
        old or from before the change onset; while a jump away from the nameplate is not
        confirmed by the next sound window (:func:`_confirmed`), the evidence before it."""
        ev = self._last.get(name)
        prev = self._prev.get(name)
        if ev is not None and prev is not None and not _confirmed(ev, prev):
            ev = prev
        if ev is None or health.window - ev.window > STALE_MAX_WINDOWS:
            return None
        onset = self._onset_of(name)
        if onset is not None and ev.t_end < onset:
            return None  # from before the change: says nothing about it
        return ev

    def _onset_of(self, name: str) -> float | None:
        """The change onset [s] evidence on ``name`` is read after: the change point its own
        trend dated last, else the trends' (:meth:`_observe`). Another parameter's later
        change point says nothing of this one's evidence: on the PWM drive a winding -4 %
        was estimated -4.0 % in every window that determined Ra, and its trend's onset (57 s)
        dropped from the model; then J's trend, drifting with the fusion, dated a change at
        178 s and every Ra estimate before it was set aside (winding 0.81, then 0.01)."""
        own = self._own_onset.get(name)
        return own if own is not None else self._onset

    def _pooled(self, health: HealthMessage, name: str, ev: _Dev) -> _Dev:
        """``ev`` (the last sound evidence on ``name``) with the deviation and standard
        error of the sound estimates from the last :attr:`pool_windows` windows, after the
        onset, that estimated every parameter (:data:`POOL_WINDOWS`: inverse-variance
        weighted mean, its standard error times the Birge ratio ``sqrt(chi^2 / (n - 1))``
        when above 1, and at least the last pooled one's over :data:`POOL_SHRINK`); ``ev``
        itself when that error is not below ``ev``'s, fewer than :data:`POOL_MIN` windows
        qualify, the last jump is not
        confirmed yet, or the estimates are read along an alias (:meth:`_alias`: they move
        with a parameter the twin does not estimate, an error every window shares). It keeps
        ``ev``'s window (its age, the alias read from it)."""
        if (self.pool_windows < POOL_MIN or ev is not self._last.get(name)
                or self._alias_signs):
            return ev
        onset = self._onset_of(name)
        pool = [d for d in self._pool.get(name, ())
                if d.full and health.window - d.window < self.pool_windows
                and (onset is None or d.t_end > onset)]
        if len(pool) < POOL_MIN:
            return ev
        dev = np.array([d.dev for d in pool])
        w = 1.0 / np.array([d.sd for d in pool]) ** 2
        mean = float(np.sum(w * dev) / np.sum(w))
        chi2 = float(np.sum(w * (dev - mean) ** 2))
        sd = math.sqrt(max(1.0, chi2 / (len(pool) - 1)) / float(np.sum(w)))
        sd = max(sd, pool[-1].sd / POOL_SHRINK, SD_FLOOR_PCT)
        if sd >= ev.sd:  # the windows disagree beyond their errors: a change under way, the
            return ev    # last estimate tells more than their mean (which lags it)
        return dataclasses.replace(ev, dev=mean, sd=sd,
                                   value=ev.nominal * (1.0 + mean / 100.0), pooled=len(pool))

    def _variables(self, health: HealthMessage, speed: tuple[float, float] | None
                   ) -> tuple[list[Variable], list[TermHealth]]:
        """The window's evidence variables (trends, model check, stuck sensors, discovered
        terms and the terms faults expect but the window lacks; deviations are
        :meth:`_dev_factors`') and the terms no fault explains."""
        out: dict[str, Variable] = {}
        self._dev_leak = {}
        if health.model_check is not None:
            self._outputs.append((health.window, {k: o.passed for k, o in
                                                  health.model_check.outputs.items()}))
        for f in self.faults:
            self._signature_vars(health, f, out)
        self._unexplained_vars(health, out)
        for name, (_, (direction, _, owners)) in self._alias_signs.items():
            # the fault that moves an estimate moves its trend too: a drift read as one change
            # of a parameter the window does not estimate is that change's (the unknown
            # fault's, or the faults naming it), not the library's faults of that estimate
            key = f"trend:{name}:{direction}"
            var = out.get(key)
            if var is None:
                continue
            for i in owners:
                fid = "unknown" if i == len(self.faults) else self.faults[i].id
                if fid not in var.links:
                    var.links[fid] = max(var.links.values(), default=UNKNOWN_DEV_LINK)
                    var.what[fid] = f"{name} drifting {direction} (the alias pattern)"
        for p, (c, sd_c, moves) in self._across_fit.items():
            if abs(c) < ACROSS_Z * sd_c:
                continue
            for e in moves:
                # the estimate's trend follows the held parameter's part, which changes sign
                # with each set-point step (J +50 % on the default motor: D's trend
                # "degrading at +18 %/h", read as a weaker field's at 0.39): no evidence
                # either way while the read explains it
                for direction in ("up", "down"):
                    var = out.get(f"trend:{e}:{direction}")
                    if var is not None and var.s != 0.5:
                        var.s = 0.5
                        var.present = var.absent = (f"{e}'s trend, moved by {p}'s "
                                                    f"{c:+.1f} % read across windows")
        if "model_check" not in out:
            out["model_check"] = model_check_variable(health)
        out["model_check"].links["unknown"] = UNKNOWN_CHECK_LINK
        if health.model_check is not None:
            for name in health.model_check.outputs:
                key = f"check:{name}"
                if key not in out:
                    out[key] = self.check_rate_variable(name)
                out[key].links["unknown"] = UNKNOWN_CHECK_RATE_LINK
                out[key].may.add("unknown")  # a fault its term captures passes the check
                out[key].what["unknown"] = (f"{name}'s model check failing in most windows "
                                            f"(the twin cannot reproduce it)")
        seen_speed = self._track(health, speed)
        unexplained = self._term_vars(health, seen_speed, out)
        self._missing_term_vars(health, seen_speed, out)
        return list(out.values()), unexplained

    def _signature_vars(self, health: HealthMessage, f: FaultMode,
                        out: dict[str, Variable]) -> None:
        """A fault's variables of every evidence kind that has them (trends, model check,
        output checks, stuck sensors: :data:`~twinwatch.twin.diagnosis.evidence.
        EVIDENCE_KINDS`, shared by key)."""
        for kind in EVIDENCE_KINDS.values():
            kind.add_variables(self, health, f, out)

    def _term_vars(self, health: HealthMessage, seen_speed: list[list[_Ratio] | None],
                   out: dict[str, Variable]) -> list[TermHealth]:
        """One variable per discovered term, each fault's link scaled by its match; returns
        the terms no fault explains (the unknown fault's, and model error in their
        equation: :meth:`_model_error`)."""
        unexplained: list[TermHealth] = []
        stuck = {s.channel for _, s in self.recent_sensors(health)}
        for i, term in enumerate(health.terms):
            var = self._term_var(i, term)
            best = 0.0
            matches = [(f, sg, *_term_match(sg, term, seen_speed[i]))
                       for f in self.faults for sg in f.terms]
            matches = self._harmonic_recall(health, term, seen_speed[i], matches)
            for f, sg, m, words in matches:
                if m >= 0.2 and m * sg.link > var.links.get(f.id, 0.0):
                    var.links[f.id] = m * sg.link
                    var.what[f.id] = words
                best = max(best, m if sg.link >= 0.5 else 0.0)
            on = {c for c in stuck if term.attach in (c, f"d({c})/dt")}
            if on:  # fitted to a stuck sensor's readings: the faults naming it explain it
                for f in self.faults:
                    if any(ss.channel in ("*", *on) for ss in f.sensors):
                        var.links[f.id] = max(var.links.get(f.id, 0.0), SENSOR_TERM_LINK)
                        var.what[f.id] = (f"a term the twin fits to the stuck "
                                          f"{'/'.join(sorted(on))} readings")
                        best = 1.0
            best *= 1.0 - TERM_MISFIT_DISCOUNT * self._misfit_since(term.since_window)
            var.links["unknown"] = max(UNKNOWN_TERM_LINK * (1.0 - best), 1e-3)
            var.what["unknown"] = "a term no fault of the library explains"
            if best < 0.5:
                unexplained.append(term)
                self._model_error(out, term, var.s * (1.0 - best))
            out[var.key] = var
        return unexplained

    def _harmonic_recall(self, health: HealthMessage, term: TermHealth,
                         track: list[_Ratio] | None,
                         matches: list[tuple[FaultMode, Any, float, str]]
                         ) -> list[tuple[FaultMode, Any, float, str]]:
        """A periodic term's harmonic, remembered per attach point across a speed change: a
        decided track (one harmonic matched at 0.9 or more, every other at 0.1 or less) is
        kept; a track still undecided (fewer than :data:`HARMONIC_WINDOWS` windows since the
        shaft's last speed change, the term re-found at the new speed) within
        :data:`STALE_MAX_WINDOWS` windows of it matches that harmonic at
        :data:`HARMONIC_RECALL` and the others at 1 minus that, not 0.5 each (a misalignment
        decided at 2x read as the unbalance, 0.45 against 0.22, after each set-point
        change: the priors decided)."""
        harm = [(k, sg.harmonic, m) for k, (_, sg, m, _) in enumerate(matches)
                if sg.harmonic is not None]
        if not harm or track is None:
            return matches
        if len(track) >= HARMONIC_WINDOWS:
            won = {h for _, h, m in harm if m >= 0.9}
            if len(won) == 1 and all(m <= 0.1 for _, h, m in harm if h not in won):
                self._harmonic[term.attach] = (won.pop(), health.window)
            return matches
        kept = self._harmonic.get(term.attach)
        if kept is None or health.window - kept[1] > STALE_MAX_WINDOWS:
            return matches
        h_kept, w_kept = kept
        out = list(matches)
        for k, h, m in harm:
            f, sg, _, words = out[k]
            if m != 0.5:   # not undecided for this signature (no shaft speed, another kind)
                continue
            recall = HARMONIC_RECALL if h == h_kept else 1.0 - HARMONIC_RECALL
            out[k] = (f, sg, recall, words.split(" (undecided")[0]
                      + f" (undecided since the shaft's speed changed; its track was "
                        f"{h_kept:g} x the shaft speed in window {w_kept})")
        return out

    def _missing_term_vars(self, health: HealthMessage,
                           seen_speed: list[list[_Ratio] | None], out: dict[str, Variable]) -> None:
        """Faults expecting a term the window lacks: evidence against them, naming the term
        of that kind found elsewhere (an unbalance's periodic term at another frequency than
        the shaft's: "found: 10 rad/s against 1 x 18.5 = 18.5 rad/s")."""
        for f in self.faults:
            for j, sg in enumerate(f.terms):
                if sg.link < 0.5 or any(out[f"term:{i}"].links.get(f.id, 0.0) >= 0.5 * sg.link
                                        for i in range(len(health.terms))):
                    continue
                if self._remembered_term(health, f, sg, out):
                    continue
                key = f"noterm:{f.id}:{j}"
                kinds = "/".join(sg.kinds).replace("*", "any")
                where = "/".join(sg.attach)
                harm = (f" at {sg.harmonic:g} x the shaft speed" if sg.harmonic else "")
                near = [_term_match(sg, t, seen_speed[i])[1]
                        for i, t in enumerate(health.terms)
                        if t.kind in sg.kinds and t.attach in sg.attach and sg.harmonic]
                found = (f" (found: {near[0].split('(')[-1].rstrip(')')})" if near else "")
                out[key] = Variable(key, "term", S_MIN, "",
                                f"no {kinds} term on {where}{harm}{found}")
                out[key].links[f.id] = sg.absence_link
                out[key].what[f.id] = f"a {kinds} term on {where}{harm}"

    def _remembered_term(self, health: HealthMessage, f: FaultMode, sg: TermSign,
                         out: dict[str, Variable]) -> bool:
        """A periodic term the window lacks whose harmonic an attach point's track decided
        in the last :data:`TERM_MEMORY_WINDOWS` windows (:meth:`_harmonic_recall`), while
        the twin fails its model check: the fault that names it keeps that term as its
        evidence (strength :data:`TERM_MEMORY_STRENGTH`; a variable shared by the faults naming the
        same harmonic there), and its absence is no evidence against it. A misaligned
        coupling does not mend itself: the DC motor's 2x term, decided at 5.5 rad/s
        (misalignment 0.93), was not found again once the shaft ran at 9-18 rad/s with 1 %
        noise, and the view went to check function, or to no fault. Returns whether it
        did."""
        kept = self._harmonic.get(sg.attach[0]) if len(sg.attach) == 1 else None
        if (sg.harmonic is None or kept is None or kept[0] != sg.harmonic
                or not 0 < health.window - kept[1] <= TERM_MEMORY_WINDOWS
                or health.model_check is None or health.model_check.passed):
            return False
        h, w_kept = kept
        key = f"keptterm:{sg.attach[0]}:{h:g}"
        if key not in out:
            out[key] = Variable(
                key, "term", TERM_MEMORY_STRENGTH,
                f"a periodic term on {sg.attach[0]} at {h:g} x the shaft speed, decided in "
                f"window {w_kept} and not found again since, while the twin fails its check "
                f"(a forcing that does not mend itself, below what discovery separates from "
                f"the noise at this speed)", "")
        out[key].links[f.id] = sg.link
        out[key].what[f.id] = f"a periodic term on {sg.attach[0]} at {h:g} x the shaft speed"
        return True

    def _unexplained_vars(self, health: HealthMessage, out: dict[str, Variable]) -> None:
        """A degrading trend in a direction no fault expects is the unknown fault's evidence
        (link :data:`UNKNOWN_DEV_LINK`); deviations are :meth:`_dev_factors`'."""
        for name, p in health.parameters.items():
            if p.status in ("tied", "fixed") or not p.nominal or p.trend is None \
                    or not p.trend.degrading:
                continue
            for direction in ("up", "down"):
                key = f"trend:{name}:{direction}"
                if key not in out:
                    var = self.trend_variable(health, key, name, direction)
                    var.links["unknown"] = UNKNOWN_DEV_LINK
                    var.what["unknown"] = (f"{name} drifting {direction}, which no fault of "
                                           f"the library does")
                    var.unexplained = True
                    out[key] = var

    # -- graded deviations (twinwatch.twin.diagnosis.deviation) -----------------------------
    def _components(self, name: str, estimated: frozenset[str] = frozenset(),
                    alias: tuple[str, float, tuple[int, ...]] | None = None) -> _Comps:
        """Per hypothesis, the probability its faults move ``name`` up and down and their
        smallest sizes, and the directions no fault moves it in, in a window that estimated
        ``estimated`` (a signature's ``when_held``/``when_estimated``; cached); ``alias``:
        the alias' sign on it in this window (direction, smallest size [%], the columns of
        the faults moving it: the unknown fault's, or those naming the parameter;
        :meth:`_alias`), which leaves the directions no library fault moves it in as they
        are (a fault whose own sign moves it that way keeps its own)."""
        signs = [(i, d) for i, f in enumerate(self.faults) for d in f.deviations
                 if d.parameter == name]
        cond = frozenset(p for _, d in signs for p in (*d.when_held, *d.when_estimated))
        key = (name, estimated & cond, alias)
        c = self._comps.get(key)
        if c is not None:
            return c
        n_h = self._hyp.shape[0]
        items: list[tuple[int, str, float, float, float]] = [
            (i, d.direction, d.min_pct, d.link, d.max_pct or HI_PCT)
            for i, d in signs if d.applies(estimated)]
        covered = {direction for _, direction, _, _, _ in items}
        missing = tuple(d for d in ("up", "down") if d not in covered)
        library_items = list(items)
        if alias is not None:
            own = {i for i, d, _, _, _ in library_items if d == alias[0]}
            items.extend((i, alias[0], alias[1], ALIAS_LINK, HI_PCT) for i in alias[2]
                         if i not in own)
        arrays: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        reach: dict[str, float] = {}
        for direction in ("up", "down"):
            log_q = np.zeros(n_h)
            size = np.full(n_h, HI_PCT / 2)
            hi = np.zeros(n_h)
            for i, d, a, link, b in items:
                if d != direction:
                    continue
                on = self._hyp[:, i] > 0
                log_q += self._hyp[:, i] * math.log1p(-min(link, 1.0 - 1e-9))
                size = np.where(on, np.minimum(size, a), size)
                hi = np.where(on, np.maximum(hi, b), hi)
            arrays[direction] = (1.0 - np.exp(log_q), size, np.where(hi > 0, hi, HI_PCT))
        for _, d, _, _, b in library_items:
            reach[d] = max(reach.get(d, 0.0), b)
        c = _Comps(arrays["up"][0], arrays["up"][1], arrays["down"][0], arrays["down"][1],
                   {(i, d): a for i, d, a, _, _ in items}, missing, arrays["up"][2],
                   arrays["down"][2], reach)
        self._comps[key] = c
        return c

    def _evidence(self, health: HealthMessage) -> dict[str, tuple[_Dev, float]]:
        """Each parameter's last sound evidence and the standard error used [%] (grown by
        :data:`STALE_SD_PCT` per square root of its age in windows)."""
        names = dict.fromkeys([d.parameter for f in self.faults for d in f.deviations]
                              + [n for n, p in health.parameters.items()
                                 if p.status not in ("tied", "fixed") and p.nominal])
        evs: dict[str, tuple[_Dev, float]] = {}
        for name in names:
            ev = self._deviation(health, name)
            if ev is not None:
                evs[name] = (ev, _aged_sd(ev, health.window))
        return evs

    def _pooled_evidence(self, health: HealthMessage, evs: dict[str, tuple[_Dev, float]]
                         ) -> dict[str, tuple[_Dev, float]]:
        """``evs`` (:meth:`_evidence`'s) with each parameter's evidence pooled across the last
        windows where they allow it (:meth:`_pooled`; after :meth:`_read_aliases`, which reads
        the window's own)."""
        out = {}
        for name, (ev, sd) in evs.items():
            pooled = self._pooled(health, name, ev)
            out[name] = (ev, sd) if pooled is ev else (pooled, _aged_sd(pooled, health.window))
        return out

    def _across(self, health: HealthMessage, p: str
                ) -> tuple[float, float, int] | None:
        """A parameter ``p`` no window of the last :data:`ACROSS_WINDOWS` (after the onset)
        estimated, read from how the estimates moved with its alias from one sound window to
        the next (:data:`ACROSS_WINDOWS`' model, differenced).

        Per estimate ``e``, over its sound windows in order: ``x_k - x_{k-1} = c (a_k -
        a_{k-1}) + n_k - n_{k-1}``, the windows' noises ``n`` independent (standard errors
        ``s``), so the differences' covariance is tridiagonal (``s_k^2 + s_{k-1}^2``, and
        ``-s_k^2`` beside); generalised least squares over every estimate's differences,
        ``c``'s standard error times the Birge ratio. A window without ``p``'s alias (its
        effect negligible there, a steady speed, or none computed) is left out. Differencing
        takes each estimate's own change out, a step or a drift alike, but for the one
        difference it falls in.

        Returns:
            (its change ``c`` [%], standard error [%], the windows read) or None: ``p``
            estimated in one of those windows (its own estimates are its evidence), fewer
            than :data:`ACROSS_MIN` windows, the alias barely changing between windows
            (:data:`ACROSS_OWN`: a change of ``p`` and of the estimates themselves are then
            one pattern) or a standard error above :data:`ACROSS_MAX_SD`.
        """
        seqs: dict[str, list[tuple[float, float, float]]] = {}  # e -> [(a, x, s)]
        windows = 0
        for win, t_end, sound, al in self._aliased:
            if health.window - win >= ACROSS_WINDOWS or (
                    self._onset is not None and t_end <= self._onset):
                continue
            if p in sound:
                # estimated in the pool: its own estimates are its evidence (read along the
                # alias too, the PWM drive's Ra, held in one window of three, read +4 to
                # +6 % where its own windows said +10 %: a current reading low at 0.84)
                return None
            if not al:
                continue   # no alias computed: nothing estimated, or nothing asked
            if win in self._with_terms:
                # a meta-model term stands in the twin: what the physics lacks moves the
                # estimates between windows too (a drive's dead zone, its clip term in the
                # twin, read J -10 % +- 1.7 % and a speed reading high at 0.91)
                return None
            moves = al.get(p, {})
            used = [e for e in moves if e in sound]
            for e in used:
                d, sd = sound[e]
                seqs.setdefault(e, []).append((moves[e], d, max(sd, SD_FLOOR_PCT)))
            windows += bool(used)
        if windows < ACROSS_MIN:
            return None
        info = score = level = 0.0
        parts = []
        for seq in seqs.values():
            if len(seq) < 3:
                continue
            a = np.array([q[0] for q in seq])
            v = np.array([q[2] for q in seq]) ** 2
            da, dx = np.diff(a), np.diff(np.array([q[1] for q in seq]))
            cov = np.diag(v[1:] + v[:-1]) - np.diag(v[1:-1], 1) - np.diag(v[1:-1], -1)
            try:
                ci = np.linalg.inv(cov)
            except np.linalg.LinAlgError:
                continue
            info += float(da @ ci @ da)
            score += float(da @ ci @ dx)
            level += float(np.sum(a * a / v))
            parts.append((da, dx, ci))
        if not info > 0 or info < ACROSS_OWN * level:
            return None   # the alias barely changes: c and the estimates' changes are one
        c = score / info
        chi2 = sum(float((dx - c * da) @ ci @ (dx - c * da)) for da, dx, ci in parts)
        dof = sum(dx.size for _, dx, _ in parts) - 1
        if dof < 2 or chi2 / dof > ACROSS_FIT:
            return None   # the differences do not follow the alias: something else moved
        sd_c = math.sqrt(max(1.0, chi2 / dof) / info)
        if not sd_c < ACROSS_MAX_SD:
            return None
        return c, sd_c, windows

    def _across_evidence(self, health: HealthMessage, evs: dict[str, tuple[_Dev, float]]
                         ) -> dict[str, tuple[_Dev, float]]:
        """``evs`` with the read across windows (:meth:`_across`) of each parameter of the
        library's ``read_across`` that this window held (not fixed: those are read window by
        window, :meth:`_alias`), where it tells more than the parameter's own last evidence;
        when it is :data:`ACROSS_Z` standard errors from 0 each estimate of this window it
        moves is read net of it (explaining away: the held inertia's torque, taken by D after
        a set-point step, is not D's own change)."""
        out = dict(evs)
        self._across_fit = {}
        self._across_windows = {}
        carried = estimated_parameters(health)
        own = self._aliased[-1][3] if self._aliased and \
            self._aliased[-1][0] == health.window else {}
        for p in self.library.read_across:
            par = health.parameters.get(p)
            if par is None or par.status in ("estimated", "tied", "fixed") \
                    or not par.nominal:
                continue   # a fixed one is read window by window (:meth:`_alias`)
            read = self._across(health, p)
            hist = self._across_hist.setdefault(p, deque(maxlen=ACROSS_CONFIRM))
            hist.append(None if read is None else (read[0], read[1]))
            if read is None:
                continue
            c, sd_c, n = read
            if len(hist) < ACROSS_CONFIRM or not all(
                    q is not None and abs(q[0] - c) <= 3.0 * math.hypot(q[1], sd_c)
                    for q in hist):
                continue   # not yet read alike in the last windows
            prev = out.get(p)
            if prev is not None and prev[1] <= sd_c:
                continue
            ev = _Dev(c, sd_c, par.nominal * (1.0 + c / 100.0), par.nominal, par.unit,
                      health.window, par.status, carried, float(health.t_end),
                      pooled=n, across=f"read across {n} windows from how the estimates "
                                       f"moved with {p}'s alias in each")
            out[p] = (ev, sd_c)
            self._across_fit[p] = (c, sd_c, own.get(p, {}))
            self._across_windows[p] = n
            if abs(c) >= ACROSS_Z * sd_c:
                self._net_of(out, p, ev, own.get(p, {}), how="read across windows",
                             spend=False)
        return out

    def _fixed_alias_evidence(self, health: HealthMessage,
                              evs: dict[str, tuple[_Dev, float]]
                              ) -> dict[str, tuple[_Dev, float]]:
        """``evs`` with the change of a fixed parameter a fault of the library names, read
        from this window's estimates along its alias (:meth:`_alias`, named), as that
        parameter's evidence, and each estimate it moves read net of it (explaining away,
        as :meth:`_across_evidence` does for a held one): its signs on them are then spent.
        The PWM drive's Coulomb torque, fixed in its twin: Tc +150 % published Ra +5.3 %,
        Ke -4.2 %, D +18.7 %, read as Tc +164 % +- 24 % (1 sigma), while the D it moved kept
        worn bearings first at 0.64."""
        fit = self._alias_fit
        if fit is not None and fit.named:
            p = fit.parameter
            seen = self._alias_seen.get(p)
            par = health.parameters.get(p)
            if (seen is not None and seen[0] == health.window and par is not None
                    and par.status == "fixed" and par.nominal
                    and abs(fit.change) >= ALIAS_Z * fit.change_sd):
                c, sd_c = fit.change, fit.change_sd
                moves = {e: float(m) for e, m in health.aliases[p].moves.items()
                         if m is not None} if p in health.aliases else {}
                self._fixed_read[p] = (_Dev(
                    c, sd_c, par.nominal * (1.0 + c / 100.0), par.nominal, par.unit,
                    health.window, par.status, estimated_parameters(health),
                    float(health.t_end),
                    across=f"read from window {health.window}'s estimates along {p}'s alias"),
                    moves)
        out = dict(evs)
        for p, (ev, moves) in list(self._fixed_read.items()):
            onset = self._onset_of(p)
            if health.window - ev.window > ALIAS_MEMORY_WINDOWS or (
                    onset is not None and ev.t_end < onset):
                del self._fixed_read[p]
                continue
            out[p] = (ev, ev.sd)
            self._net_of(out, p, ev, moves, how="read along its alias", spend=True)
        return out

    def _net_of(self, out: dict[str, tuple[_Dev, float]], p: str, read: _Dev,
                moves: Mapping[str, float], *, how: str, spend: bool) -> None:
        """Each estimate in ``out`` whose evidence is from the window ``p``'s change was
        ``read`` in (its deviation and standard error [%]), read net of it along its alias
        there ``moves`` (estimate -> % per % of ``p``), in place: ``x_e - a_e c``, its
        variance grown by ``(a_e sd_c)^2``; ``how`` the read was made, for a person.
        ``spend``: the estimate counts as if its window had estimated ``p``, its
        ``when_held`` signs on ``p`` and its alias signs spent on the read (a fixed
        parameter's read along its alias, which is those signs' evidence)."""
        c, sd_c = read.dev, read.sd
        for e, a in moves.items():
            got = out.get(e)
            if got is None or got[0].window != read.window or e == p:
                continue
            e_ev, e_sd = got
            moved = a * c
            sd = math.sqrt(e_sd ** 2 + (a * sd_c) ** 2)
            out[e] = (dataclasses.replace(
                e_ev, dev=e_ev.dev - moved, sd=sd,
                value=e_ev.nominal * (1.0 + (e_ev.dev - moved) / 100.0),
                estimated=e_ev.estimated | {p} if spend else e_ev.estimated,
                across=f"net of {p}'s {c:+.1f} % {how} ({moved:+.2f} % of its "
                       f"{e_ev.dev:+.2f} %)"), sd)
            if spend:
                self._alias_signs.pop(e, None)

    def _read_aliases(self, health: HealthMessage,
                      evs: dict[str, tuple[_Dev, float]]) -> None:
        """This window's alias fit (:meth:`_alias`), its signs kept with the window of the
        evidence they were read from: a parameter whose last sound evidence is still that
        window's keeps the unknown fault's sign on it (the window after one that estimated Ra,
        Ke, J and D may estimate Ke and D only, and Ra's evidence is still the former's)."""
        fit = self._alias(health, evs)
        if fit is not None:
            self._alias_fit = fit
            self._alias_seen[fit.parameter] = (health.window, fit.change)
            for name, sign in fit.signs.items():
                self._alias_signs[name] = (health.window, sign)
        window = {n: ev.window for n, (ev, _) in evs.items()}
        for name in list(self._alias_signs):
            if window.get(name) != self._alias_signs[name][0]:
                del self._alias_signs[name]
        if not self._alias_signs:
            self._alias_fit = None

    def _alias_sign(self, name: str, ev: _Dev) -> tuple[str, float, tuple[int, ...]] | None:
        """The alias' sign on ``name`` read from ``ev``'s window (the unknown fault's, or the
        faults naming the aliased parameter: :meth:`_alias`), or None."""
        kept = self._alias_signs.get(name)
        return kept[1] if kept is not None and kept[0] == ev.window else None

    def _dev_factors(self, health: HealthMessage,
                     evs: dict[str, tuple[_Dev, float]]) -> list[_DevFactor]:
        """One factor per parameter with sound evidence (``evs``: :meth:`_evidence`'s, read
        once a window)."""
        out = []
        for name, (ev, sd) in evs.items():
            age = max(health.window - ev.window, 0)
            comps = self._components(name, ev.estimated, self._alias_sign(name, ev))
            leak, note = self._dev_leak.get(name, (LEAK["deviation"], ""))
            lik = likelihood(ev.dev, sd, comps.p_up, comps.size_up, comps.p_down,
                             comps.size_down, leak, comps.hi_up, comps.hi_down)
            when = "" if ev.window == health.window else f", last sound window {ev.window}"
            # which uncertainty: this window's estimate (rel_std_pct), not the fused evidence's
            # narrower one; floored at the twin's model error, widened with the evidence's age
            pooled = (ev.across if ev.across else
                      f"{ev.pooled} windows' estimates pooled" if ev.pooled > 1 else "")
            whose = ("the model-error floor" if sd <= SD_FLOOR_PCT * 1.0001 else
                     f"{pooled}, grown with its age" if age and pooled else
                     "grown with its age" if age else pooled or "this window's estimate")
            text = (f"{name} = {ev.value:.5g} {ev.unit} is {ev.dev:+.2f} % from its nameplate "
                    f"{ev.nominal:.5g} {ev.unit} (+/- {2 * sd:.2f} %, 2 sigma: {whose}; "
                    f"{ev.status}{when})")
            out.append(_DevFactor(name, ev, text, np.log(np.maximum(lik, 1e-300)), comps,
                                  sd, note))
        return out

    def _alias(self, health: HealthMessage, evs: dict[str, tuple[_Dev, float]]
               ) -> _AliasFit | None:
        """The estimates of this window read as one change of a parameter it did not
        estimate (``health.aliases``, :mod:`twinwatch.twin.estimation.aliases`): the unknown
        fault's signature in this window when no fault of the library names the parameter,
        else that of the faults seen through the estimates while it is held (a deviation
        sign on it that way and ``when_held`` signs on it: the PWM drive's dry friction and
        its fixed Tc), or None.

        For each such parameter ``p`` whose effect the estimates mimic
        (:data:`ALIAS_ABSORBED`), the change ``c`` [%] that best explains this window's
        deviations ``x_e`` (standard errors ``sd_e``) along its alias ``a_e`` is weighted
        least squares, ``c = sum(a x / sd^2) / sum(a^2 / sd^2)``. It is read when ``c`` is
        :data:`ALIAS_Z` standard errors from 0, what it leaves fits (chi-square p-value at
        least :data:`ALIAS_FIT_P`) and it moves two estimates or more by
        :data:`ALIAS_MIN_PCT` and twice their standard error; the best fit wins. The unknown
        fault then moves each of those estimates in the alias' direction by at least half
        the size it predicts (link :data:`ALIAS_LINK`): the PWM drive's tau_e +50 % (fixed
        in that twin) published Ra +28 %, Ke -6 %, J -12 %, D -6 %, which read as worn
        brushes and a weakened magnet at once.

        An alias read in the last :data:`ALIAS_MEMORY_WINDOWS` windows is read with one
        estimate moved (the unknown fault's only). A library fault's alias needs each
        estimate the pattern moves to have moved its way by a standard error itself: its
        Coulomb torque Tc +150 % published Ra +9 %, Ke -4 %, J -12 %, D +13 % (a current
        sensor reading low was named beside the friction at 0.92), while worn brushes and
        bearings at once, Ra +13 % and D +23 % with Ke put, fitted Tc's pattern loosely
        (p 0.02) and read as dry friction at 0.96 until that check."""
        best: tuple[float, _AliasFit] | None = None
        for p, a in health.aliases.items():
            if a.absorbed is None or a.absorbed < ALIAS_ABSORBED:
                continue
            pts = [(e, float(m), *evs[e]) for e, m in a.moves.items()
                   if m is not None and e in evs and evs[e][0].window == health.window]
            if len(pts) < 2:
                continue
            x = np.array([m for _, m, _, _ in pts])
            d = np.array([ev.dev for _, _, ev, _ in pts])
            sd = np.array([sd for _, _, _, sd in pts])
            w = 1.0 / sd ** 2
            sxx = float(np.sum(w * x * x))
            if sxx <= 0.0:
                continue
            c = float(np.sum(w * x * d)) / sxx
            c_sd = 1.0 / math.sqrt(sxx)
            pred = c * x
            chi = float(np.sum(w * (d - pred) ** 2))
            fit_p = float(chdtrc(len(pts) - 1, chi))
            moved = [(e, float(v)) for (e, _, _, s_e), v in zip(pts, pred, strict=True)
                     if abs(v) >= max(ALIAS_MIN_PCT, 2.0 * s_e)]
            named = p in self._named
            if named and p in health.parameters \
                    and health.parameters[p].status != "fixed":
                # estimated at times: its own estimates are its evidence (or, in the
                # library's read_across, its read across windows: :meth:`_across`)
                continue
            seen = self._alias_seen.get(p)
            recalled = (not named and seen is not None
                        and health.window - seen[0] <= ALIAS_MEMORY_WINDOWS and seen[1] * c > 0)
            if abs(c) < ALIAS_Z * c_sd or fit_p < ALIAS_FIT_P or len(moved) < (
                    1 if recalled else 2):
                continue
            if named and not all(ev.dev * v >= 0 and abs(ev.dev) >= s_e
                                 for (e, _, ev, s_e), v in zip(pts, pred, strict=True)
                                 if any(e == m for m, _ in moved)):
                # a fault of the library would explain these estimates through it: each one
                # the pattern moves must have moved its way itself (a Ke that stayed put
                # is no Coulomb friction's, whatever Ra and D did)
                continue
            owners = (self._through.get((p, "up" if c > 0 else "down"), ()) if named
                      else (len(self.faults),))
            if not owners:  # named, and no fault is seen through the estimates that way
                continue
            signs = {e: ("up" if v > 0 else "down", _grid(0.5 * abs(v)), owners)
                     for e, v in moved}
            said = ", ".join(f"{e} {ev.dev:+.1f} %" for e, _, ev, _ in pts
                             if e in signs)
            status = health.parameters[p].status if p in health.parameters else "fixed"
            whose = (", ".join(self.faults[i].id for i in owners) + f" moves {p} so"
                     if named else "a change the library does not know")
            fit = _AliasFit(p, c, c_sd, float(a.absorbed), signs,
                            f"{said} moved together, as a change of {p} by {c:+.1f} % +/- "
                            f"{2 * c_sd:.1f} % (2 sigma) would move them: {p} is not "
                            f"estimated here ({status}), and the estimates carry "
                            f"{100 * a.absorbed:.1f} % of its effect (the pattern fits: "
                            f"p = {fit_p:.2f}); {whose}", named)
            if best is None or fit_p > best[0]:
                best = (fit_p, fit)
        return best[1] if best is not None else None

    @staticmethod
    def _unexplained_dev_var(devs: list[_DevFactor]) -> Variable | None:
        """One variable for the unknown fault: some parameter moved beyond
        :data:`UNEXPLAINED_PCT` in a direction no fault of the library moves it, or beyond the
        largest size (``max_pct``) of every fault that moves it that way (the strongest such
        deviation's strength). One, not one per parameter: a fault the library
        does not know moves some parameter, and every other one staying put is no evidence
        against it."""
        best: tuple[float, str] | None = None
        for d in devs:
            for direction in d.comps.unexplained:
                signed = d.ev.dev if direction == "up" else -d.ev.dev
                s = _phi((signed - UNEXPLAINED_PCT) / d.sd)
                if best is None or s > best[0]:
                    best = (s, f"{d.text}: no fault of the library moves {d.name} "
                               f"{direction}")
            for direction, reach in d.comps.reach.items():
                if reach >= HI_PCT:
                    continue
                signed = d.ev.dev if direction == "up" else -d.ev.dev
                s = _phi((signed - reach) / d.sd)
                if best is None or s > best[0]:
                    best = (s, f"{d.text}: beyond the {reach:g} % any fault of the library "
                               f"moves {d.name} {direction}")
        if best is None:
            return None
        var = Variable("dev:unexplained", "deviation", clip(best[0]), best[1],
                   "no parameter moved where no fault of the library moves it",
                   links={"unknown": UNKNOWN_DEV_LINK},
                   what={"unknown": "a parameter moving where no fault of the library "
                                    "moves it"}, unexplained=True)
        return var

    def _intermittent_vars(self) -> list[Variable]:
        """A change that comes and goes, over the last :data:`INTERMITTENT_WINDOWS` windows:
        the unknown fault's evidence (link :data:`INTERMITTENT_LINK`), named in
        ``unexplained``; present only when seen (a fault the library does not know need not
        come and go: its absence is no evidence against it).

        * ``intermittent:parameter``: a sound estimate away from its nameplate (by
          :data:`INTERMITTENT_AWAY_PCT` and :data:`INTERMITTENT_AWAY_SD` standard errors)
          came back home :data:`INTERMITTENT_RETURNS` times or more. No library fault's
          signature comes back by itself (a repaired part returns once).
        * ``intermittent:model_check``: the twin failed its check in bursts
          (:data:`INTERMITTENT_FAIL_SHARE` of the windows or more, in
          :data:`INTERMITTENT_RUNS` separate runs, the same share passing): something
          acts on the machine part of the time. The faults that may leave a check failing
          or passing (``may_pass``) explain it with that check's largest link (an
          unbalance's periodic term fitted at one frequency a window leaves the check
          failing in some); a fault whose check fails throughout (a speed reading's gain)
          does not.

        Isermann, *Fault-Diagnosis Systems* (2006), sec. 2.2: a fault's time behaviour is
        abrupt, incipient or intermittent; the library's modes are the first two."""
        out: list[Variable] = []
        seqs: dict[str, list[tuple[int, float, float]]] = {}
        for w, sound in self._sound:
            for name, (dev, sd) in sound.items():
                seqs.setdefault(name, []).append((w, dev, sd))
        best: tuple[int, str] | None = None
        for name, seq in seqs.items():
            away, returns, peak, first = False, 0, 0.0, None
            for w, dev, sd in seq:
                if abs(dev) >= max(INTERMITTENT_AWAY_PCT, INTERMITTENT_AWAY_SD * sd):
                    away, peak = True, max(peak, abs(dev))
                    first = w if first is None else first
                elif (abs(dev) <= max(INTERMITTENT_HOME_PCT, INTERMITTENT_HOME_SD * sd)
                      and abs(dev) < peak / 4):
                    if away:
                        returns += 1
                    away, peak = False, 0.0
            if returns >= INTERMITTENT_RETURNS and (best is None or returns > best[0]):
                far = max((d for _, d, _ in seq), key=abs)
                best = (returns, f"{name} went {far:+.0f} % from its nameplate and came back "
                                 f"to it {returns} times in the last {len(self._sound)} "
                                 f"windows (since window {first}): a change that comes and "
                                 f"goes")
        if best is not None:
            out.append(Variable(
                "intermittent:parameter", "deviation", clip(1.0), best[1],
                "no estimate came and went", links={"unknown": INTERMITTENT_LINK},
                what={"unknown": "a change that comes and goes (an intermittent load or "
                                 "fault), which no fault of the library does"},
                leak=INTERMITTENT_LEAK, unexplained=True))
        rec = list(self._passed)
        n, k = len(rec), sum(1 for ok in rec if not ok)
        runs = sum(1 for i, ok in enumerate(rec) if not ok and (i == 0 or rec[i - 1]))
        if (2 * n >= INTERMITTENT_WINDOWS and runs >= INTERMITTENT_RUNS
                and k >= INTERMITTENT_FAIL_SHARE * n and n - k >= INTERMITTENT_FAIL_SHARE * n):
            text = (f"the model check failed in {k} of the last {n} windows, in {runs} "
                    f"separate runs: something that comes and goes")
            var = Variable("intermittent:model_check", "model_check", clip(1.0), text,
                           "the model check did not fail in bursts",
                           links={"unknown": INTERMITTENT_LINK},
                           what={"unknown": "the twin failing its check part of the time "
                                            "(something that comes and goes)"},
                           leak=INTERMITTENT_LEAK, unexplained=True)
            for f in self.faults:
                links = [c.link for c in f.checks if c.may_pass]
                if links:
                    var.links[f.id] = max(links)
                    var.what[f.id] = "its model checks failing in some windows"
            out.append(var)
        return out

    def _model_error(self, out: dict[str, Variable], term: TermHealth, weight: float) -> None:
        """A term no fault explains is model error in its equation: the deviations and trends
        of that equation's parameters (the library's ``equations``) leak up to
        :data:`LEAK_UNEXPLAINED`, by ``weight`` (the term's strength times how little the
        library explains it). Noisy-OR's explaining away: Ra pushed up by a drive's dead zone is
        no longer near-proof of worn brushes."""
        names = self.library.equations.get(term.attach, [])
        for name in names:
            leak = LEAK["deviation"] + (LEAK_UNEXPLAINED - LEAK["deviation"]) * weight
            if leak > self._dev_leak.get(name, (LEAK["deviation"], ""))[0]:
                self._dev_leak[name] = (leak, f" (a term no fault explains acts in the same "
                                              f"equation, {term.attach}: leak {leak:.2f})")
        for v in out.values():
            kind, _, rest = v.key.partition(":")
            if kind != "trend" or rest.split(":", 1)[0] not in names:
                continue
            base = v.leak if v.leak is not None else LEAK[v.kind]
            leak = LEAK[v.kind] + (LEAK_UNEXPLAINED - LEAK[v.kind]) * weight
            if leak > base:
                v.leak = leak
                if v.present and "no fault explains" not in v.present:
                    v.present += (f" (a term no fault explains acts in the same equation, "
                                  f"{term.attach}: leak {leak:.2f})")

    def _track(self, health: HealthMessage, speed: tuple[float, float] | None
               ) -> list[list[_Ratio] | None]:
        """Per term of the message, its frequency against the shaft speed window by window
        (the last :data:`HARMONIC_WINDOWS` windows in a row; None: not a periodic term of
        time, or no shaft speed). A term continues the track of the last window's periodic
        term on the same attach point whose ratio is within :data:`RATIO_STEP` of its own,
        across re-discoveries: an unbalance that follows the shaft is re-found at each new
        speed, its ratio staying 1."""
        out: list[list[_Ratio] | None] = []
        kept: list[tuple[str, list[_Ratio]]] = []
        for term in health.terms:
            b = term.params.get("b")
            if (term.kind != "periodic" or b is None or term.input != "t" or speed is None
                    or speed[0] <= 0):
                out.append(None)
                continue
            r = _Ratio(health.window, abs(b), term.params_std.get("b") or 0.0, speed[0],
                       speed[1])
            ratio = r.b / r.speed
            best: list[_Ratio] | None = None
            for attach, tr in self._tracks:
                last = tr[-1]
                step = abs(ratio - last.b / last.speed)
                if (attach == term.attach and last.window == health.window - 1
                        and step <= RATIO_STEP * last.b / last.speed
                        and all(tr is not k for _, k in kept)
                        and (best is None or step < abs(ratio - best[-1].b / best[-1].speed))):
                    best = tr
            track = ((best or []) + [r])[-HARMONIC_WINDOWS:]
            kept.append((term.attach, track))
            out.append(track)
        self._tracks = kept
        return out

    def trend_variable(self, health: HealthMessage, key: str, name: str, direction: str
                       ) -> Variable:
        """A parameter's trend degrading in ``direction``: strength 0.95 for a degrading trend
        that way, 0.05 the other way, 0.2 for a flat one, 0.5 without a trend or without an
        estimate since the change (:class:`~twinwatch.twin.diagnosis.evidence.
        EvidenceSource`)."""
        p = health.parameters.get(name)
        t = p.trend if p is not None else None
        if t is None or t.model is None or t.rate is None:
            return Variable(key, "trend", 0.5, "", f"{name}: no trend yet")
        if self._deviation(health, name) is None:
            # not estimated since the change (or for long): its trend is the held value's
            return Variable(key, "trend", 0.5, "", f"{name}: not estimated since the change")
        up = t.rate > 0
        if t.degrading:
            s = 0.95 if up == (direction == "up") else 0.05
        else:
            # flat within its uncertainty: weaker against a fault its rate leans towards
            s = TREND_FLAT_LEANING if up == (direction == "up") and t.rate else TREND_FLAT
        rate = (f"{t.rate_pct_per_h:+.3g} %/h" if t.rate_pct_per_h is not None
                else f"{t.rate:+.3g} {p.unit}/s")  # type: ignore[union-attr]
        text = (f"{name} trend ({t.model}, {t.evidence} windows) "
                + (f"degrading at {rate}" if t.degrading else f"flat within its uncertainty "
                   f"({rate})"))
        return Variable(key, "trend", clip(s), text, text)

    def _misfit_since(self, window: int | None) -> float:
        """Probability that the twin fails its model check (any output) in more than
        :data:`CHECK_RATE` of its windows since ``window`` (a term's first; at most the last
        :data:`CHECK_RATE_WINDOWS`), from their record (a Beta posterior, uniform prior)."""
        seen = [all(o.values()) for w, o in self._outputs if window is None or w >= window]
        if not seen:
            return 0.0
        n, k = len(seen), sum(1 for ok in seen if not ok)
        return _rate_above(k, n)

    def recent_sensors(self, health: HealthMessage) -> list[tuple[int, SensorHealth]]:
        """The stuck sensors of this window and of the last :data:`SENSOR_WINDOWS` (the window
        each was last found in, what was found then)."""
        if self._stuck_window != health.window:
            self._stuck_window = health.window
            for s in health.sensors:
                self._stuck[(s.kind, s.channel)] = (health.window, s)
        return [(w, s) for w, s in self._stuck.values()
                if 0 <= health.window - w <= SENSOR_WINDOWS]

    def check_rate_variable(self, output: str) -> Variable:
        """An output failing its model check persistently: the share of the last
        :data:`CHECK_RATE_WINDOWS` windows that failed on it, its strength the probability
        that the output's failure rate exceeds :data:`CHECK_RATE` (a Beta posterior from a
        uniform prior)."""
        seen = [o[output] for _, o in self._outputs if output in o]
        n, k = len(seen), sum(1 for ok in seen if not ok)
        if n == 0:
            return Variable(f"check:{output}", "model_check", 0.5, "",
                            f"no model check of {output}")
        s = _rate_above(k, n)
        text = f"{output}'s model check failed in {k} of the last {n} windows"
        return Variable(f"check:{output}", "model_check", clip(s), text, text)

    def scaling_variable(self, health: HealthMessage, key: str, name: str,
                         power: float) -> Variable | None:
        """``name``'s deviation scaling as the shaft speed to ``power``: over the windows of
        the last :data:`SCALING_WINDOWS` that estimated it since the change onset, moved from
        the nameplate one way (beyond :data:`MOVED_SD` standard errors and :data:`MOVED_PCT`),
        the least-squares slope ``e`` of ln|deviation| against ln(speed); strength
        ``exp(-((e - power) / SCALING_TOL)^2 / 2)``. Undecided (None) with fewer than
        :data:`SCALING_MIN_WINDOWS` such windows or speeds spanning less than a factor
        :data:`SCALING_SPAN`. A Coulomb friction absorbed into D (DC motor, Tc 0.002 N m):
        slope -1.0 over 5.5-18 rad/s; worn bearings D +8 %: -0.05; a weakened field with Ke
        held (D +57 %): about 0."""
        pts = [(w, sp, dev, sd) for w, t, sp, dev, sd in self._speed_devs.get(name, ())
               if (self._onset is None or t >= self._onset) and _moved(dev, sd)]
        if pts and not (all(d > 0 for _, _, d, _ in pts) or all(d < 0 for _, _, d, _ in pts)):
            return None
        speeds = [sp for _, sp, _, _ in pts]
        if len(pts) < SCALING_MIN_WINDOWS or max(speeds) < SCALING_SPAN * min(speeds):
            return None
        x = np.log(np.array(speeds))
        y = np.log(np.abs(np.array([d for _, _, d, _ in pts])))
        e = float(np.polyfit(x, y, 1)[0])
        s = clip(math.exp(-0.5 * ((e - power) / SCALING_TOL) ** 2))
        lo = min(pts, key=lambda q: q[1])
        hi = max(pts, key=lambda q: q[1])
        said = (f"{name}'s deviation scales as the shaft speed to the power {e:.2f} over "
                f"{len(pts)} windows ({lo[2]:+.1f} % at {lo[1]:.3g} rad/s, {hi[2]:+.1f} % at "
                f"{hi[1]:.3g} rad/s)")
        return Variable(key, "scaling", s, said, said + f", not {power:g}")

    @staticmethod
    def _term_var(i: int, term: TermHealth) -> Variable:
        # the main coefficient against its standard error: over the windows the term has
        # explained (params_std) or, before its first polish, this window's significance
        sig = term.significance
        z_all = None
        if term.weight is not None:
            for k, v in term.params.items():
                std = term.params_std.get(k)
                if v == term.weight and std:
                    z_all = abs(v) / std
        z = max(x for x in (sig, z_all, 0.0) if x is not None)
        s = clip(_phi((z if (sig is not None or z_all is not None) else 5.0) - 3.0))
        sig_txt = (f"{z:.1f} standard errors from 0"
                   if sig is not None or z_all is not None else "kept")
        return Variable(f"term:{i}", "term", s,
                    f"term {term.equation} ({sig_txt}, since window {term.since_window})",
                    f"term {term.equation} is not significant ({sig_txt})")

    # -- inference ----------------------------------------------------------------------------
    def update(self, health: HealthMessage, speed: tuple[float, float] | None = None
               ) -> DiagnosisHealth:
        """The ranked fault modes after this window.

        Args:
            health: the window's health message (parameters, terms, model check, sensors).
            speed: the window's mean absolute shaft speed and its spread [rad/s]
                (:func:`shaft_speed`), for a periodic term's harmonic.
        """
        self._observe(health, speed)
        evs = self._evidence(health)
        # an alias is read from this window's own estimates: its pattern is the window's
        self._read_aliases(health, evs)
        evs = self._pooled_evidence(health, evs)
        evs = self._across_evidence(health, evs)
        evs = self._fixed_alias_evidence(health, evs)
        variables, unexplained = self._variables(health, speed)
        devs = self._dev_factors(health, evs)
        extra = self._unexplained_dev_var(devs)
        if extra is not None:
            variables.append(extra)
        variables.extend(self._intermittent_vars())
        marg, post, lik0, s, leak = self._posterior(variables, devs)
        p_none = float(post[0])
        order = [int(i) for i in np.argsort(-marg[:-1])]
        said = {i: self._said(i, variables, devs, lik0, s, leak) for i in order}
        faults = self._listed(order, marg, said)
        ruled_out = [self._why_not(i, float(marg[i]), said[i], order[0], said[order[0]])
                     for rank, i in enumerate(order)
                     if rank > 0 and marg[i] < 0.2
                     and (said[i][0] or any("(found: " in c for c in said[i][1]))]
        p_unknown = float(marg[-1])
        top = faults[0] if faults else None
        status, best = _outcome(p_none, p_unknown, top)
        since, record, share = self._check_function(health)
        # a named fault or a discovered term no fault explains (the unknown fault) is the
        # failed checks' explanation: the twin lacks that, it is not a twin that stopped fitting
        explained = ((status == "fault" and order and _explains_check(said[order[0]][0]))
                     or (status == "unknown" and bool(unexplained)))
        if since is not None and not explained:
            status = "check_function"
            best = share  # the share of the horizon's windows the twin did not describe
        return DiagnosisHealth(
            status=status,
            top=top.id if status == "fault" and top is not None else None,
            probability=best,
            no_fault=p_none,
            unknown=p_unknown,
            unknown_terms=[t.equation for t in unexplained],
            faults=faults,
            shaft_speed=speed[0] if speed else None,
            library=f"{self.library.model} ({self.source})",
            evidence=(sum(1 for v in variables if abs(v.s - 0.5) > 0.1)
                      + sum(1 for d in devs if np.ptp(d.log_lik) > 0.2)),
            check_function_since=since,
            check_failed=record,
            unexplained=self._unexplained_lines(variables) + (
                [self._alias_fit.text] if self._alias_fit is not None
                and not self._alias_fit.named and p_unknown > 0.2 else []),
            ruled_out=ruled_out,
            unobserved=self._unobserved(health),
            read_across={p: AcrossRead(deviation_pct=c, std_pct=sd_c,
                                       over_windows=self._across_windows.get(p, 0))
                         for p, (c, sd_c, _) in self._across_fit.items()},
        )

    def _unobserved(self, health: HealthMessage) -> list[str]:
        """The fault modes this window cannot see: each parameter their deviation signs move
        (link 0.5 or more) has no evidence from the last :data:`STALE_MAX_WINDOWS` windows,
        and they have no term, sensor or output-check sign (which every window can show).
        "No fault" about them is their prior, not a finding (a load inertia step of 50 % with
        J never determined by a window read "no fault 0.98")."""
        out = []
        for f in self.faults:
            if f.terms or f.sensors or any(c.link >= 0.5 for c in f.checks):
                continue
            names = list(dict.fromkeys(d.parameter for d in f.deviations if d.link >= 0.5))
            if not names or any(self._deviation(health, n) is not None
                                or n in self._across_fit for n in names):
                continue
            why = []
            for n in names:
                p = health.parameters.get(n)
                seen = self._last.get(n)
                since = ("never determined by a window" if seen is None else
                         f"last determined in window {seen.window}")
                state = "not estimated" if p is None or p.status in ("fixed", "tied") \
                    else p.status
                why.append(f"{n} {state}, {since}")
            out.append(f"{f.id} ({f.component}) cannot be seen now: {'; '.join(why)}")
        return out

    def _listed(self, order: list[int], marg: np.ndarray,
                said: dict[int, tuple[list[tuple[float, str, str]], list[str]]]
                ) -> list[FaultHealth]:
        """The :attr:`listed` most probable fault modes (``order``: the faults by decreasing
        marginal ``marg``), each with its evidence for and against (``said``)."""
        faults: list[FaultHealth] = []
        for i in order[:self.listed]:
            pro, con = said[i]
            f = self.faults[i]
            faults.append(FaultHealth(
                id=f.id, component=f.component, probability=float(marg[i]),
                action=f.action, urgency=f.urgency, source=f.source,
                evidence_for=[t for _, t, _ in pro], evidence_against=con))
        return faults

    def _posterior(self, variables: list[Variable], devs: list[_DevFactor]
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Exact posterior over the hypotheses of at most two faults (the module's model):
        each fault's marginal (n_faults + 1, unknown last), the hypotheses' posterior
        (n_hyp), the no-fault hypothesis' likelihood of each variable, the strengths and the
        leaks (n_vars)."""
        idx = {fid: i for i, fid in enumerate(self._ids)}
        n_e = len(variables)
        log_q = np.zeros((len(self._ids), n_e))       # log(1 - link)
        log_q_strict = np.zeros((len(self._ids), n_e))  # without the links of ``may``
        s = np.empty(n_e)
        leak = np.empty(n_e)
        for j, v in enumerate(variables):
            s[j] = v.s
            leak[j] = v.leak if v.leak is not None else LEAK[v.kind]
            for fid, link in v.links.items():
                log_q[idx[fid], j] = math.log1p(-min(link, 1.0 - 1e-9))
                if fid not in v.may:
                    log_q_strict[idx[fid], j] = log_q[idx[fid], j]
        # P(e | H) for every hypothesis, then the soft observation's likelihood (its absence
        # read without the links that only permit it)
        p_e = 1.0 - np.exp(self._hyp @ log_q + np.log1p(-leak)[None, :])
        p_e_strict = 1.0 - np.exp(self._hyp @ log_q_strict + np.log1p(-leak)[None, :])
        lik = s[None, :] * p_e + (1.0 - s[None, :]) * (1.0 - p_e_strict)
        log_post = self._log_prior + np.log(lik).sum(axis=1)
        for d in devs:
            log_post = log_post + d.log_lik
        log_post -= log_post.max()
        post = np.exp(log_post)
        post /= post.sum()
        return self._hyp.T @ post, post, lik[0], s, leak

    def _said(self, i: int, variables: list[Variable], devs: list[_DevFactor], lik0: np.ndarray,
              s: np.ndarray, leak: np.ndarray
              ) -> tuple[list[tuple[float, str, str]], list[str]]:
        """The evidence for fault ``i`` (log likelihood ratio, sentence, what it is about) and
        against it, strongest first: each piece's log likelihood ratio alone, the fault
        against no fault, beyond :data:`LLR_SAID`."""
        fid = self._ids[i]
        pro: list[tuple[float, str, str]] = []
        con: list[tuple[float, str]] = []
        for d in devs:
            llr = float(d.log_lik[1 + i] - d.log_lik[0])
            up, down = d.comps.sizes.get((i, "up")), d.comps.sizes.get((i, "down"))
            if up is None and down is None:
                continue
            direction, size = (("up", up) if up is not None and (down is None or d.ev.dev > 0)
                               else ("down", down))
            side = "above" if direction == "up" else "below"
            signed = d.ev.dev if direction == "up" else -d.ev.dev
            word = "beyond" if signed > (size or 0.0) else "within"
            said = f"{d.text}: {word} the {size:g} % {direction}"
            if llr > LLR_SAID:
                pro.append((llr, said + d.leak_note, d.name))
            elif llr < -LLR_SAID:
                con.append((-llr, f"{said} (expects {d.name} {side} nameplate by at least "
                                  f"{size:g} %)"))
        for j, v in enumerate(variables):
            if fid not in v.links:
                continue
            pe = 1.0 - (1.0 - leak[j]) * (1.0 - v.links[fid])
            absent = 1.0 - (leak[j] if fid in v.may else pe)
            llr = math.log((s[j] * pe + (1 - s[j]) * absent) / lik0[j])
            if llr > LLR_SAID and v.present:
                text = v.present
                if v.key.startswith("term:") and "shaft speed" in v.what.get(fid, ""):
                    text += ": " + v.what[fid].split(" (", 1)[-1].rstrip(")")
                pro.append((llr, text, v.key.split(":")[1] if v.kind == "trend" else v.key))
            elif llr < -LLR_SAID:
                con.append((-llr, f"{v.absent or v.present} (expects "
                                  f"{v.what.get(fid, 'it')})"))
        return (sorted(pro, key=lambda x: -x[0]), [t for _, t in sorted(con, reverse=True)])

    def _why_not(self, i: int, p: float, said: tuple[list[tuple[float, str, str]], list[str]],
                 top: int, top_said: tuple[list[tuple[float, str, str]], list[str]]) -> str:
        """Why a fault with evidence for it was ruled out, for a person: the strongest thing it
        expects and the window does not show, then the mode that explains its evidence with
        one fault (explaining away)."""
        f = self.faults[i]
        pro, con = said
        why = [con[0]] if con else []
        if top != i:
            t = self.faults[top]
            shared = dict.fromkeys(w for _, _, w in pro if w in {w2 for _, _, w2 in top_said[0]})
            if shared:
                why.append(f"{t.id} ({t.component}) explains {' and '.join(shared)} as one "
                           f"fault")
        if not why and pro:
            why.append(f"its evidence ({pro[0][1]}) is better explained otherwise")
        return f"{f.id} ({f.component}) ruled out at {p:.2f}" + (
            ": " + "; ".join(why) if why else "")

    @staticmethod
    def _unexplained_lines(variables: list[Variable]) -> list[str]:
        """The deviations and trends no fault of the library expects that are there (the
        unknown fault's evidence), for a person."""
        return [v.present for v in variables if v.unexplained and v.s > 0.5 and v.present]

    def _check_function(self, health: HealthMessage
                        ) -> tuple[float | None, str | None, float]:
        """The twin-no-longer-fits state (NAMUR NE 107 *check function*): entered when at
        least :attr:`check_share` of the windows of the last :attr:`check_after_s` of plant
        time failed their model check; left after :attr:`check_clear` windows in a row that
        passed (the failures before them forgotten: entering again takes a new stretch).
        Returns the plant time it started (None: not in it), the record of the horizon for a
        person (None: no failed check in it) and the share of its windows that failed."""
        mc = health.model_check
        if mc is None:
            return self._cf_since, None, 0.0
        self._checks.append((health.t_start, health.t_end, mc.passed))
        while self._checks and self._checks[0][0] < health.t_end - self.check_after_s - 1e-6:
            self._checks.popleft()  # keep the windows within the horizon
        self._passed_run = self._passed_run + 1 if mc.passed else 0
        failed = [c for c in self._checks if not c[2]]
        covered = health.t_end - self._checks[0][0]
        share = len(failed) / len(self._checks)
        if self._cf_since is None:
            if covered >= 0.95 * self.check_after_s and share >= self.check_share:
                self._cf_since = failed[0][0]
        elif self._passed_run >= self.check_clear:
            # the twin fits again: a new check function needs a new stretch of failures
            self._cf_since = None
            self._checks = deque(list(self._checks)[-self.check_clear:])
        if not failed:
            return self._cf_since, None, 0.0
        record = (f"the model check failed in {len(failed)} of the last {len(self._checks)} "
                  f"windows ({covered:.0f} s)")
        return self._cf_since, record, share


def _rate_above(k: int, n: int) -> float:
    """Probability that a check's failure rate exceeds :data:`CHECK_RATE` after ``k``
    failures in ``n`` windows (the Beta(k + 1, n - k + 1) posterior of a uniform prior)."""
    return float(betainc(n - k + 1, k + 1, 1.0 - CHECK_RATE))


#: A sound estimate that jumps away from the nameplate by more than this many combined
#: standard errors, and by more than :data:`JUMP_SHARE` of its deviation, from the sound
#: estimate before it is not the machine's until the next sound window confirms it.
JUMP_SD = 3.0
JUMP_SHARE = 0.5


def _aged_sd(ev: _Dev, window: int) -> float:
    """``ev``'s standard error [%] grown by :data:`STALE_SD_PCT` per square root of its age in
    windows at ``window``."""
    return math.hypot(ev.sd, STALE_SD_PCT * math.sqrt(max(window - ev.window, 0)))


def _confirmed(ev: _Dev, prev: _Dev) -> bool:
    """Whether ``ev``, the last sound evidence on a parameter, stands after ``prev``, the one
    before it: a fault is a persistent symptom (Isermann, *Fault-Diagnosis Systems*, 2006,
    sec. 7.3: a change detected is confirmed over more than one sample). A move back towards
    the nameplate stands at once (a repair); a jump away from it by more than
    :data:`JUMP_SD` combined standard errors and :data:`JUMP_SHARE` of its own size waits
    for the next sound window. A drift moves each window by a small share of its size and
    stands; an intermittent load that one window of a twin failing its check around it
    absorbed into the hydraulic D (+5.5 % for one window, the windows before and after at
    0) read as degraded fluid at 0.94 for 12 s."""
    if abs(ev.dev) <= abs(prev.dev):
        return True
    step = abs(ev.dev - prev.dev)
    return step <= max(JUMP_SD * math.hypot(ev.sd, prev.sd), JUMP_SHARE * abs(ev.dev))


def _grid(x: float) -> float:
    """``x`` > 0 on a grid of 20 steps a decade (a cache key that stays small)."""
    return float(10.0 ** (round(20.0 * math.log10(x)) / 20.0))


def _outcome(p_none: float, p_unknown: float, top: FaultHealth | None
             ) -> tuple[Literal["no_fault", "fault", "unknown", "check_function"], float]:
    """The window's status before the check function and its probability: the most probable
    of a named fault (``top``), a fault the library does not know and no fault."""
    best = max(p_none, p_unknown, top.probability if top else 0.0)
    if top is not None and best == top.probability:
        return "fault", best
    if best == p_unknown and p_unknown > p_none:
        return "unknown", best
    return "no_fault", best


def _moved(dev: float, sd: float) -> bool:
    """A deviation [%] with standard error ``sd`` [%] beyond its nameplate's interval."""
    return abs(dev) > max(MOVED_SD * sd, MOVED_PCT)


def _change_onset(health: HealthMessage) -> float | None:
    """The earliest onset [s] (change point) among the window's trends, or None: a trend
    that has stopped rising (a step, a drift that ended) keeps the onset it found."""
    onsets = [p.trend.onset for p in health.parameters.values()
              if p.trend is not None and p.trend.onset is not None]
    return min(onsets) if onsets else None


def _explains_check(pro: list[tuple[float, str, str]]) -> bool:
    """The top fault's evidence for it includes a discovered term, the failed model check
    or a stuck sensor (the evidence kinds that explain failed checks): the failed checks are
    its evidence (what the twin lacks, a sensor it cannot follow), not a twin that no longer
    fits."""
    return any(explains_check(k) for _, _, k in pro)


def _term_match(sg: object, term: TermHealth, track: list[_Ratio] | None
                ) -> tuple[float, str]:
    """How well a discovered term fits a signature's term (0..1) and what it expects; a
    harmonic is judged on the term's ``track`` (:meth:`Diagnoser._track`)."""
    assert isinstance(sg, TermSign)
    kinds = "/".join(sg.kinds).replace("*", "any")
    where = "/".join(sg.attach)
    if "*" not in sg.kinds and term.kind not in sg.kinds:
        return 0.0, f"a {kinds} term on {where}"
    if "*" not in sg.attach and term.attach not in sg.attach:
        return 0.0, f"a {kinds} term on {where}"
    if sg.mode is not None and term.mode != sg.mode:
        return 0.0, f"a {sg.mode} {kinds} term on {where}"
    if sg.harmonic is None:
        return 1.0, f"a {kinds} term on {where}"
    want = f"a {kinds} term on {where} at {sg.harmonic:g} x the shaft speed"
    b = term.params.get("b")
    if term.kind != "periodic" or b is None or term.input != "t":
        return 0.0, want
    if track is None:
        return 0.5, want + " (shaft speed unknown)"
    if len(track) < HARMONIC_WINDOWS:
        return 0.5, (f"{want} (undecided: its frequency against the shaft speed in "
                     f"{len(track)} window(s) in a row, fewer than {HARMONIC_WINDOWS})")
    h, tol = sg.harmonic, sg.tolerance
    z = 0.0
    for r in track:  # every window of the track: a term that follows the shaft, or not
        sigma = math.hypot(r.b_std, tol * h * r.speed, h * r.spread)
        z = max(z, abs(r.b - h * r.speed) / sigma if sigma > 0 else math.inf)
    m = 1.0 if z <= 1.0 else math.exp(-0.5 * (z - 1.0) ** 2)
    now = track[-1]
    ratios = [r.b / r.speed for r in track]
    speeds = [r.speed for r in track]
    span = (f"{min(speeds):.3g} rad/s" if max(speeds) - min(speeds) < 0.005 * max(speeds)
            else f"{min(speeds):.3g}-{max(speeds):.3g} rad/s")
    return m, (f"{want} ({now.b:.3g} rad/s against {h:g} x {now.speed:.3g} = "
               f"{h * now.speed:.3g} rad/s +/- {100 * tol:.0f} %; {min(ratios):.3f}-"
               f"{max(ratios):.3f} x the shaft speed over the last {len(track)} windows, the "
               f"shaft at {span})")
