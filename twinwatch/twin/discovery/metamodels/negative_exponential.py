"""Negative exponential meta-model ``a*exp(-b*z)`` (paper Table 1: ageing, degradation,
fatigue, crack growth)."""

from __future__ import annotations

import numpy as np

from twinwatch.twin.discovery.metamodels.base import MetaModel, fmt
from twinwatch.twin.model import FloatArray


class NegativeExponential(MetaModel):
    """``U(z) = a*exp(-b*z)`` (b >= 0); nonlinear in the rate ``b``."""

    kind = "negative_exponential"
    equation = "a*exp(-b*z)"
    conditions = "ageing, degradation, fatigue, crack growth"
    params = ("a", "b")
    z_powers = (0, -1)
    nonlinear = ("b",)
    simplifies_to_constant = True

    def evaluate(self, p: FloatArray, z: FloatArray) -> FloatArray:
        p = np.atleast_2d(np.asarray(p, dtype=float))
        z = np.asarray(z, dtype=float)[None, :]
        with np.errstate(all="ignore"):
            return p[:, 0, None] * np.exp(-p[:, 1, None] * z)

    def basis(self, nl: FloatArray, u: FloatArray) -> FloatArray:
        nl = np.atleast_2d(np.asarray(nl, dtype=float))
        u = np.asarray(u, dtype=float)[None, :]
        with np.errstate(all="ignore"):
            return np.exp(-nl[:, :1] * u)[:, None, :]

    def bounds(self, amplitude: float, *, b_range: tuple[float, float] | None = None
               ) -> tuple[FloatArray, FloatArray]:
        a = float(amplitude)
        return np.array([-a, 0.0]), np.array([a, 5.0])

    def move_origin(self, p: FloatArray, d: float) -> FloatArray | None:
        """``a exp(-b z) = (a exp(-b d)) exp(-b (z - d))``."""
        q = np.array(p, dtype=float, copy=True)
        with np.errstate(all="ignore"):
            q[0] = q[0] * np.exp(-q[1] * d)
        return q if np.all(np.isfinite(q)) else None

    def render(self, p: FloatArray, z: str, precision: int = 2) -> str:
        return f"{fmt(float(p[0]), precision)}*exp(-{fmt(float(p[1]), max(precision, 4))}*{z})"
