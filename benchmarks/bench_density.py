"""How many machines this box monitors in real time (issues 19, 22): one process per machine
against the service host on a directory (``twinwatch run DIR``: its worker processes, one per
core by default, ``--workers``). Runs on a plain install (no test helpers, no pytest).

N machines (the simulated DC motor, each its own recording: seed, noise 0.5 %) are monitored
for ``--seconds`` of plant time, all started at the same moment. The plants run *before* the
monitor, in a separate process (``_plants``): each machine's samples are written to a CSV that
the monitor's file driver replays in real time (``realtime = true``: each row when its time
stamp is due on the wall clock; a live source, so a window the estimator cannot take is dropped
and counted as an overrun). The plants' cost is therefore none of the figures: they are the
monitor's own, acquisition (the file driver's parsing and pacing, as a bus driver's decoding
would be) included. Each machine stores every window in its state database and publishes it
on Zenoh (one port per process; in gateway mode one shared session); no Rerun recording
(``--recording`` adds it).

Printed per run (N, mode): windows estimated of those expected, overruns, the estimation time
per window over every machine (p50, p95, max: the health message's ``elapsed_s``, the first,
compiling window included), the windows' queue wait (median of the machines' medians, the
largest; from the run summaries), CPU share of the whole box's cores (100 % = one core) and
per machine, resident memory per machine (the peak of the processes' VmRSS summed, divided by
N; a host's worker processes are summed with it, their CPU too; RSS counts the libraries every
process maps, about 130 MB each, once per process; PSS divides each shared page among the
processes that map it: the memory the box gives the fleet), and ``late60``: the worst window
after the first minute of plant time, how much later than the machine's promptest window it
was stored (ms; the file replays in real time, so a window's end is due at a fixed offset from
its plant time: this is the queueing a window suffered beyond the machine's best case), and
under the row the box's load from other processes and the fleet's CPU seconds per window
estimated (less sensitive to that load than the overruns).
``--cold`` points ``NUMBA_CACHE_DIR`` at an empty directory: every kernel is compiled, as on
the first start after an install (a reboot with an installed unit keeps its cache in
``/var/cache/twinwatch``). Each run is bounded by ``--seconds`` + 150 s of wall time.

Usage::

    python benchmarks/bench_density.py --n 4 16 [--seconds 40] [--mode both|gateway|process]
                                       [--cold] [--workers K] [--slots K] [--gateways K]
                                       [--acquisition-only] [--recording] [--keep DIR]
                                       [--opcua]

``--opcua`` adds ``[outputs.opcua]`` to every machine: in gateway mode one OPC UA server per
Zenoh port (so per worker process: the machines of one endpoint share it), one per machine
otherwise.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SIM = ROOT / "config" / "dc-motor-sim.toml"
CLK_TCK = os.sysconf("SC_CLK_TCK")

sys.path.insert(0, str(ROOT))
from twinwatch.daemon.slots import default_processes  # noqa: E402

PORT_BASE = 27400
OPCUA_OFFSET = 1000  # --opcua: the OPC UA endpoint of a machine is its Zenoh port + this

FILE_DRIVER = """[driver]
type = "file"
path = "{path}"
time_column = "t"
sample_period = 0.01
realtime = true
[driver.columns]
Va = {{ column = "Va" }}
ia = {{ column = "ia" }}
omega = {{ column = "omega" }}
Tload = {{ column = "Tload" }}
setpoint = {{ column = "setpoint" }}
"""


def write_plants(directory: Path, n: int, seconds: float) -> None:
    """(Runs in its own process.) One recording per machine: the simulated DC motor, the
    resistance degrading, set-point levels and noise seeded by the machine's number."""
    for i in range(n):
        path = plant_path(directory, i, seconds)
        if not path.exists():
            plant_csv(path, seconds + 4.0, plant={
                "scenario": "resistance_degradation", "fault_start": 5.0,
                "noise": {"ia": 0.5, "omega": 0.5}, "seed": i,
                "setpoint": {"seed": i + 1}})


def plant_csv(path: Path, seconds: float, plant: dict) -> None:  # type: ignore[type-arg]
    """A CSV recording of the simulated DC motor (``t`` and the plant's channels): written
    here, not by the test suite's helper, so the benchmark runs on a plain install."""
    from twinwatch.plant.dcmotor import CHANNELS, DCMotorPlant, DCMotorPlantConfig

    cfg = DCMotorPlantConfig(**{"scenario": "nominal", "duration": seconds, **plant})
    p = DCMotorPlant(cfg)
    rows = ["t," + ",".join(CHANNELS)]
    for _ in range(int(round(seconds / cfg.sample_period))):
        smp = p.next_sample()
        rows.append(f"{smp.t:.7f}," + ",".join(repr(smp.values[c]) for c in CHANNELS))
    path.write_text("\n".join(rows) + "\n")


def windows_expected(name: str, seconds: float, mode: str) -> int:
    """Windows of 200 samples at 10 ms in ``seconds`` of plant time; in a gateway the first
    one is lengthened by the machine's phase (``[acquisition] stagger``)."""
    samples = int(round(seconds / 0.01))
    phase = zlib.crc32(name.encode()) % 200 if mode == "gateway" else 0
    return (samples - phase) // 200


def plant_path(directory: Path, i: int, seconds: float) -> Path:
    return directory / f"plant{i:03d}-{seconds:g}s.csv"


def machine_config(i: int, recording: Path, port: int, record: bool,
                   acquisition_only: bool = False, opcua: int | None = None) -> str:
    text = SIM.read_text().replace('name = "dc-motor-sim"', f'name = "m{i:03d}"')
    start, end = text.index("[driver]"), text.index("[zenoh]")
    text = text[:start] + FILE_DRIVER.format(path=recording) + "\n" + text[end:]
    text = text.replace("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{port}")
    if not record:
        text = text.replace("[recording]", "[recording]\nenabled = false")
    if acquisition_only:  # a window longer than the run: samples acquired, nothing estimated
        text = text.replace("window = 200 ", "window = 100000 ")
    if opcua is not None:  # the OPC UA output on 127.0.0.1:<opcua> (issue 35)
        text += f'\n[outputs.opcua]\nendpoint = "opc.tcp://127.0.0.1:{opcua}"\n'
    return text


def _cpu_ticks(pid: int) -> int | None:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return int(fields[11]) + int(fields[12])  # utime + stime


def _tree(pid: int) -> list[int]:
    """``pid`` and its descendants (a host's worker processes)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        try:
            for task in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass
    return out


def _reaped_ticks(pid: int) -> int:
    """CPU ticks of ``pid``'s children it has waited for (a worker that died and was
    restarted)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0
    return int(fields[13]) + int(fields[14])  # cutime + cstime


def _proc_mb(pid: int, file: str, key: str) -> float | None:
    """The ``key:`` line of ``/proc/<pid>/<file>`` [kB] in MB; None once the process is gone."""
    try:
        for line in Path(f"/proc/{pid}/{file}").read_text().splitlines():
            if line.startswith(key):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def _rss_mb(pid: int) -> float | None:
    return _proc_mb(pid, "status", "VmRSS:")


def _pss_mb(pid: int) -> float | None:
    """Proportional resident memory: each shared page (the libraries every worker maps)
    divided among the processes that map it, so a sum over processes counts it once."""
    return _proc_mb(pid, "smaps_rollup", "Pss:")


@dataclass
class Run:
    n: int
    mode: str
    expected: int = 0
    estimated: int = 0
    overruns: int = 0
    failures: int = 0
    elapsed: list[float] = field(default_factory=list)
    first: list[float] = field(default_factory=list)
    wait_medians: list[float] = field(default_factory=list)
    wait_max: float = 0.0
    cpu_s: float = 0.0
    wall_s: float = 0.0
    peak_rss_mb: float = 0.0
    peak_pss_mb: float = 0.0
    exit_codes: list[int] = field(default_factory=list)
    start_s: float = 0.0
    #: the latest window stored after the first minute, against the machine's promptest (ms)
    late_ms: float = float("nan")
    #: which window was the latest, and its estimation time
    late_where: str = ""
    #: the worst lateness [ms] of the windows ending in each 30 s of plant time (0: 0-30 s)
    late_by_30s: dict[int, float] = field(default_factory=dict)
    #: the latest windows after the first minute: (ms late, machine, window, stored at [s
    #: after launch], its estimation [ms]), latest first
    latest: list[tuple[float, str, int, float, float]] = field(default_factory=list)
    #: the box's busy CPU over the run, every process (ours too), and the hypervisor's steal [s]
    box_s: float = 0.0
    steal_s: float = 0.0
    #: every window's storing moment [s since the epoch] (the state databases' ``wall``)
    walls: list[float] = field(default_factory=list)
    #: the steady state (:func:`steady_state`): (from, to [s after launch], CPU per window
    #: stored there [s], windows stored per second there); None when the run is too short
    steady: tuple[float, float, float, float] | None = None

    def others(self) -> str:
        """The rest of the box's load during the run: a lateness figure depends on it (the two
        cores are shared)."""
        if not self.wall_s:
            return ""
        per_window = (f"; the fleet's CPU {self.cpu_s:.0f} s, "
                      f"{1e3 * self.cpu_s / self.estimated:.1f} ms per window estimated (less "
                      f"load-sensitive than the overruns; windows dropped cost their "
                      f"acquisition)" if self.estimated else "")
        return (f"box busy {100 * self.box_s / self.wall_s:.0f} % over the run, of which "
                f"other processes {100 * max(self.box_s - self.cpu_s, 0.0) / self.wall_s:.0f} %,"
                f" steal {100 * self.steal_s / self.wall_s:.0f} %" + per_window)

    def row(self) -> str:
        e = sorted(self.elapsed)

        def pct(q: float) -> float:
            return e[min(len(e) - 1, int(q * len(e)))] * 1e3 if e else float("nan")

        cpu = 100.0 * self.cpu_s / self.wall_s if self.wall_s else float("nan")
        wait_med = statistics.median(self.wait_medians) if self.wait_medians else float("nan")
        return (f"{self.n:>4} {self.mode:<8} {self.estimated:>5}/{self.expected:<5} "
                f"{self.overruns:>8} {pct(0.5):>7.0f} {pct(0.95):>7.0f} "
                f"{(e[-1] * 1e3 if e else float('nan')):>8.0f} "
                f"{(max(self.first) * 1e3 if self.first else float('nan')):>8.0f} "
                f"{wait_med:>8.0f} {self.wait_max:>8.0f} {cpu:>7.0f} {cpu / self.n:>8.1f} "
                f"{self.peak_rss_mb / self.n:>9.1f} {self.peak_pss_mb / self.n:>9.1f} "
                f"{self.peak_rss_mb:>8.0f} "
                f"{self.start_s:>7.1f} {self.late_ms:>8.0f} "
                f"{','.join(map(str, sorted(set(self.exit_codes))))}")


HEADER = (f"{'N':>4} {'mode':<8} {'windows':>11} {'overruns':>8} {'p50ms':>7} {'p95ms':>7} "
          f"{'max ms':>8} {'1st ms':>8} {'wait50':>8} {'waitmax':>8} {'CPU%':>7} "
          f"{'CPU%/m':>8} {'RSS/m MB':>9} {'PSS/m MB':>9} {'RSS MB':>8} {'start s':>7} "
          f"{'late60':>8} exit")


def read_results(run: Run, dirs: list[Path], launched: float = 0.0) -> None:
    """Fill ``run`` from the machines' state databases (``launched``: the run's start [s
    since the epoch], for the wall-clock moments of the latest windows)."""
    for d in dirs:
        db = d / "state.sqlite"
        if not db.exists():
            continue
        con = sqlite3.connect(db)
        try:
            docs = [json.loads(r[0]) for r in con.execute("SELECT doc FROM health ORDER BY id")]
            stamps = con.execute("SELECT t_end, wall FROM health ORDER BY id").fetchall()
        finally:
            con.close()
        if not docs:
            continue
        run.estimated += len(docs)
        if stamps:
            # a file replayed in real time: a window's end is due at a fixed wall-clock offset
            # from its plant time; how much later than the machine's promptest window each
            # one was stored, from the first minute of plant time on
            offsets = [wall - t_end for t_end, wall in stamps]
            best = min(offsets)
            for (t_end, _), o in zip(stamps, offsets, strict=True):
                b = int((t_end - stamps[0][0]) // 30)
                run.late_by_30s[b] = max(run.late_by_30s.get(b, 0.0), 1e3 * (o - best))
            late = [(o - best, k) for k, ((t_end, _), o) in enumerate(
                zip(stamps, offsets, strict=True)) if t_end - stamps[0][0] >= 60.0]
            run.latest += [(1e3 * lag, d.name, k, stamps[k][1] - launched,
                            1e3 * float(docs[k]["elapsed_s"])) for lag, k in late]
            run.latest = sorted(run.latest, reverse=True)[:8]
            if late:
                lag, k = max(late)
                worst = 1e3 * lag
                if math.isnan(run.late_ms) or worst > run.late_ms:
                    run.late_ms = worst
                    run.late_where = (f"{d.name} window {k} (t_end {stamps[k][0]:.0f} s): "
                                      f"{worst:.0f} ms late, its estimation "
                                      f"{1e3 * float(docs[k]['elapsed_s']):.0f} ms, the one "
                                      f"before {1e3 * float(docs[k - 1]['elapsed_s']):.0f} ms")
        run.walls += [float(wall) for _, wall in stamps]
        run.elapsed += [float(doc["elapsed_s"]) for doc in docs]
        run.first.append(float(docs[0]["elapsed_s"]))
        counters = docs[-1].get("counters", {})
        run.overruns += int(counters.get("overruns", 0))
        run.failures += int(counters.get("numeric_failures", 0))


#: The steady state starts this long [s] after the last machine's first window: past each
#: machine's start swarm and the first windows' one-off work (the diagnosis learns its baseline
#: in the first 10 windows, a trend is first fitted after 10).
STEADY_AFTER_S = 30.0
#: A window every this many seconds per machine (200 samples at 10 ms, :data:`FILE_DRIVER`).
WINDOW_S = 2.0


def steady_state(series: list[tuple[float, float]], t_launch: float, walls: list[float],
                 launched: float, start_s: float) -> tuple[float, float, float, float] | None:
    """The fleet's CPU per window in the steady state: from :data:`STEADY_AFTER_S` after the
    last machine's first window (``start_s`` after launch, less its 2 s of acquisition) to the
    last window stored less 2 s, the processes' CPU over the windows stored in between.

    Args:
        series: (monotonic time, the processes' CPU seconds so far), from :func:`monitor`.
        t_launch: the launch's monotonic time.
        walls: every window's storing moment [s since the epoch].
        launched: the launch [s since the epoch].
        start_s: :attr:`Run.start_s`.

    Returns:
        (from, to [s after launch], CPU per window stored [s], windows stored per second), or
        None when the span is shorter than 10 s or holds no window.
    """
    if len(series) < 2 or not walls:
        return None
    t_from = start_s + 2.0 + STEADY_AFTER_S
    t_to = max(walls) - launched - 2.0
    if t_to - t_from < 10.0:
        return None
    times = np.array([t - t_launch for t, _ in series])
    cpu = np.array([c for _, c in series])
    stored = sum(1 for w in walls if t_from <= w - launched <= t_to)
    if not stored:
        return None
    used = float(np.interp(t_to, times, cpu) - np.interp(t_from, times, cpu))
    return t_from, t_to, used / stored, stored / (t_to - t_from)


WAIT_RE = re.compile(r"queue wait per window: median (\d+) ms, max (\d+) ms")


def monitor(procs: list[subprocess.Popen[str]], timeout: float,
            series: list[tuple[float, float]] | None = None
            ) -> tuple[float, float, float, float, float, float]:
    """Sample CPU and memory of ``procs`` until they exit: (CPU seconds, wall seconds, the
    peak of the processes' summed RSS and of their summed PSS [MB], the box's busy CPU
    seconds over the same span (every process, ours included), of which steal). ``series``
    gets (monotonic time, the processes' CPU seconds so far) at every sample."""
    t0 = time.monotonic()
    box0 = _box_ticks()
    last_ticks = {p.pid: 0 for p in procs}
    peak = {p.pid: 0.0 for p in procs}
    peak_pss = {p.pid: 0.0 for p in procs}
    trees: dict[int, list[int]] = {}
    next_slow = t0
    deadline = t0 + timeout
    while any(p.poll() is None for p in procs):
        if time.monotonic() > deadline:
            for p in procs:
                if p.poll() is None:
                    p.terminate()
            print(f"  (timeout after {timeout:.0f} s: stopped)", file=sys.stderr)
            deadline = float("inf")
        # the measurement's own cost kept off the box it measures: a PSS read walks the
        # process's page tables (5.6 ms of CPU for a 300 MB worker; every 0.5 s for five
        # processes it was 6 % of a core), so PSS and the process tree every 5 s, the cheap
        # figures (CPU ticks, VmRSS) every 0.5 s
        slow = time.monotonic() >= next_slow
        if slow:
            next_slow = time.monotonic() + 5.0
        for p in procs:  # the process and its workers, summed
            if slow or p.pid not in trees:
                trees[p.pid] = _tree(p.pid)
            tree = trees[p.pid]
            ticks = [t for q in tree if (t := _cpu_ticks(q)) is not None]
            if ticks:
                last_ticks[p.pid] = max(last_ticks[p.pid], sum(ticks) + _reaped_ticks(p.pid))
            rss = [r for q in tree if (r := _rss_mb(q)) is not None]
            if rss:
                peak[p.pid] = max(peak[p.pid], sum(rss))
            pss = [r for q in tree if (r := _pss_mb(q)) is not None] if slow else []
            if pss:
                peak_pss[p.pid] = max(peak_pss[p.pid], sum(pss))
        if series is not None:
            series.append((time.monotonic(), sum(last_ticks.values()) / CLK_TCK))
        time.sleep(0.5)
    box1 = _box_ticks()
    return (sum(last_ticks.values()) / CLK_TCK, time.monotonic() - t0, sum(peak.values()),
            sum(peak_pss.values()), (box1[0] - box0[0]) / CLK_TCK, (box1[1] - box0[1]) / CLK_TCK)


def _box_ticks() -> tuple[int, int]:
    """(busy, steal) clock ticks of the whole box since boot (``/proc/stat``: user, nice,
    system, irq, softirq, steal; steal alone: what the hypervisor gave other guests)."""
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:]]
    return v[0] + v[1] + v[2] + v[5] + v[6] + v[7], v[7]


def run_once(n: int, mode: str, seconds: float, plants: Path, *, cold: bool, record: bool,
             workers: int | None, acquisition_only: bool = False, gateways: int = 1,
             keep: Path | None = None, opcua: bool = False, slots: int | None = None) -> Run:
    run = Run(n=n, mode=mode if gateways == 1 or mode != "gateway" else f"gw x{gateways}",
              expected=0 if acquisition_only else sum(
                  windows_expected(f"m{i:03d}", seconds, mode) for i in range(n)))
    with tempfile.TemporaryDirectory(prefix=f"density-{mode}-{n}-") as tmp:
        root = Path(tmp)
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        if cold:
            env["NUMBA_CACHE_DIR"] = str(root / "numba-cache")
        machines = root / "machines"
        machines.mkdir()
        shards = [root / f"machines{k}" for k in range(gateways)]
        for i in range(n):
            # a host's machines share one Zenoh session per process: one port per worker
            # process (machines with one [zenoh] table go to one worker)
            ports = max(gateways, workers if workers is not None else default_processes(n))
            port = PORT_BASE + i % ports if mode == "gateway" else PORT_BASE + 100 + i
            where = shards[i % gateways] if mode == "gateway" and gateways > 1 else machines
            where.mkdir(exist_ok=True)
            # the OPC UA output: one server per Zenoh group (per worker process), its
            # machines sharing it (one process per machine: a server each)
            (where / f"m{i:03d}.toml").write_text(
                machine_config(i, plant_path(plants, i, seconds), port, record,
                               acquisition_only, opcua=port + OPCUA_OFFSET if opcua else None))
        cmd = [sys.executable, "-m", "twinwatch", "run", "--no-progress", "--duration",
               str(seconds)]
        t_start = time.monotonic()
        procs: list[subprocess.Popen[str]] = []
        if mode == "gateway":
            if workers is not None:
                cmd += ["--workers", str(workers)]
            if slots is not None:
                cmd += ["--slots", str(slots)]
            for k, shard in enumerate(shards if gateways > 1 else [machines]):
                procs.append(subprocess.Popen([*cmd, str(shard)], cwd=root, env=env,
                                              stdout=subprocess.PIPE,
                                              stderr=(root / f"stderr-{k}.txt").open("w"),
                                              text=True))
            dirs = [root / f"m{i:03d}" for i in range(n)]
        else:
            dirs = []
            for i in range(n):
                d = root / f"m{i:03d}"
                d.mkdir()
                dirs.append(d)
                procs.append(subprocess.Popen([*cmd, str(machines / f"m{i:03d}.toml")],
                                              cwd=d, env=env, stdout=subprocess.PIPE,
                                              stderr=(root / f"stderr-{i}.txt").open("w"),
                                              text=True))
        out: list[str] = []
        import threading

        readers = [threading.Thread(target=lambda p=p: out.append(p.stdout.read()))
                   for p in procs]
        for t in readers:
            t.start()
        series: list[tuple[float, float]] = []
        (run.cpu_s, run.wall_s, run.peak_rss_mb, run.peak_pss_mb, run.box_s,
         run.steal_s) = monitor(procs, seconds + 150, series)
        for t in readers:
            t.join()
        run.exit_codes = [p.returncode for p in procs]
        for i, code in enumerate(run.exit_codes):
            if code not in (0, None):  # say why a monitor died: its last log lines
                tail = (root / f"stderr-{i}.txt").read_text(errors="replace").splitlines()
                print(f"  process {i} exited {code}:", *tail[-6:], sep="\n    ",
                      file=sys.stderr)
        text = "\n".join(out)
        for m in WAIT_RE.finditer(text):
            run.wait_medians.append(float(m.group(1)))
            run.wait_max = max(run.wait_max, float(m.group(2)))
        # start: wall time until the first window was stored (from the databases' wall)
        firsts = []
        for d in dirs:
            db = d / "state.sqlite"
            if db.exists():
                con = sqlite3.connect(db)
                row = con.execute("SELECT MIN(wall) FROM health").fetchone()
                con.close()
                if row and row[0]:
                    firsts.append(row[0])
        launched = time.time() - (time.monotonic() - t_start)  # the launch [s since the epoch]
        if firsts:
            run.start_s = max(firsts) - launched - 2.0
        read_results(run, dirs, launched=launched)
        run.steady = steady_state(series, t_start, run.walls, launched, run.start_s)
        if keep is not None:  # the databases and the processes' logs, for a closer look
            dest = keep / f"{n}-{run.mode.replace(' ', '')}"
            dest.mkdir(parents=True, exist_ok=True)
            for f in root.glob("stderr-*.txt"):
                shutil.copy2(f, dest / f.name)
            for d in dirs:
                if (d / "state.sqlite").exists():
                    shutil.copy2(d / "state.sqlite", dest / f"{d.name}.sqlite")
            print(f"       kept in {dest}", flush=True)
    return run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, nargs="+", default=[4, 16])
    ap.add_argument("--seconds", type=float, default=40.0, help="plant time per machine [s]")
    ap.add_argument("--mode", choices=["both", "gateway", "process"], default="both")
    ap.add_argument("--cold", action="store_true", help="an empty numba cache (compile all)")
    ap.add_argument("--recording", action="store_true", help="also record to Rerun")
    ap.add_argument("--workers", type=int, default=None,
                    help="gateway mode: the host's worker processes (default: one per core; "
                    "1: every machine in the host process)")
    ap.add_argument("--slots", type=int, default=None,
                    help="gateway mode: windows each process estimates at once (default: its "
                    "cores; 0: no limit, the 'no slots' row of docs/gateway.md)")
    ap.add_argument("--gateways", type=int, default=1,
                    help="gateway mode: the machines split over this many gateway processes "
                    "(each its own Zenoh port)")
    ap.add_argument("--acquisition-only", action="store_true",
                    help="windows longer than the run: the cost of acquiring, storing nothing")
    ap.add_argument("--opcua", action="store_true",
                    help="also serve the health over OPC UA ([outputs.opcua]: one server per "
                    "worker process, its machines sharing it)")
    ap.add_argument("--keep", type=Path, default=None,
                    help="copy each machine's state database and the processes' logs here")
    ap.add_argument("--plants", type=Path, default=Path(tempfile.gettempdir()) / "density-plants")
    args = ap.parse_args()
    args.plants.mkdir(parents=True, exist_ok=True)
    t = time.monotonic()
    subprocess.run([sys.executable, __file__, "_plants", str(args.plants), str(max(args.n)),
                    str(args.seconds)], check=True)
    print(f"plants: {max(args.n)} recordings of {args.seconds + 4:g} s written by a separate "
          f"process in {time.monotonic() - t:.1f} s ({args.plants})")
    cores = len(os.sched_getaffinity(0))
    print(f"box: {cores} cores; {'cold (empty numba cache)' if args.cold else 'warm cache'}; "
          f"CPU% of one core (box = {100 * cores} %); start s: from launch to the last "
          "machine's first window, less its 2 s of acquisition")
    print(HEADER)
    modes = ["process", "gateway"] if args.mode == "both" else [args.mode]
    for n in args.n:
        for mode in modes:
            r = run_once(n, mode, args.seconds, args.plants, cold=args.cold,
                         record=args.recording, workers=args.workers,
                         acquisition_only=args.acquisition_only, gateways=args.gateways,
                         keep=args.keep, opcua=args.opcua, slots=args.slots)
            print(r.row(), flush=True)
            print(f"       {r.others()}", flush=True)
            if r.steady is not None:
                t0, t1, per_window, rate = r.steady
                print(f"       steady state {t0:.0f}-{t1:.0f} s after launch: "
                      f"{1e3 * per_window:.1f} ms of CPU per window stored, {rate:.1f} windows/s; "
                      f"at that cost the box's {cores} cores hold at most "
                      f"{cores * WINDOW_S / per_window:.0f} machines (a window each every "
                      f"{WINDOW_S:g} s, nothing to spare)", flush=True)
            if r.late_where:
                print(f"       late60: {r.late_where}", flush=True)
            if r.latest:
                print("       latest after the first minute (ms late, machine/window, stored "
                      "at s after launch, estimation ms): " + "; ".join(
                          f"{ms:.0f} {m}/{k} at {at:.1f} s {est:.0f}"
                          for ms, m, k, at, est in r.latest), flush=True)
            if r.late_by_30s:
                print("       worst lateness by plant time [ms]: " + ", ".join(
                    f"{30 * b}-{30 * b + 30} s {v:.0f}" for b, v in sorted(r.late_by_30s.items())),
                    flush=True)


if __name__ == "__main__":
    if len(sys.argv) == 5 and sys.argv[1] == "_plants":
        write_plants(Path(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4]))
    else:
        main()
