"""``twinwatch explain``: the chain from the last windows' data to the decision, for a person.

From the stored health messages of a machine (the state database): the fit of the last
windows (RMSE, nRMSE, model check, DT' against DT''), the parameters with their intervals and
status, the meta-model terms with their parameters' standard errors, the trend and remaining
useful life, and the ranked faults with the evidence for and against each.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import Any

from twinwatch.twin.health import (
    HealthMessage,
    HealthView,
    check_function_line,
    developing_line,
    diagnosis_line,
    read_health,
    trend_line,
)

__all__ = ["explain_lines", "read_windows"]


def read_windows(db: Path, machine: str, count: int) -> list[HealthView]:
    """The machine's last ``count`` stored health messages (their typed view,
    :func:`~twinwatch.twin.health.read_health`: any schema), oldest first, read-only (the
    daemon may be writing the file: SQLite's read-only mode takes no lock it holds).

    Raises:
        FileNotFoundError: no such file. sqlite3.Error: not a twinwatch state database.
        ValueError: a stored message that is not JSON or not a health message's shape.
    """
    if not db.is_file():
        raise FileNotFoundError(f"{db}: no such state database")
    conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5.0)
    try:
        rows = conn.execute("SELECT doc FROM health WHERE machine = ? ORDER BY id DESC "
                            "LIMIT ?", (machine, int(count))).fetchall()
    finally:
        conn.close()
    return [read_health(r[0]) for r in reversed(rows)]


def _num(x: float | None, fmt: str = ".4g") -> str:
    return "n/a" if x is None else format(x, fmt)


def explain_lines(docs: list[HealthView]) -> list[str]:
    """The explanation of the last of ``docs`` (stored health messages, oldest first, as
    :func:`~twinwatch.twin.health.read_health` reads them), with the fit of each of them.
    Messages of a schema before 8 carry no diagnosis: said so."""
    if not docs:
        return ["no stored window for this machine"]
    last_doc = docs[-1]
    try:  # trend and diagnosis: from the message as the model reads it ...
        last: Any = HealthMessage.model_validate(last_doc.model_dump(by_alias=True,
                                                                     exclude_unset=True))
    except ValueError:
        # ... or, from a newer daemon (a field this version does not know), its typed view:
        # the same attribute names, unknown fields ignored
        last = last_doc
    return [f"{last_doc.machine} ({last_doc.model}), run {last_doc.run}, schema "
            f"{last_doc.schema_}: the last {len(docs)} windows", "",
            *_fit_lines(docs), "", *_parameter_lines(last_doc), "", *_term_lines(last_doc), "",
            *_trend_lines(last), "", *_diagnosis_lines(last)]


def _fit_lines(docs: list[HealthView]) -> list[str]:
    """1. the fit of each window, DT' against DT'', the stuck sensors."""
    lines = ["1. the fit (the twin against the measurements, per window):"]
    for d in docs:
        check = d.model_check
        verdict = ("" if check is None else
                   ", model check passed" if check.passed else
                   f", model check FAILED ({'; '.join(check.reasons or [])})")
        rmse = ", ".join(f"{k} {_num(v, '.3g')}" for k, v in (d.rmse or {}).items())
        n_terms = len(d.terms or [])
        trusted = "trusted" if d.trusted else "not trusted"
        lines.append(f"   window {d.window} [{d.t_start or 0:.1f}-"
                     f"{d.t_end or 0:.1f} s]: RMSE {rmse}; nRMSE "
                     f"{_num(d.nrmse, '.2e')}, {trusted}{verdict}"
                     + (f", {n_terms} term{'s' if n_terms > 1 else ''}" if n_terms else ""))
    last_doc = docs[-1]
    res = last_doc.residual
    if res is not None and res.dt_second:
        before = _num(res.dt_prime.nrmse if res.dt_prime else None, ".2e")
        after = _num(res.dt_second.nrmse, ".2e")
        lines.append(f"   DT' (physical twin alone) nRMSE {before} -> DT'' (with its terms) "
                     f"{after}")
    for sensor in last_doc.sensors or []:
        lines.append(f"   sensor {sensor.channel} {sensor.kind} at "
                     f"{_num(sensor.value)} for {_num(sensor.duration_s, '.1f')} "
                     f"s: the window's estimates are suspect")
    return lines


def _parameter_lines(last_doc: HealthView) -> list[str]:
    """2. the parameters of the last window: this window's estimate with its 2-sigma
    interval (the one the diagnosis reads) and, when fused, the evidence of every window."""
    lines = ["2. the parameters (the last window; 2-sigma intervals of this window's estimate, "
             "and of the fused evidence):"]
    for name, p in (last_doc.parameters or {}).items():
        status = p.status
        if status in ("tied", "fixed"):
            lines.append(f"   {name:<8} {p.reason or status}")
            continue
        value, rel = p.value, p.rel_std_pct
        band = (f" +/- {_num(2 * rel * abs(value) / 100.0, '.3g')} (+/- {2 * rel:.2g} %)"
                if value is not None and rel is not None else "")
        fused = p.fused
        fz = (f"; fused {_num(fused.value, '.6g')} +/- {2 * fused.rel_std_pct:.2g} %"
              if fused is not None and fused.value is not None
              and fused.rel_std_pct is not None else "")
        dev = p.deviation_pct
        lines.append(f"   {name:<8} {_num(value, '.6g')} {p.unit}{band}, "
                     f"{_num(dev, '+.2f')} % vs nameplate {p.nominal:g}, {status}"
                     + (f" ({p.reason})" if p.reason else "") + fz)
    return lines


def _term_lines(last_doc: HealthView) -> list[str]:
    """3. the meta-model terms with their parameters' intervals and meaning."""
    terms = last_doc.terms or []
    lines = ["3. the meta-model terms (what the physical twin lacks):"
             if terms else "3. no meta-model term: the physical twin explains the data"]
    for t in terms:
        params = ", ".join(
            f"{k} = {v:.4g}" + (f" +/- {2 * s:.2g}" if (s := (t.params_std or {})
                                                         .get(k)) is not None else "")
            for k, v in (t.params or {}).items())
        lines.append(f"   {t.equation}  (since window {t.since_window}, "
                     f"significance {_num(t.significance, '.1f')}; {params})")
        lines.append(f"     {t.meaning}")
    return lines


def _trend_lines(last: Any) -> list[str]:
    """4. each parameter's trend and remaining useful life."""
    trends = [line for name, p in (last.parameters or {}).items()
              if (line := trend_line(name, p))]
    return [("4. trend and remaining useful life (95 % intervals):" if trends
             else "4. no trend (prognostics off, or too little evidence)"),
            *[f"   {x}" for x in trends]]


def _diagnosis_lines(last: Any) -> list[str]:
    """5. the diagnosis: the check function, the ranked faults with the evidence for and
    against each, what no fault explains, why plausible faults were ruled out, the decision."""
    diag = last.diagnosis
    if diag is None:
        return ["5. no diagnosis in the stored messages (schema before 8, or "
                "[diagnosis] enabled = false)"]
    lines = [f"5. the diagnosis ({diag.library}; {diag.evidence} evidence variables; "
             f"no fault {diag.no_fault:.3f}, unknown fault {diag.unknown:.3f}"
             + (f"; shaft speed {diag.shaft_speed:.3g} rad/s" if diag.shaft_speed else "")
             + "):"]
    if diag.status == "check_function":
        lines.append(f"   {check_function_line(diag, label='CHECK FUNCTION')}; the ranking "
                     f"below rests on the last windows the twin described")
    for i, f in enumerate(diag.faults, 1):
        lines.append(f"   {i}. {f.id} ({f.component}): {f.probability:.3f}, urgency {f.urgency}")
        if i == 1 or f.probability >= 0.05:
            lines += [f"      + {s}" for s in f.evidence_for]
            lines += [f"      - {s}" for s in f.evidence_against]
            lines.append(f"      action: {f.action}")
            lines.append(f"      source: {f.source}")
    for eq in diag.unknown_terms:
        lines.append(f"   no fault mode explains: {eq}")
    for text in diag.unexplained or []:
        lines.append(f"   no fault mode explains: {text}")
    for text in diag.ruled_out or []:
        lines.append(f"   {text}")
    for text in getattr(diag, "unobserved", None) or []:
        lines.append(f"   {text}")
    lines.append("")
    lines.append(diagnosis_line(diag) or "")
    developing = developing_line(diag, last.parameters or {})
    if developing:
        lines.append(developing)
    return lines
