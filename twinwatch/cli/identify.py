"""``twinwatch identify``: commissioning, a machine's baseline identified from a recording
(:mod:`twinwatch.commissioning`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from twinwatch.cli.app import EX_CONFIG, fail, setup_logging


def _fraction_range(value: str | None) -> tuple[float, float] | None:
    if value is None:
        return None
    try:
        a, b = (float(x) for x in value.split(":"))
    except ValueError:
        raise click.BadParameter(f"{value!r}: give START:END as fractions, e.g. 0:0.5") from None
    return a, b


@click.command()
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

    setup_logging(log_level)
    try:
        cfg = load_config(config)
        update: dict[str, Any] = {}
        for key, value in (("train", _fraction_range(train)),
                           ("validate", _fraction_range(validate))):
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
            table = {**cfg.identify.model_dump(by_alias=True), **update}  # by alias: validate
            cfg = cfg.model_copy(update={"identify": type(cfg.identify).model_validate(table)})
            for name in cfg.identify.weights:
                if name not in _outputs(cfg):
                    raise ConfigError(f"--weight {name}: not an output of the twin")
    except ValueError as exc:  # a ConfigError, or a bad --train/--validate range
        fail(exc, EX_CONFIG)
    from twinwatch.commissioning.commission import CommissionError, commission
    from twinwatch.commissioning.identify import parameters_block
    from twinwatch.commissioning.report import report
    from twinwatch.drivers import DriverError

    try:
        found = commission(cfg, config.resolve().parent, duration=duration, record=record)
    except (CommissionError, DriverError) as exc:
        fail(f"cannot identify: {exc}")
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
