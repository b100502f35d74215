"""What a valid configuration still needs from the machine it runs on, checked before anything
is opened: the files it names exist, the directories it writes to exist, and the driver delivers
every channel the twin needs. ``twinwatch check-config`` and ``twinwatch run`` (at start and on
each SIGHUP) call the same :func:`check_runnable`; run refuses with exit status 78.

Drivers and outputs take part without being named here: a driver configuration may provide
``twin_channels() -> tuple[str, ...]`` (the twin channels it delivers) and
``required_files(base_dir) -> dict[str, Path]`` (config key -> file that must exist); every
output's table (:class:`~twinwatch.sinks.base.SinkConfig`) says which files it reads
(``input_files``: they must exist and be readable) and which it creates (``output_files``: their
directory must exist and be writable).
"""

from __future__ import annotations

import os
from pathlib import Path

from twinwatch.config.loader import ConfigError
from twinwatch.config.schema import TwinwatchConfig
from twinwatch.sinks import sink_class
from twinwatch.twin.models import create_model

__all__ = ["check_runnable", "referenced_files", "runnable_problems"]


def _dir_problem(key: str, path: Path) -> str | None:
    """Why the file ``path`` cannot be created (its directory), or None."""
    parent = path.parent
    if not parent.exists():
        return f"{key}: directory {parent} does not exist: create it or change {key}"
    if not parent.is_dir():
        return f"{key}: {parent} is not a directory"
    if not os.access(parent, os.W_OK | os.X_OK):
        return f"{key}: directory {parent} is not writable by this user"
    if path.is_dir():
        return f"{key}: {path} is a directory: give a file name"
    return None


def _file_problem(key: str, f: Path, *, readable: bool = False) -> str | None:
    """Why the file ``f`` cannot be read, or None."""
    if f.is_dir():
        return f"{key}: {f} is a directory: give the file in it"
    if not f.is_file():
        return f"{key}: file {f} not found"
    if readable and not os.access(f, os.R_OK):
        return f"{key}: file {f} is not readable by this user"
    return None


def runnable_problems(cfg: TwinwatchConfig, *, base_dir: Path, cwd: Path | None = None,
                      persist: bool = True) -> list[str]:
    """Everything that keeps ``cfg`` from starting here, one ``key: why`` line each.

    Args:
        cfg: a validated configuration.
        base_dir: the configuration file's directory (driver files are relative to it).
        cwd: the working directory (the recording and the state database are relative to
            it); default the current one.
        persist: the gate (the state database) will be opened (the CLI's run).

    Returns:
        The problems, empty if none.
    """
    cwd = Path.cwd() if cwd is None else cwd
    problems: list[str] = []
    required_files = getattr(cfg.driver, "required_files", None)
    files = required_files(base_dir) if required_files is not None else {}
    found = [_file_problem(key, Path(path)) for key, path in files.items()]
    for output in cfg.output_tables():
        if not output.config.enabled or (not persist and sink_class(output.name).role == "gate"):
            continue
        found += [_file_problem(f"{output.key}.{key}", Path(file), readable=True)
                  for key, file in output.config.input_files().items()]
        found += [_dir_problem(f"{output.key}.{key}", path)
                  for key, path in output.config.output_files(cwd).items()]
    problems += [p for p in found if p]
    channels = getattr(cfg.driver, "twin_channels", None)
    if channels is not None:
        delivered = set(channels())
        model = create_model(cfg.machine.model, cfg.machine.options)
        missing = [c for c in model.required_channels() if c not in delivered]
        structure = getattr(model, "structure", None)
        what = f"the {structure + ' ' if structure else ''}{cfg.machine.model} twin"
        for ch in missing:
            hint = f"map {ch!r} in [driver]"
            if ch == "setpoint" and structure == "closed_loop":
                hint += ' or set machine.options.structure = "open_loop"'
            problems.append(f"driver: {what} needs channel {ch!r}, which "
                            f"the {cfg.driver.type} driver does not deliver (it delivers "
                            f"{', '.join(sorted(delivered))}): {hint}")
    return problems


def referenced_files(cfg: TwinwatchConfig, *, base_dir: Path,
                     cwd: Path | None = None) -> dict[str, Path]:
    """Every file the configuration reads besides itself, config key -> path: the driver's
    (``required_files``: a DBC, a CAN log, a recording; relative to ``base_dir``), the enabled
    outputs' (``input_files``: certificates, keys, password files) and the fault library
    (``diagnosis.library``, relative to ``cwd``, default the current directory). A reload
    compares their contents to know whether a machine changed (:mod:`twinwatch.daemon.host`).
    """
    cwd = Path.cwd() if cwd is None else cwd
    files: dict[str, Path] = {}
    required_files = getattr(cfg.driver, "required_files", None)
    if required_files is not None:
        files.update({key: Path(path) for key, path in required_files(base_dir).items()})
    for output in cfg.output_tables():
        if output.config.enabled:
            files.update({f"{output.key}.{key}": Path(file)
                          for key, file in output.config.input_files().items()})
    library = cfg.diagnosis.library if cfg.diagnosis.enabled else None
    if library is not None:
        path = Path(library).expanduser()
        files["diagnosis.library"] = path if path.is_absolute() else cwd / path
    return files


def check_runnable(cfg: TwinwatchConfig, source: str, *, base_dir: Path,
                   cwd: Path | None = None, persist: bool = True) -> None:
    """Raise :class:`ConfigError` listing :func:`runnable_problems`, if any.

    Raises:
        ConfigError: ``"<source>: cannot run this configuration"`` and one line per problem.
    """
    problems = runnable_problems(cfg, base_dir=base_dir, cwd=cwd, persist=persist)
    if problems:
        raise ConfigError("\n".join([f"{source}: cannot run this configuration",
                                     *(f"  {p}" for p in problems)]))
