"""Command line: ``twinwatch run``, ``twinwatch check-config``, ``twinwatch sample-config``.

The only module that prints. Everything else logs. Each command imports what it needs when it
runs, so ``twinwatch --help`` loads click and nothing else (``benchmarks/bench_startup.py``).
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from twinwatch import __version__

if TYPE_CHECKING:
    from twinwatch.config.schema import TwinwatchConfig

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
    from twinwatch.config.loader import ConfigError, default_config, load_config
    from twinwatch.daemon.supervisor import StartError, Supervisor

    def load() -> TwinwatchConfig:
        return load_config(config) if config else default_config()

    supervisor = Supervisor(load, base_dir=config.resolve().parent if config else Path.cwd(),
                            source=str(config) if config else "the built-in default")
    _setup_logging(log_level)
    try:
        supervisor.start()
    except ConfigError as exc:
        click.echo(f"Error: {exc}", err=True)
        sys.exit(EX_CONFIG)
    except StartError as exc:
        raise click.ClickException(f"cannot start: {exc}") from None
    cfg = supervisor.config
    assert cfg is not None

    from twinwatch.drivers import get_driver_class

    total = duration if duration is not None else (
        get_driver_class(cfg.driver.type).duration(cfg.driver))
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

        supervisor.add_callback(_progress)
    try:
        supervisor.run(duration=duration)
    except StartError as exc:
        raise click.ClickException(f"cannot restart after a reload: {exc}") from None
    finally:
        if bar is not None:
            bar.close()
    assert supervisor.config is not None and supervisor.daemon is not None
    _print_summary(supervisor.config, supervisor.daemon)


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
        fused = p.get("fused") or {}
        status = {"estimated": "estimated",
                  "fused": f"fused over the windows (this one alone: {p['reason']})",
                  "held": f"held: {p['reason']}"}.get(
            p["status"], p["reason"] or p["status"])  # tied, fixed: the reason says to what
        if fused.get("value") is not None and p["status"] in ("estimated", "held"):
            status += (f"; fused {fused['value']:.6g} +- {2 * fused['rel_std_pct']:.2g} % "
                       "(2 sigma)")
        dev = p["deviation_pct"]
        click.echo(f"  {name:<3} = {p['value']:<11.6g} {p['unit']:<10} "
                   f"({'n/a' if dev is None else f'{dev:+.2f}'} % vs nominal {p['nominal']:g}) "
                   f"{status}")
    disc = last.get("discovery") or {}
    if disc.get("enabled"):
        terms = last.get("terms") or []
        res = last.get("residual") or {}
        check = last.get("model_check") or {}
        if terms:
            verdict = ":"
        elif disc.get("too_large") or check.get("passed") is False:
            verdict = (": none kept, yet the residual is too large for the physical model "
                       "(no candidate meta-model describes what it misses)")
        else:
            verdict = ": the physical model explains the data"
        click.echo(f"twin structure (DT''): {len(terms)} meta-model term(s){verdict}")
        for term in terms:
            click.echo(f"  {term['equation']}  [{term['meaning']}]")
        worst = {k: (res.get(v) or {}).get("max_abs") or {} for k, v in
                 (("DT'", "dt_prime"), ("DT''", "dt_second"))}
        if terms:
            click.echo("  worst error in the last window: " + "; ".join(
                f"{k} " + ", ".join(f"{o} {e:.3g}" for o, e in w.items() if e is not None)
                for k, w in worst.items() if w))
    checks = [h["model_check"]["passed"] for h in daemon.history if h.get("model_check")]
    if checks:
        failed = len(checks) - sum(checks)
        reasons = (last.get("model_check") or {}).get("reasons") or []
        click.echo(f"model check: passed in {sum(checks)} of {len(checks)} windows"
                   + (f"; failing windows are not trusted and their intervals widened (last: "
                      f"{reasons[0]})" if failed and reasons else ""))
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
    from twinwatch.config.loader import ConfigError, load_config

    try:
        cfg = load_config(config)
    except ConfigError as exc:
        click.echo(str(exc), err=True)
        sys.exit(1)
    # Drivers validate what only they can check (DBC names, files, columns) at open time;
    # open them without starting acquisition where that cannot touch a device.
    from twinwatch.drivers import DriverError, create_driver, get_driver_class

    if get_driver_class(cfg.driver.type).safe_to_probe(cfg.driver):
        try:
            create_driver(cfg.driver, base_dir=config.resolve().parent).close()
        except DriverError as exc:
            click.echo(f"{config}: driver: {exc}", err=True)
            sys.exit(1)
    click.echo(f"{config}: OK ({cfg.machine.model} '{cfg.machine.name}', "
               f"{cfg.driver.type} driver, estimating {', '.join(cfg.estimation.estimate or [])})")


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
              help="Write the fits and residuals of both ranges to this Rerun file.")
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
    (one free-run simulation over the whole range), gives every parameter its interval,
    scores the fit on the validation range (fit % per output), and prints a
    [machine.parameters] block with the bounds it used, ready to paste into the monitoring
    configuration. Exit 78 for a bad configuration, 1 if the recording cannot be identified
    from."""
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
    from twinwatch.daemon.commission import CommissionError, commission, report
    from twinwatch.drivers import DriverError
    from twinwatch.twin.identify import parameters_block

    try:
        result, data = commission(cfg, config.resolve().parent, duration=duration,
                                  record=record)
    except (CommissionError, DriverError) as exc:
        click.echo(f"Error: cannot identify: {exc}", err=True)
        sys.exit(1)
    click.echo(f"{data.t.size} samples from {data.source}"
               + (f" ({data.dropped} left out: a channel missing or not finite)"
                  if data.dropped else ""))
    click.echo(report(result))
    block = parameters_block(result, f"{config} ({data.t.size} samples)")
    click.echo("")
    click.echo(block, nl=False)
    if output is not None:
        output.write_text(block, encoding="utf-8")
        click.echo(f"written to {output}")
    if record is not None:
        click.echo(f"fits and residuals: {record} (open with: rerun {record})")


def _outputs(cfg: Any) -> list[str]:
    from twinwatch.twin.registry import create_model

    return list(create_model(cfg.machine.model, cfg.machine.options).output_names)


@main.command("sample-config")
def sample_config() -> None:
    """Print a commented sample configuration (the built-in default)."""
    click.echo(_SAMPLE_CONFIG.read_text(encoding="utf-8"), nl=False)


if __name__ == "__main__":  # pragma: no cover
    main()
