"""CanDriver against a real python-can ``virtual`` bus (in-process, no network, no hardware).

Frames are encoded with cantools from the DBC and sent by a second virtual bus on the same
channel, the way the simulated plant or a real drive would put them on the wire.
"""

from __future__ import annotations

import math
import threading
import time
import tomllib
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from unittest import mock

import can
import cantools
import numpy as np
import pytest
from cantools.database.can import Database
from pydantic import ValidationError

from twinwatch.drivers import (
    Driver,
    DriverInitializationError,
    DriverOperationError,
    EndOfStream,
    Sample,
)
from twinwatch.drivers import create_driver as create_any_driver
from twinwatch.drivers.can import CanDriver, CanDriverConfig

REPO = Path(__file__).resolve().parents[1]
PLANT_DBC = REPO / "twinwatch" / "plant" / "dcmotor.dbc"
SHARED_DATA = REPO.parent / "shared" / "data"
ODRIVE_DBC = SHARED_DATA / "dbc" / "odrive-cansimple-0.6.10.dbc"
ODRIVE_CONFIG = REPO / "config" / "dc-motor-odrive.toml"
TS = 0.01  # [s] plant sample period used in these tests


# Thread leaks fail every test: see the autouse fixture in tests/conftest.py.


@pytest.fixture
def channel() -> str:
    """A virtual CAN channel no other test uses."""
    return f"twinwatch-test-{uuid.uuid4().hex}"


@pytest.fixture
def tx(channel: str) -> Iterator[can.BusABC]:
    """The sending side: a second virtual bus on the test's channel (keeps time stamps)."""
    with can.Bus(interface="virtual", channel=channel, preserve_timestamps=True) as bus:
        yield bus


@pytest.fixture(scope="module")
def plant_db() -> Database:
    db = cantools.database.load_file(PLANT_DBC)
    assert isinstance(db, Database)
    return db


def plant_config(channel: str, **overrides: Any) -> dict[str, Any]:
    """The [driver] table a machine config would hold for the simulated plant."""
    config: dict[str, Any] = {
        "type": "can",
        "interface": "virtual",
        "channel": channel,
        "dbc": str(PLANT_DBC),
        "sync_message": "TW_Motor_Sample",
        "time_source": "counter",
        "counter_signal": "TW_Motor_Sample.sample_counter",
        "sample_period": TS,
        "signals": {
            "Va": {"message": "TW_Motor_Electrical", "signal": "Va", "unit": "V"},
            "ia": {"message": "TW_Motor_Electrical", "signal": "ia", "unit": "A"},
            "omega": {"message": "TW_Motor_Mechanical", "signal": "omega", "unit": "rad/s"},
            "Tload": {"message": "TW_Motor_Mechanical", "signal": "Tload", "unit": "N.m"},
            "setpoint": {"message": "TW_Motor_Sample", "signal": "setpoint", "unit": "rad/s"},
        },
    }
    config.update(overrides)
    return config


def frame(db: Database, name: str, timestamp: float = 0.0, **signals: float) -> can.Message:
    message = db.get_message_by_name(name)
    return can.Message(
        arbitration_id=message.frame_id,
        is_extended_id=message.is_extended_frame,
        data=message.encode(signals),
        timestamp=timestamp,
    )


def plant_frames(db: Database, k: int, values: dict[str, float]) -> list[can.Message]:
    """The three frames the plant sends for sample ``k``, in the plant's order."""
    return [
        frame(db, "TW_Motor_Electrical", Va=values["Va"], ia=values["ia"]),
        frame(db, "TW_Motor_Mechanical", omega=values["omega"], Tload=values["Tload"]),
        frame(db, "TW_Motor_Sample", setpoint=values["setpoint"], sample_counter=k),
    ]


def f32(x: float) -> float:
    return float(np.float32(x))


def read_all(driver: Driver, timeout: float = 0.05, misses: int = 3) -> list[Sample]:
    """Every sample the driver has queued: read until ``misses`` reads in a row return None.
    One None is not the end: python-can's software filter spends a read's timeout on a frame
    it drops, and after a batch nap (a receive that took over WAITED_S, as on a loaded box)
    that timeout is 0, so a read can return None with frames still queued behind."""
    samples: list[Sample] = []
    missed = 0
    while missed < misses:
        sample = driver.read(timeout)
        if sample is None:
            missed += 1
        else:
            samples.append(sample)
            missed = 0
    return samples


# -- the plant's DBC ----------------------------------------------------------------------


def test_plant_dbc_declares_the_three_messages_as_float32(plant_db: Database) -> None:
    expected = {
        "TW_Motor_Electrical": (0x100, ["Va", "ia"]),
        "TW_Motor_Mechanical": (0x101, ["omega", "Tload"]),
        "TW_Motor_Sample": (0x102, ["setpoint", "sample_counter"]),
    }
    for name, (frame_id, signals) in expected.items():
        message = plant_db.get_message_by_name(name)
        assert message.frame_id == frame_id
        assert message.length == 8 and not message.is_extended_frame
        assert message.senders == ["TW_Plant"]
        assert [s.name for s in message.signals] == signals
        for signal in message.signals:
            assert signal.byte_order == "little_endian" and signal.length == 32
            assert signal.comment, f"{name}.{signal.name} has no CM_ comment"
            assert signal.is_float == (signal.name != "sample_counter")
    counter = plant_db.get_message_by_name("TW_Motor_Sample").get_signal_by_name("sample_counter")
    assert not counter.is_signed and not counter.is_float


def test_plant_dbc_round_trips_float32_exactly(plant_db: Database) -> None:
    rng = np.random.default_rng(1)
    values = rng.normal(0.0, 300.0, size=(200, 2)).astype(np.float32)
    electrical = plant_db.get_message_by_name("TW_Motor_Electrical")
    for va, ia in values:
        decoded = electrical.decode(electrical.encode({"Va": float(va), "ia": float(ia)}))
        assert decoded == {"Va": float(va), "ia": float(ia)}
        assert isinstance(decoded["Va"], float)
    sample = plant_db.get_message_by_name("TW_Motor_Sample")
    data = sample.encode({"setpoint": 1.1, "sample_counter": 2**32 - 1})
    assert data == np.float32(1.1).tobytes() + (2**32 - 1).to_bytes(4, "little")
    assert sample.decode(data) == {"setpoint": f32(1.1), "sample_counter": 2**32 - 1}


# -- assembling samples -------------------------------------------------------------------


def test_sync_message_emits_one_sample_with_every_signal(
    channel: str, tx: can.BusABC, plant_db: Database
) -> None:
    sent = [
        {
            "Va": 12.0 + 0.1 * k,
            "ia": 0.3 * k,
            "omega": 100.0 / 3 * k,
            "Tload": -0.01,
            "setpoint": 50,
        }
        for k in range(5)
    ]
    config = CanDriverConfig.model_validate(plant_config(channel))
    with CanDriver(config) as driver:
        assert driver.channels == ("Va", "ia", "omega", "Tload", "setpoint")
        assert driver.sample_period == TS
        for k, values in enumerate(sent, start=100):
            for msg in plant_frames(plant_db, k, values):
                tx.send(msg)
        samples = read_all(driver)
        assert [s.t for s in samples] == [k * TS for k in range(100, 105)]
        for sample, values in zip(samples, sent, strict=True):
            assert sample.values == {ch: f32(v) for ch, v in values.items()}
            assert list(sample.values) == list(driver.channels)
        assert driver.stats.as_dict() == {
            "frames": 15,
            "samples": 5,
            "bad_frames": 0,
            "bad_values": 0,
            "gaps": 0,
            "errors": 0,
        }


def test_sync_before_every_signal_was_seen_gives_no_sample(
    channel: str, tx: can.BusABC, plant_db: Database
) -> None:
    """Joining mid-sample: the first sync message finds no Va yet and is skipped."""
    values = {"Va": 1.0, "ia": 2.0, "omega": 3.0, "Tload": 4.0, "setpoint": 5.0}
    with CanDriver(CanDriverConfig.model_validate(plant_config(channel))) as driver:
        for msg in plant_frames(plant_db, 0, values)[1:] + plant_frames(plant_db, 1, values):
            tx.send(msg)
        samples = read_all(driver)
        assert [s.t for s in samples] == [1 * TS]
        assert driver.stats.extra["incomplete_syncs"] == 1


def test_slow_signal_is_held_at_its_latest_value(
    channel: str, tx: can.BusABC, plant_db: Database
) -> None:
    values = {"Va": 1.0, "ia": 2.0, "omega": 3.0, "Tload": 4.0, "setpoint": 5.0}
    with CanDriver(CanDriverConfig.model_validate(plant_config(channel))) as driver:
        for msg in plant_frames(plant_db, 0, values):
            tx.send(msg)
        tx.send(frame(plant_db, "TW_Motor_Mechanical", omega=30.0, Tload=4.0))
        tx.send(frame(plant_db, "TW_Motor_Sample", setpoint=5.0, sample_counter=1))
        first, second = read_all(driver)
        assert first.values["omega"] == 3.0 and second.values["omega"] == 30.0
        assert second.values["Va"] == 1.0  # not re-sent: held


def test_counter_jump_counts_the_lost_samples_as_gaps(
    channel: str, tx: can.BusABC, plant_db: Database
) -> None:
    values = {"Va": 1.0, "ia": 2.0, "omega": 3.0, "Tload": 4.0, "setpoint": 5.0}
    with CanDriver(CanDriverConfig.model_validate(plant_config(channel))) as driver:
        for k in (0, 1, 4, 5):  # samples 2 and 3 lost
            for msg in plant_frames(plant_db, k, values):
                tx.send(msg)
        samples = read_all(driver)
        assert [s.t for s in samples] == [0.0, TS, 4 * TS, 5 * TS]
        assert driver.stats.gaps == 2
        assert driver.stats.samples == 4


def test_counter_wraps_around_uint32_without_a_gap(
    channel: str, tx: can.BusABC, plant_db: Database
) -> None:
    values = {"Va": 1.0, "ia": 2.0, "omega": 3.0, "Tload": 4.0, "setpoint": 5.0}
    with CanDriver(CanDriverConfig.model_validate(plant_config(channel))) as driver:
        for k in (2**32 - 2, 2**32 - 1, 0, 1):
            for msg in plant_frames(plant_db, k, values):
                tx.send(msg)
        samples = read_all(driver)
        assert [s.t for s in samples] == [(2**32 - 2 + i) * TS for i in range(4)]
        assert driver.stats.gaps == 0


def test_counter_going_back_is_a_reset_not_a_gap(
    channel: str, tx: can.BusABC, plant_db: Database
) -> None:
    values = {"Va": 1.0, "ia": 2.0, "omega": 3.0, "Tload": 4.0, "setpoint": 5.0}
    with CanDriver(CanDriverConfig.model_validate(plant_config(channel))) as driver:
        for k in (50, 51, 0, 1):  # the plant restarted
            for msg in plant_frames(plant_db, k, values):
                tx.send(msg)
        assert [s.t for s in read_all(driver)] == [50 * TS, 51 * TS, 0.0, TS]
        assert driver.stats.gaps == 0
        assert driver.stats.extra["counter_resets"] == 1


@pytest.mark.parametrize("time_source", ["frame", "signal:TW_Motor_Sample.setpoint"])
def test_time_source_frame_or_signal(
    channel: str, tx: can.BusABC, plant_db: Database, time_source: str
) -> None:
    config = plant_config(channel, time_source=time_source)
    with CanDriver(CanDriverConfig.model_validate(config)) as driver:
        for k in range(3):
            stamp = 1700000000.0 + 0.25 * k
            tx.send(frame(plant_db, "TW_Motor_Electrical", stamp, Va=1.0, ia=2.0))
            tx.send(frame(plant_db, "TW_Motor_Mechanical", stamp, omega=3.0, Tload=4.0))
            tx.send(frame(plant_db, "TW_Motor_Sample", stamp, setpoint=0.5 * k, sample_counter=k))
        times = [s.t for s in read_all(driver)]
    if time_source == "frame":
        assert times == [1700000000.0, 1700000000.25, 1700000000.5]
    else:
        assert times == [0.0, 0.5, 1.0]


# -- bad input ----------------------------------------------------------------------------


def test_wrong_length_frame_is_a_bad_frame_and_the_driver_goes_on(
    channel: str, tx: can.BusABC, plant_db: Database
) -> None:
    values = {"Va": 1.0, "ia": 2.0, "omega": 3.0, "Tload": 4.0, "setpoint": 5.0}
    with CanDriver(CanDriverConfig.model_validate(plant_config(channel))) as driver:
        for msg in plant_frames(plant_db, 0, values):
            tx.send(msg)
        tx.send(can.Message(arbitration_id=0x100, is_extended_id=False, data=b"\x01\x02\x03"))
        for msg in plant_frames(plant_db, 1, values):
            tx.send(msg)
        samples = read_all(driver)
        assert [s.t for s in samples] == [0.0, TS]
        assert driver.stats.bad_frames == 1
        assert driver.stats.frames == 7


MUX_DBC = """VERSION ""
NS_ :
BS_:
BU_: Dev
BO_ 512 Telemetry: 8 Dev
 SG_ Page M : 0|8@1+ (1,0) [0|0] "" Vector__XXX
 SG_ Speed m1 : 8|16@1- (0.1,0) [0|0] "rpm" Vector__XXX
 SG_ Current m2 : 8|16@1- (0.01,0) [0|0] "A" Vector__XXX
BO_ 513 Tick: 2 Dev
 SG_ Counter : 0|16@1+ (1,0) [0|0] "" Vector__XXX
"""


def page(number: int, value: int) -> bytes:
    """An 8-byte Telemetry frame: page number, then a little-endian int16."""
    return bytes([number]) + value.to_bytes(2, "little", signed=True) + bytes(5)


def test_undecodable_mapped_frame_is_a_bad_frame(tmp_path: Path, channel: str) -> None:
    """A multiplexed message with an unknown page cannot be decoded; the next ones can."""
    (tmp_path / "mux.dbc").write_text(MUX_DBC)
    config = {
        "type": "can",
        "interface": "virtual",
        "channel": channel,
        "dbc": "mux.dbc",  # relative to base_dir
        "sync_message": "Tick",
        "counter_signal": "Tick.Counter",
        "time_source": "counter",
        "sample_period": 0.1,
        "signals": {
            "omega": {"message": "Telemetry", "signal": "Speed", "scale": 2 * math.pi / 60},
            "ia": {"message": "Telemetry", "signal": "Current"},
        },
    }
    with (
        create_any_driver(config, base_dir=tmp_path) as driver,
        can.Bus(interface="virtual", channel=channel) as bus,
    ):
        bus.send(can.Message(arbitration_id=512, is_extended_id=False, data=page(1, 1000)))
        bus.send(can.Message(arbitration_id=512, is_extended_id=False, data=page(7, 0)))
        bus.send(can.Message(arbitration_id=512, is_extended_id=False, data=page(2, 500)))
        bus.send(can.Message(arbitration_id=513, is_extended_id=False, data=b"\x09\x00"))
        (sample,) = read_all(driver)
        assert driver.stats.bad_frames == 1
        assert sample.t == pytest.approx(0.9)
        assert sample.values["omega"] == pytest.approx(100.0 * 2 * math.pi / 60)
        assert sample.values["ia"] == pytest.approx(5.0)


def test_nan_is_counted_and_delivered(channel: str, tx: can.BusABC, plant_db: Database) -> None:
    values = {"Va": math.nan, "ia": math.inf, "omega": 3.0, "Tload": 4.0, "setpoint": 5.0}
    with CanDriver(CanDriverConfig.model_validate(plant_config(channel))) as driver:
        for msg in plant_frames(plant_db, 0, values):
            tx.send(msg)
        (sample,) = read_all(driver)
        assert math.isnan(sample.values["Va"]) and sample.values["ia"] == math.inf
        assert sample.values["omega"] == 3.0
        assert driver.stats.bad_values == 2


def test_shared_bus_unknown_ids_are_ignored_and_the_bus_is_left_open(
    channel: str, tx: can.BusABC, plant_db: Database
) -> None:
    values = {"Va": 1.0, "ia": 2.0, "omega": 3.0, "Tload": 4.0, "setpoint": 5.0}
    config = CanDriverConfig.model_validate(plant_config(channel) | {"interface": None})
    with can.Bus(interface="virtual", channel=channel) as shared:
        with (
            mock.patch.object(shared, "send", side_effect=AssertionError("driver sent")),
            CanDriver(config, bus=shared) as driver,
        ):
            tx.send(can.Message(arbitration_id=0x7FF, is_extended_id=False, data=b"\x00"))
            tx.send(can.Message(arbitration_id=0x100, is_extended_id=True, data=bytes(8)))
            tx.send(can.Message(arbitration_id=0x102, is_remote_frame=True, dlc=8))
            for msg in plant_frames(plant_db, 0, values):
                tx.send(msg)
            assert len(read_all(driver)) == 1
            assert driver.stats.frames == 6
            assert driver.stats.bad_frames == 0
            assert driver.stats.extra["remote_frames"] == 1
        # the driver is closed; the bus it was given still works
        tx.send(can.Message(arbitration_id=0x123, data=b"\x01"))
        assert shared.recv(1.0) is not None


def test_driver_shuts_down_the_bus_it_opened(channel: str) -> None:
    from can.interfaces import virtual

    driver = CanDriver(CanDriverConfig.model_validate(plant_config(channel)))
    assert channel in virtual.channels
    driver.close()
    driver.close()  # idempotent
    assert channel not in virtual.channels
    with pytest.raises(DriverOperationError):
        driver.read(0)


def test_read_zero_returns_a_sample_already_queued(
    channel: str, tx: can.BusABC, plant_db: Database
) -> None:
    values = {"Va": 1.0, "ia": 2.0, "omega": 3.0, "Tload": 4.0, "setpoint": 5.0}
    with CanDriver(CanDriverConfig.model_validate(plant_config(channel))) as driver:
        for k in range(2):
            for msg in plant_frames(plant_db, k, values):
                tx.send(msg)
        assert [driver.read(0), driver.read(0), driver.read(0)] == [
            Sample(0.0, values),
            Sample(TS, values),
            None,
        ]


def test_read_times_out_with_none(channel: str) -> None:
    with CanDriver(CanDriverConfig.model_validate(plant_config(channel))) as driver:
        start = time.monotonic()
        assert driver.read(0.05) is None
        assert 0.04 <= time.monotonic() - start < 5.0  # a generous deadline: never blocks
        assert driver.stats.samples == 0


# -- configuration errors -----------------------------------------------------------------


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (
            {"signals": {"Va": {"message": "TW_Motor_Electricl", "signal": "Va"}}},
            "signals.Va: message 'TW_Motor_Electricl' not in DBC; "
            "did you mean 'TW_Motor_Electrical'? available messages: TW_Motor_Electrical, "
            "TW_Motor_Mechanical, TW_Motor_Sample",
        ),
        (
            {"signals": {"ia": {"message": "TW_Motor_Electrical", "signal": "Ia"}}},
            "signals.ia: message 'TW_Motor_Electrical' has no signal 'Ia'; did you mean 'ia'? "
            "available signals: Va, ia",
        ),
        ({"sync_message": "TW_Motor_Samples"}, "sync_message: message 'TW_Motor_Samples'"),
        (
            {"counter_signal": "TW_Motor_Sample.counter"},
            "counter_signal: message 'TW_Motor_Sample' has no signal 'counter'",
        ),
        ({"dbc": "/nonexistent/motor.dbc"}, "dbc: file '/nonexistent/motor.dbc' not found"),
    ],
)
def test_bad_names_fail_at_construction_naming_the_key(
    channel: str, change: dict[str, Any], message: str
) -> None:
    config = CanDriverConfig.model_validate(plant_config(channel, **change))
    with pytest.raises(DriverInitializationError) as info:
        CanDriver(config)
    assert message in str(info.value)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"interface": "virtul"}, "did you mean 'virtual'?"),
        ({"sync": "TW_Motor_Sample"}, "Extra inputs are not permitted"),
        ({"time_source": "counter", "counter_signal": None}, "needs counter_signal"),
        ({"time_source": "wallclock"}, "expected 'frame', 'counter' or 'signal:"),
        ({"sample_period": 0.0}, "greater than 0"),
        ({"signals": {}}, "signals"),
    ],
)
def test_invalid_config_is_refused(channel: str, change: dict[str, Any], message: str) -> None:
    with pytest.raises(ValidationError, match=message):
        CanDriverConfig.model_validate(plant_config(channel, **change))
    with pytest.raises(DriverInitializationError, match="invalid CAN driver config"):
        create_any_driver(plant_config(channel, **change), base_dir=REPO)


# -- log replay ---------------------------------------------------------------------------


def write_candump_log(path: Path, db: Database, n: int, t0: float, period: float) -> None:
    with can.CanutilsLogWriter(path, channel="can0") as writer:
        for k in range(n):
            values = {"Va": 2.0 * k, "ia": 0.5, "omega": 10.0 * k, "Tload": 0.0, "setpoint": 1.0}
            for msg in plant_frames(db, k, values):
                msg.timestamp = t0 + k * period
                writer.on_message_received(msg)


def test_candump_log_replay_then_end_of_stream(tmp_path: Path, plant_db: Database) -> None:
    log = tmp_path / "plant.log"
    write_candump_log(log, plant_db, n=20, t0=1700000000.0, period=TS)
    config = plant_config("unused", log_file="plant.log", time_source="frame", interface=None)
    with CanDriver.from_config(config, base_dir=tmp_path) as driver:
        samples = []
        with pytest.raises(EndOfStream):
            while True:
                sample = driver.read(0)
                assert sample is not None, "as fast as possible: never waits"
                samples.append(sample)
        with pytest.raises(EndOfStream):
            driver.read(0)
    assert len(samples) == 20
    assert [s.t for s in samples] == pytest.approx([1700000000.0 + k * TS for k in range(20)])
    assert [s.values["omega"] for s in samples] == [10.0 * k for k in range(20)]
    assert driver.stats.frames == 60 and driver.stats.samples == 20


def test_candump_log_realtime_replay_is_paced(tmp_path: Path, plant_db: Database) -> None:
    log = tmp_path / "plant.log"
    write_candump_log(log, plant_db, n=6, t0=0.0, period=0.04)
    config = plant_config("unused", log_file=str(log), realtime=True)
    with CanDriver.from_config(config, base_dir=REPO) as driver:
        start = time.monotonic()
        assert driver.read(None) is not None  # sample 0 is due at once
        assert driver.read(0.005) is None  # sample 1 is due 40 ms after sample 0
        n = 1
        with pytest.raises(EndOfStream):
            while True:
                n += driver.read(1.0) is not None
        elapsed = time.monotonic() - start
    assert n == 6
    assert elapsed >= 0.19  # paced by the log: its 6 frames span 0.2 s


def test_missing_log_file_fails_at_construction(tmp_path: Path) -> None:
    config = plant_config("unused", log_file="nope.log")
    with pytest.raises(DriverInitializationError, match="log_file: cannot read"):
        CanDriver.from_config(config, base_dir=tmp_path)


# -- a real vendor DBC through configuration alone ----------------------------------------


def odrive_driver_table() -> dict[str, Any]:
    if not ODRIVE_DBC.is_file():
        pytest.skip(f"../shared/data not present: {ODRIVE_DBC} is missing")
    with ODRIVE_CONFIG.open("rb") as f:
        table: dict[str, Any] = tomllib.load(f)["driver"]
    return table


def test_odrive_config_decodes_the_vendor_dbc(channel: str, tx: can.BusABC) -> None:
    table = odrive_driver_table()
    config = CanDriverConfig.model_validate(table)
    assert config.log_file is not None and config.log_file.name == "odrive-axis0.log.gz"
    # the example replays its shipped log; here the same table on a live (virtual) bus
    config = config.model_copy(update={"interface": "virtual", "channel": channel,
                                       "log_file": None})
    db = cantools.database.load_file(ODRIVE_DBC)
    assert isinstance(db, Database)

    with create_any_driver(config, base_dir=ODRIVE_CONFIG.parent) as driver:
        assert driver.channels == ("omega", "ia", "Va")
        assert driver.sample_period == 0.01
        # what an ODrive (axis 0, plus a second axis and polling by the master) puts on the bus
        tx.send(frame(db, "Axis0_Heartbeat", Axis_Error=0, Axis_State=8, Procedure_Result=0,
                      Trajectory_Done_Flag=1))  # fmt: skip
        tx.send(frame(db, "Axis0_Get_Iq", Iq_Setpoint=1.5, Iq_Measured=1.37))
        tx.send(frame(db, "Axis0_Get_Bus_Voltage_Current", Bus_Voltage=24.1, Bus_Current=0.8))
        tx.send(frame(db, "Axis1_Get_Encoder_Estimates", Pos_Estimate=9.0, Vel_Estimate=99.0))
        tx.send(can.Message(arbitration_id=0x009, is_extended_id=False, is_remote_frame=True))
        tx.send(frame(db, "Axis0_Get_Encoder_Estimates", Pos_Estimate=12.25, Vel_Estimate=-7.3))
        tx.send(frame(db, "Axis0_Get_Iq", Iq_Setpoint=1.5, Iq_Measured=2.0))
        tx.send(frame(db, "Axis0_Get_Encoder_Estimates", Pos_Estimate=12.3, Vel_Estimate=5.0))
        first, second = read_all(driver)

    assert first.values == {
        "omega": f32(-7.3) * 6.283185307179586,
        "ia": f32(1.37),
        "Va": f32(24.1),
    }
    assert first.values["omega"] == pytest.approx(-7.3 * 2 * math.pi, rel=1e-7)
    assert second.values == {"omega": 5.0 * 2 * math.pi, "ia": 2.0, "Va": f32(24.1)}
    assert driver.stats.bad_frames == 0
    assert driver.stats.extra["remote_frames"] == 1


def test_odrive_misspelt_message_names_the_key_and_suggests(channel: str) -> None:
    table = odrive_driver_table()
    table["signals"]["omega"]["message"] = "Axis0_Get_Encoder_Estimate"
    with pytest.raises(DriverInitializationError) as info:
        create_any_driver(table, base_dir=ODRIVE_CONFIG.parent)
    assert str(info.value).startswith(
        "signals.omega: message 'Axis0_Get_Encoder_Estimate' not in DBC; "
        "did you mean 'Axis0_Get_Encoder_Estimates'"
    )


# -- a lossy bus (issue 56) ----------------------------------------------------------------------
@pytest.mark.parametrize("time_source", ["counter", "frame"])
def test_two_percent_of_the_frames_lost_every_window_is_estimated(tmp_path, time_source):
    """A candump log of the simulated motor (Ra degrading from 0 s) with 2 % of its frames
    lost at random: a lost sync frame is a missing sample (its slot holds the previous
    sample's values), a lost signal frame leaves that signal's last value (the driver's
    sample-and-hold). Every window is estimated, Ra within 0.2 % of the plant as without
    loss; the missing samples are counted."""
    import random

    from harness.sources import CAN_DRIVER, candump_line, plant_frames
    from twinwatch.config.loader import load_config
    from twinwatch.daemon.runner import Daemon
    from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig

    plant = {"scenario": "resistance_degradation", "fault_start": 0.0}
    rng = random.Random(56)
    frames = list(plant_frames(60.0, plant=plant))
    kept = [f for f in frames if rng.random() >= 0.02]
    log = tmp_path / "m.log"
    log.write_text("\n".join(candump_line(*f) for f in kept) + "\n")
    sim = (REPO / "config" / "dc-motor-sim.toml").read_text()
    text = (sim[:sim.index("[driver]")] + CAN_DRIVER.format(
        dbc=PLANT_DBC, log=log, time_source=time_source).strip() + "\n\n"
        + sim[sim.index("[zenoh]"):])
    text = text.replace("[zenoh]", "[zenoh]\nenabled = false").replace(
        "[recording]", "[recording]\nenabled = false").replace(
        'path = "state.sqlite"', f'path = "{tmp_path / "state.sqlite"}"')
    (tmp_path / "m.toml").write_text(text)
    cfg = load_config(tmp_path / "m.toml")
    with create_any_driver(cfg.driver, base_dir=tmp_path) as driver:
        with Daemon(cfg, driver=driver, publish=False, record=False) as daemon:
            daemon.run()
            c = daemon.counters()
        hist = list(daemon.history)
    kept_set = set(kept)
    syncs_lost = sum(1 for f in frames[2::3] if f not in kept_set)  # the sync frame is third
    assert 0.01 < 1 - len(kept) / len(frames) < 0.03 and syncs_lost > 20
    assert len(hist) == 30 and c["windows_abandoned"] == 0, c
    # a lost sync frame is a missing sample, unless it fell between two windows
    assert syncs_lost - 5 <= c["samples_missing"] <= syncs_lost, (syncs_lost, c)
    truth = DCMotorPlant(DCMotorPlantConfig(duration=60.0, **plant))
    err = np.asarray([h["parameters"]["Ra"]["value"]
                      / truth.truth(0.5 * (h["t_start"] + h["t_end"])).Ra - 1.0
                      for h in hist]) * 100.0
    assert np.all(np.abs(err) <= 0.2), err


# -- a live bus: delivered whatever the estimation does ----------------------------------------
def test_a_live_bus_and_a_paced_log_are_live_sources_a_plant_s_bus_and_a_fast_log_are_not(
        tmp_path: Path, channel: str, tx: can.BusABC, plant_db: Database) -> None:
    """An interface the driver opens, and a log replayed in real time, deliver frames at the
    bus's pace (:attr:`Driver.live`: the daemon drops a window it cannot take, it does not
    stop reading); a bus passed in (a simulated plant's, stepped by the reads) and a log
    replayed as fast as read wait for the estimation."""
    log = tmp_path / "plant.log"
    write_candump_log(log, plant_db, n=3, t0=0.0, period=TS)
    fast = plant_config("unused", log_file=str(log), interface=None)
    for config, bus, live in ((plant_config(channel), None, True),
                              (plant_config(channel), tx, False),
                              ({**fast, "realtime": True}, None, True),
                              (fast, None, False)):
        with CanDriver.from_config(config, base_dir=REPO, bus=bus) as driver:
            assert driver.live is live, (config, bus)


def test_a_live_bus_is_read_on_while_the_estimation_is_behind(
        tmp_path: Path, channel: str, tx: can.BusABC, plant_db: Database,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The daemon on a live interface with a slow estimation (0.4 s a window) and 12 windows'
    frames sent at once: the acquisition reads every frame as it comes (on a real interface a
    reader that waited for the estimation would let the kernel's receive queue overflow),
    the windows the worker's queue cannot take are dropped and counted as overruns, and the
    windows taken are estimated."""
    from harness.sources import CAN_DRIVER
    from harness.sources import plant_frames as plant_stream
    from twinwatch.config.loader import load_config
    from twinwatch.daemon.runner import Daemon
    from twinwatch.twin.estimation.estimator import Estimator

    sim = (REPO / "config" / "dc-motor-sim.toml").read_text()
    table = CAN_DRIVER.format(dbc=PLANT_DBC, log="x.log", time_source="counter").replace(
        'log_file = "x.log"', f'interface = "virtual"\nchannel = "{channel}"')
    text = (sim[:sim.index("[driver]")] + table.strip() + "\n\n" + sim[sim.index("[zenoh]"):])
    text = text.replace("[zenoh]", "[zenoh]\nenabled = false").replace(
        "[recording]", "[recording]\nenabled = false").replace(
        'path = "state.sqlite"', f'path = "{tmp_path / "state.sqlite"}"')
    (tmp_path / "m.toml").write_text(text)
    cfg = load_config(tmp_path / "m.toml")
    cfg.driver.reopen_after = None  # the bus goes quiet after the frames: not a failure here
    estimate = Estimator.estimate

    def slow(self: Estimator, *args: Any, **kwargs: Any) -> Any:
        time.sleep(0.4)
        return estimate(self, *args, **kwargs)

    monkeypatch.setattr(Estimator, "estimate", slow)
    frames = [can.Message(arbitration_id=i, data=d, is_extended_id=False)
              for _, i, d in plant_stream(24.0)]
    with create_any_driver(cfg.driver, base_dir=tmp_path) as driver:
        assert driver.live
        with Daemon(cfg, driver=driver, publish=False, record=False) as daemon:
            runner = threading.Thread(target=daemon.run, name="test-live-can")
            runner.start()
            try:
                for f in frames:
                    tx.send(f)
                start = time.monotonic()
                deadline = start + 60.0
                while driver.stats.frames < len(frames) and time.monotonic() < deadline:
                    time.sleep(0.05)
                read_in = time.monotonic() - start
                assert driver.stats.frames == len(frames), driver.stats
                while (daemon.windows_estimated + daemon.counters()["overruns"] < 12
                       and time.monotonic() < deadline):
                    time.sleep(0.05)
            finally:
                daemon.stop()
                runner.join(30.0)
            c = daemon.counters()
    # 12 windows at 0.4 s each would hold a waiting reader for 4.8 s
    assert read_in < 4.0, read_in
    assert c["windows_completed"] == 12 and c["overruns"] >= 4, c
    assert daemon.windows_estimated + c["overruns"] == 12, c
