"""A source that goes silent: the stall is reported once and recovered, and systemd's watchdog
is pinged only while windows are processed (issue #5, items 1 and 4).

The daemon runs with a real ``Watchdog`` on a datagram socket standing in for systemd
(``WatchdogSec=0.5``: a ping every 0.25 s, pings stop after 0.5 s without a finished window).
The source delivers three windows, falls silent for 1.8 s once the worker has finished them,
then delivers three more. The source itself samples the watchdog's ping count during the silence.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from twinwatch.config.loader import default_config
from twinwatch.daemon.runner import Daemon
from twinwatch.daemon.systemd import Notifier, Watchdog
from twinwatch.drivers.base import Driver, Sample
from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig

SILENCE = 1.8  # s of wall time without a sample
WATCHDOG_SEC = 0.5
#: age of the silence [s] at which the pings are first sampled: 0.5 s after the last ping a
#: quiet watchdog may send (``max_quiet`` = WatchdogSec), 2.4 ping intervals before the last read
MID = 2 * WATCHDOG_SEC


class _SilentDriver(Driver):
    """The nominal plant; after ``silent_after`` samples it stops delivering for ``SILENCE`` s
    (``read`` returns None, as a driver does while its device is quiet), then goes on."""

    channels = ("Va", "ia", "omega", "Tload", "setpoint")

    @classmethod
    def from_config(cls, config, *, base_dir=None):  # type: ignore[no-untyped-def]
        raise NotImplementedError("built by the test, not from a configuration")

    def __init__(self, silent_after: int, watchdog: Watchdog) -> None:
        super().__init__()
        self.plant = DCMotorPlant(DCMotorPlantConfig(scenario="nominal", duration=11.0))
        self.silent_after = silent_after
        self.watchdog = watchdog
        self.daemon: Daemon | None = None
        self.sent = 0
        self.silence: tuple[float, float] | None = None
        self.pings_mid: int | None = None   # pings sent when the silence is MID s old
        self.pings_late: int | None = None  # ... and in its last read

    def _read_internal(self, timeout: float | None) -> Sample | None:
        if self.sent == self.silent_after and self.silence is None:
            assert self.daemon is not None
            while self.daemon.windows_estimated < self.silent_after // 200:  # worker done
                time.sleep(0.01)
            now = time.monotonic()
            self.silence = (now, now + SILENCE)
        if self.silence is not None and time.monotonic() < self.silence[1]:
            time.sleep(min(timeout or 0.2, 0.05))
            age = time.monotonic() - self.silence[0]
            if age >= MID and self.pings_mid is None:
                self.pings_mid = self.watchdog.pings
            if age >= SILENCE - 0.2:
                self.pings_late = self.watchdog.pings
            return None
        self.sent += 1
        if self.silence is not None:
            # after the silence, about real time / 4: acquisition still runs (and pings) when
            # the worker finishes the next windows (unpaced, the source ended first and a 3 ms
            # estimation finished them after the last ping)
            time.sleep(0.0025)
        return self.plant.next_sample()  # EndOfStream at the plant's duration


@pytest.fixture()
def notify_socket(tmp_path: Path) -> Iterator[str]:
    """The socket, read as systemd reads it: unread, its queue (``net.unix.max_dgram_qlen``,
    10 datagrams here) would fill at these pings and the daemon drop the later ones."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path = str(tmp_path / "notify")
    sock.bind(path)
    sock.settimeout(0.05)
    stop = threading.Event()

    def drain() -> None:
        while not stop.is_set():
            try:
                sock.recv(4096)
            except TimeoutError:
                pass

    reader = threading.Thread(target=drain, name="test-systemd-notify")
    reader.start()
    yield path
    stop.set()
    reader.join()
    sock.close()


def _run(policy: str, path: str) -> tuple[Daemon, _SilentDriver, Watchdog]:
    notifier = Notifier(env={"NOTIFY_SOCKET": path,
                             "WATCHDOG_USEC": str(int(WATCHDOG_SEC * 1e6))})
    watchdog = Watchdog(notifier)
    cfg = default_config()
    cfg.acquisition.stall_timeout = 0.5
    cfg.acquisition.watchdog = policy  # type: ignore[assignment]
    driver = _SilentDriver(silent_after=600, watchdog=watchdog)
    with Daemon(cfg, driver=driver, publish=False, record=False, watchdog=watchdog) as daemon:
        driver.daemon = daemon
        daemon.run()
    driver.close()
    notifier.close()
    return daemon, driver, watchdog


def test_pings_stop_while_the_source_is_silent_and_resume_with_windows(
        notify_socket: str, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    daemon, driver, watchdog = _run("windows", notify_socket)
    assert daemon.windows_estimated == 5  # 3 before the silence, 2 after (1101 samples)
    msgs = [r.getMessage() for r in caplog.records]
    # the stall: reported once, with what to check; its end is logged
    assert sum("no sample from the simulated driver" in m for m in msgs) == 1
    assert any("check the device" in m for m in msgs)
    assert sum("delivers samples again after a stall" in m for m in msgs) == 1
    # the watchdog: no ping from MID s into the silence to its end, one error saying why
    assert driver.pings_mid is not None and driver.pings_late is not None
    assert driver.pings_late == driver.pings_mid
    stopped = [m for m in msgs if "no window processed for" in m]
    assert len(stopped) >= 1 and 'watchdog = "alive"' in stopped[0]
    # windows again: pings again
    assert watchdog.pings > driver.pings_late


def test_alive_policy_keeps_pinging_through_a_silent_source(
        notify_socket: str, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    daemon, driver, watchdog = _run("alive", notify_socket)
    assert daemon.windows_estimated == 5
    msgs = [r.getMessage() for r in caplog.records]
    assert sum("no sample from the simulated driver" in m for m in msgs) == 1
    assert driver.pings_mid is not None and driver.pings_late is not None
    assert driver.pings_late > driver.pings_mid  # 0.25 s interval, 0.6 s between the two reads
    assert not any("no window processed for" in m for m in msgs)
