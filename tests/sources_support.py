"""Sources as real machines deliver them, for the issue 15 tests and benchmarks.

* :func:`plant_can_log`: a candump log of the simulated DC motor (the package's DBC), with
  frame time stamps on a jittery clock, duplicated or reordered counter frames and malformed
  lines where asked;
* :class:`SocketcandServer`: a tiny server of the socketcand protocol on 127.0.0.1 (python-can's
  ``socketcand`` interface connects to it: a loopback CAN gateway that can be dropped and
  brought back);
* :func:`frame_lines`: a plant's frames as (time stamp, id, data).
"""

from __future__ import annotations

import random
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cantools

from .conftest import ROOT

PLANT_DBC = ROOT / "twinwatch" / "plant" / "dcmotor.dbc"
MESSAGES = (("TW_Motor_Electrical", ("Va", "ia")),
            ("TW_Motor_Mechanical", ("omega", "Tload")),
            ("TW_Motor_Sample", ("setpoint",)))


def plant_frames(seconds: float, *, jitter: float = 0.0, seed: int = 0,
                 plant: dict[str, Any] | None = None, counter_bits: int = 32
                 ) -> Iterator[tuple[float, int, bytes]]:
    """The simulated DC motor's frames (three per 10 ms sample, the sync frame last):
    ``(time stamp [s], arbitration id, data)``. Each frame's stamp is its sample's time plus
    a uniform error in [-jitter, jitter] [s] (a bus adapter's receive stamp)."""
    from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig

    db = cantools.database.load_file(PLANT_DBC)
    msgs = [(db.get_message_by_name(m), sigs) for m, sigs in MESSAGES]
    cfg = DCMotorPlantConfig(**{"scenario": "nominal", "duration": seconds, **(plant or {})})
    p = DCMotorPlant(cfg)
    rng = random.Random(seed)
    last = 0.0
    for k in range(int(round(seconds / cfg.sample_period))):
        s = p.next_sample()
        for msg, sigs in msgs:
            data = {x: s.values[x] for x in sigs}
            if msg.name == "TW_Motor_Sample":
                data["sample_counter"] = k % (1 << counter_bits)
            stamp = max(last, s.t + rng.uniform(-jitter, jitter))  # a receive clock: monotonic
            last = stamp
            yield stamp, msg.frame_id, msg.encode(data)


def candump_line(stamp: float, frame_id: int, data: bytes, channel: str = "can0") -> str:
    return f"({stamp:.6f}) {channel} {frame_id:03X}#{data.hex().upper()}"


def plant_can_log(path: Path, seconds: float, *, jitter: float = 0.0, seed: int = 0,
                  plant: dict[str, Any] | None = None) -> Path:
    """A candump log of :func:`plant_frames`."""
    path.write_text("\n".join(candump_line(*f) for f in plant_frames(
        seconds, jitter=jitter, seed=seed, plant=plant)) + "\n")
    return path


CAN_DRIVER = """
[driver]
type = "can"
dbc = "{dbc}"
log_file = "{log}"
sync_message = "TW_Motor_Sample"
time_source = "{time_source}"
counter_signal = "TW_Motor_Sample.sample_counter"
sample_period = 0.01
[driver.signals]
Va = {{ message = "TW_Motor_Electrical", signal = "Va" }}
ia = {{ message = "TW_Motor_Electrical", signal = "ia" }}
omega = {{ message = "TW_Motor_Mechanical", signal = "omega" }}
Tload = {{ message = "TW_Motor_Mechanical", signal = "Tload" }}
setpoint = {{ message = "TW_Motor_Sample", signal = "setpoint" }}
"""


#: the DC motor's channels as float32 input registers (no counter: a device stamped by the
#: poll clock); the counter, where used, at address 0
DC_MODBUS_REGISTERS = {"Va": 2, "ia": 4, "omega": 6, "Tload": 8, "setpoint": 10}


def dc_modbus_server(seconds: float, *, counter: bool = False, seed: int = 0,
                     plant: dict[str, Any] | None = None, port: int = 0) -> Any:
    """The simulated DC motor served as a Modbus TCP device on 127.0.0.1 in real time (not
    started): float32 input registers (:data:`DC_MODBUS_REGISTERS`), with or without a uint32
    sample counter at address 0."""
    from twinwatch.io.modbus_registers import ModbusChannelMap, ModbusCounterMap
    from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig
    from twinwatch.plant.modbus_server import PlantModbusServer

    cfg = DCMotorPlantConfig(**{"scenario": "nominal", "duration": seconds, "seed": seed,
                                **(plant or {})})
    regs = {ch: ModbusChannelMap(address=a, table="input", type="float32")
            for ch, a in DC_MODBUS_REGISTERS.items()}
    ctr = ModbusCounterMap(address=0, table="input", type="uint32") if counter else None
    return PlantModbusServer(DCMotorPlant(cfg), regs, counter=ctr, pacing="realtime",
                             port=port)


def dc_modbus_driver(port: int, *, counter: bool = False, poll_period: float | None = None,
                     extra: str = "") -> str:
    """The ``[driver]`` table reading :func:`dc_modbus_server` (TOML)."""
    lines = ["[driver]", 'type = "modbus"', 'host = "127.0.0.1"', f"port = {port}",
             "timeout = 0.5", "sample_period = 0.01", "backoff_max = 1.0"]
    if poll_period is not None:
        lines.append(f"poll_period = {poll_period}")
    if counter:
        lines += ['time_source = "counter"',
                  'counter = { address = 0, table = "input", type = "uint32" }']
    else:
        lines.append('time_source = "clock"')
    lines.append(extra)
    lines.append("[driver.registers]")
    lines += [f'{ch} = {{ address = {a}, table = "input", type = "float32" }}'
              for ch, a in DC_MODBUS_REGISTERS.items()]
    return "\n".join(lines)


def plant_csv(path: Path, seconds: float, *, jitter: float = 0.0, seed: int = 0,
              plant: dict[str, Any] | None = None) -> Path:
    """A CSV recording of the simulated DC motor with a time column ``t`` [s] whose values
    carry a uniform error in [-jitter, jitter] (a logger's clock)."""
    from twinwatch.plant.dcmotor import CHANNELS, DCMotorPlant, DCMotorPlantConfig

    cfg = DCMotorPlantConfig(**{"scenario": "nominal", "duration": seconds, **(plant or {})})
    p = DCMotorPlant(cfg)
    rng = random.Random(seed)
    rows = ["t," + ",".join(CHANNELS)]
    for _ in range(int(round(seconds / cfg.sample_period))):
        s = p.next_sample()
        rows.append(f"{s.t + rng.uniform(-jitter, jitter):.7f}," + ",".join(
            repr(s.values[c]) for c in CHANNELS))
    path.write_text("\n".join(rows) + "\n")
    return path


FILE_DRIVER = """
[driver]
type = "file"
path = "{path}"
time_column = "t"
sample_period = 0.01
[driver.columns]
Va = {{ column = "Va" }}
ia = {{ column = "ia" }}
omega = {{ column = "omega" }}
Tload = {{ column = "Tload" }}
setpoint = {{ column = "setpoint" }}
"""


class NotifySocket:
    """systemd's notification socket (``NOTIFY_SOCKET``) for a test: collects the datagrams."""

    def __init__(self, path: Path) -> None:
        import socket

        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0)
        self.messages: list[str] = []

    def drain(self) -> list[str]:
        """Every datagram received so far (kept in :attr:`messages`)."""
        while True:
            try:
                self.messages.append(self.sock.recv(65536).decode())
            except BlockingIOError:
                return self.messages

    def statuses(self) -> list[str]:
        """The ``STATUS=`` lines received so far, in order."""
        return [ln.removeprefix("STATUS=") for m in self.drain() for ln in m.splitlines()
                if ln.startswith("STATUS=")]

    def close(self) -> None:
        self.sock.close()


class ServedDevice:
    """:func:`dc_modbus_server` in a process of its own (as a device on the network is: its
    timing does not share this process's interpreter), until :meth:`close`.

    Attributes:
        port: the TCP port it listens on (127.0.0.1).
    """

    def __init__(self, *, counter: bool = False, seed: int = 0, port: int = 0,
                 plant: dict[str, Any] | None = None, seconds: float = 3600.0) -> None:
        import json
        import subprocess
        import sys

        args = json.dumps({"counter": counter, "seed": seed, "port": port, "plant": plant,
                           "seconds": seconds})
        self.proc = subprocess.Popen([sys.executable, "-m", "tests.sources_support", args],
                                     cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     text=True)
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line.startswith("port "):
            self.close()
            raise RuntimeError(f"the device did not start: {line!r}")
        self.port = int(line.split()[1])

    def close(self) -> None:
        if self.proc.poll() is None:
            assert self.proc.stdin is not None
            self.proc.stdin.close()
            try:
                self.proc.wait(10)
            except Exception:  # noqa: BLE001 - a hung server is killed
                self.proc.kill()
                self.proc.wait()
        if self.proc.stdout is not None:
            self.proc.stdout.close()

    def __enter__(self) -> ServedDevice:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _serve(args: dict[str, Any]) -> None:
    """``python -m tests.sources_support JSON``: serve until stdin closes."""
    import sys

    srv = dc_modbus_server(args["seconds"], counter=args["counter"], seed=args["seed"],
                           plant=args["plant"], port=args["port"]).start()
    print(f"port {srv.port}", flush=True)
    sys.stdin.read()
    srv.stop()


if __name__ == "__main__":
    import json
    import sys

    _serve(json.loads(sys.argv[1]))


def plant_asc_log(path: Path, seconds: float, *, bad: int = 0, seed: int = 0) -> int:
    """A Vector ASC log (python-can's writer: header, absolute time stamps) of the simulated
    DC motor, with ``bad`` of its frame lines replaced by malformed ones, spread evenly.

    Returns:
        The log's number of lines.
    """
    import can

    with can.ASCWriter(path) as writer:
        for stamp, frame_id, data in plant_frames(seconds, seed=seed):
            writer.on_message_received(can.Message(timestamp=stamp, arbitration_id=frame_id,
                                                   data=data, is_extended_id=False))
    lines = path.read_text().splitlines()
    frames = [i for i, ln in enumerate(lines) if " Rx " in ln]
    for j in range(bad):
        i = frames[(j * len(frames)) // bad + len(frames) // (2 * bad)]
        lines[i] = lines[i].split(" Rx ")[0] + " Rx   d 8 ZZ"  # a data byte that is not hex
    path.write_text("\n".join(lines) + "\n")
    return len(lines)
