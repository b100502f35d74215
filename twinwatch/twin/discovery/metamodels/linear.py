"""Linear meta-model ``m*z + b`` (paper Table 1: friction, misalignment, backlash)."""

from __future__ import annotations

import numpy as np

from twinwatch.twin.discovery.metamodels.base import MetaModel, fmt, plus
from twinwatch.twin.model import AttachPoint, FloatArray


class Linear(MetaModel):
    """``U(z) = m*z + b``; both parameters optional: with the slope switched off it is a
    constant ``b`` (a steady offset or gain, which the paper reads as a leak on the hydraulic
    pressure, Section 5.3.2)."""

    kind = "linear"
    equation = "m*z + b"
    conditions = "friction, misalignment, backlash"
    params = ("m", "b")
    z_powers = (-1,)
    optional = ("m", "b")

    def main_index(self, active: tuple[bool, ...] | None = None) -> int:
        """The slope ``m``, or the constant ``b`` when the slope is switched off."""
        return 1 if active is not None and not active[0] else 0

    def interpret(self, attach: AttachPoint, active: tuple[bool, ...]) -> str:
        if not active[0]:
            what = "gain" if attach.mode == "multiplicative" else "offset"
            return (f"constant on {attach.quantity}: a steady {what} (a leak, a constant "
                    f"load or loss; Table 1 linear: {self.meaning})")
        return super().interpret(attach, active)

    def evaluate(self, p: FloatArray, z: FloatArray) -> FloatArray:
        p = np.atleast_2d(np.asarray(p, dtype=float))
        z = np.asarray(z, dtype=float)[None, :]
        with np.errstate(all="ignore"):
            return p[:, 0, None] * z + p[:, 1, None]

    def basis(self, nl: FloatArray, u: FloatArray) -> FloatArray:
        n_p = np.atleast_2d(nl).shape[0]
        u = np.asarray(u, dtype=float)[None, :]
        return np.stack([np.repeat(u, n_p, axis=0), np.ones((n_p, u.shape[1]))], axis=1)

    def shift_origin(self, p: FloatArray, t_ref: float) -> tuple[FloatArray, float]:
        q = np.array(p, dtype=float, copy=True)
        q[1] = q[1] - q[0] * t_ref
        return q, 0.0

    def move_origin(self, p: FloatArray, d: float) -> FloatArray | None:
        """``m z + b = m (z - d) + b + m d``."""
        q = np.array(p, dtype=float, copy=True)
        q[1] = q[1] + q[0] * d
        return q

    def render(self, p: FloatArray, z: str, precision: int = 2) -> str:
        if p[0] == 0:
            return fmt(float(p[1]), precision)
        out = f"{fmt(float(p[0]), precision)}*{z}"
        return out + plus(float(p[1]), precision) if p[1] != 0 else out
