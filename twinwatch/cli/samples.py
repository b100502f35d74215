"""``twinwatch sample-config``: a commented sample configuration for any registered driver.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import click


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


@click.command("sample-config")
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
