"""``twinwatch watch`` and ``tail``: the machines on a Zenoh network (:mod:`twinwatch.watch`), and
the options by which they, and ``explain``, reach the daemons.
"""

from __future__ import annotations

import contextlib
import functools
import json
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import click

from twinwatch.cli.app import fail

CONNECT_HELP = ("Zenoh endpoint to connect to: a daemon (a peer) or a router the daemons "
                "connect to (repeatable). Default: tcp/127.0.0.1:7447 only, where a daemon "
                "listens unless its [zenoh] listen says otherwise. No scouting: only these are "
                "used.")

CONFIG_HELP = ("Also {verb} the machines configured in this file or gateway directory "
               "(*.toml): each one's Zenoh endpoint ([zenoh] listen; a client's connect, its "
               "router; 0.0.0.0 read as 127.0.0.1) and their key_prefix. An endpoint of theirs "
               "where nothing answers (a machine not running) is skipped with a note. Without "
               "--connect, only these are used.")

#: --prefix's help: plain (``tail``, ``explain``), and where a ``*`` chunk is taken: ``watch``
#: with --fleet and ``fleet report`` read the fleet summaries under it
PREFIX_HELP = "The daemons' [zenoh] key_prefix."
WILDCARD = ("chunks after the first may be *: twinwatch/* follows gateways whose key_prefix is "
            "twinwatch/<box>")
WATCH_PREFIX_HELP = f"The daemons' [zenoh] key_prefix (with --fleet, {WILDCARD})."
FLEET_PREFIX_HELP = f"The daemons' [zenoh] key_prefix ({WILDCARD})."


def zenoh_options(fn: Callable[..., Any] | None = None, *, prefix_help: str = PREFIX_HELP
                  ) -> Any:
    """--connect, --mode, --prefix: how ``watch``, ``tail``, ``explain`` and ``fleet report``
    reach the daemons (``@zenoh_options``, or ``@zenoh_options(prefix_help=...)`` for a
    command that takes a ``*`` chunk in --prefix)."""
    if fn is None:
        return functools.partial(zenoh_options, prefix_help=prefix_help)
    fn = click.option("--prefix", default="twinwatch", show_default=True, help=prefix_help)(fn)
    fn = click.option("--mode", type=click.Choice(["client", "peer"]), default="client",
                      show_default=True, help="Zenoh mode of this session.")(fn)
    return click.option("--connect", "connect", multiple=True, default=("tcp/127.0.0.1:7447",),
                        show_default=True, metavar="ENDPOINT", help=CONNECT_HELP)(fn)


def config_option(fn: Callable[..., Any] | None = None, *, verb: str = "watch") -> Any:
    """--config: ``watch``, ``tail`` and ``fleet report`` find the endpoints of configured
    machines (``verb``: what the command does with them, for the help)."""
    if fn is None:
        return functools.partial(config_option, verb=verb)
    return click.option("--config", "config", default=None, metavar="PATH",
                        type=click.Path(exists=True, path_type=Path),
                        help=CONFIG_HELP.format(verb=verb))(fn)


@dataclass(frozen=True)
class Reach:
    """Where a watcher connects: the endpoints (``optional``: those read from --config, which
    may have nothing answering), the key prefix, and which machine files name each endpoint
    read from the configuration."""

    connect: tuple[str, ...]
    prefix: str
    optional: frozenset[str] = frozenset()
    files: dict[str, list[str]] = field(default_factory=dict)

    def skip(self, endpoint: str, why: str) -> None:
        """Say on stderr that nothing answers at a configured machine's endpoint (``why``, the
        session's error, is left out: it says the same at length)."""
        names = self.files.get(endpoint, [])
        more = f" and {len(names) - 3} more" if len(names) > 3 else ""
        click.echo(f"twinwatch: nothing answers at {endpoint} ({', '.join(names[:3])}{more}): "
                   "not watched (not running?)", err=True)


def reach(connect: tuple[str, ...], config: Path | None, prefix: str) -> Reach:
    """The endpoints and the prefix ``watch``/``tail`` use: ``--connect`` as given (its default
    without ``--config``) and those of :func:`config_endpoints`, their key prefix unless
    ``--prefix`` is given.

    Raises:
        click.BadParameter: --config unreadable or not a configuration (one line), no machine
            there publishes on Zenoh, or they use several key prefixes and --prefix is not
            given.
    """
    if config is None:
        return Reach(connect, prefix)
    ctx = click.get_current_context()
    explicit = ctx.get_parameter_source("connect") not in (
        click.core.ParameterSource.DEFAULT, None)
    found, prefixes = config_endpoints(config)
    if not found:
        raise click.BadParameter(f"{config}: no machine there publishes on Zenoh "
                                 "([zenoh] enabled = false)", param_hint="--config")
    if ctx.get_parameter_source("prefix") in (click.core.ParameterSource.DEFAULT, None):
        if len(prefixes) > 1:
            raise click.BadParameter(f"{config}: the machines use several key prefixes "
                                     f"({', '.join(sorted(prefixes))}): give --prefix",
                                     param_hint="--config")
        prefix = next(iter(prefixes))
    given = tuple(connect) if explicit else ()
    derived = tuple(e for e in found if e not in given)
    return Reach(given + derived, prefix, frozenset(derived), found)


def config_endpoints(path: Path) -> tuple[dict[str, list[str]], set[str]]:
    """The Zenoh endpoints the machines configured at ``path`` (a file, or a gateway's
    directory) publish on, each with the files that name it, and their key prefixes: a
    machine's ``[zenoh] listen`` (:func:`watch_endpoint`), else its ``connect`` (a client: the
    router); none when its Zenoh output is off. Only the ``[zenoh]`` table is read.

    Raises:
        click.BadParameter: a file cannot be read, is not TOML, or its [zenoh] table is not
            valid (one line naming the file and the key); a directory without ``*.toml``.
    """
    import tomllib

    from pydantic import ValidationError

    from twinwatch.sinks.zenoh import ZenohConfig

    if path.is_dir():
        from twinwatch.daemon.host import MACHINE_GLOB

        files = sorted(p for p in path.glob(MACHINE_GLOB) if p.is_file())
        if not files:
            raise click.BadParameter(f"{path}: no machine configuration ({MACHINE_GLOB}) in "
                                     "this directory", param_hint="--config")
    else:
        files = [path]
    found: dict[str, list[str]] = {}
    prefixes: set[str] = set()
    for f in files:
        try:
            data = tomllib.loads(f.read_text(encoding="utf-8"))
        except OSError as exc:
            raise click.BadParameter(f"{f}: cannot read it: {exc.strerror}",
                                     param_hint="--config") from None
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise click.BadParameter(f"{f}: not a TOML configuration: {exc}",
                                     param_hint="--config") from None
        try:
            table = ZenohConfig.model_validate(data.get("zenoh", {}))
        except ValidationError as exc:
            err = exc.errors(include_url=False)[0]
            loc = ".".join(str(x) for x in ("zenoh", *err["loc"]))
            raise click.BadParameter(f"{f}: {loc}: {err['msg']}", param_hint="--config"
                                     ) from None
        if not table.enabled:
            continue
        endpoints = table.listen if table.mode != "client" and table.listen else table.connect
        for e in endpoints:
            found.setdefault(watch_endpoint(e), []).append(f.name)
        if endpoints:
            prefixes.add(table.key_prefix)
    return found, prefixes


def watch_endpoint(listen: str) -> str:
    """The endpoint a watcher on this host connects to for a daemon's ``listen`` endpoint:
    its metadata (``#...``, ``?...``) dropped, an unspecified address (``0.0.0.0``, ``[::]``)
    read as the loopback one."""
    proto, _, rest = listen.partition("/")
    rest = rest.split("#", 1)[0].split("?", 1)[0]
    host, _, port = rest.rpartition(":")
    host = {"0.0.0.0": "127.0.0.1", "[::]": "[::1]"}.get(host, host)
    return f"{proto}/{host}:{port}"


@click.command()
@zenoh_options(prefix_help=WATCH_PREFIX_HELP)
@config_option
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
@click.option("--stale", type=click.FloatRange(min=0), default=None,
              help="A machine on the network without a window for this long (at least 3 "
              "window lengths) is shown stale [s]. Default 10; with --fleet, without a "
              "summary for this long: 180 (3 summary intervals).")
@click.option("--fleet", "fleet_mode", is_flag=True,
              help="The fleet at size: read each machine's fleet summary (a few hundred bytes, "
              "<prefix>/<machine>/summary) instead of its full health, rank the machines by "
              "urgency (alarm, then the diagnosis' urgency, then the RUL median), list a "
              "screen's worth and count the rest.")
@click.option("--state", "states", multiple=True,
              type=click.Choice(["alarm", "check_function", "warning", "normal", "stale",
                                 "alive"]),
              help="--fleet: only machines in this state (repeatable; stale/alive: whether "
              "their summary is older than --stale).")
@click.option("--model", "models", multiple=True, metavar="MODEL",
              help="--fleet: only machines of this twin model (repeatable).")
@click.option("--machines", default="*", show_default=True, metavar="PATTERN",
              help="--fleet: the machines to follow, one chunk of a Zenoh key expression: a "
              "name, * or a pattern such as 'line1-$*' (names starting with line1-).")
@click.option("--by-box", is_flag=True,
              help="--fleet: one line per box (the host a daemon runs on, [zenoh] box): its "
              "machines by state and its most urgent one.")
@click.option("--limit", type=click.IntRange(min=0), default=None,
              help="--fleet: machines listed (default: a screen's worth; with --json every "
              "one; 0: none, only the counts).")
@click.option("--show", "show", default=None, metavar="MACHINE",
              help="--fleet: fetch this machine's full health (its latest window) and print "
              "it, then exit.")
def watch(connect: tuple[str, ...], mode: str, prefix: str, config: Path | None, once: bool,
          as_json: bool, wait: float, interval: float, stale: float | None, fleet_mode: bool,
          states: tuple[str, ...], models: tuple[str, ...], machines: str, by_box: bool,
          limit: int | None, show: str | None) -> None:
    """Every machine on a Zenoh network at a glance: found by their daemons' liveliness tokens
    (directly or through a router), each with its state (alive, stale, gone and since when),
    its last window (age, index, run), each parameter's deviation from nominal, status, alarm
    level and remaining useful life, its raised alarms, its discovered terms and its data
    quality. Machines appear and disappear as their daemons start and stop. Ctrl-C exits.

    What it connects to: only the endpoints given, no scouting. By default
    tcp/127.0.0.1:7447, where a daemon listens unless its [zenoh] listen says otherwise (most
    DC motor examples); a machine publishing on another port (the hydraulic examples on 7448
    and 7449, the OPC UA ones on 7450 and 7451, the CANopen one on 7453, a gateway whose
    machines' [zenoh] table says another) is not shown unless its endpoint is given with
    --connect or its configuration with --config (a file or a gateway's directory: twinwatch
    watch --config config/ watches every shipped example that runs).

    Exit status: 0; 1 when the network cannot be reached; 2 for a bad option (--config
    unreadable)."""
    from twinwatch.watch import Fleet, WatchError, console, render, watching

    where = reach(connect, config, prefix)
    connect, prefix = where.connect, where.prefix
    if fleet_mode or show:
        watch_fleet(where, mode, once=once, as_json=as_json, wait=wait, interval=interval,
                    stale=180.0 if stale is None else stale, states=states, models=models,
                    machines=machines, by_box=by_box, limit=limit, show=show)
        return
    if any((states, models, machines != "*", by_box, limit is not None)):
        raise click.UsageError("--state, --model, --machines, --by-box and --limit go with "
                               "--fleet")
    fleet = Fleet(stale_after=10.0 if stale is None else stale)
    title = _fleet_title(connect, mode)
    try:
        with watching(connect, mode, prefix, fleet,  # type: ignore[arg-type]
                      optional=where.optional, on_skip=where.skip) as watcher:
            if once:
                watcher.settle(wait)
                snap = fleet.snapshot()
                if as_json:
                    click.echo(json.dumps(snap, indent=2, allow_nan=False))
                else:
                    console().print(render(snap, title=title))
                return
            if not sys.stdout.isatty():
                # into a file or a pipe: every refresh written and flushed, SIGTERM ends it
                import signal

                def _stop(*_: Any) -> None:
                    raise KeyboardInterrupt

                with contextlib.suppress(ValueError):  # not the main thread (tests)
                    signal.signal(signal.SIGTERM, _stop)

            def changed() -> None:
                fleet.changed.wait(interval)
                fleet.changed.clear()

            _refresh((lambda: time.sleep(interval)) if as_json else changed,
                     lambda: render(fleet.snapshot(), title=title),
                     (lambda: json.dumps(fleet.snapshot(), separators=(",", ":"),
                                         allow_nan=False)) if as_json else None)
    except WatchError as exc:
        fail(exc)


def watch_fleet(where: Reach, mode: str, *, once: bool, as_json: bool, wait: float,
                interval: float, stale: float, states: tuple[str, ...],
                models: tuple[str, ...], machines: str, by_box: bool, limit: int | None,
                show: str | None) -> None:
    """``watch --fleet``: the machines' summaries ranked (:mod:`twinwatch.watch.ranking`);
    live (not ``--once``, not ``--show``) it waits for the network and the first summary
    (:func:`fleet_following`)."""
    from twinwatch.watch import Fleet, WatchError, console, render
    from twinwatch.watch.ranking import fleet_view
    from twinwatch.watch.render_fleet import render_fleet, screen_rows

    title = _fleet_title(where.connect, mode)
    try:
        with fleet_following(where.connect, mode, where.prefix, machines,
                             optional=where.optional, on_skip=where.skip,
                             wait=not (once or show)) as summaries:
            if show:
                doc = summaries.health(show, timeout=max(wait, 1.0))
                if doc is None:
                    fail(f"{show}: no health answered within {max(wait, 1.0):g} s (not "
                         "running, or not on this network)")
                if as_json:
                    click.echo(json.dumps(doc.model_dump(by_alias=True, exclude_unset=True),
                                          indent=2, allow_nan=False))
                    return
                one = Fleet(stale_after=1e9)
                one.health(show, doc)
                console().print(render(one.snapshot(), title=f"{title}: {show}"))
                return
            out = console()

            def view() -> dict[str, Any]:
                rows = limit if limit is not None else (
                    None if as_json else screen_rows(out.size.height if out.is_terminal
                                                     else None))
                return fleet_view(summaries.received, time.time(), states=states,
                                  models=models, limit=rows, stale_after=stale)

            if once:
                summaries.settle(wait)
                if as_json:
                    click.echo(json.dumps(view(), indent=2, allow_nan=False))
                else:
                    out.print(render_fleet(view(), title=title, by_box=by_box))
                return
            _refresh(lambda: summaries.wait(interval),
                     lambda: render_fleet(view(), title=title, by_box=by_box),
                     (lambda: json.dumps(view(), allow_nan=False, separators=(",", ":")))
                     if as_json else None, rest=interval)
    except KeyboardInterrupt:  # while it waited for the network or the first summary
        return
    except WatchError as exc:
        fail(exc)


def _refresh(pause: Callable[[], None], table: Callable[[], Any],
             line: Callable[[], str] | None = None, *, rest: float = 0.0) -> None:
    """Until Ctrl-C, after each ``pause()``: ``line()`` (one line of JSON) when given, else
    ``table()`` printed (into a file or a pipe, flushed) or drawn again in place (at a
    terminal); then ``rest`` [s]."""
    from twinwatch.watch import console

    try:
        if line is not None or not sys.stdout.isatty():
            out = console()
            while True:
                pause()
                if line is not None:
                    click.echo(line())
                else:
                    out.print(table())
                sys.stdout.flush()
                time.sleep(rest)
        from rich.live import Live

        with Live(table(), auto_refresh=False) as live:
            while True:
                pause()
                live.update(table(), refresh=True)
                time.sleep(rest)
    except KeyboardInterrupt:
        return


#: ``watch --fleet``: the first and the longest delay between attempts to reach the network
#: while nothing answers there yet [s]
FLEET_RETRY_S = (0.5, 5.0)


@contextlib.contextmanager
def fleet_following(connect: tuple[str, ...], mode: str, prefix: str, machines: str, *,
                    optional: frozenset[str] = frozenset(),
                    on_skip: Callable[[str, str], None] | None = None, wait: bool = False,
                    say: Callable[[str], None] | None = None,
                    sleep: Callable[[float], None] = time.sleep) -> Iterator[Any]:
    """The fleet's summaries (:func:`~twinwatch.watch.summaries.following`). With ``wait``
    (``watch --fleet`` live, not ``--once``): until the network answers and the first fleet
    summary has come, each wait said once on stderr, instead of exiting because no daemon is
    up yet; nothing answering is tried again with a delay doubling from
    :data:`FLEET_RETRY_S` ``[0]`` to ``[1]`` s. Ctrl-C ends the wait.

    Raises:
        WatchError: a bad endpoint, prefix or pattern; nothing answers (without ``wait``).
    """
    from twinwatch.watch.session import Unreachable
    from twinwatch.watch.summaries import following, machines_key

    say = say or (lambda line: click.echo(line, err=True))
    key = machines_key(prefix, machines)
    delay, said = FLEET_RETRY_S[0], set()
    while True:
        stack = contextlib.ExitStack()
        try:
            summaries = stack.enter_context(following(
                connect, mode, prefix, machines, optional=optional,  # type: ignore[arg-type]
                on_skip=on_skip))
        except Unreachable as exc:
            stack.close()
            if not wait:
                raise
            if "network" not in said:
                said.add("network")
                say(f"twinwatch: waiting for the fleet: {exc}; trying again (Ctrl-C to stop)")
            sleep(delay)
            delay = min(2 * delay, FLEET_RETRY_S[1])
            continue
        break
    with stack:
        if wait and not summaries.received:
            say(f"twinwatch: waiting for the first fleet summary on {key} (a daemon publishes "
                "its machine's at its first window, then on a change and every [zenoh] "
                "summary_interval; Ctrl-C to stop)")
            while not summaries.received:
                summaries.wait(1.0)
        yield summaries


def _fleet_title(connect: tuple[str, ...], mode: str) -> str:
    return f"twinwatch fleet on {', '.join(connect)} ({mode})"


@click.command()
@click.argument("machine")
@zenoh_options
@config_option(verb="follow")
@click.option("--json", "as_json", is_flag=True,
              help="Each health message as one line of JSON, exactly as published.")
@click.option("--count", type=click.IntRange(min=1), default=None,
              help="Exit after this many health messages.")
@click.option("--history", type=click.IntRange(min=1), default=1, show_default=True,
              help="Start with each machine's last N windows (from its daemon's cache, at most "
              "its [zenoh] cache).")
def tail(machine: str, connect: tuple[str, ...], mode: str, prefix: str, config: Path | None,
         as_json: bool, count: int | None, history: int) -> None:
    """Follow MACHINE (its [machine] name, or * for every machine): one line per health message
    as it arrives, the last window (or --history N) first; in text, each alarm change too. The
    machine appearing and going are said on stderr, and so are windows missed on the way (a
    router outage): those are then asked from the machine's history and printed once got.
    Ctrl-C exits. It connects where `watch` does (--connect, --config: see `twinwatch watch
    --help`).

    Exit status: 0; 1 when the network cannot be reached; 2 for a bad option."""
    from twinwatch.watch import Fleet, Tail, WatchError, watching

    where = reach(connect, config, prefix)
    connect, prefix = where.connect, where.prefix
    printer = Tail(click.echo, as_json=as_json, note=lambda line: click.echo(line, err=True))
    try:
        with watching(connect, mode, prefix, Fleet(), machine,  # type: ignore[arg-type]
                      optional=where.optional, on_skip=where.skip,
                      history=history, alarm_history=0, on_health=printer.on_health,
                      on_alarm=printer.on_alarm, on_token=printer.on_token,
                      on_gap=printer.on_gap):
            try:
                printer.run(count, waiting=f"{prefix}/{machine}")
            except KeyboardInterrupt:
                return
    except WatchError as exc:
        fail(exc)
