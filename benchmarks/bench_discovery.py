"""A fresh unknown-component discovery per window: time and accuracy (issue: "a fresh
discovery finishes within one window's length on this machine").

    python benchmarks/bench_discovery.py [--windows 20]

Windows are cut from the simulated plant in the unbalanced-shaft scenario (paper Eq. 13,
5*sin(10 t) rad/s^2 on d(omega)/dt), one every 10 windows from 10 s on, so the forcing meets
every phase and set-point. On each, a discovery starts from nothing (no kept term, the nominal
parameters) with the candidates of config/dc-motor-unbalanced-sim.toml (all six Table 1
meta-models of time on d(omega)/dt), and prints what it kept, its time, the amplitude and
frequency errors and the worst speed error of DT' and DT''.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from twinwatch.config.loader import load_config  # noqa: E402
from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig  # noqa: E402
from twinwatch.twin.discovery import Discovery, compose  # noqa: E402
from twinwatch.twin.estimation import Estimator  # noqa: E402
from twinwatch.twin.model import WindowData  # noqa: E402
from twinwatch.twin.registry import create_model  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--windows", type=int, default=20)
    args = ap.parse_args()
    cfg = load_config(ROOT / "config" / "dc-motor-unbalanced-sim.toml")
    model = create_model(cfg.machine.model, cfg.machine.options)
    plant = DCMotorPlant(DCMotorPlantConfig(scenario="unbalanced_shaft",
                                            duration=20.0 * args.windows + 30))
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"Python {platform.python_version()}")
    print(f"discovery: {len(cfg.discovery.candidates[0].kinds)} candidates, PSO "
          f"{cfg.discovery.pso.pop_size} x {cfg.discovery.pso.max_generations}, time budget "
          f"{cfg.discovery.time_budget} s; window {cfg.acquisition.window} samples = "
          f"{cfg.acquisition.window * cfg.acquisition.sample_period:g} s")
    # Warm up numba and pymoo once (compilation is not discovery time).
    est = Estimator(model, cfg.estimation)
    disc = Discovery(model, cfg.discovery, est)
    rows = []
    k = 0
    theta = model.nominal_vector()
    print(f"{'t [s]':>8} {'time [ms]':>9} {'kept':<48} {'|a| err %':>9} {'|b| err %':>9} "
          f"{'DT worst':>9} {'DT2 worst':>9}")
    warm = True
    while len(rows) < args.windows:
        ss = [plant.next_sample() for _ in range(200)]
        k += 1
        if ss[0].t < 10 or (k % 10 and not warm):
            continue
        w = WindowData(t=np.array([s.t for s in ss]),
                       channels={c: np.array([s.values[c] for s in ss]) for c in ss[0].values},
                       index=k)
        new, rep = disc.discover(w, theta, [])
        if warm:
            warm = False
            continue
        dt = np.max(np.abs(model.simulate(theta[None], w)[0][:, 1] - w["omega"]))
        y2 = model.simulate(theta[None], w, compose(new, w))[0]
        dt2 = np.max(np.abs(y2[:, 1] - w["omega"]))
        ok = [t.meta.kind for t in new] == ["periodic"]
        a_err = abs(abs(new[0].params[0]) - 5) / 5 * 100 if ok else np.nan
        b_err = abs(abs(new[0].params[1]) - 10) / 10 * 100 if ok else np.nan
        rows.append((rep.elapsed_s, ok, a_err, b_err, dt, dt2))
        kept = "; ".join(t.expression() for t in new) or "(nothing)"
        print(f"{w.t[0]:8.1f} {rep.elapsed_s * 1e3:9.0f} {kept:<48.48} {a_err:9.3f} "
              f"{b_err:9.4f} {dt:9.3f} {dt2:9.4f}")
    arr = np.array(rows, dtype=float)
    print(f"\nfound exactly the periodic term in {int(arr[:, 1].sum())}/{len(rows)} windows; "
          f"amplitude error max {np.nanmax(arr[:, 2]):.3f} %, frequency error max "
          f"{np.nanmax(arr[:, 3]):.4f} %")
    print(f"discovery time: median {np.median(arr[:, 0]) * 1e3:.0f} ms, max "
          f"{arr[:, 0].max() * 1e3:.0f} ms (window length 2 s)")
    print(f"worst speed error: DT' median {np.median(arr[:, 4]):.3f} rad/s, DT'' max "
          f"{arr[:, 5].max():.4f} rad/s")


if __name__ == "__main__":
    main()
