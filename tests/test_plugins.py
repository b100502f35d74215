"""What a registry says when a module cannot be imported (issue 57: the hint named extras,
``twinwatch[mqtt]`` and ``twinwatch[watch]``, that pyproject.toml does not define)."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

from twinwatch import plugins

ROOT = Path(__file__).resolve().parents[1]

PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]


def _name(requirement: str) -> str:
    return re.split(r"[\s\[<>=!~;]", requirement, maxsplit=1)[0].lower().replace("_", "-")


def test_a_missing_dependency_is_named_with_its_distribution_and_no_extra() -> None:
    hint = plugins._install_hint(ModuleNotFoundError("No module named 'paho'", name="paho.mqtt"),
                                 "twinwatch.sinks.mqtt")
    assert "paho-mqtt is a dependency of twinwatch" in hint
    assert "pip install paho-mqtt" in hint and "twinwatch[" not in hint


def test_a_plugin_package_missing_is_named_as_such() -> None:
    hint = plugins._install_hint(ModuleNotFoundError("x", name="acme_twin"), "acme_twin.driver")
    assert hint.startswith("Is the package that provides acme_twin.driver installed")
    hint = plugins._install_hint(ModuleNotFoundError("x", name="serial"), "acme_twin.driver")
    assert hint == "Install the package that provides 'serial' (pip install serial)"


def test_the_import_names_map_to_dependencies_that_exist() -> None:
    dependencies = {_name(r) for r in PYPROJECT["dependencies"]}
    assert set(plugins._DISTRIBUTIONS.values()) <= dependencies


def test_every_extra_the_package_and_the_docs_name_exists() -> None:
    """``twinwatch[<extra>]`` in the package's messages, ``.[<extra>]`` in the docs' commands:
    each names an extra of pyproject.toml (``pip install -e '.[docs]'`` did not exist)."""
    extras = set(PYPROJECT["optional-dependencies"])
    named = set()
    for path in (ROOT / "twinwatch").rglob("*.py"):
        named |= set(re.findall(r"twinwatch\[([\w,-]+)\]", path.read_text(encoding="utf-8")))
    for path in [ROOT / "README.md", *(ROOT / "docs").glob("*.md")]:
        named |= set(re.findall(r"(?:twinwatch|\.)\[([\w,-]+)\]'", path.read_text(
            encoding="utf-8")))
    named = {e for group in named for e in group.split(",")}
    assert {"test", "docs"} <= named  # the scan sees the install commands at all
    assert named <= extras


def test_the_docs_extra_builds_the_site() -> None:
    """The docs extra holds what mkdocs.yml needs: MkDocs and its theme."""
    docs = {_name(r) for r in PYPROJECT["optional-dependencies"]["docs"]}
    theme = re.search(r"^theme:\s*\n\s+name:\s*(\w+)", (ROOT / "mkdocs.yml").read_text(),
                      re.MULTILINE)
    assert theme is not None
    assert {"mkdocs", f"mkdocs-{theme[1]}"} <= docs
