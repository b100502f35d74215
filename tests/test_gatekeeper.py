"""The pipeline's gate keeper (twinwatch/daemon/gatekeeper.py): the windows held while another
process holds the state database's write lock (issue 26 item 4), against a real state store and
a real lock taken by a second SQLite connection. The whole daemon under a 30 s lock is the slow
case of tests/test_fault_injection.py; these take about a second."""

from __future__ import annotations

import logging
import sqlite3
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from twinwatch.config.loader import default_config
from twinwatch.daemon.gatekeeper import GateKeeper
from twinwatch.plant.dcmotor import DCMotorPlantConfig
from twinwatch.sinks.base import ProcessedWindow, Sink
from twinwatch.sinks.store import StateStore
from twinwatch.twin.adaptation import TwinAdapter
from twinwatch.twin.health import build_health
from twinwatch.twin.models import create_model

from .helpers.plant import plant_windows

log = logging.getLogger("twinwatch.daemon.pipeline")


@pytest.fixture(scope="module")
def windows() -> list[ProcessedWindow]:
    """Windows 0..3 of one machine (one estimation, the message renumbered)."""
    cfg = default_config()
    model = create_model(cfg.machine.model, cfg.machine.options)
    adapter = TwinAdapter(model, cfg.estimation, cfg.discovery)
    _, (w,) = plant_windows(DCMotorPlantConfig(scenario="nominal", duration=10), 1, skip=1)
    result = adapter.process(w)
    h = build_health(machine="m1", model_name="dc_motor", run="r1", model=model, window=w,
                     adaptation=result, nominal={}, counters={"overruns": 0})
    out = []
    for i in range(4):
        hi = h.model_copy(update={"window": i, "t_start": 2.0 * i, "t_end": 2.0 * i + 2.0})
        out.append(ProcessedWindow(window=w, result=result, health=hi,
                                   health_json=hi.to_json(), events=[{"window": i}],
                                   twin_state=None))
    return out


@pytest.fixture
def store(tmp_path: Path) -> Iterator[StateStore]:
    st = StateStore(tmp_path / "state.sqlite", busy_timeout=0.1, prune_every=0)
    yield st
    st.close()


@pytest.fixture
def locker(tmp_path: Path, store: StateStore) -> Iterator[sqlite3.Connection]:
    """A second connection holding the database's write lock (a backup tool's)."""
    con = sqlite3.connect(tmp_path / "state.sqlite", isolation_level=None)
    con.execute("BEGIN IMMEDIATE")
    yield con
    if con.in_transaction:
        con.execute("ROLLBACK")
    con.close()


def _write(sink: Sink, out: ProcessedWindow) -> Any:
    return sink.write(out)


def _stored(store: StateStore) -> list[int]:
    return [h.window for h in store.history(limit=None)]


def test_held_windows_are_stored_oldest_first_once_the_lock_goes(
        store: StateStore, locker: sqlite3.Connection, windows: list[ProcessedWindow],
        caplog: pytest.LogCaptureFixture) -> None:
    keeper = GateKeeper("m1", _write, log)
    keeper.gate = store
    assert keeper.store(windows[0], can_hold=True) is None  # locked: held, not failed
    assert store.locked and keeper.held == 1
    assert keeper.hold(windows[1]) is None
    assert keeper.retry(give_up=False) is None  # still locked: they wait
    assert keeper.held == 2 and _stored(store) == []
    locker.execute("ROLLBACK")  # the lock is released
    with caplog.at_level(logging.WARNING, logger=log.name):
        released = keeper.retry(give_up=False)
    assert released is not None
    held, stored = released
    assert stored and [o.health.window for o in held] == [0, 1]
    assert _stored(store) == [0, 1]
    assert keeper.held == 0 and store.not_stored == 0
    assert keeper.counters() == {"store_delayed": 2}
    assert "2 windows that waited in memory are stored and published now" in caplog.text
    (line,) = keeper.summary()
    assert "2 windows waited in memory" in line and "still waiting" not in line
    assert keeper.store(windows[2], can_hold=True) is True  # and it writes at once again
    assert _stored(store) == [0, 1, 2]


def test_held_windows_are_given_up_when_the_daemon_stops(
        store: StateStore, locker: sqlite3.Connection, windows: list[ProcessedWindow],
        caplog: pytest.LogCaptureFixture) -> None:
    keeper = GateKeeper("m1", _write, log)
    keeper.gate = store
    assert keeper.store(windows[0], can_hold=True) is None
    assert keeper.hold(windows[1]) is None
    with caplog.at_level(logging.ERROR, logger=log.name):
        released = keeper.retry(give_up=True)
    assert released is not None
    held, stored = released
    assert not stored and [o.health.window for o in held] == [0, 1]
    assert keeper.held == 0
    assert store.not_stored == 2  # neither published; both wait in the store's backlog
    assert store.waiting == 2
    assert "2 windows that waited for its lock are not published (the daemon stops)" in (
        caplog.text)


def test_without_a_thread_to_retry_a_locked_window_is_not_held(
        store: StateStore, locker: sqlite3.Connection, windows: list[ProcessedWindow]) -> None:
    keeper = GateKeeper("m1", _write, log)
    keeper.gate = store
    assert keeper.store(windows[0], can_hold=False) is False
    assert keeper.held == 0 and keeper.delayed == 0 and keeper.summary() == []


def test_without_a_gate_every_window_counts_as_stored(windows: list[ProcessedWindow]) -> None:
    keeper = GateKeeper("m1", _write, log)
    assert keeper.store(windows[0], can_hold=True) is True
    assert keeper.retry(give_up=False) is None


def test_a_window_beyond_the_held_limit_publishes_its_alarm_events_once_later(
        windows: list[ProcessedWindow], monkeypatch: pytest.MonkeyPatch) -> None:
    """A window the keeper cannot hold (HELD_MAX held already: stored later, not published)
    hands its alarm events to the next stored window, once (they were queued twice: by the
    pipeline's hold and again by its fan-out)."""
    from twinwatch.daemon.pipeline import WindowPipeline

    published: list[list[Any]] = []

    class Publisher:  # what the fan-out uses of a publishing output
        name = "pub"
        publishes = True

        def write(self, out: ProcessedWindow) -> None:
            published.append(list(out.events))

    pipe = WindowPipeline(adapter=None, alarms=None, machine="m1",  # type: ignore[arg-type]
                          model_name="dc_motor", run="r1", nominal={}, counters=dict,
                          history=10)
    pipe.sinks = [Publisher()]  # type: ignore[list-item]
    monkeypatch.setattr(pipe.keeper, "hold", lambda out: False)  # the limit reached
    monkeypatch.setattr(pipe.keeper, "store", lambda out, can_hold: True)
    pipe._hold(windows[0])
    assert published == []
    pipe._deliver(windows[1])
    assert published == [[{"window": 0}, {"window": 1}]]
