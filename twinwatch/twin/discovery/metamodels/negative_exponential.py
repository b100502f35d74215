"""Negative exponential meta-model ``a*exp(-b*z)`` (paper Table 1: ageing, degradation,
fatigue, crack growth)."""

from __future__ import annotations

import numpy as np

from twinwatch.twin.discovery.metamodels.base import ScaledShape, fmt
from twinwatch.twin.model import FloatArray


class NegativeExponential(ScaledShape):
    """``U(z) = a*exp(-b*z)`` (b >= 0); nonlinear in the rate ``b``."""

    kind = "negative_exponential"
    equation = "a*exp(-b*z)"
    conditions = "ageing, degradation, fatigue, crack growth"
    z_powers = (0, -1)
    simplifies_to_constant = True
    b_bounds = (0.0, 5.0)

    @staticmethod
    def shape(z: FloatArray, b: FloatArray) -> FloatArray:
        """``exp(-b*z)``."""
        return np.exp(-b * z)

    def move_origin(self, p: FloatArray, d: float) -> FloatArray | None:
        """``a exp(-b z) = (a exp(-b d)) exp(-b (z - d))``."""
        q = np.array(p, dtype=float, copy=True)
        with np.errstate(all="ignore"):
            q[0] = q[0] * np.exp(-q[1] * d)
        return q if np.all(np.isfinite(q)) else None

    def render(self, p: FloatArray, z: str, precision: int = 2) -> str:
        return f"{fmt(float(p[0]), precision)}*exp(-{fmt(float(p[1]), max(precision, 4))}*{z})"
