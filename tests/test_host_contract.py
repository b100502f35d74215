"""The service contract (issue 36, item 1): one :class:`ServiceHost` whichever way the machines
run; workers report to their host in typed messages (a :class:`FleetStatus` on the
notification socket, a :class:`RunSummary` on stdout), never in prose a regex reads."""

from __future__ import annotations

import ast
import socket
from pathlib import Path

import pytest

from twinwatch.daemon.host import Host
from twinwatch.daemon.service import (
    FLEET_REPORT,
    FleetStatus,
    MachineSummary,
    RunSummary,
    ServiceHost,
)
from twinwatch.daemon.workers import ProcessHost, Worker

from .helpers.paths import ROOT


def _send(path: Path, *assignments: str) -> None:
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
        s.sendto("\n".join(assignments).encode(), str(path))


@pytest.fixture
def process_host(tmp_path: Path):  # type: ignore[no-untyped-def]
    # a directory whose name holds the brackets the old regex could not read past
    directory = tmp_path / "line 2 (hall B)"
    directory.mkdir()
    host = ProcessHost(directory, workers=2, work_root=tmp_path)
    for k in range(2):
        w = Worker(k, host)
        w.files = [directory / f"m{2 * k + i}.toml" for i in range(2)]
        host.workers.append(w)
    yield host
    for w in host.workers:
        w.close()
    host.close()


def test_both_hosts_are_one_contract() -> None:
    assert issubclass(Host, ServiceHost) and issubclass(ProcessHost, ServiceHost)
    assert not ServiceHost.__abstractmethods__ - {"start", "run", "status_line", "exit_status",
                                                  "summary", "abandon"}
    assert not Host.__abstractmethods__ and not ProcessHost.__abstractmethods__


def test_a_workers_status_is_read_from_its_typed_report_not_its_text(
        process_host: ProcessHost) -> None:
    """The human STATUS line is ignored (any wording, any directory name); the report is
    summed. A worker that has not reported is named starting."""
    w0, w1 = process_host.workers
    report = FleetStatus(monitored=1, machines=2, degraded=["m1: lost (invalid configuration: "
                                                            "machine.model (x))"])
    _send(w0.socket_path, "READY=1", "STATUS=anything at all (even brackets) :)",
          f"{FLEET_REPORT}={report.model_dump_json()}")
    w0.drain()
    assert w0.ready and w0.report == report
    _send(w0.socket_path, "STATUS=stopping: the machines finish their queued windows")
    w0.drain()
    assert w0.report == report  # a line that is not a report changes nothing
    status = process_host.fleet_status()
    # w0 is not alive (no process): its machines count, none as monitored
    assert (status.monitored, status.machines) == (0, 4)
    assert status.degraded == [*report.degraded, "worker 1: not running"]
    line = process_host.status_line()
    assert line.startswith(f"gateway: 0 of 4 machines monitored ({process_host.directory}; "
                           "0 worker processes); DEGRADED: m1: lost (invalid configuration")
    _send(w1.socket_path, f"{FLEET_REPORT}=not json")
    w1.drain()  # a broken report is logged and ignored, not half-read
    assert w1.report is None


def test_the_summary_is_merged_from_the_workers_typed_summaries(
        process_host: ProcessHost) -> None:
    """Each machine's last block in file order (a machine tried again: its last attempt), a
    given-up worker's machines lost, the total line counted from the blocks."""
    w0, w1 = process_host.workers
    w0.summaries.append(RunSummary(machines=[
        MachineSummary(name="m1", file="m1.toml", lost="invalid configuration: x"),
        MachineSummary(name="m0", file="m0.toml", lines=["twinwatch: 3 windows estimated"]),
        MachineSummary(name="m1", file="m1.toml", lines=["twinwatch: 1 windows estimated"]),
    ], total="ignored", exit_status=0))
    w0.codes = [-9, 0]  # killed once, then ended by itself
    w1.given_up = "worker 1 ended by SIGKILL 6 times within 120 s: given up"
    summary = process_host.summary()
    assert [m.file for m in summary.machines] == ["m0.toml", "m1.toml", "m2.toml", "m3.toml"]
    assert summary.lines() == [
        "== m0 (m0.toml): stopped", "twinwatch: 3 windows estimated",
        "== m1 (m1.toml): stopped", "twinwatch: 1 windows estimated",
        f"== m2 (m2.toml): lost: {w1.given_up}",
        f"== m3 (m3.toml): lost: {w1.given_up}",
        f"twinwatch gateway: 4 machines, 2 ran, 2 lost: m2 (m2.toml): {w1.given_up}; "
        f"m3 (m3.toml): {w1.given_up} (2 worker processes, 1 restarted)"]
    assert summary.exit_status == 1
    again = RunSummary.model_validate_json(summary.model_dump_json())
    assert again == summary  # what a worker prints is what its host reads


def test_the_command_line_holds_one_host_and_only_prints() -> None:
    """``run`` and ``_run_host`` dispatch on no attribute (no ``hasattr``, no ``host.fleet``
    branch in what is printed) and ``host`` is bound to one annotated type."""
    tree = ast.parse((ROOT / "twinwatch" / "cli" / "run.py").read_text())
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call)
             and isinstance(n.func, ast.Name) and n.func.id in ("hasattr", "getattr")
             and n.args and isinstance(n.args[0], ast.Name) and n.args[0].id == "host"]
    assert calls == []
    fns = {n.name: n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)}
    printer = fns["_run_host"]
    assert isinstance(printer.args.args[0].annotation, ast.Name)
    assert printer.args.args[0].annotation.id == "ServiceHost"
    reads = {n.attr for n in ast.walk(printer) if isinstance(n, ast.Attribute)
             and isinstance(n.value, ast.Name) and n.value.id == "host"}
    assert reads <= {"start", "notices", "progress", "run", "summary"}, reads
