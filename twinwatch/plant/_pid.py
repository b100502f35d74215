"""The simulated plants' drive-loop update (compiled), shared by the DC motor and the hydraulic
actuator.

Written apart from the twin's (:mod:`twinwatch.twin.models._pid`) on purpose: a twin that shared the
plant's code would reproduce the plant's mistakes, and the exactness tests could not see them.
"""

from __future__ import annotations

from numba import njit


@njit(cache=True, nogil=True)
def pid_tick(loop, i_s, f_s, r, y, period):  # pragma: no cover - compiled
    """One update of a drive loop as :mod:`twinwatch.io.drive` describes it: P/PI/PID with
    the derivative filter N, the output clamped to [loop[4], loop[5]] with the loop's
    anti-windup (paper Eq. 17 for the valve).

    Args:
        loop: the packed loop (``LoopConfig.pack`` order, limits resolved), (12,): the last
            two are the integrator's and the filter's method (0 forward Euler, 1 backward
            Euler, 1/2 trapezoidal).
        i_s, f_s: the integrator and the derivative filter's state before the update.
        r, y: reference and feedback (rad/s and rad/s, A and A, or m and m).
        period: the loop's update period [s].

    Returns:
        (u, I, f): the output held until the next update (V or m^2), the integrator and the
        filter state after the update.
    """
    kp, ki, kd, nf = loop[0], loop[1], loop[2], loop[3]
    lo, hi, aw, tt, kff, sgn = loop[4], loop[5], loop[6], loop[7], loop[8], loop[9]
    # The integrator's and the derivative filter's discretisation (Discrete-Time Integrator
    # realisation y(n) = x(n) + c*K*T*u(n), x(n+1) = x(n) + K*T*u(n)): c = 0 forward Euler,
    # 1 backward Euler, 1/2 trapezoidal. The filter's output f(n) = s + c_d*T*d(n) makes
    # d = N*(kd*e - f) implicit in d: solved for d below.
    c_int, c_filt = loop[10], loop[11]
    e = sgn * (r - y)
    d = 0.0
    if kd != 0.0:
        d = nf * (kd * e - f_s) / (1.0 + c_filt * nf * period)
    integral = i_s + c_int * ki * period * e
    u_pid = kp * e + integral + d + kff * r
    u = min(max(u_pid, lo), hi)
    if aw == 1.0:
        if not ((u_pid > hi and ki * e > 0.0) or (u_pid < lo and ki * e < 0.0)):
            i_s += ki * period * e
    elif aw == 2.0:
        i_s += ki * period * e + (period / tt) * (u - u_pid)
    else:
        i_s += ki * period * e
    return u, i_s, f_s + period * d
