"""docs/mqtt.md's snippets against the real message (issue 18): the Telegraf ``json_v2`` paths
(GJSON, evaluated by gjson-py) on a health message the daemon stored, the Node-RED function
node run by Node.js on it, the Home Assistant templates rendered by Jinja2 on the real flat
values, and the example configuration."""

from __future__ import annotations

import json
import re
import shutil
import sqlite3
import subprocess
import tomllib
from pathlib import Path
from typing import Any

import pytest

from harness.daemon import sim_config
from twinwatch.sinks.mqtt import discovery_payload, flat_values

from .helpers.cli import cli
from .helpers.net import free_port
from .helpers.paths import ROOT

DOC = (ROOT / "docs" / "mqtt.md").read_text()


def blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", DOC, flags=re.S)


@pytest.fixture(scope="module")
def health(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """A health message as the daemon stored (and the MQTT output publishes) it: with the
    output configured (its counters), its broker absent (the windows wait in the outbox; no
    ``close_timeout`` spent at the stop retrying a broker that never comes)."""
    tmp = tmp_path_factory.mktemp("docs")
    cfg = sim_config(tmp, extra=f"\n[outputs.mqtt]\nport = {free_port()}\nclose_timeout = 0.0\n")
    result = cli("run", str(cfg), "--no-progress")
    assert result.exit_code == 0, result.output
    con = sqlite3.connect(tmp / "state.sqlite")
    try:
        text = con.execute("SELECT doc FROM health ORDER BY id DESC LIMIT 1").fetchone()[0]
    finally:
        con.close()
    return dict(json.loads(text))


def _topic_matches(pattern: str, topic: str) -> bool:
    import paho.mqtt.client as mqtt

    return bool(mqtt.topic_matches_sub(pattern, topic))


def test_telegraf_json_v2_paths_read_the_real_message(health: dict[str, Any]):
    gjson = pytest.importorskip("gjson", reason="pip install gjson (the test extra)")
    (toml_text,) = [b for b in blocks("toml") if "inputs.mqtt_consumer" in b]
    conf = tomllib.loads(toml_text)["inputs"]["mqtt_consumer"][0]
    assert conf["data_format"] == "json_v2" and conf["qos"] == 1
    assert all(_topic_matches(t, "twinwatch/dc-motor-sim/health") for t in conf["topics"])
    spec = conf["json_v2"][0]
    kinds = {"int": int, "float": float, "string": str}
    for tag in spec["tag"]:
        assert gjson.get(health, tag["path"]) == health["machine"]
    assert len(spec["field"]) >= 8
    for field in spec["field"]:
        value = gjson.get(health, field["path"])
        assert value is not None, field["path"]
        want = kinds[field.get("type", "float")]
        assert isinstance(value, want) or (want is float and isinstance(value, int)), field
    ra = health["parameters"]["Ra"]
    assert gjson.get(health, "parameters.Ra.value") == ra["value"]
    assert gjson.get(health, "alarms.Ra.level") == health["alarms"]["Ra"]["level"]


def test_node_red_flow_runs_on_the_real_message(health: dict[str, Any], tmp_path: Path):
    (flow_text,) = [b for b in blocks("json") if '"mqtt in"' in b]
    flow = json.loads(flow_text)
    nodes = {n["id"]: n for n in flow}
    mqtt_in = next(n for n in flow if n["type"] == "mqtt in")
    assert mqtt_in["datatype"] == "json" and mqtt_in["qos"] == "1"
    assert _topic_matches(mqtt_in["topic"], "twinwatch/dc-motor-sim/health")
    assert nodes[mqtt_in["broker"]]["type"] == "mqtt-broker"
    func = nodes[mqtt_in["wires"][0][0]]
    assert func["type"] == "function"
    node = shutil.which("node")
    if node is None:
        pytest.skip("Node.js is not installed: the function node's code is not run")
    harness = tmp_path / "run.js"
    harness.write_text(
        "const msg = JSON.parse(require('fs').readFileSync(0, 'utf8'));\n"
        f"const f = new Function('msg', 'node', {json.dumps(func['func'])});\n"
        "process.stdout.write(JSON.stringify(f(msg, {warn() {}, error() {}})));\n")
    out = subprocess.run([node, str(harness)], input=json.dumps(
        {"topic": "twinwatch/dc-motor-sim/health", "payload": health}), text=True,
        capture_output=True, timeout=30, check=True)
    flat = json.loads(out.stdout)["payload"]
    assert flat["machine"] == "dc-motor-sim" and flat["window"] == health["window"]
    for name, p in health["parameters"].items():
        assert flat[name] == p["value"] and flat[f"{name}_status"] == p["status"]
    assert flat["Ra_alarm"] == health["alarms"]["Ra"]["level"]


def test_home_assistant_templates_render_the_real_flat_values(health: dict[str, Any]):
    jinja2 = pytest.importorskip("jinja2", reason="pip install jinja2 (the test extra)")
    env = jinja2.Environment()
    flat = flat_values(health)
    payload = discovery_payload("dc-motor-sim", "dc_motor", "twinwatch/dc-motor-sim", health,
                                {"Ra": "ohm"})
    base = "twinwatch/dc-motor-sim/"

    def render(template: str, text: str) -> str:
        # Home Assistant's variables: value (the payload) and value_json (it, parsed)
        try:
            value_json = json.loads(text)
        except ValueError:
            value_json = None
        return env.from_string(template).render(value=text, value_json=value_json)

    for key, c in payload["cmps"].items():
        text = flat[c["stat_t"].removeprefix(base)]
        if key in ("diagnosis_fault", "diagnosis_action"):  # text sensors
            assert text == (health["diagnosis"]["top"] or health["diagnosis"]["status"]
                            if key == "diagnosis_fault" else text), key
            continue
        if "val_tpl" not in c:
            assert text in ("estimated", "fused", "held", "tied", "fixed"), key
            continue
        got = render(c["val_tpl"], text)
        if c["p"] == "binary_sensor":
            assert got == ("OFF" if text == "normal" else "ON")
            for level, state in (("normal", "OFF"), ("warning", "ON"), ("alarm", "ON")):
                assert render(c["val_tpl"], level) == state
        else:
            assert got == "None" if text == "null" else float(got) == float(text), key
            assert render(c["val_tpl"], "null") == "None"   # Home Assistant's unknown


def test_example_config_runs_its_output(tmp_path: Path):
    """config/dc-motor-sim-mqtt.toml is the documented table, Home Assistant on."""
    import tomllib as t

    conf = t.loads((ROOT / "config" / "dc-motor-sim-mqtt.toml").read_text())
    mqtt = conf["outputs"]["mqtt"]
    assert (mqtt["host"], mqtt["port"]) == ("127.0.0.1", 1883)
    assert conf["outputs"]["mqtt"]["home_assistant"]["discovery"] is True
    assert "dc-motor-sim-mqtt.toml" in DOC
