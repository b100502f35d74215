"""Discovery's trigger: detection on a running machine, false alarms on healthy ones (issue 23
item 2).

    python benchmarks/bench_trigger.py [--seconds 1200] [--seeds 3]

Detection: the DC motor of config/dc-motor-unbalanced-sim.toml with an unbalance of
3 sin(7 t) rad/s^2 unlike the paper's, 1 % measurement noise on ia and omega, its windows
starting at 10 s (a daemon started, or restarted, on a machine already running: no start-up
transient to trigger on). Per seed: when the term is kept (plant time since the first window),
its amplitude and frequency errors then and 60 s after the first window, and how many of those
windows the former criterion (normalised RMSE over 3 times the noise level, per window) and the
whiteness test flag.

False alarms: the nominal plant for ``--seconds`` of plant time at 0, 1 and 2 % noise, windows
from 10 s: searches run, terms kept (must be 0), windows whose residual was structured (their
estimates published ``suspect``), and CPU per window [ms].
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from twinwatch.config.loader import load_config  # noqa: E402
from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig  # noqa: E402
from twinwatch.twin.adaptation import TwinAdapter  # noqa: E402
from twinwatch.twin.estimation.statistics import noise_level  # noqa: E402
from twinwatch.twin.model import WindowData  # noqa: E402
from twinwatch.twin.models import create_model  # noqa: E402

CONFIG = ROOT / "config" / "dc-motor-unbalanced-sim.toml"
AMPLITUDE, FREQUENCY = 3.0, 7.0
START = 10.0  # s: the first window starts here


def windows(plant_cfg: DCMotorPlantConfig, n: int, start: float = START):  # type: ignore[no-untyped-def]
    """Yield ``n`` windows of 200 samples from the plant, the first at ``start``."""
    plant = DCMotorPlant(plant_cfg)
    skip = int(round(start / plant_cfg.sample_period))
    for _ in range(skip):
        plant.next_sample()
    for k in range(n):
        ss = [plant.next_sample() for _ in range(200)]
        yield WindowData(t=np.array([s.t for s in ss]),
                         channels={c: np.array([s.values[c] for s in ss])
                                   for c in ss[0].values}, index=k)


def former_criterion(result, fit) -> bool:  # type: ignore[no-untyped-def]
    """The trigger before issue 23: pooled normalised RMSE > 3 x the pooled noise level."""
    res = fit.error_matrix(result.estimate.simulated)
    nrmse = float(np.sqrt(np.mean(res * res)))
    noise = float(np.sqrt(np.mean(noise_level(res) ** 2)))
    return nrmse > 0.002 and nrmse > 3.0 * noise


def adapter(cfg):  # type: ignore[no-untyped-def]
    return TwinAdapter(create_model(cfg.machine.model, cfg.machine.options), cfg.estimation,
                       cfg.discovery)


def detection(cfg, seed: int, n: int = 30) -> dict[str, float]:  # type: ignore[no-untyped-def]
    ad = adapter(cfg)
    plant_cfg = DCMotorPlantConfig(scenario="unbalanced_shaft", duration=START + 2.0 * n + 5,
                                   unbalance_amplitude=AMPLITUDE,
                                   unbalance_frequency=FREQUENCY,
                                   noise={"ia": 1.0, "omega": 1.0}, seed=seed)
    out: dict[str, float] = {"kept_s": math.nan, "old": 0, "new": 0}
    for w in windows(plant_cfg, n):
        r = ad.process(w)
        out["old"] += former_criterion(r, ad.estimator.window_fit(w))
        out["new"] += r.too_large
        if r.terms and math.isnan(out["kept_s"]):
            out["kept_s"] = float(w.t[-1]) - START
            a, b = r.terms[0].params[:2]
            out["a_kept"], out["b_kept"] = abs(a), b
        if r.terms:
            a, b = r.terms[0].params[:2]
            out["a_end"], out["b_end"] = abs(a), b
    out["windows"] = n
    return out


def false_alarms(cfg, noise: float, seconds: float, seed: int) -> dict[str, float]:  # type: ignore[no-untyped-def]
    ad = adapter(cfg)
    n = int(seconds / 2.0)
    plant_cfg = DCMotorPlantConfig(scenario="nominal", duration=START + seconds + 5,
                                   noise={"ia": noise, "omega": noise}, seed=seed)
    ran = kept = structured = 0
    t0 = time.process_time()
    for w in windows(plant_cfg, n):
        r = ad.process(w)
        ran += bool(r.discovery and r.discovery.ran)
        kept += len(r.discovery.kept) if r.discovery else 0
        structured += r.too_large
    cpu = (time.process_time() - t0) / n * 1e3
    return {"windows": n, "ran": ran, "kept": kept, "structured": structured, "cpu_ms": cpu}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=1200.0)
    ap.add_argument("--seeds", type=int, default=3)
    args = ap.parse_args()
    cfg = load_config(CONFIG)
    d = cfg.discovery
    print(f"# {platform.python_version()} on {platform.machine()}, {os.cpu_count()} cores; "
          f"trigger_windows {d.trigger_windows}, false_alarm {d.false_alarm:g}, window_alpha "
          f"{d.window_alpha:g}, whiteness_lags {d.whiteness_lags}, min_nrmse {d.min_nrmse:g}")
    print("\n## detection: 3 sin(7 t) rad/s^2, 1 % noise, windows from 10 s (30 windows, 60 s)")
    print("seed  kept after [s]  |a| err kept/60 s [%]  b err kept/60 s [%]  "
          "flagged: former / whiteness")
    for seed in range(args.seeds):
        o = detection(cfg, seed)
        ea = [100 * abs(o.get(k, math.nan) - AMPLITUDE) / AMPLITUDE for k in ("a_kept", "a_end")]
        eb = [100 * abs(o.get(k, math.nan) - FREQUENCY) / FREQUENCY for k in ("b_kept", "b_end")]
        print(f"{seed:4d}  {o['kept_s']:13.0f}  {ea[0]:9.2f} / {ea[1]:5.2f}       "
              f"{eb[0]:8.3f} / {eb[1]:6.3f}      {o['old']:3.0f} / {o['new']:3.0f} of "
              f"{o['windows']:.0f}")
    print(f"\n## false alarms: nominal plant, {args.seconds:.0f} s, windows from 10 s")
    print("noise [%]  windows  searches  terms kept  structured windows  CPU/window [ms]")
    for noise in (0.0, 1.0, 2.0):
        o = false_alarms(cfg, noise, args.seconds, seed=7)
        print(f"{noise:9.0f}  {o['windows']:7.0f}  {o['ran']:8.0f}  {o['kept']:10.0f}  "
              f"{o['structured']:18.0f}  {o['cpu_ms']:15.1f}")


if __name__ == "__main__":
    main()
