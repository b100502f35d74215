"""Every reader of the health message reads its typed view (issue 24, item 5).

The readers (``watch`` and ``tail``, the recording, the MQTT output and Home Assistant,
``explain``, the run's live query, the alarms' restore) read the message through
:func:`twinwatch.twin.health.read_health`, never by indexing the decoded JSON with the name of a
field: a new field is one line on the model plus the readers that show it. This scan fails on a
subscript, a ``.get`` or an ``in`` test with a string that names a field of the message, outside
the few functions listed below that read other documents whose keys share those names.
"""

from __future__ import annotations

import ast
from typing import Any, get_args, get_origin

import pytest
from pydantic import BaseModel

from twinwatch.twin.health import HealthMessage, read_health, sent

from .helpers.paths import ROOT

PACKAGE = ROOT / "twinwatch"

READERS = [
    "watch/session.py",
    "watch/fleet.py",
    "watch/view.py",
    "watch/subscription.py",
    "watch/render.py",
    "watch/tail.py",
    "sinks/rerun/views.py",
    "sinks/rerun/texts.py",
    "sinks/rerun/projection.py",
    "sinks/rerun/style.py",
    "sinks/rerun/recorder.py",
    "sinks/rerun/live.py",
    "sinks/mqtt/encoding.py",
    "sinks/mqtt/publisher.py",
    "sinks/mqtt/outbox.py",
    "sinks/mqtt/delivery.py",
    "sinks/sparkplug/metrics.py",
    "sinks/sparkplug/publisher.py",
    "sinks/sparkplug/node.py",
    "sinks/opcua/model.py",
    "sinks/opcua/server.py",
    "sinks/opcua/publisher.py",
    "twin/diagnosis/explain.py",
    "daemon/alarms.py",
    "cli/app.py",
    "cli/run.py",
    "cli/check.py",
    "cli/identify.py",
    "cli/explain.py",
    "cli/watch.py",
    "cli/samples.py",
    "daemon/summary.py",
    "sinks/zenoh/publisher.py",
    "sinks/zenoh/queries.py",
    "daemon/resume.py",
    "twin/prognostics/engine.py",
]
"""The reader modules (paths under twinwatch/), every one converted: also the restart's, the
alarm levels and the twin resumed (``daemon/resume.py``) and the trends replayed
(``twin/prognostics/engine.py``) from the stored messages (:class:`~twinwatch.sinks.base.Gate`'s
``latest_health``, ``history`` and ``timeline`` return typed views)."""

OTHER_DOCUMENTS = {
    ("watch/fleet.py", "Fleet.machines"): "the watcher's own snapshot (watch --once --json)",
    ("watch/subscription.py", "FleetWatcher._ask_latest"): "the watcher's own snapshot",
    ("watch/subscription.py", "FleetWatcher.settle"): "the watcher's own snapshot",
    ("watch/render.py", "_rul"): "a parameter entry of the watcher's snapshot",
    ("watch/render.py", "render"): "the watcher's own snapshot (its table)",
    ("watch/render.py", "_last_cell"):
        "a machine entry of the watcher's snapshot (its table's cell)",
    ("watch/render.py", "_parameters_cell"): "a machine entry of the watcher's snapshot",
    ("watch/render.py", "_alarms_cell"): "a machine entry of the watcher's snapshot",
    ("watch/render.py", "_diagnosis_cell"): "a machine entry of the watcher's snapshot",
    ("watch/render.py", "_quality_cell"): "a machine entry of the watcher's snapshot",
    ("watch/render.py", "_gap_words"): "the snapshot's delivery entry",
    ("watch/tail.py", "Tail.on_alarm"): "an alarm event (<prefix>/<machine>/alarm)",
    ("sinks/rerun/views.py", "RecordingViews._event_ops"): "an alarm event",
    ("sinks/rerun/texts.py", "event_row"): "an alarm event (its short log row)",
    ("daemon/summary.py", "resumed_line"): "the daemon's resume summary (Daemon.resumed)",
    ("daemon/summary.py", "new_run_line"): "the daemon's new-run summary (Daemon.new_run)",
    ("sinks/zenoh/queries.py", "history_parameters"): "the history query's parameters",
    ("sinks/opcua/server.py", "OpcUaServer._alarm"): "an alarm event (out.events)",
}
"""(file, function) -> the document it reads instead of the health message."""


def _field_names(model: type[BaseModel], seen: set[type[BaseModel]] | None = None) -> set[str]:
    """Every field name (and alias) of ``model`` and the models it contains."""
    seen = set() if seen is None else seen
    if model in seen:
        return set()
    seen.add(model)
    names: set[str] = set()

    def walk(tp: Any) -> None:
        if isinstance(tp, type) and issubclass(tp, BaseModel):
            names.update(_field_names(tp, seen))
        for arg in get_args(tp) if get_origin(tp) is not None or get_args(tp) else ():
            walk(arg)

    for name, f in model.model_fields.items():
        names.add(name)
        if f.alias:
            names.add(f.alias)
        walk(f.annotation)
    return names


FIELDS = _field_names(HealthMessage)


def string_indexes(source: str) -> list[tuple[str, int, str]]:
    """(function, line, key) of every read of a health field by its name in ``source``:
    ``x["window"]``, ``x.get("window")``, ``"window" in x``."""
    found: list[tuple[str, int, str]] = []

    def key_of(node: ast.AST) -> str | None:
        if isinstance(node, ast.Constant) and isinstance(node.value, str) \
                and node.value in FIELDS:
            return node.value
        return None

    def visit(node: ast.AST, scope: str) -> None:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            scope = f"{scope}.{node.name}" if scope else node.name
        key = None
        if isinstance(node, ast.Subscript) and isinstance(node.ctx, ast.Load):
            key = key_of(node.slice)
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) \
                and node.func.attr == "get" and node.args:
            key = key_of(node.args[0])
        elif isinstance(node, ast.Compare) and len(node.ops) == 1 \
                and isinstance(node.ops[0], ast.In | ast.NotIn):
            key = key_of(node.left)
        if key is not None:
            found.append((scope, node.lineno, key))  # type: ignore[attr-defined]
        for child in ast.iter_child_nodes(node):
            visit(child, scope)

    visit(ast.parse(source), "")
    return found


def test_the_scan_finds_a_string_index_of_the_message() -> None:
    """The scan is not vacuous: each kind of string index of a field is found, a key that is
    no field of the message (a counter's name, a config key) is not."""
    source = ('def f(doc):\n'
              '    a = doc["parameters"]["Ra"]\n'
              '    b = doc.get("window", 0)\n'
              '    c = "rul" in doc["parameters"]["Ra"]\n'
              '    d = doc["counters"].get("windows_estimated")\n'
              '    doc["alarms"] = {}\n')
    assert string_indexes(source) == [("f", 2, "parameters"), ("f", 3, "window"),
                                      ("f", 4, "rul"), ("f", 4, "parameters"),
                                      ("f", 5, "counters")]
    assert {"schema", "run", "rul_s", "evidence_for", "p_value", "waiting"} <= FIELDS


@pytest.mark.parametrize("reader", READERS)
def test_no_reader_indexes_the_decoded_message_by_a_field_name(reader: str) -> None:
    source = (PACKAGE / reader).read_text()
    found = [(scope, line, key) for scope, line, key in string_indexes(source)
             if (reader, scope) not in OTHER_DOCUMENTS]
    assert found == [], (f"twinwatch/{reader} reads the health message by string (read it "
                         f"through twinwatch.twin.health.read_health): {found}")


def test_every_allowed_function_still_exists() -> None:
    """An allow-list entry whose function is gone is removed, not kept as a hole."""
    for reader, scope in OTHER_DOCUMENTS:
        source = (PACKAGE / reader).read_text()
        tree = ast.parse(source)
        defs = (ast.FunctionDef, ast.AsyncFunctionDef)
        names = {f"{c.name}.{f.name}" for c in ast.walk(tree) if isinstance(c, ast.ClassDef)
                 for f in c.body if isinstance(f, defs)}
        names |= {f.name for f in tree.body if isinstance(f, defs)}
        assert scope in names, (reader, scope)


def test_the_message_states_the_estimations_parameter_statuses() -> None:
    """health.py restates ParameterStatus (so that a reader loads no estimation): the same."""
    from twinwatch.twin import health
    from twinwatch.twin.estimation import publish

    assert get_args(health.ParameterStatus) == get_args(publish.ParameterStatus)


def test_the_view_reads_an_older_or_partial_message_as_sent() -> None:
    """Schema 5 (no run, no trend, no diagnosis), a part of the wrong shape, a newer field,
    a null against an absent field: what each reader relies on."""
    view = read_health('{"schema": 5, "machine": "m1", "window": 3, "t_start": 0, '
                       '"parameters": {"Ra": {"value": 6.5, "status": "held", "rul": null},'
                       ' "La": 7}, "rmse": 0.1, "new_field": {"x": 1}, "nrmse": NaN}')
    assert (view.schema_, view.machine, view.run, view.window) == (5, "m1", None, 3)
    assert view.t_start == 0 and isinstance(view.t_start, int)  # as sent, not 0.0
    assert list(view.parameters) == ["Ra"] and view.rmse is None  # wrong shapes: absent
    ra = view.parameters["Ra"]
    assert ra.status == "held" and ra.trend is None and ra.rul is None
    assert sent(ra, "rul") and not sent(ra, "trend")
    assert view.nrmse is None and view.diagnosis is None and view.alarms is None
    with pytest.raises(AttributeError):
        sent(ra, "rull")
    with pytest.raises(ValueError):
        read_health("[1, 2]")
    full = read_health(view.model_dump_json(by_alias=True, exclude_unset=True))
    assert full == view
