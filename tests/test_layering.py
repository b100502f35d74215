"""The package structure: no import cycle between twinwatch's sub-packages.

Read statically from the modules' syntax trees (nothing is imported): every ``import`` and
``from ... import`` anywhere in a module counts, also inside functions (a lazy import is still
a dependency), except those under ``if TYPE_CHECKING:`` (annotations, never executed).
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import twinwatch

ROOT = Path(twinwatch.__file__).parent
#: the sub-packages the issue names; every other first-level name is checked too
CORE = ("config", "daemon", "drivers", "twin", "plant")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _imports(tree: ast.AST, module: str, is_package: bool) -> list[tuple[str, int]]:
    """(imported module, line) for every runtime import in ``tree``."""
    found: list[tuple[str, int]] = []

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            found.extend((alias.name, node.lineno) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                base = base[: len(base) - node.level + (1 if is_package else 0)]
                target = ".".join([*base, node.module] if node.module else base)
            else:
                target = node.module or ""
            found.append((target, node.lineno))
            # ``from twinwatch import drivers`` imports the sub-package
            found.extend((f"{target}.{alias.name}", node.lineno) for alias in node.names)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return found


def _package_of(module: str) -> str | None:
    parts = module.split(".")
    if parts[0] != "twinwatch" or len(parts) < 2:
        return None
    first = parts[1]
    return first if (ROOT / first).is_dir() else None


def package_graph() -> dict[str, dict[str, list[str]]]:
    """package -> imported package -> ["module:line", ...] (the evidence)."""
    graph: dict[str, dict[str, list[str]]] = defaultdict(lambda: defaultdict(list))
    for path in sorted(ROOT.rglob("*.py")):
        module = _module_name(path)
        src_pkg = _package_of(module)
        if src_pkg is None:
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        for target, line in _imports(tree, module, path.name == "__init__.py"):
            dst_pkg = _package_of(target)
            if dst_pkg is not None and dst_pkg != src_pkg:
                if f"{module}:{line}" not in graph[src_pkg][dst_pkg]:
                    graph[src_pkg][dst_pkg].append(f"{module}:{line}")
    return graph


def find_cycle(graph: dict[str, dict[str, list[str]]]) -> list[str] | None:
    """A cycle of packages, as a closed path, or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def dfs(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, {})):
            if state.get(nxt) == 1:
                return [*stack[stack.index(nxt):], nxt]
            if nxt not in state and (cycle := dfs(nxt)) is not None:
                return cycle
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (cycle := dfs(node)) is not None:
            return cycle
    return None


def test_the_checker_finds_a_cycle() -> None:
    graph = {"a": {"b": ["a.x:1"]}, "b": {"c": ["b.y:2"]}, "c": {"a": ["c.z:3"]}}
    assert find_cycle(graph) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b": ["a.x:1"]}, "b": {}}) is None


def test_relative_and_type_checking_imports_are_read_correctly() -> None:
    tree = ast.parse("from typing import TYPE_CHECKING\n"
                     "from ..daemon import runner\n"
                     "if TYPE_CHECKING:\n    from twinwatch.plant import dcmotor\n"
                     "def f():\n    import twinwatch.twin.model\n")
    found = {t for t, _ in _imports(tree, "twinwatch.config.schema", False)}
    assert "twinwatch.daemon.runner" in found
    assert "twinwatch.twin.model" in found  # a lazy import is a dependency
    assert not any(t.startswith("twinwatch.plant") for t in found)


def test_no_import_cycle_between_packages() -> None:
    graph = package_graph()
    for pkg in CORE:
        assert (ROOT / pkg).is_dir(), pkg
    cycle = find_cycle(graph)
    if cycle is not None:
        evidence = "\n".join(
            f"  {a} -> {b}: {', '.join(graph[a][b][:3])}" for a, b in zip(cycle, cycle[1:],
                                                                       strict=False))
        raise AssertionError(f"import cycle {' -> '.join(cycle)}:\n{evidence}")


def test_plant_does_not_import_the_drivers() -> None:
    """The simulated plants and the drivers share only twinwatch.io (sample, register map)."""
    graph = package_graph()
    assert "drivers" not in graph.get("plant", {}), graph["plant"]["drivers"]
    assert "io" in graph["plant"] and "io" in graph["drivers"]
