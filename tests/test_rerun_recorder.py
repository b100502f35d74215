"""RerunRecorder writes .rrd files that the rerun CLI accepts, also after the process dies.

Every call of the ``rerun`` CLI runs with ``CI=true`` so it writes no analytics files.
"""

from __future__ import annotations

import calendar
import json
import math
import os
import re
import select
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rerun as rr
from pydantic import ValidationError

from twinwatch.sinks.rerun import RecorderError, RecordingConfig, RerunRecorder

from .helpers.recording import DT, OUTPUTS, PARAMETERS, TIMEOUT, N, recorder, rerun_cli, window

ROOT = Path(__file__).resolve().parents[1]


def verify(path: Path, *options: str) -> subprocess.CompletedProcess[str]:
    return rerun_cli("rrd", "verify", *options, path)


def rows(path: Path) -> Counter[str]:
    """Non-static rows per entity path in the recording store of ``path``."""
    counts: Counter[str] = Counter()
    for chunk in rr.chunk.RrdReader(path).stream():
        if not chunk.is_static:
            counts[chunk.entity_path] += chunk.num_rows
    return counts


def expected_rows(machine: str, windows: int) -> Counter[str]:
    counts: Counter[str] = Counter()
    for o in OUTPUTS:
        counts[f"/{machine}/outputs/{o}/measured"] = N * windows
        counts[f"/{machine}/outputs/{o}/twin"] = N * windows
        counts[f"/{machine}/residual/{o}"] = N * windows  # measured - twin, every sample
        counts[f"/{machine}/outputs/{o}/frame"] = windows  # two labelled ticks on its axis
        counts[f"/{machine}/residual/{o}/frame"] = windows  # the same for the residual
    counts[f"/{machine}/parameters"] = windows  # one series per parameter
    counts[f"/{machine}/health"] = windows
    counts[f"/{machine}/log"] = windows
    counts[f"/{machine}/model"] = windows  # the twin DT'' at each window
    return counts


def test_windows_are_recorded_and_the_file_verifies(tmp_path: Path) -> None:
    path = tmp_path / "m1.rrd"
    with recorder(path) as rec:
        for k in range(3):
            rec.log_window(**window(k))
        assert rec.windows == 3 and rec.errors == 0
    assert rec.closed
    rec.close()  # idempotent

    result = verify(path)
    assert result.returncode == 0, result.stderr
    assert rows(path) == expected_rows("m1", 3)

    reader = rr.chunk.RrdReader(path)
    assert [s.application_id for s in reader.recordings()] == ["twinwatch"]
    assert len(reader.blueprints()) == 1
    times: list[int] = []
    health_docs: list[str] = []
    for chunk in reader.stream():
        batch = chunk.to_record_batch()
        if chunk.entity_path == "/m1/outputs/omega/measured" and not chunk.is_static:
            times += batch.column("plant_time").cast("int64").to_pylist()
        if chunk.entity_path == "/m1/health":
            health_docs += batch.column("TextDocument:text").to_pylist()
    # plant_time is a duration timeline in ns: 0 .. 5.99 s over the 3 windows
    assert sorted(times)[0] == 0 and sorted(times)[-1] == round(5.99e9)
    last = [d[0] for d in health_docs if '"window": 2' in d[0]]
    assert len(last) == 1 and '"rmse": 0.05' in last[0]
    body = last[0].split("```json\n", 1)[1].rsplit("\n```", 1)[0]
    assert json.loads(body)["status"] == "ok"


def test_two_recorders_coexist_in_one_process(tmp_path: Path) -> None:
    with recorder(tmp_path / "a.rrd", "a") as rec_a, recorder(tmp_path / "b.rrd", "b") as rec_b:
        for k in range(2):
            rec_a.log_window(**window(k))
            rec_b.log_window(**window(k))
        rec_b.log_window(**window(2))
    for machine, windows in (("a", 2), ("b", 3)):
        path = tmp_path / f"{machine}.rrd"
        result = verify(path)
        assert result.returncode == 0, result.stderr
        assert rows(path) == expected_rows(machine, windows)


@pytest.mark.parametrize("case", ["missing-dir", "parent-is-file", "path-is-dir"])
def test_unwritable_path_raises_recorder_error_at_construction(tmp_path: Path, case: str) -> None:
    (tmp_path / "file").write_text("")
    (tmp_path / "dir.rrd").mkdir()
    path = {
        "missing-dir": tmp_path / "nope" / "m1.rrd",
        "parent-is-file": tmp_path / "file" / "m1.rrd",
        "path-is-dir": tmp_path / "dir.rrd",
    }[case]
    named = path if case == "path-is-dir" else path.parent
    with pytest.raises(RecorderError, match=re.escape(str(named))):
        recorder(path)
    assert not (tmp_path / "nope").exists()


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes through directory permissions")
def test_read_only_directory_raises_recorder_error(tmp_path: Path) -> None:
    ro = tmp_path / "ro"
    ro.mkdir(mode=0o500)
    try:
        with pytest.raises(RecorderError, match="not writable"):
            recorder(ro / "m1.rrd")
    finally:
        ro.chmod(0o700)


def test_directory_without_write_permission_raises_recorder_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The permission check itself, also when the tests run as root (which os.access lets by)."""
    monkeypatch.setattr("twinwatch.sinks.rerun.recorder.os.access", lambda path, mode: False)
    with pytest.raises(RecorderError, match="is not writable by this user"):
        recorder(tmp_path / "m1.rrd")
    assert not (tmp_path / "m1.rrd").exists()


CHILD = r"""
import os, signal, sys, time
import numpy as np
from tests.helpers.recording import recorder, window

mode, path = sys.argv[1], sys.argv[2]
if mode == "sigterm-handled":  # what the daemon's CLI does: SIGTERM becomes a normal shutdown
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))
rec = recorder(path)
for k in range(3):
    rec.log_window(**window(k))
if mode == "os-exit":
    os._exit(0)
print("logged", flush=True)
time.sleep(60)
"""


def run_child(mode: str, path: Path) -> int:
    """Run CHILD: it logs 3 windows and never calls close(); stop it as ``mode`` says."""
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, mode, str(path)],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT), "CI": "true"},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        if mode != "os-exit":
            assert proc.stdout is not None
            ready, _, _ = select.select([proc.stdout], [], [], TIMEOUT)
            assert ready, f"child did not log its windows within {TIMEOUT} s"
            assert proc.stdout.readline() == "logged\n", proc.stderr and proc.stderr.read()
            proc.send_signal({"sigint": signal.SIGINT}.get(mode, signal.SIGTERM))
        return proc.wait(timeout=TIMEOUT)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=TIMEOUT)
        for stream in (proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()


@pytest.mark.parametrize("mode", ["sigterm-handled", "sigint"])
def test_interrupted_process_leaves_a_complete_file(tmp_path: Path, mode: str) -> None:
    """SIGINT, or SIGTERM turned into SystemExit, without close(): the file is complete."""
    path = tmp_path / "m1.rrd"
    run_child(mode, path)
    result = verify(path)
    assert result.returncode == 0, result.stderr
    assert rows(path) == expected_rows("m1", 3)


@pytest.mark.filterwarnings("ignore:RRD file has no footer")
@pytest.mark.parametrize("mode", ["os-exit", "sigterm-default"])
def test_hard_stop_keeps_every_flushed_window(tmp_path: Path, mode: str) -> None:
    """os._exit or an unhandled SIGTERM: no footer, but every window is on disk and readable.

    ``rerun rrd verify`` then reports the missing footer unless told not to check it;
    ``rerun rrd optimize`` makes a complete copy (the documented recovery).
    """
    path = tmp_path / "m1.rrd"
    code = run_child(mode, path)
    assert code == (0 if mode == "os-exit" else -signal.SIGTERM)
    assert rows(path) == expected_rows("m1", 3)
    result = verify(path, "--check-footers", "false")
    assert result.returncode == 0, result.stderr

    fixed = tmp_path / "m1-fixed.rrd"
    result = rerun_cli("rrd", "optimize", path, "-o", fixed)
    assert result.returncode == 0, result.stderr
    result = verify(fixed)
    assert result.returncode == 0, result.stderr
    assert rows(fixed) == expected_rows("m1", 3)


def test_log_window_rejects_bad_input_without_recording(tmp_path: Path) -> None:
    with recorder(tmp_path / "m1.rrd") as rec:
        good = window(0)
        bad_cases: list[dict[str, Any]] = [
            {"t": good["t"][:, None]},
            {"t": good["t"][:0]},
            {"t": np.full(N, np.nan)},
            {"measured": {"ia": good["measured"]["ia"][:-1]}},
            {"simulated": {"torque": good["simulated"]["ia"]}},
            {"parameters": {"Kt": 0.1}},
        ]
        for change in bad_cases:
            with pytest.raises(ValueError):
                rec.log_window(**{**good, **change})
        with pytest.raises(TypeError):
            rec.log_window(**{**good, "health": {"x": object()}})
        assert rec.windows == 0
        rec.log_window(**{**good, "measured": {"ia": good["measured"]["ia"]}})  # omega absent
        assert rec.windows == 1


def test_log_from_worker_while_main_thread_closes(tmp_path: Path) -> None:
    path = tmp_path / "m1.rrd"
    rec = recorder(path)
    failures: list[BaseException] = []
    started = threading.Event()

    def worker() -> None:
        try:
            for k in range(200):
                rec.log_window(**window(k))
                started.set()
        except BaseException as exc:  # noqa: BLE001 - any escape is the failure under test
            failures.append(exc)

    thread = threading.Thread(target=worker, name="record-worker")
    thread.start()
    assert started.wait(TIMEOUT)
    rec.close()
    thread.join(TIMEOUT)
    assert not thread.is_alive() and failures == []
    assert rec.closed and 1 <= rec.windows <= 200
    result = verify(path)
    assert result.returncode == 0, result.stderr
    assert rows(path) == expected_rows("m1", rec.windows)


def test_disabled_recorder_writes_nothing(tmp_path: Path) -> None:
    path = tmp_path / "m1.rrd"
    config = RecordingConfig(path=str(path), enabled=False)
    with RerunRecorder(config, "m1", outputs=OUTPUTS, parameters=PARAMETERS) as rec:
        rec.log_window(**window(0))
        assert rec.recording is None and rec.windows == 0
    assert not path.exists()


def test_config_is_strict() -> None:
    assert RecordingConfig().path == "twinwatch.rrd"
    with pytest.raises(ValidationError):
        RecordingConfig.model_validate({"file": "x.rrd"})
    with pytest.raises(ValidationError):
        RecordingConfig(path=" ")
    with pytest.raises(ValueError):
        RerunRecorder(RecordingConfig(enabled=False), "m1", outputs=[], parameters={})


def test_rotation_writes_complete_files_and_leaks_no_stream(tmp_path: Path) -> None:
    """``rotate_windows = 3``, ``keep_files = 2``, 10 windows: files of windows 0-2, 3-5, 6-8
    (the first deleted), then the run's file with window 9 (``path`` links to it). Each file
    verifies, holds its own windows, model document and series styles; the process has no more
    threads after three rotations than before (one recording stream is re-pointed, never
    replaced: the SDK never frees a Python stream, rerun-io/rerun#2116)."""
    path = tmp_path / "m1.rrd"
    cfg = RecordingConfig(path=str(path), rotate_windows=3, keep_files=2)
    with RerunRecorder(cfg, "m1", outputs=OUTPUTS, parameters=PARAMETERS) as rec:
        threads = len(os.listdir("/proc/self/task"))
        for k in range(10):
            rec.log_window(**window(k))
        assert rec.rotations == 3 and rec.errors == 0
        assert len(os.listdir("/proc/self/task")) <= threads
    assert path.is_symlink() and path.resolve() == rec.path  # the run's file, m1-<UTC>.rrd
    rotated = sorted(tmp_path.glob(f"{rec.path.stem}.*.rrd"))
    assert [p.name.split(".")[-2] for p in rotated] == ["0001", "0002"]
    assert (tmp_path / "m1.rbl").is_file()  # the viewer layout for rotated files
    for f, windows in ((rotated[0], 3), (rotated[1], 3), (path, 1)):
        assert verify(f).returncode == 0, f
        assert rows(f) == expected_rows("m1", windows), f
        static = {c.entity_path for c in rr.chunk.RrdReader(f).stream() if c.is_static}
        assert "/m1/outputs/ia/measured" in static, (f, static)  # its series styles


# -- what the recording shows (issue 16) -------------------------------------------------------
def _views(container: Any) -> list[Any]:
    """Every view of a blueprint container, depth first (layout order)."""
    import rerun.blueprint as rrb

    out: list[Any] = []
    for part in container.contents:
        out += _views(part) if isinstance(part, rrb.Container) else [part]
    return out


def _prop(view: Any, archetype: str, field: str) -> Any:
    """A view property's value as plain Python."""
    batch = getattr(view.properties[archetype], field)
    return batch.as_arrow_array().to_pylist()


def _time_range(view: Any, archetype: str = "VisibleTimeRanges") -> list[tuple[str, Any]]:
    """A view's time range as ``[(kind, value), (kind, value)]`` for its start and end, kind
    ``Infinite``, ``CursorRelative`` [ns] or ``Absolute`` [ns] (the timeline: plant_time)."""
    props = view.properties[archetype]
    arr = (props.ranges if archetype == "VisibleTimeRanges" else props.view_range
           ).as_arrow_array()
    if archetype == "VisibleTimeRanges":
        assert arr.field("timeline").to_pylist() == ["plant_time"]
        arr = arr.field("range")
    out = []
    for end in ("start", "end"):
        union = arr.field(end)
        kind = union.type.field(union.type_codes.to_pylist()[0]).name
        out.append((kind, union.to_pylist()[0]))
    return out


STORY_UNITS = {"ia": "A", "omega": "rad/s", "Va": "V"}
STORY_PARAMETERS = {"Ra": "ohm", "La": "H", "J": "kg m^2", "Ke": "V s/rad", "Kt": "N m/A",
                    "D": "N m s/rad"}


def story_recorder(path: Path, **config: Any) -> RerunRecorder:
    """The default machine's recorder: Ra has the default alarm rule, Kt is tied (no view)."""
    from twinwatch.sinks.base import AlarmBands

    return RerunRecorder(
        RecordingConfig(path=str(path), **config), "m1", outputs=tuple(STORY_UNITS),
        parameters=STORY_PARAMETERS, output_units=STORY_UNITS,
        nominal={"Ra": 6.5, "La": 0.673, "J": 0.001171, "Ke": 0.038, "Kt": 0.038,
                 "D": 0.00143},
        estimated=("Ra", "La", "J", "Ke", "D"),
        alarm_bands={"Ra": AlarmBands(warning_high=5.0, warning_low=-5.0, alarm_high=10.0,
                                      alarm_low=-10.0)})


def test_the_blueprint_tells_the_story(tmp_path: Path) -> None:
    """Health views over the whole run, one per estimated parameter (the one with an alarm
    rule first and tallest), titled with its nominal and thresholds; measured vs twin and the
    residual per output over the last ``recent_s`` seconds with the output's unit; the
    data-quality strip over the whole run; model, log and key; no legend over a trace; the time
    panel follows the newest data. The file carries that blueprint."""
    path = tmp_path / "m1.rrd"
    with story_recorder(path, recent_s=8.0) as rec:
        bp = rec.views.blueprint()
        rec.log_window(**window(0))
    assert bp.time_panel.play_state == "following" and bp.time_panel.timeline == "plant_time"
    views = _views(bp.root_container)
    by_origin = {str(v.origin): v for v in views}
    whole = [("Infinite", None), ("Infinite", None)]
    health = [o for o in by_origin if o.startswith("/m1/health/")
              and not o.endswith(("/summary", "/projection"))]
    assert health == [f"/m1/health/{p}" for p in ("Ra", "La", "J", "Ke", "D")]  # not Kt
    # beside the panel of a parameter with an alarm rule (only), its projection: a 2-D view
    projections = [o for o in by_origin if o.endswith("/projection")]
    assert projections == ["/m1/health/Ra/projection"]
    assert by_origin["/m1/health/Ra/projection"].class_identifier == "2D"
    assert "- $origin/projection/**" in by_origin["/m1/health/Ra"].contents
    # each panel writes its summary (RUL, alarm moments) under its plot
    for p in ("Ra", "La", "J", "Ke", "D"):
        assert by_origin[f"/m1/health/{p}/summary"].class_identifier == "TextDocument"
    assert by_origin["/m1/health/Ra"].name == "Ra [% of 6.5 ohm]: warning +-5, alarm +-10 %"
    assert by_origin["/m1/health/J"].name == "J [% of 0.001171 kg m^2]"
    health_box = bp.root_container.contents[1].contents[0].contents[0]
    assert list(health_box.row_shares) == [2.0, 2.8]  # Ra, then the other four in a 2x2 grid
    # Ra's summary under its plot; the grid's rows are short: each summary beside its plot
    # (under it, the plot was about 50 px at 1600x1000 and its -10 label was cut)
    import rerun.blueprint as rrb

    ra_panel, grid = health_box.contents
    assert isinstance(ra_panel.contents[0], rrb.Vertical)
    for part in grid.contents:
        assert isinstance(part, rrb.Horizontal), part.name
        assert [str(v.origin).rsplit("/", 1)[-1] for v in part.contents] == [part.name, "summary"]
    # without a parameter under a rule the panels have the column: summaries under the plots
    from twinwatch.sinks.rerun.views import RecordingViews

    views_free = RecordingViews("m1", outputs=tuple(STORY_UNITS), parameters=STORY_PARAMETERS,
                              output_units=STORY_UNITS, nominal=rec.views.nominal,
                              estimated=("Ra", "La", "J", "Ke", "D"), alarm_bands={})
    free = views_free.blueprint().root_container.contents[1].contents[0].contents[0]
    assert all(isinstance(part, rrb.Vertical) for part in free.contents[0].contents)
    for o in (*health, "/m1/quality", "/m1/quality/elapsed_ms", "/m1/quality/problems"):
        v = by_origin[o]
        # the x axis spans the whole run (the data queried are the whole run by default)
        assert _time_range(v, "TimeAxis") == whole and "VisibleTimeRanges" not in v.properties
    recent = [("CursorRelative", -8_000_000_000), ("CursorRelative", 0)]
    for o, unit in STORY_UNITS.items():
        for origin, title in ((f"/m1/outputs/{o}", f"{o} [{unit}]: measured, twin"),
                              (f"/m1/residual/{o}", f"{o} residual [{unit}]")):
            v = by_origin[origin]
            assert v.name == title
            assert _time_range(v) == recent, origin  # the data queried: the axis follows
    for v in views:
        if "PlotLegend" in v.properties:
            assert _prop(v, "PlotLegend", "visible") == [False], v.origin
    assert {"/m1/model", "/m1/health", "/m1/log", "/m1/key"} <= set(by_origin)
    assert by_origin["/m1/quality"].contents == [
        "/m1/quality/nrmse_dt_prime", "/m1/quality/nrmse_dt_second", "/m1/quality/nrmse",
        "/m1/quality/model_check_failed", "/m1/quality/frame"]
    # the file holds the layout: the same view origins are in its blueprint
    blueprint = rr.chunk.RrdReader(rec.path).blueprints()
    assert len(blueprint) == 1
    origins = set()
    for chunk in rr.chunk.RrdReader(rec.path).stream(store=blueprint[0]):
        batch = chunk.to_record_batch()
        for name in batch.schema.names:
            if name.endswith("space_origin"):
                origins |= {o[0] for o in batch.column(name).to_pylist() if o}
    assert set(by_origin) <= origins


def _log_rows(path: Path, machine: str) -> list[tuple[str, str]]:
    """(level, text) of every TextLog row of ``machine`` in the recording at ``path``."""
    out: list[tuple[float, str, str]] = []
    for chunk in rr.chunk.RrdReader(path).stream():
        if chunk.entity_path != f"/{machine}/log" or chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        times = batch.column("plant_time").cast("int64").to_pylist()
        for t, text, level in zip(times, batch.column("TextLog:text").to_pylist(),
                                  batch.column("TextLog:level").to_pylist(), strict=True):
            out.append((t, level[0], text[0]))
    return [(level, text) for _, level, text in sorted(out, key=lambda r: r[0])]


def _scalars(path: Path, entity: str) -> list[tuple[float, list[float]]]:
    """(plant time [s], values) of every row of a Scalars entity, in time order."""
    return sorted((t, row["Scalars:scalars"]) for t, row in _rows(path, entity))


def story_window(k: int, dev: float, level: str = "normal",
                 status: str = "estimated") -> dict[str, Any]:
    """:func:`window` with a health message of the default machine: Ra ``dev`` % off."""
    w = window(k)
    ra = 6.5 * (1 + dev / 100)
    params = {p: {"value": 1.0, "unit": u, "nominal": 1.0, "deviation_pct": 0.0,
                  "status": "held", "rel_std_pct": None, "fused": None, "reason": "held"}
              for p, u in STORY_PARAMETERS.items()}
    params["Ra"] = {"value": ra, "unit": "ohm", "nominal": 6.5, "deviation_pct": dev,
                    "status": status, "rel_std_pct": 0.5, "fused": None, "reason": None}
    w["parameters"] = {"Ra": ra}
    w["measured"] = {"ia": w["measured"]["ia"], "omega": w["measured"]["omega"]}
    w["simulated"] = {"ia": w["simulated"]["ia"], "omega": w["simulated"]["omega"]}
    w["health"] = {"machine": "m1", "model": "dc_motor", "window": k, "t_start": 2.0 * k,
                   "t_end": 2.0 * k + 1.99, "parameters": params, "nrmse": 1e-3,
                   "elapsed_s": 0.15,
                   "model_check": {"passed": k != 1, "reasons": ["ia: not white"] * (k == 1)},
                   "terms": [], "residual": {"dt_prime": {"rmse": {"ia": 0.01}, "nrmse": 1e-3},
                                             "dt_second": None},
                   "counters": {"windows_abandoned": 1 if k >= 2 else 0, "windows_completed": k},
                   "alarms": {"Ra": {"level": level, "deviation_pct": dev}}}
    return w


def test_the_log_rows_follow_the_machines_state_a_rul_alarm_is_warn(tmp_path: Path) -> None:
    """Issue 56: Ra in deviation warning with its RUL alarm raised (schedule the maintenance:
    NE 107 MAINTENANCE_REQUIRED) is a WARN row, as its RUL ALARM event (before: every row
    ERROR while the machine was in WARNING); a deviation alarm is ERROR."""
    path = tmp_path / "m1.rrd"
    rul_ev = {"kind": "rul", "parameter": "Ra", "level": "alarm", "previous": "warning",
              "rul_s": 79.0, "rul_low_s": 49.0, "rul_high_s": 752.0, "t": 3.99, "window": 1,
              "message": "m1: RUL ALARM: Ra reaches its alarm threshold in 79 s"}

    def rul(k: int, dev: float, level: str, rul_level: str) -> dict[str, Any]:
        w = story_window(k, dev, level)
        w["health"]["alarms"]["Ra"]["rul"] = {"level": rul_level, "rul_s": 79.0}
        w["health"]["model_check"] = {"passed": True, "reasons": []}
        w["health"]["counters"] = {}
        return w

    with story_recorder(path) as rec:
        rec.log_window(**rul(0, -6.0, "warning", "warning"))
        rec.log_window(**rul(1, -7.0, "warning", "alarm"), events=[rul_ev])
        rec.log_window(**rul(2, -11.0, "alarm", "alarm"))
    rows = _log_rows(rec.path, "m1")
    per_window = [lvl for lvl, text in rows if text.startswith("window ")]
    assert per_window == ["WARN", "WARN", "ERROR"], rows
    (event,) = [(lvl, text) for lvl, text in rows if "RUL ALARM raised" in text]
    assert event[0] == "WARN", rows


def test_alarm_changes_and_values_are_in_the_log_and_on_the_plot(tmp_path: Path) -> None:
    """An alarm raise is an ERROR row with its message and a red marker at its deviation; a
    clear a WARN row and a green marker; the rows of windows in alarm are ERROR, in warning
    WARN, with the values; a failed model check and lost data are WARN; each window's
    deviation, its band and the thresholds are on the parameter's view."""
    path = tmp_path / "m1.rrd"
    raise_ev = {"parameter": "Ra", "level": "alarm", "previous": "normal",
                "deviation_pct": -12.0, "t": 3.99, "window": 1,
                "message": "m1: ALARM: Ra is 12.00 % below nominal (5.72 ohm vs nominal 6.5 ohm)"}
    clear_ev = {"parameter": "Ra", "level": "warning", "previous": "alarm",
                "deviation_pct": -8.0, "t": 7.99, "window": 3,
                "message": "m1: alarm cleared to warning: Ra is back to -8.00 % of nominal"}
    with story_recorder(path) as rec:
        rec.log_window(**story_window(0, -1.0))
        rec.log_window(**story_window(1, -12.0, "alarm"), events=[raise_ev])
        rec.log_window(**story_window(2, -11.0, "alarm", "fused"))
        rec.log_window(**story_window(3, -8.0, "warning", "held"), events=[clear_ev])
    rows = _log_rows(rec.path, "m1")
    # each row short enough for the log panel at 1600x1000 (a Rerun log row is not wrapped)
    assert max(len(text) for _, text in rows) <= 80, rows
    assert ("ERROR", "0:04 ALARM raised: Ra -12.00 % of nominal") in rows
    assert ("WARN", "0:08 Ra alarm cleared to warning (-8.00 %)") in rows
    per_window = [(lvl, text) for lvl, text in rows if text.startswith("window ")]
    assert [lvl for lvl, _ in per_window] == ["INFO", "ERROR", "ERROR", "WARN"]
    assert per_window[0][1] == "window 0 0:02 Ra -1.00 % (6.435 ohm)"
    assert per_window[1][1] == "window 1 0:04 Ra -12.00 % (5.72 ohm) ALARM | model check " \
        "FAILED: ia: not white"
    # the whole-run axis frame is logged when it changes: -16..16 % from the first window on
    assert _scalars(rec.path, "/m1/health/Ra/frame") == [(1.99, [-16.0, 16.0])]
    assert per_window[2][1].endswith("fused, ALARM | lost: windows_abandoned +1")
    assert per_window[3][1] == "window 3 0:08 Ra -8.00 % held, WARNING"  # held: no value
    assert _scalars(rec.path, "/m1/health/Ra/events/alarm") == [(3.99, [-12.0])]
    assert _scalars(rec.path, "/m1/health/Ra/events/cleared") == [(7.99, [-8.0])]
    assert [t for t, _ in _scalars(rec.path, "/m1/health/Ra/estimated")] == [1.99, 3.99]
    assert [t for t, _ in _scalars(rec.path, "/m1/health/Ra/fused")] == [5.99]
    assert [t for t, _ in _scalars(rec.path, "/m1/health/Ra/held")] == [7.99]
    # band (value +- 2 x 0.5 %), nominal, thresholds, headroom, deviation
    [series] = [v for t, v in _scalars(rec.path, "/m1/health/Ra/deviation") if t == 3.99]
    band_low, band_high = ((0.88 * (1 + s * 0.01) - 1) * 100 for s in (-1, 1))
    assert series == pytest.approx([band_low, band_high, 0.0, 5.0, -5.0, 10.0, -10.0,
                                    16.0, -16.0, -12.0])
    assert _scalars(rec.path, "/m1/quality/model_check_failed") == [(3.99, [1e3])]  # ppm
    assert [v for _, v in _scalars(rec.path, "/m1/quality/problems")] == [[0.0], [0.0], [1.0],
                                                                          [1.0]]


def test_a_second_run_loses_no_existing_recording(tmp_path: Path) -> None:
    """Each run writes its own file, ``<stem>-<UTC start>[-<run id>].rrd``; ``path`` is a link
    to the newest. A file an earlier version left at ``path`` is kept under its time; a run
    whose file another recorder is writing is refused, naming it; nothing is ever replaced."""
    path = tmp_path / "m1.rrd"
    path.write_bytes(b"an earlier version's recording")
    with recorder(path) as first:
        for k in range(2):
            first.log_window(**window(k))
        assert path.resolve() == first.path and first.path.parent == tmp_path
        assert re.fullmatch(r"m1-\d{8}T\d{6}Z(-2)?\.rrd", first.path.name), first.path.name
        with pytest.raises(RecorderError, match=r"recording .*m1\.rrd is in use by process "
                           + str(os.getpid())):
            recorder(path)
    kept = [p for p in tmp_path.glob("m1-*.rrd") if p != first.path]
    assert [p.read_bytes() for p in kept] == [b"an earlier version's recording"]
    assert any("was kept as" in line for line in first.summary())
    config = RecordingConfig(path=str(path))
    with RerunRecorder(config, "m1", outputs=OUTPUTS, parameters=PARAMETERS,
                       run="4f2a/run 7") as second:
        second.log_window(**window(0))
        summary = second.summary()
    assert re.fullmatch(r"m1-\d{8}T\d{6}Z-4f2a_run_7(-2)?\.rrd", second.path.name)
    with RerunRecorder(config, "m1", outputs=OUTPUTS, parameters=PARAMETERS,
                       run="20261122T101530Z-3f9a2c") as third:  # the daemon's run ids
        assert third.path.name == "m1-20261122T101530Z-3f9a2c.rrd"
    assert path.resolve() == third.path  # rerun m1.rrd opens the newest run
    assert summary[0] == f"recording: {second.path} (open with: rerun {path}, the link to it)"
    for rec, windows in ((first, 2), (second, 1)):
        assert verify(rec.path).returncode == 0
        assert rows(rec.path) == expected_rows("m1", windows)
    assert kept[0].read_bytes() == b"an earlier version's recording"


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
    return port


def _reader(url: str, out: Path) -> subprocess.Popen[str]:
    """A viewer stand-in: the rerun CLI saving what the live server sends to ``out`` (its own
    server on a free loopback port; its log in ``out`` + ``.log``)."""
    import rerun_cli

    binary = Path(rerun_cli.__file__).with_name("rerun")  # not the wrapper: a kill reaches it
    if not binary.exists():
        pytest.skip(f"rerun binary not found at {binary}")
    with open(f"{out}.log", "w") as log:
        return subprocess.Popen(
            [str(binary), url, "--save", str(out), "--bind", "127.0.0.1", "--port",
             str(_free_port())], env={**os.environ, "CI": "true"}, stdout=subprocess.DEVNULL,
            stderr=log, text=True)


def _received(out: Path, proc: subprocess.Popen[str], size: int = 20_000) -> None:
    """Wait until the viewer stand-in has saved at least ``size`` bytes."""
    deadline = time.monotonic() + TIMEOUT
    while not (out.exists() and out.stat().st_size >= size):
        assert proc.poll() is None, Path(f"{out}.log").read_text()
        got = out.stat().st_size if out.exists() else 0
        assert time.monotonic() < deadline, f"the viewer got {got} B in {TIMEOUT} s"
        time.sleep(0.1)


def _values(path: Path) -> dict[str, list[Any]]:
    """Every non-static row per entity (time and values), order-independent."""
    out: dict[str, list[Any]] = {}
    for chunk in rr.chunk.RrdReader(path).stream():
        if chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        times = batch.column("plant_time").cast("int64").to_pylist()
        data = [n for n in batch.schema.names if ":" in n and not n.startswith("log_")]
        rows_ = zip(times, *(batch.column(n).to_pylist() for n in data), strict=True)
        out.setdefault(chunk.entity_path, []).extend(repr(r) for r in rows_)
    return {k: sorted(v) for k, v in out.items()}


@pytest.mark.filterwarnings("ignore:RRD file has no footer")  # the viewer's file, being written
def test_the_live_stream_holds_what_the_file_holds(tmp_path: Path) -> None:
    """``serve = true``: a Rerun gRPC server on 127.0.0.1 with the same data: a viewer that
    connects after three windows gets them all (the history), a viewer killed mid-run
    disturbs nothing, and what a viewer saved equals the file, row for row. A recorder opened
    later on the address goes on with the same server (a reload: the viewer stays)."""
    import signal

    port = _free_port()
    path = tmp_path / "m1.rrd"
    with story_recorder(path, serve=True, serve_port=port) as rec:
        url = rec.live_url
        assert url == f"rerun+http://127.0.0.1:{port}/proxy"
        assert rec.status == f"live view on {url}"
        lost = _reader(url, tmp_path / "lost.rrd")
        for k in range(3):
            rec.log_window(**story_window(k, -2.0 * k))
        _received(tmp_path / "lost.rrd", lost)
        lost.send_signal(signal.SIGKILL)  # a viewer that goes away
        lost.wait(TIMEOUT)
        late = _reader(url, tmp_path / "live.rrd")
        _received(tmp_path / "live.rrd", late)  # the three windows before it connected
        for k in range(3, 6):
            rec.log_window(**story_window(k, -2.0 * k))
        assert rec.errors == 0 and rec.problem is None
    try:
        recorded = _values(rec.path)
        deadline = time.monotonic() + TIMEOUT
        while True:  # the viewer saves as it receives
            try:
                live = _values(tmp_path / "live.rrd")
            except (RuntimeError, ValueError, OSError):  # a chunk being written
                live = {}
            if live == recorded or time.monotonic() > deadline:
                break
            time.sleep(0.2)
        assert live.keys() == recorded.keys() and "/m1/health/Ra/deviation" in live
        for entity, values in recorded.items():
            assert live[entity] == values, entity
        assert sum(len(v) for v in live.values()) > 6 * 20
        # a reload: the next recorder on the address takes the server over, viewer and all
        with story_recorder(tmp_path / "m2.rrd", serve=True, serve_port=port) as again:
            assert again.live_url == url and rec.live_url is None
            again.log_window(**story_window(6, -12.0))
        deadline = time.monotonic() + TIMEOUT
        while True:
            try:
                rows = len(_values(tmp_path / "live.rrd").get("/m1/log", []))
            except (RuntimeError, ValueError, OSError):  # a chunk being written: rerun
                # raises RuntimeError "payload exceeds file size" (CI)
                rows = 0
            if rows >= 7:
                break
            assert time.monotonic() < deadline, "the viewer did not get the reload's window"
            time.sleep(0.2)
    finally:
        late.send_signal(signal.SIGINT)
        try:
            late.wait(TIMEOUT)
        finally:
            if late.poll() is None:
                late.kill()


def test_a_live_port_in_use_refuses_to_start_naming_the_key(tmp_path: Path) -> None:
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(RecorderError, match=rf"127\.0\.0\.1:{port}.*serve_port"):
            story_recorder(tmp_path / "m1.rrd", serve=True, serve_port=port)
    assert not list(tmp_path.glob("m1*.rrd")) or all(
        p.stat().st_size == 0 for p in tmp_path.glob("m1-*.rrd"))
    with pytest.raises(ValidationError, match="not an IP address"):
        RecordingConfig(serve_bind="localhost")
    with pytest.raises(ValidationError, match="amount of memory"):
        RecordingConfig(server_memory_limit="lots")
    assert RecordingConfig().serve is False and RecordingConfig().serve_bind == "127.0.0.1"


def test_the_daemons_alarm_reaches_the_recording(tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """Through the daemon: the simulated motor whose nameplate says Ra = 5.8 ohm (the plant has
    6.5: +12 %) raises the Ra alarm after 10 s; the recording holds the raise as an ERROR row
    with its values and a marker on Ra's view, and every window in alarm is an ERROR row."""
    from click.testing import CliRunner

    from twinwatch.cli import main

    text = (ROOT / "config" / "dc-motor-sim.toml").read_text()
    for old, new in (("duration = 1200.0", "duration = 24.0"), ("Ra = 6.5 ", "Ra = 5.8 "),
                     ("[zenoh]", "[zenoh]\nenabled = false")):
        assert old in text, old
        text = text.replace(old, new)
    (tmp_path / "m.toml").write_text(text)
    monkeypatch.chdir(tmp_path)
    r = CliRunner().invoke(main, ["run", "m.toml", "--no-progress"])
    assert r.exit_code == 0, r.output
    link = tmp_path / "twinwatch.rrd"
    assert f"recording: {link.resolve()} (open with: rerun twinwatch.rrd, the link to it)" \
        in r.output
    docs = [c.to_record_batch().column("TextDocument:text").to_pylist()
            for c in rr.chunk.RrdReader(link).stream() if c.entity_path == "/dc-motor-sim/health"]
    run = json.loads(docs[0][0][0].split("```json\n", 1)[1].rsplit("\n```", 1)[0])["run"]
    assert link.resolve().name == f"twinwatch-{run}.rrd"  # the run's own file, by its id
    rows_ = _log_rows(link, "dc-motor-sim")
    raised = [(lvl, text) for lvl, text in rows_ if "ALARM raised: Ra" in text]
    assert len(raised) == 1 and raised[0][0] == "ERROR", rows_
    assert re.fullmatch(r"0:\d\d ALARM raised: Ra \+1[12]\.\d\d % of nominal", raised[0][1]), raised
    marker = _scalars(link, "/dc-motor-sim/health/Ra/events/alarm")
    assert len(marker) == 1 and 11.0 < marker[0][1][0] < 13.0 and 9.9 <= marker[0][0] <= 16.0
    windows = [(lvl, text) for lvl, text in rows_ if text.startswith("window ")]
    assert len(windows) == 12
    in_alarm = [(lvl, text) for lvl, text in windows if text.endswith(" ALARM")]
    assert in_alarm and all(lvl == "ERROR" for lvl, _ in in_alarm)
    assert re.fullmatch(r"window 11 0:24 Ra \+1\d\.\d\d % \(6\.\d+ ohm\) ALARM",
                        in_alarm[-1][1]), in_alarm


def test_a_trend_and_its_rul_are_drawn_when_the_message_has_them(tmp_path: Path) -> None:
    """A health message with prognostics (``parameters.<p>.trend``, ``.rul``): the trend and
    its 2-sigma band in % of nominal on the parameter's view, the RUL's median in the log row
    (its interval on the parameter's panel)."""
    w = story_window(0, -4.0)
    ra = w["health"]["parameters"]["Ra"]
    ra["trend"] = {"level": 6.5 * 0.95, "level_std": 6.5 * 0.005}
    ra["rul"] = {"status": "degrading",
                 "warning": {"status": "crossed"},
                 "alarm": {"status": "predicted", "rul_s": 1200.0, "low_s": 900.0,
                           "high_s": 1500.0}}
    with story_recorder(tmp_path / "m1.rrd") as rec:
        rec.log_window(**w)
    [(t, trend)] = _scalars(rec.path, "/m1/health/Ra/trend")
    assert t == 1.99 and trend == pytest.approx([-6.0, -4.0, -5.0])
    [row] = [text for _, text in _log_rows(rec.path, "m1") if text.startswith("window 0")]
    assert row == "window 0 0:02 Ra -4.00 % (6.24 ohm) RUL alarm 20m 00s"


def _rows(path: Path, entity: str) -> list[tuple[float, Any]]:
    """(plant time [s], record batch row as a dict) of every row of ``entity``, in time
    order (a Clear: its ``Clear:is_recursive``)."""
    out = []
    for chunk in rr.chunk.RrdReader(path).stream():
        if chunk.entity_path != entity or chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        times = batch.column("plant_time").cast("int64").to_pylist()
        columns = {n: batch.column(n).to_pylist() for n in batch.schema.names
                   if ":" in n and not n.startswith("rerun.")}
        out += [(t / 1e9, {n: v[i] for n, v in columns.items()})
                for i, t in enumerate(times)]
    return sorted(out, key=lambda r: r[0])


def test_the_projection_to_the_alarm_is_drawn_latest_only(tmp_path: Path) -> None:
    """A parameter with an alarm rule whose message predicts the alarm's crossing: its trend
    from the level now to the threshold (median and both ends of the interval), the threshold
    and the moment now drawn in a 2-D view, each window's on the same entities (latest at the
    cursor: one projection on screen, never every window's stacked); the crossing's plant time
    and interval written on it; cleared when a window predicts none; never on a time-series
    view (which would keep every window's)."""
    from twinwatch.sinks.rerun.projection import BOX as _BOX

    windows = []
    for k, (dev, t_cross, t_high) in enumerate(((-4.0, 1090.0, 1200.0),
                                                 (-6.0, 1060.0, None), (-7.5, None, None))):
        w = story_window(k, dev)
        ra = w["health"]["parameters"]["Ra"]
        ra["trend"] = {"model": "exponential", "degrading": True, "growth": 1e-3,
                       "level": 6.5 * (1 + dev / 100), "level_std": 0.001}
        ra["rul"] = {"status": "degrading", "warning": {"status": "crossed"},
                     "alarm": ({"status": "predicted", "threshold": 6.5 * 0.9, "t": t_cross,
                                "t_low": t_cross - 40.0, "t_high": t_high}
                               if t_cross else {"status": "crossed", "threshold": 5.85})}
        windows.append(w)
    with story_recorder(tmp_path / "m1.rrd") as rec:
        for w in windows:
            rec.log_window(**w)
    lines = _rows(rec.path, "/m1/health/Ra/projection/lines")
    labels = _rows(rec.path, "/m1/health/Ra/projection/labels")
    assert [t for t, _ in lines] == [t for t, _ in labels] == [1.99, 3.99]  # one per window
    # what the first draws: the thresholds in range, now, the recent deviations, the band's
    # two ends and the median, all inside the view's bounds
    first, second = (row["LineStrips2D:strips"] for _, row in lines)
    assert len(first) == 6  # warning, alarm, now, the band's two ends, the median
    assert len(second) == 6  # alarm, now, the deviations so far, the band's one end, median
    for strip in (*first, *second):
        xy = np.array(strip)
        assert (xy[:, 0] >= 0).all() and (xy[:, 0] <= _BOX[0]).all()
        assert (xy[:, 1] >= 0).all() and (xy[:, 1] <= _BOX[1]).all()
    median, alarm = np.array(first[-1]), np.array(first[1])
    assert median[-1, 1] == pytest.approx(alarm[0, 1])  # the median reaches the threshold
    assert median[0, 1] < alarm[0, 1]  # from the level now (-4 %, higher: y is down)
    assert np.array(second[2]).shape == (2, 2)  # the two windows' deviations
    text = labels[0][1]["Points2D:labels"]
    assert {"alarm -10 %", "warning -5 %", "now 0:02", "18:10 (17:30-20:00)"} <= set(text)
    # the second's interval has an open end
    assert "17:40 (17:00-never)" in labels[1][1]["Points2D:labels"]
    # the third predicts none: the view is cleared (its children with it)
    [(t, clear)] = _rows(rec.path, "/m1/health/Ra/projection")
    assert t == 5.99 and clear["Clear:is_recursive"] == [True]
    # a parameter without an alarm rule has none
    assert not _rows(rec.path, "/m1/health/La/projection/lines")


def _rendered_lines(markdown: str, chars: int) -> float:
    """How many text lines ``markdown`` takes in a Rerun text panel ``chars`` characters wide
    (seen at 1600x1000: a text line 15 px, a table row 23 px, a paragraph's gap 8 px; text
    wraps at the panel's width, a table row does not)."""
    lines = 0.0
    for line in markdown.splitlines():
        text = re.sub(r"\*\*|`", "", line).strip()
        if not text:
            lines += 0.5
        elif text.startswith("|---"):
            continue
        elif text.startswith("|"):
            lines += 1.5
            assert len(text) <= chars, f"a table row wider than its panel: {text}"
        else:
            lines += math.ceil(len(text) / chars)
    return lines


def test_the_model_and_the_parameters_table_fit_at_1600x1000(tmp_path: Path) -> None:
    """The bottom row holds the model (the diagnosis, DT'' and its terms, the fit) and, beside
    it, the parameters' table (value and status, the fixed ones in a line, why the held ones
    are held) and the log: each text is whole in its panel at 1600x1000 for the default
    machine's message at the end of the demo (its six parameters, three held, one tied, and
    the diagnosis with its evidence). Measured against the blueprint's shares with the text
    sizes seen in the pictures (6.3 px a character, a text line 15 px; a panel's title and
    margins 45 px; the viewer's menu and the collapsed time panel 65 px)."""
    import rerun.blueprint as rrb

    from twinwatch.sinks.rerun.texts import model_document as _model_document
    from twinwatch.sinks.rerun.texts import parameter_table as _parameter_table
    from twinwatch.twin.health import read_health

    w = story_window(499, -7.71)
    params = w["health"]["parameters"]
    params["Ra"].update(value=5.99874, rel_std_pct=0.011)
    for name, unit, value in (("La", "H", 0.673), ("J", "kg m^2", 0.001171),
                              ("Ke", "V s/rad", 0.038)):
        params[name].update(value=value, nominal=value, unit=unit, status="held",
                            reason="held with Ke (lower priority): held at last trusted "
                            "value" if name != "Ke" else "not separable from D in this "
                            "window: held at last trusted value")
    params["Kt"].update(value=0.038, nominal=0.038, status="tied", reason="tied to Ke")
    params["D"].update(value=0.00143017, nominal=0.00143, deviation_pct=0.01,
                       status="estimated", rel_std_pct=0.067, reason=None)
    w["health"]["rmse"] = {"ia": 0.000366, "omega": 0.00148, "Va": 0.000456}
    w["health"]["diagnosis"] = {
        "status": "fault", "top": "winding_short", "probability": 0.96, "no_fault": 0.04,
        "unknown": 0.0, "faults": [
            {"id": "winding_short", "component": "armature winding", "probability": 0.96,
             "urgency": "high", "source": "", "action": "measure the armature resistance "
             "and the insulation resistance (megger, IEEE 43) at the next stop; rewind or "
             "replace the armature if turns are shorted", "evidence_against": [],
             "evidence_for": ["Ra = 5.9987 ohm is -7.71 % from its nameplate 6.5 ohm (+/- "
                              "0.10 %, 2 sigma, estimated): beyond the 1 % down",
                              "Ra trend (exponential, 500 windows) degrading at -90.6 %/h"]},
            *({"id": f, "component": "", "probability": 0.0, "urgency": "low", "source": "",
               "action": "", "evidence_for": [], "evidence_against": []}
              for f in ("load_inertia_change", "magnet_weakening", "unbalance"))]}
    doc = read_health(json.dumps(w["health"]))
    model, table = _model_document("m1", 999.99, doc), _parameter_table(doc)
    assert "| parameter |" not in model
    assert table.startswith("| parameter | value | status (+- 2 sigma) |")
    assert "| Kt | 0.038 N m/A | tied to Ke |" in table
    assert "La, J held: held with Ke (lower priority)" in table and "trusted" not in table

    with story_recorder(tmp_path / "m1.rrd") as rec:
        bp = rec.views.blueprint()
    root = bp.root_container
    bottom = root.contents[2]
    assert isinstance(bottom, rrb.Horizontal)
    tabs, beside, log = bottom.contents
    assert str(tabs.contents[0].origin) == "/m1/model"
    assert str(beside.origin) == "/m1/parameter_table" and str(log.origin) == "/m1/log"
    row_shares = list(root.row_shares)
    height = (1000 - 65) * row_shares[2] / sum(row_shares) - 45
    shares = list(bottom.column_shares)
    for text, share in ((model, shares[0]), (table, shares[1])):
        chars = int((1600 * share / sum(shares) - 20) / 6.3)
        assert _rendered_lines(text, chars) * 15 <= height, (text, chars, height)
    # the model and the table in one panel, as before, did not fit
    together = model + "\n" + table
    assert _rendered_lines(together, int((1600 * 0.75 / 2.0 - 20) / 6.3)) * 15 > height
    # no part named: what was ruled out and what cannot be seen (issue 34), and it still fits
    w["health"]["diagnosis"].update(
        status="no_fault", top=None, probability=0.95, no_fault=0.95,
        ruled_out=["unbalance (rotor and load balance) ruled out at 0.00: no periodic term on "
                   "d(omega)/dt at 1 x the shaft speed"],
        unobserved=["load_inertia_change (coupled load) cannot be seen now: J held, never "
                    "determined by a window"])
    quiet = _model_document("m1", 999.99, read_health(json.dumps(w["health"])))
    assert "**Diagnosis: no fault** (probability 0.95)" in quiet
    assert "*load_inertia_change (coupled load) cannot be seen now: J held, never determined " \
           "by a window*" in quiet
    chars = int((1600 * shares[0] / sum(shares) - 20) / 6.3)
    assert _rendered_lines(quiet, chars) * 15 <= height, (quiet, chars, height)
    # a part named with a near twin the data cannot tell from it, and a share for a change
    # the library does not know: both said under the part, and it still fits
    w["health"]["diagnosis"].update(
        status="fault", top="winding_short", probability=0.5, no_fault=0.0, unknown=0.3,
        split=["winding_short", "voltage_sensor_low"],
        separate="winding_short: measure the armature resistance at standstill; "
                 "voltage_sensor_low: measure the armature voltage at the motor's terminals",
        unexplained=["the window's own estimate fits the 150 windows since the change better "
                     "than any fault mode's twin: a change the library does not know"])
    w["health"]["diagnosis"]["faults"][0]["probability"] = 0.5
    split = _model_document("m1", 999.99, read_health(json.dumps(w["health"])))
    assert "*the data cannot tell winding_short and voltage_sensor_low apart; to tell: " \
           "winding_short: measure the armature resistance at standstill;" in split
    assert "*unknown 0.30: the window's own estimate fits the 150 windows" in split
    assert _rendered_lines(split, chars) * 15 <= height, (split, chars, height)


def _documents(path: Path, entity: str) -> list[tuple[float, str]]:
    """(plant time [s], text) of every TextDocument row of ``entity``, in time order."""
    return sorted((t, row["TextDocument:text"][0]) for t, row in _rows(path, entity))


def test_each_panel_writes_its_rul_and_the_moments_its_alarms_were_raised(
        tmp_path: Path) -> None:
    """Under each parameter's plot, its summary: the RUL to each threshold of its rule with its
    95 % interval and the plant time of the crossing (minutes:seconds), the moments its
    deviation alarm and its RUL alarm were raised (apart; a RUL raise also a marker of its own
    on the plot), a 2-sigma band that leaves the view said so; the nRMSE in ppm; an output whose
    window spans less than one labelled tick gets a transparent frame that reaches the next."""
    rul_ev = {"kind": "rul", "parameter": "Ra", "level": "warning", "previous": "normal",
              "t": 721.99, "window": 0, "message": "m1: RUL WARNING: Ra reaches ..."}
    dev_ev = {"kind": "deviation", "parameter": "Ra", "level": "warning",
              "previous": "normal", "deviation_pct": -5.2, "t": 877.99, "window": 1,
              "message": "m1: WARNING: Ra is 5.20 % below nominal"}
    windows = []
    for k, (dev, t_end) in enumerate(((-4.0, 721.99), (-5.2, 877.99))):
        w = story_window(k, dev)
        w["t"] = w["t"] - w["t"][0] + t_end - 1.99
        w["measured"]["ia"] = 50396.0 + 8.0 * np.linspace(0, 1, N)  # one tick: 50 400
        w["simulated"]["ia"] = w["measured"]["ia"] - 0.01
        ra = w["health"]["parameters"]["Ra"]
        ra["trend"] = {"model": "exponential", "degrading": True, "rate_pct_per_h": -165.0,
                       "level": 6.5 * (1 + dev / 100), "level_std": 0.001}
        ra["rul"] = {"status": "degrading",
                     "warning": ({"status": "crossed"} if k else
                                 {"status": "predicted", "rul_s": 156.0, "low_s": 120.0,
                                  "high_s": 200.0, "t": 878.0, "t_low": 842.0,
                                  "t_high": 922.0}),
                     "alarm": {"status": "predicted", "rul_s": 212.0, "low_s": 170.0,
                               "high_s": None, "t": 1090.0, "t_low": 1048.0,
                               "t_high": None}}
        la = w["health"]["parameters"]["La"]
        la.update(status="fused", nominal=1.0, value=1.0, deviation_pct=0.0,
                  fused={"low": -3.2, "high": 5.2})  # +-420 %
        windows.append((w, [rul_ev] if k == 0 else [dev_ev]))
    with story_recorder(tmp_path / "m1.rrd") as rec:
        for w, events in windows:
            rec.log_window(**w, events=events)
    docs = _documents(rec.path, "/m1/health/Ra/summary")
    assert [t for t, _ in docs] == [721.99, 877.99]
    first, last = docs[0][1], docs[1][1]
    assert "**Ra -4.00 %** estimated +- 1 % (2 sigma); trend exponential -165 %/h" in first
    assert ("**RUL to warning 2m 36s (2m 00s-3m 20s), at 14:38 (14:02-15:22), RUL to alarm "
            "3m 32s (2m 50s-never), at 18:10 (17:28-never)**") in first
    assert "RUL warning raised at 12:02" in first and "deviation" not in first
    assert "**warning crossed, RUL to alarm 3m 32s" in last
    assert "deviation warning raised at 14:38; RUL warning raised at 12:02" in last
    [(_, la_doc)] = [d for d in _documents(rec.path, "/m1/health/La/summary") if d[0] > 800]
    assert "2-sigma band from -420 to +420 %, drawn to +-11.5 %" in la_doc
    # the RUL raise on the plot, at Ra's deviation then, apart from the deviation's raise
    assert _scalars(rec.path, "/m1/health/Ra/events/rul_warning") == [(721.99, [-4.0])]
    assert _scalars(rec.path, "/m1/health/Ra/events/warning") == [(877.99, [-5.2])]
    assert [v for _, v in _scalars(rec.path, "/m1/quality/nrmse")] == [[1e3], [1e3]]
    frames = _scalars(rec.path, "/m1/outputs/ia/frame")
    # 50 390 reached, with room below it for its label (12 % of the axis)
    [(low, high)] = {tuple(v) for _, v in frames}
    assert high == 50404.0 and 0.12 <= (50390.0 - low) / (high - low) < 0.15
    omega = _scalars(rec.path, "/m1/outputs/omega/frame")  # 100 cos t: two ticks already
    assert all(v[0] >= -130.0 and v[1] <= 130.0 for _, v in omega)  # room for +-100 only


def test_render_views_leaves_the_tracked_pictures_alone_unless_asked() -> None:
    """Issue 24: scripts/render_views.py wrote over docs/images/*.png on every run; now into
    build/views/ (or --out), over docs/images/ only with --update."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("render_views",
                                                  ROOT / "scripts" / "render_views.py")
    assert spec is not None and spec.loader is not None
    script = importlib.util.module_from_spec(spec)
    sys.modules["render_views"] = script  # its dataclasses look their module up
    try:
        spec.loader.exec_module(script)
    finally:
        del sys.modules["render_views"]
    assert script.images_dir([]) == ROOT / "build" / "views"
    assert script.images_dir(["--out", "/tmp/x"]) == Path("/tmp/x")
    assert script.images_dir(["--update"]) == ROOT / "docs" / "images"
    with pytest.raises(SystemExit):
        script.images_dir(["--update", "--out", "/tmp/x"])


def test_a_source_on_the_wall_clock_gets_a_timestamp_timeline(tmp_path: Path) -> None:
    """Issue 24: a source whose time stamps are the wall clock (seconds since the epoch, e.g.
    a recorded log) showed plant time as +490 000 h; its timeline is now a timestamp and the
    text gives the UTC time of day."""
    t0 = float(calendar.timegm((2026, 11, 22, 14, 38, 5)))  # UTC
    w = story_window(0, -1.0)
    w["t"] = t0 + DT * np.arange(N)
    w["health"].update(t_start=t0, t_end=t0 + 1.99)
    with story_recorder(tmp_path / "m1.rrd") as rec:
        rec.log_window(**w)
    kinds = set()
    for chunk in rr.chunk.RrdReader(rec.path).stream():
        if not chunk.is_static and "plant_time" in chunk.to_record_batch().schema.names:
            kinds.add(str(chunk.to_record_batch().schema.field("plant_time").type))
    assert kinds == {"timestamp[ns]"}, kinds
    [(_, row)] = [(lvl, text) for lvl, text in _log_rows(rec.path, "m1")
                  if text.startswith("window 0")]
    assert row == "window 0 14:38:07Z Ra -1.00 % (6.435 ohm)", row


def test_an_alarm_change_is_one_short_row_of_its_own_kind() -> None:
    """Each kind of event gets a row that fits the log panel (the full message is in the
    health message): a fault the diagnosis raised or cleared names the fault, not a
    parameter's deviation (it once read 'alarm cleared to normal (n/a %)')."""
    from twinwatch.sinks.rerun.texts import event_row as _event_row

    fault = {"machine": "m1", "kind": "diagnosis", "fault": "unbalance", "level": "normal",
             "previous": "alarm", "probability": 0.12, "t": 286.0, "window": 142,
             "message": "m1: FAULT CLEARED: unbalance (probability 0.12): cleared: ..."}
    assert _event_row(fault, 286.0, "deviation", False, {}) == \
        "4:46 fault cleared: unbalance (probability 0.12)"
    assert _event_row(dict(fault, level="alarm", previous="normal", probability=0.9), 286.0,
                      "deviation", True, {}) == "4:46 FAULT raised: unbalance (probability 0.90)"
    other = {"machine": "m1", "kind": "sensor", "level": "warning", "previous": "normal",
             "message": "m1: sensor ia stuck"}
    assert _event_row(other, 61.0, "deviation", True, {}) == "1:01 sensor ia stuck"
    rul = {"machine": "m1", "kind": "rul", "parameter": "Ra", "level": "warning",
           "previous": "normal", "t": 488.0}
    assert _event_row(rul, 488.0, "rul", True, {}) == "8:08 RUL WARNING raised: Ra"
    assert _event_row(dict(rul, level="normal", previous="warning"), 500.0, "rul", False,
                      {}) == "8:20 Ra RUL warning cleared to normal"


R = 0.12 / (1 - 2 * 0.12)  # 12 % of the widened axis on each side


@pytest.mark.parametrize(("high", "frame"), [
    (30.0, (0.0, 100.0 / 0.88)),  # 0, 10, 20, 30 too dense in the strip: 0 and 100
    (220.0, (0.0, 200.0 / 0.88)),  # 0, 100, 200 labelled; room above 200
    (322.0, (0.0, 1000.0 / 0.88)),  # the default's first window: 0 and 1000, not 0 alone
    (1200.0, (0.0, 1200.0)),  # 0 and 1000, the top label 17 % below the edge
])
def test_the_estimation_panel_keeps_two_labels(high: float, frame: tuple[float, float]) -> None:
    """Issue 24: the estimation strip is about 55 px at 1600x1000; when the first window took
    322 ms the viewer labelled its axis 0 alone (ticks a hundred apart closer than it labels).
    Its frame reaches the next power of ten instead, with room for that label."""
    from twinwatch.sinks.rerun.style import sparse_frame as _sparse_frame

    assert _sparse_frame(high) == pytest.approx(list(frame))


@pytest.mark.parametrize(("values", "frame"), [
    ((-11.5, 11.5), (-10.0 - R * 23.0, 10.0 + R * 23.0)),  # an output's +-10
    ((0.0, 100.5), (-R * 100.5, 100.0 + R * 100.5)),  # the fit strip: 0 and 100
    ((-16.0, 16.0), (-16.0, 16.0)),  # +-10 far enough from the edges already
    ((0.0, 1.0), (-R, 1.0 + R)),  # the lost panel's counts while none was lost
])
def test_an_axis_frame_leaves_room_for_its_outermost_labels(
        values: tuple[float, float], frame: tuple[float, float]) -> None:
    """Issue 24: the viewer centres a tick's label on it and clips what leaves the plot: the
    fit strip's 100 was cut in half at 1600x1000. The frame reaches a labelled tick at both
    ends and leaves 12 % of the axis beyond it (a parameter's small panel too, whose +-10
    labels the layout gives about 100 px: the summary beside the plot, test above)."""
    from twinwatch.sinks.rerun.style import axis_frame as _frame

    assert _frame(np.array(values)) == pytest.approx(list(frame))
    low, high = _frame(np.array([0.0, 0.0]))  # one value: a frame around it, not a line
    assert low < 0.0 < high
    assert _frame(np.array([-11.5, 11.5]), room=False) == [-11.5, 11.5]


def test_the_estimation_frame_is_in_every_file() -> None:
    """The estimation panel's frame follows the run's slowest window, is logged only when it
    changes, and again after a new file's static part (a rotated file without it labelled 0
    alone again)."""
    from twinwatch.sinks.rerun.views import RecordingViews
    from twinwatch.twin.health import HealthView

    views = RecordingViews("m1", outputs=("ia",), parameters={"Ra": "ohm"})
    path = "/m1/quality/elapsed_ms/frame"

    def frames(elapsed_s: float) -> int:
        ops = views._quality_ops(HealthView.model_validate({"elapsed_s": elapsed_s}), 1.0)
        return sum(1 for op in ops if "/" + op.entity.lstrip("/") == path)

    views.static_ops()
    assert frames(0.322) == 1  # the first window: 0 .. 1000 with room
    assert views._frames["quality/elapsed_ms"] == pytest.approx([0.0, 1000.0 / 0.88])
    assert frames(0.030) == 0  # the same frame: not logged again
    views.static_ops()  # a new file
    assert frames(0.030) == 1  # the run's frame again, not the window's
    assert views._frames["quality/elapsed_ms"] == pytest.approx([0.0, 1000.0 / 0.88])
