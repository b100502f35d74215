"""``twinwatch identify``: read a whole recording through the configured driver, identify the
baseline on its training range (:mod:`~twinwatch.commissioning.identify`) for the configured
structure and every candidate ``[identify.candidates]`` lists, pick the winner, score it on the
validation range, record it in a Rerun file and hand back the ``[machine.parameters]`` block.

Any driver works: a file (CSV, .mat), a CAN log, the simulated plants, or a live bus for
``duration`` seconds. Samples that lack a channel the twin needs or hold NaN/inf are counted
and left out; a range that the source interrupted (a time step above ``max_gap`` sample
periods) is refused with the time of the gap, since one free-run simulation cannot cross it.

The report is :mod:`~twinwatch.commissioning.report` (text and Markdown); the Rerun file,
MATLAB's ``compare`` and ``resid``: :func:`~twinwatch.commissioning.record.record_fit`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from twinwatch.commissioning.identify import (
    Comparison,
    Identification,
    compare_structures,
    identify,
)
from twinwatch.commissioning.record import record_fit
from twinwatch.config.identify import AS_CONFIGURED, merge_options
from twinwatch.drivers import EndOfStream, create_driver
from twinwatch.errors import CommissionError
from twinwatch.twin.model import TwinModel, WindowData
from twinwatch.twin.models import create_model

if TYPE_CHECKING:
    from twinwatch.config.schema import TwinwatchConfig

logger = logging.getLogger(__name__)


@dataclass
class Recording:
    """A whole recording as arrays: times (N,), channel -> values (N,), and what was left out.

    Attributes:
        t: sample times [s].
        channels: twin channel -> values [SI].
        dropped: samples left out (a channel missing, NaN or inf).
        source: what was read, for the report.
    """

    t: np.ndarray
    channels: dict[str, np.ndarray]
    dropped: int
    source: str

    def stretch(self, frac: tuple[float, float], max_gap: float, what: str) -> WindowData:
        """The samples of a fraction range [start, end) of the recording as one window.

        Raises:
            CommissionError: fewer than 10 samples, or a gap inside (the time is named).
        """
        n = self.t.size
        a, b = int(round(frac[0] * n)), int(round(frac[1] * n))
        t = self.t[a:b]
        if t.size < 10:
            raise CommissionError(f"the {what} range {frac[0]:g}-{frac[1]:g} holds {t.size} "
                                  f"of the recording's {n} samples: too few")
        dt = np.diff(t)
        period = float(np.median(dt))
        bad = np.flatnonzero((dt > max_gap * period) | (dt <= 0))
        if bad.size:
            k = int(bad[0])
            raise CommissionError(
                f"the {what} range is interrupted at t = {t[k]:.3f} s (next sample "
                f"{t[k + 1]:.3f} s; sample period {period:g} s): choose [identify] ranges "
                "without a gap")
        return WindowData(t=t, channels={c: v[a:b] for c, v in self.channels.items()}, index=0)


@dataclass
class Commissioning:
    """What :func:`commission` found.

    Attributes:
        result: the winning structure's identification (the configured one when no
            candidates are listed).
        data: the recording read.
        comparison: every structure's identification and the ranking (None when
            ``[identify.candidates]`` is empty).
    """

    result: Identification
    data: Recording
    comparison: Comparison | None = None


def read_recording(cfg: TwinwatchConfig, base_dir: Path, duration: float | None = None
                   ) -> Recording:
    """Read every sample the configured driver delivers (to its end, or ``duration`` seconds
    of source time).

    Raises:
        CommissionError: the source ended before a single usable sample.
        twinwatch.drivers.DriverError: the driver could not be opened or failed.
    """
    model = create_model(cfg.machine.model, cfg.machine.options)
    need = model.required_channels()
    times: list[float] = []
    values: dict[str, list[float]] = {c: [] for c in need}
    dropped = 0
    t0: float | None = None
    driver = create_driver(cfg.driver, base_dir=base_dir)
    with driver:
        while True:
            try:
                sample = driver.read(timeout=1.0)
            except EndOfStream:
                break
            if sample is None:
                continue
            if t0 is None:
                t0 = sample.t
            if duration is not None and sample.t - t0 > duration:
                break
            row = [sample.values.get(c, math.nan) for c in need]
            if not all(math.isfinite(v) for v in row):
                dropped += 1
                continue
            times.append(sample.t)
            for c, v in zip(need, row, strict=True):
                values[c].append(v)
    if not times:
        raise CommissionError(f"the {cfg.driver.type} source delivered no sample with every "
                              f"channel the twin needs ({', '.join(need)})")
    if dropped:
        logger.warning("%d samples left out: a channel the twin needs was missing or not "
                       "finite", dropped)
    return Recording(t=np.asarray(times), channels={c: np.asarray(v) for c, v in values.items()},
                     dropped=dropped, source=f"the {cfg.driver.type} source of "
                     f"machine '{cfg.machine.name}'")


def _structures(cfg: TwinwatchConfig) -> list[tuple[str, dict[str, Any], TwinModel]]:
    """(name, options over [machine.options], model) of the configured structure and every
    candidate."""
    out: list[tuple[str, dict[str, Any], TwinModel]] = [
        (AS_CONFIGURED, {}, create_model(cfg.machine.model, cfg.machine.options))]
    for k, cand in enumerate(cfg.identify.candidates):
        try:
            model = create_model(cfg.machine.model,
                                 merge_options(cfg.machine.options, cand.options))
        except ValueError as exc:
            raise CommissionError(f"identify.candidates[{k}] ({cand.name}).options: {exc}"
                                  ) from exc
        out.append((cand.name, dict(cand.options), model))
    return out


def commission(cfg: TwinwatchConfig, base_dir: Path, *, duration: float | None = None,
               record: Path | None = None) -> Commissioning:
    """Identify the baseline of ``cfg``'s machine from its source (see the module docstring).

    Args:
        cfg: the validated configuration (``[identify]`` says the ranges, the weights, what to
            hold and the candidate structures).
        base_dir: directory relative paths of the configuration resolve against.
        duration: stop reading after this many seconds of source time (a live bus).
        record: write the fits, the residual tests and the tables to this Rerun file.

    Raises:
        CommissionError, twinwatch.drivers.DriverError: as :func:`read_recording`, or a range
            that cannot be identified from, or a candidate whose options the model refuses.
    """
    data = read_recording(cfg, base_dir, duration)
    gap = cfg.acquisition.max_gap
    train = data.stretch(cfg.identify.train, gap, "training")
    validation = data.stretch(cfg.identify.validate_, gap, "validation")
    results: list[Identification] = []
    first: dict[str, float] | None = None
    for name, options, model in _structures(cfg):
        table = cfg.identify.for_structure(model)
        params = {k: v for k, v in cfg.machine.parameters.items()
                  if k in model.parameter_names}
        try:
            result = identify(model, cfg.estimation, table, train, validation, params,
                              start=first, structure=name, options=options)
        except ValueError as exc:
            raise CommissionError(f"{name}: {exc}" if cfg.identify.candidates
                                  else str(exc)) from exc
        if first is None and result.full is not None:
            first = result.full.values  # a warm start for the candidates
        results.append(result)
    comparison = compare_structures(results) if len(results) > 1 else None
    best = comparison.best if comparison is not None else results[0]
    if record is not None:
        record_fit(record, cfg.machine.name, best, comparison)
    return Commissioning(best, data, comparison)


__all__ = ["CommissionError", "Commissioning", "Recording", "commission", "read_recording"]
