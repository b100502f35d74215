"""What the recording says in words: the diagnosis, the parameters' table, the model document,
the alarm events' and the log's rows, the parts an alarm rule names (markdown).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from twinwatch.sinks.rerun.projection import rul_short
from twinwatch.sinks.rerun.style import RANK, as_number, as_text, clock, fmt, rr

if TYPE_CHECKING:
    from twinwatch.twin.health import AlarmView, DiagnosisView, HealthView, ParameterView


def diagnosis_lines(d: DiagnosisView | None, parameters: Any = None) -> list[str]:
    """The diagnosis as markdown lines (none without one): the outcome, the first fault's
    action and its evidence for and against, the next faults with their probabilities; with
    no fault yet, what is developing (:func:`~twinwatch.twin.health.developing_line`)."""
    if d is None:
        return []
    faults = d.faults or []
    status = d.status
    if status == "fault" and faults:
        lines = _fault_lines(d, faults[0])
    elif status == "check_function":
        since = d.check_function_since
        lines = ["**CHECK FUNCTION: the twin does not describe this machine**"
                 + (f" since {fmt(since, '.0f')} s" if since is not None else "")
                 + f" ({d.check_failed or 'its model check failing'}): its "
                 "estimates are held and no fault is named; check the sensors and the model  "]
    elif status == "unknown":
        lines = [f"**Diagnosis: a fault the library does not know** (probability "
                 f"{fmt(d.unknown, '.2f')}): " + "; ".join(
                     [f"`{t}`" for t in d.unknown_terms or []]
                     + list(d.unexplained or [])) + "  "]
    else:
        lines = [f"**Diagnosis: no fault** (probability {fmt(d.no_fault, '.2f')})"]
        from twinwatch.twin.health import developing_line

        developing = developing_line(d, parameters or {})
        if developing:
            lines[0] += "  "
            lines.append(f"*{developing}*")
    others = [f"{f.id} {fmt(f.probability, '.2f')}"
              for f in faults[1 if status == "fault" else 0:4]]
    if others:
        lines.append("next: " + ", ".join(others) + "  ")
    if status != "fault":  # no part named: why the plausible ones were ruled out, short
        lines += [f"*{x.split(' (expects ')[0]}*  " for x in (d.ruled_out or [])[:2]]
        # and what the diagnosis cannot see (its "no fault" there is the prior)
        lines += [f"*{x}*  " for x in (getattr(d, "unobserved", None) or [])[:2]]
    return [*lines, ""]


def _fault_lines(d: DiagnosisView, f: Any) -> list[str]:
    """The part named: its action, its evidence for and against, the modes the data cannot
    tell it from (with the check that can) and a share for a change the library does not
    know."""
    lines = [f"**Diagnosis: {f.id}** ({f.component}), probability "
             f"{fmt(f.probability, '.2f')}, urgency {f.urgency}: {f.action}  "]
    lines += [f"+ {x}  " for x in f.evidence_for or []]
    lines += [f"- {x}  " for x in f.evidence_against or []]
    split = list(getattr(d, "split", None) or [])
    if len(split) > 1:
        lines.append(f"*the data cannot tell {' and '.join(split)} apart; to tell: "
                     f"{d.separate}*  ")
    if (d.unknown or 0.0) >= 0.1:
        lines.append(f"*unknown {fmt(d.unknown, '.2f')}: "
                     + "; ".join(d.unexplained or ["a change the library does not know"])
                     + "*  ")
    return lines


def parameter_table(doc: HealthView) -> str:
    """Every parameter at the window as markdown: a table of the parameters not fixed, the
    fixed ones in a line under it, then why the held ones are held. Empty without
    parameters."""
    table = doc.parameters or {}
    if not table:
        return ""
    lines = ["| parameter | value | status (+- 2 sigma) |", "|---|---:|---|"]
    reasons: dict[str, list[str]] = {}
    fixed = []
    for name, p in table.items():
        status = as_text(p.status)
        value = f"{fmt(p.value)} {as_text(p.unit)}".rstrip()
        if status == "fixed":
            fixed.append(f"{name} {value}")
            continue
        rel = as_number(p.rel_std_pct)
        if status in ("estimated", "fused") and math.isfinite(rel):
            status += f" +- {2 * rel:.2g} %"  # 2 sigma, as the header says
        elif status == "tied" and p.reason:
            status = str(p.reason)
        elif status == "held" and p.reason:
            reasons.setdefault(str(p.reason).removesuffix(_HELD), []).append(str(name))
        lines.append(f"| {name} | {value} | {status} |")
    notes = []
    if fixed:
        notes.append("fixed: " + ", ".join(fixed))
    notes += [f"{', '.join(names)} held: {reason}" for reason, names in reasons.items()]
    if notes:
        lines += ["", "  \n".join(notes)]
    return "\n".join(lines) + "\n"


_HELD = ": held at last trusted value"
"""The end of every reason a parameter is held (:mod:`twinwatch.twin.estimation.gate`): the
table says "held" already."""


def model_document(machine: str, t: float, doc: HealthView) -> str:
    """The twin DT'' as markdown: the diagnosis first, each meta-model term (equation,
    meaning, evidence), then the fit."""
    terms = doc.terms or []
    model = doc.model
    twin = f"`{model}`" if model else "the physical twin"
    window = doc.window
    at = f"at {clock(t)}" + (f", window {window}" if window is not None else "")
    lines = diagnosis_lines(doc.diagnosis, doc.parameters)
    if not terms:
        lines.append(f"**DT'' = DT** {at}: {twin} alone explains the data.")
    else:
        n = len(terms)
        lines.append(f"**DT'' = {twin} + {n} meta-model term{'s' if n > 1 else ''}** {at} "
                     "(paper Eq. 3):")
        for i, term in enumerate(terms, 1):
            lines.append("")
            lines.append(f"**{i}.** `{as_text(term.equation, '?')}`  ")
            if term.meaning:
                lines.append(f"{term.meaning}  ")
            params = term.params or {}
            std = term.params_std or {}
            values = ", ".join(
                f"{k} = {fmt(v, '.5g')}" + (f" +- {fmt(std[k], '.2g')}"
                                             if math.isfinite(as_number(std.get(k))) else "")
                for k, v in params.items())
            evidence = []
            if term.since_window is not None:
                evidence.append(f"found in window {term.since_window}")
            if math.isfinite(as_number(term.significance)):
                evidence.append(f"significance {fmt(term.significance, '.3g')}")
            if values:
                evidence.append(values + " (1 sigma)")
            if math.isfinite(as_number(term.evidence_windows)):
                evidence.append(f"evidence of {fmt(term.evidence_windows, '.3g')} windows")
            if evidence:
                lines.append("; ".join(evidence))
    disc = doc.discovery
    if disc is not None and disc.too_large:
        lines += ["", f"The residual is too large for the twin ({disc.consecutive} "
                  "windows in a row): discovery searches for what the model lacks."]
    rmse = doc.rmse
    if rmse:
        fit = ", ".join(f"{k} {fmt(v, '.3g')}" for k, v in rmse.items())
        lines += ["", f"fit: nRMSE {fmt(doc.nrmse, '.3g')}; RMSE {fit}"]
    return "\n".join(lines) + "\n"


def event_row(ev: Mapping[str, Any], t: float, rule: str, raised: bool,
               params: Mapping[str, ParameterView]) -> str:
    """An alarm change as one short log row: ``15:08 ALARM raised: Ra -10.02 % of nominal``,
    ``16:20 Ra alarm cleared to warning (-8.00 %)``, ``4:46 fault cleared: unbalance
    (probability 0.12)``."""
    p, level, previous = str(ev.get("parameter", "")), ev.get("level"), ev.get("previous")
    when = clock(t)
    if ev.get("kind") == "diagnosis":
        word = "FAULT raised" if raised else "fault cleared"
        odds = fmt(ev.get("probability"), ".2f")
        return f"{when} {word}: {ev.get('fault')} (probability {odds})"
    if not p:  # an event of another kind: its own message, without the machine's name
        return f"{when} " + str(ev.get("message", "")).removeprefix(f"{ev.get('machine')}: ")
    if rule == "rul":
        if not raised:
            return f"{when} {p} RUL {previous} cleared to {level}"
        ph = params.get(p)
        rul = rul_short(ph) if ph is not None else ""
        rul = rul.replace("RUL ", "", 1).replace(" ", " in ", 1) if rul.startswith("RUL") else rul
        return f"{when} RUL {str(level).upper()} raised: {p}" + (f", {rul}" if rul else "")
    dev = as_number(ev.get("deviation_pct"))
    if raised:
        return f"{when} {str(level).upper()} raised: {p} {fmt(dev, '+.2f')} % of nominal"
    return f"{when} {p} {previous} cleared to {level} ({fmt(dev, '+.2f')} %)"


def log_row(t_end: float, doc: HealthView, terms_changed: bool, grew: Mapping[str, int],
            health_json: str = "{}") -> tuple[str, rr.TextLogLevel]:
    """One short line for the window (a Rerun log row is not wrapped), and its level, the
    machine's state: ERROR while a parameter is in deviation alarm, WARN while one is in
    warning or has a RUL level raised, the model check fails, the structure changed or data
    were lost, else INFO. A document that is no health message (``health_json``) shows its
    top-level scalars."""
    parts = [f"window {as_text(doc.window, '?')} {clock(t_end)}"]
    alarms = doc.alarms or {}
    params = doc.parameters or {}
    ruled, worst = _ruled_parts(alarms, params)
    if ruled:
        parts.append("; ".join(ruled))
    elif params:  # no alarm rule: the estimated deviations
        parts.append(", ".join(f"{name} {fmt(ph.deviation_pct, '+.2f')} %"
                               for name, ph in params.items()
                               if ph.status in ("estimated", "fused")))
    wrong, failed, changed = _wrong_parts(doc, terms_changed, grew)
    if wrong:
        parts.append("| " + ", ".join(wrong))
    if not alarms and not params and len(parts) == 1:  # not a health message: its scalars
        parts.append(", ".join(f"{k}={v}" for k, v in json.loads(health_json).items()
                               if isinstance(v, bool | str | int | float) or v is None))
    if worst == 2:
        level = rr.TextLogLevel.ERROR
    elif worst == 1 or failed or changed or grew:
        level = rr.TextLogLevel.WARN
    else:
        level = rr.TextLogLevel.INFO
    return " ".join(parts), level


def _ruled_parts(alarms: Mapping[str, AlarmView],
                 params: Mapping[str, ParameterView]) -> tuple[list[str], int]:
    """The log row's part for each parameter with an alarm rule (tied and fixed ones left
    out): ``Ra -5.14 % (6.16593 ohm) WARNING, RUL ALARM``; and the row's level (:data:`RANK`):
    2 only for a deviation alarm (NE 107 FAILURE); a deviation warning or any RUL level
    raised is 1."""
    worst = 0
    ruled = []
    for name, a in alarms.items():
        words = []
        ph = params.get(name)
        if ph is not None and ph.status in ("tied", "fixed"):
            continue
        if ph is not None and ph.status not in (None, "estimated"):
            words.append(str(ph.status))
        level = str(a.level)
        if RANK.get(level, 0) > 0:
            worst = max(worst, RANK[level])
            words.append(level.upper())
        rul_level = str(a.rul.level if a.rul is not None else None)
        if RANK.get(rul_level, 0) > 0:
            # a RUL level asks to plan the maintenance (NE 107 MAINTENANCE_REQUIRED): WARN
            worst = max(worst, 1)
            words.append(f"RUL {rul_level.upper()}")
        elif ph is not None and (rul := rul_short(ph)):
            words.append(rul)
        dev = a.deviation_pct if ph is None else ph.deviation_pct
        head = f"{name} {fmt(dev, '+.2f')} %"
        if ph is not None and ph.status != "held":  # a held value is the last trusted one
            head += f" ({fmt(ph.value, '.5g')} {as_text(ph.unit)})"
        ruled.append(" ".join([head, ", ".join(words)]).strip())
    return ruled, worst


def _wrong_parts(doc: HealthView, terms_changed: bool,
                 grew: Mapping[str, int]) -> tuple[list[str], bool, bool]:
    """What went wrong in the window, for the log row; and whether the check failed and
    whether the structure changed."""
    wrong = []
    check = doc.model_check
    failed = check is not None and check.passed is False
    if check is not None and failed:  # a check that passed is the rule: in the model panel
        wrong.append("model check FAILED: " + "; ".join(map(str, check.reasons or [])))
    disc = doc.discovery
    changed = terms_changed or (disc is not None and bool(disc.changed))
    if changed and disc is not None:
        kept, dropped = disc.kept or [], disc.dropped or []
        wrong.append("DT'' changed" + "".join(f"; added {e}" for e in kept)
                     + "".join(f"; dropped {e}" for e in dropped))
    elif changed:
        wrong.append("DT'' changed")
    if grew:
        wrong.append("lost: " + ", ".join(f"{k} +{v}" for k, v in grew.items()))
    return wrong, failed, changed
