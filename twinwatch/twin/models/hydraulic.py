"""The hydraulic actuator twin (paper Section 4.2 and 5.3, Eq. 6-10 and 14-18).

A constant-displacement pump feeds a piston cylinder; a controlled valve of cross-section
A_valve returns fluid to the reservoir; the load F_load sits on the piston. With Ts the
sub-step (the paper's integration step, 1e-4 s), one sub-step j -> j+1 reads::

    v_{j+1} = (q_pump - A_valve*sqrt(2*p_j)) / A_piston + f_x            (Eq. 7-8)
    x_{j+1} = x_j + Ts*v_{j+1}                                           (Eq. 14-15)
    p_{j+1} = (1 + U) * (F_load + k_spring*x_{j+1} + D*v_{j+1} + F_resist) / A_piston
                                                                         (Eq. 16, 18)

(density is left out of the valve flow, as in the paper; see NOTES.md). ``U`` and ``f_x`` are
the meta-model terms of discovery (paper Eq. 3), zero for the plain DT. ``U`` = C reproduces the
internal leak of Eq. 18 (the paper's discovery prints ``p_k = p'_k - 0.19999991*p'_k``, Eq. 20:
the same term with the sign of its own convention; ours is ``p = (1 + U)*p'``, U ~ +0.2).

The model is nonlinear (sqrt) and has no exact sample map, so one compiled kernel runs the
sub-steps for every particle of the swarm and every sample of the window.

**Structure: open loop** (the default). The measured valve area and load drive the twin; it
starts each window from the measured x and p of the window's first sample. The plant's Eq. 17
PID runs every 1e-4 s (with these gains it is unstable from a 0.2 ms period on; see
:mod:`twinwatch.plant.hydraulic`), so the area moves within a sample. Option ``input_hold``:

* ``linear`` (default): the area (and load) is interpolated linearly between consecutive samples
  over the sub-steps (first-order hold); against the plant at its true parameters its error
  stays far below D's share of the pressure (1.4e-4), fluid degradation included.
* ``zoh``: each sample's value is held until the next one: exact for a valve whose command is
  really held between samples.

The measured area is clipped to [0, A_max] (the valve cannot open further), so A_max matters
only when a reading exceeds it: a window never determines A_max.

An open loop on the sampled area is biased wherever the area moved within a sample in a way
the hold does not describe (a valve controller that holds its output between updates: a
staircase). With a well-tuned drive this stays below D's share of the pressure, so D is still
estimated; but the twin does not reproduce the machine, and a window where the valve leaves
its limit fails the model check.

**Structure: closed loop** (``structure = "closed_loop"``, option ``drive``,
:class:`ValveDriveConfig`). The twin contains the valve controller as the drive runs it
(:mod:`twinwatch.io.drive`: an update every ``period`` from x and the reference, the area
held in between, clamped to the loop's limits, by default the valve's own [0, A_max], with
clamping or back-calculation anti-windup; no table: the paper's PID every sub-step). It is
driven by the measured reference ``x_ref`` (interpolated to the updates between samples by
``reference_hold``: a cubic through the four nearest samples by default, exact at the
samples) and the load, and the area becomes an output compared with the measurement. Each
window starts from the measured x (with the estimator's offset) and p, and the controller's
state is recovered from the data:

* the integrator, exactly, from the measured area of the first sample (``I = A - kp*e -
  d - kff*r``, the update on the sample reproducing the measured area);
* where the measured area sits at a limit the integrator is hidden: the measured area drives
  the piston (its residual is zero there) while the controller keeps running on the twin's
  position, and at the first sample inside the limits the twin restarts from the measured x
  and p with the integrator recovered there (the window is cut, as the DC twin does);
* the derivative filter's state is not measured. Where the stretch inside the limits is at
  least 3 samples long, it is set so that the closed loop's area over the next
  :data:`SPLIT_SAMPLES` samples matches the measured one (secant steps until the area is
  affine in it to rounding): exact when the twin's parameters are the machine's, and the
  window's only fitted controller state. In a shorter stretch it keeps the value the
  controller ran to (at the first sample: at rest, d = 0).

Against the plant with its controller's own period this reproduces every window to rounding.
Approximate: a controller whose updates do not fall on the samples
(``phase``: the update before a window's first sample is taken to have seen that sample's
error), a stretch inside the limits shorter than 3 samples (a valve that slams between its
limits), and noise on the area or the position at a restart (the integrator takes it). A swarm
costs about 20 % more than the open loop (the secant runs of the derivative filter's state).

**Meta-model terms** (attach points, :attr:`HydraulicActuatorTwin.attach_points`):

* ``p`` (multiplicative, dimensionless): ``U[k]`` multiplies the pressure equation on every
  sub-step of the step k-1 -> k, so the pressure at sample k is ``(1 + U[k])`` times the
  plain equation's value, and the next step's valve flow sees that pressure, exactly as in the
  plant's leak (Eq. 18). ``U[0]`` is unused: the window starts from the measured pressure.
* ``d(x)/dt`` (additive, m/s): ``f_x[k]`` is added to the piston velocity on every sub-step of
  the step k -> k+1 (value k drives step k -> k+1, as for the DC motor); it is a velocity of
  the piston, so it enters the damping force D*v as well. ``f_x[N-1]`` is unused.

**Sensitivity caveat.** The damping force D*v is at most ~1.4 N at nominal D (|v| <= 0.014
m/s), about 7 Pa of the 50 kPa pressure (a 1.4e-4 share). D is seen only through the pressure,
only in clean data, and not at all when the piston reverses (v ~ 0): the estimator holds it
there. The position fixes q_pump/A_piston and 1/A_piston; the pressure fixes
(F_load + F_resist)/A_piston, k_spring/A_piston and D/A_piston. Within one 2 s window, though,
x is nearly linear and v nearly constant, so D*v trades with the pressure level: q_pump and D
together are determined, D with k_spring, A_piston or F_resist is not, and A_max never (the
valve does not saturate). Estimate q_pump and D; keep the others at nameplate. The closed loop
compares the area too: D enters it through the controller's response to the pressure.

Paper numbers (Table 4, Eq. 17): k_spring 200 N/m, D 100 N/(m/s), q_pump 0.02 m^3/s, A_max 1e-4
m^2, A_piston 0.196349375 m^2, load 1000 kg; PID Kp 0.000346, Ki 3.513406, Kd 0.000119, N
2.076743; reference 0.45 m at 0.005 Hz; fluid degradation D error below 3 %; leak C = 0.2.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numba import njit
from pydantic import (
    ValidationError,
)

from twinwatch.io.drive import ValveDriveConfig
from twinwatch.twin.model import (
    AttachPoint,
    EstimationDefaults,
    FloatArray,
    IntArray,
    OutputSpec,
    ParameterSpec,
    SubStepTwin,
    WindowData,
    term_array,
)
from twinwatch.twin.models._pid import pid_update

logger = logging.getLogger(__name__)

HYDRAULIC_PARAMETERS: tuple[ParameterSpec, ...] = (
    ParameterSpec("k_spring", "N/m", 200.0, "elastic constant of the system",
                  "change of the mounting's or the load's compliance"),
    ParameterSpec("D", "N/(m/s)", 100.0, "viscous damping coefficient",
                  "hydraulic fluid degradation (viscosity change: ageing, contamination, "
                  "temperature), seal friction"),
    ParameterSpec("q_pump", "m^3/s", 0.02, "flow of the constant-displacement pump",
                  "pump wear or an external leak on the supply side (falls)"),
    ParameterSpec("A_max", "m^2", 1e-4, "largest cross-section of the valve",
                  "valve clogging or erosion (only seen when the valve saturates)"),
    ParameterSpec("A_piston", "m^2", 0.196349375, "piston area",
                  "effective area change: seal damage, internal bypass"),
    ParameterSpec("F_resist", "N", 0.0, "internal resistance force (not defined by the paper)",
                  "seal or guide friction, mechanical binding"),
)

_ATTACH = ("p", "d(x)/dt")

#: A measured area within this fraction of the limits' span of a limit sits at it.
LIMIT_TOLERANCE = 1e-9

#: Samples over which the closed loop's area sets the derivative filter's state at a restart,
#: and the secant steps at most.
SPLIT_SAMPLES = 20
SPLIT_ITERATIONS = 3

@njit(cache=True, nogil=True, inline="always")
def _piston_step(x: float, p: float, a: float, fl: float, gain: float, fx: float, ks: float,
                 d: float, qp: float, a_max: float, inv_ap: float, fr: float,
                 dt: float) -> tuple[float, float]:
    # pragma: no cover - compiled
    """One sub-step of the piston, paper Eq. 14-16: the valve area ``a`` [m^2] clipped to
    [0, a_max], the valve flow from the previous pressure, the piston speed (plus the additive
    term ``fx`` [m/s]), the position by explicit Euler over ``dt`` [s], the pressure from the
    force balance (times the multiplicative term ``gain``). Returns (x [m], p [Pa]); a negative
    pressure (cavitation, outside the model) gives nan."""
    if a < 0.0:
        a = 0.0
    elif a > a_max:
        a = a_max
    if p >= 0.0:
        q_valve = a * math.sqrt(2.0 * p)
    else:
        q_valve = np.nan  # cavitation: outside the model
    v = (qp - q_valve) * inv_ap + fx
    x = x + dt * v
    return x, gain * (fl + ks * x + d * v + fr) * inv_ap


@njit(cache=True, nogil=True)
def _simulate_kernel(theta: FloatArray, a_in: FloatArray, f_in: FloatArray, x0: FloatArray,
                     p0: FloatArray, n_sub: int, dt: float, linear: bool, u_p: FloatArray,
                     f_x: FloatArray, y: FloatArray) -> None:
    # pragma: no cover - compiled
    """Sub-step Eq. 14-16 for every particle; fills ``y`` (P, N, 2) with x and p.

    ``theta`` (P, 6): k_spring, D, q_pump, A_max, A_piston, F_resist. ``a_in``, ``f_in`` (N,)
    measured area and load. ``x0``, ``p0`` (P,): each particle's initial state. ``u_p`` (1 or
    P, N): multiplicative pressure term, ``U[k]`` on the sub-steps of step k-1 -> k. ``f_x``
    (1 or P, N): additive velocity term, ``f_x[k]`` on the sub-steps of step k -> k+1. A
    particle whose state stops being finite gets nan from there (nan stays nan through
    :func:`_piston_step`).

    The particles advance side by side, sub-step by sub-step: each one's arithmetic is its
    own, in its own order (the same numbers as one particle at a time), while the processor
    overlaps the particles' independent chains of square roots and products.
    """
    n_p, n_k = y.shape[0], y.shape[1]
    shared_u = u_p.shape[0] == 1
    shared_f = f_x.shape[0] == 1
    inv = 1.0 / n_sub
    x = np.empty(n_p)
    p = np.empty(n_p)
    inv_ap = np.empty(n_p)
    gain = np.empty(n_p)
    fx = np.empty(n_p)
    for q in range(n_p):
        x[q], p[q] = x0[q], p0[q]
        y[q, 0, 0] = x[q]
        y[q, 0, 1] = p[q]
        inv_ap[q] = 1.0 / theta[q, 4]
    for k in range(n_k - 1):
        a0, a1 = a_in[k], a_in[k + 1]
        l0, l1 = f_in[k], f_in[k + 1]
        for q in range(n_p):
            gain[q] = 1.0 + u_p[0 if shared_u else q, k + 1]
            fx[q] = f_x[0 if shared_f else q, k]
        for s in range(n_sub):
            if linear:
                w = s * inv
                a = a0 + (a1 - a0) * w
                fl = l0 + (l1 - l0) * w
            else:
                a = a0
                fl = l0
            for q in range(n_p):
                x[q], p[q] = _piston_step(x[q], p[q], a, fl, gain[q], fx[q], theta[q, 0],
                                          theta[q, 1], theta[q, 2], theta[q, 3], inv_ap[q],
                                          theta[q, 5], dt)
        for q in range(n_p):
            if not (math.isfinite(x[q]) and math.isfinite(p[q])):
                x[q], p[q] = np.nan, np.nan
            y[q, k + 1, 0] = x[q]
            y[q, k + 1, 1] = p[q]


@njit(cache=True, nogil=True)
def _recover_integrator(loop: FloatArray, f_s: float, r: float, y: float, area: float,
                        period: float, ticked: bool) -> float:  # pragma: no cover
    """The integrator (before the update when ``ticked``) that makes an update on (r, y) with
    the derivative filter state ``f_s`` give ``area``; without an update on the sample, the
    integrator after an update taken to have seen this error."""
    kp, ki, kd, nf, kff, sgn = loop[0], loop[1], loop[2], loop[3], loop[8], loop[9]
    ci, cd = loop[10], loop[11]
    e = sgn * (r - y)
    d = nf * (kd * e - f_s) / (1.0 + cd * nf * period) if kd != 0.0 else 0.0
    i_s: float = area - kp * e - d - kff * r - ci * ki * period * e
    if not ticked:
        i_s += ki * period * e
    return i_s


@njit(cache=True, nogil=True)
def _interval(x: float, p: float, i_s: float, f_s: float, area: float, limited: bool, j: int,
              t_off: int, m: int, r_t: FloatArray, loop: FloatArray, period: float, hi: float,
              n_sub: int, linear: bool, l0: float, l1: float, gain: float, fx: float,
              prm: FloatArray, dt: float
              ) -> tuple[float, float, float, float, float]:  # pragma: no cover - compiled
    """Sub-steps of one sample from the sub-step ``j`` (the update on the sample itself is
    the caller's): the controller updates when due (its output applied unless ``limited``),
    the piston Eq. 14-16. ``prm`` = (k_spring, D, q_pump, A_max, 1/A_piston, F_resist).
    Returns (x, p, I, f, area)."""
    ks, d, qp, a_max, inv_ap, fr = prm[0], prm[1], prm[2], prm[3], prm[4], prm[5]
    inv = 1.0 / n_sub
    for s in range(n_sub):
        js = j + s
        if s > 0 and js >= t_off and (js - t_off) % m == 0:
            u, i_s, f_s = pid_update(loop, i_s, f_s, r_t[(js - t_off) // m], x, period, hi)
            if not limited:
                area = u
        fl = l0 + (l1 - l0) * (s * inv) if linear else l0
        x, p = _piston_step(x, p, area, fl, gain, fx, ks, d, qp, a_max, inv_ap, fr, dt)
    return x, p, i_s, f_s, area


@njit(cache=True, nogil=True)
def _ahead(x: float, p: float, i_s: float, f_s: float, area: float, k: int, count: int,
           t_off: int, m: int, r_t: FloatArray, loop: FloatArray, period: float, hi: float,
           n_sub: int, linear: bool, f_in: FloatArray, u_p: FloatArray, f_x: FloatArray,
           prm: FloatArray, dt: float, out: FloatArray) -> None:  # pragma: no cover - compiled
    """The closed loop from sample ``k`` (controller recovered, before the update on the
    sample) over ``count`` samples; ``out[i]``: the area at sample k + 1 + i."""
    j = k * n_sub
    if j >= t_off and (j - t_off) % m == 0:
        area, i_s, f_s = pid_update(loop, i_s, f_s, r_t[(j - t_off) // m], x, period, hi)
    for i in range(count):
        kk = k + i
        x, p, i_s, f_s, area = _interval(x, p, i_s, f_s, area, False, kk * n_sub, t_off, m,
                                         r_t, loop, period, hi, n_sub, linear, f_in[kk],
                                         f_in[kk + 1], 1.0 + u_p[kk + 1], f_x[kk], prm, dt)
        jn = (kk + 1) * n_sub
        if jn >= t_off and (jn - t_off) % m == 0:
            area, i_s, f_s = pid_update(loop, i_s, f_s, r_t[(jn - t_off) // m], x, period, hi)
        out[i] = area


@njit(cache=True, nogil=True)
def _closed_kernel(theta: FloatArray, a_in: FloatArray, x_in: FloatArray, p_in: FloatArray,
                   f_in: FloatArray, r_s: FloatArray, r_t: FloatArray, t_off: int, m: int,
                   stretch: IntArray, x0: FloatArray, n_sub: int, dt: float, linear: bool,
                   loop: FloatArray, hi_is_amax: bool, tol: float, n_ahead: int,
                   u_p: FloatArray, f_x: FloatArray,
                   y: FloatArray) -> None:  # pragma: no cover - compiled
    """The closed loop (valve controller inside the twin) for every particle; fills ``y``
    (P, N, 3) with x, p and the valve area.

    ``a_in``, ``x_in``, ``p_in``, ``f_in``, ``r_s`` (N,): measured area, position, pressure,
    load and reference. ``r_t``: the reference at the controller's updates, which fall on the
    sub-steps ``t_off + n*m`` (relative to the window's first sample). ``stretch`` (N,): the
    first sample at a limit after each sample (N if none). ``x0`` (P,): each particle's
    initial position. ``loop``: the packed controller; its upper limit is
    the particle's A_max when ``hi_is_amax``. ``tol`` [m^2]: a measured area within it of a
    limit sits at the limit.

    The limits, restarts and the derivative filter's state over the next ``n_ahead`` samples
    (at most :data:`SPLIT_ITERATIONS` secant steps) as the module docstring's closed loop
    says. Terms as in :func:`_simulate_kernel`.
    """
    n_p, n_k = y.shape[0], y.shape[1]
    shared_u = u_p.shape[0] == 1
    shared_f = f_x.shape[0] == 1
    period = m * dt
    lo, kd, nf, sgn = loop[4], loop[2], loop[3], loop[9]
    prm = np.empty(6)
    out0 = np.empty(max(n_ahead, 1))
    out1 = np.empty(max(n_ahead, 1))
    for q in range(n_p):
        prm[0], prm[1], prm[2], prm[3] = theta[q, 0], theta[q, 1], theta[q, 2], theta[q, 3]
        prm[4], prm[5] = 1.0 / theta[q, 4], theta[q, 5]
        hi = theta[q, 3] if hi_is_amax else loop[5]
        u_q = u_p[0] if shared_u else u_p[q]
        f_q = f_x[0] if shared_f else f_x[q]
        x, p = x0[q], p_in[0]
        f_s = kd * sgn * (r_s[0] - x)  # the derivative filter at rest (d = 0) to begin with
        i_s = 0.0
        area = a_in[0]
        limited = True  # at the first sample the controller is recovered if inside
        ok = True
        for k in range(n_k):
            j = k * n_sub
            ticked = j >= t_off and (j - t_off) % m == 0
            meas = a_in[k]
            at_limit = meas <= lo + tol or meas >= hi - tol
            if ok and limited and not at_limit:
                if k > 0:  # restart from the measured state
                    x, p = x_in[k], p_in[k]
                r = r_t[(j - t_off) // m] if ticked else r_s[k]
                i_s = _recover_integrator(loop, f_s, r, x, meas, period, ticked)
                count = min(n_ahead, stretch[k] - 1 - k)
                if kd != 0.0 and nf > 0.0 and count >= 2:
                    # the split between the integrator and the derivative term
                    eps = 1e-6 * (hi - lo) / nf
                    for _ in range(SPLIT_ITERATIONS):
                        _ahead(x, p, i_s, f_s, meas, k, count, t_off, m, r_t, loop, period, hi,
                               n_sub, linear, f_in, u_q, f_q, prm, dt, out0)
                        i_e = _recover_integrator(loop, f_s + eps, r, x, meas, period, ticked)
                        _ahead(x, p, i_e, f_s + eps, meas, k, count, t_off, m, r_t, loop,
                               period, hi, n_sub, linear, f_in, u_q, f_q, prm, dt, out1)
                        num = 0.0
                        den = 0.0
                        for i in range(count):
                            g = (out1[i] - out0[i]) / eps
                            num += g * (a_in[k + 1 + i] - out0[i])
                            den += g * g
                        if not (den > 0.0 and math.isfinite(num) and math.isfinite(den)):
                            break
                        f_s += num / den
                        i_s = _recover_integrator(loop, f_s, r, x, meas, period, ticked)
                        if abs(num / den) * nf <= 1e-13 * (hi - lo):
                            break  # the area is affine in it to rounding from here
                area = meas
            if ok and ticked:
                u, i_s, f_s = pid_update(loop, i_s, f_s, r_t[(j - t_off) // m], x, period, hi)
                area = u
            if at_limit:
                area = meas
            limited = at_limit
            if not ok:
                y[q, k, 0] = np.nan
                y[q, k, 1] = np.nan
                y[q, k, 2] = np.nan
                continue
            y[q, k, 0] = x
            y[q, k, 1] = p
            y[q, k, 2] = area
            if k == n_k - 1:
                break
            x, p, i_s, f_s, area = _interval(x, p, i_s, f_s, area, limited, j, t_off, m, r_t,
                                             loop, period, hi, n_sub, linear, f_in[k],
                                             f_in[k + 1], 1.0 + u_q[k + 1], f_q[k], prm, dt)
            if not (math.isfinite(x) and math.isfinite(p)):
                ok = False


@dataclass
class HydraulicActuatorTwin(SubStepTwin):
    """Hydraulic actuator twin; see the module docstring for the equations.

    Open loop: inputs ``A_valve`` [m^2] and ``F_load`` [N]; outputs ``x`` [m] and ``p`` [Pa].
    Closed loop: inputs ``x_ref`` [m], ``F_load`` and ``A_valve`` (the initial state of the
    controller and the area while it sits at a limit); outputs ``x``, ``p`` and ``A_valve``.

    Args:
        structure: ``open_loop`` (default: the measured area drives the piston) or
            ``closed_loop`` (the valve controller inside the twin, driven by ``x_ref``).
        drive: closed loop: the valve controller as it runs
            (:class:`ValveDriveConfig` or its table: update period, phase, the PID with its
            limits and anti-windup); default: the paper's Eq. 17 PID every sub-step, clamped
            to [0, A_max].
        sub_step: integration sub-step [s] (paper: 1e-4); the sample period (and the drive's
            period) must be a whole multiple of it (to 1e-6 relative).
        input_hold: ``linear`` (interpolate the inputs between samples; default) or ``zoh``
            (hold each sample's inputs until the next one): the area and the load in open
            loop, the load in closed loop.
        reference_hold: closed loop: the reference between samples at the controller's
            updates: ``cubic`` (default: the cubic through the four nearest samples; a smooth
            trajectory), ``linear`` or ``zoh`` (a set-point written once per sample).
        position_scale: residual normalisation floor for x [m].
        pressure_scale: residual normalisation floor for p [Pa].
        area_scale: closed loop: residual normalisation floor for the valve area [m^2].
        min_speed: D is held in a window whose RMS piston speed (from the measured x) is
            below this [m/s]: the damping force D*v is then a fraction of a pascal (the piston
            reversing; the paper's error spikes). 0.0015 m/s is about 10 % of the paper's
            largest speed; 0 disables the test.

    Raises:
        ValueError: an option that cannot work (the message names it).
    """

    structure: Literal["open_loop", "closed_loop"] = "open_loop"
    drive: ValveDriveConfig | dict[str, Any] | None = None
    sub_step: float = 1e-4
    input_hold: Literal["linear", "zoh"] = "linear"
    reference_hold: Literal["cubic", "linear", "zoh"] = "cubic"
    position_scale: float = 0.01
    pressure_scale: float = 1000.0
    area_scale: float = 1e-5
    min_speed: float = 0.0015

    def __post_init__(self) -> None:
        self._check_choices()
        if not self.sub_step > 0:
            raise ValueError("sub_step must be > 0")
        closed = self.structure == "closed_loop"
        if self.drive is not None and not closed:
            raise ValueError("drive: describes the valve controller of a closed-loop twin; an "
                             "open-loop twin is driven by the measured valve area")
        if isinstance(self.drive, Mapping):
            try:
                self.drive = ValveDriveConfig.model_validate(self.drive)
            except ValidationError as exc:
                err = exc.errors()[0]
                loc = ".".join(str(part) for part in err["loc"])
                raise ValueError(f"drive{'.' + loc if loc else ''}: {err['msg']}") from None
        self._drive = self.drive or ValveDriveConfig()
        if closed:
            try:
                self._drive.ticks(self.sub_step)
            except ValueError as exc:
                raise ValueError(f"drive.{exc}") from None
        self.parameters = HYDRAULIC_PARAMETERS
        self.outputs = (
            OutputSpec("x", "m", self.position_scale),
            OutputSpec("p", "Pa", self.pressure_scale),
        )
        if closed:
            # A_valve: the controller's initial state (its integrator) and the area while it
            # sits at a limit, and an output compared with the measurement.
            self.inputs = ("x_ref", "F_load", "A_valve")
            self.outputs = (*self.outputs, OutputSpec("A_valve", "m^2", self.area_scale))
            self.exogenous = ("x_ref", "F_load")
            # x starts from the measurement (with an offset); p follows x algebraically (Eq.
            # 16); the integrator follows from the measured area (an offset there would do
            # nothing in a window that starts at a limit: a dead column in the fit).
            self.initial_states = ("x",)
        else:
            self.inputs = ("A_valve", "F_load")
            self.exogenous = ("A_valve", "F_load")
            # x is the state; p follows from it algebraically (Eq. 16) and enters only the
            # first sub-step's valve flow, so its offset would wander undetermined.
            self.initial_states = ("x",)
        self.attach_points = (
            AttachPoint("p", "multiplicative", "1", "pressure"),
            AttachPoint("d(x)/dt", "additive", "m/s", "piston position"),
        )

    def excitation(self, window: WindowData) -> dict[str, str]:
        """D is not excited while the piston nearly stands still (see ``min_speed``)."""
        if self.min_speed <= 0 or window.n < 2:
            return {}
        v = np.diff(window["x"]) / np.diff(window.t)
        rms = float(np.sqrt(np.mean(v * v)))
        if rms >= self.min_speed:
            return {}
        return {"D": f"too little excitation: the piston nearly stands still (RMS speed "
                     f"{rms:.2g} m/s < {self.min_speed:g} m/s, e.g. reversing)"}

    @property
    def estimation_defaults(self) -> EstimationDefaults:
        """q_pump then D (a reversal then holds D alone); k_spring, A_piston and F_resist trade
        off with D within one window and A_max is never excited: kept at nameplate."""
        return EstimationDefaults(("q_pump", "D"))

    def simulate(self, theta: FloatArray, window: WindowData,
                 terms: Mapping[str, FloatArray] | None = None,
                 initial: FloatArray | None = None) -> FloatArray:
        """Simulate the window for a swarm; see :meth:`TwinModel.simulate`.

        Args:
            theta: (P, 6) parameters: k_spring [N/m], D [N/(m/s)], q_pump [m^3/s],
                A_max [m^2], A_piston [m^2], F_resist [N].
            window: needs ``A_valve``, ``F_load``, ``x``, ``p`` and, closed loop, ``x_ref``
                (N samples); the twin starts from the measured x and p of the first sample
                (closed loop: the controller from the measured area, module docstring).
            terms: ``p`` (dimensionless) and/or ``d(x)/dt`` [m/s] (the module docstring's
                meta-model terms); values of shape (N,) or (P, N).
            initial: offsets [m] (1,) or (P, 1) added to the measured x of the first sample
                (the estimator's initial-state estimate); None: 0.

        Returns:
            (P, N, 2): x [m], p [Pa]; closed loop (P, N, 3): x, p, A_valve [m^2]. A particle
            that blows up (non-finite state, negative pressure) gives nan from that sample on;
            nothing raises.

        Raises:
            KeyError: an unknown attach point in ``terms``.
            ValueError: a sample period that is not a whole number of sub-steps, or a term of
                the wrong shape.
        """
        theta = np.ascontiguousarray(np.asarray(theta, dtype=float))
        if theta.ndim != 2 or theta.shape[1] != len(self.parameters):
            raise ValueError(f"theta must have shape (P, {len(self.parameters)}), "
                             f"got {theta.shape}")
        n_sub = self.n_sub(window.sample_period)
        n = window.n
        p = theta.shape[0]
        terms = terms or {}
        unknown = set(terms) - set(_ATTACH)
        if unknown:
            raise KeyError(f"unknown attach point(s) {sorted(unknown)}; the hydraulic "
                           f"actuator twin offers {list(_ATTACH)}")
        u_p = term_array(terms.get("p"), p, n, "p")
        f_x = term_array(terms.get("d(x)/dt"), p, n, "d(x)/dt")
        a_in = np.ascontiguousarray(window["A_valve"], dtype=float)
        f_in = np.ascontiguousarray(window["F_load"], dtype=float)
        off = np.zeros((p, 1)) if initial is None else np.broadcast_to(
            np.atleast_2d(np.asarray(initial, dtype=float)), (p, 1))
        x0 = np.ascontiguousarray(float(window["x"][0]) + off[:, 0])
        if self.structure == "closed_loop":
            return self._simulate_closed(theta, window, n_sub, u_p, f_x, x0)
        p0 = np.full(p, float(window["p"][0]))
        y = np.empty((p, n, 2))
        _simulate_kernel(theta, a_in, f_in, x0, p0, n_sub, self.sub_step,
                         self.input_hold == "linear", u_p, f_x, y)
        return y

    def _simulate_closed(self, theta: FloatArray, window: WindowData, n_sub: int,
                         u_p: FloatArray, f_x: FloatArray, x0: FloatArray) -> FloatArray:
        """The closed loop through :func:`_closed_kernel`: (P, N, 3) x, p, A_valve."""
        dr = self._drive
        m, ph = dr.ticks(self.sub_step)
        n = window.n
        # The controller's clock is absolute (phase from t = 0): its updates relative to the
        # window's first sample.
        j0 = int(round(float(window.t[0]) / self.sub_step))
        t_off = ph - j0 if ph >= j0 else (ph - j0) % m
        ticks = np.arange(t_off, (n - 1) * n_sub + 1, m)
        r_s = np.ascontiguousarray(window["x_ref"], dtype=float)
        r_t = self._interpolate(r_s, ticks / n_sub, self.reference_hold)
        loop = dr.pack(math.inf)
        hi_is_amax = dr.valve.output_max is None
        span = (float(np.max(theta[:, 3])) if hi_is_amax else loop[5]) - loop[4]
        lo = loop[4]
        a_meas = np.asarray(window["A_valve"], dtype=float)
        tol = LIMIT_TOLERANCE * abs(span)
        limited = (a_meas <= lo + tol) | (a_meas >= lo + span - tol)
        # the first sample at a limit after each sample (n if none)
        nxt = np.where(limited, np.arange(n), n)
        stretch = np.minimum.accumulate(np.append(nxt, n)[::-1])[::-1][1:]
        y = np.empty((theta.shape[0], n, 3))
        _closed_kernel(theta, np.ascontiguousarray(a_meas),
                       np.ascontiguousarray(window["x"], dtype=float),
                       np.ascontiguousarray(window["p"], dtype=float),
                       np.ascontiguousarray(window["F_load"], dtype=float), r_s, r_t,
                       int(t_off), int(m), np.ascontiguousarray(stretch, dtype=np.int64), x0,
                       n_sub, self.sub_step, self.input_hold == "linear", loop, hi_is_amax, tol,
                       SPLIT_SAMPLES, u_p, f_x, y)
        return y

    @staticmethod
    def _interpolate(r_s: FloatArray, u: FloatArray, how: str) -> FloatArray:
        """A sampled signal ``r_s`` (N,) at fractional sample positions ``u`` (M,): ``zoh``,
        ``linear`` or ``cubic`` (Lagrange through the four nearest samples, one-sided at the
        ends); exact at the samples."""
        n = r_s.size
        k = np.minimum(np.floor(u).astype(np.int64), n - 1)
        w = u - k
        if how == "zoh" or n == 1:
            return np.ascontiguousarray(r_s[k])
        if how == "linear" or n < 4:
            k1 = np.minimum(k + 1, n - 1)
            return np.ascontiguousarray(r_s[k] + w * (r_s[k1] - r_s[k]))
        # Lagrange cubic through the four nearest samples (one-sided at the window's ends)
        base = np.clip(k - 1, 0, n - 4)
        t = u - base  # position in the four-node stencil 0..3
        out = np.zeros_like(u)
        for i in range(4):
            li = np.ones_like(u)
            for jn in range(4):
                if jn != i:
                    li *= (t - jn) / (i - jn)
            out += li * r_s[base + i]
        return np.ascontiguousarray(out)
