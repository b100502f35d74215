"""Start-up time of the command line (issue 11: ``--help`` under 0.5 s, ``check-config`` under
1.5 s on the 2-core reference machine): the heavy backends are imported only when used.

Prints, for ``twinwatch --help`` and ``twinwatch check-config config/dc-motor-sim.toml``, the
median, minimum and maximum wall time and CPU time (user + system) of ``--runs`` fresh
processes after one warm-up (the OS page cache and numba's on-disk cache warm), then which
heavy backends each command imports and what they cost (``python -X importtime``).

Usage::

    python benchmarks/bench_startup.py [--runs 9]
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("zenoh", "rerun", "pymodbus", "cantools", "can", "numba", "pymoo", "scipy")
COMMANDS = {
    "twinwatch --help": ["--help"],
    "twinwatch check-config config/dc-motor-sim.toml":
        ["check-config", str(ROOT / "config" / "dc-motor-sim.toml")],
}


def _env() -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=str(ROOT), CI="true")


def _once(args: list[str]) -> tuple[float, float]:
    """(wall, cpu) seconds of one ``python -m twinwatch ARGS`` process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "twinwatch", *args], env=_env(),
                          capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"twinwatch {' '.join(args)} failed:\n{proc.stderr}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def _backends(args: list[str]) -> dict[str, float]:
    """Heavy packages the command imports -> their cumulative import time [s] (each import of
    one of their modules that is not itself inside another heavy package's import)."""
    proc = subprocess.run([sys.executable, "-X", "importtime", "-m", "twinwatch", *args],
                          env=_env(), capture_output=True, text=True, check=False)
    rows = []
    for line in proc.stderr.splitlines():
        if line.startswith("import time:") and "|" in line:
            _, cumulative, name = line[len("import time:"):].split("|")
            if cumulative.strip().isdigit():
                depth = (len(name) - len(name.lstrip())) // 2
                rows.append((depth, name.strip(), int(cumulative) / 1e6))
    out: dict[str, float] = {}
    ancestors: list[str] = []
    for depth, name, seconds in reversed(rows):  # -X importtime prints children first
        del ancestors[depth:]
        root = name.split(".")[0]
        if root in HEAVY and not any(a.split(".")[0] in HEAVY for a in ancestors):
            out[root] = out.get(root, 0.0) + seconds
        ancestors.append(name)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=9, help="timed runs per command")
    runs = parser.parse_args().runs
    print(f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}, "
          f"python {sys.version.split()[0]}, {runs} runs after 1 warm-up")
    for label, args in COMMANDS.items():
        _once(args)
        walls, cpus = zip(*(_once(args) for _ in range(runs)), strict=True)
        print(f"{label}:")
        print(f"  wall median {statistics.median(walls):.3f} s "
              f"(min {min(walls):.3f}, max {max(walls):.3f})")
        print(f"  cpu  median {statistics.median(cpus):.3f} s "
              f"(min {min(cpus):.3f}, max {max(cpus):.3f})")
        loaded = _backends(args)
        print("  heavy backends imported: " + (", ".join(
            f"{k} {v:.2f} s" for k, v in sorted(loaded.items(), key=lambda kv: -kv[1]))
            or "none"))


if __name__ == "__main__":
    main()
