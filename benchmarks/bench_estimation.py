"""Per-window estimation: twinwatch's default (local first) against the swarm every window and
the paper's settings, on the same windows, in one run.

    python benchmarks/bench_estimation.py [--windows 60] [--paper-windows 2] [--every 10]

Windows are cut from the simulated plant in the resistance-degradation scenario (noise-free,
from 400 s on, every ``--every``-th window: 1 for consecutive windows as a daemon sees them).
For each method, prints the estimation time per window (median, p95, max; the process's CPU
time median beside it, steadier on a shared machine), the windows that ran the swarm, and the
Ra and D errors against the plant's values at the window's middle; then the ratio of each to
the paper's settings.

* local first (default): twinwatch's default configuration (``[estimation] strategy =
  "local_first"``): the trusted values polished locally, only the parameters the last window's
  gate admitted (``estimator.POLISH_ADMITTED``, confirmed on one sensitivity call), the swarm
  (20 iterations) only at the first window, after a rejected local fit or a sudden change and
  every ``swarm_every`` windows; identifiability gate, model check, fusion.
* swarm every window: the same with ``strategy = "swarm"`` (the default before issue 19).
* local first, full polish: the default before issue 22 (``estimator.POLISH_ADMITTED`` off:
  a local window polishes every estimated parameter, then the gate holds what it cannot
  determine).
* paper: pymoo PSO, swarm 15, 1000 iterations, w 0.9, c1 = c2 = 2.0 (Table 2), no polish,
  every listed parameter estimated, one twin call per particle (as the paper's loop does),
  ``strategy = "swarm"``.

All use the same twin (exact composite sub-stepping), so the difference is the method. The
first window of each twinwatch estimator (the numba kernels' compilation, the start's swarm)
is not timed.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from twinwatch.config.loader import default_config  # noqa: E402
from twinwatch.plant.dcmotor import DCMotorPlant  # noqa: E402
from twinwatch.twin.estimation import estimator as estimator_module  # noqa: E402
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


def windows(n: int, every: int = 10) -> tuple[DCMotorPlant, list[WindowData]]:
    """The plant and ``n`` windows of 200 samples from 400 s on, every ``every``-th."""
    cfg = default_config()
    plant = DCMotorPlant(cfg.driver.plant)  # type: ignore[union-attr]
    out: list[WindowData] = []
    k = 0
    while len(out) < n:
        ss = [plant.next_sample() for _ in range(200)]
        if ss[0].t >= 400 and k % every == 0:
            out.append(WindowData(t=np.array([s.t for s in ss]),
                                  channels={c: np.array([s.values[c] for s in ss])
                                            for c in ss[0].values}, index=k))
        k += 1
    return plant, out


def run(est: Estimator, plant: DCMotorPlant, wins: list[WindowData]) -> np.ndarray:
    """Per window: elapsed [s], |Ra error| [%], |D error| [%], PSO iterations, swarm ran,
    CPU time of the process [s]."""
    rows = []
    for w in wins:
        cpu = time.process_time()
        r = est.estimate(w)
        cpu = time.process_time() - cpu
        truth = plant.truth(float(w.t.mean()))
        rows.append((r.elapsed_s, abs(r.values["Ra"] / truth.Ra - 1) * 100,
                     abs(r.values["D"] / truth.D - 1) * 100, r.generations,
                     float(r.search == "swarm"), cpu))
    return np.array(rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--windows", type=int, default=60,
                    help="timed windows for the default and for the swarm every window")
    ap.add_argument("--paper-windows", type=int, default=2, help="windows for the paper's "
                    "settings (seconds each)")
    ap.add_argument("--every", type=int, default=1,
                    help="take every n-th window of the plant (1: consecutive)")
    args = ap.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"python {platform.python_version()}, load {os.getloadavg()[0]:.2f}")
    n = max(args.windows, args.paper_windows) + 1
    plant, wins = windows(n, args.every)
    window_s = 200 * 0.01

    results: list[tuple[str, np.ndarray]] = []
    default = estimator_module.POLISH_ADMITTED
    for label, strategy, admitted in (("local first (default)", "local_first", True),
                                      ("swarm every window", "swarm", True),
                                      ("local first, full polish", "local_first", False)):
        cfg = default_config().estimation.model_copy(update={"strategy": strategy})
        estimator_module.POLISH_ADMITTED = admitted
        try:
            est = Estimator(DCMotorTwin(), cfg)
            est.estimate(wins[0])  # compile numba kernels, warm caches, the start's swarm
            results.append((label, run(est, plant, wins[1: 1 + args.windows])))
        finally:
            estimator_module.POLISH_ADMITTED = default

    paper_cfg = EstimationConfig(
        estimate=["Ra", "D", "Ke", "La", "J"], polish=False, time_budget=3600.0,
        max_rel_std=1e9, strategy="swarm",
        pso=PSOSettings(pop_size=15, max_generations=1000, w=0.9, c1=2.0, c2=2.0,
                        adaptive=False))
    paper = Estimator(OneCallPerParticle(), paper_cfg)
    p = run(paper, plant, wins[1: 1 + args.paper_windows])
    results.append(("paper (PSO 15x1000, 1 call/part.)", p))

    p_med = float(np.median(p[:, 0]))
    print(f"\n{'method':<35}{'windows':>8}{'swarm':>7}{'median':>10}{'p95':>10}{'max':>10}"
          f"{'% of window':>13}{'x paper':>9}{'|Ra err| med/max [%]':>24}"
          f"{'|D err| med/max [%]':>23}{'CPU median':>12}")
    for name, a in results:
        med = float(np.median(a[:, 0]))
        print(f"{name:<35}{len(a):>8}{int(a[:, 4].sum()):>7}{med * 1e3:>8.1f}ms"
              f"{np.percentile(a[:, 0], 95) * 1e3:>8.1f}ms{a[:, 0].max() * 1e3:>8.1f}ms"
              f"{med / window_s * 100:>12.2f}%{med / p_med:>9.4f}"
              f"{np.median(a[:, 1]):>14.4f} / {a[:, 1].max():<8.4f}"
              f"{np.median(a[:, 2]):>13.4f} / {a[:, 2].max():<8.4f}"
              f"{np.median(a[:, 5]) * 1e3:>10.1f}ms")
    (_, d), (_, s), (_, a) = results[0], results[1], results[2]
    print(f"\nlocal first: median {np.median(d[:, 0]) * 1e3:.1f} ms, p95 "
          f"{np.percentile(d[:, 0], 95) * 1e3:.1f} ms, max {d[:, 0].max() * 1e3:.1f} ms per "
          f"{window_s:g} s window ({int(d[:, 4].sum())} of {len(d)} windows ran the swarm); "
          f"x{p_med / np.median(d[:, 0]):.0f} faster than the paper's settings (median "
          f"{p_med:.2f} s), x{np.median(s[:, 0]) / np.median(d[:, 0]):.1f} faster than the "
          f"swarm every window (median {np.median(s[:, 0]) * 1e3:.1f} ms, x"
          f"{p_med / np.median(s[:, 0]):.0f}); CPU time median: local first "
          f"{np.median(d[:, 5]) * 1e3:.1f} ms, the swarm every window "
          f"{np.median(s[:, 5]) * 1e3:.1f} ms (wall time counts the other jobs sharing the cores, "
          f"CPU time less so)")
    print(f"full polish (estimator.POLISH_ADMITTED off, the default before issue 22): CPU "
          f"time median {np.median(a[:, 5]) * 1e3:.1f} ms, x"
          f"{np.median(a[:, 5]) / np.median(d[:, 5]):.1f} the default's; the paper's settings "
          f"{np.median(p[:, 5]) * 1e3:.0f} ms of CPU a window")


if __name__ == "__main__":
    main()
