"""Two checkouts of twinwatch measured side by side: the density benchmark's fleet CPU per
window for each, both gateways running at the same moment on the same box (issue 58).

A box shared with other work changes its speed by a fifth to a third from one run to the
next, so two density runs one after the other differ by as much as the change under test.
Here both trees' gateways run at once, N machines each, each in its own network namespace
(``unshare -n``, its own loopback: both use the default ports): whatever slows the box slows
both, and the steady-state figure of :mod:`bench_density` (the fleet's CPU per window stored,
from 30 s after the last machine's first window on) is compared run by run.

Each tree runs its own code (``PYTHONPATH``) under this checkout's ``bench_density.py``; the
recordings are written once, before the first run, for both. Without ``--cold`` each tree's
numba cache is filled first by a short run (the cache is keyed by the source files' paths, so
a worktree starts empty). Needs root (``unshare -n``).

Usage::

    git worktree add /tmp/base <commit>
    python benchmarks/bench_pair.py /tmp/base . [--n 125] [--seconds 80] [--runs 3] [--cold]

Printed per run: each tree's steady-state CPU per window stored, the fleet's CPU per window over
the whole run, overruns; then the median of the runs' differences (head - base) and their range.
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

DENSITY = Path(__file__).resolve().parent / "bench_density.py"
#: The run that fills each tree's numba cache first (machines, plant time [s]): past the
#: diagnosis's baseline (10 windows) and the first trend fit, so the measured runs compile
#: nothing.
WARM_UP = (4, 90.0)
# what bench_density.py prints: the steady state, the whole run, the row (windows, overruns)
STEADY_RE = re.compile(r"steady state .*?: ([\d.]+) ms of CPU per window stored")
FLEET_RE = re.compile(r"the fleet's CPU [\d.]+ s, ([\d.]+) ms per window estimated")
ROW_RE = re.compile(r"^\s*(\d+) gateway\s+(\d+)/(\d+)\s+(\d+)", re.MULTILINE)


def _gateway(tree: Path, n: int, seconds: float, plants: Path, cold: bool
             ) -> subprocess.Popen[str]:
    """This checkout's density benchmark on ``tree``'s code, in a network namespace of its own."""
    cmd = [sys.executable, str(DENSITY), "--mode", "gateway", "--n", str(n),
           "--seconds", repr(seconds), "--plants", str(plants)] + (["--cold"] if cold else [])
    shell = "ip link set lo up && exec " + shlex.join(cmd)
    env = dict(os.environ, PYTHONPATH=str(tree))
    return subprocess.Popen(["unshare", "-n", "sh", "-c", shell], cwd=tree, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _figures(text: str) -> tuple[float, float, int, str]:
    """(steady ms per window, fleet ms per window, overruns, windows 'stored/expected')."""
    steady = STEADY_RE.search(text)
    fleet = FLEET_RE.search(text)
    row = ROW_RE.search(text)
    if steady is None or fleet is None or row is None:
        raise RuntimeError("a density run printed no steady state:\n" + text[-2000:])
    return (float(steady.group(1)), float(fleet.group(1)), int(row.group(4)),
            f"{row.group(2)}/{row.group(3)}")


def _both(base: Path, head: Path, n: int, seconds: float, plants: Path, cold: bool
          ) -> list[str]:
    """Both trees' density runs at once: their outputs (base, head)."""
    procs = [_gateway(tree, n, seconds, plants, cold) for tree in (base, head)]
    outs = [p.communicate()[0] for p in procs]
    for p, text in zip(procs, outs, strict=True):
        if p.returncode != 0:
            raise RuntimeError(f"a density run exited {p.returncode}:\n{text[-2000:]}")
    return outs


def pair(base: Path, head: Path, n: int, seconds: float, plants: Path, cold: bool
         ) -> tuple[tuple[float, float, int, str], tuple[float, float, int, str]]:
    """One run of both trees at once: each one's :func:`_figures`."""
    outs = _both(base, head, n, seconds, plants, cold)
    return _figures(outs[0]), _figures(outs[1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("base", type=Path, help="the checkout to compare against")
    ap.add_argument("head", type=Path, help="the checkout under test")
    ap.add_argument("--n", type=int, default=125, help="machines per tree")
    ap.add_argument("--seconds", type=float, default=80.0, help="plant time per machine [s]")
    ap.add_argument("--runs", type=int, default=3, help="paired runs (each both trees at once)")
    ap.add_argument("--cold", action="store_true", help="an empty numba cache every run")
    args = ap.parse_args()
    if os.geteuid() != 0:
        sys.exit("bench_pair.py needs root: each gateway runs in its own network namespace "
                 "(unshare -n)")
    base, head = args.base.resolve(), args.head.resolve()
    for tree in (base, head):
        if not (tree / "twinwatch" / "__init__.py").is_file():
            sys.exit(f"{tree}: not a twinwatch checkout (no twinwatch/__init__.py)")
    plants = Path(tempfile.gettempdir()) / "density-plants"
    plants.mkdir(parents=True, exist_ok=True)
    # the recordings written here, once: two runs writing the same file at once would race
    for n, seconds in ((args.n, args.seconds), WARM_UP):
        subprocess.run([sys.executable, str(DENSITY), "_plants", str(plants), str(n),
                        str(seconds)], check=True)
    if not args.cold:  # each tree's kernels compiled into its cache, both at once
        _both(base, head, *WARM_UP, plants, cold=False)
    print(f"{args.n} machines per tree, {args.seconds:g} s of plant time, "
          f"{'cold' if args.cold else 'warm'} cache; base {base}, head {head}")
    print("run  steady ms/window base  head  head-base   whole run ms/window base  head"
          "   overruns base  head")
    diffs = []
    for k in range(1, args.runs + 1):
        (s_b, f_b, o_b, w_b), (s_h, f_h, o_h, w_h) = pair(base, head, args.n, args.seconds,
                                                           plants, args.cold)
        diffs.append(s_h - s_b)
        print(f"{k:>3}  {s_b:>21.1f} {s_h:>5.1f} {s_h - s_b:>+10.1f}   {f_b:>24.1f} {f_h:>5.1f}"
              f"   {o_b:>13d} {o_h:>5d}  ({w_b}, {w_h} windows)", flush=True)
    print(f"head - base, steady state: median {statistics.median(diffs):+.2f} ms per window, "
          f"from {min(diffs):+.1f} to {max(diffs):+.1f} over {len(diffs)} runs")


if __name__ == "__main__":
    main()
