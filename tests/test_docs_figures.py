"""The figures and commands the docs quote still hold (issue 37: the fast lane's count and time,
getting-started's and motoshield's run times and gateway.md's ``--workers 0`` row had drifted
from what the code does). Each measured figure names the script that measures it
(``scripts/docs_figures.py``); where checking it is cheap, a test does."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import click
import pytest

from twinwatch.cli import main

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

# a value standing for any (`--workers N`, `--config <file>`, `--train START:END`)
PLACEHOLDER = re.compile(r"^(?:[A-Z][A-Z_:]*|<[^>]*>|\.\.\.|\{[^}]*\})$")


def _options() -> dict[str, list[click.Option]]:
    """Every option of every ``twinwatch`` command (hidden ones too), by its flag."""
    out: dict[str, list[click.Option]] = {}
    ctx = click.Context(main)
    for name in main.list_commands(ctx):
        command = main.get_command(ctx, name)
        assert command is not None
        for p in command.params:
            if isinstance(p, click.Option):
                for flag in p.opts:
                    out.setdefault(flag, []).append(p)
    return out


OPTION = re.compile(r"(?<![\w-])(--[a-z][a-z0-9-]*)(?:=|[ \t]+)([^\s`|;,)\]]+)")


def _quoted(text: str, known: set[str]) -> list[tuple[str, str]]:
    """``(--option, value)`` given to ``twinwatch``: in each command line of a code span or
    block (``twinwatch run DIR --workers 2``), and in an inline span of ``twinwatch``'s
    options alone (``known``; a table row's ``--workers 0``); not in another program's line
    (``bench_density.py --mode gateway``) nor in prose quoted in a block (the CLI reference's
    help text)."""
    commands = []
    for span in re.findall(r"```.*?```|`[^`\n]+`", text, re.DOTALL):
        body = span.strip("`")
        for line in body.splitlines():
            line = re.sub(r"^\s*(?:\$\s*|sudo\s+)?", "", line).split("#", 1)[0]
            if line.startswith("twinwatch ") or (
                    not span.startswith("```") and line.startswith("--")
                    and set(re.findall(r"--[a-z][a-z0-9-]*", line)) <= known):
                commands.append(line)
    return OPTION.findall("\n".join(commands))


def test_the_docs_quote_no_option_value_the_cli_rejects() -> None:
    """A docs row or command giving a ``twinwatch`` option a value the CLI refuses (gateway.md
    had a measured row for ``--workers 0``, which ``run`` rejects since ``--workers`` counts
    processes)."""
    options = _options()
    bad = []
    checked = 0
    for doc in DOCS:
        for flag, value in _quoted(doc.read_text(encoding="utf-8"), set(options)):
            params = [p for p in options.get(flag, []) if not p.is_flag and not p.count]
            if not params or PLACEHOLDER.match(value) or value.startswith("-"):
                continue
            checked += 1
            errors = []
            for p in params:
                try:
                    p.type.convert(value, p, None)
                except click.BadParameter as exc:
                    errors.append(str(exc))
                else:
                    break
            else:
                bad.append(f"{doc.relative_to(ROOT)}: {flag} {value}: {errors[0]}")
    assert checked > 20, checked  # the scan sees the docs' options at all
    assert not bad, "\n".join(bad)


def _fast_lane_counts() -> dict[str, int]:
    """The fast lane's test count each of README.md and getting-started.md quotes."""
    out = {}
    for doc in (ROOT / "README.md", ROOT / "docs" / "getting-started.md"):
        text = doc.read_text(encoding="utf-8")
        m = re.search(r"the fast lane:.*?(\d+) tests, counted by", text, re.DOTALL)
        assert m is not None, f"{doc.name} quotes no fast-lane count"
        out[doc.name] = int(m.group(1))
    return out


@pytest.mark.slow  # collecting the whole suite: about 10 s on the shared 2-core box
def test_the_fast_lane_count_the_docs_quote_is_within_10_percent_of_the_collected() -> None:
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import docs_figures
    finally:
        sys.path.remove(str(ROOT / "scripts"))
    measured = docs_figures.fast_lane_count()
    for doc, quoted in _fast_lane_counts().items():
        assert abs(quoted - measured) <= 0.1 * measured, (
            f"{doc} says the fast lane is {quoted} tests, it collects {measured}: "
            f"python scripts/docs_figures.py fast-lane")


def test_each_measured_run_time_names_the_script_that_measures_it() -> None:
    """The run times the getting-started guide and the MotoShield page quote, and the fast
    lane's count, come with the command that measures them again."""
    for doc, command in (("README.md", "scripts/docs_figures.py fast-lane"),
                         ("docs/getting-started.md", "scripts/docs_figures.py fast-lane"),
                         ("docs/getting-started.md", "scripts/docs_figures.py main-job"),
                         ("docs/motoshield.md", "scripts/docs_figures.py motoshield")):
        assert command in (ROOT / doc).read_text(encoding="utf-8"), (doc, command)
    assert len(set(_fast_lane_counts().values())) == 1  # one figure, not two
