"""A small DC motor on a PWM H-bridge, as a microcontroller drives and samples it (open loop).

The linear DC motor twin (:mod:`twinwatch.twin.models.dcmotor`) takes an armature voltage. On a
hobby or evaluation board (the AutomationShield MotoShield: an Arduino Uno, an H-bridge and a
micro motor with an encoder of 14 edges per turn) no voltage is measured: the firmware turns a
command ``u`` into a PWM duty cycle, reads one sample of the current at some instant inside the PWM
period, filters it in software and counts encoder edges. This twin describes exactly that (its
held-out fit of the MotoShield recording against the linear twin's: README).

**Drive** (option ``duty``): the command ``u`` [V] held over (t_k, t_k+1] becomes the duty
``d_k`` of a PWM of frequency ``pwm_frequency`` (period T) from a supply ``supply_voltage``
(Vs): ``motoshield`` is the firmware's ``actuatorWriteVolt``: code = floor(u^2 * 255 /
u_max^2) written to an 8-bit fast PWM, which is high for code + 1 of ``pwm_counts`` counts,
d = (code + 1)/256, and constantly low for code 0 (Arduino's analogWrite); ``square`` is the
same map without quantisation, d = (u/u_max)^2; ``linear`` d = u/u_max (clipped to [0, 1]).

**Electrical, discontinuous conduction** (La/Ra = tau_e ~ 0.1 ms is far below the 20 ms
sample, so the current is quasi-static; the small motor's current falls to zero in each off
time, the terminal then floats at the back-EMF): in each on time the current rises from zero
towards (Vs - Ke*omega)/Ra with tau_e, so its average over the PWM period is::

    ibar = g(d) * (Vs - Ke*omega)/Ra,      g(d) = d - (tau_e/T) * (1 - exp(-d*T/tau_e))

(0 when the back-EMF exceeds the supply: the bridge cannot brake, the current never reverses).

**Mechanical**, with the friction falling as the motor warms up (option ``warmup``)::

    J domega/dt = Kt*ibar - s(t)*(Tc + D*omega) + J*f_omega,    omega >= 0
    s(t) = max(1 + c_warm*exp(-(t - t_w)/tau_warm) - r_warm*(t - t_w), s_min)

t is the absolute time of the recording (``window.t``), t_w the ``warmup_origin`` (the cold
start); ``exp`` drops r_warm, ``none`` sets s = 1. At rest the shaft stays at rest while the
drive torque does not beat Tc (stiction). With s taken at the middle of each sample (the
warm-up takes seconds) the ODE is affine in omega on each branch (current flowing or not) and is
solved exactly over each sub-step; the branch, and stiction, are decided at each sub-step
(``sub_step`` divides the sample period; it only places those switchings in time).
``f_omega`` [rad/s^2] is the meta-model term of discovery (attach point ``d(omega)/dt``).

**Speed output** (``speed_measurement``): ``average``: the encoder count over (t_k-1, t_k],
i.e. the mean speed over the sample period (its 2 pi/14/Ts quantisation stays noise);
``instant``: omega(t_k).

**Current output**: the firmware reads the current once per sample, at PWM phase
``phi_k = (adc_phase + adc_phase_step * k) mod 1`` (k = round(t_k/Ts), the sample's index
since t = 0; ``adc_phase_step`` defaults to frac(Ts * pwm_frequency), 17/32 on the MotoShield),
right after writing d_k. The raw sample is then::

    i_k = [phi_k < d_k] * ((Vs - Ke*omega(t_k))/Ra * (1 - exp(-phi_k*T/tau_e)) + Iq)
          * (1 + a_adc * [(d_k - phi_k)*T < t_a]) * (1 + U_k)

zero in the off time; ``U_k`` the multiplicative meta-model term (attach point ``ia``). It then
passes the known causal filter ``current_filter_b``/``current_filter_a`` (the firmware's
``ifltr``: a 2nd-order Chebyshev-I lowpass, identified exactly from the recording) and is
compared with the measured filtered current. With ``adc_phase`` unset the sample is the
period average ``ibar + Iq*d`` instead.

**Hypotheses** (fitted, not derived from the hardware): ``Iq`` [A], a current through the shunt
during the on time that makes no torque (the bridge's or the sense amplifier's own current);
``a_adc``, a sample that falls within ``adc_edge_window`` (t_a) before the off edge reading
(1 + a_adc) times the current (switching noise coupled into the sample-and-hold; t_a = 66 us
was profiled on the recording); the absolute current scale: the sense path's gain is not
documented, and a recorded current c times the true one fits exactly as well with Ra/c and
c*J, c*D, c*Tc, c*Iq, so those are as good as the assumption that the recording is in amperes
(Ke, tau_e, the warm-up and a_adc do not depend on it). The warm-up law is a description of the
recording (96 s from a cold start), not a thermal model: its linear part must not be
extrapolated far (s is floored at ``s_min``); a long-running monitor re-identifies, or uses
``warmup = "none"`` once the motor is warm.

**Initial state** of a window: the speed 0.5*(y_0 + y_1) (the means over the periods either
side of t_0) plus the estimator's offset (``initial_states = ("omega",)``); the current filter's
state is *measured*: the filter's first m outputs (m its order) are the measured filtered
current (it is the firmware's own, noise-free filter output), its inputs there the simulated
raw samples, so the recursion continues exactly from the measured state.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numba import njit

from twinwatch.twin.model import (
    AttachPoint,
    EstimationDefaults,
    FloatArray,
    OutputSpec,
    ParameterSpec,
    SubStepTwin,
    WindowData,
    term_array,
)

logger = logging.getLogger(__name__)

#: The firmware's filter of the MotoShield's current (``ifltr``), identified from the
#: recording (residual 4e-5 A on a 2.4e-3 A signal): 2nd-order Chebyshev-I lowpass, 1 dB ripple.
MOTOSHIELD_CURRENT_FILTER_B = (0.00359886469, 0.007197729379, 0.00359886469)
MOTOSHIELD_CURRENT_FILTER_A = (1.0, -1.855749963116, 0.871904802739)

PWM_DC_MOTOR_PARAMETERS: tuple[ParameterSpec, ...] = (
    ParameterSpec("Ra", "ohm", 30.0, "armature resistance (through the current's scale)",
                  "winding temperature, shorted turns (falls) or degraded brushes and "
                  "connections (rises)"),
    ParameterSpec("tau_e", "s", 1e-4, "electrical time constant La/Ra (the rise of the "
                  "current pulses)", "winding insulation or core faults (La), winding "
                  "temperature (Ra)"),
    ParameterSpec("Ke", "V s/rad", 0.005, "back-EMF constant",
                  "field weakening, magnet ageing, commutator faults"),
    ParameterSpec("Kt", "N m/A", 0.005, "torque constant", "field weakening, magnet ageing"),
    ParameterSpec("J", "kg m^2", 1e-7, "rotor and load moment of inertia",
                  "change of the coupled load or of the rotor"),
    ParameterSpec("D", "N m s/rad", 1e-7, "viscous friction coefficient (warm)",
                  "bearing wear, lubrication loss, misalignment"),
    ParameterSpec("Tc", "N m", 1e-5, "Coulomb (dry) friction torque (warm)",
                  "bearing or brush wear, contamination (rises)"),
    ParameterSpec("Iq", "A", 5e-3, "current through the shunt in the on time that makes no "
                  "torque (hypothesis)", "a change of the power stage or the current sensing"),
)
_A_ADC = ParameterSpec("a_adc", "1", 0.5, "relative excess of a current sample taken within "
                       "adc_edge_window before the PWM off edge (hypothesis)",
                       "a change of the switching noise or the sensing's layout")
_WARM = (
    ParameterSpec("c_warm", "1", 0.2, "friction excess of the cold motor over the warm one",
                  "lubricant or bearing condition"),
    ParameterSpec("tau_warm", "s", 10.0, "time constant of the friction's fast warm-up",
                  "lubricant or bearing condition"),
    ParameterSpec("r_warm", "1/s", 1e-3, "rate of the friction's slow fall while warming "
                  "(relative, per second)", "lubricant or bearing condition"),
)


@njit(cache=True, nogil=True)
def _affine_step(a: float, b: float, h: float) -> tuple[float, float]:  # pragma: no cover
    """exp(-b h) and (1 - exp(-b h))/b of domega/dt = a - b*omega over a step h."""
    if b * h > 1e-9:
        e = math.exp(-b * h)
        return e, (1.0 - e) / b
    return 1.0, h


@njit(cache=True, nogil=True)
def _dcm_share(dk: float, tpwm: float, tau_e: float) -> float:  # pragma: no cover
    """The share of a PWM period's supply voltage that drives the average current in
    discontinuous conduction: ``dk - tau_e/tpwm * (1 - exp(-dk*tpwm/tau_e))``, at least 0
    (duty ``dk``, PWM period ``tpwm`` [s], electrical time constant ``tau_e`` [s])."""
    g = 0.0
    if dk > 0.0:
        x = dk * tpwm / tau_e
        g = dk - tau_e / tpwm * (1.0 - math.exp(-x))
        if g < 0.0:
            g = 0.0
    return g


@njit(cache=True, nogil=True)
def _simulate_kernel(prm: FloatArray, duty: FloatArray, phase: FloatArray, t: FloatArray,
                     w0: FloatArray, f_w: FloatArray, u_i: FloatArray, fb: FloatArray,
                     fa: FloatArray, y_init: FloatArray, n_sub: int, ts: float, vs: float,
                     tpwm: float, t_edge: float, sampled: bool, mean_speed: bool,
                     warm_mode: int, t_warm: float, s_min: float, y: FloatArray) -> None:
    # pragma: no cover - compiled
    """Simulate every particle; fills ``y`` (P, N, 2) with ia (filtered sample) and omega.

    ``prm`` (P, 12): Ra, tau_e, Ke, Kt, J, D, Tc, Iq, a_adc, c_warm, tau_warm, r_warm.
    ``duty``, ``phase``, ``t`` (N,): duty of sample k (held over t_k..t_k+1), ADC phase, time.
    ``w0`` (P,) initial speeds. ``f_w`` (1|P, N) additive d(omega)/dt term held over step
    k -> k+1; ``u_i`` (1|P, N) multiplicative term on the raw current sample k. ``fb``, ``fa``
    (m+1,) the current filter (a[0] = 1; m = 0: none); ``y_init`` (m,) its measured first
    outputs. A particle whose state is not finite gets nan from there.
    """
    n_p, n_k = y.shape[0], y.shape[1]
    m = fa.shape[0] - 1
    shared_f = f_w.shape[0] == 1
    shared_u = u_i.shape[0] == 1
    h = ts / n_sub
    raw = np.empty(n_k)
    for q in range(n_p):
        ra, tau_e, ke, kt, jj = prm[q, 0], prm[q, 1], prm[q, 2], prm[q, 3], prm[q, 4]
        d_v, tc, iq, a_adc = prm[q, 5], prm[q, 6], prm[q, 7], prm[q, 8]
        c_w, tau_w, r_w = prm[q, 9], prm[q, 10], prm[q, 11]
        qf = 0 if shared_f else q
        qu = 0 if shared_u else q
        ok = ra > 0.0 and tau_e > 0.0 and jj > 0.0 and math.isfinite(w0[q])
        om = w0[q] if w0[q] > 0.0 else 0.0
        for k in range(n_k):
            if not ok:
                raw[k] = np.nan
                y[q, k, 1] = np.nan
                continue
            dk = duty[k]
            # the raw current sample at t_k (the new duty is written before the ADC reads)
            if sampled:
                ph = phase[k]
                if ph < dk:
                    emf = vs - ke * om
                    if emf < 0.0:
                        emf = 0.0
                    ik = emf / ra * (1.0 - math.exp(-ph * tpwm / tau_e)) + iq
                    if (dk - ph) * tpwm < t_edge:
                        ik *= 1.0 + a_adc
                else:
                    ik = 0.0
            else:
                g = _dcm_share(dk, tpwm, tau_e)
                ik = g * (vs - ke * om) / ra
                if ik < 0.0:
                    ik = 0.0
                ik += iq * dk
            raw[k] = ik * (1.0 + u_i[qu, k])
            if k == 0:
                y[q, 0, 1] = om
            if k == n_k - 1:
                break
            # the speed over (t_k, t_k+1]: DCM average current, friction with warm-up
            g = _dcm_share(dk, tpwm, tau_e)
            ia0 = g * vs / ra
            ia1 = g * ke / ra
            fw = f_w[qf, k]
            # the friction factor at the middle of the sample (the warm-up takes seconds)
            sc = 1.0
            if warm_mode > 0:
                tt = t[k] + 0.5 * ts - t_warm
                if tt < 0.0:
                    tt = 0.0
                sc = 1.0 + c_w * math.exp(-tt / tau_w)
                if warm_mode == 2:
                    sc -= r_w * tt
                if sc < s_min:
                    sc = s_min
            # domega/dt = a - b*omega on each branch: current flowing (the back-EMF below the
            # supply) or not; the sub-step map of each, exact, computed once per sample
            a_on = (kt * ia0 - sc * tc) / jj + fw
            b_on = (kt * ia1 + sc * d_v) / jj
            a_off = -sc * tc / jj + fw
            b_off = sc * d_v / jj
            e_on, c_on = _affine_step(a_on, b_on, h)
            e_off, c_off = _affine_step(a_off, b_off, h)
            acc = 0.0
            for _s in range(n_sub):
                if ia0 - ia1 * om > 0.0:
                    a, b, e, c = a_on, b_on, e_on, c_on
                else:
                    a, b, e, c = a_off, b_off, e_off, c_off
                if om <= 0.0 and a <= 0.0:
                    om_new = 0.0  # stiction: the drive does not beat the dry friction
                    integ = 0.0
                elif b * h > 1e-9:
                    oinf = a / b
                    om_new = oinf + (om - oinf) * e
                    integ = oinf * h + (om - oinf) * c
                else:
                    om_new = om + a * h
                    integ = om * h + 0.5 * a * h * h
                if om_new < 0.0:
                    om_new = 0.0
                    if integ < 0.0:
                        integ = 0.0
                om = om_new
                acc += integ
            if not math.isfinite(om):
                ok = False
                y[q, k + 1, 1] = np.nan
                continue
            y[q, k + 1, 1] = acc / ts if mean_speed else om
        # the current filter, continued from its measured first outputs
        for k in range(n_k):
            if k < m:
                y[q, k, 0] = y_init[k]
                continue
            acc = 0.0
            for i in range(m + 1):
                acc += fb[i] * raw[k - i]
            for i in range(1, m + 1):
                acc -= fa[i] * y[q, k - i, 0]
            y[q, k, 0] = acc if math.isfinite(acc) else np.nan


@dataclass
class PWMDCMotorTwin(SubStepTwin):
    """DC motor on a PWM H-bridge in discontinuous conduction, sampled as a microcontroller
    samples it; see the module docstring for the equations.

    Input ``u`` [V] (the command the firmware turns into a duty). Outputs ``ia`` [A] (the
    current sample after the known filter) and ``omega`` [rad/s].

    Args:
        pwm_frequency: PWM frequency [Hz] (Arduino Uno timer 0: 16 MHz/64/256 = 976.5625).
        supply_voltage: the bridge's supply Vs [V].
        duty: the command -> duty map: ``motoshield`` (the firmware's), ``square``, ``linear``.
        input_full_scale: the command u_max [V] that gives full duty.
        pwm_counts: counts of one PWM period (``motoshield``: 256, 8 bits).
        adc_phase: PWM phase (fraction of a period) of the current sample at t = 0; None: the
            twin outputs the period-average current instead of a sample.
        adc_phase_step: phase advance per sample [periods]; None: frac(Ts * pwm_frequency).
        adc_edge_window: t_a [s]: samples within this time before the off edge carry the ADC
            artefact (adds the parameter ``a_adc``); 0: none.
        current_filter_b, current_filter_a: the known causal filter of the current sample
            (``scipy.signal.lfilter`` convention, a[0] = 1); None: the raw sample is compared.
        speed_measurement: ``average`` (encoder count over the sample period) or ``instant``.
        warmup: friction warm-up law: ``none``, ``exp`` (c_warm, tau_warm) or ``exp_linear``
            (also r_warm).
        warmup_origin: t_w [s], the time of the cold start.
        warmup_floor: s_min, the smallest friction factor the law may give.
        sub_step: integration sub-step [s]; the sample period must be a whole multiple of it.
        current_scale, speed_scale: residual normalisation floors [A, rad/s].
        omega_dot_scale: largest plausible d(omega)/dt term [rad/s^2] (discovery's bound).

    Raises:
        ValueError: an option that cannot work (named).
    """

    pwm_frequency: float = 976.5625
    supply_voltage: float = 5.0
    duty: Literal["motoshield", "square", "linear"] = "linear"
    input_full_scale: float = 5.0
    pwm_counts: int = 256
    adc_phase: float | None = None
    adc_phase_step: float | None = None
    adc_edge_window: float = 0.0
    current_filter_b: Sequence[float] | None = None
    current_filter_a: Sequence[float] | None = None
    speed_measurement: Literal["average", "instant"] = "average"
    warmup: Literal["none", "exp", "exp_linear"] = "none"
    warmup_origin: float = 0.0
    warmup_floor: float = 0.05
    sub_step: float = 2e-3
    current_scale: float = 1e-3
    speed_scale: float = 10.0
    omega_dot_scale: float = 1e4
    _fb: FloatArray = field(init=False, repr=False, default_factory=lambda: np.ones(1))
    _fa: FloatArray = field(init=False, repr=False, default_factory=lambda: np.ones(1))
    #: the last window's command and time arrays (by identity) and their duty and ADC phase
    #: (N,): a window is simulated tens of times, its inputs are the same each time
    _inputs: tuple[FloatArray, FloatArray, FloatArray, FloatArray] | None = field(
        init=False, repr=False, compare=False, default=None)

    def __post_init__(self) -> None:
        """Check the options (:meth:`_check_options`, :meth:`_check_acquisition`), normalise
        the current filter (:meth:`_set_current_filter`) and lay out the parameters, inputs,
        outputs and attach points the options give.

        Raises:
            ValueError: an option out of its range, naming it.
        """
        self._check_options()
        self._check_acquisition()
        self._set_current_filter()
        extra = [_A_ADC] if self.adc_edge_window > 0 else []
        extra += {"none": [], "exp": list(_WARM[:2]), "exp_linear": list(_WARM)}[self.warmup]
        self.parameters = (*PWM_DC_MOTOR_PARAMETERS, *extra)
        self.inputs = ("u",)
        self.outputs = (OutputSpec("ia", "A", self.current_scale),
                        OutputSpec("omega", "rad/s", self.speed_scale))
        self.exogenous = ("u",)
        self.initial_states = ("omega",)
        self.attach_points = (
            AttachPoint("d(omega)/dt", "additive", "rad/s^2", "shaft speed",
                        scale=self.omega_dot_scale),
            AttachPoint("ia", "multiplicative", "1", "current measurement"),
        )

    def _check_options(self) -> None:
        """The named options among their choices, the scales and rates positive numbers,
        ``pwm_counts`` an integer >= 2 (ValueError otherwise)."""
        self._check_choices()
        for key in ("pwm_frequency", "supply_voltage", "input_full_scale", "sub_step",
                    "current_scale", "speed_scale", "omega_dot_scale"):
            v = getattr(self, key)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{key} must be a number > 0, not {v!r}")
        if not (isinstance(self.pwm_counts, int) and self.pwm_counts >= 2):
            raise ValueError(f"pwm_counts must be an integer >= 2, not {self.pwm_counts!r}")

    def _check_acquisition(self) -> None:
        """The current's sampling (``adc_edge_window`` >= 0 [s] and only with a sampled
        current, ``adc_phase`` in [0, 1), a finite ``adc_phase_step``), ``warmup_floor`` in
        (0, 1], both filter coefficient lists or neither (ValueError otherwise)."""
        if not (self.adc_edge_window >= 0 and math.isfinite(self.adc_edge_window)):
            raise ValueError("adc_edge_window must be >= 0 [s]")
        if self.adc_edge_window > 0 and self.adc_phase is None:
            raise ValueError("adc_edge_window: the ADC artefact needs a sampled current "
                             "(set adc_phase)")
        if self.adc_phase is not None and not (0.0 <= self.adc_phase < 1.0):
            raise ValueError(f"adc_phase must be a fraction of a PWM period in [0, 1), not "
                             f"{self.adc_phase!r}")
        if self.adc_phase_step is not None and not math.isfinite(self.adc_phase_step):
            raise ValueError("adc_phase_step must be a finite number [PWM periods]")
        if not 0.0 < self.warmup_floor <= 1.0:
            raise ValueError("warmup_floor must be in (0, 1]")
        if (self.current_filter_b is None) != (self.current_filter_a is None):
            raise ValueError("current_filter_b and current_filter_a go together")

    def _set_current_filter(self) -> None:
        """The current filter's coefficients, checked (finite, ``a[0] != 0``, stable) and
        normalised to ``a[0] = 1``, both padded to one length (``_fb``, ``_fa``); none: the
        identity (ValueError when they do not make a stable filter)."""
        if self.current_filter_b is None or self.current_filter_a is None:
            return
        b = np.asarray(self.current_filter_b, dtype=float)
        a = np.asarray(self.current_filter_a, dtype=float)
        if b.ndim != 1 or a.ndim != 1 or a.size < 1 or b.size < 1 or \
                not np.all(np.isfinite(a)) or not np.all(np.isfinite(b)) or a[0] == 0:
            raise ValueError("current_filter_b, current_filter_a: finite coefficient "
                             "lists with a[0] != 0")
        if np.any(np.abs(np.roots(a)) >= 1.0) if a.size > 1 else False:
            raise ValueError("current_filter_a: the filter is unstable (a pole on or "
                             "outside the unit circle)")
        m = max(a.size, b.size)
        self._fb = np.zeros(m)
        self._fa = np.zeros(m)
        self._fb[:b.size] = b / a[0]
        self._fa[:a.size] = a / a[0]

    @property
    def estimation_defaults(self) -> EstimationDefaults:
        """Ke, then D and J (the speed's gain, time constant and load), then Ra (the current's
        scale), Kt tied to Ke; the hypotheses, La and the warm-up stay as identified: a 4 s
        window does not determine them (they are for ``twinwatch identify``)."""
        return EstimationDefaults(("Ke", "D", "J", "Ra"), {"Kt": "Ke"})

    # -- the acquisition ---------------------------------------------------------------------
    def duty_cycle(self, u: FloatArray) -> FloatArray:
        """The PWM duty [0..1] the firmware makes of commands ``u`` [V] (N,) (``duty``)."""
        x = np.clip(np.nan_to_num(np.asarray(u, dtype=float) / self.input_full_scale), 0, 1)
        if self.duty == "linear":
            return x
        if self.duty == "square":
            return x * x
        top = self.pwm_counts - 1
        code = np.floor(x * x * top + 1e-9)
        return np.where(code > 0, (code + 1.0) / self.pwm_counts, 0.0)

    def sample_phase(self, t: FloatArray, sample_period: float) -> FloatArray:
        """PWM phase [0, 1) of the current sample at times ``t`` [s] (N,)."""
        # rounded: Ts*f is exact in the firmware's clock (17/32 on the MotoShield), and a sample
        # that falls exactly on the PWM edge must not flip on a rounding error
        step = (self.adc_phase_step if self.adc_phase_step is not None
                else round(math.fmod(sample_period * self.pwm_frequency, 1.0), 9))
        k = np.round(np.asarray(t, dtype=float) / sample_period)
        return np.mod((self.adc_phase or 0.0) + step * k, 1.0)

    def _prm(self, theta: FloatArray) -> FloatArray:
        """(P, 12) kernel parameters from full vectors (P, n_params); absent ones 0 / 1."""
        names = self.parameter_names
        prm = np.zeros((theta.shape[0], 12))
        prm[:, :8] = theta[:, :8]
        prm[:, 10] = 1.0
        for col, name in ((8, "a_adc"), (9, "c_warm"), (10, "tau_warm"), (11, "r_warm")):
            if name in names:
                prm[:, col] = theta[:, names.index(name)]
        return prm

    # -- simulation --------------------------------------------------------------------------
    def simulate(self, theta: FloatArray, window: WindowData,
                 terms: Mapping[str, FloatArray] | None = None,
                 initial: FloatArray | None = None) -> FloatArray:
        """Simulate the window for a swarm; see :meth:`TwinModel.simulate`.

        Args:
            theta: (P, n_params) parameters in :attr:`parameters` order (SI units).
            window: needs ``u``, ``ia`` and ``omega`` (N samples); ``window.t`` is absolute
                time [s] (the PWM phase and the warm-up read it).
            terms: ``d(omega)/dt`` [rad/s^2] (added over step k -> k+1) and/or ``ia``
                (dimensionless; the raw current sample k is multiplied by ``1 + U[k]``);
                values (N,) or (P, N).
            initial: offsets [rad/s] (1,) or (P, 1) added to the initial speed estimate
                0.5*(omega_0 + omega_1) (average speed) or omega_0 (instant); None: 0.

        Returns:
            (P, N, 2): ia [A] (the filtered current sample), omega [rad/s]. The first m
            current samples (m the filter's order) are the measured ones (the filter's
            state); the first speed sample is the measured one. A particle that blows up
            gives nan from there; nothing raises.

        Raises:
            KeyError: an unknown attach point in ``terms``.
            ValueError: theta of the wrong width, a sample period that is not whole
                sub-steps, a term of the wrong shape.
        """
        theta = np.ascontiguousarray(np.atleast_2d(np.asarray(theta, dtype=float)))
        if theta.ndim != 2 or theta.shape[1] != len(self.parameters):
            raise ValueError(f"theta must have shape (P, {len(self.parameters)}), "
                             f"got {theta.shape}")
        ts = window.sample_period
        n_sub = self.n_sub(ts)
        n = window.n
        terms = terms or {}
        unknown = set(terms) - {a.name for a in self.attach_points}
        if unknown:
            raise KeyError(f"unknown attach point(s) {sorted(unknown)}; the PWM DC motor twin "
                           f"offers {[a.name for a in self.attach_points]}")
        f_w = term_array(terms.get("d(omega)/dt"), theta.shape[0], n, "d(omega)/dt")
        u_i = term_array(terms.get("ia"), theta.shape[0], n, "ia")
        rows = max(theta.shape[0], f_w.shape[0], u_i.shape[0])
        if initial is not None and np.ndim(initial) == 2:
            rows = max(rows, np.shape(initial)[0])
        if rows > theta.shape[0]:
            theta = np.repeat(theta[:1], rows, axis=0)
        off = np.zeros(rows) if initial is None else np.broadcast_to(
            np.atleast_2d(np.asarray(initial, dtype=float)), (rows, 1))[:, 0]
        omega = np.asarray(window["omega"], dtype=float)
        w0 = omega[0] if self.speed_measurement == "instant" or n < 2 \
            else 0.5 * (omega[0] + omega[1])
        t = np.ascontiguousarray(window.t, dtype=float)
        sampled = self.adc_phase is not None
        u = window["u"]
        last = self._inputs
        if last is not None and last[0] is u and last[1] is window.t:
            duty, phase = last[2], last[3]
        else:
            duty = np.ascontiguousarray(self.duty_cycle(u))
            phase = np.ascontiguousarray(self.sample_phase(t, ts) if sampled else np.zeros(n))
            self._inputs = (u, window.t, duty, phase)
        m = self._fa.size - 1
        y_init = np.ascontiguousarray(np.asarray(window["ia"], dtype=float)[:min(m, n)])
        if y_init.size < m:
            y_init = np.concatenate([y_init, np.zeros(m - y_init.size)])
        y = np.empty((rows, n, 2))
        with np.errstate(all="ignore"):
            _simulate_kernel(self._prm(theta), duty, phase, t,
                             np.ascontiguousarray(w0 + off, dtype=float), f_w, u_i,
                             self._fb, self._fa, y_init, n_sub, ts, self.supply_voltage,
                             1.0 / self.pwm_frequency, self.adc_edge_window, sampled,
                             self.speed_measurement == "average",
                             {"none": 0, "exp": 1, "exp_linear": 2}[self.warmup],
                             self.warmup_origin, self.warmup_floor, y)
        if n:
            y[:, 0, 1] = np.where(np.isfinite(y[:, 0, 1]), omega[0], np.nan)
        return y


__all__ = ["MOTOSHIELD_CURRENT_FILTER_A", "MOTOSHIELD_CURRENT_FILTER_B",
           "PWM_DC_MOTOR_PARAMETERS", "PWMDCMotorTwin"]
