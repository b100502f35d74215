"""The compiled polish and grid of the degradation models (twin/prognostics/_lm.py) give the
numbers of the numpy versions they replaced (issue 22: the same trends and RULs at a fraction
of the CPU). The numpy versions are kept here as the reference."""

from __future__ import annotations

import math

import numpy as np
import pytest

from twinwatch.twin.prognostics._lm import levenberg_marquardt, wls_grid
from twinwatch.twin.prognostics.degradation import DegradationFit, _g

CODE = {"c": 0, "m": 1, "r": 2, "t0": 3}


def reference_lm(resid, jac, x0, lo, hi, iterations=40):  # type: ignore[no-untyped-def]
    """The numpy Levenberg-Marquardt of twinwatch 0.x (degradation.py before issue 22)."""
    x = x0.copy()
    r = resid(x)
    cost = float(r @ r)
    lam = 1e-3
    for _ in range(iterations):
        j = jac(x)
        a = j.T @ j
        g = j.T @ r
        d = np.diag(a).copy()
        d[d <= 0] = 1.0
        improved = False
        for _ in range(10):
            try:
                step = np.linalg.solve(a + lam * np.diag(d), -g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            xn = np.clip(x + step, lo, hi)
            rn = resid(xn)
            cn = float(rn @ rn)
            if math.isfinite(cn) and cn < cost:
                improved = True
                small = cost - cn <= 1e-10 * cost
                x, r, cost = xn, rn, cn
                lam = max(lam / 3.0, 1e-9)
                break
            lam *= 10.0
        if not improved or small:
            break
    return x


def reference_grid(basis, y, w):  # type: ignore[no-untyped-def]
    s0 = float(np.sum(w))
    sy = float(w @ y)
    syy = float(w @ (y * y))
    s1 = basis @ w
    s2 = (basis * basis) @ w
    sgy = basis @ (w * y)
    det = s0 * s2 - s1 * s1
    ok = det > 1e-12 * np.maximum(s0 * s2, 1e-300)
    det_s = np.where(ok, det, 1.0)
    c = np.where(ok, (s2 * sy - s1 * sgy) / det_s, sy / s0)
    m = np.where(ok, (s0 * sgy - s1 * sy) / det_s, 0.0)
    chi2 = np.where(ok, np.maximum(syy - c * sy - m * sgy, 0.0), np.inf)
    return chi2, c, m


def evidence(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The paper's resistance law (onset 160 s, r = 0.003 /s) with 0.1-1 % noise."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.uniform(0.0, 900.0, 100))
    y = 6.5 - 0.044 * (np.exp(0.003 * np.maximum(t - 160.0, 0.0)) - 1.0)
    s = np.full(t.size, 6.5 * rng.uniform(1e-3, 1e-2))
    return t, y + s * rng.standard_normal(t.size), s


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("free", [("c", "m", "t0"), ("c", "m", "r"), ("c", "m", "r", "t0")])
def test_the_compiled_polish_gives_the_numpy_optimum(seed: int, free: tuple[str, ...]) -> None:
    t, y, s = evidence(seed)
    t_ref = float(t[-1])
    kind = "exponential" if "r" in free else "linear"
    start = DegradationFit(kind, t_ref, 6.3, -2e-4, 0.002 if kind == "exponential" else 0.0,
                           300.0 if "t0" in free else None, free=free)

    def unpack(x: np.ndarray) -> DegradationFit:
        f = DegradationFit(kind, t_ref, start.c, start.m, start.r, start.onset, free=free)
        for i, p in enumerate(free):
            if p == "t0":
                f.onset = float(x[i])
            else:
                setattr(f, p, float(x[i]))
        return f

    def resid(x: np.ndarray) -> np.ndarray:
        return (unpack(x).value(t) - y) / s

    def jac(x: np.ndarray) -> np.ndarray:
        return unpack(x).jacobian(t) / s[:, None]

    x0 = np.array([start._get(p) for p in free])
    span = float(t[-1] - t[0])
    lo = np.array([{"r": -6.0 / span, "t0": t[0]}.get(p, -np.inf) for p in free])
    hi = np.array([{"r": 12.0 / span, "t0": t[-1]}.get(p, np.inf) for p in free])
    want = reference_lm(resid, jac, x0, lo, hi)
    base = np.array([start.c, start.m, start.r, start.onset or 0.0])
    got = levenberg_marquardt(t, y, s, t_ref, base, start.onset is not None,
                              np.array([CODE[p] for p in free], dtype=np.int64), x0, lo, hi)
    cost_want = float(resid(want) @ resid(want))
    cost_got = float(resid(got) @ resid(got))
    assert cost_got == pytest.approx(cost_want, rel=1e-6)
    # the start's cost is well above: the polish did move
    assert cost_want < 0.5 * float(resid(x0) @ resid(x0))
    for i, p in enumerate(free):
        assert got[i] == pytest.approx(want[i], rel=1e-4, abs=1e-9), p


@pytest.mark.parametrize("seed", range(3))
def test_the_compiled_grid_gives_the_numpy_grid(seed: int) -> None:
    t, y, s = evidence(seed)
    t_ref = float(t[-1])
    w = 1.0 / s**2
    rs = np.concatenate([-np.geomspace(4.0, 0.05, 8), np.geomspace(0.05, 8.0, 18)]) / 900.0
    onsets = t[5:80:3]
    tt = np.maximum(t[None, :], onsets[:, None]) - t_ref
    cases = [
        (np.zeros(1), onsets, True, tt),
        (rs, np.zeros(0), False, _g((t - t_ref)[None, :], rs[:, None])),
        (rs, onsets, True, _g(tt[None, :, :], rs[:, None, None]).reshape(-1, t.size)),
        (np.zeros(1), np.zeros(0), False, (t - t_ref)[None, :]),
    ]
    for r_grid, o_grid, has_onset, basis in cases:
        want = reference_grid(basis, y, w)
        got = wls_grid(t, y, w, t_ref, r_grid, o_grid, has_onset)
        assert int(np.argmin(got[0])) == int(np.argmin(want[0]))
        for a, b in zip(got, want, strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-7, atol=1e-9 * float(np.max(np.abs(b))))


def test_the_small_symmetric_pseudo_inverse_is_numpys() -> None:
    """pinv_sym (issue 22) is numpy's hermitian pinv to rounding: regular and singular
    matrices of the sizes the trends and the fusion invert, and the rcond cut."""
    from twinwatch.twin.prognostics.degradation import pinv_sym

    rng = np.random.default_rng(0)
    for k in (1, 2, 3, 4, 6):
        for singular in (False, True):
            a = rng.standard_normal((10, k))
            a = a.T @ a
            if singular and k > 1:
                a[:, -1] = a[:, 0]
                a[-1, :] = a[0, :]
            ref = np.linalg.pinv(a, hermitian=True)
            np.testing.assert_allclose(pinv_sym(a), ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    a = np.diag([1.0, 1e-13])  # below rcond 1e-12 of the largest: dropped, as numpy does
    np.testing.assert_array_equal(pinv_sym(a, rcond=1e-12), np.diag([1.0, 0.0]))
    np.testing.assert_array_equal(np.linalg.pinv(a, rcond=1e-12, hermitian=True),
                                  np.diag([1.0, 0.0]))


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("free", [("c",), ("c", "m"), ("c", "m", "t0"), ("c", "m", "r"),
                                  ("c", "m", "r", "t0")])
def test_the_compiled_fit_statistics_are_the_numpy_ones(seed: int, free: tuple[str, ...]
                                                        ) -> None:
    """fit_statistics (issue 58: a polished model's residuals, information matrix, long-run
    factor and chi-square floor in one compiled pass) gives what the numpy model, Jacobian and
    FFT long-run factor give, to rounding, on the paper's resistance law with noise."""
    from twinwatch.twin.prognostics._lm import fit_statistics
    from twinwatch.twin.prognostics._lm import long_run_factor as compiled_lrf
    from twinwatch.twin.prognostics.degradation import long_run_factor

    t, y, s = evidence(seed)
    t_ref = float(t[-1])
    kind = "exponential" if "r" in free else ("linear" if "m" in free else "none")
    fit = DegradationFit(kind, t_ref, 6.4, -3e-4 if "m" in free else 0.0,
                         0.0025 if "r" in free else 0.0, 250.0 if "t0" in free else None,
                         free=free)
    want_r = (fit.value(t) - y) / s
    want_j = fit.jacobian(t) / s[:, None]
    base = np.array([fit.c, fit.m, fit.r, fit.onset or 0.0])
    codes = np.array([CODE[p] for p in free], dtype=np.int64)
    x = np.array([fit._get(p) for p in free])
    r, chi2, info, lrf, floor = fit_statistics(t, y, s, t_ref, base, fit.onset is not None,
                                               codes, x, 1e-9)
    np.testing.assert_allclose(r, want_r, rtol=1e-12, atol=1e-12)
    assert chi2 == pytest.approx(float(want_r @ want_r), rel=1e-12)
    np.testing.assert_allclose(info, want_j.T @ want_j, rtol=1e-12)
    # correlated residuals (the misfit of a wrong start) give a factor well above 1
    assert lrf == pytest.approx(long_run_factor(want_r), rel=1e-10)
    assert lrf > 2.0
    assert compiled_lrf(want_r, 3) == pytest.approx(long_run_factor(want_r, 3), rel=1e-10)
    assert floor == pytest.approx(float(np.sum((1e-9 * np.max(np.abs(y)) / s) ** 2)),
                                  rel=1e-12)
    white = np.random.default_rng(seed).standard_normal(200)
    assert compiled_lrf(white) == pytest.approx(long_run_factor(white), rel=1e-10)
    assert compiled_lrf(np.zeros(20)) == 1.0 == long_run_factor(np.zeros(20))
    assert compiled_lrf(np.ones(5)) == 1.0 == long_run_factor(np.ones(5))
