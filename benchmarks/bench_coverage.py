"""2-sigma coverage and width of the published intervals on the held-out plants (issue 55,
item 5): per plant and parameter, the share of windows whose published interval holds the
plant's true value, and how wide those intervals are.

The cases, plants and configurations are the frozen held-out set's (benchmarks/heldout/, run as
``benchmarks/bench_heldout.py`` runs them: the daemon on the recording, every window's health
message kept); the interval is the runner's (:func:`benchmarks.bench_heldout._interval`: an
``estimated`` parameter's value +- 2 ``rel_std_pct``, a ``fused`` one's ``fused.low`` ..
``fused.high``), and so is the truth (:meth:`~benchmarks.heldout.cases.Case.true_parameters` at
the window's middle). Default selection: the runner's coverage cases (library and nominal runs at
0.5 and 1 % noise).

Printed per plant and parameter: ``cover`` (covered / windows publishing an interval), the
median and 90th percentile of the interval's half-width (2 sigma, % of the value: an interval
that covers by being wide is no fix), and the windows publishing it ``estimated`` / ``fused``;
then the statuses La is published with on the plants whose electrical time constant is below the
sample period.

    python benchmarks/bench_coverage.py --plants /tmp/ho/plants --keep /tmp/cov-after
    python benchmarks/bench_coverage.py --from /tmp/cov-after        # score kept messages only
    python benchmarks/bench_coverage.py --from /tmp/ho-full/cases    # a bench_heldout --keep run

``--plants DIR``: the simulated trajectories (``<plant>-<k>.npz``, bench_heldout's phase 1, kept
by its ``--keep DIR`` as ``DIR/plants``); a plant missing there is simulated into it first.
``--no-diagnosis``: the daemon without ``[diagnosis]`` (the intervals do not depend on it; a
third of the CPU).
"""

from __future__ import annotations

import argparse
import json
import logging
import multiprocessing
import sys
import time
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.bench_heldout import (  # noqa: E402
    COVERAGE_NOISE,
    FAST_ELECTRICAL,
    _dirname,
    _interval,
    _sim_tasks,
    _simulate,
    select,
)
from benchmarks.heldout.cases import Case, batches, cases  # noqa: E402


def coverage_cases() -> list[Case]:
    """The runner's coverage cases: library and nominal runs at 0.5 and 1 % noise."""
    return [c for c in cases() if c.category in ("library", "nominal")
            and c.noise_pct in COVERAGE_NOISE]


def _run_case(args: tuple[str, str, str, bool]) -> dict[str, Any]:
    """bench_heldout's ``_run_case``, with ``[diagnosis]`` optionally off."""
    name, sim_dir, out_dir, diagnosis = args
    from twinwatch.config.loader import load_config
    from twinwatch.daemon.runner import Daemon

    logging.disable(logging.WARNING)
    case = next(c for c in cases() if c.name == name)
    scenarios, _ = batches(cases())[case.plant]
    k = scenarios.index(case.scenario())
    with np.load(Path(sim_dir) / f"{case.plant}-{k}.npz") as z:
        clean = {key: z[key] for key in z.files}
    d = Path(out_dir) / _dirname(name)
    cfg = load_config(case.write(clean, d))
    cfg.estimation.time_budget = 60.0  # as bench_heldout: the PSO's generations bound it
    if not diagnosis:
        cfg.diagnosis.enabled = False
    lines: list[str] = []
    t0 = time.process_time()
    with Daemon(cfg, publish=False, record=False, base_dir=d, work_dir=d) as daemon:
        daemon.add_callback(lambda h: lines.append(h.to_json()))
        daemon.run()
    (d / "health.jsonl").write_text("".join(line + "\n" for line in lines))
    return {"name": name, "windows": len(lines), "cpu_s": round(time.process_time() - t0, 1)}


def run(chosen: list[Case], plants_dir: Path, out: Path, workers: int, diagnosis: bool) -> None:
    """Simulate the plants missing from ``plants_dir``, then run every chosen case into
    ``out``."""
    plants_dir.mkdir(parents=True, exist_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    table = batches(cases())
    need = sorted({c.plant for c in chosen})
    missing = [p for p in need
               if not all((plants_dir / f"{p}-{k}.npz").exists() for k in range(len(table[p][0])))]
    ctx = multiprocessing.get_context("fork")
    with ctx.Pool(workers) as pool:
        for res in pool.imap_unordered(
                _simulate, [(n, ix, str(plants_dir)) for n, ix in _sim_tasks(missing)]):
            print(f"simulated {res['plant']} {res['indices']}: {res['cpu_s']:.0f} s CPU",
                  file=sys.stderr, flush=True)
        jobs = [(c.name, str(plants_dir), str(out), diagnosis)
                for c in sorted(chosen, key=lambda c: -c.duration)]
        for rec in pool.imap_unordered(_run_case, jobs):
            print(f"ran {rec['name']}: {rec['windows']} windows, {rec['cpu_s']} s CPU",
                  file=sys.stderr, flush=True)


def score(chosen: list[Case], out: Path) -> dict[str, Any]:
    """Coverage, widths and statuses per plant and parameter from the kept messages."""
    hit: dict[tuple[str, str], list[int]] = defaultdict(lambda: [0, 0])
    width: dict[tuple[str, str], list[float]] = defaultdict(list)
    status: dict[tuple[str, str], Counter[str]] = defaultdict(Counter)
    la: dict[str, Counter[str]] = defaultdict(Counter)
    la_reason: dict[str, Counter[str]] = defaultdict(Counter)
    ran = 0
    for c in chosen:
        f = out / _dirname(c.name) / "health.jsonl"
        if not f.exists():
            continue
        ran += 1
        for line in f.read_text().splitlines():
            if not line.strip():
                continue
            m = json.loads(line)
            tm = 0.5 * (float(m["t_start"]) + float(m["t_end"]))
            truth = c.true_parameters(tm)
            for p, q in (m.get("parameters") or {}).items():
                if p == "La" and c.plant in FAST_ELECTRICAL:
                    la[c.plant][str(q.get("status"))] += 1
                    if q.get("status") not in ("estimated", "fused"):
                        la_reason[c.plant][str(q.get("reason"))[:70]] += 1
                if p not in truth:
                    continue
                iv = _interval(q)
                if iv is None:
                    continue
                key = (c.plant, p)
                status[key][str(q["status"])] += 1
                hit[key][1] += 1
                hit[key][0] += int(iv[0] <= truth[p] <= iv[1])
                mid = 0.5 * (iv[0] + iv[1])
                width[key].append(100.0 * 0.5 * (iv[1] - iv[0]) / abs(mid) if mid else np.inf)
    rows = {}
    for key in sorted(hit, key=lambda k: (k[0], k[1])):
        w = np.asarray(width[key])
        rows[f"{key[0]}/{key[1]}"] = {
            "covered": hit[key][0], "windows": hit[key][1],
            "share": round(hit[key][0] / hit[key][1], 3),
            "half_width_median_pct": round(float(np.median(w)), 4),
            "half_width_p90_pct": round(float(np.percentile(w, 90)), 4),
            "estimated": status[key]["estimated"], "fused": status[key]["fused"]}
    tot = [sum(v[0] for v in hit.values()), sum(v[1] for v in hit.values())]
    return {"cases": ran, "rows": rows, "total": tot,
            "La": {p: dict(v) for p, v in la.items()},
            "La_reasons": {p: dict(v.most_common(3)) for p, v in la_reason.items()}}


def report(s: dict[str, Any]) -> None:
    print(f"2-sigma coverage on {s['cases']} held-out cases (published intervals: estimated "
          "value +- 2 rel_std, fused low..high)")
    print(f"{'plant/parameter':18} {'cover':>14} {'half-width % (median, p90)':>28} "
          f"{'estimated':>9} {'fused':>6}")
    for k, r in s["rows"].items():
        print(f"{k:18} {r['covered']:5d}/{r['windows']:<5d} {100 * r['share']:3.0f} % "
              f"{r['half_width_median_pct']:12.3g} {r['half_width_p90_pct']:12.3g}   "
              f"{r['estimated']:9d} {r['fused']:6d}")
    hit, tot = s["total"]
    if tot:
        print(f"{'total':18} {hit:5d}/{tot:<5d} {100 * hit / tot:3.0f} %")
    shares = [r["share"] for r in s["rows"].values() if r["windows"] >= 5]
    if shares:
        print(f"worst plant/parameter (>= 5 windows): {100 * min(shares):.0f} %")
    for p, st in s["La"].items():
        print(f"La on {p} (tau_e below the sample period): {st}; reasons "
              f"{s['La_reasons'].get(p, {})}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default=None, help="comma-separated case-name prefixes "
                    "(default: the coverage cases)")
    ap.add_argument("--plant", default=None, help="comma-separated plants (default: all)")
    ap.add_argument("--plants", type=Path, default=Path("/tmp/heldout-plants"))
    ap.add_argument("--keep", type=Path, default=Path("/tmp/bench-coverage"))
    ap.add_argument("--from", dest="source", type=Path, default=None,
                    help="score the health.jsonl kept under this directory, run nothing")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--no-diagnosis", action="store_true")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    chosen = select(cases(), args.only) if args.only else coverage_cases()
    if args.plant:
        chosen = [c for c in chosen if c.plant in args.plant.split(",")]
    out = args.source
    if out is None:
        out = args.keep
        t0 = time.perf_counter()
        run(chosen, args.plants, out, args.workers, not args.no_diagnosis)
        print(f"{len(chosen)} cases in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    s = score(chosen, out)
    report(s)
    if args.json:
        args.json.write_text(json.dumps(s, indent=1))


if __name__ == "__main__":
    main()
