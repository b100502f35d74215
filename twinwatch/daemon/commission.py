"""``twinwatch identify``: read a whole recording through the configured driver, identify the
baseline on its training range (:mod:`~twinwatch.twin.estimation.identify`), score it on the
validation range, record both in a Rerun file and hand back the ``[machine.parameters]`` block.

Any driver works: a file (CSV, .mat), a CAN log, the simulated plants, or a live bus for
``duration`` seconds. Samples that lack a channel the twin needs or hold NaN/inf are counted
and left out; a range that the source interrupted (a time step above ``max_gap`` sample
periods) is refused with the time of the gap, since one free-run simulation cannot cross it.
"""

from __future__ import annotations

import logging
import math
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from twinwatch._lazy import lazy_module
from twinwatch.drivers import EndOfStream, create_driver
from twinwatch.errors import CommissionError
from twinwatch.twin.estimation.identify import Identification, identify
from twinwatch.twin.model import WindowData
from twinwatch.twin.models import create_model

if TYPE_CHECKING:
    import rerun as rr

    from twinwatch.config.schema import TwinwatchConfig
else:
    rr = lazy_module("rerun")

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
                if duration is not None and t0 is not None:
                    continue
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


def commission(cfg: TwinwatchConfig, base_dir: Path, *, duration: float | None = None,
               record: Path | None = None) -> tuple[Identification, Recording]:
    """Identify the baseline of ``cfg``'s machine from its source (see the module docstring).

    Args:
        cfg: the validated configuration (``[identify]`` says the ranges and weights).
        base_dir: directory relative paths of the configuration resolve against.
        duration: stop reading after this many seconds of source time (a live bus).
        record: write the training and validation fits to this Rerun file.

    Raises:
        CommissionError, twinwatch.drivers.DriverError: as :func:`read_recording`, or a range
            that cannot be identified from.
    """
    data = read_recording(cfg, base_dir, duration)
    gap = cfg.acquisition.max_gap
    train = data.stretch(cfg.identify.train, gap, "training")
    validation = data.stretch(cfg.identify.validate_, gap, "validation")
    model = create_model(cfg.machine.model, cfg.machine.options)
    try:
        result = identify(model, cfg.estimation, cfg.identify, train, validation,
                          cfg.machine.parameters)
    except ValueError as exc:
        raise CommissionError(str(exc)) from exc
    if record is not None:
        record_fit(record, cfg.machine.name, result)
    return result, data


def record_fit(path: Path, machine: str, result: Identification) -> None:
    """Write measured, identified-twin and residual series of both ranges to a Rerun file
    (entities ``identify/<range>/<output>/{measured,twin,residual}``, timeline ``time``)."""
    rec = rr.RecordingStream("twinwatch-identify", recording_id=uuid.uuid4())
    rec.save(str(path))
    rec.send_recording_name(f"{machine} identification")
    for what, score in (("training", result.train), ("validation", result.validation)):
        index = [rr.TimeColumn("time", duration=score.t)]
        for j, name in enumerate(score.fit_pct):
            base = f"identify/{what}/{rr.escape_entity_path_part(name)}"
            for kind, series in (("measured", score.measured[:, j]),
                                 ("twin", score.simulated[:, j]),
                                 ("residual", score.measured[:, j] - score.simulated[:, j])):
                rec.send_columns(f"{base}/{kind}", indexes=index,
                                 columns=rr.Scalars.columns(scalars=series))
    rec.log("identify/report", rr.TextDocument(report(result), media_type=rr.MediaType.MARKDOWN),
            static=True)
    rec.flush(timeout_sec=10.0)
    rec.disconnect()


def report(result: Identification) -> str:
    """The identification as text: every parameter with its interval, fit % per output on
    both ranges, the model check of each."""
    lines = ["parameter    value          interval (1 sigma)"]
    for name in result.estimated:
        lines.append(f"{name:<12} {result.values[name]:<14.6g} +- "
                     f"{100 * result.rel_std[name]:.3g} %   bounds "
                     f"[{result.bounds[name][0]:.4g}, {result.bounds[name][1]:.4g}]")
    lines.append("fit % (100 (1 - |y - y_hat| / |y - mean(y)|)):")
    for name in result.train.fit_pct:
        lines.append(f"  {name:<10} training {result.train.fit_pct[name]:6.1f}   "
                     f"validation {result.validation.fit_pct[name]:6.1f}")
    for what, score in (("training", result.train), ("validation", result.validation)):
        check = score.check
        lines.append(f"model check ({what}): " + ("passed" if check.passed else
                                                  "failed: " + "; ".join(check.reasons)))
    if len(result.starts) > 1:
        lines.append(f"{len(result.starts)} starts reached a training nRMSE of "
                     + ", ".join(f"{c:.5g}" for c in result.starts)
                     + f"; kept {result.nrmse:.5g}")
    lines.append(f"{result.evaluations} twin simulations in {result.elapsed_s:.1f} s")
    return "\n".join(lines)


def summary(result: Identification) -> dict[str, Any]:
    """The figures as plain data (for tests and scripts)."""
    return {"values": result.values, "rel_std": result.rel_std,
            "fit_train": result.train.fit_pct, "fit_validation": result.validation.fit_pct}


__all__ = ["CommissionError", "Recording", "commission", "read_recording", "record_fit",
           "report", "summary"]
