"""systemd's STATUS follows the machine's problems when two threads report them at once (issue
57): the window worker after each window and the acquisition loop every second both run
``Supervisor._watch_problems``. It read the problems, compared them with the last ones, kept
them and sent STATUS with no lock, so a thread that had kept "degraded" but not sent it yet
could send it after the other had kept and sent "normal": STATUS stayed DEGRADED although
nothing was, and no later call corrected it (the kept problems already matched).

The interleaving is made, not waited for: the first thread is held inside the status line it
is about to send, the second runs meanwhile, and the test releases the first once the second
has finished or is waiting to enter the section the first is in.
"""

from __future__ import annotations

import dis
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from twinwatch.daemon import supervisor
from twinwatch.daemon.supervisor import Supervisor


class _Daemon:
    """The running daemon as ``_watch_problems`` reads it: its current problems."""

    def __init__(self) -> None:
        self.now: list[str] = []

    def problems(self) -> list[str]:
        return list(self.now)


def _entering(thread: threading.Thread, function: str) -> bool:
    """Whether ``thread`` is at the entry of a ``with`` block (or a call into C: a lock's
    acquire) in ``function``, its innermost frame: waiting there for what another thread
    holds."""
    frame = sys._current_frames().get(thread.ident or 0)
    if frame is None or frame.f_code.co_name != function:
        return False
    op = next((i.opname for i in dis.get_instructions(frame.f_code)
               if i.offset == frame.f_lasti), "")
    return op in ("BEFORE_WITH", "CALL", "PRECALL", "CALL_FUNCTION", "CALL_METHOD")


def _until(done: Any) -> None:
    """Poll ``done()`` until true (a hang guard at 30 s: no assertion on time)."""
    deadline = time.monotonic() + 30
    while not done():
        assert time.monotonic() < deadline, "hung"
        time.sleep(0.001)


def test_status_ends_on_the_problems_of_the_last_report(monkeypatch: pytest.MonkeyPatch,
                                                         tmp_path: Path) -> None:
    sent: list[str] = []
    # a Python function (not list.append): a thread seen in C code in _watch_problems itself
    # is one waiting for a lock
    notifier = SimpleNamespace(status=lambda line: sent.append(line))
    sup = Supervisor(lambda: None, base_dir=tmp_path, source="test",  # type: ignore[arg-type]
                     notifier=notifier, watchdog=SimpleNamespace())  # type: ignore[arg-type]
    daemon = _Daemon()
    sup.daemon, sup.config = daemon, SimpleNamespace()  # type: ignore[assignment]
    worker_in_status = threading.Event()
    release_worker = threading.Event()

    def status_line(config: Any, d: _Daemon) -> str:
        line = "DEGRADED: " + "; ".join(d.problems()) if d.problems() else "normal"
        if threading.current_thread().name == "worker":
            worker_in_status.set()  # it has kept "degraded" and is about to send it
            assert release_worker.wait(30), "never released"
        return line

    monkeypatch.setattr(supervisor, "status_line", status_line)
    daemon.now = ["source silent"]
    worker = threading.Thread(target=sup._watch_problems, args=(None,), name="worker")
    worker.start()
    assert worker_in_status.wait(30)
    daemon.now = []  # the source is back: the acquisition loop's tick reports it
    tick = threading.Thread(target=sup._watch_problems, args=(None,), name="tick")
    tick.start()
    # until the tick has reported, or waits to enter the section the worker is in
    _until(lambda: not tick.is_alive() or _entering(tick, "_watch_problems"))
    release_worker.set()
    worker.join(30)
    tick.join(30)
    assert not worker.is_alive() and not tick.is_alive()
    sup._watch_problems(None)  # the next tick: nothing changed since the last report
    assert sent[-1] == "normal", sent


def test_the_entry_check_sees_a_thread_waiting_for_a_lock() -> None:
    """The check the test above relies on: a thread waiting to enter a ``with`` block another
    thread holds is seen there; one that is not, is not."""
    lock = threading.Lock()

    def section() -> None:
        with lock:
            pass

    lock.acquire()
    waiting = threading.Thread(target=section)
    waiting.start()
    _until(lambda: _entering(waiting, "section"))
    lock.release()
    waiting.join(30)
    assert not waiting.is_alive() and not _entering(waiting, "section")

