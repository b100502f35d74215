"""Adding an output is one module plus one registry line: an output that lives in another
package, registered through the ``twinwatch.sinks`` entry-point group (an installed
distribution's ``entry_points.txt``), is configured from a TOML file under ``[outputs.<name>]``
with its own keys, validated by its own config model, and run by the real command line like the
built-in outputs: it gets every window, only once the state store has stored it, its counters go
into the health message, and ``check-config`` and ``sample-config`` know its table (issue 14).

The plug-in is a real distribution on ``sys.path`` (a package and its ``*.dist-info``), used by
``twinwatch`` in a subprocess as a user would install one, and in this process (click's runner)
where the state database is made to fail for some windows.
"""

from __future__ import annotations

import json
import os
import re
import sqlite3
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from harness.daemon import sim_config
from twinwatch.config.loader import load_config
from twinwatch.drivers import DRIVERS
from twinwatch.sinks import SINKS

from .helpers.cli import DiskFull, cli
from .helpers.paths import ROOT
from .helpers.plugins import DRIVER_PLUGIN

PLUGIN = '''
"""A third-party output: every health message it gets, one JSON line in a file."""
from __future__ import annotations

import json
import sqlite3
from pathlib import Path
from typing import Any, Self

from pydantic import Field

from twinwatch.errors import SinkError
from twinwatch.sinks.base import ProcessedWindow, Sink, SinkConfig, SinkContext


class JsonLinesConfig(SinkConfig):
    """[outputs.jsonl]"""

    path: str = Field("health.jsonl", description="file the messages are appended to")
    port: int = Field(1883, ge=1, le=65535, description="a port, for the key errors")
    ca_file: str | None = Field(None, description="a file it reads at open")
    audit_db: str | None = Field(None, description="a state database to look each window up "
                                 "in when it arrives (what the test checks)")

    def input_files(self) -> dict[str, str]:
        return {"ca_file": self.ca_file} if self.ca_file else {}

    def output_files(self, cwd: Path) -> dict[str, Path]:
        path = Path(self.path)
        return {"path": path if path.is_absolute() else cwd / path}


class JsonLinesSink(Sink):
    """Appends each window's health message to a file (a publisher: stored windows only)."""

    config_class = JsonLinesConfig

    @classmethod
    def from_config(cls, config: JsonLinesConfig, context: SinkContext) -> Self:
        path = config.output_files(context.cwd)["path"]
        if config.port == 9:  # what only opening finds out, e.g. a broker that is not there
            raise SinkError("cannot connect to 127.0.0.1:9: nothing listens there; start the "
                            "broker or set outputs.jsonl.port")
        audit = (context.cwd / config.audit_db) if config.audit_db else None
        return cls(path, audit)

    def __init__(self, path: Path, audit: Path | None) -> None:
        self.path = path
        self.audit = audit
        self.received = 0
        self._file = path.open("a", encoding="utf-8")
        self._closed = False

    def _stored(self, machine: str, window: int) -> str | None:
        """The document the state database holds for the window right now, if any."""
        if self.audit is None:
            return None
        con = sqlite3.connect(f"file:{self.audit}?mode=ro", uri=True)
        try:
            row = con.execute("SELECT doc FROM health WHERE machine = ? AND window = ?",
                              (machine, window)).fetchone()
        finally:
            con.close()
        return None if row is None else row[0]

    def write(self, out: ProcessedWindow) -> None:
        h = out.health
        stored = self._stored(h.machine, h.window)
        self._file.write(json.dumps({
            "window": h.window, "stored_before": stored is not None,
            "same_text": stored == out.health_json, "typed": type(h).__name__,
            "events": len(out.events), "counters": h.counters}) + "\\n")
        self._file.flush()
        self.received += 1

    def counters(self) -> dict[str, int]:
        return {"received": self.received}

    def summary(self) -> list[str]:
        return [f"jsonl: {self.received} windows appended to {self.path}"]

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._file.close()
'''

ENTRY_POINTS = """
[twinwatch.sinks]
jsonl = twdemo_sink.jsonl:JsonLinesSink

[twinwatch.drivers]
plant_direct = twdemo_sink.direct:PlantDirectDriver
"""


@pytest.fixture
def plugin_path(tmp_path: Path) -> Path:
    """A distribution ``twdemo-sink`` (package + dist-info) in ``tmp_path/site``: the output
    ``jsonl`` and, for ``sample-config --driver``, the driver of tests/test_driver_plugin.py."""
    site = tmp_path / "site"
    pkg = site / "twdemo_sink"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "jsonl.py").write_text(PLUGIN)
    (pkg / "direct.py").write_text(DRIVER_PLUGIN)
    info = site / "twdemo_sink-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: twdemo-sink\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(ENTRY_POINTS)
    return site


@pytest.fixture
def installed(plugin_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """The plug-in installed in this process (on sys.path; the registries read again)."""
    monkeypatch.syspath_prepend(str(plugin_path))
    SINKS.cache_clear()
    DRIVERS.cache_clear()
    yield plugin_path
    monkeypatch.undo()
    SINKS.cache_clear()
    DRIVERS.cache_clear()


def _twinwatch(site: Path, *args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, CI="true", PYTHONPATH=os.pathsep.join([str(site), str(ROOT)]))
    return subprocess.run([sys.executable, "-m", "twinwatch", *args], capture_output=True,
                          text=True, env=env, cwd=cwd, timeout=300)


OUTPUT = textwrap.dedent("""
    [outputs.jsonl]
    path = "health.jsonl"
    port = 8883
    audit_db = "state.sqlite"
""")


def _config(tmp: Path, outputs: str = OUTPUT, **kw: Any) -> Path:
    """The simulated motor (6 s: 3 windows), state database in ``tmp``, the output ``jsonl``."""
    path = sim_config(tmp, **kw)
    path.write_text(path.read_text() + outputs)
    return path


def _lines(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def _stored(db: Path) -> dict[int, str]:
    con = sqlite3.connect(db)
    try:
        return dict(con.execute("SELECT window, doc FROM health ORDER BY id"))
    finally:
        con.close()


# -- configured from TOML, checked by its own model ----------------------------------------------
@pytest.mark.slow  # about 10 s on the shared 2-core box: out of the fast lane
def test_check_config_validates_the_plugin_output_table(tmp_path: Path, plugin_path: Path):
    ok = _twinwatch(plugin_path, "check-config", str(_config(tmp_path)), cwd=tmp_path)
    assert ok.returncode == 0, ok.stderr

    bad = _twinwatch(plugin_path, "check-config", str(_config(
        tmp_path, OUTPUT.replace("port = 8883", "port = 0") + "colour = 'red'\n")), cwd=tmp_path)
    assert bad.returncode == 1
    assert "outputs.jsonl.port: Input should be greater than or equal to 1" in bad.stderr
    assert "outputs.jsonl.colour: unknown key" in bad.stderr

    unknown = _twinwatch(plugin_path, "check-config", str(_config(
        tmp_path, "[outputs.mqttx]\nhost = 'broker'\n")), cwd=tmp_path)
    assert unknown.returncode == 1
    line = next(ln for ln in unknown.stderr.splitlines() if "outputs.mqttx" in ln)
    assert "unknown output 'mqttx'; known outputs: mqtt, sparkplug, opcua, jsonl" in line
    assert "[state]" in line and "[zenoh]" in line and "[recording]" in line

    builtin = _twinwatch(plugin_path, "check-config", str(_config(
        tmp_path, "[outputs.zenoh]\nenabled = false\n")), cwd=tmp_path)
    assert builtin.returncode == 1
    assert "outputs.zenoh: the 'zenoh' output is configured in [zenoh]" in builtin.stderr

    # what the output reads and writes is checked before anything opens (run: exit 78)
    missing = _config(tmp_path, OUTPUT.replace('path = "health.jsonl"',
                                               'path = "no/such/dir/h.jsonl"\nca_file = "ca.pem"'))
    res = _twinwatch(plugin_path, "check-config", str(missing), cwd=tmp_path)
    assert res.returncode == 1
    assert f"outputs.jsonl.ca_file: file {tmp_path / 'ca.pem'} not found" in res.stderr \
        or "outputs.jsonl.ca_file: file ca.pem not found" in res.stderr
    assert "outputs.jsonl.path: directory" in res.stderr
    run = _twinwatch(plugin_path, "run", str(missing), "--no-progress", cwd=tmp_path)
    assert run.returncode == 78, run.stderr

    # a start error (a SinkError) is one line, exit 1, like the built-ins'
    absent = _config(tmp_path, OUTPUT.replace("port = 8883", "port = 9"))
    run = _twinwatch(plugin_path, "run", str(absent), "--no-progress", cwd=tmp_path)
    assert run.returncode == 1, run.stderr
    assert run.stderr.strip().splitlines()[-1] == (
        "Error: cannot start: cannot connect to 127.0.0.1:9: nothing listens there; start the "
        "broker or set outputs.jsonl.port")
    assert "Traceback" not in run.stderr


def test_without_the_plugin_its_table_is_refused(tmp_path: Path):
    cfg = _config(tmp_path)
    res = cli("check-config", str(cfg))
    assert res.exit_code == 1
    assert "outputs.jsonl: unknown output 'jsonl'; known outputs: mqtt" in res.output


# -- run by the real command line ----------------------------------------------------------------
def test_the_plugin_output_gets_every_window_once_stored(tmp_path: Path, plugin_path: Path):
    res = _twinwatch(plugin_path, "run", str(_config(tmp_path, duration=8.0)), "--no-progress",
                     cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert "4 windows estimated" in res.stdout
    got = _lines(tmp_path / "health.jsonl")
    stored = _stored(tmp_path / "state.sqlite")
    assert [g["window"] for g in got] == sorted(stored) == [0, 1, 2, 3]
    # each window was in the state database when it arrived, byte for byte as stored
    assert all(g["stored_before"] and g["same_text"] and g["typed"] == "HealthMessage"
               for g in got)
    # its counters are in the health message (counted before the window is written)
    counters = [json.loads(stored[w])["counters"] for w in sorted(stored)]
    assert [c["jsonl_received"] for c in counters] == [0, 1, 2, 3]
    assert {"store_waiting", "windows_not_stored"} <= set(counters[-1])
    assert f"jsonl: 4 windows appended to {tmp_path / 'health.jsonl'}" in res.stdout


def test_a_window_the_store_cannot_take_is_not_given_to_the_plugin(
        tmp_path: Path, installed: Path, monkeypatch: pytest.MonkeyPatch):
    DiskFull(monkeypatch, range(2, 5))  # the state database is full for windows 2-4 of 10
    monkeypatch.chdir(tmp_path)  # the working directory: the output's relative paths
    res = cli("run", str(_config(tmp_path, duration=20.0)), "--no-progress")
    assert res.exit_code == 0, res.output
    got = _lines(tmp_path / "health.jsonl")
    stored = _stored(tmp_path / "state.sqlite")
    assert sorted(stored) == list(range(10))  # written with window 5
    # like the Zenoh publisher: windows 2-4 were never published (the history query serves
    # them), every window it got was stored when it got it
    assert [g["window"] for g in got] == [0, 1, 5, 6, 7, 8, 9]
    assert all(g["stored_before"] and g["same_text"] for g in got)
    last = json.loads(stored[9])["counters"]
    assert last["jsonl_received"] == 6 and last["windows_not_stored"] == 3
    assert "3 windows could not be stored when estimated" in res.output
    assert "jsonl: 7 windows appended" in res.output


def test_a_reload_keeps_the_plugin_open_unless_its_table_changed(
        tmp_path: Path, installed: Path, monkeypatch: pytest.MonkeyPatch):
    from twinwatch.daemon.runner import Daemon

    monkeypatch.chdir(tmp_path)
    cfg = load_config(_config(tmp_path, duration=4.0))
    first = Daemon(cfg, persist=True, record=False)
    first.run()
    sink = first.sinks["jsonl"]
    # what the supervisor does on SIGHUP: the new daemon is opened beside the running one,
    # adopting what it hands over, and takes over once the running one has released the rest
    keep, wait = first.handover(cfg)
    second = Daemon(cfg, persist=True, record=False, resume=False,
                    reuse={k: first.sinks[k] for k in keep}, defer=wait)
    first.close(keep=keep)
    second.open_deferred()
    second.continue_from(first)
    assert second.sinks["jsonl"] is sink and list(second.sinks) == ["store", "jsonl"]
    second.run()
    changed = cfg.model_copy(deep=True)
    changed.outputs["jsonl"].port = 1884
    # what a reload to it may keep open, and what must wait for the running one's file
    assert second.handover(cfg) == (["store", "jsonl"], [])
    assert second.handover(changed) == (["store"], ["jsonl"])
    moved = changed.model_copy(deep=True)
    moved.outputs["jsonl"].path = "other.jsonl"
    assert second.handover(moved) == (["store"], [])
    keep, wait = second.handover(changed)
    third = Daemon(changed, persist=True, record=False, resume=False,
                   reuse={k: second.sinks[k] for k in keep}, defer=wait)
    assert "jsonl" not in third.sinks  # its file is the running one's: it waits
    second.close(keep=keep)
    third.open_deferred()
    third.continue_from(second)
    assert third.sinks["jsonl"] is not sink and sink._closed
    third.close()
    # numbering went on under one run id; the plug-in got each window once
    assert [g["window"] for g in _lines(tmp_path / "health.jsonl")] == [0, 1, 2, 3]


# -- sample-config: from the registries ----------------------------------------------------------
def test_sample_config_shows_the_plugin_table_and_takes_plugin_drivers(tmp_path: Path,
                                                                         plugin_path: Path):
    sample = _twinwatch(plugin_path, "sample-config", cwd=tmp_path)
    assert sample.returncode == 0, sample.stderr
    block = sample.stdout[sample.stdout.index("# [outputs.jsonl]"):]
    assert re.search(r"^# port = 1883 +# a port, for the key errors$", block, re.M), block
    assert re.search(r"^# ca_file = +# a file it reads at open \(default: unset\)$", block,
                     re.M), block
    # uncommented (the keys with a default), the plug-in's sample is a valid table
    enabled = sample.stdout.replace(block, re.sub(r"^# ((\[|\w+ = [^\s#]).*)$", r"\1", block,
                                                  flags=re.M))
    (tmp_path / "with.toml").write_text(enabled)
    check = _twinwatch(plugin_path, "check-config", str(tmp_path / "with.toml"), cwd=tmp_path)
    assert check.returncode == 0, check.stderr

    # --driver takes its choices from the driver registry: a plug-in's sample is generated
    # from its config model, and checks
    driver = _twinwatch(plugin_path, "sample-config", "--driver", "plant_direct", cwd=tmp_path)
    assert driver.returncode == 0, driver.stderr
    assert 'type = "plant_direct"' in driver.stdout and "# [driver.plant]" in driver.stdout
    (tmp_path / "direct.toml").write_text(driver.stdout)
    check = _twinwatch(plugin_path, "check-config", str(tmp_path / "direct.toml"), cwd=tmp_path)
    assert check.returncode == 0, check.stderr
    assert "plant_direct driver" in check.stdout
    bad = _twinwatch(plugin_path, "sample-config", "--driver", "profinet", cwd=tmp_path)
    assert bad.returncode == 2 and "'plant_direct'" in bad.stderr


def test_the_built_in_outputs_are_the_same_contract(tmp_path: Path):
    from twinwatch.sinks import BUILTIN_SINKS, HISTORIC_TABLES, sink_class
    from twinwatch.sinks.base import Gate, Sink, SinkConfig

    cfg = load_config(ROOT / "config" / "dc-motor-sim.toml")
    assert [t.name for t in cfg.output_tables()] == list(BUILTIN_SINKS)[:3] == [
        "store", "zenoh", "rerun"]
    # under [outputs.mqtt], [outputs.sparkplug], [outputs.opcua]
    assert list(BUILTIN_SINKS)[3:] == ["mqtt", "sparkplug", "opcua"]
    roles = {}
    for t in cfg.output_tables():
        cls = sink_class(t.name)
        assert issubclass(cls, Sink) and isinstance(t.config, cls.config_class)
        assert isinstance(t.config, SinkConfig) and t.key == HISTORIC_TABLES[t.name]
        roles[t.name] = cls.role
    assert roles == {"store": "gate", "zenoh": "publisher", "rerun": "recorder"}
    assert issubclass(sink_class("store"), Gate)
    # what a reload must wait for: the port, the locked files
    tables = {t.name: t.config for t in cfg.output_tables()}
    assert tables["zenoh"].exclusive_resources(tmp_path) == {"tcp/127.0.0.1:7447"}
    assert tables["store"].exclusive_resources(tmp_path) == {str(tmp_path / "state.sqlite")}
    assert tables["rerun"].exclusive_resources(tmp_path) == {str(tmp_path / "twinwatch.rrd")}
