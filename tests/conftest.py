"""Fixtures every test runs under: no thread leaked, the signal dispositions restored. The
helpers the tests share are in ``tests/helpers/`` (and ``harness/``), imported, never this file."""

from __future__ import annotations

import signal
import threading

import pytest


@pytest.fixture(autouse=True)
def _no_leaked_threads():
    """Fail a test that leaves threads behind (as pymodbus' conftest does)."""
    before = set(threading.enumerate())
    yield
    leaked = [t for t in threading.enumerate()
              if t not in before and t.is_alive() and not t.name.startswith(("pydevd", "zenoh"))]
    for t in leaked:
        t.join(timeout=2.0)
    leaked = [t for t in leaked if t.is_alive()]
    assert not leaked, f"threads leaked: {[t.name for t in leaked]}"


#: What every test starts and ends with: SIGINT raises KeyboardInterrupt, SIGTERM and SIGHUP
#: their default action. Not what the session started with: a test run started as a background
#: job of a non-interactive shell (``pytest &``, a CI runner) inherits SIGINT ignored, and an
#: ignored signal stays ignored in every child process (a handled one is reset to its default
#: at exec), so the recorder and watch tests' children ignored the SIGINT they were sent.
_DISPOSITIONS = {signal.SIGINT: signal.default_int_handler, signal.SIGTERM: signal.SIG_DFL,
                 signal.SIGHUP: signal.SIG_DFL}


def _restore_dispositions() -> None:
    for n, h in _DISPOSITIONS.items():
        if signal.getsignal(n) is not h:
            signal.signal(n, h)


_restore_dispositions()


@pytest.fixture(autouse=True)
def _signal_dispositions_restored():
    """Give every test the signal dispositions of ``_DISPOSITIONS``, before and after it.
    `twinwatch run` invoked in-process (click's CliRunner) ends by ignoring SIGTERM and SIGINT
    at the OS level (``cli._ignore_late_stops``: a late stop must not kill a process that
    stopped cleanly); an ignored disposition is inherited by every child process. Restored
    *before* each test too: a module-scoped fixture that runs the CLI in-process
    (test_prognostics_resume, test_mqtt_docs) runs outside any test's own restore."""
    _restore_dispositions()
    yield
    _restore_dispositions()
