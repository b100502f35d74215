"""The twin model contract: a white-box physics model that simulates a whole swarm at once.

Paper Section 3.1 (the DT step): the twin is a parameterised, modular white-box model. A machine
plugs into twinwatch by providing one :class:`TwinModel` subclass (registered in
:mod:`twinwatch.twin.models`) and a configuration; the daemon never needs to change.

Conventions (after python-control's ``nlsys``): a model names its parameters (with SI units and
nominal values), its input channels, its output channels and its options; :meth:`TwinModel.simulate`
is the fast, vectorised path that the estimator calls with a whole swarm.
"""

from __future__ import annotations

import abc
import dataclasses
import math
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numba import njit
from numpy.typing import NDArray

from twinwatch import _kernels

# the processes on one kernel cache take turns compiling (a gateway's workers on a cold cache)
_kernels.share_compilation()

FloatArray = NDArray[np.float64]
#: Index and count arrays (the compiled kernels' event plans, state positions).
IntArray = NDArray[np.int64]
#: Masks (the compiled kernels' event flags).
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True, slots=True)
class ParameterSpec:
    """A physical parameter of a twin model.

    Attributes:
        name: standard symbol (``Ra``, ``La``, ``J``, ``Ke``, ``Kt``, ``D``, ...).
        unit: SI unit as text (``ohm``, ``H``, ``kg m^2``, ...).
        nominal: nameplate value used when nothing else is configured.
        description: what it is, in words.
        meaning: what a drift of it usually means for the machine (for the health report).
    """

    name: str
    unit: str
    nominal: float
    description: str
    meaning: str = ""


@dataclass(slots=True)
class WindowData:
    """One acquisition window, as the twin sees it.

    Attributes:
        t: sample times [s], shape (N,), strictly increasing, (nearly) uniform.
        channels: channel name -> samples, each of shape (N,), in SI units.
        index: window index (0, 1, ...) since the daemon started.
        stamp_jitter: the source's time stamps minus ``t`` [s], shape (N,), when the
            acquisition placed the samples on the nominal grid (``t`` uniform, the stamps
            jittered: :mod:`twinwatch.daemon.ringbuffer`); None when ``t`` are the stamps.
    """

    t: FloatArray
    channels: dict[str, FloatArray]
    index: int = 0
    stamp_jitter: FloatArray | None = None
    #: (the ``t`` it was computed from, the median sample period): a cache, read on every
    #: twin call.
    _period: tuple[Any, float] | None = field(default=None, repr=False, compare=False)

    @property
    def n(self) -> int:
        return int(self.t.shape[0])

    @property
    def sample_period(self) -> float:
        """Median sample period [s], computed once per ``t`` array."""
        cached = self._period
        if cached is not None and cached[0] is self.t:
            return cached[1]
        value = _median(np.diff(self.t)) if self.n > 1 else 0.0
        self._period = (self.t, value)
        return value

    def __getitem__(self, name: str) -> FloatArray:
        return self.channels[name]


def _median(x: FloatArray) -> float:
    """``float(np.median(x))`` of a 1-D float array (n >= 1): the middle of the partitioned
    values, the mean of the two middle ones for an even count, NaN if any is NaN; without
    ``np.median``'s dispatch (most of its cost on a window's stamps)."""
    k = x.size
    if np.isnan(x).any():
        return math.nan
    if k % 2:
        return float(np.partition(x, k // 2)[k // 2])
    part = np.partition(x, [k // 2 - 1, k // 2])
    return float(np.add.reduce(part[k // 2 - 1:k // 2 + 1]) / 2)


@dataclass(frozen=True, slots=True)
class OutputSpec:
    """An output of the twin compared with a measured channel.

    Attributes:
        name: channel name (``ia``, ``omega``, ...).
        unit: SI unit as text.
        scale: typical magnitude used to normalise residuals when a window's own RMS is
            smaller (a floor that keeps a near-zero signal from dominating the RMSE).
    """

    name: str
    unit: str
    scale: float


@dataclass(frozen=True, slots=True)
class AttachPoint:
    """A place in the twin's equations where a meta-model term can attach (paper Eq. 3).

    The specialist's configuration (``[discovery]``) picks attach points by :attr:`name`; the
    discovery fits meta-model terms there and the twin composes them (DT'' = DT + sum U_i).

    Attributes:
        name: the equation, as it reads in reports: ``d(omega)/dt`` for a state equation,
            ``p`` for an output (algebraic) equation.
        mode: ``additive``: the term's value, in :attr:`unit`, is added to the equation's
            right-hand side and held over each sample (the value passed for sample k drives the
            step k -> k+1); ``multiplicative``: the equation's value at sample k is multiplied
            by ``1 + U[k]`` (U dimensionless).
        unit: unit of an additive term (``rad/s^2``); ``1`` for a multiplicative one.
        quantity: what the equation governs, in words (``shaft speed``, ``pressure``): the
            interpretation says where the unknown component acts.
        scale: largest plausible magnitude of a term here, in :attr:`unit` (the discovery's
            default search bound; configurable per candidate).
    """

    name: str
    mode: Literal["additive", "multiplicative"]
    unit: str
    quantity: str
    scale: float = 1.0


@dataclass(frozen=True, slots=True)
class EstimationDefaults:
    """What a model estimates when the configuration does not say (``[estimation]`` keys
    ``estimate`` and ``tie`` left out).

    Attributes:
        estimate: parameters to estimate, in priority order (the first are kept when a window
            cannot determine them all).
        tie: dependent parameter -> the parameter it equals (``Kt = Ke`` in SI units).
    """

    estimate: tuple[str, ...]
    tie: Mapping[str, str] = field(default_factory=dict)


@dataclass
class TwinModel(abc.ABC):
    """Base class of every twin model.

    Subclasses define :attr:`parameters`, :attr:`inputs`, :attr:`outputs` and implement
    :meth:`simulate`.
    """

    parameters: tuple[ParameterSpec, ...] = field(init=False, default=())
    inputs: tuple[str, ...] = field(init=False, default=())
    outputs: tuple[OutputSpec, ...] = field(init=False, default=())
    attach_points: tuple[AttachPoint, ...] = field(init=False, default=())
    #: Outputs whose first sample sets the twin's initial state; :meth:`simulate` takes offsets
    #: to them (``initial``), which the estimator fits per window (a noisy first sample would
    #: otherwise leave a transient in every residual).
    initial_states: tuple[str, ...] = field(init=False, default=())
    #: Inputs set from outside the machine's loop (a closed loop's set-point, an open loop's
    #: command): the model validation tests the residual's independence from them. Default:
    #: every input.
    exogenous: tuple[str, ...] = field(init=False, default=())

    @property
    def parameter_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters)

    @property
    def output_names(self) -> tuple[str, ...]:
        return tuple(o.name for o in self.outputs)

    @property
    def estimation_defaults(self) -> EstimationDefaults:
        """What to estimate, and the ties, when the configuration does not say (default:
        every parameter, untied)."""
        return EstimationDefaults(self.parameter_names)

    def check_sample_period(self, sample_period: float) -> None:  # noqa: B027 - optional hook
        """Raise ValueError (saying why) if the twin cannot run at this sample period [s]
        (e.g. it is not a whole number of integration sub-steps). Default: any period."""

    def _check_choices(self) -> None:
        """ValueError naming an option whose value its ``Literal`` annotation does not admit."""
        hints = typing.get_type_hints(type(self))
        for f in dataclasses.fields(self):
            if f.init and typing.get_origin(hints[f.name]) is Literal:
                allowed = typing.get_args(hints[f.name])
                value = getattr(self, f.name)
                if value not in allowed:
                    raise ValueError(f"{f.name} must be one of {list(allowed)}, not {value!r}")

    def parameter(self, name: str) -> ParameterSpec:
        for p in self.parameters:
            if p.name == name:
                return p
        raise KeyError(f"unknown parameter {name!r}; the model has {list(self.parameter_names)}")

    def nominal_vector(self, values: Mapping[str, float] | None = None) -> FloatArray:
        """Full parameter vector (n_params,) in :attr:`parameters` order, nominal unless given."""
        values = values or {}
        return np.array([float(values.get(p.name, p.nominal)) for p in self.parameters])

    def attach_point(self, name: str) -> AttachPoint:
        for a in self.attach_points:
            if a.name == name:
                return a
        raise KeyError(f"unknown attach point {name!r}; the model offers "
                       f"{[a.name for a in self.attach_points]}")

    def required_channels(self) -> tuple[str, ...]:
        """Channels a window must hold: the inputs and the outputs."""
        return tuple(dict.fromkeys((*self.inputs, *self.output_names)))

    @abc.abstractmethod
    def simulate(self, theta: FloatArray, window: WindowData,
                 terms: Mapping[str, FloatArray] | None = None,
                 initial: FloatArray | None = None) -> FloatArray:
        """Simulate the window for every parameter vector of a swarm.

        Args:
            theta: full parameter vectors, shape (P, n_params), in :attr:`parameters` order.
            window: the measured window; the simulation starts from its first sample's
                measured state and is driven by its measured inputs.
            terms: meta-model terms composed into the twin (DT'', paper Eq. 3): attach-point
                name (one of :attr:`attach_points`) -> the summed terms' values at each sample,
                shape (N,) (the same for every particle) or (P, N). ``None`` or empty: the
                plain DT.
            initial: offsets added to the measured first sample of :attr:`initial_states`,
                shape (n_init,) or (P, n_init), in their units; None: none (models without
                :attr:`initial_states` ignore it).

        Returns:
            Simulated outputs, shape (P, N, n_outputs), in :attr:`outputs` order. Rows of
            parameter vectors that make the model blow up contain ``nan`` or ``inf``; they never
            raise.
        """

    def time_constants(self, values: Mapping[str, float]) -> dict[str, tuple[float, str]]:
        """Parameters that set a time constant of the twin on their own, with it.

        A dynamic faster than the sample period leaves almost nothing in the sampled outputs:
        sampled every ``T``, a pole at ``-1/tau`` becomes ``z = exp(-T/tau)`` (Astrom and
        Wittenmark, *Computer-Controlled Systems*, 3rd ed., Section 2.3), and with ``tau``
        below ``T`` both ``z`` and its sensitivity to ``tau`` are small. The estimator holds
        such a parameter as not observable at this sample rate
        (:mod:`twinwatch.twin.estimation.estimator`). Default: none.

        Args:
            values: every parameter -> its current value [SI] (the trusted values).

        Returns:
            parameter name -> (its time constant [s] at ``values``, how it is formed, e.g.
            ``"tau_e = La/Ra"``).
        """
        return {}

    def excitation(self, window: WindowData) -> dict[str, str]:
        """Parameters this window does not excite physically, with the reason.

        The estimator's identifiability gate judges what the data determine statistically;
        this hook adds the physics the data cannot show (with very clean data a damping
        coefficient is "determined" while the piston stands still). Default: every parameter
        is excited.

        Args:
            window: the measured window.

        Returns:
            parameter name -> reason (held, with this reason, at its last trusted value).
        """
        return {}

    def describe(self) -> str:
        """Human-readable summary: parameters, inputs, outputs."""
        lines = [f"{type(self).__name__}:"]
        lines.append("  inputs:  " + ", ".join(self.inputs))
        lines.append("  outputs: " + ", ".join(f"{o.name} [{o.unit}]" for o in self.outputs))
        lines.append("  parameters:")
        for p in self.parameters:
            lines.append(f"    {p.name:<8} = {p.nominal:<12g} {p.unit:<12} {p.description}")
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.describe()


class SubStepTwin(TwinModel):
    """A twin integrated at a fixed sub-step: its option ``sub_step`` [s]."""

    sub_step: float

    def n_sub(self, sample_period: float) -> int:
        """Number of sub-steps per sample; raises ValueError if not a whole number."""
        return sub_steps(sample_period, self.sub_step)

    def check_sample_period(self, sample_period: float) -> None:
        """The sample period must be a whole number of sub-steps (ValueError otherwise)."""
        self.n_sub(sample_period)


def sub_steps(sample_period: float, sub_step: float) -> int:
    """Number of integration sub-steps [-] in one sample.

    Args:
        sample_period: acquisition sample period [s].
        sub_step: the twin's integration step [s] (paper: 1e-4).

    Raises:
        ValueError: the sample period is not a whole multiple of the sub-step (to 1e-6
            relative); the message names both.
    """
    ratio = sample_period / sub_step
    n = int(round(ratio))
    if n < 1 or abs(ratio - n) > 1e-6 * max(1.0, ratio):
        raise ValueError(f"sample period {sample_period:g} s is not a whole multiple of the "
                         f"twin's sub-step {sub_step:g} s")
    return n


def as_rows(values: Any) -> FloatArray:
    """``np.atleast_2d(np.asarray(values, dtype=float))``: the same object when ``values`` is
    a float64 array of rows already (the twins' and the fit's every call), without numpy's
    two wrappers (a microsecond each, some fifty calls a window)."""
    if type(values) is np.ndarray and values.ndim == 2 and values.dtype == np.float64:
        return values
    out: FloatArray = np.atleast_2d(np.asarray(values, dtype=float))
    return out


def readonly(values: FloatArray) -> FloatArray:
    """``values`` as a C-contiguous float64 array that cannot be written (a view when it is
    one already; a copy otherwise): what the twins pass their compiled kernels, whose every
    mix of writable and read-only arrays numba would compile anew (seconds each on a cold
    cache)."""
    out = np.ascontiguousarray(values, dtype=float)
    if out.flags.writeable:
        out = out.view()
        out.flags.writeable = False
    return out


def term_array(values: FloatArray | float | None, p: int, n: int, name: str) -> FloatArray:
    """A meta-model term's values (paper Eq. 3) as a C-contiguous array for a compiled kernel.

    Args:
        values: None (no term: zeros), a scalar, (N,) shared by the swarm, or (P, N) one row
            per particle, in the attach point's unit.
        p: particles in the swarm.
        n: samples in the window.
        name: the attach point, for the error message.

    Returns:
        (1, N) or (P, N) float array.

    Raises:
        ValueError: any other shape (the message names the attach point and both shapes).
    """
    if values is None:
        return np.zeros((1, n))
    arr = np.asarray(values, dtype=float)
    if arr.ndim == 0:
        arr = np.full((1, n), float(arr))
    elif arr.ndim == 1:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != n or arr.shape[0] not in (1, p):
        raise ValueError(f"term {name!r} has shape {np.shape(values)}; expected ({n},) or "
                         f"({p}, {n})")
    return np.ascontiguousarray(arr)


def composite_zoh(a: FloatArray, b: FloatArray, n_sub: int) -> tuple[FloatArray, FloatArray]:
    """Compose ``n_sub`` steps of the linear map ``x' = A x + B u`` with ``u`` held.

    Returns ``Phi = A^n`` and ``Gamma = sum_{j<n} A^j B``, computed exactly (to rounding) by
    squaring the augmented matrix ``[[A, B], [0, I]]``. This is the exact zero-order-hold
    discretisation of the sub-stepped model, in about log2(n_sub) matrix products.

    Args:
        a: shape (P, n, n).
        b: shape (P, n, m).
        n_sub: number of sub-steps per sample (>= 1).

    Returns:
        (Phi, Gamma) with shapes (P, n, n) and (P, n, m).
    """
    p, n, _ = a.shape
    m = b.shape[2]
    aug = np.zeros((p, n + m, n + m))
    aug[:, :n, :n] = a
    aug[:, :n, n:] = b
    aug[:, n:, n:] = np.eye(m)
    powered = _matrix_power(aug, n_sub)
    return powered[:, :n, :n], powered[:, :n, n:]


def _matrix_power(a: FloatArray, n: int) -> FloatArray:
    """``np.linalg.matrix_power(a, n)`` for ``n >= 1``, the same products in the same order
    (the same numbers) through the ``np.matmul`` ufunc, without the wrapper's overhead."""
    if n <= 3:
        return np.linalg.matrix_power(a, n)
    mm = np.matmul
    z = a
    result: FloatArray | None = None
    while True:
        n, bit = divmod(n, 2)
        if bit:
            result = z if result is None else mm(result, z)
        if n == 0:
            break
        z = mm(z, z)
    assert result is not None  # n > 3 has a set bit
    return result


@njit(cache=True, nogil=True)
def _power_into(aug: FloatArray, n: int, out: FloatArray) -> None:  # pragma: no cover
    """``aug ** n`` (n >= 1) into ``out``: the products of :func:`_matrix_power` (and of
    ``np.linalg.matrix_power`` for n <= 3) in the same order through the same BLAS ``dgemm``,
    so the same numbers. Copied into ``out`` element by element (:func:`_copy_into`)."""
    if n == 1:
        _copy_into(aug, out)
        return
    if n == 2:
        _copy_into(np.dot(aug, aug), out)
        return
    if n == 3:
        _copy_into(np.dot(np.dot(aug, aug), aug), out)
        return
    z = aug.copy()
    result = np.empty_like(aug)
    have = False
    while True:
        bit = n % 2
        n //= 2
        if bit:
            if have:
                result = np.dot(result, z)
            else:
                result = z.copy()
                have = True
        if n == 0:
            break
        z = np.dot(z, z)
    _copy_into(result, out)


@njit(cache=True, nogil=True)
def _copy_into(src: FloatArray, out: FloatArray) -> None:  # pragma: no cover - compiled
    """``out[:] = src`` for two (n, m) arrays of the same shape, as a loop: numba's slice
    assignment compiles its shape-mismatch message (string formatting: seconds of a cold
    start) into every kernel that uses it."""
    for i in range(src.shape[0]):
        for j in range(src.shape[1]):
            out[i, j] = src[i, j]


@njit(cache=True, nogil=True)
def _zoh_propagate_kernel(a: FloatArray, b: FloatArray, n_sub: int, x: FloatArray,
                          drive: FloatArray, tl: FloatArray, f_w: FloatArray,
                          f_i: FloatArray) -> None:  # pragma: no cover - compiled
    """:func:`zoh_propagate`'s work for the twins whose inputs are ``u = [drive, Tload,
    f_omega, f_ia]``: per particle, the augmented matrix raised to ``n_sub``, then
    ``x[k+1] = Phi x[k] + Gamma u[k]`` (``x[:, 0]`` holds the initial states; ``f_w``,
    ``f_i``: (1 or P, N))."""
    p, nk, n = x.shape
    m = b.shape[2]
    shared = f_w.shape[0] == 1
    aug = np.zeros((n + m, n + m))
    powered = np.empty((n + m, n + m))
    u = np.empty(m)
    for q in range(p):
        aug[:] = 0.0
        for i in range(n):
            for j in range(n):
                aug[i, j] = a[q, i, j]
            for j in range(m):
                aug[i, n + j] = b[q, i, j]
        for j in range(m):
            aug[n + j, n + j] = 1.0
        _power_into(aug, n_sub, powered)
        qu = 0 if shared else q
        for k in range(nk - 1):
            u[0] = drive[k]
            u[1] = tl[k]
            u[2] = f_w[qu, k]
            u[3] = f_i[qu, k]
            for i in range(n):
                acc = 0.0
                for j in range(m):
                    acc += powered[i, n + j] * u[j]
                for j in range(n):
                    acc += powered[i, j] * x[q, k, j]
                x[q, k + 1, i] = acc


def zoh_propagate(a: FloatArray, b: FloatArray, n_sub: int, x0: FloatArray,
                  drive: FloatArray, tload: FloatArray, f_w: FloatArray,
                  f_i: FloatArray) -> FloatArray:
    """Run ``n_sub`` sub-steps of ``x' = A x + B u`` per sample with ``u`` held: the same
    numbers as :func:`composite_zoh` then the recursion ``x[k+1] = Gamma u[k] + Phi x[k]``
    (summed in that order), in one compiled call.

    Args:
        a: shape (P, n, n).
        b: shape (P, n, 4), the inputs ``[drive, Tload, f_omega, f_ia]``.
        n_sub: sub-steps per sample (>= 1).
        x0: initial states, shape (P, n).
        drive: the first input per sample, shape (N,) (set-point, Va or its increment).
        tload: the load torque per sample [N m], shape (N,).
        f_w, f_i: the meta-model terms per sample, shape (1 or P, N).

    Returns:
        States, shape (P, N, n), with ``x[:, 0] = x0``. Overflow gives inf/nan.

    Raises:
        ValueError: ``b`` has not 4 input columns, an input's length is not N, or a term has
            neither 1 nor P rows (the message gives the shapes).
    """
    p, n, _ = a.shape
    nk = drive.shape[0]
    if (b.shape[2] != 4 or tload.shape != (nk,) or f_w.shape != f_i.shape
            or f_w.shape[1] != nk or f_w.shape[0] not in (1, p)):
        raise ValueError(f"zoh_propagate: b {b.shape}, drive {drive.shape}, tload "
                         f"{tload.shape}, f_w {f_w.shape}, f_i {f_i.shape}: expected b "
                         f"({p}, {n}, 4), inputs ({nk},) and terms (1 or {p}, {nk})")
    x = np.empty((p, nk, n))
    x[:, 0] = x0
    _zoh_propagate_kernel(np.ascontiguousarray(a), np.ascontiguousarray(b), int(n_sub), x,
                          np.ascontiguousarray(drive, dtype=float),
                          np.ascontiguousarray(tload, dtype=float),
                          np.ascontiguousarray(f_w), np.ascontiguousarray(f_i))
    return x
