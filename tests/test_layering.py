"""The rooms and their rules: which room may import which (docs/architecture.md, "Rooms").

Read statically from the modules' syntax trees (nothing is imported). Every ``import`` and
``from ... import`` anywhere in a module counts, also inside functions (a lazy import is still
a dependency) and under ``if TYPE_CHECKING:`` (an annotation that names a room above is a back
edge too). A string naming a twinwatch module (``"twinwatch.drivers.can:CanDriver"`` in a
registry table) counts as an import of it, and a module that imports by a computed name
(``importlib.import_module(name)``) must be one of the few that are allowed to (the registry
and the lazy-module helper, which only ever receive such literals or third-party names).
"""

from __future__ import annotations

import ast
import functools
import re
from collections import defaultdict
from pathlib import Path

import twinwatch

ROOT = Path(twinwatch.__file__).parent

#: "twinwatch.pkg.module" or "twinwatch.pkg.module:Class" (a registry entry), a whole string.
_MODULE_STRING = re.compile(r"^(twinwatch(?:\.[a-z_][a-z0-9_]*)+)(?::[A-Za-z_]\w*)?$")

#: Room -> the module prefixes it holds (the longest prefix places a module).
ROOMS: dict[str, tuple[str, ...]] = {
    "base": ("twinwatch.errors", "twinwatch.plugins", "twinwatch._lazy",
             "twinwatch._lifecycle", "twinwatch._kernels", "twinwatch._table",
             "twinwatch._forward", "twinwatch.__init__"),
    "io": ("twinwatch.io",),
    "plant": ("twinwatch.plant",),
    "twin.model": ("twinwatch.twin.model",),
    "twin.models": ("twinwatch.twin.models",),
    "twin.estimation": ("twinwatch.twin.estimation",),
    "twin.discovery": ("twinwatch.twin.discovery",),
    "twin.prognostics": ("twinwatch.twin.prognostics",),
    "twin": ("twinwatch.twin",),
    "drivers": ("twinwatch.drivers",),
    "sinks": ("twinwatch.sinks",),
    "config": ("twinwatch.config",),
    "daemon": ("twinwatch.daemon",),
    "commissioning": ("twinwatch.commissioning",),
    "watch": ("twinwatch.watch",),
    "cli": ("twinwatch.cli", "twinwatch.__main__"),
}

#: Room -> the rooms it may import (besides itself). The floors, from the ground up: base; io;
#: plant, the twin's contract; the machines, the estimation; the discovery; the twin's top
#: (adaptation, health); drivers, sinks; config; daemon; commissioning (beside the daemon: a
#: baseline identified offline from a recording); watch (beside the daemon, reading what the
#: daemons publish); cli.
ALLOWED: dict[str, set[str]] = {
    "base": set(),
    "io": {"base"},
    "plant": {"base", "io"},                     # the plant shares nothing with the twin
    "twin.model": {"base"},
    "twin.models": {"base", "io", "twin.model"},  # a machine knows no estimator
    "twin.estimation": {"base", "twin.model"},    # it estimates any machine
    "twin.discovery": {"base", "twin.model", "twin.estimation"},
    # trend and RUL: read the estimation's results, know no machine, no discovery
    "twin.prognostics": {"base", "twin.model", "twin.estimation"},
    "twin": {"base", "io", "twin.model", "twin.estimation", "twin.discovery",
             "twin.prognostics"},
    "drivers": {"base", "io", "plant"},
    "sinks": {"base", "io", "twin.model", "twin"},  # the message and the window, no internals
    "config": {"base", "io", "drivers", "sinks", "twin.model", "twin.models",
               "twin.estimation", "twin.discovery", "twin.prognostics", "twin"},
    "daemon": {"base", "io", "config", "drivers", "sinks", "twin.model", "twin.models",
               "twin.estimation", "twin.discovery", "twin.prognostics", "twin"},
    # reads a recording through a driver and identifies the baseline: never the daemon or an
    # output (it runs once, offline), nothing of the twin's top (the message, the diagnosis)
    "commissioning": {"base", "io", "config", "drivers", "twin.model", "twin.models",
                      "twin.estimation"},
    # reads the network's health messages: never the daemon (a watcher runs anywhere)
    "watch": {"base", "io", "twin"},
    "cli": set(ROOMS) - {"cli"},
}

#: Modules allowed to import by a computed name.
DYNAMIC_IMPORTERS = {"twinwatch.plugins", "twinwatch._lazy"}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _imports(tree: ast.AST, module: str, is_package: bool) -> list[tuple[str, int]]:
    """(imported module, line) for every import in ``tree`` (annotation-only ones included) and
    every string literal that names a twinwatch module."""
    found: list[tuple[str, int]] = []

    def visit(node: ast.AST) -> None:
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
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            m = _MODULE_STRING.match(node.value)
            if m:
                found.append((m.group(1), node.lineno))
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return found


def room_of(module: str) -> str | None:
    """The room holding ``module`` (a dotted name under twinwatch), or None."""
    best: tuple[int, str] | None = None
    for room, prefixes in ROOMS.items():
        for prefix in prefixes:
            if module == prefix or module.startswith(prefix + "."):
                if best is None or len(prefix) > best[0]:
                    best = (len(prefix), room)
    if best is None and module == "twinwatch":
        return "base"
    return None if best is None else best[1]


@functools.cache
def _tree(path: Path) -> ast.AST:
    """The module's syntax tree, parsed once for all the tests here (they only read it)."""
    return ast.parse(path.read_text(encoding="utf-8"), str(path))


def _sources() -> list[tuple[str, Path]]:
    return [(_module_name(p), p) for p in sorted(ROOT.rglob("*.py"))]


def room_graph() -> dict[str, dict[str, list[str]]]:
    """room -> imported room -> ["module:line", ...] (the evidence)."""
    graph: dict[str, dict[str, list[str]]] = defaultdict(lambda: defaultdict(list))
    for module, path in _sources():
        src = room_of(module if not module.endswith("__init__") else module)
        if src is None:
            continue
        tree = _tree(path)
        for target, line in _imports(tree, module, path.name == "__init__.py"):
            if not target.startswith("twinwatch"):
                continue
            dst = room_of(target)
            if dst is not None and dst != src and f"{module}:{line}" not in graph[src][dst]:
                graph[src][dst].append(f"{module}:{line}")
    return graph


def _dynamic_imports(tree: ast.AST) -> list[int]:
    """Lines that call ``import_module``/``__import__`` with a name that is not a literal."""
    lines = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            fn = node.func
            name = fn.attr if isinstance(fn, ast.Attribute) else getattr(fn, "id", "")
            if name in ("import_module", "__import__") and not (
                    node.args and isinstance(node.args[0], ast.Constant)):
                lines.append(node.lineno)
    return lines


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


def test_imports_are_read_correctly() -> None:
    tree = ast.parse("from typing import TYPE_CHECKING\n"
                     "from ..daemon import runner\n"
                     "if TYPE_CHECKING:\n    from twinwatch.plant import dcmotor\n"
                     "def f():\n    import twinwatch.twin.model\n"
                     "TABLE = {'x': 'twinwatch.sinks.zenoh:ZenohSink'}\n"
                     "NOT = 'twinwatch is a name, not a module'\n")
    found = {t for t, _ in _imports(tree, "twinwatch.config.schema", False)}
    assert "twinwatch.daemon.runner" in found
    assert "twinwatch.twin.model" in found  # a lazy import is a dependency
    assert "twinwatch.plant.dcmotor" in found  # so is an annotation's
    assert "twinwatch.sinks.zenoh" in found  # and a registry entry
    assert not any("not a module" in t for t in found)
    assert room_of("twinwatch.twin.models.dcmotor") == "twin.models"
    assert room_of("twinwatch.twin.model") == "twin.model"
    assert room_of("twinwatch.twin.health") == "twin"
    assert room_of("twinwatch.errors") == "base"
    assert room_of("twinwatch.commissioning.identify") == "commissioning"
    assert room_of("twinwatch.config.identify") == "config"
    assert _dynamic_imports(ast.parse("importlib.import_module(name)")) == [1]
    assert _dynamic_imports(ast.parse("importlib.import_module('zenoh')")) == []


def test_every_module_is_in_a_room() -> None:
    homeless = [m for m, _ in _sources() if room_of(m) is None]
    assert not homeless, f"modules in no room (add them to ROOMS and the docs): {homeless}"


def test_the_rooms_keep_their_rules() -> None:
    graph = room_graph()
    broken = []
    for src, targets in sorted(graph.items()):
        for dst, evidence in sorted(targets.items()):
            if dst not in ALLOWED[src]:
                broken.append(f"  {src} -> {dst}: {', '.join(evidence[:4])}")
    assert not broken, "imports against the room rules:\n" + "\n".join(broken)


def test_no_arrow_runs_back_up() -> None:
    """No cycle between rooms, annotation-only imports included."""
    graph = room_graph()
    cycle = find_cycle(graph)
    if cycle is not None:
        evidence = "\n".join(
            f"  {a} -> {b}: {', '.join(graph[a][b][:3])}" for a, b in zip(cycle, cycle[1:],
                                                                       strict=False))
        raise AssertionError(f"import cycle {' -> '.join(cycle)}:\n{evidence}")


def test_no_string_import_the_checker_cannot_see() -> None:
    hidden = []
    for module, path in _sources():
        if module in DYNAMIC_IMPORTERS:
            continue
        lines = _dynamic_imports(_tree(path))
        hidden.extend(f"{module}:{line}" for line in lines)
    assert not hidden, ("imports by a computed name (use a registry, a literal or a plain "
                        f"import): {hidden}")


def test_the_rules_allow_no_cycle() -> None:
    """The rules themselves are floors: no two rooms may import each other."""
    rules = {src: {dst: ["rule"] for dst in dsts} for src, dsts in ALLOWED.items()}
    assert find_cycle(rules) is None


def test_the_plant_and_the_twin_share_only_io() -> None:
    graph = room_graph()
    plant = set(graph.get("plant", {}))
    assert plant <= {"base", "io"}, graph["plant"]
    assert "io" in graph["drivers"] and "io" in graph["twin.models"]


def module_graph(package: str) -> dict[str, dict[str, list[str]]]:
    """module -> imported module -> ["line", ...], for the modules of ``package`` (a dotted
    name) importing each other; annotation-only and lazy imports included."""
    graph: dict[str, dict[str, list[str]]] = defaultdict(lambda: defaultdict(list))
    for module, path in _sources():
        if not module.startswith(package + "."):
            continue
        tree = _tree(path)
        for target, line in _imports(tree, module, path.name == "__init__.py"):
            if target.startswith(package + ".") and target != module:
                # ``from twinwatch.daemon.x import Name``: the module, not the name
                parts = target.split(".")
                while len(parts) > 2 and not (ROOT.parent.joinpath(*parts).with_suffix(".py")
                                              .exists()
                                              or ROOT.parent.joinpath(*parts).is_dir()):
                    parts.pop()
                dst = ".".join(parts)
                if dst != module:
                    graph[module][dst].append(str(line))
    return graph


def test_no_cycle_between_the_daemon_modules() -> None:
    """The service host sits on top of the daemon room: host -> supervisor -> runner -> slots,
    never back (``gateway -> supervisor -> runner -> gateway`` was a cycle: the estimation
    slots lived in the gateway)."""
    graph = module_graph("twinwatch.daemon")
    assert "twinwatch.daemon.runner" in graph["twinwatch.daemon.supervisor"]  # it reads imports
    cycle = find_cycle(graph)
    if cycle is not None:
        evidence = "\n".join(f"  {a} -> {b}: lines {', '.join(graph[a][b][:3])}"
                             for a, b in zip(cycle, cycle[1:], strict=False))
        raise AssertionError(f"import cycle in daemon/: {' -> '.join(cycle)}:\n{evidence}")


DAEMON_PARTS = ("acquisition", "window_worker", "outputs", "resume")


def test_the_daemon_is_a_composition_of_parts_that_import_none_of_each_other() -> None:
    """``Daemon`` (runner.py) puts its parts together: acquisition, the window worker, the
    outputs, resume. Each part stands on the modules below it (the ring buffer, the source, the
    pipeline, the alarms, the slots, systemd), never on another part, the runner or the service
    above it: a part can be read, tested and replaced alone."""
    graph = module_graph("twinwatch.daemon")
    parts = {f"twinwatch.daemon.{p}" for p in DAEMON_PARTS}
    above = parts | {f"twinwatch.daemon.{m}" for m in
                     ("runner", "supervisor", "host", "service", "summary", "workers")}
    assert parts <= set(graph["twinwatch.daemon.runner"]), graph["twinwatch.daemon.runner"]
    tangled = [f"{src} -> {dst}: lines {', '.join(graph[src][dst][:3])}"
               for src in sorted(parts) for dst in sorted(graph.get(src, {}))
               if dst in above]
    assert not tangled, "a part of the daemon imports another or one above it:\n" + "\n".join(
        tangled)


def test_the_daemon_modules_import_alone_in_any_order() -> None:
    """Every module of ``daemon/`` imports first in a fresh interpreter (a cycle of
    module-level imports fails there with a partly initialised module, whatever the checker
    above reads)."""
    import subprocess
    import sys

    modules = sorted(m for m, _ in _sources() if m.startswith("twinwatch.daemon."))
    code = ("import importlib, sys\n"
            "for name in sys.argv[1:]:\n"
            "    for m in [m for m in sys.modules if m.startswith('twinwatch')]:\n"
            "        del sys.modules[m]\n"
            "    importlib.import_module(name)\n")
    done = subprocess.run([sys.executable, "-c", code, *modules], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
