"""The suite's own rules (issue 57): a test module imports no other test module (nor
``conftest``); what tests share lives in ``tests/helpers/``, and what they share with the
benchmarks in ``harness/``; ``benchmarks/`` and ``harness/`` import nothing of ``tests``.
Read from every module's syntax tree, function-level imports included."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _imported(path: Path) -> list[str]:
    """The absolute module names ``path`` imports (relative imports resolved)."""
    package = ".".join(path.relative_to(ROOT).parent.parts)
    names = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                module = ".".join([*base, *([node.module] if node.module else [])])
            else:
                module = node.module or ""
            names += [module] + [f"{module}.{a.name}" for a in node.names]
    return names


def _test_module(name: str) -> bool:
    parts = name.split(".")
    return parts[0] == "tests" and any(p.startswith("test_") or p == "conftest" for p in parts)


def test_no_test_module_imports_another() -> None:
    bad = [f"{p.relative_to(ROOT)}: {n}" for p in sorted(ROOT.glob("tests/**/*.py"))
           for n in _imported(p) if _test_module(n)]
    assert bad == []


def test_benchmarks_and_the_harness_import_nothing_of_the_tests() -> None:
    bad = [f"{p.relative_to(ROOT)}: {n}"
           for p in sorted([*ROOT.glob("benchmarks/*.py"), *ROOT.glob("harness/*.py")])
           for n in _imported(p) if n.split(".")[0] == "tests"]
    assert bad == []


def test_the_check_sees_a_test_module_imported() -> None:
    assert _test_module("tests.test_service.db_rows") and _test_module("tests.conftest.ROOT")
    assert not _test_module("tests.helpers.net.free_port")
    here = _imported(Path(__file__))
    assert "ast" in here and not any(_test_module(n) for n in here)
