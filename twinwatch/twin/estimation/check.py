"""Stage 4, the model check: is the window's residual what a twin that describes the machine
leaves? (Ljung, System Identification, 2nd ed., ch. 16.6; MATLAB's ``resid``.)

Each output's residual must be white (Ljung-Box) and independent of the model's exogenous
inputs (:attr:`TwinModel.exogenous`: a closed loop's set-point, an open loop's command). Before
the tests, what a linear drift of the estimated parameters within the window explains is
removed (:func:`drift_residual`). An output fails only where its residual is material
(:func:`~twinwatch.twin.estimation.statistics.check_model`). A window that fails is published
with its reasons, does not update the trusted values or the fusion, and its standard errors
are multiplied by :attr:`ModelCheck.widen` (which usually holds the parameters at the gate).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from pydantic import Field, StrictFloat, StrictInt

from twinwatch._table import StrictTable
from twinwatch.twin.estimation.fit import (
    WindowFit,
    explained_dof,
    explained_rms,
    parameter_covariance,
)
from twinwatch.twin.estimation.problem import FitPoint, WindowProblem
from twinwatch.twin.estimation.statistics import ModelCheck, check_model, noise_level
from twinwatch.twin.model import FloatArray


class ValidationConfig(StrictTable):
    """Per-window model validation (table ``[estimation.validation]``; Ljung, System
    Identification, ch. 16): the residual of a twin that describes the machine is white and
    independent of the inputs."""

    enabled: bool = Field(True, description="check every window's residuals")
    alpha: StrictFloat = Field(0.01, gt=0, lt=0.5, description="level of the whiteness and "
                               "residual-input tests, and of the bound on the share of a "
                               "residual the estimates' uncertainty explains")
    lags: StrictInt = Field(20, ge=1, le=1000, description="lags of both tests (samples)")
    sensor_run: StrictInt = Field(
        50, ge=0, le=100_000, description="a measured output that repeats one value exactly "
        "for this many samples while the twin's moves is a frozen or saturated sensor: the "
        "window is not sound, its estimates suspect (0: off)")


def check_twin(fit: WindowFit, y: FloatArray, exogenous: Sequence[str],
               settings: ValidationConfig, model_error: float,
               explained: FloatArray | None = None, drift: FloatArray | None = None,
               explained_dof: FloatArray | None = None) -> ModelCheck:
    """Validate the twin on a window from its simulated outputs.

    Args:
        fit: the window's fit (measured outputs, their scales).
        y: simulated outputs (N, n_out).
        exogenous: the model's exogenous inputs (:attr:`TwinModel.exogenous`); those the
            window carries are tested against the residual.
        settings: the test level and lags (``[estimation.validation]``; the lags at most a
            quarter of the window).
        model_error: the normalised residual level below which structure is accepted model
            error.
        explained: per output (n_out,), the residual RMS the estimates' uncertainty explains.
        drift: the residual matrix (N-1, n_out) to test instead of ``y``'s, with what a drift
            of the estimated parameters within the window explains removed
            (:func:`drift_residual`).
        explained_dof: per output, the degrees of freedom of ``explained``'s square
            (:func:`~twinwatch.twin.estimation.fit.explained_dof`).

    Returns:
        The check (:func:`~twinwatch.twin.estimation.statistics.check_model`).
    """
    win = fit.window
    exog = [c for c in exogenous if c in win.channels]
    inputs = np.column_stack([win[c][1:] for c in exog]) if exog else None
    res = fit.error_matrix(y) if drift is None else drift
    return check_model(res, fit.names, inputs, alpha=settings.alpha,
                       lags=min(settings.lags, max(1, win.n // 4)),
                       floor=model_error, explained=explained, quanta=fit.quanta,
                       explained_dof=explained_dof)


def drift_residual(fit: WindowFit, r: FloatArray, jac: FloatArray) -> FloatArray | None:
    """The residual (N-1, n_out), normalised per output, with what a linear drift of the
    estimated parameters within the window explains removed.

    The paper's faults are slow degradations: a parameter that moves within the window
    leaves a smooth residual although the model is right. Its effect at sample k is about
    ``J_k (t_k - t_mid) rate`` (exact where the output follows the parameter without memory,
    as the hydraulic pressure follows D; close where the memory is short against the
    window); the rates come from linear least squares on the residual, and the model check
    tests what is left.

    Args:
        fit: the window's fit.
        r: (M,) normalised residuals at the estimate.
        jac: (M, n) their Jacobian with respect to the estimated ln-parameters.

    Returns:
        The residual matrix, or None without estimated parameters.
    """
    if jac.shape[1] == 0:
        return None
    n_out = fit.n_out
    t = fit.window.t[1:]
    tau = np.repeat((t - 0.5 * (t[0] + t[-1])) / max(float(t[-1] - t[0]), 1e-12), n_out)
    ramp = jac * tau[:, None]
    rates, *_ = np.linalg.lstsq(ramp, r, rcond=None)
    left = (r - ramp @ rates).reshape(-1, n_out)
    # back to the per-output normalisation of WindowFit.error_matrix (no weights, no 1/sqrt(M))
    out: FloatArray = left * math.sqrt(r.size) / np.where(fit.weights != 0, fit.weights, 1.0)
    return out


def model_check(problem: WindowProblem, point: FitPoint, y: FloatArray,
                exogenous: Sequence[str], settings: ValidationConfig, model_error: float
                ) -> ModelCheck:
    """The model check of the window's estimate.

    What the white noise alone does to the estimates, and so to a noise-free output's
    residual, is computed from the white-noise level of the residual (its own level would
    count model error as noise): the covariance of the admitted parameters and the initial
    state (:func:`~twinwatch.twin.estimation.fit.parameter_covariance` with those levels), and
    per output the residual RMS it explains and that RMS's spread (its square's degrees of
    freedom, :func:`~twinwatch.twin.estimation.fit.explained_dof`).

    Args:
        problem: the window's problem.
        point: the estimate the gate admitted: residuals (M,) and Jacobian (M, n_active), the
            initial state's columns last.
        y: the twin's outputs there (N, n_out).
        exogenous: the model's exogenous inputs (:attr:`TwinModel.exogenous`).
        settings: ``[estimation.validation]``.
        model_error: ``[estimation] model_error``.

    Returns:
        The check; :attr:`ModelCheck.widen` is the factor to multiply the window's standard
        errors by (1 when passed).
    """
    n_out = problem.n_out
    r, jac = point.r, point.jac
    white = noise_level(r.reshape(-1, n_out)) * math.sqrt(r.size)
    cov = parameter_covariance(jac, r, n_out, model_error, white)
    n_par = jac.shape[1] - problem.nuisance.size
    return check_twin(problem.fit, y, exogenous, settings, model_error,
                      explained_rms(jac, cov, n_out),
                      drift=drift_residual(problem.fit, r, jac[:, :n_par]),
                      explained_dof=explained_dof(jac, cov, n_out))
