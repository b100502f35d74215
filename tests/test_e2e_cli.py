"""The README's first command, end to end, as a user runs it: ``twinwatch run`` with the
built-in default (simulated DC motor over virtual CAN, health on tcp/127.0.0.1:7447,
recording to ./twinwatch.rrd), a separate process receiving the health over Zenoh, and
``rerun rrd verify`` accepting the recording, also after SIGTERM."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from .helpers.cli import rerun_exe

SUBSCRIBER = r"""
import json, sys, time, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"client"')
conf.insert_json5("connect/endpoints", '["tcp/127.0.0.1:7447"]')
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("scouting/gossip/enabled", "false")
deadline = time.monotonic() + 60
session = None
while session is None:
    try:
        session = zenoh.open(conf)
    except Exception:
        if time.monotonic() > deadline:
            raise
        time.sleep(0.1)
got = []
with session:
    sub = session.declare_subscriber("twinwatch/*/health")
    while len(got) < 3 and time.monotonic() < deadline:
        s = sub.try_recv()
        if s is None:
            time.sleep(0.01)
            continue
        got.append(json.loads(s.payload.to_string()))
    latest = [json.loads(r.ok.payload.to_string())
              for r in session.get("twinwatch/dc-motor-sim/health", timeout=5.0)
              if r.ok is not None]
    alive = [str(r.ok.key_expr) for r in session.liveliness().get("twinwatch/*/alive",
                                                                  timeout=5.0) if r.ok]
    sub.undeclare()
print(json.dumps({"health": got, "latest": latest, "alive": alive}))
"""


def _port_free(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) != 0


def _stored(db: Path) -> int:
    """Health rows in the state database (0 before it exists)."""
    import sqlite3

    if not db.exists():
        return 0
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5)
    try:
        return int(con.execute("SELECT COUNT(*) FROM health").fetchone()[0])
    except sqlite3.OperationalError:
        return 0
    finally:
        con.close()


def _twinwatch(*args: str) -> list[str]:
    return [sys.executable, "-m", "twinwatch", *args]


@pytest.fixture
def env() -> dict[str, str]:
    e = dict(os.environ, CI="true")
    e["PYTHONPATH"] = str(Path(__file__).resolve().parents[1])
    return e


@pytest.mark.slow
def test_readme_first_command_publishes_health_to_another_process(tmp_path: Path, env):
    if not _port_free(7447):
        pytest.skip("tcp/127.0.0.1:7447 is in use (another twinwatch or zenoh peer runs)")
    # 300 s of plant time: long enough for the subscriber to connect while it runs.
    daemon = subprocess.Popen(_twinwatch("run", "--duration", "300", "--no-progress"),
                              cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
    try:
        sub = subprocess.run([sys.executable, "-c", SUBSCRIBER], capture_output=True,
                             text=True, timeout=120, env=env)
        out, err = daemon.communicate(timeout=300)
    finally:
        if daemon.poll() is None:
            daemon.kill()
            daemon.wait()
    assert sub.returncode == 0, sub.stderr
    received = json.loads(sub.stdout.strip().splitlines()[-1])
    assert len(received["health"]) == 3
    h = received["health"][0]
    assert h["machine"] == "dc-motor-sim"
    for key in ("window", "t_start", "t_end", "parameters", "rmse", "elapsed_s"):
        assert key in h
    ra = h["parameters"]["Ra"]
    assert {"value", "unit", "nominal", "deviation_pct", "held", "reason"} <= set(ra)
    assert ra["unit"] == "ohm" and ra["nominal"] == 6.5
    assert set(h["rmse"]) == {"ia", "omega", "Va"}
    assert received["latest"] and received["latest"][0]["machine"] == "dc-motor-sim"
    assert received["alive"] == ["twinwatch/dc-motor-sim/alive"]
    assert daemon.returncode == 0, err
    assert "150 windows estimated" in out
    rrd = tmp_path / "twinwatch.rrd"
    assert rrd.stat().st_size > 0
    verify = subprocess.run([rerun_exe(), "rrd", "verify", str(rrd)], capture_output=True,
                            text=True, env=env, timeout=120)
    assert verify.returncode == 0, verify.stderr


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_recording_is_valid_after_a_signal(tmp_path: Path, env, sig):
    cfg = tmp_path / "sim.toml"
    text = (Path(__file__).resolve().parents[1] / "config" / "dc-motor-sim.toml").read_text()
    text = text.replace("[zenoh]", "[zenoh]\nenabled = false")  # no port: runs beside others
    cfg.write_text(text)
    daemon = subprocess.Popen(_twinwatch("run", str(cfg), "--no-progress", "--log-level",
                                         "info"),
                              cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
    rrd = tmp_path / "twinwatch.rrd"
    db = tmp_path / "state.sqlite"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and _stored(db) < 2:  # mid-run: windows are estimated
        time.sleep(0.1)
    t0 = time.monotonic()
    daemon.send_signal(sig)
    out, err = daemon.communicate(timeout=60)
    stop_s = time.monotonic() - t0
    assert daemon.returncode == 0, err
    assert "received: finishing the queued windows and stopping" in err
    # bounded: the queued windows (acquisition.queue = 4, about 0.1 s each) and the sinks
    assert stop_s < 15, f"took {stop_s:.1f} s to stop"
    # every estimated window is in the state database, which was closed cleanly (no WAL left)
    import re

    estimated = int(re.search(r"(\d+) windows estimated", out).group(1))  # type: ignore[union-attr]
    assert _stored(db) == estimated >= 2
    assert "recording of dc-motor-sim closed" in err and "zenoh" not in out
    verify = subprocess.run([rerun_exe(), "rrd", "verify", str(rrd)], capture_output=True,
                            text=True, env=env, timeout=120)
    assert verify.returncode == 0, verify.stderr


@pytest.mark.slow  # about 11 s on the shared 2-core box: out of the fast lane
def test_a_commissioning_configuration_is_refused_by_run_and_warns_with_force(
        tmp_path: Path, env):
    """Issue 23 item 6: `[machine] purpose = "commissioning"` (the MotoShield's raw and
    board-2 files, for `twinwatch identify`, against generic nominal values) is refused by
    `run`, naming the key, with exit 78 and nothing stored; with --force it runs and says what
    it is before the first window is published."""
    text = (Path(__file__).resolve().parents[1] / "config" / "dc-motor-sim.toml").read_text()
    text = text.replace("[zenoh]", "[zenoh]\nenabled = false")
    text = text.replace('name = "dc-motor-sim"',
                        'name = "dc-motor-sim"\npurpose = "commissioning"', 1)
    assert 'purpose = "commissioning"' in text
    cfg = tmp_path / "commissioning.toml"
    cfg.write_text(text)
    refused = subprocess.run(_twinwatch("run", str(cfg), "--no-progress"), cwd=tmp_path,
                             env=env, capture_output=True, text=True, timeout=120)
    assert refused.returncode == 78, refused.stderr
    assert 'purpose = "commissioning"' in refused.stderr and "--force" in refused.stderr
    assert not (tmp_path / "state.sqlite").exists()
    forced = subprocess.run(_twinwatch("run", str(cfg), "--no-progress", "--force",
                                       "--duration", "4"), cwd=tmp_path, env=env,
                            capture_output=True, text=True, timeout=120)
    assert forced.returncode == 0, forced.stderr
    # said at load, before the daemon opens (so before anything is published)
    assert "is not this machine's health" in forced.stderr
    assert "2 windows estimated" in forced.stdout + forced.stderr
    assert _stored(tmp_path / "state.sqlite") == 2
    for shipped in ("dc-motor-motoshield-raw.toml", "dc-motor-motoshield-board2.toml"):
        from twinwatch.config.loader import load_config
        path = Path(__file__).resolve().parents[1] / "config" / shipped
        assert load_config(path).machine.purpose == "commissioning"
