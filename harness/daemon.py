"""The daemon as a user and the unit run it: the simulated motor's example configuration made
short (:func:`sim_config`, :func:`with_driver`), ``twinwatch run`` in a subprocess
(:class:`Service`) and its state database read back (:func:`db_rows`)."""

from __future__ import annotations

import json
import os
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from harness import ROOT

SIM = (ROOT / "config" / "dc-motor-sim.toml").read_text()


def twinwatch_env() -> dict[str, str]:
    """The environment ``twinwatch`` runs in as a subprocess: this checkout first on the path,
    ``CI=true`` (the rerun SDK writes no analytics files)."""
    return dict(os.environ, PYTHONPATH=str(ROOT), CI="true")


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


def with_driver(tmp: Path, driver: str, **kw: Any) -> Path:
    """:func:`sim_config` with its ``[driver]`` tables replaced by ``driver`` (TOML)."""
    path = sim_config(tmp, **kw)
    text = path.read_text()
    start, end = text.index("[driver]"), text.index("[zenoh]")
    path.write_text(text[:start] + driver.strip() + "\n\n" + text[end:])
    return path


class Service:
    """``twinwatch run CONFIG --log-level info`` in a subprocess, as the unit runs it; its stderr
    is read line by line by a thread (a log flood cannot block it on a full pipe).

    Args:
        prelude: Python run in the child before the CLI (e.g. a resource limit).
    """

    #: run CONFIG as a fleet (a directory holding a link to it: the host's directory path,
    #: ``twinwatch-gateway.service``) instead of one file (``twinwatch@.service``)
    fleet = False

    def __init__(self, cfg: Path, cwd: Path, prelude: str = "") -> None:
        target = cfg
        if self.fleet:
            target = cwd / "machines.d"
            target.mkdir(exist_ok=True)
            (target / cfg.name).symlink_to(cfg)
        code = f"import sys\n{prelude}\nfrom twinwatch.cli import main\nmain(sys.argv[1:])\n"
        self.proc = subprocess.Popen(
            [sys.executable, "-c", code, "run", str(target), "--no-progress", "--log-level",
             "info"],
            cwd=cwd, env=twinwatch_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.lines: list[str] = []
        self.stdout = ""
        self._lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, name="stderr-reader", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            with self._lock:
                self.lines.append(line.rstrip("\n"))

    def count(self, *texts: str) -> int:
        """Lines of stderr holding any of ``texts``."""
        with self._lock:
            return sum(any(t in ln for t in texts) for ln in self.lines)

    def wait_for(self, *texts: str, n: int = 1, timeout: float = 60.0) -> bool:
        """True once ``n`` lines hold one of ``texts``; False on timeout or when it exits."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.count(*texts) >= n:
                return True
            if self.proc.poll() is not None:
                self._reader.join(timeout=10)
                return self.count(*texts) >= n
            time.sleep(0.02)
        return False

    def send(self, signum: int) -> None:
        self.proc.send_signal(signum)

    def wait(self, timeout: float) -> int | None:
        """Its exit status, or None if it still runs after ``timeout`` [s]."""
        try:
            return self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return None

    def open_files(self) -> int:
        """Descriptors the process has open (/proc/PID/fd)."""
        return len(os.listdir(f"/proc/{self.proc.pid}/fd"))

    def close(self) -> None:
        """Kill it if it still runs; keep its stdout (the summary)."""
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self._reader.join(timeout=10)
        assert self.proc.stdout is not None and self.proc.stderr is not None
        self.stdout = self.proc.stdout.read()
        self.proc.stdout.close()
        self.proc.stderr.close()


def endless_sim(tmp: Path, **replace: str) -> Path:
    """The simulated motor running until stopped (its armature replaced every 1200 s)."""
    return sim_config(tmp, duration=100000.0,
                      **{"# fault_period = 1200.0": "fault_period = 1200.0"}, **replace)


def db_rows(path: Path, run: str | None = None) -> list[dict[str, Any]]:
    """Health rows of the state database (read-only, while the daemon may be writing)."""
    if not path.exists():
        return []
    for attempt in range(50):
        con = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=5)
        try:
            sql = "SELECT run, doc FROM health ORDER BY id"
            rows = [(r, json.loads(d)) for r, d in con.execute(sql)]
            break
        except sqlite3.OperationalError as exc:
            if "no such table" in str(exc):  # tables not created yet
                return []
            # busy or not openable while a daemon opens or recovers the database: read again
            # (read as no rows, a resume test took 95 stored windows for 0 and stopped its
            # next run before it stored any)
            if attempt == 49:
                raise
            time.sleep(0.1)
        finally:
            con.close()
    return [d | {"_run": r} for r, d in rows if run is None or r == run]
