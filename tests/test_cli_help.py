"""Every ``--help`` names only options that exist (issue 57: ``explain --help`` and ``tail
--help`` described a ``--fleet`` they lack, ``fleet report --config`` said "watch").

Read from the click commands themselves (no subprocess): each command's help page as
``--help`` prints it; an option it names must be one of its own, unless the text names the
command it belongs to (``twinwatch watch --fleet``, ``see `twinwatch watch --help```), where it
must be one of that command's.
"""

from __future__ import annotations

import re
from collections.abc import Iterator

import click
import pytest

from twinwatch.cli import main

#: ``twinwatch <command> [<subcommand>] --opt ...``: options named with their command
QUALIFIED = re.compile(r"twinwatch((?: [a-z][a-z-]*)+)"
                       r"((?:\s+--[a-z][a-z0-9-]*(?:[ =][^\s`-][^\s`]*)?)+)")
OPTION = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")


def _commands(group: click.Group = main, path: tuple[str, ...] = ()
              ) -> Iterator[tuple[tuple[str, ...], click.Command]]:
    ctx = click.Context(group)
    for name in group.list_commands(ctx):
        command = group.get_command(ctx, name)
        assert command is not None
        yield (*path, name), command
        if isinstance(command, click.Group):
            yield from _commands(command, (*path, name))


COMMANDS = dict(_commands())


def _own(command: click.Command) -> set[str]:
    flags = {"--help"}
    for p in command.params:
        if isinstance(p, click.Option):
            flags |= {o for o in (*p.opts, *p.secondary_opts) if o.startswith("--")}
    return flags


def _help(path: tuple[str, ...], command: click.Command) -> str:
    parent = click.Context(main, info_name="twinwatch")
    ctx = click.Context(command, info_name=" ".join(path), parent=parent)
    return command.get_help(ctx)


def named_options(path: tuple[str, ...], text: str) -> list[str]:
    """The options ``text`` names that the command they are named for lacks, each as
    ``"twinwatch <command> --opt"``."""
    missing = []
    unwrapped = re.sub(r"\s+", " ", text)

    def qualified(m: re.Match[str]) -> str:
        words = m[1].split()
        # the longest prefix of the words that names a command (``fleet report``, ``watch``)
        target = next((tuple(words[:k]) for k in range(len(words), 0, -1)
                       if tuple(words[:k]) in COMMANDS), None)
        if target is None:
            return m[0]  # not a command (``twinwatch run DIR --workers``: checked below)
        for opt in OPTION.findall(m[2]):
            if opt not in _own(COMMANDS[target]):
                missing.append(f"twinwatch {' '.join(target)} {opt}")
        return ""

    rest = QUALIFIED.sub(qualified, unwrapped)
    own = _own(COMMANDS[path])
    missing += [f"twinwatch {' '.join(path)} {opt}" for opt in OPTION.findall(rest)
                if opt not in own]
    return missing


@pytest.mark.parametrize("path", sorted(COMMANDS), ids=" ".join)
def test_every_option_a_help_text_names_exists(path: tuple[str, ...]) -> None:
    command = COMMANDS[path]
    text, _, listed = _help(path, command).partition("\nCommands:\n")
    missing = named_options(path, text)
    if isinstance(command, click.Group):  # a subcommand's summary names its own options
        assert listed
        for name in command.list_commands(click.Context(command)):
            sub = (*path, name)
            missing += named_options(sub, COMMANDS[sub].get_short_help_str(limit=10_000))
    assert missing == []


def test_fleet_reports_config_option_says_what_the_report_does() -> None:
    """``fleet report --config`` reads the machines' summaries: its help said "watch"."""
    (config,) = [p for p in COMMANDS[("fleet", "report")].params if p.name == "config"]
    assert isinstance(config, click.Option) and config.help is not None
    assert "watch" not in config.help and config.help.startswith("Also ask the machines")


def test_the_check_sees_an_option_a_command_lacks() -> None:
    """The check itself: an option the command lacks is found, alone or named with another
    command; one named with the command that has it is not."""
    tail = ("tail",)
    assert named_options(tail, "Connects where watch does (--connect).") == []
    assert named_options(tail, "with --fleet and for fleet report") == ["twinwatch tail --fleet"]
    assert named_options(tail, "see `twinwatch watch --help`; `twinwatch watch --fleet`") == []
    assert named_options(tail, "`twinwatch watch --fleets`") == ["twinwatch watch --fleets"]
    assert named_options(("fleet", "report"), "as `twinwatch fleet report --horizon 7d`") == []


def test_every_command_is_checked() -> None:
    assert {("run",), ("watch",), ("tail",), ("explain",), ("fleet",), ("fleet", "report"),
            ("check-config",), ("sample-config",), ("identify",)} <= set(COMMANDS)
