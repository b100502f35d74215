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
        loop: the packed loop (``LoopConfig.pack`` order, limits resolved), (10,).
        i_s, f_s: the integrator and the derivative filter's state before the update.
        r, y: reference and feedback (rad/s and rad/s, A and A, or m and m).
        period: the loop's update period [s].

    Returns:
        (u, I, f): the output held until the next update (V or m^2), the integrator and the
        filter state after the update.
    """
    kp, ki, kd, nf = loop[0], loop[1], loop[2], loop[3]
    lo, hi, aw, tt, kff, sgn = loop[4], loop[5], loop[6], loop[7], loop[8], loop[9]
    e = sgn * (r - y)
    d = nf * (kd * e - f_s) if kd != 0.0 else 0.0
    u_pid = kp * e + i_s + d + kff * r
    u = min(max(u_pid, lo), hi)
    if aw == 1.0:
        if not ((u_pid > hi and ki * e > 0.0) or (u_pid < lo and ki * e < 0.0)):
            i_s += ki * period * e
    elif aw == 2.0:
        i_s += ki * period * e + (period / tt) * (u - u_pid)
    else:
        i_s += ki * period * e
    return u, i_s, f_s + period * d
