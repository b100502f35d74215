"""numba's kernel cache follows every kernel source (twinwatch/_kernels.py): a change to a
module a kernel calls into (``_pid.py``) compiles the callers afresh."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import twinwatch
from twinwatch import _kernels

PKG = Path(twinwatch.__file__).resolve().parent


def test_the_cache_directory_changes_with_a_callee_source(tmp_path: Path) -> None:
    copy = tmp_path / "twinwatch"
    for sub in _kernels._KERNEL_DIRS:
        (copy / sub).mkdir(parents=True, exist_ok=True)
        for f in (PKG / sub).glob("*.py"):
            shutil.copy(f, copy / sub / f.name)
    before = _kernels.sources_hash(copy)
    assert before == _kernels.sources_hash(PKG)
    pid = copy / "twin" / "models" / "_pid.py"
    pid.write_text(pid.read_text() + "\n# the integrator method changed\n")
    assert _kernels.sources_hash(copy) != before


def test_the_daemon_uses_it_and_a_child_process_the_same(tmp_path: Path) -> None:
    env = dict(os.environ, XDG_CACHE_HOME=str(tmp_path))
    env.pop("NUMBA_CACHE_DIR", None)
    env.pop("TWINWATCH_NUMBA_BASE", None)
    code = ("import os, subprocess, sys, twinwatch; print(os.environ['NUMBA_CACHE_DIR']); "
            "sys.stdout.flush(); subprocess.run([sys.executable, '-c', 'import os, twinwatch; "
            "print(os.environ[\"NUMBA_CACHE_DIR\"])'])")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True).stdout.split()
    want = str(tmp_path / "twinwatch" / "numba" / _kernels.sources_hash())
    assert out == [want, want]


def test_an_unwritable_cache_home_leaves_numba_alone(tmp_path: Path) -> None:
    blocked = tmp_path / "file"
    blocked.write_text("not a directory")
    env = dict(os.environ, TWINWATCH_NUMBA_BASE=str(blocked / "numba"))
    env.pop("NUMBA_CACHE_DIR", None)
    code = "import os, twinwatch; print(os.environ.get('NUMBA_CACHE_DIR', 'default'))"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "default"
