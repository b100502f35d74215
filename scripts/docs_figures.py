"""Measure the figures the README and the docs quote, so they are regenerated, not remembered.

Each figure in the docs names the command here that measures it; ``tests/test_docs_figures.py``
compares the cheap ones (the fast lane's test count) with what the docs say.

    python scripts/docs_figures.py fast-lane          # the fast lane's test count (collect only)
    python scripts/docs_figures.py fast-lane --time   # ... and its wall time (runs it: minutes)
    python scripts/docs_figures.py main-job           # README's `twinwatch run`: wall time,
                                                      # windows, estimation time (1-2 min)
    python scripts/docs_figures.py motoshield         # docs/motoshield.md's identify and run times

Every figure is printed with the date, the commit and the machine's load (1-minute load average
and cores): times on a shared box vary with what else runs, so the docs quote them with that.
Runs on a plain install of the test extra (pytest); ``twinwatch`` from this checkout.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MOTOSHIELD = ("config/dc-motor-motoshield-raw.toml", "config/dc-motor-motoshield.toml")

FAST_LANE = [sys.executable, "-m", "pytest", "-q", "-n", "2", "-m", "not slow"]


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _context() -> str:
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, text=True,
                            capture_output=True).stdout.strip() or "?"
    load = os.getloadavg()[0]
    return (f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC, commit {commit}, load {load:.1f} on "
            f"{os.cpu_count()} cores")


def fast_lane_count() -> int:
    """The tests of the fast lane (``pytest -m "not slow"``), counted by collecting them.

    Raises:
        RuntimeError: pytest's collection did not end with its count line.
    """
    out = subprocess.run([*FAST_LANE, "--collect-only"], cwd=ROOT, env=_env(), text=True,
                         capture_output=True).stdout
    m = re.search(r"^(\d+)(?:/\d+)? tests? collected", out, re.MULTILINE)
    if m is None:
        raise RuntimeError(f"pytest --collect-only did not count the tests:\n{out[-2000:]}")
    return int(m.group(1))


def _timed(cmd: list[str], cwd: Path) -> tuple[float, str]:
    start = time.monotonic()
    r = subprocess.run(cmd, cwd=cwd, env=_env(), text=True, capture_output=True)
    wall = time.monotonic() - start
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)}: exit {r.returncode}\n{r.stdout[-3000:]}"
                         f"{r.stderr[-3000:]}")
    return wall, r.stdout + r.stderr


def _twinwatch(*args: str) -> list[str]:
    return [sys.executable, "-m", "twinwatch", *args]


def main_job() -> str:
    """README's main job (``twinwatch run``, the built-in configuration, 1200 s of plant time
    as fast as possible) in a scratch directory: wall time, windows, estimation time."""
    with tempfile.TemporaryDirectory(prefix="twinwatch-figures-") as tmp:
        wall, out = _timed(_twinwatch("run", "--no-progress"), Path(tmp))
    windows = re.search(r"(\d+) windows estimated", out)
    est = re.search(r"estimation time per window: median (\S+ ms), max (\S+ ms)", out)
    return (f"main job: {wall:.0f} s of wall time for 1200 s of plant time, "
            f"{windows.group(1) if windows else '?'} windows, estimation median "
            f"{est.group(1) if est else '?'}, max {est.group(2) if est else '?'} per window")


def motoshield() -> list[str]:
    """docs/motoshield.md's commands: each ``identify``'s and the ``run``'s wall time."""
    lines = []
    with tempfile.TemporaryDirectory(prefix="twinwatch-figures-") as tmp:
        for cfg in MOTOSHIELD:
            wall, _ = _timed(_twinwatch("identify", str(ROOT / cfg)), Path(tmp))
            lines.append(f"twinwatch identify {cfg}: {wall:.0f} s")
        wall, out = _timed(_twinwatch("run", str(ROOT / MOTOSHIELD[1]), "--no-progress"),
                           Path(tmp))
        windows = re.search(r"(\d+) windows estimated", out)
        lines.append(f"twinwatch run {MOTOSHIELD[1]}: {wall:.0f} s, "
                     f"{windows.group(1) if windows else '?'} windows")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="figure", required=True)
    fast = sub.add_parser("fast-lane", help="the fast lane's test count (and --time)")
    fast.add_argument("--time", action="store_true", help="run it and print its wall time")
    sub.add_parser("main-job", help="README's twinwatch run")
    sub.add_parser("motoshield", help="docs/motoshield.md's identify and run")
    args = ap.parse_args(argv)
    print(_context())
    if args.figure == "fast-lane":
        print(f"fast lane: {fast_lane_count()} tests")
        if args.time:
            wall, out = _timed(FAST_LANE, ROOT)
            print(f"fast lane: {wall / 60:.1f} min of wall time ({out.strip().splitlines()[-1]})")
    elif args.figure == "main-job":
        print(main_job())
    else:
        print("\n".join(motoshield()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
