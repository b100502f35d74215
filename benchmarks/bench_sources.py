"""Sources that misbehave, measured (issue 15): the figures the tests do not time.

``replay``: replaying a Vector ASC log of the simulated motor (18,000 lines, 60 s) through the
CAN driver, clean and with 300 malformed lines: wall time of each and their ratio. A bad line
costs O(1) (the reader resumes at the next line); it used to cost a re-read from the top.

``gateway``: CPU while the daemon waits for a CAN gateway that went away. A loopback socketcand
server (harness/sources.py) feeds the simulated motor's frames to ``twinwatch run`` (in a
subprocess, as the unit runs it) in real time; it is stopped for ``--outage`` seconds and
started again. Prints the process's CPU share while the gateway is away (measured from
/proc/PID/stat over the outage, less the first second), whether and when it reconnected, and
the windows stored before and after.

Usage::

    python benchmarks/bench_sources.py replay [--runs 3]
    python benchmarks/bench_sources.py gateway [--outage 5] [--twinwatch /work/main]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from harness.sources import PLANT_DBC, plant_asc_log  # noqa: E402


def _replay_once(log: Path) -> tuple[float, int, int]:
    from twinwatch.drivers import EndOfStream, create_driver

    table = {"type": "can", "dbc": str(PLANT_DBC), "log_file": str(log),
             "sync_message": "TW_Motor_Sample", "time_source": "counter",
             "counter_signal": "TW_Motor_Sample.sample_counter", "sample_period": 0.01,
             "signals": {ch: {"message": m, "signal": ch} for m, chs in (
                 ("TW_Motor_Electrical", ("Va", "ia")),
                 ("TW_Motor_Mechanical", ("omega", "Tload")),
                 ("TW_Motor_Sample", ("setpoint",))) for ch in chs}}
    n = 0
    t0 = time.perf_counter()
    with create_driver(table, base_dir=None) as drv:
        try:
            while True:
                if drv.read(0) is not None:
                    n += 1
        except EndOfStream:
            pass
        bad = drv.stats.bad_frames
    return time.perf_counter() - t0, n, bad


def replay(runs: int) -> None:
    import logging

    logging.disable(logging.WARNING)
    with tempfile.TemporaryDirectory() as tmp:
        times = {}
        for bad in (0, 300):
            log = Path(tmp) / f"bad{bad}.asc"
            lines = plant_asc_log(log, 60.0, bad=bad)
            runs_s = []
            for _ in range(runs):
                dt, n, nbad = _replay_once(log)
                runs_s.append(dt)
            times[bad] = statistics.median(runs_s)
            print(f"ASC log, {lines} lines, {nbad} malformed: {n} samples, replayed in "
                  f"{times[bad]:.2f} s (median of {runs})")
        print(f"300 malformed lines cost x{times[300] / times[0]:.2f} the clean replay")


def _cpu_seconds(pid: int) -> float:
    """utime + stime of a process [s] (/proc/PID/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _prelude(checkout: str | None) -> str:
    """Python run in the daemon's process first: import twinwatch from ``checkout`` (another
    worktree, for a before/after figure) instead of the installed one."""
    if not checkout:
        return ""
    return ("import sys\nsys.meta_path[:] = [f for f in sys.meta_path if 'editable' not in "
            f"repr(f).lower()]\nsys.path.insert(0, {checkout!r})")


def gateway(outage: float, checkout: str | None = None) -> None:
    from harness.daemon import Service, db_rows
    from harness.sources import SocketcandServer, gateway_config

    with tempfile.TemporaryDirectory() as tmp_s, SocketcandServer() as server:
        tmp = Path(tmp_s)
        cfg = gateway_config(tmp, server.port)
        svc = Service(cfg, tmp, prelude=_prelude(checkout))
        db = tmp / "state.sqlite"
        try:
            if not svc.wait_for("twinwatch.daemon.pipeline: window ", n=2, timeout=120):
                print("no window before the outage:", *svc.lines[-20:], sep="\n")
                return
            before = len(db_rows(db))
            server.stop()
            time.sleep(1.0)  # the daemon notices (no frame for its silence limit)
            c0, w0 = _cpu_seconds(svc.proc.pid), time.monotonic()
            time.sleep(max(outage - 1.0, 1.0))
            c1, w1 = _cpu_seconds(svc.proc.pid), time.monotonic()
            server.start()
            back = time.monotonic()
            ok = svc.wait_for("is open again", "delivers samples again", timeout=60)
            reconnect_s = time.monotonic() - back
            n = len(db_rows(db))
            resumed = svc.wait_for("twinwatch.daemon.pipeline: window ", n=before + 2,
                                   timeout=60)
            after = len(db_rows(db))
        finally:
            svc.send(15)
            svc.wait(30)
            svc.close()
    print(f"gateway away {outage:.0f} s: the daemon used {100 * (c1 - c0) / (w1 - w0):.1f} % "
          f"of one core while waiting ({c1 - c0:.2f} s CPU over {w1 - w0:.1f} s)")
    print(f"reconnected: {ok} ({reconnect_s:.1f} s after the gateway came back); windows "
          f"stored: {before} before the outage, {n} at reconnection, {after} after "
          f"(resumed: {resumed})")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="what", required=True)
    r = sub.add_parser("replay")
    r.add_argument("--runs", type=int, default=3)
    g = sub.add_parser("gateway")
    g.add_argument("--outage", type=float, default=5.0)
    g.add_argument("--twinwatch", default=None, metavar="CHECKOUT",
                   help="run the daemon from this checkout (e.g. a worktree of main)")
    args = p.parse_args()
    if args.what == "replay":
        replay(args.runs)
    else:
        gateway(args.outage, args.twinwatch)


if __name__ == "__main__":
    main()
