"""Coulomb (dry) friction meta-model ``a*sign(z) + c`` on a speed input: brush, seal or bearing
friction that opposes motion with a force independent of the speed. Not in paper Table 1
(issue 9: terms real drives need)."""

from __future__ import annotations

import numpy as np

from twinwatch.twin.metamodels.base import MetaModel, fmt, plus
from twinwatch.twin.model import FloatArray

#: Fewest samples, as a fraction of the window, where ``sign(z)`` differs from its most common
#: value: below it, the sign is (nearly) a constant and says nothing a constant does not.
MINORITY_FRACTION = 0.02


class Coulomb(MetaModel):
    """``U(z) = a*sign(z) + c`` (``sign(0) = 0``: no dry friction at rest); ``c`` optional.

    Linear in both parameters, so it needs no smoothing: the input is a *measured* signal, the
    basis ``sign(z)`` is a fixed column for the least squares and the fit is exact in one step.
    (A smoothed ``tanh(z/eps)`` would only matter if the sign were taken of a simulated state
    differentiated by the solver.) The cost: noise on a speed near zero flips the sign; such
    samples are few where the speed crosses zero, and a window where the sign barely changes
    is not used (:meth:`identifiable`: then it is a constant, which the linear meta-model
    states). As a twin term on ``d(omega)/dt`` it reads ``-Tc/J*sign(omega)``: ``a < 0``.
    """

    kind = "coulomb"
    equation = "a*sign(z) + c"
    conditions = "dry (Coulomb) friction on a speed input: brushes, seals, bearings"
    params = ("a", "c")
    optional = ("c",)

    def evaluate(self, p: FloatArray, z: FloatArray) -> FloatArray:
        p = np.atleast_2d(np.asarray(p, dtype=float))
        z = np.asarray(z, dtype=float)[None, :]
        with np.errstate(all="ignore"):
            return p[:, 0, None] * np.sign(z) + p[:, 1, None]

    def basis(self, nl: FloatArray, u: FloatArray) -> FloatArray:
        n_p = np.atleast_2d(nl).shape[0]
        s = np.repeat(np.sign(np.asarray(u, dtype=float))[None, :], n_p, axis=0)
        return np.stack([s, np.ones_like(s)], axis=1)

    def bounds(self, amplitude: float, *, b_range: tuple[float, float] | None = None
               ) -> tuple[FloatArray, FloatArray]:
        a = float(amplitude)
        return np.array([-a, -a]), np.array([a, a])

    def identifiable(self, u: FloatArray) -> bool:
        s = np.sign(np.asarray(u, dtype=float))
        counts = [int(np.sum(s == v)) for v in (-1.0, 0.0, 1.0)]
        return s.size - max(counts) >= max(3, MINORITY_FRACTION * s.size)

    def render(self, p: FloatArray, z: str, precision: int = 2) -> str:
        out = f"{fmt(float(p[0]), precision)}*sign({z})"
        return out + plus(float(p[1]), precision) if p[1] != 0 else out
