"""Zenoh over mutual TLS on loopback, configured from config/dc-motor-sim-tls.toml (issue #5,
item 6): a CA, a router certificate (localhost) and a client certificate are generated in the
test with the openssl CLI; a Python zenoh session in router mode stands in for zenohd.

This zenoh build (eclipse-zenoh 1.10.2) has the TLS link: ``tls/`` endpoints and
``transport/link/tls`` with ``enable_mtls`` work; the example's access-control table is passed
through and enforced by the same session.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import threading
import time
from pathlib import Path

import pytest
import zenoh
import zenoh.ext

from twinwatch.config.loader import load_config
from twinwatch.sinks.zenoh import HealthPublisher, PublisherError

from .helpers.net import free_port
from .helpers.paths import ROOT

EXAMPLE = ROOT / "config" / "dc-motor-sim-tls.toml"


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True, timeout=30)


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if shutil.which("openssl") is None:
        pytest.skip("the openssl CLI is not installed")
    d = tmp_path_factory.mktemp("pki")
    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
    _openssl("req", "-x509", *ec, "-keyout", "ca.key", "-out", "ca.pem", "-days", "2",
             "-subj", "/CN=twinwatch-test-ca", cwd=d)
    (d / "ext.cnf").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n"
                               "basicConstraints=CA:FALSE\nkeyUsage=digitalSignature\n"
                               "extendedKeyUsage=serverAuth,clientAuth\n")
    for name, cn in (("router", "localhost"), ("twinwatch", "twinwatch")):
        _openssl("req", *ec, "-keyout", f"{name}.key", "-out", f"{name}.csr",
                 "-subj", f"/CN={cn}", cwd=d)
        _openssl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
                 "-CAcreateserial", "-out", f"{name}.pem", "-days", "2", "-extfile", "ext.cnf",
                 cwd=d)
        (d / f"{name}.key").chmod(0o600)
    return d


def _router(pki: Path, port: int) -> zenoh.Session:
    conf = zenoh.Config()
    for key, value in {
        "mode": "router",
        "listen/endpoints": [f"tls/localhost:{port}"],
        "scouting/multicast/enabled": False,
        "scouting/gossip/enabled": False,
        "transport/link/tls/root_ca_certificate": str(pki / "ca.pem"),
        "transport/link/tls/listen_certificate": str(pki / "router.pem"),
        "transport/link/tls/listen_private_key": str(pki / "router.key"),
        "transport/link/tls/enable_mtls": True,
    }.items():
        conf.insert_json5(key, json.dumps(value))
    return zenoh.open(conf)


def _example(pki: Path, port: int, tmp_path: Path, *, client_cert: bool = True) -> Path:
    text = EXAMPLE.read_text().replace("/etc/twinwatch/tls/", f"{pki}/")
    text = text.replace("tls/localhost:7447", f"tls/localhost:{port}")
    if not client_cert:  # a client without a certificate (mTLS must refuse it)
        text = text.replace("enable_mtls = true", "enable_mtls = false")
        text = "\n".join(line for line in text.splitlines()
                         if not line.startswith(("connect_certificate", "connect_private_key")))
    cfg = tmp_path / "tls.toml"
    cfg.write_text(text)
    cfg.chmod(0o640)
    return cfg


def test_health_over_mutual_tls_from_the_example_config(pki: Path, tmp_path: Path) -> None:
    port = free_port()
    cfg = load_config(_example(pki, port, tmp_path))
    assert cfg.zenoh.tls is not None and cfg.zenoh.tls.enable_mtls
    assert cfg.zenoh.access_control is not None and cfg.zenoh.access_control["enabled"]
    got: list[dict] = []
    done = threading.Event()

    def on(sample: zenoh.Sample) -> None:
        got.append(json.loads(sample.payload.to_string()))
        done.set()

    with _router(pki, port) as router:
        sub = router.declare_subscriber("twinwatch/dc-motor-sim-tls/health", on)
        with HealthPublisher(cfg.zenoh, cfg.machine.name) as pub:
            deadline = time.monotonic() + 10
            while not done.is_set() and time.monotonic() < deadline:
                pub.publish({"machine": cfg.machine.name, "window": 0})
                done.wait(0.2)
            replies = [json.loads(r.ok.payload.to_string())
                       for r in router.get("twinwatch/dc-motor-sim-tls/health", timeout=5)
                       if r.ok is not None]
            for window in (1, 2):
                pub.publish({"machine": cfg.machine.name, "window": window})
            # a late joiner's history comes from the publisher's cache (under .../@adv/...)
            cached: list[int] = []
            late = zenoh.ext.declare_advanced_subscriber(
                router, "twinwatch/*/health",
                lambda s: cached.append(json.loads(s.payload.to_string())["window"]),
                history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=2))
            deadline = time.monotonic() + 10
            while len(cached) < 2 and time.monotonic() < deadline:
                time.sleep(0.05)
            late.undeclare()
        sub.undeclare()
    assert got and got[0] == {"machine": "dc-motor-sim-tls", "window": 0}
    assert replies and replies[0]["window"] == 0  # queries pass the access control too
    assert cached == [1, 2]  # and so does the publisher's cache


def test_mtls_router_refuses_a_client_without_certificate(pki: Path, tmp_path: Path) -> None:
    port = free_port()
    cfg = load_config(_example(pki, port, tmp_path, client_cert=False))
    with _router(pki, port):
        with pytest.raises(PublisherError, match="cannot connect to tls/localhost"):
            HealthPublisher(cfg.zenoh, cfg.machine.name)


def test_tls_endpoint_without_certificates_is_refused_at_load(tmp_path: Path) -> None:
    text = EXAMPLE.read_text()
    cut = text[:text.index("[zenoh.tls]")]
    cfg = tmp_path / "bad.toml"
    cfg.write_text(cut)
    with pytest.raises(Exception, match="tls/ connect endpoint needs \\[zenoh.tls\\] "
                                        "root_ca_certificate"):
        load_config(cfg)
