"""The documentation (issue 24): the README is the front page, the rest a site built from docs/.

* ``mkdocs build --strict`` passes (every page in the nav, every link resolves);
* the README is at most 300 lines and starts with the two commands a fresh machine runs;
* no page carries a leftover template placeholder (``@@NAME@@``);
* the configuration reference (docs/configuration.md) is the one the models generate today and
  names every key of every table the models define; the command reference (docs/cli.md) is
  the one the click commands print today;
* every shipped example configuration is in the examples table, each with its own recording.
"""

from __future__ import annotations

import dataclasses
import os
import re
import subprocess
import sys
import tomllib
import typing
from pathlib import Path

import pytest
from pydantic import BaseModel

from .helpers.paths import ROOT

sys.path.insert(0, str(ROOT / "scripts"))
import gen_cli_reference  # noqa: E402
import gen_config_reference as ref  # noqa: E402

PAGES = sorted((ROOT / "docs").glob("*.md"))
README = (ROOT / "README.md").read_text(encoding="utf-8")


def test_the_site_builds_in_strict_mode(tmp_path: Path) -> None:
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet",
                        "-f", str(ROOT / "mkdocs.yml"), "-d", str(tmp_path / "site")],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    assert (tmp_path / "site" / "configuration" / "index.html").exists()
    assert (tmp_path / "site" / "health-message" / "index.html").exists()
    # issue 37: on the site the first command was cut behind a scroll bar and the
    # configuration reference broke keys mid-word ("machine.option|s.structure"): shell
    # commands wrap, a key breaks after its dots only (seen in headless Chromium, 1280 px)
    css = (tmp_path / "site" / "stylesheets" / "extra.css").read_text(encoding="utf-8")
    assert re.search(r"code\.language-sh[^{]*\{[^}]*white-space: pre-wrap", css, re.S)
    # issue 57: TOML blocks were cut at the right edge (a scroll bar shown only under the
    # pointer): configuration blocks wrap too, every other block's scroll bar is always drawn
    assert re.search(r"code\.language-toml[^{]*\{[^}]*white-space: pre-wrap", css, re.S)
    assert re.search(r"pre > code \{[^}]*scrollbar-color: var\(--md-default-fg-color--light\)",
                     css)
    assert re.search(r"td:first-child code[^{]*\{[^}]*word-break: normal", css, re.S)
    start = (tmp_path / "site" / "getting-started" / "index.html").read_text(encoding="utf-8")
    assert "stylesheets/extra.css" in start
    assert '<code class="language-sh">python3 -m venv .venv &amp;&amp;' in start
    page = (tmp_path / "site" / "configuration" / "index.html").read_text(encoding="utf-8")
    assert "<td><code>machine.<wbr>options.<wbr>structure</code></td>" in page
    assert "<td><code>0.006</code></td>" in page  # a number is no key: never broken


def test_a_key_in_a_table_may_break_after_its_dots_only() -> None:
    import mkdocs_hooks

    assert mkdocs_hooks.wrap_keys(
        "<td><code>driver.columns.&lt;name&gt;.scale</code></td><td><code>0.5</code></td>"
        "<td><code>tcp/127.0.0.1:7447</code></td><td><code>float</code></td>") == (
        "<td><code>driver.<wbr>columns.<wbr>&lt;name&gt;.<wbr>scale</code></td>"
        "<td><code>0.5</code></td><td><code>tcp/127.0.0.1:7447</code></td>"
        "<td><code>float</code></td>")


def test_every_page_is_in_the_nav() -> None:
    nav = (ROOT / "mkdocs.yml").read_text(encoding="utf-8")
    missing = [p.name for p in PAGES if f": {p.name}" not in nav]
    assert missing == []


def test_the_readme_is_the_front_page() -> None:
    lines = README.splitlines()
    assert len(lines) <= 300, f"README.md is {len(lines)} lines (at most 300)"
    blocks = re.findall(r"```sh\n(.*?)\n```", README, flags=re.S)
    assert blocks[0] == ("python3 -m venv .venv && . .venv/bin/activate && pip install -e . "
                         "&& twinwatch run")
    assert blocks[1] == ("python3 -m venv .venv && . .venv/bin/activate && pip install -e "
                         "'.[test]' && python -m pytest -q -n 2")
    # CI runs exactly the README's test command
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8").splitlines()
    assert blocks[1].rsplit(" && ", 1)[1] in ci, ".ci/run does not run the README's tests"
    # the two commands come first: nothing but their one-line introductions before them
    assert README.index(blocks[1]) < 1000


def test_the_readme_shows_what_run_prints() -> None:
    """Four alarm lines (the RUL warning and alarm among them), the diagnosis's fault lines and
    the trend block."""
    section = README.split("## What `twinwatch run` prints", 1)[1].split("\n## ", 1)[0]
    alarm_lines = [ln for ln in section.splitlines() if "twinwatch.daemon.alarms" in ln]
    kinds = [re.search(r"dc-motor-sim: (RUL WARNING|WARNING|RUL ALARM|ALARM|FAULT CLEARED|"
                       r"FAULT):", ln).group(1) for ln in alarm_lines]  # type: ignore[union-attr]
    assert [k for k in kinds if not k.startswith("FAULT")] == ["RUL WARNING", "WARNING",
                                                               "RUL ALARM", "ALARM"]
    assert kinds.count("FAULT") >= 1 and "diagnosis: winding_short" in section
    assert "trend and remaining useful life (95 % intervals):" in section
    assert "Ra RUL alarm" in section


@pytest.mark.parametrize("path", [ROOT / "README.md", *PAGES], ids=lambda p: p.name)
def test_no_leftover_placeholder(path: Path) -> None:
    text = path.read_text(encoding="utf-8")
    assert re.findall(r"@@[A-Z_]+@@", text) == []


def test_the_configuration_reference_is_up_to_date() -> None:
    page = (ROOT / "docs" / "configuration.md").read_text(encoding="utf-8")
    assert page == ref.render(), (
        "docs/configuration.md is stale: run python scripts/gen_config_reference.py")


def test_the_command_reference_is_up_to_date() -> None:
    page = (ROOT / "docs" / "cli.md").read_text(encoding="utf-8")
    assert page == gen_cli_reference.render(), (
        "docs/cli.md is stale: run python scripts/gen_cli_reference.py")
    for command in ("run", "check-config", "sample-config", "identify", "watch", "tail"):
        assert f"## twinwatch {command}\n" in page


def _keys(model: type[BaseModel], prefix: str) -> set[str]:
    """Every key path of a model, walked independently of the generator: sub-tables whose
    type (or default) is a model, tables of tables, arrays of tables."""
    out: set[str] = set()
    for name, field in model.model_fields.items():
        key = prefix + (field.alias or name)
        out.add(key)
        subs = ref._models_in(field.annotation)
        if not subs and not field.is_required():
            default = field.get_default(call_default_factory=True)
            subs = [type(default)] if isinstance(default, BaseModel) else []
        tp = ref._unwrap(field.annotation)
        if subs:
            out |= _keys(subs[0], key + ".")
        elif typing.get_origin(tp) is dict and ref._models_in(typing.get_args(tp)[1]):
            out |= _keys(ref._models_in(typing.get_args(tp)[1])[0], key + ".<name>.")
        elif typing.get_origin(tp) is list and ref._models_in(typing.get_args(tp)[0]):
            out |= _keys(ref._models_in(typing.get_args(tp)[0])[0], key + "[].")
    return out


def test_the_configuration_reference_names_every_key() -> None:
    from twinwatch.config.alarms import AlarmConfig
    from twinwatch.config.loader import default_config
    from twinwatch.config.schema import TwinwatchConfig
    from twinwatch.drivers import BUILTIN_DRIVERS
    from twinwatch.sinks import BUILTIN_SINKS, HISTORIC_TABLES
    from twinwatch.twin.models import BUILTIN_MODELS

    page = (ROOT / "docs" / "configuration.md").read_text(encoding="utf-8")
    documented = set(re.findall(r"^\| `([^`]+)` \|", page, flags=re.M))
    cfg = default_config()
    expected: set[str] = set()
    for name in TwinwatchConfig.model_fields:
        if name in ("driver", "outputs", "alarms"):
            continue
        expected |= _keys(type(getattr(cfg, name)), name + ".")
    expected |= _keys(AlarmConfig, "alarms.")
    for spec in BUILTIN_DRIVERS.values():
        expected |= _keys(ref._load(spec).config_class, "driver.")
    for name, spec in BUILTIN_SINKS.items():
        table = HISTORIC_TABLES.get(name, f"outputs.{name}")
        expected |= _keys(ref._load(spec).config_class, table + ".")
    for spec in BUILTIN_MODELS.values():
        expected |= {f"machine.options.{f.name}" for f in dataclasses.fields(ref._load(spec))
                     if f.init and not f.name.startswith("_")}
    assert "acquisition.adaptive.min_window" in expected
    assert "outputs.mqtt.home_assistant.enabled" in expected or any(
        k.startswith("outputs.mqtt.home_assistant.") for k in expected)
    assert expected - documented == set(), "keys missing from docs/configuration.md"


def test_every_example_is_listed_and_records_behind_its_own_link() -> None:
    table = (ROOT / "docs" / "getting-started.md").read_text(encoding="utf-8")
    examples = sorted((ROOT / "config").glob("*.toml"))
    links: dict[str, str] = {}
    for path in examples:
        assert f"| `{path.name}` |" in table, f"{path.name} missing from the examples table"
        assert f"| `{path.name}` |" in README, f"{path.name} missing from the README's table"
        rec = tomllib.loads(path.read_text()).get("recording", {}).get("path", "twinwatch.rrd")
        assert rec not in links, f"{path.name} and {links.get(rec)} both record behind {rec}"
        links[rec] = path.name


def test_every_benchmark_and_script_imports_what_exists() -> None:
    """Each ``from twinwatch... import name`` in benchmarks/ and scripts/ names a module or an
    attribute that exists: the benchmarks run outside the suite, and one moved function
    (``render_fleet``, to ``twinwatch.watch.render_fleet``) broke bench_fleet unseen."""
    import ast
    import importlib

    missing = []
    for path in sorted([*(ROOT / "benchmarks").glob("*.py"), *(ROOT / "scripts").glob("*.py")]):
        for node in ast.walk(ast.parse(path.read_text())):
            if not (isinstance(node, ast.ImportFrom) and node.module
                    and node.module.split(".")[0] == "twinwatch"):
                continue
            module = importlib.import_module(node.module)
            for alias in node.names:
                if hasattr(module, alias.name):
                    continue
                try:
                    importlib.import_module(f"{node.module}.{alias.name}")
                except ImportError:
                    missing.append(f"{path.name}: from {node.module} import {alias.name}")
    assert not missing, missing
