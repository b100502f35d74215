"""Rectifier (piecewise linear) meta-model ``a*max(0, z - b) + c``: a power stage that conducts
one way only (a unidirectional chopper with its freewheeling diode, a diode), a one-sided load
or stop. Not in paper Table 1."""

from __future__ import annotations

import numpy as np

from twinwatch.twin.discovery.metamodels.base import MetaModel, fmt, plus
from twinwatch.twin.model import FloatArray

#: Fewest samples, as a fraction of the window, on each side of a knee: a knee with (nearly) all
#: samples on one side is a line or a constant, which the linear meta-model states better.
SIDE_FRACTION = 0.05


def hinge_range(u: FloatArray) -> tuple[float, float] | None:
    """Knee range inside the data: between the ``SIDE_FRACTION`` quantiles of ``u`` (None when
    the input hardly varies)."""
    lo, hi = (float(x) for x in np.quantile(u, [SIDE_FRACTION, 1.0 - SIDE_FRACTION]))
    if not hi - lo > 1e-9 * max(abs(lo), abs(hi), 1.0):
        return None
    return lo, hi


class Rectifier(MetaModel):
    """``U(z) = a*max(0, z - b) + c``: zero (or the offset ``c``) up to the knee ``b``, then a
    slope ``a``.

    Separable as ``a*max(0, u - b) + c`` with the knee ``b`` the only nonlinear parameter (the
    swarm searches it inside the window's data, :meth:`data_range`); ``c`` is optional. A
    function conducting *below* its knee, ``a*max(0, b - z)``, is this one plus a line
    (``a*max(0, z - b) - a*(z - b)``): on an input the twin already uses linearly (a voltage, a
    speed), the line is the twin's own parameters, so one kind covers both sides.

    Of time, it is a ramp that starts at ``t = b`` (an onset).
    """

    kind = "rectifier"
    equation = "a*max(0, z - b) + c"
    conditions = ("a power stage that conducts one way only (unidirectional chopper, diode), "
                  "a one-sided load or stop")
    params = ("a", "b", "c")
    z_powers = (-1, 1)
    optional = ("c",)
    nonlinear = ("b",)

    def evaluate(self, p: FloatArray, z: FloatArray) -> FloatArray:
        p = np.atleast_2d(np.asarray(p, dtype=float))
        z = np.asarray(z, dtype=float)[None, :]
        with np.errstate(all="ignore"):
            return p[:, 0, None] * np.maximum(z - p[:, 1, None], 0.0) + p[:, 2, None]

    def basis(self, nl: FloatArray, u: FloatArray) -> FloatArray:
        nl = np.atleast_2d(np.asarray(nl, dtype=float))
        u = np.asarray(u, dtype=float)[None, :]
        ramp = np.maximum(u - nl[:, :1], 0.0)
        return np.stack([ramp, np.ones_like(ramp)], axis=1)

    def bounds(self, amplitude: float, *, b_range: tuple[float, float] | None = None
               ) -> tuple[FloatArray, FloatArray]:
        """|a| up to the amplitude per unit of normalised input, the knee within ``b_range``
        (default: anywhere in the input's range, [-1, 1])."""
        a = float(amplitude)
        b_lo, b_hi = b_range or (-1.0, 1.0)
        return np.array([-a, b_lo, -a]), np.array([a, b_hi, a])

    def data_range(self, u: FloatArray) -> tuple[float, float] | None:
        return hinge_range(u)

    def identifiable(self, u: FloatArray) -> bool:
        return hinge_range(u) is not None

    def shift_origin(self, p: FloatArray, t_ref: float) -> tuple[FloatArray, float]:
        q = self.move_origin(p, -t_ref)
        assert q is not None
        return q, 0.0

    def move_origin(self, p: FloatArray, d: float) -> FloatArray | None:
        """``a max(0, z - b) = a max(0, (z - d) - (b - d))``."""
        q = np.array(p, dtype=float, copy=True)
        q[1] = q[1] - d
        return q

    def render(self, p: FloatArray, z: str, precision: int = 2) -> str:
        knee = f"max(0, {z}{plus(-float(p[1]), precision)})" if p[1] != 0 else f"max(0, {z})"
        out = f"{fmt(float(p[0]), precision)}*{knee}"
        return out + plus(float(p[2]), precision) if p[2] != 0 else out
