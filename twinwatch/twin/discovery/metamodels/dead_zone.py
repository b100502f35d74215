"""Dead-zone meta-model ``a*dz(z, b)``: backlash, a voltage the power stage needs before any
current flows, a stiction band. Not in paper Table 1."""

from __future__ import annotations

import numpy as np

from twinwatch.twin.discovery.metamodels.base import ScaledShape, fmt
from twinwatch.twin.model import FloatArray


def dead_zone(z: FloatArray, b: FloatArray) -> FloatArray:
    """``dz(z, b)``: 0 for ``|z| <= b``, ``z - b*sign(z)`` beyond (b >= 0; broadcasts)."""
    out: FloatArray = np.sign(z) * np.maximum(np.abs(z) - np.abs(b), 0.0)
    return out


class DeadZone(ScaledShape):
    """``U(z) = a*dz(z, b)``: nothing while ``|z| <= b``, then a slope ``a`` from the band's edge.

    Separable with the half-width ``b`` the only nonlinear parameter, searched between 0 and
    the 95th percentile of ``|z|`` (a band holding nearly every sample is a constant; ``b = 0``
    is a line, which the simpler linear meta-model states with one parameter fewer).

    A dead zone *of an input the twin already uses* (``Va_eff = dz(Va, b)`` in ``d(ia)/dt``)
    is the twin's own linear term minus a limit: ``dz(z, b) = z - clip(z, -b, b)``; on such an
    input it shows as a saturation or, if the input keeps one sign, as a constant.
    """

    kind = "dead_zone"
    equation = "a*dz(z, b)"
    conditions = ("backlash, a voltage the power stage needs before current flows, a "
                  "stiction band")
    z_powers = (-1, 1)
    #: ``0 <= b <= 1`` unless the data say otherwise (``|a|``: per unit of normalised input)
    b_bounds = (0.0, 1.0)

    @staticmethod
    def shape(z: FloatArray, b: FloatArray) -> FloatArray:
        """The band's nonlinearity of ``z`` at half-width ``b`` (broadcasts): :func:`dead_zone`
        (a subclass with another band function shares the rest)."""
        return dead_zone(z, b)

    def data_range(self, u: FloatArray) -> tuple[float, float] | None:
        hi = float(np.quantile(np.abs(u), 0.95))
        return (0.0, hi) if hi > 0 else None

    def identifiable(self, u: FloatArray) -> bool:
        return bool(np.quantile(np.abs(u), 0.95) > 0)

    def canonical(self, p: FloatArray) -> FloatArray:
        """``b >= 0`` (the band is symmetric)."""
        q = np.array(p, dtype=float, copy=True)
        q[1] = abs(q[1])
        return q

    def render(self, p: FloatArray, z: str, precision: int = 2) -> str:
        return f"{fmt(float(p[0]), precision)}*dz({z}, {fmt(float(p[1]), precision)})"
