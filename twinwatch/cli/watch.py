"""``twinwatch watch`` and ``tail``: the machines on a Zenoh network (:mod:`twinwatch.watch`), and
the options by which they, and ``explain``, reach the daemons.
"""

from __future__ import annotations

import contextlib
import json
import sys
import time
from collections.abc import Callable
from typing import Any

import click

CONNECT_HELP = ("Zenoh endpoint to connect to: a daemon (a peer, tcp/127.0.0.1:7447 by "
                 "default) or a router the daemons connect to (repeatable). No scouting: only "
                 "these are used.")


def zenoh_options(fn: Callable[..., Any]) -> Callable[..., Any]:
    """--connect, --mode, --prefix: how ``watch`` and ``tail`` reach the daemons."""
    fn = click.option("--prefix", default="twinwatch", show_default=True,
                      help="The daemons' [zenoh] key_prefix.")(fn)
    fn = click.option("--mode", type=click.Choice(["client", "peer"]), default="client",
                      show_default=True, help="Zenoh mode of this session.")(fn)
    return click.option("--connect", "connect", multiple=True, default=("tcp/127.0.0.1:7447",),
                        show_default=True, metavar="ENDPOINT", help=CONNECT_HELP)(fn)


@click.command()
@zenoh_options
@click.option("--once", is_flag=True,
              help="Print one snapshot and exit (after at most --wait seconds).")
@click.option("--json", "as_json", is_flag=True,
              help="JSON instead of the table: with --once one document, else one line per "
              "refresh (for scripts).")
@click.option("--wait", type=click.FloatRange(min=0), default=2.0, show_default=True,
              help="--once: the longest wait for the machines to report [s]; it prints as soon "
              "as every machine found has reported its last window.")
@click.option("--interval", type=click.FloatRange(min=0.1), default=1.0, show_default=True,
              help="Refresh period [s].")
@click.option("--stale", type=click.FloatRange(min=0), default=10.0, show_default=True,
              help="A machine on the network without a window for this long (at least 3 "
              "window lengths) is shown stale [s].")
def watch(connect: tuple[str, ...], mode: str, prefix: str, once: bool, as_json: bool,
          wait: float, interval: float, stale: float) -> None:
    """Every machine on a Zenoh network at a glance: found by their daemons' liveliness tokens
    (directly or through a router), each with its state (alive, stale, gone and since when),
    its last window (age, index, run), each parameter's deviation from nominal, status, alarm
    level and remaining useful life, its raised alarms, its discovered terms and its data
    quality. Machines appear and disappear as their daemons start and stop. Ctrl-C exits.

    Exit status: 0; 1 when the network cannot be reached."""
    from twinwatch.watch import Fleet, WatchError, console, render, watching

    fleet = Fleet(stale_after=stale)
    try:
        with watching(connect, mode, prefix, fleet) as watcher:  # type: ignore[arg-type]
            if once:
                watcher.settle(wait)
                snap = fleet.snapshot()
                if as_json:
                    click.echo(json.dumps(snap, indent=2, allow_nan=False))
                else:
                    console().print(render(snap, title=_fleet_title(connect, mode)))
                return
            if not sys.stdout.isatty():
                # into a file or a pipe: every refresh written and flushed (a Live display
                # wrote nothing until it ended, and nothing at all when stopped by SIGTERM)
                import signal

                def _stop(*_: Any) -> None:
                    raise KeyboardInterrupt

                with contextlib.suppress(ValueError):  # not the main thread (tests)
                    signal.signal(signal.SIGTERM, _stop)
            try:
                if as_json:
                    while True:
                        time.sleep(interval)
                        click.echo(json.dumps(fleet.snapshot(), separators=(",", ":"),
                                              allow_nan=False))
                        sys.stdout.flush()
                if not sys.stdout.isatty():
                    out = console()
                    title = _fleet_title(connect, mode)
                    while True:
                        fleet.changed.wait(interval)
                        fleet.changed.clear()
                        out.print(render(fleet.snapshot(), title=title))
                        sys.stdout.flush()
                from rich.live import Live

                title = _fleet_title(connect, mode)
                with Live(render(fleet.snapshot(), title=title), auto_refresh=False) as live:
                    while True:
                        fleet.changed.wait(interval)
                        fleet.changed.clear()
                        live.update(render(fleet.snapshot(), title=title), refresh=True)
            except KeyboardInterrupt:
                return
    except WatchError as exc:
        click.echo(f"Error: {exc}", err=True)
        sys.exit(1)


def _fleet_title(connect: tuple[str, ...], mode: str) -> str:
    return f"twinwatch fleet on {', '.join(connect)} ({mode})"


@click.command()
@click.argument("machine")
@zenoh_options
@click.option("--json", "as_json", is_flag=True,
              help="Each health message as one line of JSON, exactly as published.")
@click.option("--count", type=click.IntRange(min=1), default=None,
              help="Exit after this many health messages.")
@click.option("--history", type=click.IntRange(min=1), default=1, show_default=True,
              help="Start with each machine's last N windows (from its daemon's cache, at most "
              "its [zenoh] cache).")
def tail(machine: str, connect: tuple[str, ...], mode: str, prefix: str, as_json: bool,
         count: int | None, history: int) -> None:
    """Follow MACHINE (its [machine] name, or * for every machine): one line per health message
    as it arrives, the last window (or --history N) first; in text, each alarm change too. The
    machine appearing and going are said on stderr, and so are windows missed on the way (a
    router outage): those are then asked from the machine's history and printed once got.
    Ctrl-C exits.

    Exit status: 0; 1 when the network cannot be reached."""
    from twinwatch.watch import Fleet, Tail, WatchError, watching

    printer = Tail(click.echo, as_json=as_json, note=lambda line: click.echo(line, err=True))
    try:
        with watching(connect, mode, prefix, Fleet(), machine,  # type: ignore[arg-type]
                      history=history, alarm_history=0, on_health=printer.on_health,
                      on_alarm=printer.on_alarm, on_token=printer.on_token,
                      on_gap=printer.on_gap):
            try:
                printer.run(count, waiting=f"{prefix}/{machine}")
            except KeyboardInterrupt:
                return
    except WatchError as exc:
        click.echo(f"Error: {exc}", err=True)
        sys.exit(1)
