"""Command line: ``twinwatch run``, ``twinwatch check-config``, ``twinwatch sample-config``.

The only module that prints. Everything else logs.
"""

from __future__ import annotations

import faulthandler
import logging
import signal
import sys
import threading
from pathlib import Path
from types import FrameType
from typing import Any

import click

from twinwatch import __version__
from twinwatch.config.loader import ConfigError, default_config, load_config

logger = logging.getLogger("twinwatch")

_SAMPLE_CONFIG = Path(__file__).parent / "config" / "default.toml"


def _setup_logging(level: str) -> None:
    logging.basicConfig(
        level=getattr(logging, level.upper()),
        format="%(asctime)s %(levelname)-7s %(name)s: %(message)s",
        stream=sys.stderr,
    )


@click.group()
@click.version_option(__version__, prog_name="twinwatch")
def main() -> None:
    """twinwatch: an interpretable digital twin that makes a machine self-aware.

    Each acquisition window it re-estimates the machine's unmeasured parameters (PSO, paper
    by Vilar-Dias et al., Sensors 2024) and publishes their drift as health over Zenoh.
    """


EX_CONFIG = 78
"""Exit status for an invalid configuration (sysexits.h); the unit does not restart on it."""


@main.command()
@click.argument("config", required=False, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--duration", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Stop after this many seconds of source time (plant or recording time).")
@click.option("--log-level", default="warning", show_default=True,
              type=click.Choice(["debug", "info", "warning", "error"], case_sensitive=False))
@click.option("--no-progress", is_flag=True, help="Do not show the progress bar.")
def run(config: Path | None, duration: float | None, log_level: str, no_progress: bool) -> None:
    """Run the monitor on CONFIG (default: the built-in simulated DC motor, resistance
    degradation, as fast as possible, recording to ./twinwatch.rrd).

    Signals: SIGTERM/SIGINT finish the windows already queued (a second one abandons them),
    close the driver, Zenoh, the Rerun file and the state database, and exit 0. SIGHUP
    reloads CONFIG: it is validated first; a bad one is refused (logged, naming the key) and
    the running configuration goes on; a good one restarts the daemon in-process, keeping the
    Zenoh session, the Rerun file and the state database open when their tables are unchanged,
    and resuming the twin from the state database."""
    from twinwatch.daemon.systemd import Notifier, Watchdog

    notifier = Notifier(unset_environment=True)
    _setup_logging(log_level)
    # systemd's watchdog kills with SIGABRT: write every thread's stack to stderr (the journal)
    # first, so a stuck worker or a hung driver read shows where it was. (An stderr without a
    # file descriptor, e.g. click's test runner, has nowhere to write it.)
    try:
        faulthandler.enable()
    except (AttributeError, ValueError, OSError):
        logger.debug("faulthandler not enabled: stderr has no file descriptor")
    try:
        cfg = load_config(config) if config else default_config()
    except ConfigError as exc:
        click.echo(f"Error: {exc}", err=True)
        notifier.notify(f"STATUS=invalid configuration: {exc}".splitlines()[0])
        sys.exit(EX_CONFIG)
    base_dir = config.resolve().parent if config else Path.cwd()

    from twinwatch.daemon.publisher import PublisherError
    from twinwatch.daemon.recorder import RecorderError
    from twinwatch.daemon.runner import SINKS, Daemon
    from twinwatch.daemon.store import StoreError
    from twinwatch.drivers.base import DriverError

    start_errors = (DriverError, PublisherError, RecorderError, StoreError, ValueError, OSError)

    # Signals first: a SIGTERM while the drivers and sinks start must stop cleanly too.
    # The handlers only set flags (a handler that logged to systemd's socket or took a lock
    # the interrupted code holds could deadlock); the main loop acts on them.
    stop_requested = threading.Event()
    reload_requested = threading.Event()
    holder: list[Any] = []

    def _on_signal(signum: int, frame: FrameType | None) -> None:
        if stop_requested.is_set():
            for d in holder:
                d.abandon = True
            logger.warning("%s received again: abandoning the queued windows",
                           signal.Signals(signum).name)
            return
        logger.warning("%s received: finishing the queued windows and stopping",
                       signal.Signals(signum).name)
        stop_requested.set()
        for d in holder:
            d.stop()

    def _on_hup(signum: int, frame: FrameType | None) -> None:
        reload_requested.set()

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, _on_signal)
        signal.signal(signal.SIGTERM, _on_signal)
        signal.signal(signal.SIGHUP, _on_hup)

    watchdog = Watchdog(notifier)
    pending: list[Any] = []  # a validated new configuration waiting for the restart

    def _check_reload() -> None:
        """Acquisition-loop tick: validate a requested reload without stopping acquisition."""
        if not reload_requested.is_set() or stop_requested.is_set():
            return
        reload_requested.clear()
        notifier.reloading("reloading the configuration")
        source = str(config) if config else "the built-in default"
        try:
            new_cfg = load_config(config) if config else default_config()
        except ConfigError as exc:
            logger.error("reload refused, the running configuration goes on: %s", exc)
            notifier.ready(status=f"reload refused ({str(exc).splitlines()[-1].strip()}); "
                           "running the previous configuration")
            return
        logger.warning("reloading %s: restarting the daemon with the new configuration",
                       source)
        pending.append(new_cfg)
        for d in holder:
            d.stop()

    def _start(c: Any, reuse: dict[str, Any] | None = None) -> Any:
        d = Daemon(c, base_dir=base_dir, persist=True, watchdog=watchdog, reuse=reuse)
        d.add_tick(_check_reload)
        return d

    try:
        daemon = _start(cfg)
    except start_errors as exc:
        # Each of these says what failed and what to do; a traceback would add nothing.
        notifier.notify(f"STATUS=cannot start: {exc}".splitlines()[0])
        raise click.ClickException(f"cannot start: {exc}") from None
    holder.append(daemon)
    if stop_requested.is_set():
        daemon.stop()
    _warm_up(daemon)
    notifier.ready(status=_status_line(cfg, daemon))

    total = duration
    if total is None and cfg.driver.type in ("simulated", "simulated_modbus"):
        total = cfg.driver.plant.duration  # type: ignore[union-attr]
    bar: Any = None
    if not no_progress:
        from tqdm import tqdm

        bar = tqdm(total=round(total, 2) if total else None, unit="s", unit_scale=False,
                   desc=f"{cfg.machine.name}", dynamic_ncols=True, file=sys.stderr,
                   bar_format="{l_bar}{bar}| {n:.0f}/{total_fmt} s plant time [{elapsed}<"
                   "{remaining}{postfix}]")
        t0: list[float] = []

        def _progress(health: dict[str, Any]) -> None:
            if not t0:
                t0.append(health["t_start"])
            bar.n = health["t_end"] - t0[0]
            bar.set_postfix_str(f"window {health['window']}, "
                                f"nRMSE {health['nrmse'] or float('nan'):.1e}", refresh=False)
            bar.refresh()

    try:
        while True:
            if bar is not None:
                daemon.add_callback(_progress)
            daemon.run(duration=duration)
            if stop_requested.is_set() or not pending:
                break
            new_cfg = pending.pop()
            kept = daemon.close(keep=SINKS)
            holder.clear()
            try:
                daemon = _start(new_cfg, reuse=kept)
                cfg = new_cfg
            except start_errors as exc:
                logger.error("the new configuration cannot start (%s): going back to the "
                             "previous one", exc)
                daemon = _start(cfg)
            holder.append(daemon)
            logger.warning("configuration reloaded; the twin resumes from the state database")
            notifier.ready(status=_status_line(cfg, daemon))
    finally:
        notifier.stopping("stopping: finishing the queued windows")
        notifier.extend_timeout(cfg.acquisition.shutdown_timeout + 10)
        daemon.close()
        if bar is not None:
            bar.close()
    _print_summary(cfg, daemon)


def _warm_up(daemon: Any) -> None:
    """Compile the twin's numba kernels before READY=1 (cached on disk after the first run),
    so the first window does not look like a stuck worker to the watchdog."""
    try:
        import numpy as np

        from twinwatch.twin.model import WindowData

        n = daemon.config.acquisition.window
        dt = daemon.config.acquisition.sample_period
        t = np.arange(n) * dt
        chans = {c: np.zeros(n) for c in daemon.model.required_channels()}
        theta = np.array([[daemon.nominal[p] for p in daemon.model.parameter_names]])
        daemon.model.simulate(theta, WindowData(t=t, channels=chans, index=-1))
    except Exception:  # noqa: BLE001 - best effort: the first window compiles otherwise
        logger.debug("numba warm-up skipped", exc_info=True)


def _status_line(cfg: Any, daemon: Any) -> str:
    parts = [f"monitoring {cfg.machine.name} ({cfg.machine.model}, {cfg.driver.type} driver)"]
    if daemon.publisher is not None:
        parts.append(f"health on {cfg.zenoh.key_prefix}/{cfg.machine.name}/health")
    if daemon.store is not None:
        parts.append(f"state {daemon.store.path}")
    if daemon.restored is not None:
        parts.append("twin resumed")
    return ", ".join(parts)


def _print_summary(cfg: Any, daemon: Any) -> None:
    last = daemon.latest
    c = daemon.counters()
    click.echo(f"twinwatch: {c['windows_estimated']} windows estimated, "
               f"{c['overruns']} overruns, {c['windows_abandoned']} windows abandoned "
               f"(gaps/bad samples), {c['numeric_failures']} numeric failures")
    if last is None:
        click.echo("no window was completed: the source delivered fewer samples than one window")
        return
    click.echo(f"last window {last['window']} [{last['t_start']:.2f}-{last['t_end']:.2f} s], "
               f"nRMSE {last['nrmse']:.2e}, estimated in {last['elapsed_s'] * 1e3:.0f} ms:")
    for name, p in last["parameters"].items():
        status = "estimated" if not p["held"] else f"held: {p['reason']}"
        dev = p["deviation_pct"]
        click.echo(f"  {name:<3} = {p['value']:<11.6g} {p['unit']:<10} "
                   f"({'n/a' if dev is None else f'{dev:+.2f}'} % vs nominal {p['nominal']:g}) "
                   f"{status}")
    disc = last.get("discovery") or {}
    if disc.get("enabled"):
        terms = last.get("terms") or []
        res = last.get("residual") or {}
        click.echo(f"twin structure (DT''): {len(terms)} meta-model term(s)"
                   + (":" if terms else ": the physical model explains the data"))
        for term in terms:
            click.echo(f"  {term['equation']}  [{term['meaning']}]")
        worst = {k: (res.get(v) or {}).get("max_abs") or {} for k, v in
                 (("DT'", "dt_prime"), ("DT''", "dt_second"))}
        if terms:
            click.echo("  worst error in the last window: " + "; ".join(
                f"{k} " + ", ".join(f"{o} {e:.3g}" for o, e in w.items() if e is not None)
                for k, w in worst.items() if w))
    times = sorted(h["elapsed_s"] for h in daemon.history)
    if times:
        med = times[len(times) // 2]
        click.echo(f"estimation time per window: median {med * 1e3:.0f} ms, max "
                   f"{times[-1] * 1e3:.0f} ms (window length "
                   f"{cfg.acquisition.window * cfg.acquisition.sample_period:g} s)")
    if cfg.recording.enabled:
        click.echo(f"recording: {Path(cfg.recording.path).resolve()} "
                   f"(open with: rerun {cfg.recording.path})")
    if cfg.zenoh.enabled:
        click.echo(f"health was published on {cfg.zenoh.key_prefix}/{cfg.machine.name}/health "
                   f"(zenoh, listening on {', '.join(cfg.zenoh.listen) or 'nothing'})")


@main.command("check-config")
@click.argument("config", type=click.Path(dir_okay=False, path_type=Path))
def check_config(config: Path) -> None:
    """Validate CONFIG; exit 0 if it is usable, 1 naming each bad key otherwise."""
    try:
        cfg = load_config(config)
    except ConfigError as exc:
        click.echo(str(exc), err=True)
        sys.exit(1)
    # Drivers validate what only they can check (DBC names, files, columns) at open time;
    # open them without starting acquisition where that cannot touch a device.
    if cfg.driver.type in ("file",) or (cfg.driver.type == "can"
                                        and getattr(cfg.driver, "log_file", None)):
        from twinwatch.drivers import create_driver
        from twinwatch.drivers.base import DriverError

        try:
            create_driver(cfg.driver, base_dir=config.resolve().parent).close()
        except DriverError as exc:
            click.echo(f"{config}: driver: {exc}", err=True)
            sys.exit(1)
    click.echo(f"{config}: OK ({cfg.machine.model} '{cfg.machine.name}', "
               f"{cfg.driver.type} driver, estimating {', '.join(cfg.estimation.estimate or [])})")


@main.command("sample-config")
def sample_config() -> None:
    """Print a commented sample configuration (the built-in default)."""
    click.echo(_SAMPLE_CONFIG.read_text(encoding="utf-8"), nl=False)


if __name__ == "__main__":  # pragma: no cover
    main()
