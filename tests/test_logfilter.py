"""The rate limit on third-party log floods (twinwatch/daemon/logfilter.py): the first ``burst``
identical messages per interval, then one line saying how many were suppressed."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import pytest

from twinwatch.daemon import logfilter
from twinwatch.daemon.logfilter import RepeatFilter, flush, install


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


NAMES = ("can.interfaces.socketcand", "can.interfaces.socketcand.socketcand",
         "twinwatch.drivers.can", "pymodbus")


@pytest.fixture
def logged() -> Iterator[tuple[RepeatFilter, list[logging.LogRecord], Clock]]:
    """A handler collecting what passes a RepeatFilter (burst 3, interval 60 s, fake clock)."""
    records: list[logging.LogRecord] = []

    class Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append(record)

    handler = Collect()
    clock = Clock()
    f = RepeatFilter(burst=3, interval=60.0, clock=clock)
    handler.addFilter(f)
    for name in NAMES:
        log = logging.getLogger(name)
        log.addHandler(handler)
        log.propagate = False
        log.setLevel(logging.DEBUG)
    yield f, records, clock
    logfilter._FILTERS.discard(f)  # what it still counts must not reach the next test
    for name in NAMES:
        log = logging.getLogger(name)
        log.removeHandler(handler)
        log.propagate = True
        log.setLevel(logging.NOTSET)


def messages(records: list[logging.LogRecord]) -> list[str]:
    return [r.getMessage() for r in records]


def test_a_flood_is_cut_to_the_burst_and_counted_when_the_interval_is_over(logged):
    _, records, clock = logged
    flood = logging.getLogger("can.interfaces.socketcand")
    for _ in range(1000):
        flood.warning("Failed to connect to server: ConnectionRefusedError")
    assert len(records) == 3
    clock.t += 61.0  # the flood went on: the next identical message comes with the count
    flood.warning("Failed to connect to server: ConnectionRefusedError")
    assert messages(records)[3] == (
        "997 more identical messages suppressed in 61 s (the first 3 of every 60 s are logged):"
        " Failed to connect to server: ConnectionRefusedError")
    assert records[3].levelno == logging.WARNING and records[3].name == flood.name
    assert messages(records)[4] == "Failed to connect to server: ConnectionRefusedError"


def test_a_flood_that_ended_is_counted_by_flush(logged):
    f, records, clock = logged
    flood = logging.getLogger("pymodbus")
    for k in range(10):
        flood.error("Connection to (%s, %d) failed", "127.0.0.1", 5020 + k % 2)  # one template
    assert len(records) == 3
    f.flush()  # within the interval: nothing yet
    assert len(records) == 3
    clock.t += 60.0
    f.flush()
    assert messages(records)[3].startswith("7 more identical messages suppressed in 60 s")
    clock.t += 120.0
    f.flush(force=True)  # nothing more to say
    assert len(records) == 4


def test_a_forced_flush_reports_at_once_and_the_limit_goes_on(logged):
    f, records, clock = logged
    flood = logging.getLogger("can.interfaces.socketcand")
    for _ in range(5):
        flood.warning("same")
    f.flush(force=True)  # e.g. right after a reload attempt
    assert messages(records)[3].startswith("2 more identical messages suppressed in 0 s")
    flood.warning("same")  # same interval: still suppressed, counted from zero again
    clock.t += 60.0
    f.flush()
    assert messages(records)[4].startswith("1 more identical messages suppressed")


def test_distinct_messages_and_twinwatch_own_lines_pass(logged):
    _, records, _ = logged
    for k in range(5):
        logging.getLogger("pymodbus").warning(f"frame {k} malformed")  # each one different
    for _ in range(5):
        logging.getLogger("twinwatch.drivers.can").warning("ours: logged once per cause")
    assert len(records) == 10


def test_python_can_s_warning_of_a_tcp_read_ending_inside_a_frame_is_dropped(logged):
    """python-can's socketcand bus completes such a frame from its next read: nothing is
    wrong, however often it says so; its other warnings are rate-limited as before."""
    _, records, _ = logged
    log = logging.getLogger("can.interfaces.socketcand.socketcand")
    for _ in range(10):
        log.warning("Got incomplete message => waiting for more data")
    log.warning("Invalid Frame: < frame 12 >")
    assert messages(records) == ["Invalid Frame: < frame 12 >"]


def test_the_module_flush_reaches_every_installed_filter() -> None:
    """What the supervisor's tick calls: it needs no reference to the CLI's filter."""
    records: list[logging.LogRecord] = []

    class Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append(record)

    clock = Clock()
    handler = Collect()
    f = install(handler, burst=1, interval=10.0, clock=clock)
    log = logging.getLogger("thirdparty.lifecycle-test")
    log.addHandler(handler)
    log.propagate = False
    try:
        for _ in range(4):
            log.warning("again")
        clock.t += 10.0
        flush()
    finally:
        log.removeHandler(handler)
        logfilter._FILTERS.discard(f)
    assert messages(records) == ["again", "3 more identical messages suppressed in 10 s (the "
                                 "first 1 of every 10 s are logged): again"]


def test_install_is_idempotent_and_the_arguments_are_checked():
    handler = logging.NullHandler()
    first = install(handler)
    assert install(handler) is first and handler.filters == [first]
    logfilter._FILTERS.discard(first)
    with pytest.raises(ValueError, match="burst must be >= 1"):
        RepeatFilter(burst=0)
