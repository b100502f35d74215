"""The health history a daemon keeps (issue 22, memory per machine): with a state store only
the messages not stored yet and :data:`~twinwatch.daemon.pipeline.MEMORY_TAIL` more stay in
memory, the rest is read back from the store, so ``health_history`` is the same as when
everything stayed in memory; the run's summary reads each window's digest, not the messages."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from twinwatch.config.loader import default_config
from twinwatch.daemon import pipeline
from twinwatch.daemon.runner import Daemon
from twinwatch.twin.health import HealthMessage


def _run(tmp_path: Path, *, store: bool, history: int = 1000
         ) -> tuple[Daemon, list[HealthMessage]]:
    cfg = default_config()
    cfg.driver.plant.duration = 20.0  # type: ignore[union-attr]  # 10 windows of 2 s
    cfg.recording.enabled = False
    cfg.zenoh.enabled = False
    cfg.acquisition.history = history
    if store:
        cfg.state.path = str(tmp_path / "state.sqlite")
    else:
        cfg.state.enabled = False
    seen: list[HealthMessage] = []
    daemon = Daemon(cfg, persist=store, record=False)
    with daemon:
        daemon.add_callback(seen.append)
        daemon.run()
    return daemon, seen


@pytest.mark.parametrize("store", [True, False])
def test_history_is_every_window_whether_in_memory_or_stored(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, store: bool) -> None:
    monkeypatch.setattr(pipeline, "MEMORY_TAIL", 3)
    daemon, seen = _run(tmp_path, store=store)
    assert len(seen) >= 9
    kept = daemon.pipeline.history
    # in memory: the tail only when the store holds the rest, everything without a store
    assert len(kept) == (3 if store else len(seen))
    history = daemon.health_history
    assert [h.window for h in history] == [h.window for h in seen]
    assert [h.to_json() for h in history] == [h.to_json() for h in seen]
    digests = daemon.window_digests
    assert [d.elapsed_s for d in digests] == [h.elapsed_s for h in seen]
    assert [d.model_check_passed for d in digests] == [
        None if h.model_check is None else h.model_check.passed for h in seen]


def test_history_keeps_its_configured_length_from_the_store(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(pipeline, "MEMORY_TAIL", 2)
    daemon, seen = _run(tmp_path, store=True, history=5)
    assert [h.window for h in daemon.health_history] == [h.window for h in seen[-5:]]
    assert len(daemon.window_digests) == 5


def test_the_diagnosis_evidence_is_saved_every_few_windows_and_at_the_stop(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The diagnoser's evidence (hundreds of kB) goes to the state database with the first
    window, every :data:`~twinwatch.daemon.pipeline.EVIDENCE_EVERY` windows and at the stop,
    not with every window; a restart resumes the last window's evidence."""
    from twinwatch.io.encoding import to_json
    from twinwatch.sinks.store import StateStore

    monkeypatch.setattr(pipeline, "EVIDENCE_EVERY", 4)
    saved: list[int] = []
    keep = StateStore._keep_state

    def spy(store: StateStore, machine: str, window: int, *args: Any) -> None:
        if args[-1].get("diagnosis") is not None:
            saved.append(window)
        keep(store, machine, window, *args)

    monkeypatch.setattr(StateStore, "_keep_state", spy)
    daemon, seen = _run(tmp_path, store=True)
    assert daemon.pipeline.diagnoser is not None and len(seen) >= 9
    last = seen[-1].window
    assert saved == [*range(0, last + 1, 4), *([last] if last % 4 else [])]
    with StateStore(tmp_path / "state.sqlite") as st:
        state = st.load_twin_state(seen[-1].machine)
        now = json.loads(to_json(daemon.pipeline.diagnoser.state()))
        assert state is not None and state["diagnosis"] == now
