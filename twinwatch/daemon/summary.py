"""The run's summary as text: what ``twinwatch run`` prints when it ends (docs/getting-started.md,
"What `twinwatch run` prints"), made from what a machine's daemon kept.

The service host (:class:`~twinwatch.daemon.host.Host`) puts these lines into its
:class:`~twinwatch.daemon.service.RunSummary`. Every function here returns lines and writes
nothing.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from twinwatch.drivers.base import source_problem_lines

if TYPE_CHECKING:
    from twinwatch.config.schema import TwinwatchConfig
    from twinwatch.daemon.pipeline import WindowDigest
    from twinwatch.daemon.runner import Daemon
    from twinwatch.twin.health import HealthMessage, ParameterHealth

__all__ = ["EPOCH_PLANT_TIME", "alarm_lines", "failed_line", "machine_lines", "new_run_line",
           "plant_moment", "plant_span", "resumed_line", "window_lines"]


def resumed_line(daemon: Daemon) -> str:
    """One line saying what was resumed from the state database, and how not to."""
    r = daemon.resumed
    assert r is not None
    what = []
    if daemon.restored is not None:
        where = (f" of window {r['window']} (t = {r['t_end']:.2f} s)"
                 if r.get("window") is not None and r.get("t_end") is not None else "")
        values = ", ".join(f"{k} = {v:.6g}" for k, v in r["trusted"].items())
        what.append(f"the twin{where} ({values}"
                    + (f"; {r['terms']} meta-model term(s)" if r["terms"] else "") + ")")
    if r["alarms"]:
        what.append("alarm levels " + ", ".join(f"{k} {v}" for k, v in r["alarms"].items()))
    return (f"twinwatch: resumed from {r['path']}: {' and '.join(what) or 'the last state'}; "
            f"to start from the nameplate values instead: twinwatch run --fresh")


def new_run_line(daemon: Daemon) -> str:
    """One line saying that the stored run was not resumed, why, and how to."""
    r = daemon.new_run
    assert r is not None
    return (f"twinwatch: a new run ({daemon.run_id}): {r['reason']}, so the twin starts from "
            f"the nameplate values and the alarms from normal; {r['path']} keeps the earlier "
            f"runs (the last: {r['run']}); to continue the last run instead: twinwatch run "
            f"--resume")


def machine_lines(cfg: TwinwatchConfig, daemon: Daemon) -> list[str]:
    """A machine's summary block, ending with why the run's exit status is 74 or 75 when it
    is."""
    c = daemon.counters()
    causes = ", ".join(f"{n} {k.replace('_', ' ')}" for k, n in daemon.ring.causes.items()
                       if n)
    lines = [f"twinwatch: {c['windows_estimated']} windows estimated, "
             f"{c['overruns']} overruns, {c['windows_abandoned']} windows abandoned "
             f"({causes or 'gaps/bad samples'}), {c['numeric_failures']} numeric failures "
             f"(run {daemon.run_id})"]
    lines += _source_lines(cfg, daemon)
    last = daemon.latest_health
    if last is not None:
        digests = daemon.window_digests
        lines += [*window_lines(last), *_trend_lines(last), *alarm_lines(last),
                  *_diagnosis_lines(last), *_structure_lines(last),
                  *_check_lines(last, digests), *_timing_lines(cfg, digests),
                  *_wait_lines(daemon),
                  *daemon.summary()]  # where each output wrote, what it lost
    if daemon.lost():
        lines.append("twinwatch: estimated windows were lost: exit status 74")
    elif daemon.mostly_failed():
        lines.append(f"twinwatch: {failed_line(daemon)}: exit status 75")
    return lines


def failed_line(daemon: Daemon) -> str:
    """Why the run counts as failed: windows failed against estimated, by cause."""
    causes = {k: n for k, n in daemon.ring.causes.items() if n}
    if daemon.numeric_failures:
        causes["numeric failure"] = daemon.numeric_failures
    what = ", ".join(f"{n} {k.replace('_', ' ')}" for k, n in causes.items())
    return (f"{daemon.windows_failed()} windows failed ({what}) and "
            f"{daemon.windows_estimated} were estimated")


EPOCH_PLANT_TIME = 1e9
"""A plant time from this many seconds on is a wall clock, seconds since the epoch (a CAN log's
or a bus adapter's frame stamps, ``time_source = "frame"``): the summary shows it as a UTC
clock time. A plant's own clock starts near 0 and stays far below it (1e9 s is 31.7 years)."""


def _utc(t: float, fmt: str) -> str:
    from datetime import UTC, datetime

    stamp = datetime.fromtimestamp(t, UTC)
    return stamp.strftime(fmt) + (f".{int(stamp.microsecond / 1e4):02d}" if "%S" in fmt else "")


def plant_span(t_start: float, t_end: float) -> str:
    """A window's plant time for a person: ``1198.00-1199.99 s``, or, for a source stamped by
    a wall clock (see :data:`EPOCH_PLANT_TIME`), ``2026-11-21 10:00:58.00-10:01:00.00 UTC``."""
    if abs(t_start) < EPOCH_PLANT_TIME:
        return f"{t_start:.2f}-{t_end:.2f} s"
    same_day = _utc(t_start, "%Y-%m-%d") == _utc(t_end, "%Y-%m-%d")
    end = _utc(t_end, "%H:%M:%S" if same_day else "%Y-%m-%d %H:%M:%S")
    return f"{_utc(t_start, '%Y-%m-%d %H:%M:%S')}-{end} UTC"


def plant_moment(t: float) -> str:
    """A moment in plant time for a person: ``plant time 1090 s``, or ``2026-11-21 10:00:58 UTC``
    for a source stamped by a wall clock (see :data:`EPOCH_PLANT_TIME`)."""
    if abs(t) < EPOCH_PLANT_TIME:
        return f"plant time {t:.0f} s"
    from datetime import UTC, datetime

    return datetime.fromtimestamp(t, UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


def window_lines(last: HealthMessage) -> list[str]:
    """The last window and each parameter: value, deviation, status."""
    width = max([3, *(len(n) for n in last.parameters)])
    return [f"last window {last.window} [{plant_span(last.t_start, last.t_end)}], "
            f"nRMSE {last.nrmse or float('nan'):.2e}, estimated in "
            f"{last.elapsed_s * 1e3:.0f} ms:",
            *(f"  {name:<{width}} = {_value(p.value)} {p.unit:<10} "
              f"({'n/a' if p.deviation_pct is None else f'{p.deviation_pct:+.2f}'} % vs nominal "
              f"{p.nominal:g}) {_status(p)}"
              for name, p in last.parameters.items())]


def _trend_lines(last: HealthMessage) -> list[str]:
    """One line per parameter with a trend: where it is going, and when it crosses its alarm
    rule's thresholds."""
    from twinwatch.twin.health import trend_line

    lines = [line for name, p in last.parameters.items() if (line := trend_line(name, p))]
    return ["trend and remaining useful life (95 % intervals):", *(f"  {x}" for x in lines)] \
        if lines else []


def _diagnosis_lines(last: HealthMessage) -> list[str]:
    """The diagnosis: the most probable fault, its probability and the action."""
    from twinwatch.twin.health import developing_line, diagnosis_line

    line = diagnosis_line(last.diagnosis)
    developing = developing_line(last.diagnosis, last.parameters)
    return [x for x in (line, developing and f"  {developing}") if x]


UNINFORMED_PCT = 50.0
"""A fused relative standard error [%, 1 sigma] from which a held parameter is said not to be
determined across the windows: the fusion's default prior on the nameplate value
(``[estimation.fusion] initial_std`` 0.5), which a parameter no window informed keeps, or
exceeds as its level wanders."""


def _value(value: float | None) -> str:
    return f"{value:<11.6g}" if value is not None else f"{'n/a':<11}"


def _status(p: ParameterHealth) -> str:
    """Why the parameter has its value (estimated, fused, held: the reason), with the fused
    evidence of an estimated or held one."""
    text = {"estimated": "estimated",
            "fused": f"fused over the windows (this one alone: {p.reason})",
            "held": f"held: {p.reason}"}.get(
        p.status, p.reason or p.status)  # tied, fixed: the reason says to what
    fused = p.fused
    if fused is not None and fused.value is not None and p.status in ("estimated", "held"):
        rel = fused.rel_std_pct if fused.rel_std_pct is not None else math.nan
        if p.status == "held" and rel >= UNINFORMED_PCT:
            text += (f"; not determined across the windows either: fused +- {_pct(2 * rel)} % "
                     "(2 sigma), no narrower than its nameplate prior")
        else:
            text += f"; fused {fused.value:.6g} +- {_pct(2 * rel)} % (2 sigma)"
    return text


def _pct(x: float) -> str:
    """A relative error [%] to two significant digits, without an exponent from 100 up."""
    two = f"{x:.2g}"
    return f"{float(two):.0f}" if "e+" in two else two


def alarm_lines(last: HealthMessage) -> list[str]:
    raised = [f"{k} {a.level}"
              + (f" (raised at {plant_moment(a.since_t)})" if a.since_t is not None else "")
              + (f", last {a.deviation_pct:+.2f} % vs nominal" if a.deviation_pct is not None
                 else "") for k, a in last.alarms.items() if a.level != "normal"]
    raised += [f"{k} RUL {a.rul.level}"
               + (f" (raised at {plant_moment(a.rul.since_t)})" if a.rul.since_t is not None
                  else "") for k, a in last.alarms.items()
               if a.rul is not None and a.rul.level != "normal"]
    if not raised:
        return []
    return ["alarms: " + "; ".join(raised)]


def _structure_lines(last: HealthMessage) -> list[str]:
    """The twin's structure DT'' when discovery is on: its terms, the worst errors."""
    if not last.discovery.enabled:
        return []
    terms = last.terms
    lines = [f"twin structure (DT''): {len(terms)} meta-model term(s){_verdict(last)}",
             *(f"  {term.equation}  [{term.meaning}]" for term in terms)]
    if terms:
        fits = (("DT'", last.residual.dt_prime), ("DT''", last.residual.dt_second))
        worst = {k: fit.max_abs for k, fit in fits if fit is not None and fit.max_abs}
        lines.append("  worst error in the last window: " + "; ".join(
            f"{k} " + ", ".join(f"{o} {e:.3g}" for o, e in w.items() if e is not None)
            for k, w in worst.items()))
    return lines


def _verdict(last: HealthMessage) -> str:
    """What the discovery concluded in the last window."""
    if last.terms:
        return ":"
    if last.discovery.too_large or (last.model_check is not None
                                    and not last.model_check.passed):
        return (": none kept, yet the residual is too large for the physical model "
                "(no candidate meta-model describes what it misses)")
    return ": the physical model explains the data"


def _check_lines(last: HealthMessage, digests: list[WindowDigest]) -> list[str]:
    """How many windows passed the model check, and why the last failing one did not."""
    checks = [d.model_check_passed for d in digests if d.model_check_passed is not None]
    if not checks:
        return []
    passed = sum(checks)
    reasons = last.model_check.reasons if last.model_check is not None else []
    return [f"model check: passed in {passed} of {len(checks)} windows"
            + (f"; failing windows are not trusted and their intervals widened (last: "
               f"{reasons[0]})" if passed < len(checks) and reasons else "")]


def _median_max(seconds: list[float]) -> str:
    """``median 12 ms, max 40 ms`` of ``seconds`` (not empty)."""
    x = sorted(seconds)
    return f"median {x[len(x) // 2] * 1e3:.0f} ms, max {x[-1] * 1e3:.0f} ms"


def _timing_lines(cfg: TwinwatchConfig, digests: list[WindowDigest]) -> list[str]:
    times = [d.elapsed_s for d in digests]
    return [f"estimation time per window: {_median_max(times)} (window length "
            f"{cfg.acquisition.window * cfg.acquisition.sample_period:g} s)"] if times else []


def _wait_lines(daemon: Daemon) -> list[str]:
    """How long the windows waited for the worker (queued, and in a gateway for an
    estimation slot) before their estimation started."""
    waits = list(daemon.queue_waits)
    lines = [f"queue wait per window: {_median_max(waits)}"] if waits else []
    if daemon.dropped_at_stop:
        lines.append(f"{daemon.dropped_at_stop} windows queued at the stop were dropped: the "
                     f"estimation did not reach them within [acquisition] shutdown_timeout "
                     f"({daemon.config.acquisition.shutdown_timeout:g} s)")
    return lines


def _source_lines(cfg: TwinwatchConfig, daemon: Daemon) -> list[str]:
    """What the source delivered and lost, by reason, with the cause when no window could be
    completed."""
    ring = daemon.ring
    lost = sum(ring.lost.values())
    window = cfg.acquisition.window
    lines = []
    jittered = [d for d in daemon.window_digests if d.jitter_max_us]
    if jittered:
        rms = max(x.jitter_rms_us or 0.0 for x in jittered)
        peak = max(x.jitter_max_us or 0.0 for x in jittered)
        lines.append(f"source: time stamps jitter around the {cfg.acquisition.sample_period:g} s "
                     f"grid the samples were placed on in {len(jittered)} windows: RMS up to "
                     f"{rms:.3g} us, max {peak:.3g} us")
    waiting, silent, faults = daemon.acquisition.source_state()
    if waiting:
        lines.append(f"source: waiting for {waiting}")
    lines.extend(f"source: {line}" for line in source_problem_lines(silent, faults))
    if lost:
        reasons = ", ".join(f"{n} {reason}" for reason, n in ring.lost.most_common())
        lines.append(f"source: {ring.samples} samples received, {lost} not in any window "
                     f"({reasons})")
    if ring.missing:
        lines.append(f"source: {ring.missing} samples missing in {ring.windows_filled} windows "
                     f"(a lost or malformed frame, a missed poll), each slot holding the "
                     f"previous sample's values (acquisition.max_missing)")
    if daemon.latest_health is not None or daemon.windows_estimated:
        return lines
    if ring.samples == 0:
        lines.append(f"no window was completed: the {cfg.driver.type} driver delivered no "
                     "sample (see the log for why)")
    elif not lost:
        lines.append(f"no window was completed: the source delivered {ring.samples} samples, "
                     f"fewer than one window ({window})")
    elif ring.windows == 0:
        reason, n = ring.lost.most_common(1)[0]
        cause = f"{n} of {ring.samples} samples lost to {reason}"
        if reason.startswith("sample without channel"):
            ch = reason.split("channel ", 1)[1]
            cause = f"every sample lacks channel {ch}" if n == ring.samples else cause
            cause += f": map {ch} in [driver]"
            if ch == "'setpoint'" and getattr(daemon.model, "structure", None) == "closed_loop":
                cause += ' or use machine.options.structure = "open_loop"'
        elif reason.startswith("NaN or inf"):
            cause += ": check the mapping (scale, units) and the sensor"
        elif "time stamp" in reason:
            cause += (f": the time stamps do not step by acquisition.sample_period "
                      f"({cfg.acquisition.sample_period:g} s)")
        lines.append(f"no window was completed: {cause}")
    else:
        lines.append("no window was estimated (see the log for why)")
    return lines


