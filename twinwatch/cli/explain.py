"""``twinwatch explain``: the chain from a machine's last windows to the decision, from its state
database or live from its daemon.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from twinwatch.cli.app import fail
from twinwatch.cli.watch import zenoh_options

if TYPE_CHECKING:
    from twinwatch.twin.health import HealthView


@click.command()
@click.argument("machine")
@click.option("--db", "db", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="The state database the daemon stores the machine's windows in ([state] "
              "path), read-only. Without it: live, from the running daemon over Zenoh "
              "(--connect).")
@click.option("--windows", type=click.IntRange(min=1, max=1000), default=5, show_default=True,
              help="The last windows whose fit is shown.")
@zenoh_options
def explain(machine: str, db: Path | None, windows: int, connect: tuple[str, ...], mode: str,
            prefix: str) -> None:
    """Explain MACHINE's state: the chain from its last windows to the decision. From the
    state database (--db, read-only, also while the daemon writes it) or live from the
    running daemon over Zenoh (its latest health and history queries): the fit of the last
    windows (RMSE, nRMSE, model check, DT' against DT''), the parameters with their 2-sigma
    intervals and status, the meta-model terms with their parameters' standard errors, the
    trend and remaining useful life, and the ranked faults of the diagnosis with the evidence
    for and against each, the action and its source (docs/diagnosis.md).

    Exit status: 0; 1 when the database or the daemon cannot be read or has no window of
    MACHINE."""
    import sqlite3

    from twinwatch.twin.diagnosis.explain import explain_lines, read_windows

    try:
        docs = (read_windows(db, machine, windows) if db is not None
                else _live_windows(machine, windows, connect, mode, prefix))
    except (OSError, sqlite3.Error) as exc:
        fail(f"cannot read {db}: {exc}")
    except RuntimeError as exc:
        fail(exc)
    if not docs:
        where = db if db is not None else f"the network at {', '.join(connect)}"
        fail(f"{where} holds no window of the machine {machine!r}")
    for line in explain_lines(docs):
        click.echo(line)


def _live_windows(machine: str, count: int, connect: tuple[str, ...], mode: str,
                  prefix: str) -> list[HealthView]:
    """The machine's last ``count`` health messages from its daemon (their typed view,
    :func:`~twinwatch.twin.health.read_health`): the latest (the health queryable), then the
    current run's history from ``count`` windows before it.

    Raises:
        RuntimeError: the network cannot be reached, the daemon does not answer or refuses.
    """

    from twinwatch.twin.health import read_health
    from twinwatch.watch import HISTORY_TIMEOUT_S, WatchError, open_session

    def ask(session: Any, selector: str) -> list[str]:
        out = []
        for reply in session.get(selector, timeout=HISTORY_TIMEOUT_S):
            if reply.ok is None:
                err = reply.err
                raise RuntimeError(f"{selector}: " + (err.payload.to_string() if err
                                                      else "an error without a message"))
            out.append(reply.ok.payload.to_string())
        return out

    base = f"{prefix}/{machine}"
    try:
        with open_session(connect, mode) as session:  # type: ignore[arg-type]
            latest = [read_health(x) for x in ask(session, f"{base}/health")]
            if not latest:
                return []
            last = max(latest, key=lambda d: d.t_end or 0.0)
            span = float(last.t_end) - float(last.t_start)
            t_from = float(last.t_start) - (count - 1) * span - 0.5 * span
            try:
                pages = [json.loads(x) for x in
                         ask(session, f"{base}/history?run={last.run};t_from={t_from!r};"
                                      f"limit={count}")] if count > 1 else []
            except RuntimeError as exc:  # no state database: the latest window only
                click.echo(f"twinwatch: no history of {machine} ({exc}): the latest window "
                           f"only", err=True)
                pages = []
    except WatchError as exc:
        raise RuntimeError(str(exc)) from exc
    # a history page: {"windows": [health message, ...], ...}
    docs = [read_health(d) for p in pages for d in p.get("windows", []) if isinstance(d, dict)]
    docs = [d for d in docs if d.window != last.window][-(count - 1):] if count > 1 else []
    return [*docs, last]
