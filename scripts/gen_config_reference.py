"""Generate docs/configuration.md, the configuration reference, from the models that validate a
configuration file.

Every key of every table: the pydantic models of the file (:class:`TwinwatchConfig` and the
tables the twin owns: ``[estimation]``, ``[discovery]``, ``[identify]``, ``[prognostics]``,
``[diagnosis]``,
``[acquisition.adaptive]``), of each built-in driver's ``[driver]`` table, of each built-in
output's table (``[state]``, ``[zenoh]``, ``[recording]``, ``[outputs.mqtt]``) and of
``[alarms]``; and the options of each built-in twin model (``[machine.options]``, the model's
constructor keywords, described from its docstring). Each row: the key's dotted path, its
type, its default and the model's own description.

    python scripts/gen_config_reference.py            # writes docs/configuration.md
    python scripts/gen_config_reference.py --check    # exit 1 if docs/configuration.md is stale
    python scripts/gen_config_reference.py --out DIR  # write DIR/configuration.md instead

``tests/test_docs.py`` runs the check, so a key added to a model without regenerating the page
fails the tests.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import inspect
import re
import sys
import types
import typing
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from pydantic import BaseModel

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "configuration.md"


def _load(spec: str) -> Any:
    module, _, name = spec.partition(":")
    return getattr(importlib.import_module(module), name)


def _unwrap(tp: Any) -> Any:
    """The type inside Annotated."""
    while typing.get_origin(tp) is typing.Annotated:
        tp = typing.get_args(tp)[0]
    return tp


def _models_in(tp: Any) -> list[type[BaseModel]]:
    """The BaseModel classes a (possibly Optional/Union) annotation allows."""
    tp = _unwrap(tp)
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        return [tp]
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return [m for a in typing.get_args(tp) for m in _models_in(a)]
    return []


def type_name(tp: Any) -> str:
    """A short readable name of an annotation: ``float``, ``list[str]``, ``"a" | "b"``."""
    tp = _unwrap(tp)
    origin = typing.get_origin(tp)
    if tp is type(None):
        return "none"
    if tp is Any:
        return "any"
    if origin is typing.Literal:
        return " \\| ".join(f'"{a}"' if isinstance(a, str) else repr(a)
                            for a in typing.get_args(tp))
    if origin in (typing.Union, types.UnionType):
        return " \\| ".join(type_name(a) for a in typing.get_args(tp))
    if origin is not None:
        args = ", ".join(type_name(a) for a in typing.get_args(tp))
        base = getattr(origin, "__name__", str(origin))
        return f"{base}[{args}]" if args else base
    if isinstance(tp, type):
        if issubclass(tp, BaseModel):
            return "table"
        return tp.__name__
    return str(tp).replace("typing.", "")


def _default(value: Any) -> str:
    if value is None:
        return "none"
    if isinstance(value, BaseModel):
        return ""
    if isinstance(value, bool):
        return "`true`" if value else "`false`"
    if isinstance(value, str):
        text = f'"{value}"'
    elif isinstance(value, Path):
        text = f'"{value}"'
    else:
        text = repr(value)
    text = text.replace("|", "\\|")
    return f"`{text}`" if len(text) <= 60 else f"`{text[:57]}...`"


def _cell(text: str | None) -> str:
    """One table cell: one line, reST roles and literals as Markdown code."""
    text = " ".join((text or "").split())
    text = re.sub(r":\w+:`~?(?:[\w.]+\.)?([\w]+)`", r"`\1`", text)
    return text.replace("``", "`").replace("|", "\\|")


Row = tuple[str, str, str, str]


def model_rows(model: type[BaseModel], prefix: str,
               resolve: Callable[[str, Any], type[BaseModel] | None] | None = None
               ) -> Iterator[Row]:
    """One row per key of ``model`` under ``prefix`` (``acquisition.``), sub-tables after their
    parent's keys: ``name.<key>`` for a table of tables, ``name[]`` for an array of tables."""
    subtables: list[tuple[str, type[BaseModel]]] = []
    attrs = _args_doc(model)
    for name, field in model.model_fields.items():
        key = prefix + (field.alias or name)
        what = field.description or attrs.get(field.alias or name) or attrs.get(name)
        tp = _unwrap(field.annotation)
        origin = typing.get_origin(tp)
        default: Any = field.get_default(call_default_factory=True) if not field.is_required() \
            else None
        sub = _models_in(tp)
        if not sub and isinstance(default, BaseModel):  # a twin's table, validated lazily
            sub = [type(default)]
        if not sub and resolve is not None:
            found = resolve(key, tp)
            sub = [found] if found else []
        if sub:
            yield key, "table", "", _cell(what or _summary(sub[0]))
            subtables.append((key + ".", sub[0]))
            continue
        if origin is dict:
            value_models = _models_in(typing.get_args(tp)[1])
            if value_models:
                yield key, "table of tables", "", _cell(what or _summary(value_models[0]))
                subtables.append((key + ".<name>.", value_models[0]))
                continue
        if origin is list:
            item_models = _models_in(typing.get_args(tp)[0])
            if item_models:
                yield key, "array of tables", "", _cell(what or _summary(item_models[0]))
                subtables.append((key + "[].", item_models[0]))
                continue
        yield (key, type_name(tp), "required" if field.is_required() else _default(default),
               _cell(what))
    for sub_prefix, sub_model in subtables:
        yield from model_rows(sub_model, sub_prefix, resolve)


def _summary(cls: type) -> str:
    """The first paragraph of a class docstring."""
    return (inspect.getdoc(cls) or "").split("\n\n", 1)[0]


def _args_doc(cls: type) -> dict[str, str]:
    """``name -> description`` from the ``Args:`` or ``Attributes:`` section of a class
    docstring (a line ``a, b: text`` describes both)."""
    doc = cls.__dict__.get("__doc__") or ""
    doc = inspect.cleandoc(doc)
    head = next((h for h in ("Attributes:", "Args:") if h in doc), None)
    if head is None:
        return {}
    section = doc.split(head, 1)[1]
    section = re.split(r"\n\S", section, maxsplit=1)[0]  # up to the next unindented section
    out: dict[str, str] = {}
    names: list[str] = []
    for line in section.splitlines():
        m = re.match(r"^ {4}([A-Za-z_][\w, ]*):\s*(.*)$", line)
        if m:
            names = [n.strip() for n in m.group(1).split(",")]
            for n in names:
                out[n] = m.group(2)
        elif line.startswith("        ") and names:
            for n in names:
                out[n] += " " + line.strip()
    return out


def model_option_rows(name: str, cls: type) -> Iterator[Row]:
    """``[machine.options]`` of a twin model: its dataclass fields (constructor keywords)."""
    docs = _args_doc(cls)
    hints = typing.get_type_hints(cls)
    subtables = []
    for f in dataclasses.fields(cls):
        if not f.init or f.name.startswith("_"):
            continue
        tp = hints.get(f.name, f.type)
        default: Any = f.default if f.default is not dataclasses.MISSING else (
            f.default_factory() if f.default_factory is not dataclasses.MISSING else None)
        key = f"machine.options.{f.name}"
        sub = _models_in(tp)
        kind = "table" if sub else type_name(tp)
        yield key, kind, "" if sub and default is None else _default(default), \
            _cell(docs.get(f.name))
        if sub:
            subtables.append((key + ".", sub[0]))
    for prefix, model in subtables:
        yield from model_rows(model, prefix)


def _table(rows: list[Row]) -> str:
    lines = ["| key | type | default | what |", "|---|---|---|---|"]
    lines += [f"| `{k}` | {t} | {d} | {w} |" for k, t, d, w in rows]
    return "\n".join(lines)


def sections() -> list[tuple[str, str, list[Row]]]:
    """``(title, intro, rows)`` per section of the page, in the file's order."""
    from twinwatch.config.alarms import AlarmConfig
    from twinwatch.config.identify import IdentifyConfig
    from twinwatch.config.schema import AcquisitionConfig, MachineConfig
    from twinwatch.drivers import BUILTIN_DRIVERS
    from twinwatch.sinks import BUILTIN_SINKS, HISTORIC_TABLES
    from twinwatch.twin.diagnosis.library import DiagnosisConfig
    from twinwatch.twin.discovery.search import DiscoveryConfig
    from twinwatch.twin.estimation.estimator import EstimationConfig
    from twinwatch.twin.models import BUILTIN_MODELS
    from twinwatch.twin.prognostics.config import PrognosticsConfig

    out: list[tuple[str, str, list[Row]]] = [
        ("[machine]", "What is monitored.", list(model_rows(MachineConfig, "machine."))),
    ]
    for name, spec in BUILTIN_MODELS.items():
        out.append((f'[machine.options] of model = "{name}"',
                    f"`{spec}`: the model's options (its constructor keywords).",
                    list(model_option_rows(name, _load(spec)))))
    out += [
        ("[acquisition]", "Windows and buffering.",
         list(model_rows(AcquisitionConfig, "acquisition."))),
        ("[estimation]", "Which parameters, bounds, ties, the search, the identifiability gate.",
         list(model_rows(EstimationConfig, "estimation."))),
        ("[discovery]", "Meta-model candidates and when to search (DT'').",
         list(model_rows(DiscoveryConfig, "discovery."))),
        ("[prognostics]", "Trend and remaining useful life of each estimated parameter.",
         list(model_rows(PrognosticsConfig, "prognostics."))),
        ("[diagnosis]", "The fault library the ranked diagnosis reads (docs/diagnosis.md).",
         list(model_rows(DiagnosisConfig, "diagnosis."))),
        ("[identify]", "Commissioning: `twinwatch identify`.",
         list(model_rows(IdentifyConfig, "identify."))),
        ("[alarms]", "Per-parameter alarm rules.", list(model_rows(AlarmConfig, "alarms."))),
    ]
    for name, spec in BUILTIN_DRIVERS.items():
        cls = _load(spec)
        out.append((f'[driver] type = "{name}"', f"`{spec}`.",
                    list(model_rows(cls.config_class, "driver."))))
    for name, spec in BUILTIN_SINKS.items():
        table = HISTORIC_TABLES.get(name, f"outputs.{name}")
        cls = _load(spec)
        out.append((f"[{table}]", f'The output "{name}" (`{spec}`).',
                    list(model_rows(cls.config_class, table + "."))))
    return out


def render() -> str:
    parts = [
        "# Configuration reference",
        "",
        "<!-- generated by scripts/gen_config_reference.py from the models: do not edit; "
        "regenerate (tests/test_docs.py fails while it is stale) -->",
        "",
        "Every key of every table a machine's TOML file may hold, as the models that validate it "
        "define them (generated by `python scripts/gen_config_reference.py`; "
        "`twinwatch sample-config` prints the same keys commented, "
        "`twinwatch sample-config --driver NAME` a driver's). Unknown keys, `nan` and `inf` are "
        "refused at load, naming the key. `<name>`: a key of your choosing (a parameter, a "
        "signal, a register); `[]`: each table of an array of tables (`[[...]]`). A plug-in's "
        "driver or output adds its own table (see the plug-ins in "
        "[Getting started](getting-started.md)).",
        "",
    ]
    for title, intro, rows in sections():
        parts += [f"## {title}", "", intro, "", _table(rows), ""]
    return "\n".join(parts)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if the page is stale")
    ap.add_argument("--out", type=Path, help="directory to write configuration.md to")
    args = ap.parse_args()
    text = render()
    if args.check:
        if not PAGE.exists() or PAGE.read_text(encoding="utf-8") != text:
            print(f"{PAGE.relative_to(ROOT)} is stale: run python scripts/gen_config_reference.py",
                  file=sys.stderr)
            return 1
        return 0
    dest = (args.out / "configuration.md") if args.out else PAGE
    dest.write_text(text, encoding="utf-8")
    print(f"wrote {dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
