"""Gateway mode: the machines of a directory in one service (``twinwatch run DIR``).

The service itself is :class:`~twinwatch.daemon.host.Host` (the one code path for a machine
and for a directory); :class:`Gateway` is the host on a directory, kept under its name for the
gateway's callers, with the estimation slots (:mod:`twinwatch.daemon.slots`) beside it.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from twinwatch.daemon.host import MACHINE_GLOB, Host, Machine
from twinwatch.daemon.slots import EstimationSlots, default_workers
from twinwatch.errors import ConfigError

if TYPE_CHECKING:
    from twinwatch.config.schema import TwinwatchConfig

__all__ = ["MACHINE_GLOB", "EstimationSlots", "Gateway", "Machine", "default_workers"]


class Gateway(Host):
    """The host on a directory of machine configurations (:class:`Host`'s arguments; a
    machine counts as stuck after ``stuck_after`` = 30 s of one window, as quiet after
    ``quiet_after`` = 30 s without one).

    Raises:
        ConfigError: ``directory`` is not a directory.
    """

    def __init__(self, directory: Path, *, read: Callable[[Path], TwinwatchConfig],
                 check: Callable[[TwinwatchConfig, Path, Path], None],
                 work_root: Path | None = None, resume: bool | None = None,
                 duration: float | None = None, workers: int | None = None,
                 stuck_after: float = 30.0, quiet_after: float = 30.0) -> None:
        if not directory.is_dir():
            raise ConfigError(f"{directory}: not a directory of machine configurations")
        super().__init__(directory, read=read, check=check, work_root=work_root,
                         resume=resume, duration=duration, workers=workers,
                         stuck_after=stuck_after, quiet_after=quiet_after)

    def start(self, timeout: float | None = 60.0) -> None:
        """:meth:`Host.start`, READY after at most ``timeout`` seconds [s] (None: no limit)."""
        self.start_timeout = timeout
        super().start()
