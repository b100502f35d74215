"""The systemd unit (``systemd/twinwatch@.service``) and the sd_notify client
(``twinwatch/daemon/systemd.py``).

The unit is checked with ``systemd-analyze verify`` (empty stderr required) and scored with
``systemd-analyze security --offline=true`` (measured 1.5 "OK" with systemd 252); the notifier
is tested against a real AF_UNIX datagram socket standing in for systemd.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from twinwatch.daemon.systemd import Notifier, Watchdog

ROOT = Path(__file__).resolve().parents[1]
UNIT = ROOT / "systemd" / "twinwatch@.service"
GATEWAY_UNIT = ROOT / "systemd" / "twinwatch-gateway.service"
UNITS = pytest.mark.parametrize("unit_file", [UNIT, GATEWAY_UNIT], ids=["instance", "gateway"])
INSTALLED_EXEC = "/opt/twinwatch/bin/twinwatch"
MAX_EXPOSURE = 2.0  # measured 1.5; what is left is the network, AF_CAN and numba's W+X pages

needs_analyze = pytest.mark.skipif(shutil.which("systemd-analyze") is None,
                                   reason="systemd-analyze is not installed")


def _unit_with_exec(tmp_path: Path, unit_file: Path = UNIT) -> Path:
    """Copy the unit to tmp_path with ExecStart pointing at an executable that exists here
    (the venv's console script if installed, else a stub): verify resolves the binary."""
    real = Path(sys.executable).with_name("twinwatch")
    if real.exists():
        exe = real
    else:
        exe = tmp_path / "twinwatch"
        exe.write_text("#!/bin/sh\nexit 0\n")
        exe.chmod(0o755)
    text = unit_file.read_text()
    assert f"ExecStart={INSTALLED_EXEC} run " in text
    (tmp_path / unit_file.name).write_text(text.replace(INSTALLED_EXEC, str(exe)))
    return tmp_path / ("twinwatch@m1.service" if unit_file == UNIT else unit_file.name)


@needs_analyze
@UNITS
def test_unit_verifies_cleanly(tmp_path: Path, unit_file: Path) -> None:
    unit = _unit_with_exec(tmp_path, unit_file)
    r = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True,
                       text=True, timeout=60, cwd=tmp_path)
    assert r.stderr == "", r.stderr
    assert r.returncode == 0


@needs_analyze
@UNITS
def test_unit_security_exposure(tmp_path: Path, unit_file: Path) -> None:
    unit = _unit_with_exec(tmp_path, unit_file)
    r = subprocess.run(["systemd-analyze", "security", "--offline=true", "--no-pager",
                        str(unit)], capture_output=True, text=True, timeout=60, cwd=tmp_path)
    m = re.search(r"Overall exposure level for \S+: ([0-9.]+) (\w+)", r.stdout)
    assert m, r.stdout + r.stderr
    score = float(m.group(1))
    print(f"systemd-analyze security --offline=true: exposure {score} {m.group(2)}")
    print("\n".join(line for line in r.stdout.splitlines() if line.startswith("\u2717")))
    assert score < MAX_EXPOSURE


def test_unit_settings() -> None:
    """What the issue asks of the unit, and what must not be there."""
    keys: dict[str, list[str]] = {}
    for line in UNIT.read_text().splitlines():
        if "=" in line and not line.startswith(("#", "[")):
            k, v = line.split("=", 1)
            keys.setdefault(k, []).append(v)
    one = {k: v[-1] for k, v in keys.items()}
    assert one["Type"] == "notify" and one["Restart"] == "on-failure"
    assert one["ExecReload"] == "/bin/kill -HUP $MAINPID"
    assert one["CapabilityBoundingSet"] == "" and one["NoNewPrivileges"] == "yes"
    assert one["User"] == "twinwatch" and one["ProtectSystem"] == "strict"
    assert one["WorkingDirectory"] == "%S/twinwatch/%i" and one["StateDirectory"] == "twinwatch/%i"
    assert "AF_CAN" in one["RestrictAddressFamilies"]
    assert any(v.startswith("NUMBA_CACHE_DIR=%C/twinwatch/%i") for v in keys["Environment"])
    assert "MemoryDenyWriteExecute" not in keys  # numba needs W->X pages: see the next test


def test_gateway_unit_settings() -> None:
    """The gateway unit runs a directory of machines, with the instance unit's hardening."""
    def settings(path: Path) -> dict[str, list[str]]:
        keys: dict[str, list[str]] = {}
        for line in path.read_text().splitlines():
            if "=" in line and not line.startswith(("#", "[")):
                k, v = line.split("=", 1)
                keys.setdefault(k, []).append(v)
        return keys

    gw, inst = settings(GATEWAY_UNIT), settings(UNIT)
    one = {k: v[-1] for k, v in gw.items()}
    assert one["ExecStart"].endswith(" /etc/twinwatch/machines.d")
    assert one["AssertDirectoryNotEmpty"] == "/etc/twinwatch/machines.d"
    assert one["WorkingDirectory"] == "%S/twinwatch/gateway"
    assert any(v == "NUMBA_CACHE_DIR=%C/twinwatch/gateway/numba" for v in gw["Environment"])
    assert one["Type"] == "notify" and one["RestartPreventExitStatus"] == "78"
    hardening = ("NoNewPrivileges", "CapabilityBoundingSet", "ProtectSystem", "ProtectHome",
                 "PrivateDevices", "RestrictAddressFamilies", "SystemCallFilter", "User",
                 "UMask", "RestrictNamespaces", "PrivateTmp", "ProtectKernelTunables")
    for k in hardening:
        assert gw[k] == inst[k], k
    assert "MemoryDenyWriteExecute" not in gw


@UNITS
def test_exec_start_flags_exist(unit_file: Path) -> None:
    """The flags ExecStart passes are accepted by ``twinwatch run``."""
    from click.testing import CliRunner

    from twinwatch.cli import main

    exec_start = next(line for line in unit_file.read_text().splitlines()
                      if line.startswith("ExecStart="))
    flags = [a for a in exec_start.split()[2:] if a.startswith("--")]
    help_text = CliRunner().invoke(main, ["run", "--help"]).output
    for flag in flags:
        assert flag in help_text, flag


_MDWE_CHILD = """
import ctypes, sys
libc = ctypes.CDLL(None, use_errno=True)
if libc.prctl(65, 1, 0, 0, 0) != 0:   # PR_SET_MDWE, PR_MDWE_REFUSE_EXEC_GAIN
    sys.exit(3)
import numba
"""


def test_numba_needs_writable_then_executable_memory() -> None:
    """Why the unit does not set MemoryDenyWriteExecute=yes: under the kernel's equivalent
    (PR_SET_MDWE, Linux >= 6.3) numba cannot even be imported."""
    r = subprocess.run([sys.executable, "-c", _MDWE_CHILD], capture_output=True, text=True,
                       timeout=60)
    if r.returncode == 3:
        pytest.skip("this kernel has no PR_SET_MDWE")
    assert r.returncode != 0
    assert "cannot allocate executable memory" in r.stderr


def _recv(sock: socket.socket) -> dict[str, str]:
    data = sock.recv(4096).decode()
    return dict(line.split("=", 1) for line in data.split("\n"))


@pytest.fixture
def systemd_socket(tmp_path: Path) -> Iterator[tuple[socket.socket, str]]:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path = str(tmp_path / "notify")
    sock.bind(path)
    sock.settimeout(2.0)
    yield sock, path
    sock.close()


def test_messages_reach_the_socket(systemd_socket: tuple[socket.socket, str]) -> None:
    sock, path = systemd_socket
    with Notifier(env={"NOTIFY_SOCKET": path}) as n:
        assert n.enabled and n.watchdog_interval is None
        n.status("window 12")
        assert sock.recv(4096) == b"STATUS=window 12"
        n.watchdog()
        assert sock.recv(4096) == b"WATCHDOG=1"
        n.stopping()
        assert sock.recv(4096) == b"STOPPING=1"
        n.extend_timeout(1.5)
        assert sock.recv(4096) == b"EXTEND_TIMEOUT_USEC=1500000"
        before = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
        n.reloading(status="reloading /etc/twinwatch/m1.toml")
        lines = sock.recv(4096).decode().split("\n")
        after = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
        assert lines[0] == "RELOADING=1"
        assert lines[1].startswith("MONOTONIC_USEC=")
        assert before <= int(lines[1].split("=")[1]) <= after
        assert lines[2] == "STATUS=reloading /etc/twinwatch/m1.toml"


def test_ready_is_one_datagram(systemd_socket: tuple[socket.socket, str]) -> None:
    sock, path = systemd_socket
    with Notifier(env={"NOTIFY_SOCKET": path}) as n:
        n.ready(status="monitoring\nm1")
        assert sock.recv(4096) == b"READY=1\nSTATUS=monitoring m1"


def test_abstract_socket() -> None:
    name = f"twinwatch-test-{os.getpid()}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    sock.settimeout(2.0)
    try:
        with Notifier(env={"NOTIFY_SOCKET": "@" + name}) as n:
            assert n.ready()
            assert sock.recv(4096) == b"READY=1"
    finally:
        sock.close()


def test_noop_outside_systemd() -> None:
    n = Notifier(env={})
    assert not n.enabled and n.watchdog_interval is None
    assert not n.ready() and not n.watchdog() and not n.stopping()
    wd = Watchdog(n)
    assert not wd.enabled and not wd.tick()


def test_unreachable_socket_does_not_raise(tmp_path: Path, caplog: pytest.LogCaptureFixture
                                           ) -> None:
    with Notifier(env={"NOTIFY_SOCKET": str(tmp_path / "absent")}) as n:
        assert not n.ready()
        assert not n.watchdog()
    warnings = [r for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and "cannot notify systemd" in warnings[0].getMessage()


def test_watchdog_interval_is_half_of_watchdog_sec() -> None:
    n = Notifier(env={"NOTIFY_SOCKET": "/x", "WATCHDOG_USEC": "30000000"})
    assert n.watchdog_interval == 15.0
    mine = Notifier(env={"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": str(os.getpid())})
    assert mine.watchdog_interval == 15.0
    other = Notifier(env={"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": "1"})
    assert other.watchdog_interval is None
    assert Notifier(env={"WATCHDOG_USEC": "junk"}).watchdog_interval is None


def test_watchdog_pings_at_interval_and_stops_when_worker_stuck(
        systemd_socket: tuple[socket.socket, str]) -> None:
    sock, path = systemd_socket
    now = [100.0]
    n = Notifier(env={"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "10000000"})  # WatchdogSec=10
    wd = Watchdog(n, clock=lambda: now[0])
    assert wd.interval == 5.0 and wd.max_busy == 10.0
    assert wd.tick()                       # first tick pings
    assert sock.recv(4096) == b"WATCHDOG=1"
    now[0] += 4.9
    assert not wd.tick()                   # not due yet
    now[0] += 0.2
    wd.busy()                              # worker starts a window
    assert wd.tick()                       # due, worker busy for 0 s: fine
    sock.recv(4096)
    now[0] += 11.0                         # the window has taken 11 s > WatchdogSec
    assert not wd.healthy() and not wd.tick()
    wd.idle()
    assert wd.tick() and wd.pings == 3
    n.close()


def test_watchdog_pings_only_while_windows_finish(
        systemd_socket: tuple[socket.socket, str]) -> None:
    sock, path = systemd_socket
    now = [0.0]
    n = Notifier(env={"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "10000000"})  # WatchdogSec=10
    strict = Watchdog(n, clock=lambda: now[0])
    alive = Watchdog(n, clock=lambda: now[0], require_windows=False)
    assert strict.max_quiet == 10.0
    assert strict.tick() and alive.tick()  # start-up: the quiet clock starts at the first tick
    now[0] = 9.0
    assert strict.tick() and alive.tick()  # no window yet, but within WatchdogSec
    strict.busy(), strict.idle()           # a window finishes at 9 s
    now[0] = 18.9
    assert strict.tick() and alive.tick()
    now[0] = 19.5                          # 10.5 s without a finished window
    assert not strict.healthy() and alive.healthy()
    now[0] = 24.0                          # a ping is due
    assert not strict.tick() and alive.tick()
    strict.busy()                          # a window is being processed: the busy limit applies
    assert strict.healthy()
    strict.idle()
    assert strict.tick()
    sock.settimeout(0.1)  # the pings were sent before tick() returned: drain what is queued
    while True:
        try:
            sock.recv(4096)
        except TimeoutError:
            break
    n.close()


def test_a_full_notification_queue_drops_pings_and_never_blocks(
        systemd_socket: tuple[socket.socket, str], caplog: pytest.LogCaptureFixture) -> None:
    """Nobody reads the socket (a Unix datagram socket queues 10 by default): a blocking
    sendto hung a daemon's acquisition thread for good once the queue was full. The pings
    and STATUS lines beyond it are dropped and counted, the warning logged once; a state
    change waits up to ``STATE_WAIT`` for room, then is dropped too; once read again, they
    pass."""
    import threading

    from twinwatch.daemon import systemd

    caplog.set_level("INFO", logger="twinwatch.daemon.systemd")
    sock, path = systemd_socket
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    results: list[bool] = []
    # not closed on a failure: close() would wait for the lock of a blocked sender
    n = Notifier(env={"NOTIFY_SOCKET": path})
    def flood() -> None:
        results.extend(n.watchdog() for _ in range(200))
        results.append(n.status("still here"))
    t = threading.Thread(target=flood, daemon=True)
    t.start()
    t.join(30.0)
    assert not t.is_alive(), "a notification blocked on the full queue"
    sent = sum(results)
    assert 1 <= sent < 200 and n.dropped == len(results) - sent
    warnings = [r for r in caplog.records if "queue is full" in r.getMessage()]
    assert len(warnings) == 1 and warnings[0].levelname == "WARNING"
    received = 0
    sock.settimeout(0.1)
    with contextlib.suppress(TimeoutError):
        while True:
            sock.recv(4096)
            received += 1
    assert received == sent  # what was not dropped arrived
    assert n.status("read again") and sock.recv(4096) == b"STATUS=read again"
    assert any("reads its notifications again (" in r.getMessage()
               for r in caplog.records)
    # a state change waits for room (STATE_WAIT), then is dropped too: never blocks
    while n.watchdog():
        pass
    systemd.STATE_WAIT, saved = 0.2, systemd.STATE_WAIT
    try:
        assert not n.stopping()
    finally:
        systemd.STATE_WAIT = saved
    n.close()
