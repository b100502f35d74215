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
read_across = ["J"]
[[faults]]
id = "shaft_custom"
component = "shaft"
terms = [{ kinds = ["periodic"], attach = ["d(omega)/dt"], harmonic = 1.0 }]
sensors = [{ kind = "frozen", channel = "ia" }]
checks = [{ output = "Va", link = 0.5 }]
deviations = [{ parameter = "D", direction = "up", min_pct = 3.0, when_held = ["Ke"] }]
scaling = [{ parameter = "D", power = -1.0 }]
action = "look"
source = "test"
"""

BAD = [
    ('kinds = ["periodic"]', 'kinds = ["periodc"]',
     "meta-model kind 'periodc', which the registry does not know; did you mean 'periodic'?"),
    ('speed_channel = "omega"', 'speed_channel = "omegaa"',
     "speed_channel 'omegaa' is not a channel of the dc_motor twin; did you mean 'omega'?"),
    ('channel = "ia"', 'channel = "iaa"',
     "fault 'shaft_custom' names the sensor channel 'iaa', which the dc_motor twin does not "
     "measure; did you mean 'ia'?"),
    ('model = "dc_motor"', 'model = "hydraulic_actuator"',
     "the library is for the 'hydraulic_actuator' model; this machine's model is 'dc_motor'"),
    ('output = "Va"', 'output = "Vaa"',
     "fault 'shaft_custom' names the output 'Vaa' in checks, which is not a channel of the "
     "dc_motor twin; did you mean 'Va'?"),
    ('when_held = ["Ke"]', 'when_held = ["Kee"]',
     "fault 'shaft_custom' names the parameter 'Kee' in when_held/when_estimated"),
    ('kind = "frozen"', 'kind = "stuck"',
     "faults.0.sensors.0.kind: Input should be 'frozen' or 'saturated'"),
    ('scaling = [{ parameter = "D"', 'scaling = [{ parameter = "Dd"',
     "fault 'shaft_custom' names the parameter 'Dd'; the dc_motor model has"),
    ('read_across = ["J"]', 'read_across = ["Jj"]',
     "read_across names 'Jj', not a parameter of the dc_motor twin; did you mean 'J'?"),
]


def _machine(tmp_path: Path, library: Path) -> Path:
    path = machine_config(tmp_path, "m1", port=None)
    path.write_text(path.read_text() + f'\n[diagnosis]\nlibrary = "{library}"\n')
    return path


@pytest.mark.parametrize(("good", "bad", "why"), BAD, ids=["kind", "speed", "sensor", "model",
                                                           "check", "when", "key", "scaling",
                                                           "across"])
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


def test_an_inline_fault_with_a_misspelt_kind_is_refused() -> None:
    from twinwatch.twin.diagnosis.library import DiagnosisConfig

    cfg = DiagnosisConfig.model_validate({"replace": True, "faults": [{
        "id": "x", "component": "c", "action": "a", "source": "s",
        "terms": [{"kinds": ["sinus"], "attach": ["*"]}]}]})
    with pytest.raises(ValueError, match=r"^diagnosis.faults: fault 'x' names the meta-model "
                       r"kind 'sinus'"):
        cfg.check_against("dc_motor", ["Ra"], ["d(ia)/dt"], channels=["ia"], outputs=["ia"])


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
            library.write_text(GOOD.replace('kinds = ["periodic"]', 'kinds = ["periodc"]'))
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
    assert "diagnosis.library" in msg and "meta-model kind 'periodc'" in msg, msg
    # and the SIGHUP said what changed, in one line (issue 37: a file it reads, not its own)
    hup = [r.getMessage() for r in caplog.records if r.getMessage().startswith("SIGHUP")]
    assert hup == ["SIGHUP: changed: diagnosis.library (faults.toml); reloading m1.toml"], hup
