"""``twinwatch fleet report``: what needs service within a horizon, from the machines' fleet
summaries on a Zenoh network (:mod:`twinwatch.watch.ranking`).
"""

from __future__ import annotations

import csv
import json
import time
from pathlib import Path
from typing import Any

import click

from twinwatch.cli.app import fail
from twinwatch.cli.watch import FLEET_PREFIX_HELP, config_option, reach, zenoh_options


@click.group()
def fleet() -> None:
    """The fleet across boxes, from each machine's fleet summary (<prefix>/<machine>/summary):
    `twinwatch fleet report` (what needs service). The live, ranked view is `twinwatch watch
    --fleet`."""


def _horizon(ctx: click.Context, param: click.Parameter, value: str) -> float:
    from twinwatch.watch.ranking import parse_duration

    try:
        return parse_duration(value)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None


@fleet.command()
@zenoh_options(prefix_help=FLEET_PREFIX_HELP)
@config_option(verb="ask")
@click.option("--horizon", default="7d", show_default=True, callback=_horizon,
              help="What is due within this long from now: 7d, 12h, 30min, 90s.")
@click.option("--machines", default="*", show_default=True, metavar="PATTERN",
              help="The machines to consider, one chunk of a Zenoh key expression: a name, * "
              "or a pattern such as 'line1-$*'.")
@click.option("--csv", "csv_path", type=click.Path(dir_okay=False, path_type=Path),
              default=None, metavar="FILE", help="Write the report as CSV to FILE ('-': "
              "standard output).")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path),
              default=None, metavar="FILE", help="Write the report as JSON to FILE ('-': "
              "standard output).")
@click.option("--wait", type=click.FloatRange(min=0), default=5.0, show_default=True,
              help="The longest wait for the machines' summaries [s]; it reports once no new "
              "machine came for 1 s.")
@click.option("--expect", type=click.IntRange(min=1), default=None, metavar="N",
              help="Report as soon as N machines are held (within --wait).")
def report(connect: tuple[str, ...], mode: str, prefix: str, config: Path | None,
           horizon: float, machines: str, csv_path: Path | None, json_path: Path | None,
           wait: float, expect: int | None) -> None:
    """What needs service within --horizon: every machine whose RUL interval (its earliest
    end, to the alarm threshold of the parameter that reaches it first) falls within the
    horizon, whose diagnosis urges action (its fault alarm raised, a fault of high urgency at
    least 0.5 probable, or check function: the twin cannot see the machine), or with an alarm
    raised; with the part and the action, most urgent first. Read from each machine's latest
    fleet summary (one get, each daemon answering with its machines' latest).

    Exit status: 0 (nothing due too); 1 when the network cannot be reached; 2 for a bad
    option."""
    from twinwatch.watch import WatchError, age
    from twinwatch.watch.ranking import REPORT_COLUMNS, flat, service_report
    from twinwatch.watch.summaries import following

    if csv_path is not None and json_path is not None and str(csv_path) == str(json_path):
        raise click.BadParameter("give --csv and --json different files", param_hint="--json")
    where = reach(connect, config, prefix)
    try:
        with following(where.connect, mode, where.prefix, machines,  # type: ignore[arg-type]
                       optional=where.optional, on_skip=where.skip) as summaries:
            summaries.settle(wait, expected=expect)
            received = summaries.received
    except WatchError as exc:
        fail(exc)
    now = time.time()
    rows = service_report(received, now, horizon)
    doc = {"t": now, "horizon_s": horizon, "machines": len(received), "due": len(rows),
           "rows": rows}
    if json_path is not None:
        _write(json_path, json.dumps(doc, indent=2, allow_nan=False) + "\n")
    if csv_path is not None:
        from io import StringIO

        buf = StringIO()
        writer = csv.writer(buf)
        writer.writerow(REPORT_COLUMNS)
        writer.writerows(flat(rows))
        _write(csv_path, buf.getvalue())
    if csv_path is None and json_path is None:
        _print(rows, len(received), horizon)
    elif "-" not in (str(csv_path), str(json_path)):
        click.echo(f"{len(rows)} of {len(received)} machines need service within "
                   f"{age(horizon)}", err=True)


def _write(path: Path, text: str) -> None:
    if str(path) == "-":
        click.echo(text, nl=False)
        return
    try:
        path.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise click.BadParameter(f"{path}: cannot write it: {exc.strerror}") from None


def _print(rows: list[dict[str, Any]], machines: int, horizon: float) -> None:
    from rich.table import Table

    from twinwatch.watch import age, console

    table = Table(title=f"what needs service within {age(horizon)}: {len(rows)} of "
                  f"{machines} machines", title_justify="left", expand=True)
    for header in ("machine", "box", "state", "why", "part", "action", "RUL (95 %)"):
        table.add_column(header, overflow="fold")
    for r in rows:
        rul = ("-" if r["rul_parameter"] is None else
               f"{r['rul_parameter']} {age(r['rul_median_s'])} ({age(r['rul_low_s'])}-"
               f"{age(r['rul_high_s'])})")
        fault = (f" ({r['fault']} {r['probability']:.2f}, {r['urgency']})"
                 if r["fault"] and isinstance(r["probability"], int | float) else "")
        table.add_row(str(r["machine"]), str(r["box"]), str(r["state"]), r["why"],
                      f"{r['part']}{fault}", str(r["action"]), rul)
    console().print(table)
