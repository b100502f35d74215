"""Periodic meta-model ``a*sin(b*z + c) + d`` (paper Table 1: unbalanced shaft, shaft
misalignment, machine unsteadiness; paper Eq. 13 is one)."""

from __future__ import annotations

import math

import numpy as np

from twinwatch.twin.discovery.metamodels.base import MetaModel, fmt, plus, wrap_phase
from twinwatch.twin.model import FloatArray, WindowData


class Periodic(MetaModel):
    """``U(z) = a*sin(b*z + c) + d``; separable as ``alpha*sin(b z) + beta*cos(b z) + d`` with
    ``a = hypot(alpha, beta)``, ``c = atan2(beta, alpha)``; nonlinear in the angular frequency
    ``b``; the offset ``d`` is optional."""

    kind = "periodic"
    equation = "a*sin(b*z + c) + d"
    conditions = "unbalanced shaft, shaft misalignment, machine unsteadiness"
    params = ("a", "b", "c", "d")
    z_powers = (0, -1)
    optional = ("d",)
    nonlinear = ("b",)

    @property
    def columns(self) -> tuple[str, ...]:
        return ("alpha", "beta", "d")

    def evaluate(self, p: FloatArray, z: FloatArray) -> FloatArray:
        p = np.atleast_2d(np.asarray(p, dtype=float))
        z = np.asarray(z, dtype=float)[None, :]
        with np.errstate(all="ignore"):
            return p[:, 0, None] * np.sin(p[:, 1, None] * z + p[:, 2, None]) + p[:, 3, None]

    def basis(self, nl: FloatArray, u: FloatArray) -> FloatArray:
        nl = np.atleast_2d(np.asarray(nl, dtype=float))
        u = np.asarray(u, dtype=float)[None, :]
        arg = nl[:, :1] * u
        return np.stack([np.sin(arg), np.cos(arg), np.ones_like(arg)], axis=1)

    def from_separable(self, nl: FloatArray, coef: FloatArray) -> FloatArray:
        alpha, beta, d = coef
        return np.array([math.hypot(alpha, beta), nl[0], math.atan2(beta, alpha), d])

    def active_from_mask(self, mask: FloatArray) -> tuple[bool, ...]:
        return (True, True, True, bool(mask[2]))

    def bounds(self, amplitude: float, *, b_range: tuple[float, float] | None = None
               ) -> tuple[FloatArray, FloatArray]:
        """a >= 0 (the sign is the phase's), c in [-pi, pi]; ``b_range`` defaults to one to
        50 periods per ``z_ref``."""
        a = float(amplitude)
        b_lo, b_hi = b_range or (2 * math.pi, 100 * math.pi)
        return np.array([0.0, b_lo, -math.pi, -a]), np.array([a, b_hi, math.pi, a])

    def polish_bounds(self, lo: FloatArray, hi: FloatArray, amplitude: float
                      ) -> tuple[FloatArray, FloatArray]:
        lo, hi = super().polish_bounds(lo, hi, amplitude)
        lo[2], hi[2] = -4 * math.pi, 4 * math.pi  # the phase may wrap while polishing
        return lo, hi

    def search_range(self, window: WindowData, input_is_time: bool, z_ref: float
                     ) -> tuple[float, float] | None:
        """One period per window up to a quarter of the sampling rate (time), or 0.5 to 50
        radians per input range (a channel)."""
        if not input_is_time:
            return (0.5, 50.0)
        span = float(window.t[-1] - window.t[0])
        return ((2 * math.pi / span) * z_ref, (math.pi / (2 * window.sample_period)) * z_ref)

    def seeds(self, residual: FloatArray, window: WindowData, input_is_time: bool,
              z_ref: float, count: int) -> list[FloatArray]:
        """The residual's largest periodogram peaks (a forcing keeps its frequency through the
        twin's linear(ised) dynamics), for a term of time."""
        if not input_is_time:
            return []
        return [np.array([w * z_ref]) for w in peak_frequencies(residual, window, count)]

    def canonical(self, p: FloatArray) -> FloatArray:
        """``a >= 0``, ``b > 0`` and ``c`` in (-pi, pi]
        (``a sin(bz + c) = -a sin(bz + c + pi) = a sin(-bz - c + pi)``)."""
        q = np.array(p, dtype=float, copy=True)
        if q[1] < 0:
            q[1], q[2] = -q[1], math.pi - q[2]
        if q[0] < 0:
            q[0], q[2] = -q[0], q[2] + math.pi
        q[2] = wrap_phase(q[2])
        return q

    def shift_origin(self, p: FloatArray, t_ref: float) -> tuple[FloatArray, float]:
        q = np.array(p, dtype=float, copy=True)
        q[2] = wrap_phase(q[2] - q[1] * t_ref)
        return q, 0.0

    def move_origin(self, p: FloatArray, d: float) -> FloatArray | None:
        """``a sin(b z + c) = a sin(b (z - d) + c + b d)``."""
        q = np.array(p, dtype=float, copy=True)
        q[2] = q[2] + q[1] * d
        return q

    def align(self, p: FloatArray, ref: FloatArray) -> FloatArray:
        """The phase within pi of ``ref``'s (2 pi apart is the same term)."""
        q = np.array(p, dtype=float, copy=True)
        q[2] = float(ref[2]) + wrap_phase(q[2] - float(ref[2]))
        return q

    def render(self, p: FloatArray, z: str, precision: int = 2) -> str:
        out = (f"{fmt(float(p[0]), precision)}*sin({fmt(float(p[1]), precision)}*{z}"
               f"{plus(float(p[2]), precision)})")
        return out + plus(float(p[3]), precision) if p[3] != 0 else out


def peak_frequencies(residual: FloatArray, window: WindowData, count: int) -> list[float]:
    """Angular frequencies [rad/s] of the largest periodogram peaks of a residual (N, n_out),
    refined by parabolic interpolation, strongest first."""
    res = np.asarray(residual, dtype=float)
    n, n_out = res.shape
    nfft = 8 * n
    spec = np.zeros(nfft // 2 + 1)
    for j in range(n_out):
        x = res[:, j] - np.mean(res[:, j])
        spec += np.abs(np.fft.rfft(x * np.hanning(n), nfft)) ** 2
    freqs = np.fft.rfftfreq(nfft, window.sample_period) * 2 * math.pi
    peaks = [k for k in range(2, spec.size - 1)
             if spec[k] >= spec[k - 1] and spec[k] > spec[k + 1]]
    peaks.sort(key=lambda k: -spec[k])
    out = []
    for k in peaks[:count]:
        a, b, c = np.log(spec[k - 1:k + 2] + 1e-300)
        den = a - 2 * b + c
        shift = 0.5 * (a - c) / den if den != 0 else 0.0
        out.append(float(freqs[k] + shift * (freqs[1] - freqs[0])))
    return out
