"""The held-out validation set (issue 55, item 8): today's diagnosis on plants the twin was
never built from.

The set (benchmarks/heldout/: the plants, the frozen case table, README.md) is run as a plant
engineer would deploy twinwatch: per case, the plant's trajectory (simulated by
:mod:`benchmarks.heldout.plants`, which shares no code with twinwatch), its recording (noise,
reading faults, the logger's resolution) as a CSV and the engineer's configuration
(``twinwatch.toml``: the file driver on that CSV) in a directory, then the daemon on it as
``bench_diagnosis.py``'s record phase runs it (``Daemon(cfg, publish=False, record=False)``,
``[estimation] time_budget`` raised to 60 s so that the PSO's generations bound it: the same on
a busy box, and ``[acquisition] shutdown_timeout`` to an hour so that the windows still queued
when the recording ends are all estimated: with the default 10 s a busy box drops the last
ones), every window's health message kept (``health.jsonl``); a case missing a window says so.

Two phases share one pool of ``--workers`` processes: each plant's batch of scenarios is
simulated once (the whole table's batch of that plant, whatever ``--only`` selects, so a case's
data never depend on the selection), then its cases run as soon as it is done.

**Scores** (per case, then per category and plant, and in total):

* confident-wrong: a window ending at or after the onset (any window of a nominal run) where a
  library fault outside ``accept`` and ``tolerate`` has probability >= 0.8;
* right: the last window's answer (``diagnosis.status``, ``fault`` replaced by
  ``diagnosis.top``) is in ``accept``; or the diagnosis publishes an honest split
  (``diagnosis.split``: the fault ids the data cannot tell apart) holding its top and an
  accepted id;
* nominal false alarm: a library fault or ``unknown`` above 0.2 in any window;
* Brier score of the last window over the library's fault ids (read from its TOML), ``unknown``
  and ``no_fault`` (a truth the library lacks is ``unknown``), as bench_diagnosis.py does;
* 2-sigma coverage on the library and nominal cases at 0.5 and 1 % noise: for each parameter
  published ``estimated`` (value +- 2 rel_std) or ``fused`` (fused.low..fused.high), the share
  of windows whose interval holds the plant's true value at the window's middle;
* La on the plants whose tau_e is below the sample period (``ind``, ``srvS``): the windows that
  publish it estimated or fused, and every status seen;
* diagnosis CPU per window, if the message carries it (``diagnosis.cpu_s``); else left out.

    python benchmarks/bench_heldout.py [--only PREFIX,...] [--workers 2] [--json FILE]
                                       [--keep DIR] [--list]
"""

from __future__ import annotations

import argparse
import json
import logging
import multiprocessing
import os
import re
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections import Counter, defaultdict
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.heldout.cases import TABLE, Case, batches, cases  # noqa: E402
from benchmarks.heldout.plants import (  # noqa: E402
    PLANTS,
    SAMPLE_PERIOD,
    HydraulicPlant,
    simulate_dc,
    simulate_hydraulic,
)

#: Probability at which a wrong answer is confident (the default ``[diagnosis] alarm``).
NAMED = 0.8
#: A nominal run's false alarm: any fault (or unknown) above this in any window.
FALSE_ALARM = 0.2
#: Plants whose electrical time constant is below the sample period.
FAST_ELECTRICAL = ("ind", "srvS")
#: Noise levels [%] at which coverage is measured.
COVERAGE_NOISE = (0.5, 1.0)
#: The twin model's fault library file.
LIBRARY = ROOT / "twinwatch" / "twin" / "diagnosis" / "library"


def library_ids(model: str) -> list[str]:
    """The fault ids of a model's shipped library (its ``id = "..."`` lines only)."""
    text = (LIBRARY / f"{model}.toml").read_text()
    return re.findall(r'^id\s*=\s*"([^"]+)"', text, flags=re.M)


def select(all_cases: Sequence[Case], only: str | None) -> list[Case]:
    """The cases whose name starts with one of the comma-separated prefixes of ``only``."""
    if not only:
        return list(all_cases)
    prefixes = [p for p in only.split(",") if p]
    return [c for c in all_cases if any(c.name.startswith(p) for p in prefixes)]


def _dirname(name: str) -> str:
    return name.replace("/", "__").replace("%", "pct")


# -- phase 1: the plants ------------------------------------------------------------------------

def _simulate(args: tuple[str, list[int], str]) -> dict[str, Any]:
    """Simulate a plant's batch (the scenarios ``indices`` of its table batch: a DC plant's
    whole batch at once, a hydraulic scenario alone) and store each trajectory as
    ``<dir>/<plant>-<index>.npz``."""
    plant_name, indices, out_dir = args
    t0, c0 = time.perf_counter(), time.process_time()
    scenarios, durations = batches(cases())[plant_name]
    plant = PLANTS[plant_name]
    if isinstance(plant, HydraulicPlant):
        logs = [simulate_hydraulic(plant, scenarios[k], durations[k]) for k in indices]
    else:
        logs = simulate_dc(plant, [scenarios[k] for k in indices],
                           [durations[k] for k in indices])
    for k, lg in zip(indices, logs, strict=True):
        np.savez(Path(out_dir) / f"{plant_name}-{k}.npz", **lg)
    return {"plant": plant_name, "indices": indices, "wall_s": time.perf_counter() - t0,
            "cpu_s": time.process_time() - c0}


def _sim_tasks(plants: Iterable[str]) -> list[tuple[str, list[int]]]:
    """One task per DC plant (its batch), one per hydraulic scenario; the heaviest first
    (drive updates per second times plant seconds)."""
    table = batches(cases())
    tasks: list[tuple[float, str, list[int]]] = []
    for name in plants:
        scs, durs = table[name]
        plant = PLANTS[name]
        if isinstance(plant, HydraulicPlant):
            tasks += [(durs[k] / 50.0, name, [k]) for k in range(len(scs))]
        else:
            tasks.append((max(durs) / plant.drive.period * 1e-3 * 1.5, name,
                          list(range(len(scs)))))
    tasks.sort(key=lambda x: -x[0])
    return [(n, ix) for _, n, ix in tasks]


# -- phase 2: the cases -------------------------------------------------------------------------

def _run_case(args: tuple[str, str, str]) -> dict[str, Any]:
    """Write one case's recording and configuration, run the daemon on it, keep every health
    message (``health.jsonl``) and return the case's record."""
    name, sim_dir, out_dir = args
    from twinwatch.config.loader import load_config
    from twinwatch.daemon.runner import Daemon

    logging.disable(logging.WARNING)
    case = next(c for c in cases() if c.name == name)
    scenarios, _ = batches(cases())[case.plant]
    k = scenarios.index(case.scenario())
    with np.load(Path(sim_dir) / f"{case.plant}-{k}.npz") as z:
        clean = {key: z[key] for key in z.files}
    d = Path(out_dir) / _dirname(name)
    cfg_path = case.write(clean, d)
    cfg = load_config(cfg_path)
    cfg.estimation.time_budget = 60.0  # the PSO's generations bound it: the same on a busy box
    cfg.acquisition.shutdown_timeout = 3600.0  # every queued window estimated at the end
    lines: list[str] = []
    wall0, cpu0 = time.perf_counter(), time.process_time()
    with Daemon(cfg, publish=False, record=False, base_dir=d, work_dir=d) as daemon:
        daemon.add_callback(lambda h: lines.append(h.to_json()))
        daemon.run()
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    (d / "health.jsonl").write_text("".join(line + "\n" for line in lines))
    expected = int(round(case.duration / (SAMPLE_PERIOD * cfg.acquisition.window)))
    if len(lines) != expected:
        print(f"{name}: {len(lines)} windows estimated of {expected}", file=sys.stderr)
    return {"name": name, "dir": str(d), "windows": len(lines), "windows_expected": expected,
            "wall_s": round(wall, 2), "cpu_s": round(cpu, 2)}


# -- scoring -----------------------------------------------------------------------------------

def _answer(diag: dict[str, Any]) -> tuple[str, float]:
    """A window's answer and its probability."""
    if diag.get("status") == "fault" and diag.get("top"):
        return str(diag["top"]), float(diag.get("probability", 0.0))
    return str(diag.get("status")), float(diag.get("probability", 0.0))


def _interval(q: dict[str, Any]) -> tuple[float, float] | None:
    """A published parameter's 2-sigma interval (estimated: value +- 2 rel_std; fused: its
    low..high), or None."""
    if q.get("status") == "estimated":
        v, r = q.get("value"), q.get("rel_std_pct")
        if v is None or r is None:
            return None
        half = 2.0 * float(r) / 100.0 * abs(float(v))
        return float(v) - half, float(v) + half
    if q.get("status") == "fused" and q.get("fused"):
        f = q["fused"]
        if f.get("low") is None or f.get("high") is None:
            return None
        return float(f["low"]), float(f["high"])
    return None


def judge(case: Case, messages: list[dict[str, Any]], ids: list[str]) -> dict[str, Any]:
    """Score one case from its health messages (dicts); ``ids``: its library's fault ids."""
    accept, tolerate = set(case.accept), set(case.tolerate)
    not_wrong = accept | tolerate
    nominal = case.category == "nominal"
    diags = [(m, m.get("diagnosis") or {}) for m in messages]
    max_wrong, wrong_id, wrong_t = 0.0, None, None
    false_alarm = False
    cpu: list[float] = []
    for m, d in diags:
        t_end = float(m["t_end"])
        faults = d.get("faults") or []
        if "cpu_s" in d and d["cpu_s"] is not None:
            cpu.append(float(d["cpu_s"]))
        if nominal and max([float(f["probability"]) for f in faults]
                           + [float(d.get("unknown") or 0.0)]) > FALSE_ALARM:
            false_alarm = True
        if not nominal and t_end < case.onset:
            continue
        for f in faults:
            if f["id"] in ids and f["id"] not in not_wrong and f["probability"] > max_wrong:
                max_wrong, wrong_id, wrong_t = float(f["probability"]), f["id"], t_end
    last = diags[-1][1] if diags else {}
    final, p_final = _answer(last) if last else ("none", 0.0)
    split = [str(x) for x in (last.get("split") or [])]
    by_split = bool(split) and final in split and bool(accept & set(split))
    right = final in accept or by_split
    outcomes = [*ids, "unknown", "no_fault"]
    truth = {x if x in outcomes else "unknown" for x in case.truth[:1]}
    truth |= {x for x in case.truth[1:] if x in outcomes}
    probs = {f["id"]: float(f["probability"]) for f in last.get("faults") or []}
    probs["unknown"] = float(last.get("unknown") or 0.0)
    probs["no_fault"] = float(last.get("no_fault") or 0.0)
    brier = statistics.fmean((probs.get(o, 0.0) - (1.0 if o in truth else 0.0)) ** 2
                             for o in outcomes)
    # coverage and La
    cover: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    la_status: Counter[str] = Counter()
    model_fail = 0
    for m in messages:
        tm = 0.5 * (float(m["t_start"]) + float(m["t_end"]))
        truth_p = case.true_parameters(tm)
        mc = m.get("model_check")
        if mc is not None and not mc.get("passed", True):
            model_fail += 1
        for pname, q in (m.get("parameters") or {}).items():
            if pname == "La":
                la_status[str(q.get("status"))] += 1
            if pname not in truth_p:
                continue
            iv = _interval(q)
            if iv is None:
                continue
            cover[pname][1] += 1
            cover[pname][0] += int(iv[0] <= truth_p[pname] <= iv[1])
    return {"name": case.name, "plant": case.plant, "category": case.category,
            "noise_pct": case.noise_pct, "seed": case.seed, "onset": case.onset,
            "expected": "|".join(sorted(accept)), "final": final, "p": round(p_final, 3),
            "split": split, "right_by_split": by_split and final not in accept,
            "right": right, "max_wrong_p": round(max_wrong, 3), "wrong_id": wrong_id,
            "wrong_t": wrong_t, "confident_wrong": max_wrong >= NAMED,
            "false_alarm": false_alarm if nominal else None, "brier": round(brier, 4),
            "windows": len(messages), "model_check_failed": model_fail,
            "coverage": {k: v for k, v in cover.items()}, "La_status": dict(la_status),
            "diagnosis_cpu_s": cpu}


def _share(rows: list[dict[str, Any]], key: str) -> list[int]:
    return [sum(bool(r[key]) for r in rows), len(rows)]


def summarise(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Totals, per category, per plant and category; coverage per plant and parameter; La."""
    cats = ("library", "sensor_supply", "off_library", "nominal")
    out: dict[str, Any] = {
        "cases": len(results),
        "confident_wrong": _share(results, "confident_wrong"),
        "right_library": _share([r for r in results if r["category"] == "library"], "right"),
        "right_sensor_supply": _share([r for r in results if r["category"] == "sensor_supply"],
                                      "right"),
        "right_off_library": _share([r for r in results if r["category"] == "off_library"],
                                    "right"),
        "nominal_false_alarms": _share([r for r in results if r["category"] == "nominal"],
                                       "false_alarm"),
        "brier": round(statistics.fmean(r["brier"] for r in results), 4) if results else None,
    }
    table: dict[str, dict[str, Any]] = {}
    for plant in sorted({r["plant"] for r in results}, key=list(PLANTS).index):
        for cat in cats:
            rows = [r for r in results if r["plant"] == plant and r["category"] == cat]
            if not rows:
                continue
            table[f"{plant}/{cat}"] = {
                "cases": len(rows), "right": sum(r["right"] for r in rows),
                "confident_wrong": sum(r["confident_wrong"] for r in rows),
                "false_alarm": (sum(bool(r["false_alarm"]) for r in rows)
                                if cat == "nominal" else None),
                "brier": round(statistics.fmean(r["brier"] for r in rows), 4)}
    out["by_plant_category"] = table
    by_cat = {}
    for cat in cats:
        rows = [r for r in results if r["category"] == cat]
        if rows:
            by_cat[cat] = {"cases": len(rows), "right": sum(r["right"] for r in rows),
                           "confident_wrong": sum(r["confident_wrong"] for r in rows),
                           "brier": round(statistics.fmean(r["brier"] for r in rows), 4)}
    out["by_category"] = by_cat
    cov: dict[str, dict[str, list[int]]] = defaultdict(lambda: defaultdict(lambda: [0, 0]))
    for r in results:
        if r["category"] not in ("library", "nominal") or r["noise_pct"] not in COVERAGE_NOISE:
            continue
        for pname, (hit, tot) in r["coverage"].items():
            cov[r["plant"]][pname][0] += hit
            cov[r["plant"]][pname][1] += tot
    out["coverage"] = {p: {k: {"covered": v[0], "windows": v[1],
                               "share": round(v[0] / v[1], 3) if v[1] else None}
                           for k, v in d.items()} for p, d in cov.items()}
    all_hit = sum(v[0] for d in cov.values() for v in d.values())
    all_tot = sum(v[1] for d in cov.values() for v in d.values())
    out["coverage_total"] = {"covered": all_hit, "windows": all_tot,
                             "share": round(all_hit / all_tot, 3) if all_tot else None}
    la: dict[str, Any] = {}
    for plant in FAST_ELECTRICAL:
        rows = [r for r in results if r["plant"] == plant]
        if not rows:
            continue
        st: Counter[str] = Counter()
        for r in rows:
            st.update(r["La_status"])
        la[plant] = {"windows": sum(st.values()),
                     "published": st.get("estimated", 0) + st.get("fused", 0),
                     "statuses": dict(st)}
    out["La_fast_electrical"] = la
    cpu = sorted(x for r in results for x in r["diagnosis_cpu_s"])
    out["diagnosis_cpu_ms_median"] = (round(1e3 * statistics.median(cpu), 3) if cpu else None)
    return out


def _frac(v: list[int]) -> str:
    return f"{v[0]}/{v[1]}" + (f" ({100 * v[0] / v[1]:.0f} %)" if v[1] else "")


def print_report(results: list[dict[str, Any]], summary: dict[str, Any],
                 timing: dict[str, Any]) -> None:
    """The per-case table, the table per plant and category, the totals, coverage and La."""
    head = (f"{'case':46} {'final (p)':30} {'max wrong':30} {'MCfail':>6} {'brier':>6}")
    print(head)
    print("-" * len(head))
    for r in results:
        mark = "" if r["right"] else " x"
        if r["right_by_split"]:
            mark = " (split)"
        wrong = (f"{r['max_wrong_p']:.2f} {r['wrong_id']}" if r["wrong_id"] else "0")
        if r["confident_wrong"]:
            wrong = "! " + wrong
        if r["false_alarm"]:
            mark += " FA"
        print(f"{r['name'][:46]:46} {(r['final'] + ' ' + format(r['p'], '.2f') + mark)[:30]:30} "
              f"{wrong[:30]:30} {r['model_check_failed']:>3}/{r['windows']:<3}"
              f"{r['brier']:>6.3f}")
    print()
    print(f"{'plant/category':24} {'cases':>5} {'right':>6} {'conf.wrong':>10} {'false al.':>9} "
          f"{'Brier':>7}")
    for key, row in summary["by_plant_category"].items():
        fa = "-" if row["false_alarm"] is None else str(row["false_alarm"])
        print(f"{key:24} {row['cases']:>5} {row['right']:>6} {row['confident_wrong']:>10} "
              f"{fa:>9} {row['brier']:>7.4f}")
    for cat, row in summary["by_category"].items():
        print(f"{'all/' + cat:24} {row['cases']:>5} {row['right']:>6} "
              f"{row['confident_wrong']:>10} {'':>9} {row['brier']:>7.4f}")
    s = summary
    print()
    print(f"confident-wrong (a wrong fault >= 0.8, any window from the onset): "
          f"{_frac(s['confident_wrong'])}")
    print(f"right at the end, library faults:            {_frac(s['right_library'])}")
    print(f"acceptable at the end, sensor/supply:        {_frac(s['right_sensor_supply'])}")
    print(f"acceptable at the end, off-library:          {_frac(s['right_off_library'])}")
    print(f"nominal runs with a false alarm (> 0.2):     {_frac(s['nominal_false_alarms'])}")
    print(f"Brier score (last window, mean over cases):  {s['brier']}")
    print()
    print("2-sigma coverage (library and nominal cases at 0.5 and 1 % noise; "
          "estimated or fused windows):")
    for plant, d in s["coverage"].items():
        print(f"  {plant:5} " + "  ".join(
            f"{k} {v['covered']}/{v['windows']} ({100 * v['share']:.0f} %)"
            if v["windows"] else f"{k} -" for k, v in sorted(d.items())))
    tot = s["coverage_total"]
    if tot["windows"]:
        print(f"  total {tot['covered']}/{tot['windows']} ({100 * tot['share']:.0f} %)")
    for plant, d in s["La_fast_electrical"].items():
        print(f"La on {plant} (tau_e below the sample period): published (estimated or fused) in "
              f"{d['published']}/{d['windows']} windows; statuses {d['statuses']}")
    if s["diagnosis_cpu_ms_median"] is not None:
        print(f"diagnosis CPU per window: median {s['diagnosis_cpu_ms_median']} ms")
    else:
        print("diagnosis CPU per window: not in the health message (skipped)")
    short = [r["name"] for r in results if r["windows"] != r["windows_expected"]]
    if short:
        print(f"cases missing windows (not every window estimated): {', '.join(short)}")
    print(f"run: {timing['cases']} cases, {timing['wall_s']} s wall, {timing['cpu_s']} s CPU "
          f"({timing['workers']} workers; plants {timing['sim_cpu_s']} s CPU, daemon "
          f"{timing['daemon_cpu_s']} s CPU)")


# -- the run -----------------------------------------------------------------------------------

def run(chosen: list[Case], workers: int, work: Path) -> tuple[list[dict[str, Any]],
                                                               dict[str, Any]]:
    """Simulate the plants the chosen cases need, run the cases, judge them."""
    sim_dir = work / "plants"
    sim_dir.mkdir(parents=True, exist_ok=True)
    plants = [p for p in PLANTS if any(c.plant == p for c in chosen)]
    tasks = _sim_tasks(plants)
    pending = {p: sum(1 for n, _ in tasks if n == p) for p in plants}
    by_plant: dict[str, list[Case]] = defaultdict(list)
    for c in chosen:
        by_plant[c.plant].append(c)
    wall0 = time.perf_counter()
    ctx = multiprocessing.get_context("fork")
    sims: list[dict[str, Any]] = []
    records: dict[str, dict[str, Any]] = {}
    with ctx.Pool(workers) as pool:
        sim_jobs = [pool.apply_async(_simulate, ((n, ix, str(sim_dir)),)) for n, ix in tasks]
        case_jobs: list[Any] = []
        done_sims: set[int] = set()
        while len(done_sims) < len(sim_jobs) or len(records) < len(case_jobs):
            for i, j in enumerate(sim_jobs):
                if i in done_sims or not j.ready():
                    continue
                done_sims.add(i)
                res = j.get()
                sims.append(res)
                print(f"simulated {res['plant']} {res['indices']}: {res['cpu_s']:.1f} s CPU",
                      file=sys.stderr, flush=True)
                pending[res["plant"]] -= 1
                if pending[res["plant"]] == 0:  # its cases, the longest first
                    for c in sorted(by_plant[res["plant"]], key=lambda c: -c.duration):
                        case_jobs.append(pool.apply_async(
                            _run_case, ((c.name, str(sim_dir), str(work / "cases")),)))
            for j in case_jobs:
                if j.ready() and id(j) not in records:
                    rec = j.get()
                    records[id(j)] = rec
                    print(f"ran {rec['name']}: {rec['windows']} windows, {rec['wall_s']} s "
                          f"wall, {rec['cpu_s']} s CPU", file=sys.stderr, flush=True)
            time.sleep(0.2)
    wall = time.perf_counter() - wall0
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    by_name = {r["name"]: r for r in records.values()}
    results = []
    ids_of: dict[str, list[str]] = {}
    for c in chosen:
        rec = by_name[c.name]
        lines = Path(rec["dir"], "health.jsonl").read_text().splitlines()
        messages = [json.loads(ln) for ln in lines if ln.strip()]
        model = messages[0]["model"] if messages else "dc_motor"
        ids = ids_of.setdefault(model, library_ids(model))
        r = judge(c, messages, ids)
        r["daemon_wall_s"], r["daemon_cpu_s"] = rec["wall_s"], rec["cpu_s"]
        r["windows_expected"] = rec["windows_expected"]
        results.append(r)
    timing = {"cases": len(chosen), "workers": workers, "wall_s": round(wall, 1),
              "cpu_s": round(ru.ru_utime + ru.ru_stime, 1),
              "sim_cpu_s": round(sum(s["cpu_s"] for s in sims), 1),
              "daemon_cpu_s": round(sum(r["daemon_cpu_s"] for r in results), 1),
              "sims": [{k: (round(v, 2) if isinstance(v, float) else v) for k, v in s.items()}
                       for s in sims],
              "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
              "cpus": os.cpu_count(), "sample_period": SAMPLE_PERIOD}
    return results, timing


def _commit() -> str | None:
    try:
        out = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                             capture_output=True, text=True, check=True)
        dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain",
                                "twinwatch"], capture_output=True, text=True, check=True)
        return out.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.CalledProcessError):
        return None


def main() -> None:
    """Command line (see the module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", default=None, help="comma-separated case-name prefixes")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", type=Path, default=None, help="write the results here")
    ap.add_argument("--keep", type=Path, default=None,
                    help="keep the recordings, configurations and health.jsonl here")
    ap.add_argument("--list", action="store_true", help="print the case table and exit")
    args = ap.parse_args()
    all_cases = cases()
    if args.list:
        for c in all_cases:
            print(f"{c.name:46} {c.category:13} onset {c.onset:>4g} s seed {c.seed} accept "
                  f"{'|'.join(sorted(c.accept)):40} {c.note}")
        return
    chosen = select(all_cases, args.only)
    if not chosen:
        raise SystemExit(f"--only {args.only}: no case")
    if args.keep is not None:
        work = args.keep
        if work.exists():
            shutil.rmtree(work)
        work.mkdir(parents=True)
        results, timing = run(chosen, args.workers, work)
    else:
        with tempfile.TemporaryDirectory(prefix="bench-heldout-") as tmp:
            results, timing = run(chosen, args.workers, Path(tmp))
    summary = summarise(results)
    print_report(results, summary, timing)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(
            {"table": TABLE, "commit": _commit(), "summary": summary,
             "results": results, "timing": timing}, indent=1, default=str))


if __name__ == "__main__":
    main()
