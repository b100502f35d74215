"""The fleet's table for ``twinwatch watch`` (:func:`render`, rich: one row per machine, each
cell its own function ``_<column>_cell``, given the machine's entry of the snapshot), the
console it is printed on, and the words shared with ``tail`` (a duration for a person, a
gap's line).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from twinwatch.watch.fleet import Gap
from twinwatch.watch.view import number

if TYPE_CHECKING:
    from rich.console import RenderableType
    from rich.text import Text



# -- formatting --------------------------------------------------------------------------------
def age(seconds: float | None) -> str:
    """A duration for a person: ``0.4 s``, ``12 s``, ``3.5 min``, ``2.1 h``, ``3.0 d``."""
    if seconds is None or not math.isfinite(seconds):
        return "-"
    if seconds < 10:
        return f"{seconds:.1f} s"
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.1f} min"
    if seconds < 172800:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.1f} d"


def value_text(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.6g}"


def deviation_text(v: float | None) -> str:
    return "n/a" if v is None else f"{v:+.2f} %"


def _rul(p: Mapping[str, Any]) -> str | None:
    status = p.get("rul_status")
    if status == "predicted" and p.get("rul_s") is not None:
        return f"RUL {age(p['rul_s'])}"
    if status == "crossed":
        return "RUL: crossed"
    return None


_LEVEL_STYLE = {"alarm": "bold red", "warning": "yellow", "normal": "green"}


_SHORT = {"estimated": "est", "fused": "fused", "held": "held"}


_STATE_LOOK = {"alive": ("●", "green"), "stale": ("◐", "yellow"), "gone": ("✕", "red"),
               "unknown": ("?", "dim")}


FILE_WIDTH = 180
"""Columns of the table written to a file or a pipe (on a terminal: the terminal's width); the
columns' least widths add up to about 110."""


def console(file: Any = None) -> Any:
    """A rich console for ``file`` (standard output by default): the terminal's width on a
    terminal, :data:`FILE_WIDTH` columns into a file or a pipe."""
    import sys as _sys

    from rich.console import Console

    stream = file if file is not None else _sys.stdout
    tty = bool(getattr(stream, "isatty", lambda: False)())
    return Console(file=stream) if tty else Console(file=stream, width=FILE_WIDTH)


def render(snapshot: Mapping[str, Any], *, title: str = "twinwatch fleet") -> RenderableType:
    """The rich table of :meth:`Fleet.snapshot`: one row per machine, each cell its own
    function (``_<column>_cell``) given the machine's entry of the snapshot."""
    from rich.table import Table
    from rich.text import Text

    machines = snapshot.get("machines", [])
    table = Table(title=f"{title}: {len(machines)} machine{'s' if len(machines) != 1 else ''}",
                  title_justify="left", expand=True, show_lines=True)
    for header, ratio, least in (("machine", 2, 8), ("state", 2, 9), ("last window", 3, 24),
                                 ("parameters (vs nominal)", 5, 24), ("alarms", 3, 12),
                                 ("terms (DT'')", 3, 10), ("diagnosis", 2, 10),
                                 ("data quality", 3, 16)):
        table.add_column(header, ratio=ratio, min_width=least, overflow="fold")
    if not machines:
        table.add_row("no machine on the network yet", "", "", "", "", "", "", "")
    for m in machines:
        terms = Text("\n".join(str(t["equation"]) for t in m["terms"]) or "none",
                     style="" if m["terms"] else "dim")
        table.add_row(Text(str(m["machine"]), style="bold"), _state_cell(m), _last_cell(m),
                      _parameters_cell(m), _alarms_cell(m), terms, _diagnosis_cell(m),
                      _quality_cell(m))
    return table


def _state_cell(m: Mapping[str, Any]) -> Text:
    """``● alive`` / ``◐ stale`` / ``✕ gone``, and since when (for how long it has been so
    while the token is there, how long ago it went)."""
    from rich.text import Text

    state = str(m["state"])
    mark, style = _STATE_LOOK.get(state, ("?", ""))
    st = Text(f"{mark} {state}", style=style)
    since = m["state_since_s"]
    if since is not None:
        st.append("\n" + (f"for {age(since)}" if m["token"] else f"{age(since)} ago"),
                  style="dim")
    return st


def _last_cell(m: Mapping[str, Any]) -> Text:
    """The last window: how long ago, its index, its plant time and its run."""
    from rich.text import Text

    if m["window"] is None:
        return Text("no window yet", style="dim")
    last = Text(f"{age(m['last_window_age_s'])} ago\n#{m['window']}")
    if m["t_start"] is not None and m["t_end"] is not None:
        last.append(f" [{m['t_start']:.0f}-{m['t_end']:.0f} s]")
    if m["run"]:
        last.append(f"\nrun {m['run']}", style="dim")
    return last


def _parameters_cell(m: Mapping[str, Any]) -> Text:
    """One line per parameter: its deviation from nominal (in its alarm level's style), its
    status, its RUL."""
    from rich.text import Text

    params = Text()
    for name, p in m["parameters"].items():
        if params:
            params.append("\n")
        level = p.get("alarm")
        params.append(f"{name:<3} {deviation_text(p['deviation_pct']):>9} ",
                      style=_LEVEL_STYLE.get(str(level), ""))
        status = str(p["status"])
        params.append(_SHORT.get(status, status), style="dim" if status == "held" else "")
        rul = _rul(p)
        if rul:
            params.append(f" {rul}", style="cyan")
    return params


def _alarms_cell(m: Mapping[str, Any]) -> Text:
    """The raised alarms (the deviation's and the RUL's, each said as what it is, since when)
    or ``none`` / ``no rules``, then the last alarm event."""
    from rich.text import Text

    alarms = Text()
    for name, a in m["alarms"].items():
        for kind, lv in (("", a), ("RUL ", a.get("rul") or {})):
            if lv.get("level") in ("warning", "alarm"):
                if alarms:
                    alarms.append("\n")
                since = (f" since t={lv['since_t']:.0f} s"
                         if lv.get("since_t") is not None else "")
                alarms.append(f"{name} {kind}{str(lv['level']).upper()}{since}",
                              style=_LEVEL_STYLE[str(lv["level"])])
    if not alarms:
        alarms.append("none" if m["alarms"] else "no rules", style="green dim")
    event = m.get("last_event")
    if event and event.get("parameter"):
        kind = "RUL " if event.get("kind") == "rul" else ""
        alarms.append(f"\nlast: {event.get('parameter')} {kind}{event.get('previous')} -> "
                      f"{event.get('level')} at {number(event.get('t'), 0.0):.0f} s",
                      style="dim")
    return alarms


def _diagnosis_cell(m: Mapping[str, Any]) -> Text:
    """The most probable fault and its probability (``n/a`` without a diagnosis)."""
    from rich.text import Text

    dg = m.get("diagnosis")
    diag = Text("n/a" if dg is None else str(dg["fault"]).replace("_", " "),
                style="dim" if dg is None or dg["fault"] == "no_fault" else "bold yellow")
    if dg is not None and isinstance(dg.get("probability"), int | float):
        diag.append(f" {dg['probability']:.2f}")
    return diag


def _quality_cell(m: Mapping[str, Any]) -> Text:
    """The fit, the model check, trust, the time per window, the losses; the windows the
    watcher missed and got back from the history."""
    from rich.text import Text

    quality = Text()
    q = m["quality"]
    if q is not None:
        quality.append(f"nRMSE {q['nrmse']:.1e}" if q["nrmse"] is not None else "nRMSE n/a")
        if q["model_check"] is not None:
            quality.append(", check ok" if q["model_check"] else ", check FAILED",
                           style="" if q["model_check"] else "yellow")
        if q["trusted"] is False:
            quality.append(", untrusted", style="yellow")
        if q["elapsed_ms"] is not None:
            quality.append(f"\n{q['elapsed_ms']:.0f} ms/window", style="dim")
        if q["problems"]:
            quality.append("\n" + ", ".join(f"{k} {v}" for k, v in q["problems"].items()),
                           style="yellow")
        else:
            quality.append("\nno losses", style="green dim")
    d = m.get("delivery") or {}
    if d.get("missed") or d.get("recovered") or d.get("error"):
        quality.append(("\n" if quality else "") + _gap_words(d),
                       style="yellow" if d.get("error") or
                       d.get("recovered", 0) < d.get("missed", 0) else "dim")
    return quality


def _gap_words(d: Mapping[str, Any]) -> str:
    """What the watcher missed and got back: ``missed 10, 10 from the history``."""
    text = f"missed {d.get('missed', 0)}, {d.get('recovered', 0)} from the history"
    return text + (f" (history failed: {d['error']})" if d.get("error") else "")


def gap_line(gap: Gap) -> str:
    """One line on a gap for ``tail`` (stderr): ``m1: 10 windows missed (a router outage or a
    lost link), 10 got from its history (windows 8-17)``."""
    text = f"{gap.machine}: "
    if gap.missed:
        text += (f"{gap.missed} window{'s' if gap.missed != 1 else ''} missed (a router "
                 "outage or a lost link), ")
    n = len(gap.recovered)
    text += f"{n} got from its history"
    if gap.recovered:
        ws = sorted(w for w in gap.recovered if isinstance(w, int))
        span = f"window {ws[0]}" if len(ws) == 1 else f"windows {ws[0]}-{ws[-1]}"
        text += f" ({span})" if ws else ""
    if gap.error:
        text += f"; the history query failed: {gap.error}"
    return text
