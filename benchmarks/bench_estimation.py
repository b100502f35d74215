"""Per-window estimation: the paper's settings against twinwatch's default, on the same windows.

    python benchmarks/bench_estimation.py [--windows 20] [--paper-windows 2]

Windows are cut from the simulated plant in the resistance-degradation scenario (noise-free,
every 10th window from 400 s on). For each, prints the estimation time and the Ra and D errors
against the plant's values at the window's middle.

* paper: pymoo PSO, swarm 15, 1000 iterations, w 0.9, c1 = c2 = 2.0 (Table 2), no polish,
  every listed parameter estimated, one twin call per particle (as the paper's loop does).
* default: twinwatch's default configuration (PSO warm start, 20 iterations, least-squares
  polish, identifiability gate), the whole swarm in one twin call.

Both use the same twin (exact composite sub-stepping), so the difference is the method.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from twinwatch.config.loader import default_config  # noqa: E402
from twinwatch.plant.dcmotor import DCMotorPlant  # noqa: E402
from twinwatch.twin.estimation.estimator import EstimationConfig, Estimator, PSOSettings  # noqa: E402
from twinwatch.twin.model import WindowData  # noqa: E402
from twinwatch.twin.models.dcmotor import DCMotorTwin  # noqa: E402


class OneCallPerParticle(DCMotorTwin):
    """The paper's evaluation: the twin simulated once per particle."""

    def simulate(self, theta, window, terms=None, initial=None):  # type: ignore[no-untyped-def]
        init = None if initial is None else np.broadcast_to(
            np.atleast_2d(initial), (np.atleast_2d(theta).shape[0], 2))
        return np.concatenate([super(OneCallPerParticle, self).simulate(
            th[None, :], window, terms, None if init is None else init[k])
            for k, th in enumerate(np.atleast_2d(theta))])


def windows(n: int) -> tuple[DCMotorPlant, list[WindowData]]:
    cfg = default_config()
    plant = DCMotorPlant(cfg.driver.plant)  # type: ignore[union-attr]
    out: list[WindowData] = []
    k = 0
    while len(out) < n:
        ss = [plant.next_sample() for _ in range(200)]
        if ss[0].t >= 400 and k % 10 == 0:
            out.append(WindowData(t=np.array([s.t for s in ss]),
                                  channels={c: np.array([s.values[c] for s in ss])
                                            for c in ss[0].values}, index=k))
        k += 1
    return plant, out


def run(est: Estimator, plant: DCMotorPlant, wins: list[WindowData]) -> np.ndarray:
    rows = []
    for w in wins:
        r = est.estimate(w)
        truth = plant.truth(float(w.t.mean()))
        rows.append((r.elapsed_s, abs(r.values["Ra"] / truth.Ra - 1) * 100,
                     abs(r.values["D"] / truth.D - 1) * 100, r.generations))
    return np.array(rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--windows", type=int, default=20, help="windows for the default")
    ap.add_argument("--paper-windows", type=int, default=2, help="windows for the paper's "
                    "settings (about 40 s each)")
    args = ap.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"python {platform.python_version()}")
    plant, wins = windows(max(args.windows, args.paper_windows))
    window_s = 200 * 0.01

    default = Estimator(DCMotorTwin(), default_config().estimation)
    default.estimate(wins[0])  # compile numba kernels, warm caches
    d = run(default, plant, wins[: args.windows])

    paper_cfg = EstimationConfig(
        estimate=["Ra", "D", "Ke", "La", "J"], polish=False, time_budget=3600.0,
        max_rel_std=1e9, pso=PSOSettings(pop_size=15, max_generations=1000, w=0.9, c1=2.0,
                                         c2=2.0, adaptive=False))
    paper = Estimator(OneCallPerParticle(), paper_cfg)
    p = run(paper, plant, wins[: args.paper_windows])

    print(f"\n{'method':<34}{'windows':>8}{'time/window [s]':>18}{'% of window':>13}"
          f"{'|Ra err| med/max [%]':>24}{'|D err| med/max [%]':>23}")
    for name, a in (("paper (PSO 15x1000, 1 call/part.)", p), ("twinwatch default", d)):
        print(f"{name:<34}{len(a):>8}{np.median(a[:, 0]):>11.3f} (max {a[:, 0].max():.3f})"
              f"{np.median(a[:, 0]) / window_s * 100:>9.1f}%"
              f"{np.median(a[:, 1]):>14.4f} / {a[:, 1].max():<8.4f}"
              f"{np.median(a[:, 2]):>13.4f} / {a[:, 2].max():<8.4f}")
    print(f"\ndefault: median {np.median(d[:, 0]) * 1e3:.0f} ms, p95 "
          f"{np.percentile(d[:, 0], 95) * 1e3:.0f} ms, max {d[:, 0].max() * 1e3:.0f} ms per "
          f"{window_s:g} s window = {np.max(d[:, 0]) / window_s * 100:.1f} % of the window at "
          f"worst; speed-up over the paper's settings "
          f"x{np.median(p[:, 0]) / np.median(d[:, 0]):.0f}")


if __name__ == "__main__":
    main()
