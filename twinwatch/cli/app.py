"""The command group (``twinwatch``), the logging every command sets up, the exit status of a
configuration that cannot run (78) and the loading of a configuration as ``run`` and
``check-config`` read it.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

import click

from twinwatch import __version__

if TYPE_CHECKING:
    from twinwatch.config.schema import TwinwatchConfig


def setup_logging(level: str, threads: bool = False) -> None:
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


def fail(message: object, status: int = 1) -> NoReturn:
    """Say ``Error: <message>`` on stderr and exit with ``status``."""
    click.echo(f"Error: {message}", err=True)
    sys.exit(status)


def load_runnable(config: Path | None, base_dir: Path,
                   cwd: Path | None = None, *, force: bool | None = None) -> TwinwatchConfig:
    """Load CONFIG (or the built-in default) and check it can run here: the files it names
    and the directories it writes to exist, the driver delivers every channel the twin needs
    (:mod:`twinwatch.config.preflight`, the check ``check-config`` makes too).

    Raises:
        ConfigError: naming each bad key, missing file or directory, unmapped channel.
    """
    from twinwatch.config.loader import ConfigError, default_config, load_config
    from twinwatch.config.preflight import check_runnable

    cfg = load_config(config) if config else default_config()
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
