"""Issue 37: a fault library's mistakes were silent. A misspelt term kind, speed channel or
sensor channel, or a library written for another model, gave a fault that could never match
and ``check-config`` said OK; a library with a bad key was refused over five lines ending in
a pydantic link. Each is now refused, naming the key, in one line: by ``check-config``, at
start (exit 78) and by a reload (one log line, the running configuration goes on)."""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from twinwatch.config.loader import ConfigError, load_config

from .helpers.cli import cli, machine_config

GOOD = """model = "dc_motor"
speed_channel = "omega"
[[faults]]
id = "shaft_custom"
component = "shaft"
alternatives = [{ term = "d(omega)/dt", shape = "periodic", harmonic = 1.0 },
                { stuck = "ia" }, { gain = "Va", range = [0.0, 50.0] },
                { parameter = "D", range = [0.0, 100.0] },
                { scale = { Ke = 1.0, Kt = 1.0 }, range = [-50.0, 0.0] }]
action = "look"
source = "test"
"""

BAD = [
    ('term = "d(omega)/dt"', 'term = "d(omegaa)/dt"',
     "fault 'shaft_custom' names the attach point 'd(omegaa)/dt'; did you mean 'd(omega)/dt'?"),
    ('speed_channel = "omega"', 'speed_channel = "omegaa"',
     "speed_channel 'omegaa' is not a channel of the dc_motor twin; did you mean 'omega'?"),
    ('stuck = "ia"', 'stuck = "iaa"',
     "fault 'shaft_custom' names the channel 'iaa'; did you mean 'ia'?"),
    ('model = "dc_motor"', 'model = "hydraulic_actuator"',
     "the library is for the 'hydraulic_actuator' model; this machine's model is 'dc_motor'"),
    ('gain = "Va"', 'gain = "Vaa"',
     "fault 'shaft_custom' names the channel 'Vaa'; did you mean 'Va'?"),
    ('shape = "periodic"', 'shape = "periodc"',
     "faults.0.alternatives.0.shape: Input should be 'constant', 'coulomb' or 'periodic'"),
    ('parameter = "D"', 'parameter = "Dd"',
     "fault 'shaft_custom' names the parameter 'Dd'; did you mean 'D'?"),
    ('Ke = 1.0, Kt', 'Kee = 1.0, Kt',
     "fault 'shaft_custom' names the parameter 'Kee'; did you mean 'Ke'?"),
    ('range = [0.0, 100.0]', 'range = [100.0, 0.0]',
     "faults.0.alternatives.3: range [100.0, 0.0]: low must be below high"),
]


def _machine(tmp_path: Path, library: Path) -> Path:
    path = machine_config(tmp_path, "m1", port=None)
    path.write_text(path.read_text() + f'\n[diagnosis]\nlibrary = "{library}"\n')
    return path


@pytest.mark.parametrize(("good", "bad", "why"), BAD, ids=["attach", "speed", "stuck", "model",
                                                           "gain", "shape", "parameter",
                                                           "scale", "range"])
def test_a_bad_library_is_refused_in_one_line_naming_the_key(
        tmp_path: Path, good: str, bad: str, why: str) -> None:
    library = tmp_path / "faults.toml"
    library.write_text(GOOD)
    path = _machine(tmp_path, library)
    load_config(path)  # the good library passes
    library.write_text(GOOD.replace(good, bad))
    with pytest.raises(ConfigError) as err:
        load_config(path)
    lines = str(err.value).splitlines()
    assert len(lines) == 2 and lines[0].endswith("invalid configuration"), lines
    assert lines[1].strip().startswith("diagnosis.library"), lines
    assert why in lines[1], lines
    assert "https://" not in str(err.value) and "Value error" not in str(err.value)
    r = cli("check-config", str(path))
    assert r.exit_code == 1 and why in r.output and "OK" not in r.output, r.output
    r = cli("run", "--no-progress", str(path))
    assert r.exit_code == 78 and why in r.output, r.output


def test_an_inline_fault_with_a_misspelt_parameter_is_refused() -> None:
    from twinwatch.twin.diagnosis.library import DiagnosisConfig

    cfg = DiagnosisConfig.model_validate({"replace": True, "faults": [{
        "id": "x", "component": "c", "action": "a", "source": "s",
        "change": {"parameter": "Raa", "range": [0.0, 10.0]}}]})
    with pytest.raises(ValueError, match=r"^diagnosis.faults: fault 'x' names the parameter "
                       r"'Raa'; did you mean 'Ra'\?"):
        cfg.check_against("dc_motor", ["Ra"], ["d(ia)/dt"], channels=["ia", "omega"],
                          outputs=["ia", "omega"])


def test_a_reload_refuses_a_bad_library_in_one_log_line(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A fleet of one: the library edited badly and SIGHUP: one log line naming the key, no
    pydantic link; the running configuration goes on."""
    from twinwatch.cli.app import load_runnable as _load_runnable
    from twinwatch.daemon.host import Host

    library = tmp_path / "faults.toml"
    library.write_text(GOOD)
    path = _machine(tmp_path, library)
    monkeypatch.chdir(tmp_path)
    host = Host(path, load=lambda: _load_runnable(path, tmp_path), workers=1)
    errors: list[BaseException] = []
    seen: dict[str, Any] = {}

    def refused() -> list[logging.LogRecord]:
        return [r for r in caplog.records if "reload refused" in r.getMessage()]

    def drive() -> None:
        try:
            deadline = time.monotonic() + 90
            while (d := host.only.supervisor.daemon) is None or d.windows_estimated < 1:
                assert time.monotonic() < deadline
                time.sleep(0.2)
            seen["daemon"] = d
            library.write_text(GOOD.replace('parameter = "D"', 'parameter = "Dd"'))
            host.reload()
            while not refused():
                assert time.monotonic() < deadline
                time.sleep(0.2)
            n = d.windows_estimated
            while d.windows_estimated < n + 1:  # it goes on
                assert time.monotonic() < deadline
                time.sleep(0.2)
        except BaseException as exc:  # noqa: BLE001 - reported by the test's thread
            errors.append(exc)
        finally:
            host.stop()

    caplog.set_level(logging.WARNING)
    host.start()
    t = threading.Thread(target=drive, daemon=True)
    t.start()
    host.run()
    t.join(5)
    assert not errors, errors
    assert host.only.supervisor.daemon is seen["daemon"]
    (record,) = refused()
    msg = record.getMessage()
    assert "\n" not in msg and "https://" not in msg, msg
    assert "diagnosis.library" in msg and "names the parameter 'Dd'" in msg, msg
    # and the SIGHUP said what changed, in one line (issue 37: a file it reads, not its own)
    hup = [r.getMessage() for r in caplog.records if r.getMessage().startswith("SIGHUP")]
    assert hup == ["SIGHUP: changed: diagnosis.library (faults.toml); reloading m1.toml"], hup
