"""Fast start: the command line and the configuration loader import the heavy backends only
when they are used (issue 11). Behaviour, not timing: which modules a fresh interpreter has
loaded (the figures are printed by ``benchmarks/bench_startup.py``)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from .helpers.paths import ROOT

HEAVY = ("zenoh", "rerun", "pymodbus", "cantools", "can", "numba", "pymoo", "scipy")


def _loaded_after(code: str) -> set[str]:
    """Heavy top-level packages in ``sys.modules`` after running ``code`` in a fresh python."""
    roots = "{m.split('.')[0] for m in sys.modules}"
    probe = f"{code}\nimport json, sys\nprint(json.dumps(sorted({roots} & {set(HEAVY)!r})))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         timeout=120, cwd=ROOT,
                         env=dict(os.environ, PYTHONPATH=str(ROOT), CI="true"))
    assert out.returncode == 0, out.stderr
    return set(json.loads(out.stdout.strip().splitlines()[-1]))


def test_importing_the_config_loader_loads_no_backend() -> None:
    assert _loaded_after("import twinwatch.config.loader") == set()


def test_the_help_loads_no_backend() -> None:
    code = ("from twinwatch.cli import main\n"
            "try:\n    main(['--help'])\nexcept SystemExit:\n    pass")
    assert _loaded_after(code) == set()
    # nor the configuration's schema, numpy or pydantic: the help needs none of them (the
    # sample list the CLI imports once pulled the schema in, 0.55 s instead of 0.13 s); nor
    # rich and the watcher (twinwatch watch imports them when it runs)
    probe = code + "\nimport sys\nprint(sorted(m for m in ('twinwatch.config.schema', " \
        "'numpy', 'pydantic', 'rich', 'twinwatch.watch') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         timeout=120, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert out.returncode == 0 and out.stdout.strip().splitlines()[-1] == "[]", out


def test_validating_a_simulated_config_loads_no_bus_zenoh_or_rerun() -> None:
    """The sinks and the CAN stack open with the daemon, not with the configuration (the twin
    still imports numba and its optimisers to validate its tables)."""
    code = ("from twinwatch.config.loader import load_config\n"
            f"load_config({str(ROOT / 'config' / 'dc-motor-sim.toml')!r})")
    loaded = _loaded_after(code)
    assert not loaded & {"zenoh", "rerun", "pymodbus", "cantools", "can"}, loaded
    code = code.replace("dc-motor-sim.toml", "hydraulic-modbus-sim.toml")
    loaded = _loaded_after(code)
    assert not loaded & {"zenoh", "rerun", "pymodbus", "cantools", "can"}, loaded


def test_a_lazy_module_is_imported_on_first_use() -> None:
    code = ("from twinwatch._lazy import lazy_module\n"
            "import sys\n"
            "zenoh = lazy_module('zenoh')\n"
            "assert 'zenoh' not in sys.modules\n"
            "zenoh.Config\n"
            "assert 'zenoh' in sys.modules")
    assert _loaded_after(code) == {"zenoh"}


def test_watch_loads_no_daemon_no_twin_and_no_sink() -> None:
    """``twinwatch watch`` and ``tail`` import zenoh and rich, never the daemon's stack: the
    watcher's room reads the published JSON, through the message's typed view (its model
    module, pydantic only: no estimation, no numpy)."""
    code = ("import sys\nfrom twinwatch import watch\nwatch.Fleet().snapshot()\n"
            "print(sorted(m for m in sys.modules if m.startswith(('twinwatch.daemon', "
            "'twinwatch.sinks', 'twinwatch.twin', 'twinwatch.config', 'numpy'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert out.returncode == 0 and out.stdout.strip().splitlines()[-1] == "[]", out
    code = code.replace("watch.Fleet().snapshot()", "fleet = watch.Fleet()\n"
                        "fleet.health('m1', {'machine': 'm1', 'window': 0})\n"
                        "watch.health_line({'machine': 'm1', 'window': 0}); fleet.snapshot()")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert out.returncode == 0, out
    assert out.stdout.strip().splitlines()[-1] == "['twinwatch.twin', 'twinwatch.twin.health']"
