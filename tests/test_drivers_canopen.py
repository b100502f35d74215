"""The CANopen driver (drivers/canopen.py) and the simulated CiA 402 drive (issue 38, part 2).

Frames are put on an in-process python-can ``virtual`` bus by hand (the master's SYNC and
RPDO1, the drive's TPDOs, EMCY, heartbeat) with the time stamps a bus would give them; the
driver decodes them from the shipped EDS (twinwatch/plant/dcmotor-cia402.eds). A listener on the
same bus checks that the driver sends nothing.
"""

from __future__ import annotations

import ast
import itertools
import math
import struct
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from click.testing import CliRunner

from twinwatch.cli import main
from twinwatch.drivers import DriverConfigError, create_driver
from twinwatch.drivers.canopen import CanopenDriver, CanopenDriverConfig, load_plan
from twinwatch.plant.canopen_drive import drive_eds_path

ROOT = Path(__file__).resolve().parents[1]
EDS = "twinwatch:plant/dcmotor-cia402.eds"
NODE = 5
MRPM = 2 * math.pi / 60 / 1000  # 0.001 rev/min -> rad/s
_channels = itertools.count()

CHANNELS = {
    "Va": {"object": "0x2100", "factor": "mV", "unit": "V"},
    "ia": {"object": "Current actual value", "factor": "per_mille_rated_current", "unit": "A"},
    "omega": {"object": "0x606Csub0", "factor": "0.001rpm", "unit": "rad/s"},
    "setpoint": {"object": "0x60FF", "factor": MRPM, "unit": "rad/s"},
}


def _config(channel: str, **over: Any) -> dict[str, Any]:
    table: dict[str, Any] = {"type": "canopen", "interface": "virtual", "channel": channel,
                             "node_id": NODE, "eds": EDS, "sample_period": 0.01,
                             "channels": dict(CHANNELS)}
    table.update(over)
    return table


class Cell:
    """A master and a drive (node ``NODE``) as raw frames on a virtual bus."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
        self.sent = 0
        self.k = 0

    def send(self, cob: int, data: bytes, t: float) -> None:
        self.bus.send(can.Message(arbitration_id=cob, data=data, is_extended_id=False,
                                  timestamp=t))
        self.sent += 1

    def cycle(self, *, omega: float = 10.0, ia: float = 1.0, va: float = 12.0,
              setpoint: float = 10.0, status: int = 0x0237, node: int = NODE,
              tpdo2: bytes | None = None, sync: bool = True, heartbeat: bool = True,
              send_tpdo2: bool = True) -> float:
        """One SYNC period: SYNC (counter), RPDO1, TPDO1, TPDO2, heartbeat every 10th."""
        t = self.k * 0.01
        if sync:
            self.send(0x80, bytes([self.k % 240 + 1]), t)
        self.send(0x200 + node, struct.pack("<Hl", 0x000F, round(setpoint / MRPM)), t + 1e-5)
        self.send(0x180 + node, struct.pack("<Hl", status, round(omega / MRPM)), t + 2e-5)
        if tpdo2 is None:
            tpdo2 = struct.pack("<hl", round(ia / 0.004), round(va * 1000))
        if send_tpdo2:
            self.send(0x280 + node, tpdo2, t + 3e-5)
        if heartbeat and self.k % 10 == 0:
            self.send(0x700 + node, b"\x05", t + 4e-5)
        self.k += 1
        return t

    def close(self) -> None:
        self.bus.shutdown()


@pytest.fixture
def cell() -> Any:
    channel = f"test-canopen-{next(_channels)}"
    c = Cell(channel)
    listener = can.Bus(interface="virtual", channel=channel)
    c.channel = channel  # type: ignore[attr-defined]
    c.listener = listener  # type: ignore[attr-defined]
    yield c
    c.close()
    listener.shutdown()


def _read(driver: CanopenDriver, n: int) -> list[Any]:
    out = []
    for _ in range(n):
        s = driver.read(timeout=0.5)
        assert s is not None, driver.stats.as_dict()
        out.append(s)
    return out


def _heard(listener: can.BusABC) -> list[can.Message]:
    frames = []
    while (m := listener.recv(0.05)) is not None:
        frames.append(m)
    return frames


# -- the plan from the EDS --------------------------------------------------------------------

def test_the_pdo_mapping_is_read_from_the_eds():
    cfg = CanopenDriverConfig.model_validate(_config("x")).resolved(Path("."))
    plan = load_plan(cfg)
    assert plan.channels == {
        "Va": "TPDO2 0x2100 Armature voltage", "ia": "TPDO2 0x6078 Current actual value",
        "omega": "TPDO1 0x606C Velocity actual value", "setpoint": "RPDO1 0x60FF Target velocity"}
    assert {p.name: hex(p.cob_id) for p in plan.all_pdos.values()} == {
        "TPDO1": "0x185", "TPDO2": "0x285", "TPDO3": "0x385", "RPDO1": "0x205"}
    assert plan.all_pdos["TPDO3"].trans_type == 10
    assert plan.sync_id == 0x80 and plan.sync_counter == 240 and plan.heartbeat_s == 0.1
    assert plan.all_pdos["TPDO1"].statusword is not None  # 0x6041 mapped: its fault bit read
    # another node id moves every COB-ID ($NODEID in the EDS)
    other = load_plan(CanopenDriverConfig.model_validate(_config("x", node_id=9)).resolved(
        Path(".")))
    assert other.all_pdos["TPDO1"].cob_id == 0x189


# -- decoding ----------------------------------------------------------------------------------

def test_samples_are_scaled_to_si_and_stamped_by_sync_and_nothing_is_sent(cell):
    driver = CanopenDriver.from_config(_config(cell.channel), base_dir=Path("."))
    try:
        for k in range(20):
            cell.cycle(omega=10.0 + k, ia=1.0 + 0.1 * k, va=12.0 - 0.01 * k,
                       setpoint=15.0)
        samples = _read(driver, 20)
    finally:
        driver.close()
    assert [round(s.t, 6) for s in samples] == [round(0.01 * k, 6) for k in range(20)]
    last = samples[-1].values
    assert last["omega"] == pytest.approx(29.0, abs=MRPM)
    assert last["ia"] == pytest.approx(2.9, abs=0.004)  # per mille of 4 A: 4 mA steps
    assert last["Va"] == pytest.approx(11.81, abs=1e-3)
    assert last["setpoint"] == pytest.approx(15.0, abs=MRPM)
    stats = driver.stats.as_dict()
    assert stats["gaps"] == 0 and stats["bad_frames"] == 0 and stats["samples"] == 20
    # passive: the listener heard the cell's frames and nothing else
    heard = _heard(cell.listener)
    assert len(heard) == cell.sent
    assert {m.arbitration_id for m in heard} == {0x80, 0x205, 0x185, 0x285, 0x705}


def test_a_live_bus_is_read_in_batches_losing_and_reordering_nothing(cell, monkeypatch):
    """Frames that come one by one at the drive's pace: once the read has caught up with the
    bus it sleeps ``BATCH_S`` and takes the frames queued meanwhile (one wake-up a batch, not
    one a frame); every sample comes, in order, with its own SYNC's time stamp."""
    import threading
    import time

    from twinwatch.drivers import base, canbus

    naps: list[float] = []
    sleep = time.sleep

    def nap(seconds: float) -> None:
        if threading.current_thread() is threading.main_thread():
            naps.append(seconds)
        sleep(seconds)

    monkeypatch.setattr(canbus.time, "sleep", nap)
    n = 60

    def drive() -> None:
        for k in range(n):
            cell.cycle(omega=10.0 + k)
            sleep(0.01)

    driver = CanopenDriver.from_config(_config(cell.channel), base_dir=Path("."))
    sender = threading.Thread(target=drive)
    try:
        sender.start()
        samples = _read(driver, n)
    finally:
        sender.join()
        driver.close()
    assert [round(s.t, 6) for s in samples] == [round(0.01 * k, 6) for k in range(n)]
    assert [s.values["omega"] for s in samples] == pytest.approx(
        [10.0 + k for k in range(n)], abs=MRPM)
    assert driver.stats.as_dict()["gaps"] == 0
    # about 0.6 s of frames (240) read in a few batches, not one wake-up a frame
    assert naps and all(0 < s <= base.BATCH_S for s in naps)
    assert len(naps) <= 0.6 / base.BATCH_S + 5, naps


def test_a_node_id_that_never_speaks_while_another_does_is_one_line_naming_it(cell, caplog):
    """Issue 56: node_id = 6 on a bus where node 5 sends: one WARNING naming node 5 and the
    key (before: six warnings that node 6 was off the bus, none saying node 5 was on it);
    STATUS's silent says it too. The live bus's receive filter lets every heartbeat in."""
    import logging

    caplog.set_level(logging.INFO, logger="twinwatch.drivers.canopen")
    driver = CanopenDriver.from_config(_config(cell.channel, node_id=6), base_dir=Path("."))
    try:
        for _ in range(300):  # 3 s: the heartbeat and every PDO long missing
            cell.cycle()
        frames = -1
        while driver.stats.frames != frames:  # until every frame queued is read
            frames = driver.stats.frames
            assert driver.read(timeout=0.05) is None
        silent = driver.silent
    finally:
        driver.close()
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1, warnings
    assert warnings[0].startswith("CANopen node 6 not heard on the bus") and \
        "node 5 (heartbeat 0x705)" in warnings[0] and "driver.node_id" in warnings[0]
    assert silent[0] == "node 6 never heard (heard on the bus: node 5 (heartbeat 0x705))"
    assert driver.stats.extra["silent_pdos"] == 3  # still counted


def test_the_right_node_id_hears_no_such_line(cell, caplog):
    driver = CanopenDriver.from_config(_config(cell.channel), base_dir=Path("."))
    try:
        for _ in range(50):
            cell.cycle()
        assert len(_read(driver, 49)) == 49
    finally:
        driver.close()
    assert "not heard" not in caplog.text and driver.silent == ()


def test_a_silent_bus_is_one_error_line_however_often_it_is_reopened(cell, caplog):
    """Issue 56: the bus goes silent under a running acquisition: the source keeper says it
    once at ERROR; opened again (a virtual interface always opens) and silent again, it is
    the same outage, until a sample comes (before: an ERROR and a WARNING every reopen, and
    the acquisition loop's generic ERROR besides). The stall line is INFO, naming it."""
    import logging
    import threading
    import time

    from twinwatch.config.loader import default_config
    from twinwatch.daemon.acquisition import Acquisition
    from twinwatch.daemon.source import open_source
    from twinwatch.twin.models import create_model

    caplog.set_level(logging.INFO)
    cfg = default_config()
    cfg.acquisition.stall_timeout = 0.5
    dcfg = CanopenDriverConfig.model_validate(_config(cell.channel, reopen_after=0.3))
    keeper = open_source(dcfg, base_dir=Path("."), wait=True, backoff_max=0.2)
    acq = Acquisition(cfg, create_model(cfg.machine.model, {}), own_driver=False)
    acq.open(keeper, base_dir=Path("."), wait=False)
    runner = threading.Thread(target=acq.run, args=(None, lambda w, b: None, lambda n: None))
    runner.start()

    def until(what: Any) -> None:
        deadline = time.monotonic() + 30
        while not what() and time.monotonic() < deadline:
            time.sleep(0.05)

    try:
        for _ in range(20):
            cell.cycle()
        until(lambda: keeper.stats.extra.get("reopens", 0) >= 3  # silent after each reopen
              and "no sample from" in caplog.text)
        for _ in range(50):
            cell.cycle()
        until(lambda: "is open again" in caplog.text)
    finally:
        acq.stop()
        # the loop sees the stop when its read returns (within its read timeout): the bus
        # talks until then, or its silence would be a second outage
        deadline = time.monotonic() + 10
        while runner.is_alive() and time.monotonic() < deadline:
            cell.cycle()
            runner.join(0.01)
        keeper.close()
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "is not available (no CAN frame for" in errors[0], errors
    assert sum("is open again" in r.getMessage() for r in caplog.records) == 1
    stall = [r for r in caplog.records if r.getMessage().startswith("no sample from")]
    assert len(stall) == 1 and stall[0].levelno == logging.INFO


def test_frames_of_other_nodes_are_ignored_and_a_truncated_pdo_is_counted(cell):
    # a bus handed in (no receive filter: a live bus opened by the driver filters in the
    # interface, where python-can can): every frame reaches the driver
    rx = can.Bus(interface="virtual", channel=cell.channel)
    driver = CanopenDriver.from_config(_config(cell.channel), base_dir=Path("."), bus=rx)
    try:
        cell.cycle(omega=10.0)
        # node 6's PDOs (the same layout, other COB-IDs) in the same cycles: not ours
        cell.k -= 1
        cell.cycle(omega=99.0, node=6, sync=False)
        first = _read(driver, 1)[0]
        cell.cycle(omega=11.0, tpdo2=b"\x10\x00\x00")  # 3 of its 6 bytes: truncated
        cell.cycle(omega=12.0)
        second = _read(driver, 1)[0]
    finally:
        driver.close()
        rx.shutdown()
    assert first.values["omega"] == pytest.approx(10.0, abs=MRPM)
    # the cycle with the truncated TPDO2 gave no sample; the next one did, node 6 ignored
    assert second.t == pytest.approx(0.02) and second.values["omega"] == pytest.approx(12.0,
                                                                                      abs=MRPM)
    stats = driver.stats.as_dict()
    assert stats["truncated_pdos"] == 1 and stats["bad_frames"] == 1
    assert stats["incomplete_syncs"] == 1
    assert stats["other_frames"] >= 4  # node 6's RPDO1, TPDO1, TPDO2, heartbeat


def test_a_sync_counter_jump_counts_the_missed_samples(cell):
    driver = CanopenDriver.from_config(_config(cell.channel), base_dir=Path("."))
    try:
        cell.cycle()
        cell.cycle()
        cell.k += 3  # three SYNC periods lost on the way (a gateway's buffer overflowed)
        cell.cycle()
        samples = _read(driver, 3)
    finally:
        driver.close()
    assert [round(s.t, 3) for s in samples] == [0.0, 0.01, 0.05]
    assert driver.stats.gaps == 3


def test_emcy_statusword_fault_and_a_missing_heartbeat_are_said_and_counted(cell):
    driver = CanopenDriver.from_config(_config(cell.channel), base_dir=Path("."))
    try:
        for _ in range(10):
            cell.cycle()
        _read(driver, 10)
        assert driver.device_faults == () and driver.silent == ()
        cell.send(0x85, struct.pack("<HB5s", 0x2310, 0x03, b""), cell.k * 0.01)
        cell.cycle(status=0x0218)  # fault bit (3) set
        _read(driver, 1)
        faults = driver.device_faults
        assert any("EMCY Code 0x2310" in f for f in faults), faults
        assert any("statusword" in f for f in faults), faults
        # the heartbeat stops (producer time 0.1 s, missing after 1.5 of them)
        for _ in range(30):
            cell.cycle(status=0x0218, heartbeat=False)
        _read(driver, 30)
        assert driver.silent and "node 5 heartbeat" in driver.silent[0], driver.silent
        # it comes back, the fault is reset
        cell.send(0x85, bytes(8), cell.k * 0.01)
        cell.send(0x705, b"\x05", cell.k * 0.01)
        for _ in range(2):
            cell.cycle()
        _read(driver, 2)
        assert driver.device_faults == () and driver.silent == ()
    finally:
        driver.close()
    extra = driver.stats.extra
    assert extra["emcy_faults"] == 1 and extra["statusword_faults"] == 1
    assert extra["heartbeat_lost"] == 1


def test_a_tpdo_that_stops_is_named_silent_and_its_cycles_counted(cell):
    driver = CanopenDriver.from_config(_config(cell.channel), base_dir=Path("."))
    try:
        for _ in range(5):
            cell.cycle()
        _read(driver, 5)
        for _ in range(150):  # 1.5 s of SYNC and TPDO1 without TPDO2 (Va, ia)
            cell.cycle(send_tpdo2=False)
        assert driver.read(timeout=0.5) is None
        assert any(s.startswith("TPDO2 (Va, ia) for 1.") for s in driver.silent), driver.silent
        assert driver.stats.extra["incomplete_syncs"] >= 149
        cell.cycle()
        cell.cycle()
        assert driver.read(timeout=0.5) is not None and driver.silent == ()
    finally:
        driver.close()


def test_sample_on_a_tpdo_without_sync(cell):
    driver = CanopenDriver.from_config(_config(cell.channel, sample_on="TPDO2"),
                                       base_dir=Path("."))
    try:
        for k in range(5):
            cell.cycle(sync=False, ia=0.5 * k)
        samples = _read(driver, 5)
    finally:
        driver.close()
    assert [round(s.t, 5) for s in samples] == [round(0.01 * k + 3e-5, 5) for k in range(5)]
    assert samples[-1].values["ia"] == pytest.approx(2.0, abs=0.004)


def test_the_driver_module_never_sends():
    """No call in the driver's source sends: no ``send``, no canopen Network (which owns the
    bus and sends NMT, SDO, SYNC, PDOs), no transmit, no SDO access."""
    import twinwatch.drivers.canopen as mod

    tree = ast.parse(Path(mod.__file__).read_text(encoding="utf-8"))
    called = {n.func.attr if isinstance(n.func, ast.Attribute) else getattr(n.func, "id", "")
              for n in ast.walk(tree) if isinstance(n, ast.Call)}
    assert not {c for c in called if c.startswith(("send", "transmit", "Network", "connect",
                                                   "RemoteNode", "sdo", "start"))
                and c != "startswith"}, called
    assert "import_od" in called


# -- bad input: check-config refuses with one line naming the key ------------------------------

_SIM = (ROOT / "config" / "dc-motor-canopen-sim.toml").read_text()
_DRIVER = '''[driver]
type = "canopen"
interface = "virtual"
channel = "check-config-canopen"
node_id = NODE_ID
eds = "EDS"
sample_period = 0.01
[driver.channels]
Va = { object = "0x2100", factor = "mV", unit = "V" }
ia = { object = "0x6078", factor = "FACTOR", unit = "A" }
omega = { object = "OMEGA", factor = "0.001rpm", unit = "rad/s" }
setpoint = { object = "0x60FF", factor = "0.001rpm", unit = "rad/s" }
'''


def _file(tmp_path: Path, *, node_id: str = "5", eds: str = EDS,
          factor: str = "per_mille_rated_current", omega: str = "0x606C") -> Path:
    head, _, rest = _SIM.partition("[driver]")
    tail = rest[rest.index("[zenoh]"):]
    driver = (_DRIVER.replace("NODE_ID", node_id).replace("EDS", eds)
              .replace("FACTOR", factor).replace("OMEGA", omega))
    path = tmp_path / "m.toml"
    path.write_text(head + driver + "\n" + tail)
    return path


def _check(path: Path) -> tuple[int, list[str]]:
    r = CliRunner().invoke(main, ["check-config", str(path)])
    return r.exit_code, [line for line in r.output.splitlines() if line.strip()]


def test_check_config_accepts_a_canopen_file_and_says_what_it_maps(tmp_path):
    code, lines = _check(_file(tmp_path))
    assert code == 0, lines
    assert "omega <- TPDO1 0x606C Velocity actual value" in lines[0], lines


@pytest.mark.parametrize("edit, key", [
    ({"node_id": "0"}, "driver.node_id"),
    ({"node_id": "128"}, "driver.node_id"),
    ({"factor": "per_mil"}, "driver.channels.ia.factor"),
    ({"omega": "0x6064"}, "driver.channels.omega.object"),   # not in the EDS
    ({"omega": "0x6075"}, "driver.channels.omega.object"),   # in it, mapped to no PDO
    ({"eds": "bad.eds"}, "driver.eds"),
], ids=["node-0", "node-128", "factor", "object-absent", "object-unmapped", "eds-unparsable"])
def test_check_config_refuses_bad_input_with_one_line_naming_the_key(tmp_path, edit, key):
    (tmp_path / "bad.eds").write_text("[1000\nParameterName=Device type\nthis is no EDS\n")
    code, lines = _check(_file(tmp_path, **edit))
    # one line naming the key (a schema error under the loader's "invalid configuration")
    assert code == 1 and len(lines) <= 2, lines
    assert len([line for line in lines if key in line]) == 1, lines
    assert not any("Traceback" in line for line in lines)


def test_unmapped_object_message_names_what_is_mapped(tmp_path):
    cfg = CanopenDriverConfig.model_validate(
        _config("x", channels={"Tload": {"object": "Motor rated current"}}))
    with pytest.raises(DriverConfigError) as exc:
        load_plan(cfg.resolved(Path(".")))
    text = exc.value.keyed()
    assert text.startswith("driver.channels.Tload.object:"), text
    assert "mapped to no TPDO or RPDO" in text and "0x606C Velocity actual value" in text


# -- the simulated drive through the daemon ------------------------------------------------------

def _sim_config(duration: float) -> Any:
    from twinwatch.config.loader import load_config

    cfg = load_config(ROOT / "config" / "dc-motor-canopen-sim.toml")
    cfg.driver.plant.duration = duration  # type: ignore[attr-defined]
    return cfg


def _ra_errors(plant: Any, history: list[dict[str, Any]], since: float) -> np.ndarray:
    return np.asarray([
        (h["parameters"]["Ra"]["value"] / plant.truth(0.5 * (h["t_start"] + h["t_end"])).Ra
         - 1.0) * 100.0 for h in history if h["t_start"] >= since])


def test_simulated_drive_fault_and_lost_heartbeat_reach_the_health_message_and_status():
    """30 s of plant time: an EMCY fault at 16 s, the heartbeat stopped at 20 s: from the
    window each happens in on (and in no window before), the health message's source says
    so, and STATUS's problems; the windows go on being estimated; Ra within 0.2 % of the
    plant."""
    from twinwatch.daemon.runner import Daemon

    cfg = _sim_config(30.0)
    cfg.driver.plant.fault_start = 0.0  # type: ignore[attr-defined]
    cfg.driver.fault_at = 16.0  # type: ignore[attr-defined]
    cfg.driver.fault_code = 0x3210  # type: ignore[attr-defined] # DC link over-voltage
    cfg.driver.heartbeat_stop_at = 20.0  # type: ignore[attr-defined]
    with create_driver(cfg.driver, base_dir=Path(".")) as driver:
        with Daemon(cfg, driver=driver, publish=False, record=False) as daemon:
            daemon.run()
            problems = daemon.problems()
        hist = list(daemon.history)
        stats = driver.stats.as_dict()
    assert len(hist) == 15 and daemon.overruns == 0 and stats["gaps"] == 0, stats
    # each window's message says the state its last sample left: the fault from the window
    # it happened in (16-18 s) on, never before; likewise the heartbeat (20-22 s)
    for h in hist:
        faults, silent = h["source"]["device_faults"], h["source"]["silent"]
        if h["t_start"] >= 16.0:
            assert any("EMCY Code 0x3210" in f for f in faults), (h["t_start"], faults)
            assert any("statusword 0x6041 fault bit" in f for f in faults), faults
        else:
            assert faults == [], (h["t_start"], faults)
        if h["t_start"] >= 20.0:
            assert any("node 5 heartbeat" in x for x in silent), (h["t_start"], silent)
        else:
            assert silent == [], (h["t_start"], silent)
    assert hist[-1]["counters"]["driver_emcy_faults"] == 1
    assert hist[-1]["counters"]["driver_heartbeat_lost"] == 1
    assert any(p.startswith("device fault: node 5 in fault: EMCY Code 0x3210") for p in problems)
    assert any("node 5 heartbeat" in p for p in problems), problems
    err = _ra_errors(driver.drive.plant, hist, since=0.0)
    assert np.all(np.abs(err) <= 0.2), err


def _lossy_run(duration: float, loss: float) -> tuple[Any, list[dict[str, Any]], dict[str, int],
                                                     dict[str, int]]:
    """The example's drive, Ra degrading from 0 s, with ``loss`` of its bus's frames lost:
    the driver, the health messages, the daemon's and the driver's counters."""
    from twinwatch.daemon.runner import Daemon

    cfg = _sim_config(duration)
    cfg.driver.plant.fault_start = 0.0  # type: ignore[attr-defined]
    cfg.driver.frame_loss = loss  # type: ignore[attr-defined]
    with create_driver(cfg.driver, base_dir=Path(".")) as driver:
        with Daemon(cfg, driver=driver, publish=False, record=False) as daemon:
            daemon.run()
            counters = daemon.counters()
        hist = list(daemon.history)
        stats = driver.stats.as_dict()
    return driver, hist, counters, stats


def test_two_percent_of_the_frames_lost_every_window_is_estimated():
    """Issue 56: 2 % of the bus's frames (SYNC, PDOs, heartbeat) lost at random; a SYNC cycle
    without its SYNC or one of its TPDOs gives no sample (about 6 % of the cycles). Before,
    each missing sample abandoned its window (0 of 17 windows, exit 75); now its slot holds
    the previous sample and every window is estimated, Ra within 0.2 % of the plant, as
    without loss."""
    driver, hist, c, stats = _lossy_run(60.0, 0.02)
    lost = driver.drive.network.bus  # the simulated bus that lost the frames
    assert 0.01 < lost.lost / (lost.lost + stats["frames"]) < 0.03, (lost.lost, stats)
    assert len(hist) == 30 and c["windows_abandoned"] == 0, c
    assert stats["gaps"] > 50 and stats["incomplete_syncs"] > 100, stats  # SYNCs, TPDOs lost
    # each missing sample is counted: a SYNC lost (its counter jumped) or a cycle incomplete,
    # less the ones between two windows (no slot to fill) and the first cycles' (no sample yet)
    assert 0.97 * (stats["gaps"] + stats["incomplete_syncs"]) <= c["samples_missing"] \
        <= stats["gaps"] + stats["incomplete_syncs"], (c, stats)
    assert c["windows_with_missing"] == 30
    assert hist[-1]["counters"]["samples_missing"] == c["samples_missing"]
    err = _ra_errors(driver.drive.plant, hist, since=0.0)
    assert np.all(np.abs(err) <= 0.2), err


@pytest.mark.slow
def test_simulated_drive_ra_within_0p2_percent_after_160_s():
    """The issue's done-when: the example's run (1200 s, Ra degrading from 160 s) over the
    CANopen path: Ra within 0.2 % of the plant in every window after 160 s, as the DBC path;
    no RUL level raised and cleared (issue 56); the model check passed in 95 % of the
    windows."""
    from twinwatch.daemon.runner import Daemon

    cfg = _sim_config(1200.0)
    with create_driver(cfg.driver, base_dir=Path(".")) as driver:
        with Daemon(cfg, driver=driver, publish=False, record=False) as daemon:
            daemon.run()
        hist = list(daemon.history)
        stats = driver.stats.as_dict()
    assert len(hist) == 600 and stats["gaps"] == 0 and stats["bad_frames"] == 0, stats
    # issue 56: no RUL level that clears (Ra only degrades): before, a RUL ALARM "79 s
    # (49-752 s)" at 180 s, cleared 40 s later
    rank = {"normal": 0, "warning": 1, "alarm": 2}
    levels = [(h["t_end"], rank[h["alarms"]["Ra"]["rul"]["level"]]) for h in hist]
    assert all(b >= a for (_, a), (_, b) in zip(levels, levels[1:], strict=False)), [
        (t, lv) for (t, lv), (_, prev) in zip(levels[1:], levels, strict=False) if lv < prev]
    # the drive reports its current in per mille of 4 A: the reading's rounding is not model
    # error (before: the check failed in about 30 % of the windows, "ia not white")
    passed = sum(h["model_check"]["passed"] for h in hist)
    assert passed >= 0.95 * len(hist), passed
    err = _ra_errors(driver.drive.plant, hist, since=160.0)
    print(f"\nover CANopen: Ra error after 160 s over {len(err)} windows: median "
          f"{np.median(np.abs(err)):.4f} %, max {np.max(np.abs(err)):.4f} %")
    assert np.all(np.abs(err) <= 0.2), np.percentile(np.abs(err), [50, 95, 100])


@pytest.mark.slow
def test_two_percent_of_the_frames_lost_over_the_examples_run():
    """Issue 56's done-when over the example's 1200 s: 2 % of the frames lost at random, at
    least 95 % of the windows estimated (measured: 595 of 600; the 4 abandoned had more than
    20 samples missing), Ra within 0.2 % of the plant after 160 s as without loss (measured
    2026-11-27: median 0.0018 %, 95th percentile 0.042 %, max 0.198 %; without loss 0.0019,
    0.043, 0.186 %)."""
    driver, hist, c, stats = _lossy_run(1200.0, 0.02)
    assert len(hist) >= 570, (len(hist), c)
    assert c["windows_abandoned"] == c["windows_abandoned_gap"] <= 30, c
    err = _ra_errors(driver.drive.plant, hist, since=160.0)
    print(f"\n2 % of the frames lost: {len(hist)} windows, {c['samples_missing']} samples "
          f"missing; Ra error after 160 s: median {np.median(np.abs(err)):.4f} %, 95th "
          f"percentile {np.percentile(np.abs(err), 95):.4f} %, max {np.max(np.abs(err)):.4f} %")
    assert np.all(np.abs(err) <= 0.2), np.percentile(np.abs(err), [50, 95, 100])


def test_the_shipped_eds_is_in_the_package_data():
    text = (ROOT / "pyproject.toml").read_text()
    assert '"plant/*.eds"' in text and drive_eds_path().is_file()


def test_a_dcf_s_values_win_over_the_eds_defaults(tmp_path):
    """A DCF (the EDS with ParameterValue, as a commissioning tool writes it) that remaps
    TPDO1's second object from the velocity to the DC link voltage: the driver follows the
    DCF, and a channel on the velocity is refused (the drive no longer sends it)."""
    text = drive_eds_path().read_text()
    section = "[1A00sub2]\n"
    assert section in text
    dcf = tmp_path / "drive.dcf"
    dcf.write_text(text.replace(section, section + "ParameterValue=0x60790020\n"))
    base = _config("x", eds=str(dcf))
    with pytest.raises(DriverConfigError) as exc:
        load_plan(CanopenDriverConfig.model_validate(base).resolved(tmp_path))
    assert exc.value.keyed().startswith("driver.channels.omega.object:")
    channels = dict(CHANNELS)
    channels["omega"] = {"object": "DC link circuit voltage", "factor": "mV"}
    plan = load_plan(CanopenDriverConfig.model_validate({**base, "channels": channels})
                     .resolved(tmp_path))
    assert plan.channels["omega"] == "TPDO1 0x6079 DC link circuit voltage"


def test_a_float_mapped_narrower_is_refused_and_a_float_statusword_is_not_watched(tmp_path):
    """A DCF that maps TPDO1's velocity as a REAL32 in 16 bits is refused naming the channel
    (its value would be read past the frame); one that declares the statusword a REAL32 keeps
    the samples and does not watch a fault bit it cannot have."""
    text = drive_eds_path().read_text()
    velocity = "[606C]\nParameterName=Velocity actual value\nObjectType=0x7\nDataType=0x0004"
    status = "[6041]\nParameterName=Statusword\nObjectType=0x7\nDataType=0x0006"
    assert velocity in text and status in text and "[1A00sub2]\n" in text
    narrow = tmp_path / "narrow.dcf"
    narrow.write_text(text.replace(velocity, velocity[:-4] + "0008")
                      .replace("[1A00sub2]\n", "[1A00sub2]\nParameterValue=0x606C0010\n"))
    with pytest.raises(DriverConfigError) as exc:
        load_plan(CanopenDriverConfig.model_validate(_config("x", eds=str(narrow)))
                  .resolved(tmp_path))
    assert exc.value.keyed().startswith("driver.channels.omega.object:")
    assert "REAL32 mapped in 16 bits" in str(exc.value)
    real_status = tmp_path / "status.dcf"
    real_status.write_text(text.replace(status, status[:-4] + "0008"))
    plan = load_plan(CanopenDriverConfig.model_validate(_config("x", eds=str(real_status)))
                     .resolved(tmp_path))
    assert all(p.statusword is None for p in plan.pdos.values())
    assert set(plan.channels) == set(CHANNELS)


def test_bit_fields_and_floats_decode_as_the_mapping_says():
    from twinwatch.drivers.canopen import _decode, _Entry

    # a signed 12-bit field at bit 4 (INTEGER16 mapped with 12 bits), -5 in it
    data = ((-5 & 0xFFF) << 4 | 0x3).to_bytes(2, "little")
    assert _decode(_Entry(0x2000, 0, "x", 4, 12, 0x3), data) == -5.0
    assert _decode(_Entry(0x2000, 0, "x", 0, 4, 0x5), data) == 3.0  # UNSIGNED8, 4 bits
    real = b"\x00\x00" + struct.pack("<f", 1.5)
    assert _decode(_Entry(0x2001, 0, "y", 16, 32, 0x8), real) == 1.5  # REAL32 at byte 2


@pytest.mark.parametrize("odd", [None, (36, 12, 0x3), (40, 24, 0x7)])
def test_a_pdo_s_compiled_layout_decodes_as_each_entry_does(odd):
    """Each PDO's layout is compiled once (one struct.Struct a frame, or entry by entry when an
    entry is off a byte boundary or not its type's width): the raw values, and so the scaled
    ones, are _decode's, NaN and infinities included."""
    import random

    from twinwatch.drivers.canopen import _decode, _Entry, _Pdo

    entries = [_Entry(0x2001, 0, "f32", 0, 32, 0x8), _Entry(0x2002, 0, "u8", 32, 8, 0x5)]
    if odd is None:  # a dummy byte, then a signed 16-bit and an unsigned 32-bit at bytes 6, 8
        entries += [_Entry(0x2003, 0, "i16", 48, 16, 0x3), _Entry(0x2004, 0, "u32", 64, 32, 0x7)]
    else:  # a signed 12-bit field at bit 36, or an UNSIGNED32 mapped with 24 bits at byte 5
        entries += [_Entry(0x2003, 0, "odd", *odd)]
    pdo = _Pdo("TPDO1", 0x185, 1, entries, 96 if odd is None else 64)
    pdo.channels = [(e.name, e, 0.5, -1.25) for e in entries]
    pdo.statusword = entries[1]
    pdo.compile()
    assert (type(pdo.unpack).__name__ == "builtin_function_or_method") == (odd is None)
    rng = random.Random(58)
    for k in range(2000):
        data = bytes(rng.randrange(256) for _ in range(pdo.bits // 8))
        if k % 50 == 0:  # NaN, inf in the REAL32
            data = struct.pack("<f", [math.nan, math.inf, -math.inf][k // 50 % 3]) + data[4:]
        raw = pdo.unpack(data)
        for (ch, at, factor, offset), (_, entry, _, _) in zip(pdo.scaled, pdo.channels,
                                                                 strict=True):
            want, got = _decode(entry, data) * factor + offset, raw[at] * factor + offset
            assert repr(got) == repr(want), (ch, data.hex())
        assert int(raw[pdo.status_at]) == int(_decode(entries[1], data))


def test_a_candump_log_of_the_simulated_drive_replays(tmp_path):
    """2 s of the simulated drive written as a candump log and replayed with ``log_file``:
    200 samples on the SYNC grid, the drive's fault in the log read as on a bus."""
    from twinwatch.drivers import EndOfStream
    from twinwatch.plant.canopen_drive import CiA402Drive
    from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig

    channel = f"test-canopen-log-{next(_channels)}"
    tx = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
    rx = can.Bus(interface="virtual", channel=channel)
    log = tmp_path / "drive.log"
    drive = CiA402Drive(DCMotorPlant(DCMotorPlantConfig(duration=2.0)), tx)
    with can.Logger(str(log)) as writer:
        for k in range(200):
            drive.step()
            if k == 150:
                drive.inject_fault()
            while (m := rx.recv(0)) is not None:
                m.channel = "can0"
                writer.on_message_received(m)
    tx.shutdown()
    rx.shutdown()
    cfg = _config("x", log_file=str(log))
    del cfg["interface"], cfg["channel"]
    driver = CanopenDriver.from_config(cfg, base_dir=Path("."))
    samples = []
    try:
        while True:
            samples.append(driver.read(timeout=0.1))
    except EndOfStream:
        pass
    finally:
        driver.close()
    assert len(samples) == 200
    assert np.allclose([s.t for s in samples], np.arange(200) * 0.01, atol=1e-6)
    assert driver.stats.extra["emcy_faults"] == 1 and driver.device_faults
