"""The state store: round trip, history ranges, restart, retention, faults, and nothing lost
when the writer is killed with SIGKILL mid-write."""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from twinwatch.sinks.store import SCHEMA_VERSION, StateStore, StoreError
from twinwatch.twin.health import read_health

ROOT = Path(__file__).resolve().parents[1]


def health(window: int, *, machine: str = "m1", ra: float = 6.5) -> dict[str, Any]:
    return {"schema": 1, "machine": machine, "model": "dc_motor", "window": window,
            "t_start": 2.0 * window, "t_end": 2.0 * window + 1.99, "samples": 200,
            "parameters": {"Ra": {"value": ra, "unit": "ohm", "nominal": 6.5,
                                  "deviation_pct": (ra / 6.5 - 1) * 100, "held": False,
                                  "reason": None, "rel_std_pct": 0.1}},
            "nrmse": 1.7e-4, "trusted": True, "counters": {"windows_completed": window + 1}}


def twin(ra: float) -> dict[str, Any]:
    return {"parameters": {"Ra": ra, "D": 0.00143}, "held": {"Ra": False, "D": True},
            "trusted": np.array([ra, 0.00143]), "terms": [{"state": "omega",
                                                          "expr": "4.92*sin(9.98*t + 2.68)"}]}


def test_round_trip_and_restart_restores(tmp_path: Path) -> None:
    db = tmp_path / "state.sqlite"
    with StateStore(db) as st:
        assert st.load_twin_state() is None and st.history() == []
        for w in range(5):
            assert st.save_window(health(w, ra=6.5 - 0.1 * w), twin(6.5 - 0.1 * w)
                                  if w != 4 else None)  # window 4 not trusted
        assert st.history()[3] == read_health(health(3, ra=6.5 - 0.3))  # typed, as saved
    with StateStore(db) as st:  # a restart
        state = st.load_twin_state()
        assert state is not None
        assert state["parameters"]["Ra"] == pytest.approx(6.2)  # window 3: the last accepted
        assert state["trusted"] == pytest.approx([6.2, 0.00143])
        assert state["terms"][0]["expr"] == "4.92*sin(9.98*t + 2.68)"
        assert state["held"] == {"Ra": False, "D": True}
        assert st.load_twin_state("m1") == state and st.load_twin_state("other") is None
        assert st.count() == 5
        latest = st.latest_health()
        assert latest is not None and latest.window == 4


def test_the_diagnosis_evidence_is_kept_apart_and_joins_its_runs_twin(tmp_path: Path) -> None:
    """A twin saved with its ``diagnosis`` (the diagnoser's evidence) is written as two rows:
    a later twin saved without it (a trusted window between two checkpoints) keeps the
    evidence on reading; another run's twin does not take it; a twin saved whole by an
    earlier version keeps its own; :meth:`StateStore.save_state` saves without a window."""
    db = tmp_path / "state.sqlite"
    evidence = {"tracks": {"winding_short": [[0.1, 0.2], [0.3, 0.4]]}, "windows": 2}
    with StateStore(db, run="r1") as st:
        assert st.save_window(health(0), {**twin(6.5), "diagnosis": evidence})
        assert st.save_window(health(1, ra=6.4), twin(6.4))
        state = st.load_twin_state("m1")
        assert state is not None and state["diagnosis"] == evidence
        assert state["parameters"]["Ra"] == 6.4
        with sqlite3.connect(db) as con:
            row = con.execute("SELECT state FROM twin").fetchone()
            assert "diagnosis" not in json.loads(row[0])
        later = {**evidence, "windows": 3}
        assert st.save_state("m1", 2, 6.0, {**twin(6.3), "diagnosis": later})
        assert st.load_twin_state() == {**twin(6.3), "trusted": [6.3, 0.00143],
                                        "diagnosis": later}
    with StateStore(db, run="r2") as st:  # a fresh run's first twin: not the old evidence
        assert st.save_window({**health(0, ra=6.5), "run": "r2"}, twin(6.5))
        state = st.load_twin_state("m1")
        assert state is not None and "diagnosis" not in state
        whole = {**twin(6.5), "diagnosis": {"windows": 9}}
        with sqlite3.connect(db) as con:  # as an earlier version saved it
            con.execute("UPDATE twin SET state = ?", (json.dumps(whole, default=list),))
        state = st.load_twin_state("m1")
        assert state is not None and state["diagnosis"] == {"windows": 9}


def test_history_by_plant_time_and_wall_time(tmp_path: Path) -> None:
    with StateStore(tmp_path / "s.sqlite") as st:
        for w in range(20):
            st.save_window(health(w), None, wall=1_000_000.0 + 10 * w)
        st.save_window(health(0, machine="m2"), None, wall=2_000_000.0)
        # plant time: windows overlapping [10, 20] s are 4 (8-9.99 s) .. 10 (20-21.99 s)
        got = [h.window for h in st.history(10.0, 20.0, machine="m1")]
        assert got == [5, 6, 7, 8, 9, 10]
        assert [h.window for h in st.history(10.0, 20.0, limit=2, machine="m1")] == [5, 6]
        assert [h.window for h in st.history(t_from=36.0, machine="m1")] == [18, 19]
        # wall time
        got = [h.window for h in st.history(1_000_050.0, 1_000_080.0, by="wall")]
        assert got == [5, 6, 7, 8]
        assert [h.machine for h in st.history(by="wall", t_from=1.5e6)] == ["m2"]
        with pytest.raises(ValueError):
            st.history(by="nonsense")  # type: ignore[arg-type]


def test_retention_by_rows_and_days_in_batches(tmp_path: Path) -> None:
    now = time.time()
    with StateStore(tmp_path / "s.sqlite", keep_rows=50, keep_days=None, prune_every=0,
                    prune_batch=7) as st:
        for w in range(120):
            st.save_window(health(w), None)
        assert st.prune() == 70 and st.count() == 50
        assert st.history(limit=1)[0].window == 70
    with StateStore(tmp_path / "d.sqlite", keep_rows=None, keep_days=1.0, prune_every=10,
                    prune_batch=3) as st:
        for w in range(30):  # 20 rows 2 days old, then 10 new: pruned automatically
            st.save_window(health(w), None, wall=now - 2 * 86400 if w < 20 else now)
        assert st.count() == 10 and st.pruned == 20


def test_future_schema_version_is_refused(tmp_path: Path) -> None:
    db = tmp_path / "s.sqlite"
    StateStore(db).close()
    with sqlite3.connect(db) as c:
        c.execute("INSERT INTO schema_version VALUES (?, 0)", (SCHEMA_VERSION + 1,))
    c.close()
    with pytest.raises(StoreError, match="written by a newer twinwatch .*upgrade twinwatch"):
        StateStore(db)


def test_corrupt_database_is_named_or_moved_aside(tmp_path: Path,
                                                  caplog: pytest.LogCaptureFixture) -> None:
    db = tmp_path / "s.sqlite"
    db.write_bytes(b"this is not a database" * 100)
    with pytest.raises(StoreError, match=r"corrupt or not a twinwatch database: stop the "
                                         r"service, move it aside"):
        StateStore(db)
    with StateStore(db, recover_corrupt=True) as st:
        assert st.count() == 0
    aside = [p for p in tmp_path.iterdir() if ".corrupt-" in p.name]
    assert len(aside) == 1 and aside[0].read_bytes().startswith(b"this is not")
    assert "moved aside" in caplog.text
    other = tmp_path / "other.sqlite"
    with sqlite3.connect(other) as c:
        c.execute("CREATE TABLE t (x)")
    c.close()
    with pytest.raises(StoreError, match="not a twinwatch database"):
        StateStore(other)


def test_locked_database_keeps_windows_in_memory(tmp_path: Path,
                                                 caplog: pytest.LogCaptureFixture) -> None:
    db = tmp_path / "s.sqlite"
    with StateStore(db, busy_timeout=0.05) as st:
        st.save_window(health(0), twin(6.5))
        locker = sqlite3.connect(db, isolation_level=None)
        locker.execute("BEGIN IMMEDIATE")  # e.g. an operator's sqlite3 shell
        assert not st.save_window(health(1), twin(6.4))
        assert not st.save_window(health(2), None)
        errors = [r for r in caplog.records if r.levelname == "ERROR"]
        assert len(errors) == 1 and "another process holds a lock" in errors[0].getMessage()
        locker.execute("ROLLBACK")
        locker.close()
        assert st.save_window(health(3), None)
        assert [h.window for h in st.history()] == [0, 1, 2, 3]
        state = st.load_twin_state()
        assert state is not None and state["parameters"]["Ra"] == 6.4


def test_reader_thread_while_writer_writes(tmp_path: Path) -> None:
    """A queryable thread reads while the worker writes: each has its own connection, reads
    never fail and never see a partial window."""
    with StateStore(tmp_path / "s.sqlite", synchronous="NORMAL") as st:
        st.save_window(health(0), twin(6.5))
        errors: list[BaseException] = []
        seen: list[int] = []
        done = threading.Event()

        def reader() -> None:
            try:
                while not done.is_set():
                    h = st.history(limit=None)
                    assert [x.window for x in h] == list(range(len(h)))
                    seen.append(len(h))
            except BaseException as exc:  # reported below
                errors.append(exc)

        t = threading.Thread(target=reader, name="store-reader")
        t.start()
        for w in range(1, 200):
            st.save_window(health(w), twin(6.5))
        done.set()
        t.join(timeout=10)
        assert not errors and seen and st.count() == 200


_CHILD = r"""
import sys, time
sys.path.insert(0, sys.argv[2])
from twinwatch.sinks.store import StateStore
st = StateStore(sys.argv[1], keep_rows=None, keep_days=None)
start = st.count()
pad = "x" * 20000          # a large document: the kill lands inside a write more often
w = start
while True:
    h = {"machine": "m1", "window": w, "t_start": 2.0 * w, "t_end": 2.0 * w + 1.99,
         "pad": pad}
    st.save_window(h, {"parameters": {"Ra": 6.5 - 1e-4 * w}, "window": w})
    print(w, flush=True)   # committed: only now is it announced
    w += 1
"""


def test_sigkill_mid_write_loses_no_committed_window(tmp_path: Path) -> None:
    db = tmp_path / "state.sqlite"
    announced: list[int] = []
    for round_, n_before_kill in enumerate((40, 25)):  # kill, restart, kill again
        proc = subprocess.Popen([sys.executable, "-c", _CHILD, str(db), str(ROOT)],
                                stdout=subprocess.PIPE, text=True)
        assert proc.stdout is not None
        got = 0
        while got < n_before_kill:
            line = proc.stdout.readline()
            assert line, "child died"
            announced.append(int(line))
            got += 1
        time.sleep(0.003 * (round_ + 1))  # let it be inside the next write
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
        assert proc.returncode == -signal.SIGKILL
        announced += [int(x) for x in proc.stdout.read().split()]  # printed before the kill
        proc.stdout.close()

        conn = sqlite3.connect(db)
        assert conn.execute("PRAGMA integrity_check").fetchall() == [("ok",)]
        stored = [r[0] for r in conn.execute("SELECT window FROM health ORDER BY id")]
        conn.close()
        assert set(announced) <= set(stored)          # every committed window is there
        assert stored == list(range(len(stored)))     # a prefix: no gap, no half window
        with StateStore(db) as st:                    # restart restores the twin
            state = st.load_twin_state()
            assert state is not None and state["window"] == stored[-1]
    print(f"SIGKILL x2: {len(announced)} windows announced, {len(stored)} stored, "
          "integrity_check ok")


def test_json_of_numpy_and_bad_synchronous(tmp_path: Path) -> None:
    with pytest.raises(ValueError):
        StateStore(tmp_path / "x.sqlite", synchronous="OFF")  # type: ignore[arg-type]
    with StateStore(tmp_path / "s.sqlite") as st:
        h = health(0)
        h["extra"] = {"v": np.float64(1.5), "a": np.arange(3)}
        st.save_window(h, None)
        extra = st.history()[0].model_extra or {}  # a field the view does not know: kept
        assert json.dumps(extra["extra"]) == '{"v": 1.5, "a": [0, 1, 2]}'


def test_history_pages_advance_with_the_after_cursor(tmp_path: Path) -> None:
    """Issue 26 item 6: paging as the docs said, ``t_from`` = the last ``t_end``, returned
    each page's last window again (``t_from`` is inclusive: a window overlapping it), and with
    ``limit = 1`` never advanced. ``after`` (only windows ending strictly after it) advances:
    every window once, also one at a time, by plant and by wall time; the Zenoh history query
    takes it and answers the next cursor (``next_after``)."""
    from twinwatch.sinks.zenoh import history_parameters

    with StateStore(tmp_path / "s.sqlite") as st:
        for w in range(7):
            st.save_window(health(w), None, wall=1_000_000.0 + 10 * w)
        # the old way: stuck on window 0
        first = st.history(limit=1, machine="m1")
        again = st.history(t_from=first[-1].t_end, limit=1, machine="m1")
        assert [h.window for h in again] == [h.window for h in first] == [0]
        for by in ("plant", "wall"):
            seen: list[int] = []
            cursor = None
            walls = {w: 1_000_000.0 + 10 * w for w in range(7)}
            while True:
                page = st.history(limit=1 if by == "plant" else 3, machine="m1", by=by,
                                  after=cursor)
                if not page:
                    break
                seen += [h.window for h in page]
                cursor = page[-1].t_end if by == "plant" else walls[page[-1].window]
            assert seen == list(range(7)), (by, seen)
    assert history_parameters({"after": "12.5", "limit": "1"}) == (
        None, None, 1, "plant", None, 12.5)
    with pytest.raises(ValueError, match="after"):
        history_parameters({"after": "inf"})


def test_the_history_reply_carries_the_cursor_by_wall_time_too(tmp_path: Path) -> None:
    """Issue 37: the docs' history example asks ``by=wall`` (the last hour), but the reply
    carried ``next_after`` by plant time only: a client paging by wall time had no cursor (the
    messages carry no wall stamp), so ``more`` said there was more and nothing said where it
    began. The reply's ``next_after`` is now the cursor of the ``by`` asked: every window once,
    one at a time, by plant and by wall time, paging only with what the replies say."""
    from types import SimpleNamespace

    from twinwatch.sinks.zenoh import HealthPublisher

    with StateStore(tmp_path / "s.sqlite") as st:
        for w in range(7):
            st.save_window(health(w), None, wall=1_000_000.0 + 10 * w)

        def history(t_from, t_to, limit, by, run=None, after=None):  # the daemon's binding
            return st.history(t_from, t_to, limit, by=by, machine="m1", run=run, after=after)

        daemon = SimpleNamespace(context=SimpleNamespace(history=history, run="r1"),
                                 _detached=False, machine="m1")
        for by in ("plant", "wall"):
            seen: list[int] = []
            params: dict[str, str] = {"by": by, "limit": "1", "t_from": "0"}
            for _ in range(20):
                reply = HealthPublisher._on_history_query(daemon, SimpleNamespace(
                    parameters=params))
                seen += [h["window"] for h in reply["windows"]]
                if not reply["more"]:
                    break
                assert reply["next_after"] is not None, (by, reply)
                params = {**params, "after": repr(reply["next_after"])}
            assert seen == list(range(7)), (by, seen)
