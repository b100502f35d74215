"""Soak benchmark: the whole daemon on the simulated plant for hours of plant time, as fast as
possible, watching memory (issue #5, item 7: "memory must stay flat").

Runs :class:`twinwatch.daemon.runner.Daemon` exactly as ``twinwatch run`` does (simulated plant
over the virtual CAN bus, the adaptation worker, optionally Zenoh and Rerun) and prints:

* windows processed, overruns, numeric failures, wall time and plant-time/wall-time ratio;
* resident memory (VmRSS from ``/proc/self/status``) at start (after start-up, before the first
  window), after the first window (numba has compiled), every ``--every`` windows and at the end;
* the RSS slope over the second half of the run in kB per 1000 windows (flat means ~0; note the
  daemon keeps the last ``[acquisition] history`` health messages, 1000 by default, in memory, so
  RSS legitimately grows until that many windows have been processed); with ``--record``, also
  the RSS just after each rotation and its slope (within a file RSS saw-tooths: Rerun keeps the
  file's footer manifest until the file is rotated), so use an ``--every`` that divides
  ``rotate_windows`` (1800);
* with ``--tracemalloc``, the ten Python allocation sites that grew most between the first
  report after warm-up and the end.

Usage, from the repository root or with twinwatch installed (6 h of plant time is the
default: at the measured ~19x real time on 2 shared cores, about 19 minutes)::

    PYTHONPATH=. python benchmarks/soak.py          # 21600 s, no Zenoh, no recording
    python benchmarks/soak.py --duration 600 --every 50 --history 50
    python benchmarks/soak.py --zenoh --record /tmp/soak.rrd --tracemalloc
    python benchmarks/soak.py --zenoh --record /tmp/soak/tw.rrd --state /tmp/soak/state.sqlite
                                      # the service as deployed: publish, record, persist

Not part of the test suite.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
import tracemalloc
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))   # this checkout's twinwatch, not an installed one

from twinwatch.config.loader import default_config  # noqa: E402
from twinwatch.daemon.runner import Daemon  # noqa: E402
from twinwatch.twin.health import HealthMessage  # noqa: E402


def rss_kib() -> int:
    """Resident set size of this process [KiB] (``VmRSS`` of ``/proc/self/status``)."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except OSError:
        pass
    try:
        import psutil

        return int(psutil.Process().memory_info().rss // 1024)
    except ImportError:  # pragma: no cover
        return -1


def _slope_kib_per_1000(points: list[tuple[int, int]]) -> float:
    """Least-squares slope of RSS [KiB] against window index, per 1000 windows."""
    if len(points) < 2:
        return float("nan")
    n = len(points)
    mx = sum(p[0] for p in points) / n
    my = sum(p[1] for p in points) / n
    sxx = sum((p[0] - mx) ** 2 for p in points)
    if sxx == 0:
        return float("nan")
    sxy = sum((p[0] - mx) * (p[1] - my) for p in points)
    return sxy / sxx * 1000.0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=21600.0,
                    help="plant time to simulate [s] (default 21600 = 6 h)")
    ap.add_argument("--scenario", default="resistance_degradation",
                    help="plant scenario (nominal | resistance_degradation | bearing_wear | ...)")
    ap.add_argument("--fault-period", type=float, default=1200.0,
                    help="restart the degradation every N s (a maintenance replaces the part; "
                    "the paper's Ra law leaves the motor's physical range 1667 s after onset, "
                    "so hours of it need one); 0: never")
    ap.add_argument("--every", type=int, default=300, help="report RSS every N windows")
    ap.add_argument("--zenoh", action="store_true", help="publish health over Zenoh")
    ap.add_argument("--zenoh-listen", default="tcp/127.0.0.1:17447",
                    help="Zenoh listen endpoint when --zenoh is given (loopback)")
    ap.add_argument("--record", metavar="PATH", default=None,
                    help="record to this .rrd file (default: no recording)")
    ap.add_argument("--rotate-windows", type=int, default=None,
                    help="with --record: windows per recording file ([recording] "
                    "rotate_windows, default 1800; 0 keeps one file, whose in-memory footer "
                    "manifest grows ~27 MiB per 1000 windows)")
    ap.add_argument("--state", metavar="PATH", default=None,
                    help="keep the health history and the twin in this SQLite file, as the "
                    "service does (default: no state store); the file size is printed")
    ap.add_argument("--tracemalloc", action="store_true",
                    help="trace Python allocations and print the top growth (slower)")
    ap.add_argument("--history", type=int, default=None,
                    help="health messages the daemon keeps in memory ([acquisition] history, "
                    "default 1000); a small value shows within a short run whether RSS is "
                    "flat once that buffer is full")
    ap.add_argument("--log-level", default="warning")
    args = ap.parse_args(argv)
    logging.basicConfig(level=getattr(logging, args.log_level.upper()),
                        format="%(asctime)s %(levelname)-7s %(name)s: %(message)s")

    cfg = default_config()
    cfg.driver.plant.duration = args.duration  # type: ignore[union-attr]
    cfg.driver.plant.scenario = args.scenario  # type: ignore[union-attr]
    cfg.driver.plant.fault_period = args.fault_period or None  # type: ignore[union-attr]
    type(cfg.driver.plant).model_validate(cfg.driver.plant.model_dump())  # refuse a bad run
    cfg.zenoh.listen = [args.zenoh_listen]
    if args.record:
        cfg.recording.path = str(Path(args.record).resolve())
    cfg.recording.enabled = bool(args.record)
    if args.rotate_windows is not None:
        cfg.recording.rotate_windows = args.rotate_windows
    if args.state:
        cfg.state.path = str(Path(args.state).resolve())
    cfg.state.enabled = bool(args.state)
    cfg.zenoh.enabled = bool(args.zenoh)
    if args.history is not None:
        cfg.acquisition.history = args.history

    if args.tracemalloc:
        tracemalloc.start(10)
    t_wall0 = time.monotonic()
    daemon = Daemon(cfg, publish=args.zenoh, record=bool(args.record), persist=bool(args.state))
    rss0 = rss_kib()
    print(f"soak: {args.duration:.0f} s of plant time ({args.scenario}, part replaced every "
          f"{args.fault_period:.0f} s), zenoh "
          f"{'on' if args.zenoh else 'off'}, recording {args.record or 'off'} (rotate every "
          f"{cfg.recording.rotate_windows} windows), state {args.state or 'off'}, "
          f"pid {os.getpid()}")
    print(f"RSS at start (daemon constructed): {rss0 / 1024:.1f} MiB")
    points: list[tuple[int, int]] = []
    snap: list[Any] = []
    first: list[int] = []
    elapsed: list[float] = []

    plant = getattr(daemon.driver, "plant", None)
    ra_err: list[float] = []   # |Ra published - Ra true| / Ra true, windows not held [%]
    held = [0]
    levels: dict[str, int] = {}

    def _on_window(health: HealthMessage) -> None:
        w = health.window
        elapsed.append(health.elapsed_s)
        ra = health.parameters.get("Ra")
        if ra is not None and ra.held:
            held[0] += 1
        elif plant is not None and ra is not None and ra.value is not None:
            true = plant.truth(0.5 * (health.t_start + health.t_end)).Ra
            ra_err.append(abs(ra.value - true) / true * 100.0)
        for name, a in health.alarms.items():
            key = f"{name} {a.level}"
            levels[key] = levels.get(key, 0) + 1
        if not first:
            first.append(w)
            r = rss_kib()
            points.append((w, r))
            print(f"RSS after first window {w} (numba compiled): {r / 1024:.1f} MiB", flush=True)
            return
        if w % args.every == 0:
            r = rss_kib()
            points.append((w, r))
            c = health.counters
            print(f"window {w:6d}  t={health.t_end:8.0f} s  RSS {r / 1024:7.1f} MiB  "
                  f"overruns {c.get('overruns', 0)}  numeric failures "
                  f"{c.get('numeric_failures', 0)}  wall {time.monotonic() - t_wall0:6.0f} s",
                  flush=True)
            if args.tracemalloc and not snap:
                snap.append(tracemalloc.take_snapshot())

    daemon.add_callback(_on_window)
    try:
        daemon.run()
    finally:
        daemon.close()
    wall = time.monotonic() - t_wall0
    rss_end = rss_kib()
    c = daemon.counters()
    # slope over the in-run reports only: closing the sinks (Rerun's final flush) moves RSS
    half = [p for p in points if p[0] >= c["windows_estimated"] / 2]
    elapsed.sort()
    print("---")
    print(f"windows processed: {c['windows_estimated']} (completed {c['windows_completed']}, "
          f"abandoned {c['windows_abandoned']})")
    print(f"overruns: {c['overruns']}  numeric failures: {c['numeric_failures']}")
    print(f"wall time: {wall:.1f} s  ({args.duration / wall:.1f}x real time)")
    if elapsed:
        print(f"estimation per window: median {elapsed[len(elapsed) // 2] * 1e3:.0f} ms, "
              f"max {elapsed[-1] * 1e3:.0f} ms")
    if ra_err:
        ra_err.sort()
        q95 = ra_err[int(0.95 * len(ra_err))]
        print(f"Ra tracking (published windows vs the plant's true Ra): {len(ra_err)} windows, "
              f"median {ra_err[len(ra_err) // 2]:.3f} %, 95th {q95:.3f} %, "
              f"max {ra_err[-1]:.2f} %; Ra held in {held[0]} windows")
    if levels:
        print("windows per alarm level: "
              + ", ".join(f"{k} {v}" for k, v in sorted(levels.items())))
    print(f"RSS start {rss0 / 1024:.1f} MiB, after first window "
          f"{points[0][1] / 1024:.1f} MiB, last in-run report {points[-1][1] / 1024:.1f} MiB, "
          f"after close {rss_end / 1024:.1f} MiB")
    print(f"RSS slope over the second half of the run: "
          f"{_slope_kib_per_1000(half):.0f} KiB per 1000 windows "
          f"(history kept in memory: {cfg.acquisition.history} health messages)")
    rotate = cfg.recording.rotate_windows if args.record else 0
    if rotate:
        # Within a recording file RSS rises (Rerun's footer manifest) and falls at rotation:
        # compare points at the same phase, just after each rotation.
        at_rotation = [p for p in points if p[0] > 0 and p[0] % rotate == 0]
        print("RSS just after each rotation: "
              + ", ".join(f"{p[1] / 1024:.1f}" for p in at_rotation)
              + f" MiB; slope {_slope_kib_per_1000(at_rotation):.0f} KiB per 1000 windows")
    if args.state:
        size = sum(p.stat().st_size for p in Path(cfg.state.path).parent.glob(
            Path(cfg.state.path).name + "*"))
        print(f"state store {cfg.state.path}: {size / 2**20:.1f} MiB (with -wal/-shm)")
    if args.record:
        rec = Path(cfg.recording.path)
        files = sorted(f for f in rec.parent.glob(rec.stem + "-*.rrd")  # the run's files
                       if not f.is_symlink())
        print(f"recording: {len(files)} file(s), "
              f"{sum(f.stat().st_size for f in files) / 2**20:.1f} MiB")
    if args.tracemalloc and snap:
        end = tracemalloc.take_snapshot()
        print("top Python allocation growth since the first report:")
        for stat in end.compare_to(snap[0], "lineno")[:10]:
            print(f"  {stat}")
    return 0 if c["numeric_failures"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
