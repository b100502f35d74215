"""The package type-checks: mypy finds nothing under the project's settings, and nothing under
``--strict`` in the twin (issue 36).

Each test runs mypy as a user runs it from the repository root (``python -m mypy``, the
settings of ``pyproject.toml``'s ``[tool.mypy]``: the pydantic plugin, ``ignore_missing_imports``),
in a subprocess of this interpreter, and prints every error it reports when it fails. mypy's
incremental cache (``.mypy_cache/tests-*``) makes a second run a few seconds; a cold one takes
about 12 s for the package and 8 s for the twin.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("mypy", reason="mypy is not installed (pip install -e '.[test]')")

ROOT = Path(__file__).resolve().parents[1]

#: An error line of mypy's output: ``path:line: error: message  [code]``.
_ERROR = re.compile(r"^(?P<path>[^:\s]+\.py):\d+(?::\d+)?: error: ")

def _mypy(cache: str, *args: str) -> list[str]:
    """Run ``python -m mypy *args`` from the repository root, its incremental cache in
    ``.mypy_cache/<cache>`` (one per set of options: the project's settings and ``--strict``
    would invalidate each other's); the error lines it printed."""
    proc = subprocess.run([sys.executable, "-m", "mypy", "--cache-dir",
                           str(ROOT / ".mypy_cache" / cache), *args],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    if proc.returncode not in (0, 1):  # 2: mypy itself failed (a bad option, a crash)
        pytest.fail(f"mypy {' '.join(args)} exited {proc.returncode}:\n"
                    f"{proc.stdout}\n{proc.stderr}")
    errors = [line for line in proc.stdout.splitlines() if _ERROR.match(line)]
    if proc.returncode == 1 and not errors:  # errors in a format the filter does not read
        pytest.fail(f"mypy {' '.join(args)} failed without an error line it recognises:\n"
                    f"{proc.stdout}\n{proc.stderr}")
    return errors


def _path(line: str) -> str:
    match = _ERROR.match(line)
    assert match is not None
    return match["path"].replace("\\", "/")


def test_error_lines_are_recognised() -> None:
    """The filter below reads mypy's own format (a line it does not recognise would pass
    silently)."""
    line = 'twinwatch/cli.py:197: error: Argument 1 has incompatible type  [arg-type]'
    assert _ERROR.match(line) and _path(line) == "twinwatch/cli.py"
    assert _ERROR.match("twinwatch/x.py:3:5: error: oops  [misc]")
    assert not _ERROR.match("twinwatch/x.py:3: note: Possible overload variants:")
    assert not _ERROR.match("Found 44 errors in 11 files (checked 115 source files)")


@pytest.mark.slow  # 20-45 s on a cold cache: the whole suite (CI) holds it, not the fast lane
def test_package_type_checks_under_project_settings() -> None:
    """``mypy twinwatch`` under ``[tool.mypy]``: no error."""
    errors = _mypy("tests-project", "twinwatch")
    assert not errors, f"mypy twinwatch: {len(errors)} errors:\n" + "\n".join(errors)


@pytest.mark.slow
def test_twin_type_checks_strict() -> None:
    """``mypy --strict twinwatch/twin``, the diagnosis included: no error."""
    errors = _mypy("tests-strict", "--strict", "twinwatch/twin")
    assert not errors, (f"mypy --strict twinwatch/twin: {len(errors)} errors:\n"
                        + "\n".join(errors))
