"""Runs keep their identity (issue 16, item 4): every health message carries its run id, the
history filters by run, a simulated plant starting from t = 0 is a new run (it does not resume
an unrelated earlier run's twin and alarm), and an alarm's clear is logged like its raise.

The reload keeping the run id is tested where reloads are (tests/test_service.py, the
``[state]`` table changed: a new store, the same run; tests/test_fault_injection.py).
Every Zenoh session is on 127.0.0.1, scouting off, on a port picked free at run time.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

import pytest

from twinwatch.config.alarms import AlarmConfig, AlarmRule
from twinwatch.config.loader import default_config
from twinwatch.daemon.runner import Daemon
from twinwatch.sinks.store import StateStore
from twinwatch.twin.health import HealthMessage

from .helpers.net import endpoint, free_port, get_json, zsession

MACHINE = "dc-motor-sim"


def _config(tmp_path: Path, *, nameplate_ra: float, duration: float,
            port: int | None = None) -> Any:
    """The default simulated motor on a healthy plant (Ra = 6.5 ohm, scenario nominal), with
    the default config's Ra rule (warning 5 %, alarm 10 %, hysteresis 1, raised after 10 s,
    cleared after 30 s) and the given nameplate Ra: 7.5 ohm makes the healthy plant read
    -13 % (an alarm), 6.5 ohm is the truth."""
    cfg = default_config()
    cfg.driver.plant.duration = duration  # type: ignore[union-attr]
    cfg.driver.plant.scenario = "nominal"  # type: ignore[union-attr]
    cfg.recording.enabled = False
    cfg.state.path = str(tmp_path / "state.sqlite")
    cfg.machine.parameters["Ra"] = nameplate_ra
    cfg.alarms = AlarmConfig(parameters={"Ra": AlarmRule(
        warning=5.0, alarm=10.0, hysteresis=1.0, raise_after_s=10.0, clear_after_s=30.0)})
    if port is None:
        cfg.zenoh.enabled = False
    else:
        cfg.zenoh.listen = [endpoint(port)]
    return cfg


def _run(cfg: Any, **kw: Any) -> tuple[Daemon, list[HealthMessage], list[dict[str, Any]]]:
    """Run a daemon on ``cfg`` to the plant's end; its messages and alarm events."""
    seen: list[HealthMessage] = []
    events: list[dict[str, Any]] = []
    daemon = Daemon(cfg, persist=True, record=False, **kw)
    with daemon:
        update = daemon.alarms.update
        daemon.alarms.update = lambda h: _extend(events, update(h))  # type: ignore[method-assign]
        daemon.add_callback(seen.append)
        daemon.run()
    return daemon, seen, events


def _extend(events: list[dict[str, Any]], new: list[dict[str, Any]]) -> list[dict[str, Any]]:
    events.extend(new)
    return new


def test_a_second_simulated_run_does_not_resume_the_first_runs_alarm(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Issue 16: 'a new simulated run resumes an unrelated earlier run's twin and alarm (Ra in
    alarm for 15 windows on a healthy plant)'. The first run ends in alarm; the second, on the
    same state database with the right nameplate, is a new run: normal from its first window,
    no event. Asked to resume (the contrast), the alarm is carried over and cleared later, and
    the clear is logged at WARNING with the values, like the raise."""
    caplog.set_level(logging.INFO)
    first, seen1, events1 = _run(_config(tmp_path, nameplate_ra=7.5, duration=16.0))
    assert [e["level"] for e in events1] == ["alarm"]
    assert seen1[-1].alarms["Ra"].level == "alarm"

    second, seen2, events2 = _run(_config(tmp_path, nameplate_ra=6.5, duration=8.0))
    assert second.run_id != first.run_id
    assert second.restored is None and second.resumed is None
    assert second.new_run is not None and second.new_run["run"] == first.run_id
    assert [h.alarms["Ra"].level for h in seen2] == ["normal"] * len(seen2) and len(seen2) == 4
    assert events2 == []
    assert {h.run for h in seen1} == {first.run_id} and {h.run for h in seen2} == {second.run_id}

    # the contrast, on another state database: resuming carries the first run's alarm onto
    # the healthy plant until its 30 s clear time has passed (15 windows), then clears it
    other = tmp_path / "resumed"
    other.mkdir()
    _run(_config(other, nameplate_ra=7.5, duration=16.0))
    caplog.clear()
    third, seen3, events3 = _run(_config(other, nameplate_ra=6.5, duration=40.0), resume=True)
    assert third.resumed is not None and third.resumed["alarms"] == {"Ra": "alarm"}
    levels = [h.alarms["Ra"].level for h in seen3]
    assert levels[0] == "alarm" and levels[-1] == "normal"
    assert [(e["previous"], e["level"]) for e in events3] == [("alarm", "normal")]
    clear = [r for r in caplog.records if "CLEARED" in r.getMessage()]
    assert len(clear) == 1 and clear[0].levelno == logging.WARNING
    text = clear[0].getMessage()
    assert re.search(r"dc-motor-sim: ALARM CLEARED to normal: Ra is \d\.\d\d % (above|below) "
                     r"nominal \(6\.5\d* ohm vs nominal 6\.5 ohm\) since plant time \d+ s, back "
                     r"within the alarm threshold [-+]10 %", text), text
    raised = [r for r in caplog.records if ": ALARM:" in r.getMessage()]
    assert raised == []  # restored, not raised again


def test_history_filters_by_run(tmp_path: Path) -> None:
    """Two runs of the simulated plant in one state database share window numbers and plant
    times; the history query keeps one run's with run=<id> (or run=current), in the store
    and over Zenoh, and refuses a malformed run id naming it."""
    first, seen1, _ = _run(_config(tmp_path, nameplate_ra=6.5, duration=8.0))
    port = free_port()
    cfg = _config(tmp_path, nameplate_ra=6.5, duration=6.0, port=port)
    with Daemon(cfg, persist=True, record=False) as second:
        second.run()
        with zsession("client", connect=[endpoint(port)]) as s:
            base = f"twinwatch/{MACHINE}/history"
            everything = get_json(s, base)
            of_first = get_json(s, f"{base}?run={first.run_id}")
            of_current = get_json(s, f"{base}?run=current;t_from=1;t_to=3")
            bad = get_json(s, f"{base}?run=no/such*run!")
    n1, n2 = len(seen1), second.windows_estimated
    assert (n1, n2) == (4, 3)
    windows = everything[0]["windows"]
    assert [h["window"] for h in windows] == [*range(n1), *range(n2)]
    assert len({h["t_start"] for h in windows}) == n1  # plant time starts over: duplicates
    assert [(h["run"], h["window"]) for h in of_first[0]["windows"]] == [
        (first.run_id, w) for w in range(n1)]
    assert of_first[0]["run"] == first.run_id
    # run=current is the answering daemon's; with a plant-time range it is one run's range
    assert of_current[0]["run"] == second.run_id
    assert [(h["run"], h["window"]) for h in of_current[0]["windows"]] == [
        (second.run_id, 0), (second.run_id, 1)]
    assert "run='no/such*run!'" in bad[0]["error"]
    with StateStore(tmp_path / "state.sqlite") as st:
        assert [h.window for h in st.history(machine=MACHINE, run=second.run_id)] == [0, 1, 2]
        assert st.history(run="20000101T000000Z-000000") == []
        assert len(st.history(t_from=0.0, t_to=1.0, machine=MACHINE)) == 2  # one per run
