"""Fault injection: bad input, broken files and resources, and a new user's first run.

Each case injects one fault and returns what it observed as a small dict of facts; the test
compares it with the case's ``expected`` dict, so a failure prints case, expected and observed
side by side. The cases are registered with :func:`case` in the order of issue #10's list;
read them top to bottom as a table (``pytest tests/test_fault_injection.py -v`` lists them).

Faults tested elsewhere: CAN bad frames and NaN (test_drivers_can.py), gaps, NaN windows,
overruns and a failing window (test_daemon.py), a Modbus server that goes away
(test_drivers_modbus.py), a silent source (test_watchdog.py), SIGKILL mid-write
(test_store.py, test_service.py).

Runs are short (a few 2 s windows of the simulated motor, Zenoh and the recording off unless
the case is about them); every socket is on 127.0.0.1.
"""

from __future__ import annotations

import json
import logging
import sqlite3
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import cantools
import pytest
from click.testing import CliRunner

from twinwatch.cli import main
from twinwatch.daemon.store import StateStore

from .conftest import ROOT

SIM = (ROOT / "config" / "dc-motor-sim.toml").read_text()


@dataclass(frozen=True)
class Case:
    name: str
    expected: dict[str, Any]
    run: Callable[[Context], dict[str, Any]]


@dataclass
class Context:
    tmp: Path
    caplog: pytest.LogCaptureFixture
    monkeypatch: pytest.MonkeyPatch


CASES: list[Case] = []


def case(name: str, **expected: Any) -> Callable[[Callable[[Context], dict[str, Any]]],
                                                  Callable[[Context], dict[str, Any]]]:
    """Register the decorated function as a fault case: it returns the observed facts."""

    def register(fn: Callable[[Context], dict[str, Any]]) -> Callable[[Context], dict[str, Any]]:
        CASES.append(Case(name, expected, fn))
        return fn

    return register


# -- helpers ------------------------------------------------------------------------------
def sim_config(tmp: Path, *, duration: float = 6.0, zenoh: bool = False,
               recording: bool = False, extra: str = "", **replace: str) -> Path:
    """The simulated motor's example config, short, written to ``tmp/m.toml``."""
    text = SIM.replace("duration = 1200.0", f"duration = {duration}")
    if not zenoh:
        text = text.replace("[zenoh]", "[zenoh]\nenabled = false")
    if not recording:
        text = text.replace("[recording]", "[recording]\nenabled = false")
    text = text.replace('path = "state.sqlite"', f'path = "{tmp / "state.sqlite"}"')
    for old, new in replace.items():
        assert old in text, old
        text = text.replace(old, new)
    path = tmp / "m.toml"
    path.write_text(text + extra)
    return path


def cli(*args: str) -> Any:
    """``twinwatch ARGS`` in this process (click's runner): exit code and output."""
    return CliRunner().invoke(main, list(args), catch_exceptions=True)


def health(window: int, machine: str = "dc-motor-sim") -> dict[str, Any]:
    return {"machine": machine, "window": window, "t_start": 2.0 * window,
            "t_end": 2.0 * window + 1.99, "parameters": {}, "alarms": {}}


def corrupt_pages(db: Path, first_page: int = 6, pages: int = 20) -> None:
    """Overwrite pages in the middle of a database, leaving its header intact."""
    con = sqlite3.connect(db)
    con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    con.close()
    with db.open("r+b") as f:
        f.seek(4096 * first_page)
        f.write(b"\x5a" * (4096 * pages))


def filled_store(db: Path, windows: int = 300) -> None:
    twin = {"parameters": {"Ra": 6.0}, "trusted": {"Ra": 6.0}, "terms": []}
    with StateStore(db) as st:
        for w in range(windows):
            st.save_window(health(w), twin)


# -- 1. the state database ------------------------------------------------------------------
@case("state db: header intact, pages corrupt, recover_corrupt = true: `run` at start",
      exit_code=0, moved_aside=1, resumed=False, says_set_recover_corrupt=False,
      windows_stored=3)
def _corrupt_pages_at_start(ctx: Context) -> dict[str, Any]:
    db = ctx.tmp / "state.sqlite"
    filled_store(db)
    corrupt_pages(db)
    cfg = sim_config(ctx.tmp, extra="recover_corrupt = true\n")
    r = cli("run", str(cfg), "--no-progress", "--log-level", "info")
    with StateStore(db) as st:
        stored = st.count()
    text = r.output + ctx.caplog.text
    return {"exit_code": r.exit_code,
            "moved_aside": len(list(ctx.tmp.glob("state.sqlite.corrupt-*"))) - len(
                list(ctx.tmp.glob("state.sqlite.corrupt-*-*"))),
            "resumed": "resumed the twin" in text,
            "says_set_recover_corrupt": "set [state] recover_corrupt" in text
            or "set recover_corrupt" in text,
            "windows_stored": stored}


@case("state db: header intact, pages corrupt, recover_corrupt = false: `run` at start",
      exit_code=1, names_the_fix="set [state] recover_corrupt = true", moved_aside=0)
def _corrupt_pages_no_recovery(ctx: Context) -> dict[str, Any]:
    db = ctx.tmp / "state.sqlite"
    filled_store(db)
    corrupt_pages(db)
    r = cli("run", str(sim_config(ctx.tmp)), "--no-progress")
    fix = "set [state] recover_corrupt = true"
    return {"exit_code": r.exit_code,
            "names_the_fix": fix if fix in r.output else r.output[-300:],
            "moved_aside": len(list(ctx.tmp.glob("state.sqlite.corrupt-*")))}


@case("state db: corruption found at run time by a history query (another thread)",
      moved_aside=1, history_after=0, next_window_stored=True, rows_in_new_db=1)
def _corrupt_pages_at_run_time(ctx: Context) -> dict[str, Any]:
    db = ctx.tmp / "state.sqlite"
    with StateStore(db, recover_corrupt=True) as st:
        for w in range(300):
            st.save_window(health(w), None)
        corrupt_pages(db)
        got: list[Any] = []
        reader = threading.Thread(target=lambda: got.append(st.history(limit=None)),
                                  name="zenoh-history-query")
        reader.start()
        reader.join()
        stored = st.save_window(health(300), None)
        rows = st.count()
    return {"moved_aside": len(list(ctx.tmp.glob("state.sqlite.corrupt-*"))),
            "history_after": len(got[0]) if got else None,
            "next_window_stored": stored, "rows_in_new_db": rows}


# -- 3. a malformed line in a CAN log --------------------------------------------------------
PLANT_DBC = ROOT / "twinwatch" / "plant" / "dcmotor.dbc"


def candump_log(path: Path, n: int, bad_lines: dict[int, str] | None = None) -> None:
    """A candump log of ``n`` plant samples (3 frames each), with some lines replaced."""
    db = cantools.database.load_file(PLANT_DBC)
    lines = []
    for k in range(n):
        for name, sig in (("TW_Motor_Electrical", {"Va": 2.0, "ia": 0.5}),
                          ("TW_Motor_Mechanical", {"omega": 10.0 * k, "Tload": 0.0}),
                          ("TW_Motor_Sample", {"setpoint": 1.0, "sample_counter": k})):
            msg = db.get_message_by_name(name)
            lines.append(f"({k * 0.01:.6f}) can0 {msg.frame_id:03X}#"
                         f"{msg.encode(sig).hex().upper()}")
    for i, text in (bad_lines or {}).items():
        lines[i] = text
    path.write_text("\n".join(lines) + "\n")


def can_log_driver(log: Path) -> dict[str, Any]:
    return {"type": "can", "dbc": str(PLANT_DBC), "log_file": str(log),
            "sync_message": "TW_Motor_Sample", "time_source": "counter",
            "counter_signal": "TW_Motor_Sample.sample_counter", "sample_period": 0.01,
            "signals": {"Va": {"message": "TW_Motor_Electrical", "signal": "Va"},
                        "ia": {"message": "TW_Motor_Electrical", "signal": "ia"},
                        "omega": {"message": "TW_Motor_Mechanical", "signal": "omega"},
                        "Tload": {"message": "TW_Motor_Mechanical", "signal": "Tload"},
                        "setpoint": {"message": "TW_Motor_Sample", "signal": "setpoint"}}}


def replay(driver_table: dict[str, Any], base_dir: Path) -> tuple[list[Any], Any, str]:
    """Read a driver to its end: samples, stats, and how it ended."""
    from twinwatch.drivers import DriverError, EndOfStream, create_driver

    samples = []
    with create_driver(driver_table, base_dir=base_dir) as drv:
        try:
            while (s := drv.read(0)) is not None or True:
                if s is not None:
                    samples.append(s)
        except EndOfStream:
            end = "end of stream"
        except DriverError as exc:
            end = f"{type(exc).__name__}: {exc}"
    return samples, drv.stats, end


@case("CAN candump log: one malformed line in the middle of 50 samples",
      end="end of stream", samples=49, bad_frames=1, logged_line_number=True)
def _can_log_malformed_line(ctx: Context) -> dict[str, Any]:
    log = ctx.tmp / "m.log"
    candump_log(log, 50, {77: "(0.250000) can0 this-is-not-a-frame"})  # sample 25 sync
    samples, stats, end = replay(can_log_driver(log), ctx.tmp)
    return {"end": end, "samples": len(samples), "bad_frames": stats.bad_frames,
            "logged_line_number": "CAN log line 78 is malformed" in ctx.caplog.text}


@case("CAN candump log: three malformed lines (garbage, short, bad hex)",
      end="end of stream", samples=47, bad_frames=3)
def _can_log_three_malformed_lines(ctx: Context) -> dict[str, Any]:
    log = ctx.tmp / "m.log"
    candump_log(log, 50, {2: "garbage", 32: "(0.1) can0", 62: "(0.2) can0 12Z#ZZ"})
    samples, stats, end = replay(can_log_driver(log), ctx.tmp)
    return {"end": end, "samples": len(samples), "bad_frames": stats.bad_frames}


@case("CAN .csv log (python-can format, with a header): one malformed line",
      end="end of stream", samples=19, bad_frames=1)
def _can_csv_log_malformed_line(ctx: Context) -> dict[str, Any]:
    src = ctx.tmp / "m.log"
    candump_log(src, 20)
    csv_log = ctx.tmp / "m.csv"
    with can.LogReader(src) as reader, can.CSVWriter(csv_log) as writer:
        for msg in reader:
            writer.on_message_received(msg)
    lines = csv_log.read_text().splitlines()
    lines[33] = "0.1,not,a,frame"  # sample 10: its sync frame (lines[0] is the header)
    csv_log.write_text("\n".join(lines) + "\n")
    samples, stats, end = replay(can_log_driver(csv_log), ctx.tmp)
    return {"end": end, "samples": len(samples), "bad_frames": stats.bad_frames}


# -- 4. configuration values that must be refused --------------------------------------------
def refused(ctx: Context, key: str, **replace: str) -> dict[str, Any]:
    """check-config and run on the simulated motor's config with ``replace`` applied."""
    cfg = sim_config(ctx.tmp, **replace)
    check = cli("check-config", str(cfg))
    run = cli("run", str(cfg), "--no-progress")
    return {"check_config": check.exit_code, "run": run.exit_code,
            "names_the_key": key in check.output and key in run.output,
            "traceback": "Traceback" in check.output + run.output
            or not isinstance(check.exception, SystemExit | None)
            or not isinstance(run.exception, SystemExit | None)}


REFUSED = {"check_config": 1, "run": 78, "names_the_key": True, "traceback": False}


@case("config: [machine.parameters] Ra = nan (the alarm could never fire)", **REFUSED)
def _nan_nameplate(ctx: Context) -> dict[str, Any]:
    return refused(ctx, "machine.parameters.Ra", **{"Ra = 6.5 ": "Ra = nan "})


@case("config: [machine.parameters] Ra = -6.5", **REFUSED)
def _negative_nameplate(ctx: Context) -> dict[str, Any]:
    return refused(ctx, "machine.parameters", **{"Ra = 6.5 ": "Ra = -6.5 "})


@case("config: acquisition.window = 1000000000 (numpy would die allocating it)", **REFUSED)
def _huge_window(ctx: Context) -> dict[str, Any]:
    return refused(ctx, "acquisition.window", **{"window = 200": "window = 1000000000"})


@case("config: acquisition.sample_period = inf", **REFUSED)
def _infinite_sample_period(ctx: Context) -> dict[str, Any]:
    return refused(ctx, "acquisition.sample_period",
                   **{"sample_period = 0.01": "sample_period = inf"})


@case("config: estimation.bounds Ra = [1.0, inf]", **REFUSED)
def _infinite_bound(ctx: Context) -> dict[str, Any]:
    return refused(ctx, "estimation.bounds.Ra", **{"Ra = [1.0, 30.0]": "Ra = [1.0, inf]"})


@case("config: machine.name of 1 MB", **REFUSED)
def _huge_machine_name(ctx: Context) -> dict[str, Any]:
    return refused(ctx, "machine.name",
                   **{'name = "dc-motor-sim"': f'name = "{"m" * 1_000_000}"'})


@case("config: machine.options.sub_step = 0 (a division by zero in the model)", **REFUSED)
def _zero_sub_step(ctx: Context) -> dict[str, Any]:
    return refused(ctx, "machine", **{"sub_step = 1e-4": "sub_step = 0.0"})


# -- 8. the history query ------------------------------------------------------------------
@case("history query: limit=inf, t_from=inf, limit=0, t_from>t_to, a misspelt key; then 30 "
      "more bad queries",
      replies=["error: limit='inf'", "error: t_from='inf'", "error: limit='0'",
               "error: t_from=5 is after t_to=1", "error: unknown parameter 'tfrom'",
               "ok: 2 windows"],
      log_lines=1, tracebacks=0)
def _history_bad_parameters(ctx: Context) -> dict[str, Any]:
    from twinwatch.config.loader import default_config
    from twinwatch.daemon.runner import Daemon

    from .test_service import zsession
    from .test_zenoh_publisher import endpoint, free_port

    port = free_port()
    cfg = default_config()
    cfg.zenoh.listen = [endpoint(port)]
    cfg.recording.enabled = False
    cfg.state.path = str(ctx.tmp / "state.sqlite")
    replies = []
    with Daemon(cfg, persist=True, record=False) as daemon:
        for w in range(2):
            daemon.store.save_window(health(w), None)
        base = f"twinwatch/{cfg.machine.name}/history"
        ctx.caplog.clear()
        with zsession("client", connect=[endpoint(port)]) as s:
            for sel in ("limit=inf", "t_from=inf", "limit=0", "t_from=5;t_to=1", "tfrom=3",
                        "t_from=0;t_to=10;limit=5"):
                for r in s.get(f"{base}?{sel}", timeout=5.0):
                    if r.ok is not None:
                        replies.append(f"ok: {json.loads(r.ok.payload.to_string())['count']} "
                                       f"windows")
                    else:
                        replies.append("error: " + r.err.payload.to_string())
            for _ in range(30):
                list(s.get(f"{base}?limit=inf", timeout=5.0))
    logged = [r for r in ctx.caplog.records if "query" in r.getMessage()
              and r.levelno >= logging.WARNING]
    return {"replies": [r.split(":")[0] + ": " + r.split(": ", 1)[1].split(":")[0]
                        if r.startswith("error") else r for r in replies],
            "log_lines": len(logged),
            "tracebacks": sum(r.exc_info is not None for r in ctx.caplog.records)}


# -- 9. reload, CSV quotes, file modes -------------------------------------------------------
@case("SIGHUP reload keeps the state database open: the window index goes on under the "
      "same run id", runs=1, windows=[0, 1, 2, 3, 4, 5], duplicate_rows=0)
def _reload_window_index(ctx: Context) -> dict[str, Any]:
    from twinwatch.config.loader import load_config
    from twinwatch.daemon.runner import SINKS, Daemon

    cfg = load_config(sim_config(ctx.tmp))
    first = Daemon(cfg, persist=True, publish=False, record=False)
    first.run()
    kept = first.close(keep=SINKS)  # what the CLI does on SIGHUP
    second = Daemon(cfg, persist=True, publish=False, record=False, reuse=kept)
    second.run()
    second.close()
    con = sqlite3.connect(ctx.tmp / "state.sqlite")
    rows = con.execute("SELECT run, window FROM health ORDER BY id").fetchall()
    con.close()
    return {"runs": len({r for r, _ in rows}), "windows": [w for _, w in rows],
            "duplicate_rows": len(rows) - len(set(rows))}


@case("CSV recording: one unterminated quote on line 304 of 1001",
      samples=1000, bad_values=2, rows_after_it_read=True, names_the_line=True)
def _csv_unterminated_quote(ctx: Context) -> dict[str, Any]:
    lines = ["t,Va,omega"] + [f"{k * 0.01:.2f},{k},{2 * k}" for k in range(1000)]
    lines[303] = '3.02,"302,604'  # row 302: line 304 of the file (line 1: header)
    data = ctx.tmp / "rec.csv"
    data.write_text("\n".join(lines) + "\n")
    samples, stats, _ = replay({"type": "file", "path": str(data), "time_column": "t",
                                "sample_period": 0.01,
                                "columns": {"Va": {"column": "Va"},
                                            "omega": {"column": "omega"}}}, ctx.tmp)
    return {"samples": len(samples), "bad_values": stats.bad_values,
            "rows_after_it_read": samples[-1].values["omega"] == 1998.0,
            "names_the_line": "(first: line 304)" in ctx.caplog.text}


@case("files `run` creates outside systemd, with umask 022: not readable by others",
      exit_code=0, others_can_read=[], umask_restored=True)
def _file_modes(ctx: Context) -> dict[str, Any]:
    import os
    import stat

    old = os.umask(0o022)
    try:
        r = cli("run", str(sim_config(ctx.tmp, duration=4.0, recording=True)), "--no-progress")
        after = os.umask(0o022)
    finally:
        os.umask(old)
    made = [p for p in ctx.tmp.iterdir() if p.name != "m.toml"]
    assert {"state.sqlite", "twinwatch.rrd", "twinwatch.rbl"} <= {p.name for p in made}
    return {"exit_code": r.exit_code,
            "others_can_read": sorted(p.name for p in made
                                      if p.stat().st_mode & stat.S_IROTH),
            "umask_restored": after == 0o022}


# -- the table ------------------------------------------------------------------------------
@pytest.mark.parametrize("fault", CASES, ids=[c.name for c in CASES])
def test_fault(fault: Case, tmp_path: Path, caplog: pytest.LogCaptureFixture,
               monkeypatch: pytest.MonkeyPatch) -> None:
    caplog.set_level(logging.INFO)
    monkeypatch.chdir(tmp_path)
    observed = fault.run(Context(tmp_path, caplog, monkeypatch))
    assert observed == fault.expected, (
        f"\ncase:     {fault.name}\nexpected: {json.dumps(fault.expected)}\n"
        f"observed: {json.dumps(observed, default=str)}")
