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


def test_the_twin_kernel_compiles_once_whatever_the_inputs_writability() -> None:
    """numba types a read-only array apart from a writable one and compiles a kernel again
    for each mix it meets: seconds each on a cold cache, in every worker process (issue 58).
    The default twin hands its kernel read-only inputs only, so a window of writable arrays,
    one of read-only arrays, the estimation's calls (no meta-model: the shared read-only
    zeros, one initial offset) and the diagnosis' (writable terms and offsets per row) run
    one compiled signature, and give the same numbers as before the arrays were frozen."""
    import numpy as np

    from twinwatch.plant.dcmotor import DCMotorPlantConfig
    from twinwatch.twin.model import WindowData
    from twinwatch.twin.models import dcmotor
    from twinwatch.twin.models.dcmotor import DCMotorTwin

    from .helpers.plant import plant_windows

    window = plant_windows(DCMotorPlantConfig(scenario="nominal", duration=6), 1, skip=1)[1][0]
    frozen = {k: v.copy() for k, v in window.channels.items()}
    for v in frozen.values():
        v.flags.writeable = False
    frozen_window = WindowData(t=window.t, channels=frozen, index=window.index)
    twin = DCMotorTwin()
    theta = np.repeat(twin.nominal_vector()[None], 3, axis=0)
    theta[1, 0] *= 1.1
    n = window.n
    writable_terms = {"d(omega)/dt": np.zeros((3, n)), "d(ia)/dt": np.full(n, 0.5)}
    y0 = twin.simulate(theta, window)
    calls = [
        twin.simulate(theta, frozen_window),
        twin.simulate(theta, window, initial=np.array([0.01, -0.2])),
        twin.simulate(theta, window, writable_terms, initial=np.zeros((3, 2))),
    ]
    assert len(dcmotor._fast_kernel.signatures) == 1
    np.testing.assert_array_equal(calls[0], y0)
    assert np.isfinite(calls[1]).all() and np.isfinite(calls[2]).all()
    assert not np.array_equal(calls[1], y0)  # the offsets reach the kernel
    assert window.channels["ia"].flags.writeable  # the caller's arrays are left alone


_TURN = """
import os, sys, time
from pathlib import Path
import numpy as np
from twinwatch.twin.estimation import fusion
ready = Path(sys.argv[1])
(ready / sys.argv[2]).touch()
while len(list(ready.glob("p*"))) < 2:  # both processes ready: they ask at the same time
    time.sleep(0.001)
fusion._safe_inverse(np.eye(3))
stats = fusion._safe_inverse_finite.stats
print(sum(stats.cache_misses.values()), sum(stats.cache_hits.values()))
"""


def test_processes_on_one_cold_cache_compile_a_kernel_once(tmp_path: Path) -> None:
    """Two processes that need the same kernel at the same moment on an empty cache (a
    gateway's workers starting): one compiles it, the other waits for it and loads it from
    the cache (issue 58: each worker compiled every kernel)."""
    cache = tmp_path / "cache"
    ready = tmp_path / "ready"
    ready.mkdir()
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    env.pop("TWINWATCH_NUMBA_BASE", None)
    procs = [subprocess.Popen([sys.executable, "-c", _TURN, str(ready), f"p{i}"], env=env,
                              stdout=subprocess.PIPE, text=True) for i in range(2)]
    outs = sorted(tuple(int(x) for x in p.communicate(timeout=120)[0].split())
                  for p in procs)
    assert outs == [(0, 1), (1, 0)]  # (compiled, loaded): one each


_GIVE_UP = """
from twinwatch import _kernels
_kernels.COMPILE_WAIT_S = 0.2
calls = []
real = _kernels._lock_file
def counted(path):
    calls.append(path)
    return real(path)
_kernels._lock_file = counted
import numpy as np
from twinwatch.twin.estimation import fit, fusion
fusion._safe_inverse(np.eye(3))
fit.covariance(np.eye(4)[:, :2], np.ones(4))
print(len(calls), flush=True)
"""


def test_a_process_that_waited_too_long_compiles_without_waiting_after(tmp_path: Path) -> None:
    """A process holding the lock file and never letting go (stopped while it compiles) costs
    another process one wait of COMPILE_WAIT_S, not one per kernel: after it the other
    compiles on its own, and says so once."""
    import fcntl

    cache = tmp_path / "cache"
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    env.pop("TWINWATCH_NUMBA_BASE", None)
    probe = subprocess.run([sys.executable, "-c", "import os, twinwatch; "
                            "print(os.environ['NUMBA_CACHE_DIR'])"], env=env,
                           capture_output=True, text=True, check=True).stdout.strip()
    lock = Path(probe) / _kernels.LOCK_NAME
    with lock.open("w") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        run = subprocess.run([sys.executable, "-c", _GIVE_UP], env=env, capture_output=True,
                             text=True, timeout=300, check=True)
    lines = run.stdout.split()
    assert lines[-1] == "1"  # one wait; the later kernels did not ask for the lock
    assert run.stderr.count("without waiting from now on") == 1
