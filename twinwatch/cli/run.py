"""``twinwatch run``: one machine or a gateway's directory on the service host; the progress bar,
the summary printed and the exit status.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from twinwatch.cli.app import EX_CONFIG, fail, load_runnable, setup_logging

if TYPE_CHECKING:
    from twinwatch.config.schema import TwinwatchConfig
    from twinwatch.daemon.service import Progress, ServiceHost
    from twinwatch.twin.health import HealthMessage

#: The command line's own logger (its lines read ``twinwatch: ...``).
logger = logging.getLogger("twinwatch")


def _ignore_late_stops() -> None:
    """The run has ended: a SIGTERM or SIGINT arriving while the summary is written or the
    interpreter shuts down, a second one from systemd or an impatient operator, must not kill
    the process with the default action (exit -15 after a clean stop). Ignored at the OS level
    (``SIG_IGN``): at its finalization Python puts ``SIG_DFL`` back in place of every Python
    handler."""
    import signal

    for signum in (signal.SIGTERM, signal.SIGINT):
        try:
            signal.signal(signum, signal.SIG_IGN)
        except ValueError:  # not the main thread (click's test runner in a thread)
            return


@click.command()
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
    machine each) spread over --workers processes: each machine has its own source, queue,
    worker, outputs and watchdog, its files in ./<machine name>/; machines configured with the
    same [zenoh] session settings share one Zenoh session and so one process. A machine whose
    configuration is invalid, whose device cannot be opened or whose driver fails is reported
    under its name and the others go on. SIGHUP re-reads the directory (new files start,
    removed files stop, changed files reload, machines not running are started again). The
    summary has one block per machine; the exit status is 1
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
            return load_runnable(config, base_dir, force=force)

        host = Host(config, load=load, resume=resume_mode, duration=duration, workers=slots)
    setup_logging(log_level, threads=host.fleet)
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
        fail(exc, EX_CONFIG)
    for line in host.notices():
        click.echo(line, err=True)
    progress = None if no_progress else host.progress()
    bar = _progress_bar(progress) if progress is not None else None
    try:
        with _logs_above(bar):
            host.run()
    except Exception as exc:  # noqa: BLE001 - one line for the operator, the stack at DEBUG
        logger.debug("run failed", exc_info=True)
        fail(f"internal error: {type(exc).__name__}: {exc}")
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
