"""RerunRecorder writes .rrd files that the rerun CLI accepts, also after the process dies.

Every call of the ``rerun`` CLI runs with ``CI=true`` so it writes no analytics files.
"""

from __future__ import annotations

import json
import os
import re
import select
import signal
import subprocess
import sys
import threading
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rerun as rr
from pydantic import ValidationError

from twinwatch.sinks.rerun import RecorderError, RecordingConfig, RerunRecorder

ROOT = Path(__file__).resolve().parents[1]
RERUN_CLI = Path(sys.executable).with_name("rerun")
OUTPUTS = ("ia", "omega")
PARAMETERS = {"Ra": "ohm", "La": "H", "J": "kg m^2"}
N = 200  # samples per window
DT = 0.01  # sample period [s]
TIMEOUT = 60.0


def rerun_cli(*args: str | Path) -> subprocess.CompletedProcess[str]:
    if not RERUN_CLI.exists():
        pytest.skip(f"rerun CLI not found at {RERUN_CLI}")
    return subprocess.run(
        [str(RERUN_CLI), *map(str, args)],
        env={**os.environ, "CI": "true"},
        capture_output=True,
        text=True,
        timeout=TIMEOUT,
    )


def verify(path: Path, *options: str) -> subprocess.CompletedProcess[str]:
    return rerun_cli("rrd", "verify", *options, path)


def window(k: int) -> dict[str, Any]:
    """Arguments of log_window for window ``k`` (200 samples at 10 ms, starting at 2k s)."""
    t = k * N * DT + DT * np.arange(N)
    return {
        "t": t,
        "measured": {"ia": np.sin(t), "omega": 100 * np.cos(t)},
        "simulated": {"ia": 0.9 * np.sin(t), "omega": 99 * np.cos(t)},
        "parameters": {"Ra": 1.2 + 0.1 * k, "La": np.float64(2e-3), "J": 1e-4},
        "health": {"machine": "m1", "window": k, "status": "ok", "rmse": np.float32(0.05)},
    }


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
    for p in PARAMETERS:
        counts[f"/{machine}/parameters/{p}"] = windows
    counts[f"/{machine}/health"] = windows
    counts[f"/{machine}/log"] = windows
    counts[f"/{machine}/model"] = windows  # the twin DT'' at each window
    return counts


def recorder(path: Path, machine: str = "m1") -> RerunRecorder:
    return RerunRecorder(
        RecordingConfig(path=str(path)), machine, outputs=OUTPUTS, parameters=PARAMETERS
    )


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
    monkeypatch.setattr("twinwatch.sinks.rerun.os.access", lambda path, mode: False)
    with pytest.raises(RecorderError, match="is not writable by this user"):
        recorder(tmp_path / "m1.rrd")
    assert not (tmp_path / "m1.rrd").exists()


CHILD = r"""
import os, signal, sys, time
import numpy as np
from tests.test_rerun_recorder import recorder, window

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
