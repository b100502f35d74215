"""The ranked fleet view of ``twinwatch watch --fleet`` (:func:`render_fleet`, rich): it reads
the machines' fleet summaries (:mod:`twinwatch.twin.summary`, ranked by
:mod:`twinwatch.watch.ranking`), not their health messages, so it indexes the summary's own
fields; a screen's worth of rows (:func:`screen_rows`), the rest counted.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from twinwatch.watch.render import _LEVEL_STYLE, age, deviation_text
from twinwatch.watch.view import number

if TYPE_CHECKING:
    from rich.console import RenderableType
    from rich.text import Text

_SUMMARY_STYLE = {"alarm": "bold red", "check_function": "magenta", "warning": "yellow",
                  "normal": "green"}


def screen_rows(height: int | None) -> int:
    """Machines a screen of ``height`` lines holds in :func:`render_fleet` (title, header, the
    counts and the prompt take 7); 20 when the height is unknown (a file or a pipe)."""
    return max((height or 27) - 7, 1)


def render_fleet(view: Mapping[str, Any], *, title: str = "twinwatch fleet",
                 by_box: bool = False) -> RenderableType:
    """The rich table of :func:`~twinwatch.watch.ranking.fleet_view`: one line per machine
    listed, most urgent first (state, diagnosis, RUL, deviations, box, age of its summary),
    then what is not listed counted; ``by_box``: one line per box instead (its machines by
    state and its most urgent one)."""
    from rich.console import Group
    from rich.table import Table
    from rich.text import Text

    counts = view.get("states", {})
    said = ", ".join(f"{counts[s]} {s}" for s in ("alarm", "check_function", "warning",
                                                  "normal") if counts.get(s))
    head = (f"{title}: {view.get('machines_total', 0)} machines, {view.get('matched', 0)} "
            f"matching ({said or 'none'})")
    table = Table(title=head, title_justify="left", expand=True, box=None, pad_edge=False)
    if by_box:
        for header in ("box", "machines", "alarm", "check fn", "warning", "normal", "stale",
                       "most urgent"):
            table.add_column(header, overflow="ellipsis", no_wrap=True)
        for box, b in view.get("boxes", {}).items():
            table.add_row(Text(box, style="bold"), str(b["machines"]),
                          Text(str(b["alarm"]), style="bold red" if b["alarm"] else "dim"),
                          str(b["check_function"]),
                          Text(str(b["warning"]), style="yellow" if b["warning"] else "dim"),
                          str(b["normal"]), str(b["stale"]), str(b["first"]))
        return table
    for header, ratio in (("machine", 2), ("box", 1), ("state", 1), ("diagnosis", 3),
                          ("RUL (95 %)", 2), ("deviation", 2), ("summary", 1)):
        table.add_column(header, ratio=ratio, overflow="ellipsis", no_wrap=True)
    for m in view.get("machines", []):
        state = str(m.get("state"))
        st = Text(state if m.get("seen") != "stale" else f"{state} (stale)",
                  style=_SUMMARY_STYLE.get(state, ""))
        table.add_row(Text(str(m.get("machine")), style="bold"), str(m.get("box")), st,
                      _fleet_diagnosis(m), _fleet_rul(m), _fleet_deviation(m),
                      f"{age(m.get('age_s'))} ago")
    more = int(view.get("more", 0))
    foot = Text(f"... and {more} more machine{'s' if more != 1 else ''} (--limit, --state, "
                "--machines to see them)" if more else "", style="dim")
    return Group(table, foot) if more else table


def _fleet_diagnosis(m: Mapping[str, Any]) -> Text:
    from rich.text import Text

    d = m.get("diagnosis")
    if not isinstance(d, Mapping):
        return Text("n/a", style="dim")
    if d.get("status") != "fault":
        return Text(str(d.get("status")).replace("_", " "),
                    style="dim" if d.get("status") == "no_fault" else "magenta")
    p = d.get("probability")
    text = Text(f"{d.get('fault')} {p:.2f}" if isinstance(p, int | float) else str(
        d.get("fault")), style="bold red" if d.get("alarm") else "yellow")
    text.append(f" {d.get('urgency')}: {d.get('part')}", style="")
    return text


def _fleet_rul(m: Mapping[str, Any]) -> Text:
    from rich.text import Text

    r = m.get("rul")
    if not isinstance(r, Mapping):
        return Text("-", style="dim")
    if r.get("status") == "crossed":
        return Text(f"{r.get('parameter')}: crossed", style="bold red")
    return Text(f"{r.get('parameter')} {age(number(r.get('median_s')))} "
                f"({age(number(r.get('low_s')))}-{age(number(r.get('high_s')))})",
                style="cyan")


_RANK = {"alarm": 2, "warning": 1}


def _fleet_deviation(m: Mapping[str, Any]) -> Text:
    """The deviation column, the machine's worst parameter first: the summary's ``worst``
    (by its own threshold: its rule's, or 5 % without one; an older daemon sends none), then
    the ruled parameters by level and size: the column is cut at its width."""
    from rich.text import Text

    out = Text()
    alarms = m.get("alarms") or {}
    devs = dict(m.get("deviation") or {})
    worst = m.get("worst")
    order: list[tuple[str, Any]] = []
    if isinstance(worst, Mapping) and worst.get("parameter"):
        name = str(worst["parameter"])
        order.append((name, worst.get("deviation_pct")))
        devs.pop(name, None)
    order += sorted(devs.items(), key=lambda kv: (
        -_RANK.get(str((alarms.get(kv[0]) or {}).get("level")), 0),
        -abs(number(kv[1], 0.0))))
    for k, (name, dev) in enumerate(order):
        if out:
            out.append(" ")
        level = str((alarms.get(name) or {}).get("level"))
        style = _LEVEL_STYLE.get(level, "")
        if k == 0 and isinstance(worst, Mapping) and level not in _RANK and (
                number(worst.get("share"), 0.0) >= 1.0):
            style = "yellow"  # beyond its own threshold, without a rule that says so
        out.append(f"{name} {deviation_text(number(dev))}", style=style)
    return out
