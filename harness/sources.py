"""Sources as real machines deliver them, for the tests and the benchmarks.

* :func:`plant_frames`: the simulated DC motor's frames as (time stamp, id, data), on a jittery
  receive clock; :func:`plant_can_log` and :func:`plant_asc_log` write them as a candump or a
  Vector ASC log (malformed lines where asked), :func:`plant_csv` as a CSV file;
* :class:`SocketcandServer`: a tiny server of the socketcand protocol on 127.0.0.1 (python-can's
  ``socketcand`` interface connects to it: a loopback CAN gateway that can be dropped and
  brought back); :class:`MuteGateway`, one that accepts and never answers;
* :func:`dc_modbus_server` and :class:`ServedDevice`: the motor as a Modbus device, in this
  process or in one of its own (``python -m harness.sources``);
* :class:`NotifySocket`: systemd's notification socket, read by the tests.
"""

from __future__ import annotations

import random
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cantools

from harness import ROOT

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
                     plant: dict[str, Any] | None = None, port: int = 0,
                     pacing: str = "realtime") -> Any:
    """The simulated DC motor served as a Modbus TCP device on 127.0.0.1, in real time or in
    lock step with its reader (not started): float32 input registers
    (:data:`DC_MODBUS_REGISTERS`), with or without a uint32 sample counter at address 0."""
    from twinwatch.io.modbus_registers import ModbusChannelMap, ModbusCounterMap
    from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig
    from twinwatch.plant.modbus_server import PlantModbusServer

    cfg = DCMotorPlantConfig(**{"scenario": "nominal", "duration": seconds, "seed": seed,
                                **(plant or {})})
    regs = {ch: ModbusChannelMap(address=a, table="input", type="float32")
            for ch, a in DC_MODBUS_REGISTERS.items()}
    ctr = ModbusCounterMap(address=0, table="input", type="uint32") if counter else None
    return PlantModbusServer(DCMotorPlant(cfg), regs, counter=ctr, pacing=pacing,  # type: ignore[arg-type]
                             port=port)


def dc_modbus_driver(port: int, *, counter: bool = False, poll_period: float | None = None,
                     lockstep: bool = False, extra: str = "") -> str:
    """The ``[driver]`` table reading :func:`dc_modbus_server` (TOML)."""
    lines = ["[driver]", 'type = "modbus"', 'host = "127.0.0.1"', f"port = {port}",
             "timeout = 0.5", "sample_period = 0.01", "backoff_max = 1.0"]
    if lockstep:
        lines.append("lockstep = true")
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


class SocketcandServer:
    """A loopback CAN gateway speaking socketcand's protocol (rawmode) on 127.0.0.1: what
    python-can's ``socketcand`` interface connects to. It streams the simulated DC motor's
    frames (:func:`plant_frames`, counter included) in real time to every client that has
    opened ``channel`` in raw mode.

    :meth:`stop` drops the gateway (the listening socket and every connection closed, as a
    gateway that reboots); :meth:`start` brings it back on the same port. The plant's clock
    runs on meanwhile: the frames of an outage are lost (the counter jumps). ``mute`` names
    messages not sent for now (a node that went silent).

    Args:
        port: TCP port (0: a free one, kept across :meth:`stop`/:meth:`start`).
        channel: the CAN channel it serves.
        seconds: plant time it streams.
    """

    def __init__(self, port: int = 0, *, channel: str = "can0", seconds: float = 3600.0,
                 seed: int = 0, plant: dict[str, Any] | None = None) -> None:
        import socket
        import threading

        if port == 0:
            with socket.socket() as probe:
                probe.bind(("127.0.0.1", 0))
                port = int(probe.getsockname()[1])
        self.port = port
        self.channel = channel
        self.mute: set[int] = set()
        self._seconds, self._seed, self._plant = seconds, seed, plant
        self._lock = threading.Lock()
        self._clients: list[Any] = []
        self._listener: Any = None
        self._accepting: Any = None
        self._closed = threading.Event()
        self._streamer = threading.Thread(target=self._stream, name="socketcand-stream",
                                          daemon=True)

    # -- lifecycle ----------------------------------------------------------------------------
    def start(self) -> SocketcandServer:
        import socket
        import threading

        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("127.0.0.1", self.port))
        listener.listen(8)
        self._listener = listener
        self._accepting = threading.Thread(target=self._accept, args=(listener,),
                                           name="socketcand-accept", daemon=True)
        self._accepting.start()
        if not self._streamer.is_alive() and not self._closed.is_set():
            self._streamer.start()
        return self

    def stop(self) -> None:
        """Drop the gateway: stop listening and close every connection."""
        import contextlib
        import socket

        listener, self._listener = self._listener, None
        if listener is not None:
            with contextlib.suppress(OSError):
                listener.shutdown(socket.SHUT_RDWR)
            listener.close()
        if self._accepting is not None:
            self._accepting.join(2.0)
        with self._lock:
            clients, self._clients = self._clients, []
        for c in clients:
            with contextlib.suppress(OSError):
                c.shutdown(socket.SHUT_RDWR)
            c.close()

    def close(self) -> None:
        self._closed.set()
        self.stop()
        if self._streamer.is_alive():
            self._streamer.join(2.0)

    def __enter__(self) -> SocketcandServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the protocol -------------------------------------------------------------------------
    def _accept(self, listener: Any) -> None:
        import threading

        while True:
            try:
                conn, _ = listener.accept()
            except OSError:
                return
            threading.Thread(target=self._handshake, args=(conn,), name="socketcand-client",
                             daemon=True).start()

    def _handshake(self, conn: Any) -> None:
        """``< hi >``, then ``< open CHANNEL >`` -> ``< ok >``, ``< rawmode >`` -> ``< ok >``;
        the client then gets the frames."""
        try:
            conn.sendall(b"< hi >")
            for expected in (f"< open {self.channel} >", "< rawmode >"):
                got = conn.recv(256).decode("ascii", "replace").strip()
                if got != expected:
                    conn.close()  # a probe that only connects, or another channel
                    return
                conn.sendall(b"< ok >")
        except OSError:
            conn.close()
            return
        with self._lock:
            if self._listener is None:
                conn.close()
                return
            self._clients.append(conn)

    def _stream(self) -> None:
        import time

        start: float | None = None
        for stamp, frame_id, data in plant_frames(self._seconds, seed=self._seed,
                                                  plant=self._plant):
            if self._closed.is_set():
                return
            if start is None:  # the plant's kernel compiled: its clock starts now
                start = time.monotonic() - stamp
            delay = start + stamp - time.monotonic()
            if delay > 0 and self._closed.wait(delay):
                return
            if frame_id in self.mute:
                continue
            line = f"< frame {frame_id:03X} {time.time():.6f} {data.hex().upper()} >"
            with self._lock:
                clients = list(self._clients)
            for c in clients:
                try:
                    c.sendall(line.encode("ascii"))
                except OSError:
                    with self._lock:
                        if c in self._clients:
                            self._clients.remove(c)


class MuteGateway:
    """A TCP server on 127.0.0.1 that accepts connections and never answers: python-can's
    socketcand bus waits for its greeting for ever, so opening a source on it does not return
    (a stand-in for a source whose opening takes long). :attr:`connections` counts them."""

    def __init__(self) -> None:
        import socket
        import threading

        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(8)
        self.port = int(self.sock.getsockname()[1])
        self.connections = 0
        self._conns: list[Any] = []
        self._thread = threading.Thread(target=self._accept, name="mute-gateway", daemon=True)
        self._thread.start()

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            self._conns.append(conn)
            self.connections += 1

    def wait_for(self, n: int, timeout: float) -> bool:
        """True once ``n`` connections were accepted."""
        import time

        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.connections >= n:
                return True
            time.sleep(0.02)
        return False

    def close(self) -> None:
        import contextlib
        import socket

        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()
        for c in self._conns:
            c.close()


def gateway_config(tmp: Path, port: int, **kw: Any) -> Path:
    """The simulated motor's example config reading the plant's frames from a socketcand
    gateway on 127.0.0.1:``port`` (time source: the plant's sample counter), running until
    stopped."""
    from harness.daemon import with_driver

    driver = CAN_DRIVER.format(dbc=PLANT_DBC, log="", time_source="counter").replace(
        'log_file = ""', 'interface = "socketcand"\nchannel = "can0"\n'
        f'bus_options = {{ host = "127.0.0.1", port = {port} }}')
    return with_driver(tmp, driver, duration=100000.0, **kw)


class ServedDevice:
    """:func:`dc_modbus_server` in a process of its own (as a device on the network is: its
    timing does not share this process's interpreter), until :meth:`close`. ``exceptions``:
    ``(from, to, code)`` [s after it started]: every read is answered with Modbus exception
    ``code`` meanwhile.

    Attributes:
        port: the TCP port it listens on (127.0.0.1).
    """

    def __init__(self, *, counter: bool = False, seed: int = 0, port: int = 0,
                 plant: dict[str, Any] | None = None, seconds: float = 3600.0,
                 exceptions: list[tuple[float, float, int]] = (),  # type: ignore[assignment]
                 pacing: str = "realtime") -> None:
        import json
        import subprocess
        import sys

        args = json.dumps({"counter": counter, "seed": seed, "port": port, "plant": plant,
                           "seconds": seconds, "exceptions": list(exceptions),
                           "pacing": pacing})
        self.proc = subprocess.Popen([sys.executable, "-m", "harness.sources", args],
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
    """``python -m harness.sources JSON``: serve until stdin closes."""
    import sys
    import threading
    import time

    srv = dc_modbus_server(args["seconds"], counter=args["counter"], seed=args["seed"],
                           plant=args["plant"], port=args["port"],
                           pacing=args["pacing"]).start()
    start = time.monotonic()

    def schedule() -> None:
        for t0, t1, code in args["exceptions"]:
            time.sleep(max(0.0, start + t0 - time.monotonic()))
            srv.exception_code = code
            time.sleep(max(0.0, start + t1 - time.monotonic()))
            srv.exception_code = None

    threading.Thread(target=schedule, daemon=True).start()
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
