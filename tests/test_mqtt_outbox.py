"""The state database as an output's outbox (issue 18): which stored windows an output has
delivered, kept in the store's own tables and written through its connection rules, survives a
restart, and the retention counts what it deletes undelivered."""

from __future__ import annotations

import threading
from pathlib import Path

from twinwatch.sinks.store import StateStore


def _save(store: StateStore, n: int, machine: str = "m1", first: int = 0) -> None:
    for w in range(first, first + n):
        assert store.save_window({"machine": machine, "window": w, "t_start": 2.0 * w,
                                  "t_end": 2.0 * w + 1.99}, None, doc=f'{{"window": {w}}}')


def test_first_open_starts_at_the_newest_window(tmp_path: Path):
    store = StateStore(tmp_path / "s.sqlite", prune_every=0)
    try:
        _save(store, 3)
        box = store.outbox("mqtt", "m1")
        position = box.start()
        assert box.pending(position, 10) == []      # the history before the output: not sent
        _save(store, 2, first=3)
        rows = box.pending(position, 10)
        assert [r.window for r in rows] == [3, 4]
        assert rows[0].doc == '{"window": 3}' and rows[0].run == store.run_id
        assert box.count(position) == 2
    finally:
        store.close()


def test_acks_and_position_survive_a_restart_and_skip_delivered(tmp_path: Path):
    path = tmp_path / "s.sqlite"
    store = StateStore(path, prune_every=0)
    box = store.outbox("mqtt", "m1")
    position = box.start()
    _save(store, 6)
    _save(store, 2, machine="other")
    rows = box.pending(position, 10)
    assert [r.window for r in rows] == list(range(6))
    # 0 and 1 delivered, 2 in flight, 3 and 5 acknowledged out of order
    box.ack([rows[0], rows[1], rows[3], rows[5]], position=rows[1].id)
    assert box.count(rows[1].id) == 2
    store.close()

    store = StateStore(path, prune_every=0)      # a restart: a new run id
    try:
        box = store.outbox("mqtt", "m1")
        position = box.start()
        assert position == rows[1].id
        assert [r.window for r in box.pending(position, 10)] == [2, 4]
        assert store.outbox("other-output", "m1").start() == rows[-1].id  # its own marks
        # a window acked twice (delivered again after a crash) is recorded once
        box.ack([rows[2], rows[2], rows[4]], position=rows[5].id)
        assert box.pending(rows[5].id, 10) == [] and box.count(rows[5].id) == 0
        assert box.doc_at_or_before(rows[5].id) == '{"window": 5}'
    finally:
        store.close()


def test_retention_counts_undelivered_windows_as_dropped(tmp_path: Path):
    store = StateStore(tmp_path / "s.sqlite", prune_every=0, keep_days=None, keep_rows=4,
                       prune_batch=3)
    try:
        box = store.outbox("mqtt", "m1")
        position = box.start()
        _save(store, 10)
        rows = box.pending(position, 20)
        box.ack([rows[0], rows[2]], position=rows[0].id)   # 0 delivered, 2 out of order
        assert store.prune() == 6                         # windows 0-5 deleted
        assert box.dropped == 4                           # 1, 3, 4, 5 never delivered
        position = box.start()
        assert position >= rows[5].id
        assert [r.window for r in box.pending(position, 20)] == [6, 7, 8, 9]
    finally:
        store.close()


def test_outbox_is_used_from_another_thread(tmp_path: Path):
    """The output's own thread reads and writes through its own connection while the worker
    stores windows."""
    store = StateStore(tmp_path / "s.sqlite", prune_every=0)
    box = store.outbox("mqtt", "m1")
    position = box.start()
    seen: list[int] = []
    errors: list[BaseException] = []

    def deliver() -> None:
        nonlocal position
        try:
            while len(seen) < 50:
                rows = box.pending(position, 7)
                if rows:
                    seen.extend(r.window for r in rows)
                    position = rows[-1].id
                    box.ack(rows, position)
        except BaseException as exc:  # noqa: BLE001 - reported by the test
            errors.append(exc)

    t = threading.Thread(target=deliver)
    t.start()
    _save(store, 50)
    t.join(timeout=30)
    store.close()
    assert not errors and seen == list(range(50))
