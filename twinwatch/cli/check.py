"""``twinwatch check-config``: a configuration (or a gateway's directory) validated and checked
as ``run`` would start it.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import click

from twinwatch.cli.app import load_runnable


@click.command("check-config")
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
    sparkplug: list[tuple[str, str, Any]] = []
    for path in files:
        ok, line = _check_one(path, names=names, sparkplug=sparkplug)
        click.echo(line, err=not ok)
        failed += not ok
    if sparkplug:  # what only the gateway's machines together can clash on
        from twinwatch.sinks.sparkplug.config import node_clashes

        clashes = node_clashes(sparkplug)
        for line in clashes:
            click.echo(line, err=True)
        failed += len({line.split(":", 1)[0] for line in clashes})
    from twinwatch.daemon.host import skipped

    for entry, why in skipped(config).items():
        click.echo(f"{config / entry}: skipped: {why}")
    click.echo(f"{config}: {len(files) - failed} of {len(files)} machine configurations OK")
    if failed:
        sys.exit(1)


def _check_one(config: Path, names: dict[str, Path] | None = None, *,
               force: bool | None = None,
               sparkplug: list[tuple[str, str, Any]] | None = None) -> tuple[bool, str]:
    """``check-config`` on one file: (usable, the line to print). ``names``: the machine
    names seen so far in a gateway's directory (a second file naming one fails).
    ``sparkplug``: a usable file's enabled ``[outputs.sparkplug]`` is appended there as (file
    name, machine, table), for the gateway's clashes between machines. ``force``:
    a single file is checked as ``run`` loads it (a commissioning file refused unless True);
    None (a gateway's file): as the gateway loads it."""
    from twinwatch.config.loader import ConfigError

    try:
        cfg = load_runnable(config, config.resolve().parent)
    except ConfigError as exc:
        return False, str(exc)
    refused: str | None = None
    if force is not None and cfg.machine.purpose == "commissioning":
        try:  # what `run` says of it (said once the source was opened: valid for identify)
            load_runnable(config, config.resolve().parent, force=force)
        except ConfigError as exc:
            refused = str(exc)
    if names is not None:
        other = names.setdefault(cfg.machine.name, config)
        if other != config:
            return False, (f"{config}: machine.name {cfg.machine.name!r} is already used by "
                           f"{other.name}: each machine of a gateway needs a name of its own")
    # Drivers check what only they can (DBC names, files, columns) when the source opens:
    # open it without acquiring or sending (a live interface receive-only where it allows).
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
    if sparkplug is not None:
        for out in cfg.output_tables():
            if out.name == "sparkplug" and getattr(out.config, "enabled", True):
                sparkplug.append((str(config), cfg.machine.name, out.config))
    if refused is not None:
        return False, (f"{refused}; it is valid for `twinwatch identify {config}` "
                       f"({cfg.machine.model} '{cfg.machine.name}', {cfg.driver.type} driver)")
    return True, (f"{config}: OK ({cfg.machine.model} '{cfg.machine.name}', "
                  f"{cfg.driver.type} driver, estimating "
                  f"{', '.join(cfg.estimation.estimate or [])})"
                  + (f"; source: {probed}" if probed and probed != "opened" else ""))
