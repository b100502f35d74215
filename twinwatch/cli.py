"""Command line: ``twinwatch run``, ``check-config``, ``sample-config``, ``identify``, and
``watch`` / ``tail`` (the health on a Zenoh network, :mod:`twinwatch.watch`).

The only module that prints. Everything else logs. Each command imports what it needs when it
runs, so ``twinwatch --help`` loads click and nothing else (``benchmarks/bench_startup.py``).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from twinwatch import __version__

if TYPE_CHECKING:
    from twinwatch.config.schema import TwinwatchConfig
    from twinwatch.daemon.service import Progress, ServiceHost
    from twinwatch.twin.health import HealthMessage, HealthView

logger = logging.getLogger("twinwatch")

def _setup_logging(level: str, threads: bool = False) -> None:
    """Log to stderr (the journal under systemd); third-party floods are rate-limited (the
    first 5 identical messages a minute, then one line counting the others). ``threads``
    (gateway mode) adds the thread's name: ``twinwatch-<machine file>`` says which machine."""
    from twinwatch.daemon import logfilter

    logging.basicConfig(
        level=getattr(logging, level.upper()),
        format="%(asctime)s %(levelname)-7s " + ("[%(threadName)s] " if threads else "")
        + "%(name)s: %(message)s",
        stream=sys.stderr,
    )
    for handler in logging.getLogger().handlers:
        logfilter.install(handler)


@click.group()
@click.version_option(__version__, prog_name="twinwatch")
def main() -> None:
    """twinwatch: an interpretable digital twin that makes a machine self-aware.

    Each acquisition window it re-estimates the machine's unmeasured parameters (PSO, paper
    by Vilar-Dias et al., Sensors 2024) and publishes their drift as health over Zenoh.
    """


EX_CONFIG = 78
"""Exit status for an invalid configuration (sysexits.h); the unit does not restart on it."""



def _load_runnable(config: Path | None, base_dir: Path,
                   cwd: Path | None = None, *, force: bool | None = None) -> TwinwatchConfig:
    """Load CONFIG (or the built-in default) and check it can run here: the files it names
    and the directories it writes to exist, the driver delivers every channel the twin needs
    (:mod:`twinwatch.config.preflight`, the check ``check-config`` makes too).

    Raises:
        ConfigError: naming each bad key, missing file or directory, unmapped channel.
    """
    from twinwatch.config.loader import ConfigError, default_config, load_config
    from twinwatch.config.preflight import check_runnable

    try:
        cfg = load_config(config) if config else default_config()
    except UnicodeDecodeError as exc:  # a file in another encoding, or not text at all
        raise ConfigError(f"{config}: not UTF-8 text (byte {exc.start}: {exc.reason}): a "
                          "configuration is a TOML file in UTF-8") from None
    check_runnable(cfg, str(config) if config else "the built-in default", base_dir=base_dir,
                   cwd=cwd)
    if force is not None and cfg.machine.purpose == "commissioning":
        what = (f"{config}: [machine] purpose = \"commissioning\": this file is for "
                "`twinwatch identify`; its nominal values are generic, not this machine's, "
                "so its deviations, trends and alarms would mean nothing")
        if not force:
            raise ConfigError(what + "; monitor with a monitoring configuration, or pass "
                              "--force to run it anyway")
        logging.getLogger("twinwatch.cli").warning(
            "%s (--force: running it; what it publishes is not this machine's health)", what)
    return cfg



def _ignore_late_stops() -> None:
    """The run has ended: a SIGTERM or SIGINT arriving while the summary is written or the
    interpreter shuts down, a second one from systemd or an impatient operator, must not kill
    the process with the default action (exit -15 after a clean stop: measured under load in
    the "two SIGTERMs while a reload opens" case). Ignored at the OS level (``SIG_IGN``): at
    its finalization Python puts ``SIG_DFL`` back in place of every handler written in Python,
    so a Python handler does not cover the last milliseconds of the process."""
    import signal

    for signum in (signal.SIGTERM, signal.SIGINT):
        try:
            signal.signal(signum, signal.SIG_IGN)
        except ValueError:  # not the main thread (click's test runner in a thread)
            return


@main.command()
@click.argument("config", required=False, type=click.Path(path_type=Path))
@click.option("--duration", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Stop after this many seconds of source time (plant or recording time).")
@click.option("--log-level", default="warning", show_default=True,
              type=click.Choice(["debug", "info", "warning", "error"], case_sensitive=False))
@click.option("--no-progress", is_flag=True, help="Do not show the progress bar.")
@click.option("--fresh", is_flag=True,
              help="Start from the nameplate twin and normal alarm levels instead of resuming "
              "those saved in the state database (its history is kept).")
@click.option("--resume", is_flag=True,
              help="Resume the last run's twin and alarm levels also when the source's time "
              "starts over (a simulated plant, a replayed recording), which otherwise starts "
              "a new run from the nameplate values.")
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="Gateway mode (CONFIG a directory): worker processes the machines are "
              "spread over (default: one per core, and one per 50 machines when that is "
              "more; 1: every machine in this process).")
@click.option("--assignment", type=click.Path(path_type=Path), default=None, hidden=True,
              help="A worker process: the file naming the machine files it runs.")
@click.option("--slots", type=click.IntRange(min=0), default=None, hidden=True,
              help="Windows estimated at once in this process (default: the cores; 0: no "
              "limit).")
@click.option("--force", is_flag=True,
              help="Run a commissioning configuration ([machine] purpose = \"commissioning\") "
              "anyway, with a warning: by default it is refused.")
def run(config: Path | None, duration: float | None, log_level: str, no_progress: bool,
        fresh: bool, resume: bool, workers: int | None, assignment: Path | None,
        slots: int | None, force: bool) -> None:
    """Run the monitor on CONFIG (default: the built-in simulated DC motor, resistance
    degradation, as fast as possible, recording to ./twinwatch.rrd).

    Gateway mode: CONFIG a directory runs every machine configuration in it (*.toml, one
    machine each) in this one process: each machine has its own source, queue, worker,
    outputs and watchdog, its files in ./<machine name>/; machines configured with the same
    [zenoh] session settings share one Zenoh session; at most --workers windows are
    estimated at once. A machine whose configuration is invalid, whose device cannot be
    opened or whose driver fails is reported under its name and the others go on. SIGHUP
    re-reads the directory (new files start, removed files stop, changed files reload, machines
    not running are started again). The summary has one block per machine; the exit status is 1
    when a machine was lost, else as below for the worst machine.

    Every start is a new run (its id is in every health message and the summary; a SIGHUP
    reload goes on in the same run). On a machine (a bus, a device) the twin and the alarm
    levels saved in the state database by the previous run are resumed (a line says so);
    --fresh starts from the nameplate values. A source whose time starts over (a simulated
    plant from t = 0, a replayed recording) starts from the nameplate values unless --resume.

    Exit status: 0; 1 when the daemon cannot start or its driver fails; 78 for a configuration
    that cannot run here (the systemd unit does not restart on it); 74 when estimated windows
    were lost (not stored in the state database or not recorded); 75 when more windows failed
    (numeric failures, abandoned for gaps, bad values, jitter or time jumps) than were
    estimated.

    Signals: SIGTERM/SIGINT finish the windows already queued (a second one abandons them),
    close the driver, Zenoh, the Rerun file and the state database, and exit 0 (also while it
    starts or reloads). SIGHUP reloads CONFIG: it is validated first; a bad one is refused
    (logged, naming the key) and the running configuration goes on; a good one is started
    beside the running one and takes over at a window boundary, keeping the source, the Zenoh
    session, the Rerun file and the state database open when their tables are unchanged, going
    on with the window numbering and resuming the twin from the state database; if it cannot
    start, the running configuration goes on untouched."""
    from twinwatch.daemon.host import Host

    if fresh and resume:
        raise click.UsageError("--fresh and --resume exclude each other")
    resume_mode = False if fresh else (True if resume else None)
    host: ServiceHost
    if config is not None and config.is_dir():
        from twinwatch.config.loader import load_config
        from twinwatch.config.preflight import check_runnable
        from twinwatch.daemon.workers import ProcessHost, worker_processes

        def check(cfg: TwinwatchConfig, path: Path, work_dir: Path) -> None:
            check_runnable(cfg, str(path), base_dir=path.resolve().parent, cwd=work_dir)

        n = 1 if assignment is not None else worker_processes(config, workers)
        if n > 1:
            host = ProcessHost(config, workers=n, resume=resume_mode, duration=duration,
                               log_level=log_level, slots=slots)
        else:
            host = Host(config, read=load_config, check=check, resume=resume_mode,
                        duration=duration, workers=slots, stuck_after=30.0, quiet_after=30.0,
                        assignment=assignment)
    else:
        base_dir = config.resolve().parent if config else Path.cwd()

        def load() -> TwinwatchConfig:  # at start and at each SIGHUP: refused there too
            return _load_runnable(config, base_dir, force=force)

        host = Host(config, load=load, resume=resume_mode, duration=duration, workers=slots)
    _setup_logging(log_level, threads=host.fleet)
    _umask_0027()
    _run_host(host, no_progress=no_progress, as_json=assignment is not None)


def _umask_0027() -> None:
    """Files the daemon creates (state database, recordings, layout) are 0640 and directories
    0750, as under the unit's UMask=0027, also when run by hand; a stricter umask is kept."""
    old_umask = os.umask(0o027)
    os.umask(old_umask | 0o027)
    click.get_current_context().call_on_close(lambda: os.umask(old_umask))


def _run_host(host: ServiceHost, *, no_progress: bool, as_json: bool) -> None:
    """Start the host, run it, print its summary (``as_json``: a worker process's, one JSON
    document for its host) and exit with its exit status."""
    from twinwatch.errors import ConfigError

    try:
        host.start()
    except ConfigError as exc:  # a directory without machines
        click.echo(f"Error: {exc}", err=True)
        sys.exit(EX_CONFIG)
    for line in host.notices():
        click.echo(line, err=True)
    progress = None if no_progress else host.progress()
    bar = _progress_bar(progress) if progress is not None else None
    try:
        with _logs_above(bar):
            host.run()
    except Exception as exc:  # noqa: BLE001 - one line for the operator, the stack at DEBUG
        logger.debug("run failed", exc_info=True)
        click.echo(f"Error: internal error: {type(exc).__name__}: {exc}", err=True)
        sys.exit(1)
    finally:
        _ignore_late_stops()
        if bar is not None:
            bar.close()
    summary = host.summary()
    if as_json:
        click.echo(summary.model_dump_json())
    else:
        for line in summary.lines():
            click.echo(line)
        for line in summary.errors:
            click.echo(line, err=True)
    if summary.exit_status:
        sys.exit(summary.exit_status)


def _progress_bar(progress: Progress) -> Any:
    """A fleet of one at a terminal: the source time acquired, the window and its nRMSE."""
    from tqdm import tqdm

    total = progress.total
    bar = tqdm(total=round(total, 2) if total else None, unit="s", unit_scale=False,
               desc=progress.name, dynamic_ncols=True, file=sys.stderr,
               bar_format="{l_bar}{bar}| {n:.0f}/{total_fmt} s plant time [{elapsed}<"
               "{remaining}{postfix}]")
    t0: list[float] = []

    def _progress(health: HealthMessage) -> None:
        if not t0:
            t0.append(health.t_start)
        bar.n = health.t_end - t0[0]
        bar.set_postfix_str(f"window {health.window}, "
                            f"nRMSE {health.nrmse or float('nan'):.1e}", refresh=False)
        bar.refresh()

    progress.add_callback(_progress)
    return bar


@contextlib.contextmanager
def _logs_above(bar: Any) -> Iterator[None]:
    """While the progress bar is shown, the console's log lines are written above it (tqdm's
    ``logging_redirect_tqdm``: the bar is cleared, the line written, the bar drawn again), so a
    line never continues the bar's last redraw. The rate limit stays on the console's handler."""
    if bar is None:
        yield
        return
    from tqdm.contrib.logging import logging_redirect_tqdm

    from twinwatch.daemon import logfilter

    with logging_redirect_tqdm(tqdm_class=type(bar)):
        for handler in logging.getLogger().handlers:
            logfilter.install(handler)  # an older tqdm does not copy the filters
        yield


@main.command("check-config")
@click.argument("config", type=click.Path(path_type=Path))
@click.option("--force", is_flag=True,
              help="Check a commissioning configuration ([machine] purpose = "
              "\"commissioning\") as `run --force` runs it: by default it is refused, as "
              "`run` refuses it.")
def check_config(config: Path, force: bool) -> None:
    """Validate CONFIG and check it can run here (the files it names and the directories it
    writes to exist, the driver delivers every channel the twin needs: what `run` checks
    before it starts); exit 0 if `run` would start it, 1 naming each bad key otherwise (a
    commissioning configuration: valid for `twinwatch identify`, refused by `run` without
    --force). CONFIG a directory (a gateway's): every machine configuration in it (*.toml),
    each machine name once; exit 1 if any cannot run."""
    if not config.is_dir():
        ok, line = _check_one(config, force=force)
        click.echo(line, err=not ok)
        if not ok:
            sys.exit(1)
        return
    from twinwatch.daemon.host import MACHINE_GLOB

    files = sorted(p for p in config.glob(MACHINE_GLOB) if p.is_file())
    if not files:
        click.echo(f"{config}: no machine configuration ({MACHINE_GLOB}) in this directory",
                   err=True)
        sys.exit(1)
    names: dict[str, Path] = {}
    failed = 0
    for path in files:
        ok, line = _check_one(path, names=names)
        click.echo(line, err=not ok)
        failed += not ok
    from twinwatch.daemon.host import skipped

    for entry, why in skipped(config).items():
        click.echo(f"{config / entry}: skipped: {why}")
    click.echo(f"{config}: {len(files) - failed} of {len(files)} machine configurations OK")
    if failed:
        sys.exit(1)


def _check_one(config: Path, names: dict[str, Path] | None = None, *,
               force: bool | None = None) -> tuple[bool, str]:
    """``check-config`` on one file: (usable, the line to print). ``names``: the machine
    names seen so far in a gateway's directory (a second file naming one fails). ``force``:
    a single file is checked as ``run`` loads it (a commissioning file refused unless True);
    None (a gateway's file): as the gateway loads it."""
    from twinwatch.config.loader import ConfigError

    try:
        cfg = _load_runnable(config, config.resolve().parent)
    except ConfigError as exc:
        return False, str(exc)
    refused: str | None = None
    if force is not None and cfg.machine.purpose == "commissioning":
        try:  # what `run` says of it (said once the source was opened: valid for identify)
            _load_runnable(config, config.resolve().parent, force=force)
        except ConfigError as exc:
            refused = str(exc)
    if names is not None:
        other = names.setdefault(cfg.machine.name, config)
        if other != config:
            return False, (f"{config}: machine.name {cfg.machine.name!r} is already used by "
                           f"{other.name}: each machine of a gateway needs a name of its own")
    # Drivers validate what only they can check (DBC names, files, columns) at open time:
    # open the source without starting acquisition and without sending (a live interface
    # receive-only where it allows), and say if it cannot be opened.
    from twinwatch.drivers import DriverConfigError, DriverError, get_driver_class

    try:
        probed = get_driver_class(cfg.driver.type).probe(cfg.driver,
                                                          base_dir=config.resolve().parent)
    except DriverConfigError as exc:
        return False, f"{config}: {exc.keyed()}"
    except DriverError as exc:
        return False, (f"{config}: the configuration is valid; the source cannot be opened "
                       f"here: {exc} (`run` would wait for it)"
                       if get_driver_class(cfg.driver.type).reopens(cfg.driver)
                       else f"{config}: driver: {exc}")
    if refused is not None:
        return False, (f"{refused}; it is valid for `twinwatch identify {config}` "
                       f"({cfg.machine.model} '{cfg.machine.name}', {cfg.driver.type} driver)")
    return True, (f"{config}: OK ({cfg.machine.model} '{cfg.machine.name}', "
                  f"{cfg.driver.type} driver, estimating "
                  f"{', '.join(cfg.estimation.estimate or [])})"
                  + (f"; source: {probed}" if probed and probed != "opened" else ""))


_CONNECT_HELP = ("Zenoh endpoint to connect to: a daemon (a peer, tcp/127.0.0.1:7447 by "
                 "default) or a router the daemons connect to (repeatable). No scouting: only "
                 "these are used.")


def _zenoh_options(fn: Callable[..., Any]) -> Callable[..., Any]:
    """--connect, --mode, --prefix: how ``watch`` and ``tail`` reach the daemons."""
    fn = click.option("--prefix", default="twinwatch", show_default=True,
                      help="The daemons' [zenoh] key_prefix.")(fn)
    fn = click.option("--mode", type=click.Choice(["client", "peer"]), default="client",
                      show_default=True, help="Zenoh mode of this session.")(fn)
    return click.option("--connect", "connect", multiple=True, default=("tcp/127.0.0.1:7447",),
                        show_default=True, metavar="ENDPOINT", help=_CONNECT_HELP)(fn)


@main.command()
@_zenoh_options
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


@main.command()
@click.argument("machine")
@_zenoh_options
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


@main.command()
@click.argument("machine")
@click.option("--db", "db", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="The state database the daemon stores the machine's windows in ([state] "
              "path), read-only. Without it: live, from the running daemon over Zenoh "
              "(--connect).")
@click.option("--windows", type=click.IntRange(min=1, max=1000), default=5, show_default=True,
              help="The last windows whose fit is shown.")
@_zenoh_options
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
        click.echo(f"Error: cannot read {db}: {exc}", err=True)
        sys.exit(1)
    except RuntimeError as exc:
        click.echo(f"Error: {exc}", err=True)
        sys.exit(1)
    if not docs:
        where = db if db is not None else f"the network at {', '.join(connect)}"
        click.echo(f"Error: {where} holds no window of the machine {machine!r}", err=True)
        sys.exit(1)
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


def _fraction_range(value: str | None) -> tuple[float, float] | None:
    if value is None:
        return None
    try:
        a, b = (float(x) for x in value.split(":"))
    except ValueError:
        raise click.BadParameter(f"{value!r}: give START:END as fractions, e.g. 0:0.5") from None
    return a, b


@main.command()
@click.argument("config", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--train", "train", default=None, metavar="START:END",
              help="Training range, fractions of the recording (default [identify] train, "
              "0:0.5).")
@click.option("--validate", "validate", default=None, metavar="START:END",
              help="Validation range (default [identify] validate, 0.5:1).")
@click.option("--weight", "weights", multiple=True, metavar="OUTPUT=W",
              help="Weight of an output in the fitness (repeatable; default 1).")
@click.option("--duration", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Read this many seconds of source time (a live bus); default: to its end.")
@click.option("--record", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Write the fits, the residual tests (autocorrelation, residual-input "
              "cross-correlation) and the tables to this Rerun file.")
@click.option("--output", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also write the [machine.parameters] block to this file.")
@click.option("--log-level", default="warning", show_default=True,
              type=click.Choice(["debug", "info", "warning", "error"], case_sensitive=False))
def identify(config: Path, train: str | None, validate: str | None, weights: tuple[str, ...],
             duration: float | None, record: Path | None, output: Path | None,
             log_level: str) -> None:
    """Commission the baseline: identify the parameters CONFIG estimates from its recording.

    Reads the whole source of CONFIG (a file, a CAN log, a simulated plant, or a live bus for
    --duration), fits the twin to the training range with the daemon's global and local search
    (one free-run simulation over the whole range), says which parameters and combinations
    the recording determines (rank and conditioning of the information matrix, correlations,
    parameters at a bound), holds the others at their stated values ([identify.fixed] or
    [machine.parameters]) and re-fits the rest, compares the candidate structures
    [identify.candidates] lists (validation fit, model check, BIC), scores the fit on the
    validation range (fit % per output), and prints a [machine.parameters] block of the
    determined parameters (the held ones commented with the reason), ready to paste into the
    monitoring configuration. Exit 78 for a bad configuration, 1 if the recording cannot be
    identified from."""
    from twinwatch.config.loader import ConfigError, load_config

    _setup_logging(log_level)
    try:
        cfg = load_config(config)
        update: dict[str, Any] = {}
        for key, value in (("train", _fraction_range(train)),
                           ("validate_", _fraction_range(validate))):
            if value is not None:
                update[key] = value
        if weights:
            w = dict(cfg.identify.weights)
            for item in weights:
                name, _, val = item.partition("=")
                try:
                    w[name.strip()] = float(val)
                except ValueError:
                    raise click.BadParameter(f"{item!r}: give OUTPUT=WEIGHT") from None
            update["weights"] = w
        if update:
            table = cfg.identify.model_dump(by_alias=True)
            table.update({("validate" if k == "validate_" else k): v for k, v in update.items()})
            cfg = cfg.model_copy(update={"identify": type(cfg.identify).model_validate(table)})
            for name in cfg.identify.weights:
                if name not in _outputs(cfg):
                    raise ConfigError(f"--weight {name}: not an output of the twin")
    except ConfigError as exc:
        click.echo(f"Error: {exc}", err=True)
        sys.exit(EX_CONFIG)
    except ValueError as exc:  # a bad --train/--validate range
        click.echo(f"Error: {exc}", err=True)
        sys.exit(EX_CONFIG)
    from twinwatch.commissioning.commission import CommissionError, commission
    from twinwatch.commissioning.identify import parameters_block
    from twinwatch.commissioning.report import report
    from twinwatch.drivers import DriverError

    try:
        found = commission(cfg, config.resolve().parent, duration=duration, record=record)
    except (CommissionError, DriverError) as exc:
        click.echo(f"Error: cannot identify: {exc}", err=True)
        sys.exit(1)
    data, result = found.data, found.result
    click.echo(f"{data.t.size} samples from {data.source}"
               + (f" ({data.dropped} left out: a channel missing or not finite)"
                  if data.dropped else ""))
    click.echo(report(result, found.comparison))
    block = parameters_block(result, f"{config} ({data.t.size} samples)")
    click.echo("")
    click.echo(block, nl=False)
    if output is not None:
        output.write_text(block, encoding="utf-8")
        click.echo(f"written to {output}")
    if record is not None:
        click.echo(f"fits, residual tests and tables: {record} (open with: rerun {record})")


def _outputs(cfg: Any) -> list[str]:
    from twinwatch.twin.models import create_model

    return list(create_model(cfg.machine.model, cfg.machine.options).output_names)


class _RegistryChoice(click.Choice[str]):
    """A choice among a registry's names, read when a value is checked or the command's help
    is shown (not when the command line is built: ``twinwatch --help`` imports no registry)."""

    def __init__(self, names: Callable[[], list[str]]) -> None:
        super().__init__(())
        self._names = names
        self._cache: tuple[str, ...] | None = None

    @property  # type: ignore[override]
    def choices(self) -> tuple[str, ...]:
        if self._cache is None:
            self._cache = tuple(self._names())
        return self._cache

    @choices.setter
    def choices(self, value: Any) -> None:
        pass


def _driver_names() -> list[str]:
    from twinwatch.drivers import DRIVERS

    return DRIVERS.names()


@main.command("sample-config")
@click.option("--driver", type=_RegistryChoice(_driver_names), default="simulated",
              show_default=True,
              help="Print the complete example for this driver (every key documented; any "
              "registered driver, plug-ins included).")
def sample_config(driver: str) -> None:
    """Print a commented sample configuration: every key of every table it uses, optional ones
    commented out with their default (without --driver: the built-in default, the simulated
    DC motor)."""
    from twinwatch.config.samples import sample_config as sample

    click.echo(sample(driver), nl=False)


if __name__ == "__main__":  # pragma: no cover
    main()
