"""A window's CPU in the daemon's own code path, stage by stage, and the acquisition's per window.

    python benchmarks/bench_window.py [--machine dc|pwm|hydraulic] [--windows 60]
                                      [--realtime-windows 2]

The machine's configuration, built the way the daemon builds it: the twin, its
:class:`~twinwatch.twin.adaptation.TwinAdapter` and the ring buffer. ``dc`` (default): the
default configuration (the simulated DC motor, resistance degradation; default
``[estimation]``, ``[prognostics]`` and alarm rules); ``pwm``: ``config/dc-motor-motoshield.toml``,
the PWM drive's twin on the MotoShield board's real recording (``../shared``: 24 windows of
4 s); ``hydraulic``: ``config/hydraulic-modbus-sim.toml``'s plant (fluid degradation) read
directly, not over Modbus. The samples are made or read beforehand (the plant's own cost is
not the monitor's). Per window, CPU time
(``time.process_time``, medians, means and p95 over ``--windows`` windows from ``--from`` seconds
of plant time on, as in ``bench_estimation.py``; the windows before are processed, not
reported):

* ``window``: from the ring buffer's completed window to the health message encoded
  (:meth:`TwinAdapter.process`: estimation, fusion, discovery when due, prognostics; then
  :func:`~twinwatch.twin.health.build_health` and its JSON), split into the estimation
  (:meth:`Estimator.estimate`, fusion included), the prognostics and the rest (the reading
  check among it: the outputs the fault library names, ``ia`` here), and the diagnosis
  (:meth:`~twinwatch.twin.diagnosis.Diagnoser.update`: the fault library's hypothesis twins
  fitted on the window, as the daemon's pipeline runs it). The outputs'
  own writes (SQLite, Zenoh, MQTT) are not included: they belong to the sinks, measured by
  ``bench_density.py`` in a running host; printed after it, the saved twin the state store
  writes each window (the adapter's and the diagnosis's state, built and encoded: what a
  restart resumes from); and the cold start: the CPU of a fresh process processing the
  machine's first 3 windows on an empty numba cache and again on the cache it filled (their
  difference: the kernels' compilation, which each worker process of a gateway pays on a
  first start; ``--no-cold-start`` skips it).
* ``floor``: what a window's twin costs at its least, on the last timed window: one
  simulation of the window through the twin's exact step matrices (``model.simulate``, one
  parameter vector), and a Gauss-Newton fit of the parameters the window's gate admitted,
  from the nameplate, through the same kernel (the Jacobian by forward differences in
  ln-parameters, its columns one batched call; plain ``lstsq`` steps until they fall below
  1e-10). Its values beside the estimator's published ones say that the floor fits the same
  window to the same answer.
* ``acquisition``: the ring buffer's ``append`` for a window's 200 samples; the file driver
  reading them from a CSV as fast as it can (``realtime = false``) and replaying
  ``--realtime-windows`` windows in real time (``realtime = true``: its waiting included);
  the file driver and the ring buffer together as the acquisition loop runs them, sample by
  sample and in blocks (``read_block``, ``append_block``), and 50 real-time replays in
  threads at once with the driver waking every 0.2 s and every 1 s (``PACE_SLACK``: what a
  machine's thread costs is mostly its wake-ups); the
  CAN driver replaying a Vector ASC log of the same plant (needs the test helpers; skipped
  without them), with the libraries' share of it: python-can's ``LogReader`` reading the log
  alone and cantools decoding each frame alone (the driver's floor while it uses them); the
  reader of a queued driver (the Modbus and OPC UA drivers' base) while a thread queues a
  sample every 10 ms, in batches (``BATCH_S``) and woken once a sample. The Modbus driver
  itself needs a server on a port: ``bench_density.py`` measures it.
"""

from __future__ import annotations

import argparse
import collections
import csv
import itertools
import logging
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from twinwatch.config.loader import default_config, load_config  # noqa: E402
from twinwatch.daemon.acquisition import READ_TIMEOUT_S  # noqa: E402
from twinwatch.daemon.pipeline import EVIDENCE_EVERY, saved_twin  # noqa: E402
from twinwatch.daemon.ringbuffer import RingBuffer  # noqa: E402
from twinwatch.daemon.window_worker import make_diagnoser  # noqa: E402
from twinwatch.drivers import EndOfStream, create_driver  # noqa: E402
from twinwatch.drivers import file as file_driver  # noqa: E402
from twinwatch.io.encoding import to_json  # noqa: E402
from twinwatch.plant.dcmotor import DCMotorPlant  # noqa: E402
from twinwatch.twin.adaptation import TwinAdapter  # noqa: E402
from twinwatch.twin.health import build_health, complete_health  # noqa: E402
from twinwatch.twin.models import create_model  # noqa: E402


class _Clock:
    """CPU time spent inside a wrapped method, per window."""

    def __init__(self) -> None:
        self.spent = 0.0

    def wrap(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        def timed(*args: Any, **kwargs: Any) -> Any:
            c = time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                self.spent += time.process_time() - c
        return timed


def _stats(x: list[float]) -> str:
    a = np.asarray(x) * 1e3
    return (f"median {np.median(a):7.2f} ms   mean {np.mean(a):7.2f} ms   "
            f"p95 {np.percentile(a, 95):7.2f} ms")


#: ``--machine``: the configuration each machine is built from (the default: the built-in
#: one); the PWM drive replays the MotoShield board's recording (``../shared``), the others
#: run their simulated plant.
MACHINES = {"dc": None, "pwm": "dc-motor-motoshield.toml", "hydraulic": "hydraulic-modbus-sim.toml"}


def _machine(machine: str, noise: float) -> tuple[Any, Any]:
    """The configuration of ``machine`` (:data:`MACHINES`) and an iterator of its samples."""
    name = MACHINES[machine]
    if name is None:
        cfg = default_config()
        plant_cfg = cfg.driver.plant  # type: ignore[union-attr]
        if noise:
            plant_cfg = plant_cfg.model_copy(update={"noise": {"ia": noise, "omega": noise}})
        return cfg, _until_end(DCMotorPlant(plant_cfg).next_sample)
    cfg = load_config(ROOT / "config" / name)
    if machine == "hydraulic":
        from twinwatch.plant.hydraulic import HydraulicPlant

        plant = HydraulicPlant(cfg.driver.plant)  # type: ignore[union-attr]
        return cfg, _until_end(plant.next_sample)

    def recording() -> Any:
        with create_driver(cfg.driver, base_dir=ROOT / "config") as drv:
            yield from (s for s in _until_end(lambda: drv.read(None)) if s is not None)
    return cfg, recording()


def _until_end(next_sample: Callable[[], Any]) -> Any:
    """The samples ``next_sample`` returns until it raises :class:`EndOfStream`."""
    try:
        while True:
            yield next_sample()
    except EndOfStream:
        return


def window_cost(n_windows: int, t_from: float, noise: float = 0.0,
                keep: dict[str, Any] | None = None, machine: str = "dc") -> tuple[list, Any]:
    """Per window from ``t_from`` [s] on, CPU [s]: (whole, estimation, prognostics, ring
    buffer, diagnosis, the saved twin alone and with the diagnosis evidence); and the
    samples. The windows before are processed
    (the trends' evidence, the fusion's history), not reported. ``machine``: a key of
    :data:`MACHINES`. ``noise`` (the default machine's only): the plant's measurement noise on
    ia and omega [% of their scale] (the density benchmark's plants have 0.5). ``keep``: given,
    receives the twin (``model``), its nameplate (``nominal``), the last window (``window``)
    and its estimate (``estimate``)."""
    cfg, source = _machine(machine, noise)
    model = create_model(cfg.machine.model, cfg.machine.options)
    nominal = {p.name: cfg.machine.parameters.get(p.name, p.nominal) for p in model.parameters}
    acq = cfg.acquisition
    adapter = TwinAdapter(model, cfg.estimation, cfg.discovery, nominal,
                          prognostics=cfg.prognostics,
                          thresholds=cfg.alarms.rul_targets(nominal), adaptive=acq.adaptive)
    ring = RingBuffer(model.required_channels(), window=acq.window,
                      sample_period=acq.sample_period, jitter_tolerance=acq.jitter_tolerance,
                      capacity=4 * acq.window)
    diagnoser = make_diagnoser(cfg, model, nominal)
    before = int(round(t_from / acq.sample_period))
    samples = list(itertools.islice(source, before + (n_windows + 1) * acq.window))
    est, prog = _Clock(), _Clock()
    adapter.estimator.estimate = est.wrap(adapter.estimator.estimate)  # type: ignore[method-assign]
    if adapter.prognostics is not None:
        adapter.prognostics.update = prog.wrap(  # type: ignore[method-assign]
            adapter.prognostics.update)
    rows = []
    ring_cpu = 0.0
    for s in samples:
        c = time.process_time()
        win = ring.append(s.t, s.values)
        ring_cpu += time.process_time() - c
        if win is None:
            continue
        est.spent = prog.spent = 0.0
        c = time.process_time()
        result = adapter.process(win)
        health = build_health(machine="bench", model_name=cfg.machine.model, run="bench",
                              model=model, window=win, adaptation=result, nominal=nominal,
                              counters={}, discovery_enabled=adapter.enabled)
        d = time.process_time()
        diagnosis = None
        if diagnoser is not None:
            e = result.estimate
            free = sum(1 for s in e.status.values() if s == "estimated") + (
                0 if e.initial is None else int(np.size(e.initial)))
            diagnosis = diagnoser.update(health, result.fit, e.simulated, free, e.initial)
        diag_cpu = time.process_time() - d
        if keep is not None:  # how each window was searched, every window processed
            reason = result.estimate.search_reason
            kind = ("the model check failed" if "model check" in reason
                    else reason.split(":")[0])
            keep.setdefault("searches", collections.Counter())[
                (result.estimate.search, kind)] += 1
            keep.setdefault("search_cpu", collections.defaultdict(list))[
                (result.estimate.search, kind)].append(est.spent)
        complete_health(health, diagnosis=diagnosis, alarms={}).to_json()
        whole = time.process_time() - c
        saved = []  # the state store's resume point, as the pipeline saves it: the twin
        for evidence in (False, True):  # alone, and with the diagnoser's evidence
            s = time.process_time()
            state = saved_twin(adapter, diagnoser, result.estimate.trusted, evidence)
            if state is not None:
                to_json(state.as_dict())
            saved.append(time.process_time() - s)
        if win.t[0] >= t_from and win.index > 0:
            rows.append((whole, est.spent, prog.spent, ring_cpu, diag_cpu, *saved))
            if keep is not None:
                keep.update(model=model, nominal=nominal, window=win, estimate=result.estimate)
        ring_cpu = 0.0
    return rows, samples[-n_windows * acq.window:]


def floor_cost(model: Any, window: Any, estimated: list[str], nominal: dict[str, float],
               reps: int = 200) -> tuple[float, float, int, dict[str, float]]:
    """The floor of a window's twin (module docstring): CPU [s] of one simulation (median of
    ``reps``), CPU [s] of one Gauss-Newton fit of ``estimated`` from ``nominal`` (median of
    ``reps // 10``), its iterations (one batched kernel call each) and the values it ends at."""
    names = list(model.parameter_names)
    theta0 = np.array([[nominal[n] for n in names]])
    idx = [names.index(n) for n in estimated]
    meas = np.column_stack([np.asarray(window[o], dtype=float) for o in model.output_names])
    scale = np.maximum(np.sqrt(np.mean(meas**2, axis=0)), 1e-12)

    def fit() -> tuple[np.ndarray, int]:
        x = np.log(theta0[0, idx])
        pts = np.repeat(theta0, len(idx) + 1, axis=0)
        calls = 0
        while calls < 20:
            pts[:, idx] = np.exp(x)
            for k, j in enumerate(idx):
                pts[k + 1, j] = np.exp(x[k] + 1e-6)
            y = model.simulate(pts, window)
            calls += 1
            r = ((y[:, 1:, :] - meas[None, 1:, :]) / scale).reshape(len(pts), -1)
            jac = (r[1:] - r[0]).T / 1e-6
            dx = np.linalg.lstsq(jac, -r[0], rcond=None)[0]
            x = x + dx
            if np.max(np.abs(dx)) < 1e-10:
                break
        return np.exp(x), calls

    sim = []
    for _ in range(reps):
        c = time.process_time()
        model.simulate(theta0, window)
        sim.append(time.process_time() - c)
    fits = []
    for _ in range(max(reps // 10, 1)):
        c = time.process_time()
        values, iterations = fit()
        fits.append(time.process_time() - c)
    return (float(np.median(sim)), float(np.median(fits)), iterations,
            dict(zip(estimated, values.tolist(), strict=True)))


def cold_start_cost(machine: str, windows: int = 3) -> tuple[float, float]:
    """CPU [s] of a fresh process that builds ``machine``'s twin and processes its first
    ``windows`` windows (:func:`window_cost`, the samples made first), on an empty numba cache
    (every kernel compiled, as on a first start after an install, a worker process of a
    gateway on a cold cache) and again with the cache it filled; their difference is the
    compilation."""
    code = ("import logging, sys; sys.path.insert(0, sys.argv[1]); "
            "logging.disable(logging.WARNING); import bench_window as bw; "
            "bw.window_cost(int(sys.argv[2]), 0.0, machine=sys.argv[3])")
    out = []
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        env.pop("TWINWATCH_NUMBA_BASE", None)  # this process's, which twinwatch would read
        for _ in range(2):
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            subprocess.run([sys.executable, "-c", code, str(Path(__file__).parent),
                            str(windows), machine], check=True, env=env)
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            out.append(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
    return out[0], out[1]


def _write_csv(path: Path, samples: list) -> None:
    chans = list(samples[0].values)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", *chans])
        for s in samples:
            w.writerow([repr(s.t), *(repr(s.values[c]) for c in chans)])


def file_cost(path: Path, chans: list[str], realtime: bool, limit: int | None,
              ring: RingBuffer | None = None, blocks: bool = False,
              clock: Callable[[], float] = time.process_time) -> tuple[float, int]:
    """CPU [s] and samples read by the file driver (``realtime`` as configured), with
    ``ring`` stored into it too, with ``blocks`` read a window's rest at a time
    (``read_block``, ``append_block``) instead of sample by sample; each read with the
    acquisition loop's timeout (:data:`~twinwatch.daemon.acquisition.READ_TIMEOUT_S`)."""
    table = {"type": "file", "path": str(path), "time_column": "t", "realtime": realtime,
             "columns": {c: {"column": c} for c in chans}}
    if limit is not None:
        table["stop"] = limit
    n = 0
    with create_driver(table, base_dir=None) as drv:
        c = clock()
        try:
            while True:
                if blocks:
                    got = drv.read_block(READ_TIMEOUT_S, 200 if ring is None else
                                         ring.window - ring.pending)
                    if got is not None:
                        n += len(got[0])
                        if ring is not None:
                            ring.append_block(*got)
                elif (s := drv.read(READ_TIMEOUT_S)) is not None:
                    n += 1
                    if ring is not None:
                        ring.append(s.t, s.values)
        except EndOfStream:
            pass
        return clock() - c, n


def threads_cost(path: Path, chans: list[str], limit: int, machines: int, pace: float
                 ) -> float:
    """CPU [s] a sample of ``machines`` real-time replays in threads of one process at once,
    each read in blocks into its ring buffer, the file driver waking every ``pace`` seconds
    (its ``PACE_SLACK``): the threads' own CPU (``time.thread_time``), summed."""
    import threading

    spent: list[tuple[float, int]] = []
    saved = file_driver.PACE_SLACK
    file_driver.PACE_SLACK = pace

    def one() -> None:
        spent.append(file_cost(path, chans, True, limit, RingBuffer(
            chans, window=200, sample_period=0.01), blocks=True, clock=time.thread_time))

    try:
        threads = [threading.Thread(target=one) for _ in range(machines)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        file_driver.PACE_SLACK = saved
    return sum(c for c, _ in spent) / sum(n for _, n in spent)


def queued_cost(samples: int, batch: float) -> float:
    """CPU [s] a sample of the thread reading a queued driver (the Modbus and OPC UA drivers'
    base: their own thread queues each sample) while a thread queues ``samples`` at 100 Hz in
    real time, read as the acquisition loop reads (``read(0.2)``) with ``BATCH_S`` = ``batch``
    (0: a wake-up a sample)."""
    import threading

    from twinwatch.drivers import base

    class Polled(base.QueuedDriver):
        driver_name = "polled"
        channels = ("x",)
        live = True

        def __init__(self) -> None:
            super().__init__()
            self._init_queue(1000)

        def _close_internal(self) -> None:
            self._stop.set()

    def poll(driver: Polled) -> None:
        t0 = time.monotonic()
        for k in range(samples):
            driver._put_dropping_oldest(base.Sample(0.01 * k, {"x": float(k)}))
            wait = t0 + 0.01 * (k + 1) - time.monotonic()
            if wait > 0:
                time.sleep(wait)

    saved, base.BATCH_S = base.BATCH_S, batch
    try:
        with Polled() as driver:
            poller = threading.Thread(target=poll, args=(driver,))
            poller.start()
            cpu = time.thread_time()
            for _ in range(samples):
                driver.read(timeout=0.2)
            cpu = time.thread_time() - cpu
            poller.join()
    finally:
        base.BATCH_S = saved
    return cpu / samples


def can_cost(seconds: float) -> tuple[float, int, float, float, int] | None:
    """CPU [s] and samples of the CAN driver replaying an ASC log of the plant, then the
    libraries' share of it: CPU [s] of python-can's ``LogReader`` reading the log alone, of
    cantools decoding its frames alone, and the frames (None without the harness beside this
    checkout)."""
    try:
        import can
        import cantools

        from harness.sources import PLANT_DBC, plant_asc_log
    except Exception:  # noqa: BLE001 - optional: harness/ beside this checkout
        return None
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "plant.asc"
        plant_asc_log(log, seconds)
        table = {"type": "can", "dbc": str(PLANT_DBC), "log_file": str(log),
                 "sync_message": "TW_Motor_Sample", "time_source": "counter",
                 "counter_signal": "TW_Motor_Sample.sample_counter", "sample_period": 0.01,
                 "signals": {ch: {"message": m, "signal": ch} for m, chs in (
                     ("TW_Motor_Electrical", ("Va", "ia")),
                     ("TW_Motor_Mechanical", ("omega", "Tload")),
                     ("TW_Motor_Sample", ("setpoint",))) for ch in chs}}
        n = 0
        with create_driver(table, base_dir=None) as drv:
            c = time.process_time()
            try:
                while True:
                    if drv.read(0) is not None:
                        n += 1
            except EndOfStream:
                pass
            cpu = time.process_time() - c
        c = time.process_time()
        frames = list(can.LogReader(str(log)))
        read = time.process_time() - c
        by_id = {m.frame_id: m for m in cantools.database.load_file(PLANT_DBC).messages}
        c = time.process_time()
        for f in frames:
            by_id[f.arbitration_id].decode(bytes(f.data), decode_choices=False,
                                           allow_truncated=False, allow_excess=True)
        decode = time.process_time() - c
        return cpu, n, read, decode, len(frames)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--windows", type=int, default=60, help="timed windows (after the first)")
    ap.add_argument("--machine", choices=sorted(MACHINES), default="dc",
                    help="dc: the built-in simulated motor; pwm: the PWM drive replaying the "
                    "MotoShield recording (../shared; 24 windows of 4 s); hydraulic: the "
                    "simulated hydraulic actuator, fluid degradation")
    ap.add_argument("--from", dest="t_from", type=float, default=None,
                    help="report the windows from this plant time [s] on, the windows before "
                    "processed, not reported (default: dc 400 s, the resistance degrading from "
                    "160 s; hydraulic 300 s, D from 160 s; pwm 8 s, the recording's third window)")
    ap.add_argument("--noise", type=float, default=0.0,
                    help="plant measurement noise on ia and omega [%% of reading] (the density "
                    "benchmark's plants: 0.5)")
    ap.add_argument("--realtime-windows", type=int, default=2,
                    help="windows the file driver replays in real time (2 s each)")
    ap.add_argument("--no-cold-start", dest="cold_start", action="store_false",
                    help="skip the cold start (two fresh processes, about 15 s)")
    args = ap.parse_args()
    logging.disable(logging.WARNING)
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"python {platform.python_version()}, load {os.getloadavg()[0]:.2f}")
    kept: dict[str, Any] = {}
    if args.t_from is None:
        args.t_from = {"dc": 400.0, "hydraulic": 300.0, "pwm": 8.0}[args.machine]
    rows, samples = window_cost(args.windows, args.t_from, args.noise, keep=kept,
                                machine=args.machine)
    a = np.array(rows)
    per = kept["window"].n
    print(f"\n{args.machine}: window of {per} samples ({per * kept['window'].sample_period:g} s), "
          f"CPU over {len(rows)} windows from {args.t_from:g} s:")
    print(f"  whole window (ring buffer's window -> health message): {_stats(list(a[:, 0]))}")
    print(f"    estimation (fusion included):                       {_stats(list(a[:, 1]))}")
    print(f"    prognostics:                                        {_stats(list(a[:, 2]))}")
    print(f"    diagnosis (the fault library's twins):              {_stats(list(a[:, 4]))}")
    print(f"    the rest (discovery check, health, JSON):            "
          f"{_stats(list(a[:, 0] - a[:, 1] - a[:, 2] - a[:, 4]))}")
    print("  after it, the saved twin (state store's resume point):")
    print(f"    the twin, each trusted window:                      {_stats(list(a[:, 5]))}")
    label = f"    with the diagnosis evidence, every {EVIDENCE_EVERY} windows:"
    print(f"{label:<56}{_stats(list(a[:, 6]))}")
    if args.cold_start:
        cold, warm = cold_start_cost(args.machine)
        print(f"  cold start, a fresh process's first 3 windows: {cold:5.1f} s of CPU on an "
              f"empty numba cache, {warm:.1f} s with it filled (the kernels compiled: "
              f"{cold - warm:.1f} s)")
    searches = kept["searches"]
    print(f"  searches over the {sum(searches.values())} windows processed (from 0 s): "
          + ", ".join(f"{s}{f' ({why})' if why else ''} {k}"
                      for (s, why), k in sorted(searches.items())))
    print("    the estimation's CPU by search (median over those windows): " + ", ".join(
        f"{s}{f' ({why})' if why else ''} {1e3 * float(np.median(cpu)):.2f} ms"
        for (s, why), cpu in sorted(kept["search_cpu"].items())))
    e = kept["estimate"]
    estimated = [n for n, st in e.status.items() if st == "estimated"]
    sim, gn, iterations, values = floor_cost(kept["model"], kept["window"], estimated,
                                                   kept["nominal"])
    print(f"\nfloor, on the last window ({', '.join(estimated)} estimated):")
    print(f"  one simulation of the window (the twin's kernel):      {sim * 1e3:7.3f} ms")
    print(f"  Gauss-Newton fit from the nameplate, same kernel:      {gn * 1e3:7.3f} ms "
          f"({iterations} iterations, a batched twin call each)")
    for n, v in values.items():
        pub = float(e.values[n])
        print(f"    {n}: floor fit {v:.6g}, estimator {pub:.6g} ({(v / pub - 1) * 100:+.4f} %)")
    print(f"\nacquisition, CPU per window of {per} samples:")
    print(f"  ring buffer append:                                   {_stats(list(a[:, 3]))}")
    if args.machine != "dc":
        print("  the drivers: measured on the default machine (--machine dc)")
        return
    chans = list(samples[0].values)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "plant.csv"
        _write_csv(path, samples)
        cpu, n = file_cost(path, chans, False, None)
        print(f"  file driver, as fast as read ({n} samples):          "
              f"{cpu / n * per * 1e3:7.2f} ms ({cpu / n * 1e6:.1f} us a sample)")
        if args.realtime_windows > 0:
            cpu, n = file_cost(path, chans, True, args.realtime_windows * per)
            print(f"  file driver, real time ({n} samples):                "
                  f"{cpu / n * per * 1e3:7.2f} ms ({cpu / n * 1e6:.1f} us a sample)")
        print("  file driver -> ring buffer, as the acquisition loop runs it (blocks: "
              "read_block, append_block):")
        for realtime in (False, True):
            if realtime and args.realtime_windows <= 0:
                continue
            limit = args.realtime_windows * per if realtime else None
            for blocks in (False, True):
                cpu, n = file_cost(path, chans, realtime, limit, blocks=blocks, ring=RingBuffer(
                    chans, window=per, sample_period=kept["window"].sample_period))
                how = "in blocks" if blocks else "sample by sample"
                label = f"    {'real time' if realtime else 'as fast as read'}, {how}:"
                print(f"{label:<56}{cpu / n * per * 1e3:7.2f} ms ({cpu / n * 1e6:.1f} us a "
                      "sample)")
        if args.realtime_windows > 0:
            print("    real time in blocks, 50 machines' threads at once, the driver waking")
            for pace in (0.2, 1.0):
                cpu = threads_cost(path, chans, args.realtime_windows * per, 50, pace)
                now = " (PACE_SLACK)" if pace == file_driver.PACE_SLACK else ""
                label = f"      every {pace:g} s{now}:"
                print(f"{label:<56}{cpu * per * 1e3:7.2f} ms ({cpu * 1e6:.1f} us a sample)")
    can = can_cost(min(60.0, len(samples) * 0.01))
    if can is None:
        print("  CAN driver (ASC log replay): skipped (needs the test extras)")
    else:
        cpu, n, read, decode, frames = can
        print(f"  CAN driver, ASC log replay ({n} samples):            "
              f"{cpu / n * per * 1e3:7.2f} ms ({cpu / n * 1e6:.1f} us a sample)")
        print(f"    of which python-can reading the log alone ({frames} frames): "
              f"{read / n * per * 1e3:5.2f} ms ({read / n * 1e6:.1f} us a sample)")
        print(f"    and cantools decoding its frames alone:             "
              f"{decode / n * per * 1e3:7.2f} ms ({decode / n * 1e6:.1f} us a sample)")
    if args.realtime_windows > 0:
        n = args.realtime_windows * per
        print(f"  a queued driver's reader (Modbus, OPC UA), a 100 Hz queue in real time ({n} "
              "samples):")
        for batch in (0.1, 0.0):
            cpu = queued_cost(n, batch)
            label = (f"    in batches (BATCH_S {batch:g} s):" if batch else
                     "    woken once a sample:")
            print(f"{label:<56}{cpu * per * 1e3:7.2f} ms ({cpu * 1e6:.1f} us a sample)")
    print("  Modbus driver: needs a server on a port (bench_density.py measures it in a host)")


if __name__ == "__main__":
    main()
