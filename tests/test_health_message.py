"""The health message: one typed layout, documented field by field, one encoder (issue 11).

* the reference table of docs/health-message.md names every field of
  :class:`~twinwatch.twin.health.HealthMessage` and no field it does not have;
* a parameter's ``status`` is typed (no prose to parse), and the built message carries it;
* non-finite numbers are ``null`` in every copy: Zenoh, the state database, the recording.
"""

from __future__ import annotations

import ast
import itertools
import json
import math
import re
import sqlite3
import types
import typing
from pathlib import Path
from typing import Any

import pytest
from pydantic import BaseModel, ValidationError

from twinwatch.config.loader import default_config
from twinwatch.daemon.pipeline import ProcessedWindow
from twinwatch.plant.dcmotor import DCMotorPlantConfig
from twinwatch.sinks.store import StateStore
from twinwatch.twin.adaptation import TwinAdapter, TwinState
from twinwatch.twin.health import SCHEMA_VERSION, HealthMessage, build_health, summary_line
from twinwatch.twin.models import create_model

from .helpers.paths import ROOT
from .helpers.plant import plant_windows

PLACEHOLDER = re.compile(r"<[^>]+>")


# -- the reference table against the model----------------------------------------------------
def _unwrap(tp: Any) -> Any:
    """The type inside Optional/Annotated."""
    while True:
        origin = typing.get_origin(tp)
        if origin is typing.Annotated:
            tp = typing.get_args(tp)[0]
        elif origin in (typing.Union, types.UnionType):
            args = [a for a in typing.get_args(tp) if a is not type(None)]
            if len(args) != 1:
                return tp
            tp = args[0]
        else:
            return tp


def model_paths(model: type[BaseModel], prefix: str = "") -> set[str]:
    """Every leaf of the layout: ``parameters.<>.value``, ``terms[].kind``, ``rmse.<>``,
    ``discovery.kept`` (``<>``: a key, e.g. a parameter or output name; ``[]``: each item)."""
    out: set[str] = set()
    for name, field in model.model_fields.items():
        path = prefix + (field.alias or name)
        tp = _unwrap(field.annotation)
        while True:
            origin = typing.get_origin(tp)
            if origin is dict:
                path += ".<>"
                tp = _unwrap(typing.get_args(tp)[1])
            elif origin is list:
                item = _unwrap(typing.get_args(tp)[0])
                if not (isinstance(item, type) and issubclass(item, BaseModel)):
                    break  # a list of strings is one field (discovery.kept)
                path += "[]"
                tp = item
            else:
                break
        if isinstance(tp, type) and issubclass(tp, BaseModel):
            out |= model_paths(tp, path + ".")
        else:
            out.add(path)
    return out


def _expand(spec: str) -> list[str]:
    """``a.{b, c}.d`` -> ``a.b.d``, ``a.c.d`` (any number of brace groups)."""
    parts = re.split(r"(\{[^}]*\})", spec)
    choices = [[c.strip() for c in p[1:-1].split(",")] if p.startswith("{") else [p]
               for p in parts]
    return ["".join(c) for c in itertools.product(*choices)]


def readme_paths() -> set[str]:
    """The fields docs/health-message.md's table documents (the README links to it)."""
    text = (ROOT / "docs" / "health-message.md").read_text(encoding="utf-8")
    section = text.split("# The health message", 1)[1].split("\n## ", 1)[0]
    rows = [ln for ln in section.splitlines() if ln.startswith("| `")]
    assert rows, "no field table under '# The health message' in docs/health-message.md"
    out: set[str] = set()
    for row in rows:
        first = row.split("|")[1]
        for spec in re.findall(r"`([^`]+)`", first):
            out |= {PLACEHOLDER.sub("<>", p) for p in _expand(spec)}
    return out


def test_the_reference_documents_every_field_of_the_message_and_no_other() -> None:
    model = model_paths(HealthMessage)
    documented = readme_paths()
    assert "parameters.<>.status" in model and "residual.dt_second.rmse.<>" in model
    assert model - documented == set(), "fields missing from docs/health-message.md's table"
    assert documented - model == set(), (
        "docs/health-message.md documents fields the message does not have")


def test_the_table_reader_expands_groups() -> None:
    assert _expand("residual.{dt_prime, dt_second}.{rmse.<output>, nrmse}") == [
        "residual.dt_prime.rmse.<output>", "residual.dt_prime.nrmse",
        "residual.dt_second.rmse.<output>", "residual.dt_second.nrmse"]


# -- the message as built ---------------------------------------------------------------------
@pytest.fixture(scope="module")
def processed() -> tuple[Any, Any, Any]:
    cfg = default_config()
    model = create_model(cfg.machine.model, cfg.machine.options)
    adapter = TwinAdapter(model, cfg.estimation, cfg.discovery)
    _, (w,) = plant_windows(DCMotorPlantConfig(scenario="nominal", duration=10), 1, skip=1)
    result = adapter.process(w)
    return model, w, result


def _message(processed: tuple[Any, Any, Any], **over: Any) -> HealthMessage:
    model, w, result = processed
    return build_health(machine="m1", model_name="dc_motor", run="r1", model=model, window=w,
                        adaptation=result, nominal={}, counters={"overruns": 0}, **over)


def test_each_parameter_has_a_typed_status(processed) -> None:  # type: ignore[no-untyped-def]
    h = _message(processed)
    assert h.as_dict()["schema"] == SCHEMA_VERSION == 14
    assert h.as_dict()["run"] == "r1"
    status = {n: p.status for n, p in h.parameters.items()}
    assert status["Kt"] == "tied" and status["Ra"] == "estimated"
    for p in h.parameters.values():
        assert p.held == (p.status != "estimated")
        assert (p.reason is None) == (p.status == "estimated")
        if p.status in ("estimated", "fused"):
            assert p.rel_std_pct is not None
        elif p.status != "suspect":  # a suspect estimate keeps its (widened) error
            assert p.rel_std_pct is None
        # every estimated parameter carries the fused evidence and its interval
        assert (p.fused is not None) == (p.status in ("estimated", "fused", "held"))
        if p.fused is not None:
            assert p.fused.low <= p.fused.value <= p.fused.high
    assert h.model_check is not None and h.model_check.passed  # the twin is the plant
    assert set(h.model_check.outputs) == {"ia", "omega", "Va"}
    line = summary_line(h)
    assert "Ra6.5" in line and "Kt" not in line  # tied and fixed are left out, by status
    with pytest.raises(ValidationError):
        h.parameters["Ra"].status = "guessed"  # type: ignore[assignment]
    with pytest.raises(ValidationError):
        HealthMessage.model_validate({**h.as_dict(), "colour": "red"})  # no undocumented field


def test_the_compiled_serialiser_writes_the_one_encoders_document(processed) -> None:  # type: ignore[no-untyped-def]
    """HealthMessage.to_json (pydantic's serialiser, issue 22) is the document the project's
    one encoder makes of the message's fields: the same keys, values and nulls, compact."""
    from twinwatch.io.encoding import to_json

    h = _message(processed)
    h = h.model_validate(h.model_dump() | {"nrmse": math.nan})  # validated: NaN -> None
    h.parameters["Ra"].deviation_pct = math.inf
    text = h.to_json()
    assert json.loads(text) == json.loads(to_json(h.as_dict()))
    assert "\n" not in text and len(text) <= len(to_json(h.as_dict())) + 64  # compact
    assert list(json.loads(text)) == list(h.as_dict())  # the fields in the same order


def test_non_finite_numbers_are_null_in_every_copy(processed, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    h = _message(processed)
    h = h.model_validate(h.model_dump() | {"nrmse": math.nan})  # validated: NaN -> None
    h.parameters["Ra"].deviation_pct = math.inf
    assert h.nrmse is None and h.parameters["Ra"].deviation_pct is None
    text = h.to_json()
    assert "NaN" not in text and "Infinity" not in text
    msg = json.loads(text)
    assert msg["nrmse"] is None and msg["parameters"]["Ra"]["deviation_pct"] is None
    model, w, result = processed
    out = ProcessedWindow(window=w, result=result, health=h, health_json=text, events=[],
                          twin_state=TwinState({"Ra": math.nan}))
    with StateStore(tmp_path / "s.sqlite") as store:
        store.write(out)
        # a message handed to the store as a plain mapping goes through the same encoder
        store.save_window({**msg, "window": 1, "nrmse": math.nan}, None)
    con = sqlite3.connect(tmp_path / "s.sqlite")
    rows = [r[0] for r in con.execute("SELECT doc FROM health ORDER BY window")]
    twin = con.execute("SELECT state FROM twin").fetchone()[0]
    con.close()
    assert rows[0] == text  # stored byte for byte as published
    assert '"nrmse":null' in rows[1] and "NaN" not in rows[1]
    assert json.loads(twin) == {"trusted": {"Ra": None}, "terms": [], "fusion": None,
                                "floor": None}


def test_a_built_message_is_frozen(processed) -> None:  # type: ignore[no-untyped-def]
    """Built once, never edited (issue 36): assigning a field of a built message raises; a
    variant is a new message (``model_copy(update=...)``) and leaves the first unchanged."""
    h = _message(processed)
    with pytest.raises(ValidationError, match="frozen"):
        h.alarms = {}
    with pytest.raises(ValidationError, match="frozen"):
        h.diagnosis = None
    window = h.window
    other = h.model_copy(update={"window": window + 7})
    assert (other.window, h.window) == (window + 7, window)


def test_the_windows_message_is_the_reading_with_what_was_derived(processed) -> None:  # type: ignore[no-untyped-def]
    """complete_health: the same message build_health makes with the diagnosis and the alarms
    passed in, a new one; the estimation's message it was made from stays as it was."""
    from twinwatch.twin.health import AlarmStatus, complete_health

    reading = _message(processed)
    before = reading.to_json()
    alarms = {"Ra": AlarmStatus(level="warning", since_t=10.0, since_window=5,
                                deviation_pct=-5.2, pending=None, rul=None)}
    done = complete_health(reading, diagnosis=None, alarms=alarms)
    assert done is not reading and reading.to_json() == before and reading.alarms == {}
    assert done.to_json() == _message(processed, alarms=alarms).to_json()
    assert done.alarms["Ra"].level == "warning"


#: The fields of the message and of its diagnosis: what the pipeline derives after the
#: estimation and once wrote into the built message (source, diagnosis, alarms, ...).
_MESSAGE_FIELDS = set(HealthMessage.model_fields) | {"schema"}


def message_writes(source: str) -> list[tuple[int, str]]:
    """(line, target) of every assignment in ``source`` to ``<name>.<field>`` (or deeper,
    ``<name>.diagnosis.alarms``) where ``<field>`` is a field of the message and ``<name>`` is
    not ``self``: writing into a built message (or a part of it)."""
    found: list[tuple[int, str]] = []
    for node in ast.walk(ast.parse(source)):
        targets: list[ast.expr] = []
        if isinstance(node, ast.Assign):
            targets = list(node.targets)
        elif isinstance(node, ast.AugAssign | ast.AnnAssign):
            targets = [node.target]
        flat: list[ast.expr] = []
        for t in targets:
            flat += list(t.elts) if isinstance(t, ast.Tuple | ast.List) else [t]
        for t in flat:
            chain: list[str] = []
            node_: ast.expr = t
            while isinstance(node_, ast.Attribute | ast.Subscript):
                if isinstance(node_, ast.Attribute):
                    chain.append(node_.attr)
                node_ = node_.value
            root = node_.id if isinstance(node_, ast.Name) else None
            if root is None or root == "self" or not chain:
                continue
            if chain[-1] in _MESSAGE_FIELDS or (len(chain) > 1 and chain[-2] == "diagnosis"):
                found.append((t.lineno, ast.unparse(t)))
    return found


def test_the_scan_finds_a_write_into_a_message() -> None:
    """Not vacuous: the writes the pipeline made before issue 36 are found."""
    before = ("def process(self, window):\n"
              "    health = build_health()\n"
              "    health.source = self._source_health(window)\n"
              "    health.diagnosis = self.diagnoser.update(health)\n"
              "    health.alarms = {}\n"
              "    d = health.diagnosis\n"
              "    health.diagnosis.alarms = []\n"
              "    self.latest = health\n"
              "    p.value, p.status = 1.0, 'held'\n")
    assert message_writes(before) == [(3, "health.source"), (4, "health.diagnosis"),
                                      (5, "health.alarms"), (7, "health.diagnosis.alarms")]


@pytest.mark.parametrize("module", ["daemon/pipeline.py", "daemon/alarms.py",
                                    "daemon/window_worker.py", "daemon/runner.py",
                                    "daemon/outputs.py"])
def test_the_daemon_writes_into_no_built_message(module: str) -> None:
    found = message_writes((ROOT / "twinwatch" / module).read_text())
    assert found == [], f"twinwatch/{module} writes into a built health message: {found}"
