"""The OPC UA input (issue 35): drivers/opcua.py against a real asyncua server on a free
loopback port, and the simulated DC motor over OPC UA through the whole daemon.

The fast tests start a small server in the test (:func:`_server`: one object, variables with
EngineeringUnits, values written with source timestamps and status codes) and assert what the
driver delivers: samples joined by source timestamp, status codes as missing samples, counted
gaps, refusals naming the key. The slow ones run the daemon on the simulated motor.
"""

from __future__ import annotations

import asyncio
import math
import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from twinwatch.drivers import DriverConfigError, DriverInitializationError, create_driver
from twinwatch.drivers.opcua import OpcUaDriver, OpcUaDriverConfig, unit_matches

asyncua = pytest.importorskip("asyncua")
from asyncua import Server, ua  # noqa: E402

CHANNELS = {"Va": "V", "ia": "A"}
PERIOD = 0.01
EPOCH = datetime(1970, 1, 1, tzinfo=UTC)


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class _TestServer:
    """An asyncua server in a thread: object Dev with Double variables (EngineeringUnits);
    :meth:`write` puts values with a given source timestamp and status code."""

    def __init__(self, units: dict[str, str], port: int | None = None,
                 users: dict[str, str] | None = None, pki: dict[str, Path] | None = None,
                 trusted: Path | None = None) -> None:
        self.pki = pki  # server certificate and key: Basic256Sha256 SignAndEncrypt only
        self.trusted = trusted  # a directory of trusted client certificates (None: any)
        self.units = units
        self.port = port or _free_port()
        self.users = users
        self.loop: asyncio.AbstractEventLoop | None = None
        self.server: Any = None
        self.nodes: dict[str, Any] = {}
        self._ready = threading.Event()
        self._stop: asyncio.Event | None = None
        self._thread = threading.Thread(target=self._main, daemon=True)

    @property
    def endpoint(self) -> str:
        return f"opc.tcp://127.0.0.1:{self.port}"

    def start(self) -> _TestServer:
        self._thread.start()
        assert self._ready.wait(30)
        return self

    def stop(self) -> None:
        if self.loop is not None and self._stop is not None:
            self.loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(10)

    def _main(self) -> None:
        asyncio.run(self._serve())

    async def _serve(self) -> None:
        from asyncua.crypto.permission_rules import SimpleRoleRuleset  # noqa: F401
        from asyncua.server.user_managers import UserManager

        self.loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        users = self.users

        class Users(UserManager):
            def get_user(self, iserver: Any, username: str | None = None,
                         password: str | None = None, certificate: Any = None) -> Any:
                from asyncua.crypto.permission_rules import User, UserRole
                if users is None:
                    return User(role=UserRole.User)
                if username in users and users[username] == password:
                    return User(role=UserRole.User)
                return None

        self.server = Server(user_manager=Users())
        await self.server.init()
        self.server.set_endpoint(self.endpoint)
        if self.pki is None:
            self.server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        else:
            await self.server.load_certificate(str(self.pki["server.der"]))
            await self.server.load_private_key(str(self.pki["server.pem"]))
            self.server.set_security_policy(
                [ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt])
            if self.trusted is not None:
                from asyncua.crypto.truststore import TrustStore
                from asyncua.crypto.validator import (
                    CertificateValidator,
                    CertificateValidatorOptions,
                )

                store = TrustStore([self.trusted], [])
                await store.load()
                self.server.set_certificate_validator(
                    CertificateValidator(CertificateValidatorOptions.TRUSTED_VALIDATION
                                         | CertificateValidatorOptions.PEER_CLIENT,
                                         trust_store=store).validate)
        ns = await self.server.register_namespace("urn:test")
        obj = await self.server.nodes.objects.add_object(ua.NodeId("Dev", ns),
                                                         ua.QualifiedName("Dev", ns))
        for ch, unit in self.units.items():
            var = await obj.add_variable(ua.NodeId(f"Dev.{ch}", ns), ua.QualifiedName(ch, ns),
                                         0.0)
            if unit:
                eu = ua.EUInformation(DisplayName=ua.LocalizedText(unit), UnitId=-1)
                await var.add_property(ua.NodeId(f"Dev.{ch}.EU", ns),
                                       ua.QualifiedName("EngineeringUnits", 0),
                                       ua.Variant(eu, ua.VariantType.ExtensionObject))
            self.nodes[ch] = var.nodeid
            # the initial value, as a device's server holds it: sample 0 of the source clock
            await self.server.write_attribute_value(var.nodeid, ua.DataValue(
                ua.Variant(0.0, ua.VariantType.Double),
                SourceTimestamp=EPOCH + timedelta(seconds=BASE)))
        await self.server.start()
        self._ready.set()
        await self._stop.wait()
        await self.server.stop()

    def write(self, k: int, values: dict[str, float], *, base: float,
              status: dict[str, int] | None = None, source: bool = True) -> None:
        """Write sample ``k`` (source time ``base + k * PERIOD``)."""
        async def put() -> None:
            stamp = EPOCH + timedelta(seconds=base + k * PERIOD)
            for ch, v in values.items():
                code = (status or {}).get(ch, 0)
                dv = ua.DataValue(ua.Variant(v, ua.VariantType.Double),
                                  StatusCode=ua.StatusCode(code),
                                  SourceTimestamp=stamp if source else None,
                                  ServerTimestamp=datetime.now(UTC))
                await self.server.write_attribute_value(self.nodes[ch], dv)

        assert self.loop is not None
        asyncio.run_coroutine_threadsafe(put(), self.loop).result(10)


@contextmanager
def _server(units: dict[str, str] | None = None, **kw: Any) -> Iterator[_TestServer]:
    srv = _TestServer(CHANNELS if units is None else units, **kw).start()
    try:
        yield srv
    finally:
        srv.stop()


def _config(srv: _TestServer, **kw: Any) -> OpcUaDriverConfig:
    channels = kw.pop("channels", None) or {
        ch: {"node": f"ns=2;s=Dev.{ch}", "unit": unit} for ch, unit in CHANNELS.items()}
    return OpcUaDriverConfig.model_validate({
        "type": "opcua", "endpoint": srv.endpoint, "sample_period": PERIOD,
        "publishing_interval": 0.05, "timeout": 1.0, "backoff_max": 0.5,
        "channels": channels, **kw})


def _read_all(driver: OpcUaDriver, n: int, timeout: float = 5.0) -> list[Any]:
    out = []
    deadline = time.monotonic() + timeout
    while len(out) < n and time.monotonic() < deadline:
        s = driver.read(0.1)
        if s is not None:
            out.append(s)
    return out


BASE = 1.8e9  # a source-time base [POSIX s]: the driver's time_origin


def test_samples_are_joined_by_source_timestamp_every_one_delivered():
    """100 samples written in bursts of 10 (as a 10 ms device in 100 ms notifications): all
    delivered, in order, each with both channels of its own time stamp, none counted lost."""
    with _server() as srv, OpcUaDriver(_config(srv), time_origin=BASE) as d:
        assert [s.t for s in _read_all(d, 1)] == [0.0]  # the initial values: sample 0
        srv.write(999, {"Va": -1.0, "ia": -0.5}, base=BASE)
        assert [round(s.t / PERIOD) for s in _read_all(d, 1)] == [999]
        assert d.stats.gaps == 998  # 1-998 never written
        for burst in range(10):
            for k in range(burst * 10, burst * 10 + 10):
                srv.write(1000 + k, {"Va": float(k), "ia": 0.5 * k}, base=BASE)
            time.sleep(0.1)
        got = _read_all(d, 100)
        assert [round(s.t / PERIOD) for s in got] == list(range(1000, 1100))
        assert all(s.values["ia"] == 0.5 * s.values["Va"] for s in got)
        assert d.stats.extra["overflows"] == 0 and d.stats.extra["dropped"] == 0
        assert d.stats.gaps == 998, d.stats.as_dict()


def test_a_bad_status_is_a_missing_sample_counted_per_channel_and_an_overflow_counted():
    with _server() as srv, OpcUaDriver(_config(srv), time_origin=BASE) as d:
        for k in range(1, 11):
            status = {"ia": 0x80000000} if k in (4, 5) else None  # Bad on ia for two samples
            if k == 7:  # Good with the Overflow info bits: the server discarded older values
                status = {"Va": 0x480}
            srv.write(k, {"Va": 1.0 * k, "ia": 2.0 * k}, base=BASE, status=status)
        got = _read_all(d, 9)
        slots = [round(s.t / PERIOD) for s in got]
        assert slots == [0, 1, 2, 3, 6, 7, 8, 9, 10]
        assert all(math.isfinite(v) for s in got for v in s.values.values())
        assert d.stats.extra["status_ia"] == 2 and d.stats.extra["status_Va"] == 0
        assert d.stats.gaps == 2
        assert d.stats.extra["overflows"] == 1 and got[slots.index(7)].values["Va"] == 7.0


def test_samples_missing_with_a_bad_status_are_held_over_by_the_daemons_ring_buffer():
    """Issue 56: two samples whose ia is Bad (a device's read failing now and then) are
    missing; with the daemon's default limits the window keeps its other samples, the two
    slots holding the previous sample's values, instead of being abandoned."""
    from twinwatch.config.schema import AcquisitionConfig
    from twinwatch.daemon.ringbuffer import RingBuffer

    acq = AcquisitionConfig()
    ring = RingBuffer(("Va", "ia"), window=20, sample_period=PERIOD,
                      max_missing=acq.max_missing, max_missing_run=acq.max_missing_run)
    with _server() as srv, OpcUaDriver(_config(srv), time_origin=BASE) as d:
        for k in range(1, 21):
            status = {"ia": 0x80000000} if k in (8, 9) else None
            srv.write(k, {"Va": 1.0 * k, "ia": 2.0 * k}, base=BASE, status=status)
        got = _read_all(d, 19)
        assert d.stats.gaps == 2
    wins = [w for s in got if (w := ring.append(s.t, s.values)) is not None]
    assert len(wins) == 1 and sum(ring.causes.values()) == 0 and ring.missing == 2
    va = wins[0]["Va"]
    assert list(va[7:11]) == [7.0, 7.0, 7.0, 10.0] and list(wins[0]["ia"][7:11]) == [
        14.0, 14.0, 14.0, 20.0]


def test_a_channel_that_stops_is_named_silent_and_its_samples_counted_missing():
    with _server() as srv, OpcUaDriver(_config(srv), time_origin=BASE) as d:
        for k in range(1, 6):
            srv.write(k, {"Va": 1.0, "ia": 1.0}, base=BASE)
        assert len(_read_all(d, 6)) == 6 and d.silent == ()
        for k in range(6, 40):  # ia's variable stops updating; Va goes on
            srv.write(k, {"Va": 1.0}, base=BASE)
            time.sleep(0.05)
        assert [s.split(" for ")[0] for s in d.silent] == ["ia"]
        srv.write(40, {"Va": 1.0, "ia": 1.0}, base=BASE)
        got = _read_all(d, 1)
        assert [round(s.t / PERIOD) for s in got] == [40] and d.stats.gaps == 34


def test_a_server_without_source_timestamps_gives_server_timestamps_said_once(caplog):
    with _server() as srv, OpcUaDriver(_config(srv)) as d:
        for k in range(5):  # a changing value: without source time stamps, only a change
            srv.write(k, {"Va": 1.0 + k, "ia": 2.0 + k}, base=BASE, source=False)
            time.sleep(PERIOD)
        got = _read_all(d, 2)
        # POSIX seconds of the server (an hour either way: not the plant's seconds from 0,
        # and no bound on how late a loaded box reads them)
        assert got and abs(got[-1].t - time.time()) < 3600.0
        # every value is counted once its notification is in (the suite on two workers: 8 of
        # 10 when the samples were read)
        deadline = time.monotonic() + 5.0
        while d.stats.extra.get("server_stamps", 0) < 10 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert d.stats.extra["server_stamps"] == 10
    assert sum("sends no source timestamps" in r.message for r in caplog.records) == 1


def test_browse_path_finds_the_node():
    with _server() as srv:
        cfg = _config(srv, channels={"Va": {"browse_path": "0:Objects/2:Dev/2:Va", "unit": "V"},
                                     "ia": {"node": "ns=2;s=Dev.ia"}})
        with OpcUaDriver(cfg, time_origin=BASE) as d:
            srv.write(3, {"Va": 7.0, "ia": 1.0}, base=BASE)
            got = _read_all(d, 2)
            assert got[-1].values == {"Va": 7.0, "ia": 1.0}


@pytest.mark.parametrize(("channels", "key", "words"), [
    ({"Va": {"node": "ns=2;s=Dev.nope"}}, "driver.channels.Va.node", "no node ns=2;s=Dev.nope"),
    ({"Va": {"browse_path": "0:Objects/2:Dev/2:nope"}}, "driver.channels.Va.browse_path",
     "matches nothing"),
    ({"Va": {"node": "ns=2;s=Dev.Va", "unit": "mV"}}, "driver.channels.Va.unit",
     "is in 'V'"),
    ({"Va": {"node": "ns=2;s=Dev"}}, "driver.channels.Va", "is a Object, not a Variable"),
])
def test_start_refuses_a_bad_node_or_unit_in_one_line(channels, key, words):
    with _server() as srv:
        with pytest.raises(DriverConfigError) as exc:
            OpcUaDriver(_config(srv, channels=channels))
    msg = str(exc.value)
    assert msg.startswith(key) and words in msg and "\n" not in msg
    if "unit" in key:
        assert "'mV'" in msg and "ns=2;s=Dev.Va" in msg


def test_start_refuses_a_user_the_server_rejects(tmp_path: Path):
    pw = tmp_path / "pw"
    pw.write_text("wrong\n")
    with _server(users={"op": "right"}) as srv:
        with pytest.raises(DriverConfigError) as exc:
            OpcUaDriver(_config(srv, username="op", password_file=str(pw)))
        assert str(exc.value).startswith("driver.username:") and "'op'" in str(exc.value)
        pw.write_text("right\n")
        with OpcUaDriver(_config(srv, username="op", password_file=str(pw)),
                         time_origin=BASE) as d:
            srv.write(1, {"Va": 1.0, "ia": 1.0}, base=BASE)
            assert _read_all(d, 1)


def _pki(tmp: Path) -> dict[str, Path]:
    """A self-signed server and client certificate (DER) and their keys (PEM)."""
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID

    for who, use in (("server", ExtendedKeyUsageOID.SERVER_AUTH),
                     ("client", ExtendedKeyUsageOID.CLIENT_AUTH)):
        asyncio.run(setup_self_signed_certificate(
            tmp / f"{who}.pem", tmp / f"{who}.der", f"urn:twinwatch:test-{who}",
            socket.gethostname(), [use], {"commonName": f"twinwatch test {who}"}))
    return {p.name: p for p in tmp.iterdir()}


@pytest.mark.slow
def test_basic256sha256_sign_and_encrypt_and_an_untrusted_certificate(tmp_path: Path):
    pki = _pki(tmp_path)
    secure = {"security_policy": "Basic256Sha256", "security_mode": "SignAndEncrypt",
              "certificate": str(pki["client.der"]), "private_key": str(pki["client.pem"]),
              "server_certificate": str(pki["server.der"])}
    trusted = tmp_path / "trusted"
    trusted.mkdir()
    (trusted / "client.der").write_bytes(pki["client.der"].read_bytes())
    with _server(pki=pki, trusted=trusted) as srv:
        with OpcUaDriver(_config(srv, **secure), time_origin=BASE) as d:
            srv.write(1, {"Va": 3.0, "ia": 4.0}, base=BASE)
            got = _read_all(d, 2)
            assert got[-1].values == {"Va": 3.0, "ia": 4.0}
        with pytest.raises(DriverInitializationError):  # the server offers no None endpoint
            OpcUaDriver(_config(srv))
    other = tmp_path / "others"  # trusts another certificate only (asyncua: not empty)
    other.mkdir()
    (other / "server.der").write_bytes(pki["server.der"].read_bytes())
    with _server(pki=pki, trusted=other) as srv:
        with pytest.raises(DriverConfigError) as exc:
            OpcUaDriver(_config(srv, **secure))
    assert str(exc.value).startswith("driver.certificate: the OPC UA server")
    assert "refused the client certificate" in str(exc.value)


def _opcua_machine(tmp_path: Path, driver: dict[str, Any]) -> Path:
    """The OPC UA example with its ``[driver]`` table replaced by ``driver``."""
    src = Path(__file__).parents[1] / "config" / "dc-motor-opcua-sim.toml"
    head, _, rest = src.read_text().partition("[driver]")
    rest = rest[rest.index("\n[zenoh]"):].replace("[zenoh]", "[zenoh]\nenabled = false", 1)
    channels = driver.pop("channels")
    lines = ["[driver]", *(f"{k} = {_toml(v)}" for k, v in driver.items()), "[driver.channels]",
             *(f"{ch} = {_toml(m)}" for ch, m in channels.items()), ""]
    path = tmp_path / "m.toml"
    path.write_text(head + "\n".join(lines) + rest)
    return path


def test_a_server_without_the_configured_security_is_a_configuration_error(tmp_path: Path,
                                                                            caplog: Any):
    """Issue 56: a server that offers Basic256Sha256 SignAndEncrypt only, a configuration
    asking for no security: one line naming driver.security_policy and what the server
    offers; `run` exits 78 at once instead of waiting for a server that will never accept it
    (before: retried as "not available" forever, 60 s later still waiting), and check-config
    says it."""
    from click.testing import CliRunner

    from twinwatch.cli import main

    pki = _pki(tmp_path)
    with _server(pki=pki) as srv:
        with pytest.raises(DriverConfigError) as exc:
            OpcUaDriver(_config(srv))
        line = str(exc.value)
        assert line.startswith("driver.security_policy: the OPC UA server")
        assert "no endpoint for security 'None'" in line
        assert "it offers Basic256Sha256 SignAndEncrypt" in line and "\n" not in line
        channels = {ch: {"node": f"ns=2;s=Dev.{ch}"} for ch in ("Va", "ia", "omega", "Tload",
                                                                 "setpoint")}
        path = _opcua_machine(tmp_path, {"type": "opcua", "endpoint": srv.endpoint,
                                         "sample_period": 0.01, "channels": channels})
        start = time.monotonic()
        r = CliRunner().invoke(main, ["run", "--no-progress", str(path)])
        took = time.monotonic() - start
        print(f"\nrun exited {r.exit_code} after {took:.2f} s")
        assert r.exit_code == 78, r.output
        assert "driver.security_policy: the OPC UA server" in r.output, r.output
        assert "not available" not in r.output + caplog.text  # refused, not waited for
        r = CliRunner().invoke(main, ["check-config", str(path)])
        assert r.exit_code == 1 and "driver.security_policy:" in r.output, r.output


def test_a_killed_server_is_one_error_line(caplog: Any):
    """Issue 56: the server goes away under a running acquisition: the driver's ERROR is the
    only one (before: the acquisition loop's generic "check the device, cable and bus" too);
    its stall line is INFO, naming what the driver waits for."""
    import logging

    from twinwatch.config.loader import default_config
    from twinwatch.daemon.acquisition import Acquisition
    from twinwatch.twin.models import create_model

    cfg = default_config()
    cfg.acquisition.stall_timeout = 0.5
    caplog.set_level(logging.INFO)
    srv = _TestServer(CHANNELS).start()
    driver = OpcUaDriver(_config(srv), time_origin=BASE)
    acq = Acquisition(cfg, create_model(cfg.machine.model, {}), own_driver=False)
    acq.open(driver, base_dir=Path("."), wait=False)
    runner = threading.Thread(target=acq.run, args=(None, lambda w, b: None, lambda n: None))
    runner.start()
    try:
        for k in range(1, 6):
            srv.write(k, {"Va": 1.0, "ia": 1.0}, base=BASE)
        srv.stop()
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and "no sample from" not in caplog.text:
            time.sleep(0.05)
    finally:
        acq.stop()
        runner.join(10)
        driver.close()
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR
              and r.name.startswith("twinwatch")]
    assert len(errors) == 1 and errors[0].startswith("OPC UA server"), errors
    stall = [r for r in caplog.records if r.getMessage().startswith("no sample from")]
    assert len(stall) == 1 and stall[0].levelno == logging.INFO
    assert "away for" in stall[0].getMessage()


def test_an_unreachable_server_is_an_initialization_error_the_daemon_waits_for():
    cfg = OpcUaDriverConfig.model_validate({
        "type": "opcua", "endpoint": f"opc.tcp://127.0.0.1:{_free_port()}",
        "sample_period": PERIOD, "timeout": 0.5, "channels": {"Va": {"node": "ns=2;s=X"}}})
    with pytest.raises(DriverInitializationError) as exc:
        OpcUaDriver(cfg)
    assert not isinstance(exc.value, DriverConfigError)
    assert OpcUaDriver.reopens(cfg)


@pytest.mark.parametrize(("table", "words"), [
    ({"security_policy": "Basic128Rsa15"}, "security_policy"),
    ({"security_policy": "Basic256Sha256"}, "needs security_mode, certificate, private_key"),
    ({"security_mode": "Sign"}, "need security_policy = 'Basic256Sha256'"),
    ({"password": "x"}, "a password needs a username"),
    ({"endpoint": "http://127.0.0.1:4840"}, "endpoint"),
    ({"channels": {"Va": {}}}, "give node (a NodeId string) or browse_path"),
])
def test_check_config_refuses_what_it_can_know_offline(table, words, tmp_path: Path):
    from twinwatch.config.loader import ConfigError, load_config

    src = Path(__file__).parents[1] / "config" / "dc-motor-opcua-sim.toml"
    text = src.read_text()
    driver = {"type": "opcua", "endpoint": "opc.tcp://127.0.0.1:4841", "sample_period": 0.01,
              "channels": {ch: {"node": f"ns=2;s=Motor.{ch}"} for ch in
                           ("Va", "ia", "omega", "Tload", "setpoint")}}
    driver.update(table)
    head, _, rest = text.partition("[driver]")
    rest = rest[rest.index("\n[zenoh]"):]
    path = tmp_path / "m.toml"
    path.write_text(head + "[driver]\n" + "".join(f"{k} = {_toml(v)}\n" for k, v in
                                                   driver.items()) + rest)
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    assert words in str(exc.value)


def _toml(v: Any) -> str:
    if isinstance(v, dict):
        return "{ " + ", ".join(f'"{k}" = {_toml(x)}' for k, x in v.items()) + " }"
    if isinstance(v, str):
        return f'"{v}"'
    return repr(v)


def test_check_config_refuses_a_missing_certificate_file(tmp_path: Path):
    from click.testing import CliRunner

    from twinwatch.cli import main

    src = Path(__file__).parents[1] / "config" / "dc-motor-opcua-sim.toml"
    text = src.read_text()
    head, _, rest = text.partition("[driver]")
    rest = rest[rest.index("\n[zenoh]"):]
    driver = "\n".join([
        "[driver]", 'type = "opcua"', 'endpoint = "opc.tcp://127.0.0.1:4841"',
        "sample_period = 0.01", 'security_policy = "Basic256Sha256"',
        'security_mode = "SignAndEncrypt"', 'certificate = "pki/client.der"',
        'private_key = "pki/client.pem"', 'server_certificate = "pki/server.der"',
        "[driver.channels]",
        *(f'{ch} = {{ node = "ns=2;s=Motor.{ch}" }}' for ch in
          ("Va", "ia", "omega", "Tload", "setpoint")), ""])
    path = tmp_path / "m.toml"
    path.write_text(head + driver + rest)
    r = CliRunner().invoke(main, ["check-config", str(path)])
    assert r.exit_code != 0
    assert f"driver.certificate: file {tmp_path}/pki/client.der not found" in r.output
    assert "driver.server_certificate" in r.output


def test_a_private_key_others_can_read_is_refused(tmp_path: Path):
    from twinwatch.config.loader import ConfigError, check_secrets, load_config

    src = Path(__file__).parents[1] / "config" / "dc-motor-opcua-sim.toml"
    head, _, rest = src.read_text().partition("[driver]")
    rest = rest[rest.index("\n[zenoh]"):]
    (tmp_path / "pki").mkdir()
    for name in ("client.der", "client.pem", "server.der"):
        (tmp_path / "pki" / name).write_text("x")
    (tmp_path / "pki" / "client.pem").chmod(0o644)
    driver = "\n".join([
        "[driver]", 'type = "opcua"', 'endpoint = "opc.tcp://127.0.0.1:4841"',
        "sample_period = 0.01", 'security_policy = "Basic256Sha256"', 'security_mode = "Sign"',
        'certificate = "pki/client.der"', 'private_key = "pki/client.pem"',
        'server_certificate = "pki/server.der"', "[driver.channels]",
        *(f'{ch} = {{ node = "ns=2;s=Motor.{ch}" }}' for ch in
          ("Va", "ia", "omega", "Tload", "setpoint")), ""])
    path = tmp_path / "m.toml"
    path.write_text(head + driver + rest)
    with pytest.raises(ConfigError) as exc:
        check_secrets(load_config(path), path)
    assert "driver.private_key" in str(exc.value) and "chmod o-rwx" in str(exc.value)
    (tmp_path / "pki" / "client.pem").chmod(0o600)
    check_secrets(load_config(path), path)


def test_unit_matches_display_names_and_unece_codes():
    assert unit_matches("N m", "N·m", None) and unit_matches("rad/s", "rad/s", None)
    assert unit_matches("V", None, 5655636)  # "VLT"
    assert not unit_matches("V", "mV", None) and not unit_matches("A", None, 5655636)


@pytest.mark.slow
def test_server_gone_mid_run_is_a_counted_gap_and_a_reconnect():
    port = _free_port()
    with _server(port=port) as srv:
        d = OpcUaDriver(_config(srv), time_origin=BASE)
    try:
        with _server(port=port) as srv:
            deadline = time.monotonic() + 15
            while d.stats.extra["reconnects"] < 1 and time.monotonic() < deadline:
                time.sleep(0.1)  # subscribed again: what is written now is seen
            for k in range(1, 21):
                srv.write(k, {"Va": 1.0, "ia": 1.0}, base=BASE)
            # sample 0 (the first server's initial value), then 1-20
            assert [round(s.t / PERIOD) for s in _read_all(d, 21)] == list(range(21))
        # the server is gone: the driver waits and says so
        deadline = time.monotonic() + 10
        while d.waiting is None and time.monotonic() < deadline:
            time.sleep(0.1)
        assert d.waiting is not None and "reconnecting" in d.waiting
        with _server(port=port) as srv2:
            deadline = time.monotonic() + 15
            while d.stats.extra["reconnects"] < 2 and time.monotonic() < deadline:
                time.sleep(0.1)
            assert d.waiting is None
            for k in range(51, 71):  # samples 21-50 were lost while the server was away
                srv2.write(k, {"Va": 2.0, "ia": 2.0}, base=BASE)
            got = _read_all(d, 20)
            assert [round(s.t / PERIOD) for s in got] == list(range(51, 71))
            assert d.stats.gaps == 30, d.stats.as_dict()
            assert d.stats.extra["outages"] == 2 and d.stats.extra["reconnects"] == 2
            assert d.stats.extra["duplicates"] >= 2  # sample 0 again, from each new server
    finally:
        d.close()


# -- the simulated DC motor over OPC UA, through the daemon ------------------------------------

def _sim_config(duration: float, **driver: Any) -> Any:
    from twinwatch.config.loader import load_config

    cfg = load_config(Path(__file__).parents[1] / "config" / "dc-motor-opcua-sim.toml")
    cfg.driver.port = 0  # type: ignore[attr-defined]
    cfg.driver.plant.duration = duration  # type: ignore[attr-defined]
    for k, v in driver.items():
        setattr(cfg.driver, k, v)
    return cfg


def _ra_errors(plant: Any, history: list[dict[str, Any]], since: float) -> np.ndarray:
    out = []
    for h in history:
        if h["t_start"] < since:
            continue
        true = plant.truth(0.5 * (h["t_start"] + h["t_end"])).Ra
        out.append((h["parameters"]["Ra"]["value"] / true - 1.0) * 100.0)
    return np.asarray(out)


def test_simulated_motor_over_opcua_through_the_daemon_a_short_run():
    """20 s of plant time, Ra degrading from 0 s: every window estimated through a real
    subscription, no gap, Ra within the paper's 0.2 % of the plant."""
    from twinwatch.daemon.runner import Daemon

    cfg = _sim_config(20.0)
    cfg.driver.plant.fault_start = 0.0  # type: ignore[attr-defined]
    with create_driver(cfg.driver, base_dir=Path(".")) as driver:
        with Daemon(cfg, driver=driver, publish=False, record=False) as daemon:
            daemon.run()
        assert driver.stats.gaps == 0 and driver.stats.frames >= 5 * 1900
        hist = list(daemon.history)
        assert len(hist) == 10 and daemon.overruns == 0
        err = _ra_errors(driver.plant, hist, since=0.0)
        assert np.all(np.abs(err) <= 0.2), err


@pytest.mark.slow
def test_simulated_motor_over_opcua_ra_within_0p2_percent_and_a_server_restart_costs_its_gap():
    """The issue's done-when: the default run (1200 s, Ra degrading from 160 s) through a real
    subscription; the plant's server is stopped for 2 s at 400 s of plant time and started
    again: the driver counts the gap, reconnects, and only the windows the gap falls in are
    abandoned; Ra within 0.2 % of the plant in every window after 160 s."""
    from twinwatch.daemon.runner import Daemon

    cfg = _sim_config(1200.0)
    with create_driver(cfg.driver, base_dir=Path(".")) as driver:
        def restart() -> None:
            while driver.plant.t < 400.0 and not driver.closed:
                time.sleep(0.05)
            driver.server.stop()
            time.sleep(2.0)
            driver.server.start()

        killer = threading.Thread(target=restart, daemon=True)
        killer.start()
        with Daemon(cfg, driver=driver, publish=False, record=False) as daemon:
            daemon.run()
        killer.join(5)
        hist = list(daemon.history)
        stats = driver.stats.as_dict()
        abandoned = sum(daemon.ring.discarded.values())
        served = driver.server.samples_served
    print(f"\nover OPC UA: {len(hist)} windows, {abandoned} abandoned, driver {stats}")
    assert stats["reconnects"] == 1 and stats["outages"] == 1
    # every sample served is delivered or counted missing: nothing unseen, nothing twice
    assert stats["samples"] + stats["gaps"] == served == 120001, (served, stats)
    assert 0 < stats["gaps"] <= 1000
    # only the windows of the gap are lost: at most the gap's length in windows, plus the
    # partial windows on either side (abandoned by the ring buffer, counted)
    assert abandoned <= 2
    assert 600 - len(hist) <= stats["gaps"] // 200 + 2, (len(hist), abandoned, stats)
    err = _ra_errors(driver.plant, hist, since=160.0)
    print(f"Ra error after 160 s over {len(err)} windows: median {np.median(np.abs(err)):.4f} %,"
          f" max {np.max(np.abs(err)):.4f} %")
    assert np.all(np.abs(err) <= 0.2), np.percentile(np.abs(err), [50, 95, 100])


def test_monitoring_only_the_driver_never_writes_a_node_nor_calls_a_method():
    """No call in the driver's source writes an attribute or calls a method (asyncua's
    write_value, write_attribute(s), set_value, call_method, Node.call...)."""
    import ast

    import twinwatch.drivers.opcua as mod

    tree = ast.parse(Path(mod.__file__).read_text(encoding="utf-8"))
    called = {node.func.attr for node in ast.walk(tree)
              if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)}
    forbidden = {n for n in called if n.startswith(("write", "set_value", "set_attribute",
                                                    "set_data_value", "call", "add_", "delete"))
                 and n != "call_soon_threadsafe"}  # asyncio's, waking the driver's loop
    assert forbidden == set(), forbidden
    assert {"create_subscription", "create_monitored_items", "read_node_class"} <= called


def test_the_simulated_server_on_a_taken_port_refuses_in_one_line():
    from twinwatch.drivers.simulated_opcua import SimulatedOpcUaDriver

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(DriverInitializationError) as exc:
            SimulatedOpcUaDriver.from_config({"type": "simulated_opcua", "port": port})
    msg = str(exc.value)
    assert msg.startswith("driver.port:") and f"127.0.0.1:{port}" in msg and "\n" not in msg


def test_the_hydraulic_actuator_over_opcua_through_the_daemon():
    """config/hydraulic-opcua-sim.toml for 20 s: every sample through the subscription (the
    Actuator's five Double variables, units checked), every window estimated, D as the
    plant's within the paper's 3 % where it is estimated."""
    from twinwatch.config.loader import load_config
    from twinwatch.daemon.runner import Daemon

    cfg = load_config(Path(__file__).parents[1] / "config" / "hydraulic-opcua-sim.toml")
    cfg.driver.port = 0  # type: ignore[attr-defined]
    cfg.driver.plant.duration = 20.0  # type: ignore[attr-defined]
    cfg.discovery.enabled = False
    with create_driver(cfg.driver, base_dir=Path(".")) as driver:
        assert driver.channels == ("x", "p", "A_valve", "F_load", "x_ref")
        with Daemon(cfg, driver=driver, publish=False, record=False) as daemon:
            daemon.run()
        assert driver.stats.gaps == 0 and driver.stats.samples == 2001
        hist = list(daemon.history)
        assert len(hist) == 10 and daemon.overruns == 0
        estimated = [h for h in hist if h["parameters"]["D"]["status"] == "estimated"]
        assert estimated
        for h in estimated:
            true = driver.plant.truth(0.5 * (h["t_start"] + h["t_end"])).D
            assert abs(h["parameters"]["D"]["value"] / true - 1) <= 0.03
