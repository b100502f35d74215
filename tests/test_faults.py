"""Faults of issue #5 not covered elsewhere (CAN bad frames/NaN: test_drivers_can.py; gaps,
NaN windows, overruns, a failing window: test_daemon.py; Modbus down and back:
test_drivers_modbus.py; stall: runner + test_drivers_modbus.py):

* Zenoh unreachable at start and lost mid-run: the daemon starts, estimates and stores every
  window, publishes once a router is there (a Python zenoh session in router mode stands in
  for zenohd), and the history query fills the gap;
* an unwritable Rerun path: a clear error at start, before the device is touched;
* secrets readable by others are refused, naming the file and the fix.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from twinwatch.cli import main
from twinwatch.config.loader import ConfigError, load_config

from .conftest import ROOT
from .test_service import Collector, _env, _write_config, db_rows, get_json, wait_for, zsession
from .test_zenoh_publisher import endpoint, free_port

SIM = (ROOT / "config" / "dc-motor-sim.toml").read_text()


def _client_config(port: int) -> str:
    text = SIM.replace('mode = "peer"', 'mode = "client"')
    text = text.replace('listen = ["tcp/127.0.0.1:7447"]', f'connect = ["{endpoint(port)}"]')
    text = text.replace("\nconnect = []", "\nretry_max = 0.5")
    text = text.replace("duration = 1200.0", "duration = 100000.0\nfault_period = 1200.0")
    return text.replace("[recording]", "[recording]\nenabled = false")


def test_zenoh_unreachable_at_start_and_lost_mid_run(tmp_path: Path) -> None:
    port = free_port()
    cfg = tmp_path / "m.toml"
    _write_config(cfg, _client_config(port))
    db = tmp_path / "state.sqlite"
    proc = subprocess.Popen([sys.executable, "-m", "twinwatch", "run", str(cfg), "--no-progress",
                             "--log-level", "info"], cwd=tmp_path, env=_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    key = "twinwatch/dc-motor-sim"
    try:
        # nobody listens: the daemon runs anyway and stores every window
        wait_for(lambda: len(db_rows(db)) >= 3, 60, "windows stored without zenoh")
        with zsession("router", listen=[endpoint(port)]) as router:
            seen = Collector(router, f"{key}/health")
            wait_for(seen.snapshot, 20, "health once the router is up")
            first_live = min(h["window"] for h in seen.snapshot())
            assert first_live >= 3
            # the history fills the gap: windows 0 .. first_live - 1 were never published
            hist = get_json(router, f"{key}/history?limit=1000")[0]["windows"]
            assert [h["window"] for h in hist[:first_live]] == list(range(first_live))
            assert hist[0]["counters"].get("zenoh_published", 0) == 0
        # the router goes away mid-run: estimation and storage go on
        n = len(db_rows(db))
        wait_for(lambda: len(db_rows(db)) >= n + 3, 30, "windows stored while zenoh is lost")
        assert proc.poll() is None
        with zsession("router", listen=[endpoint(port)]) as router:
            seen = Collector(router, f"{key}/health")
            wait_for(seen.snapshot, 30, "health after the router came back")
            gap_from = n - 1
            back = min(h["window"] for h in seen.snapshot())
            hist = get_json(router, f"{key}/history?t_from={2 * gap_from}")[0]["windows"]
            assert {h["window"] for h in hist} >= set(range(gap_from, back))
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert "nothing answers there" in err and "publishing resumes" in err


def test_unwritable_rerun_path_is_a_clear_error_at_start(tmp_path: Path) -> None:
    cfg = tmp_path / "m.toml"
    missing = tmp_path / "no-such-dir" / "m.rrd"
    cfg.write_text(SIM.replace('path = "twinwatch.rrd"', f'path = "{missing}"')
                   .replace("[zenoh]", "[zenoh]\nenabled = false"))
    r = subprocess.run([sys.executable, "-m", "twinwatch", "run", str(cfg), "--duration", "4"],
                       cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=60)
    assert r.returncode == 1
    assert (f"cannot start: cannot record to {missing}: directory {missing.parent} does not "
            "exist; create it or set [recording].path") in r.stderr
    assert "Traceback" not in r.stderr


def _tls_config(tmp_path: Path, **extra: str) -> Path:
    lines = "".join(f'{k} = "{v}"\n' for k, v in extra.items())
    text = SIM.replace('listen = ["tcp/127.0.0.1:7447"]', 'listen = ["tls/localhost:17448"]')
    text += ('\n[zenoh.tls]\nroot_ca_certificate = "ca.pem"\nlisten_certificate = "srv.pem"\n'
             + ("" if "listen_private_key_base64" in extra
                else 'listen_private_key = "srv.key"\n') + lines)
    cfg = tmp_path / "tls.toml"
    cfg.write_text(text)
    for name in ("ca.pem", "srv.pem", "srv.key"):
        (tmp_path / name).write_text("placeholder\n")
    return cfg


def test_secret_key_file_readable_by_others_is_refused(tmp_path: Path) -> None:
    cfg = _tls_config(tmp_path)
    key = tmp_path / "srv.key"
    key.chmod(0o644)
    with pytest.raises(ConfigError) as exc:
        load_config(cfg)
    assert f"zenoh.tls.listen_private_key = {key} is a secret readable by other users" in str(
        exc.value)
    assert f"chmod o-rwx {key}" in str(exc.value)
    r = CliRunner().invoke(main, ["run", str(cfg)])
    assert r.exit_code == 78 and "readable by other users" in r.output
    key.chmod(0o640)
    loaded = load_config(cfg)  # certificates are public: 0644 is fine for them
    assert loaded.zenoh.tls is not None
    assert loaded.zenoh.tls.root_ca_certificate == str(tmp_path / "ca.pem")  # relative to cfg


def test_config_holding_an_inline_secret_must_not_be_readable_by_others(tmp_path: Path) -> None:
    cfg = _tls_config(tmp_path, listen_private_key_base64="TUlJQ...")
    cfg.chmod(0o644)
    with pytest.raises(ConfigError) as exc:
        load_config(cfg)
    assert "holds secrets (zenoh.tls.listen_private_key_base64)" in str(exc.value)
    assert f"chmod o-rwx {cfg}" in str(exc.value)
    cfg.chmod(0o640)
    assert load_config(cfg).zenoh.inline_secrets() == ["zenoh.tls.listen_private_key_base64"]
    assert os.stat(cfg).st_mode & 0o004 == 0
