"""The interpretable diagnosis (issue 25): the fault libraries as data, and the ranked faults
through the real pipeline (simulated plant -> driver -> ring buffer -> estimation, discovery,
prognostics -> health message -> noisy-OR diagnosis).

The fast lane runs short scenarios whose fault is there from the start (60-80 s of plant time);
the long ones are marked slow.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
from pydantic import ValidationError

from twinwatch.config.loader import default_config, load_config
from twinwatch.config.schema import TwinwatchConfig
from twinwatch.daemon.runner import Daemon
from twinwatch.plant.dcmotor import SetpointSchedule
from twinwatch.twin.diagnosis import DiagnosisConfig, shipped_library
from twinwatch.twin.health import DiagnosisHealth, HealthMessage

ROOT = Path(__file__).resolve().parents[1]


# -- the library ------------------------------------------------------------------------------
@pytest.mark.parametrize("model", ["dc_motor", "dc_motor_pwm", "hydraulic_actuator"])
def test_a_library_is_shipped_per_model_with_actions_and_sources(model: str) -> None:
    lib = shipped_library(model)
    assert lib is not None and lib.model == model and len(lib.faults) >= 5
    for f in lib.faults:
        assert f.action and f.source and f.component


def _cfg(**diagnosis: Any) -> dict[str, Any]:
    raw = default_config().model_dump(mode="json", exclude_none=True)
    raw["diagnosis"] = diagnosis
    return raw


def test_a_bad_key_in_an_inline_fault_is_refused_naming_it() -> None:
    fault = {"id": "my_fault", "component": "gearbox", "action": "check the gearbox",
             "source": "vendor manual", "deviations": [{"parameter": "D", "direction": "up",
                                                        "min_pct": 3.0, "lnk": 0.9}]}
    with pytest.raises(ValidationError) as exc:
        TwinwatchConfig.model_validate(_cfg(faults=[fault]))
    assert "diagnosis.faults.0.deviations.0.lnk" in str(exc.value).replace("\n", "")


def test_a_fault_naming_a_parameter_the_model_lacks_is_refused() -> None:
    fault = {"id": "pump", "component": "pump", "action": "a", "source": "s",
             "deviations": [{"parameter": "q_pump", "direction": "down", "min_pct": 2.0}]}
    with pytest.raises(ValidationError, match="fault 'pump' names the parameter 'q_pump'"):
        TwinwatchConfig.model_validate(_cfg(faults=[fault]))


def test_a_library_file_extends_and_overrides_the_shipped_one(tmp_path: Path) -> None:
    path = tmp_path / "lib.toml"
    path.write_text('model = "dc_motor"\n[[faults]]\nid = "bearing_wear"\n'
                    'component = "bearings (our grease plan)"\naction = "grease"\n'
                    'source = "plant manual"\n'
                    'deviations = [{ parameter = "D", direction = "up", min_pct = 5.0 }]\n'
                    '[[faults]]\nid = "gearbox"\ncomponent = "gearbox"\naction = "oil"\n'
                    'source = "vendor"\nterms = [{ kinds = ["periodic"], attach = ["*"], '
                    'harmonic = 3.0 }]\n')
    d = DiagnosisConfig(library=str(path))
    lib = d.resolve("dc_motor")
    ids = [f.id for f in lib.faults]
    assert "gearbox" in ids and "winding_short" in ids
    assert next(f for f in lib.faults if f.id == "bearing_wear").action == "grease"
    with pytest.raises(ValidationError, match="cannot read the fault library"):
        DiagnosisConfig(library=str(tmp_path / "missing.toml"))


# -- through the real pipeline ----------------------------------------------------------------
def _run(cfg: TwinwatchConfig) -> list[HealthMessage]:
    with Daemon(cfg, publish=False, record=False) as daemon:
        daemon.run()
    assert daemon.numeric_failures == 0
    return list(daemon.health_history)


def _motor(config: str | None = None, **plant: Any) -> list[HealthMessage]:
    cfg = load_config(ROOT / "config" / config) if config else default_config()
    cfg.estimation.time_budget = 60.0  # no wall-clock cap: the same result under load
    pc = cfg.driver.plant  # type: ignore[union-attr]
    for key, value in plant.items():
        setattr(pc, key, value)
    return _run(cfg)


def _final(history: list[HealthMessage]) -> DiagnosisHealth:
    d = history[-1].diagnosis
    assert d is not None
    return d


def test_a_worn_armature_winding_ranks_first_with_the_numbers() -> None:
    """Ra 4.6 % below the nameplate (6.2 ohm against 6.5), 60 s: the winding, >= 0.8, and its
    sentences name the estimate and the deviation."""
    d = _final(_motor(scenario="resistance_degradation", Ra=6.2, fault_start=0.0,
                      duration=60.0))
    assert d.status == "fault" and d.top == "winding_short", d
    assert d.faults[0].probability >= 0.8
    text = " ".join(d.faults[0].evidence_for)
    # the plant: 6.2 ohm degrading to 6.191 ohm at 60 s (-4.75 %)
    assert re.search(r"Ra = 6\.19\d* ohm is -4\.[6-9]\d % from its nameplate 6\.5 ohm", text), text
    assert "beyond the 1 % down" in text
    # the opposite fault is argued against with the same numbers
    against = next(f for f in d.faults if f.id == "brushes_connections").evidence_against
    assert any("-4." in s and "within the 1 % up" in s for s in against), against


def test_a_rising_viscous_friction_is_the_bearings() -> None:
    d = _final(_motor(scenario="nominal", D=0.0016, duration=60.0))
    assert d.top == "bearing_wear" and d.faults[0].probability >= 0.8, d
    assert any("D = 0.0016" in s for s in d.faults[0].evidence_for)


def test_an_unbalance_at_the_shaft_speed_is_named_and_checked_against_it() -> None:
    """3 sin(7 t) rad/s^2 on a shaft held at 7 rad/s, 80 s: the periodic term is found and
    matched to 1 x the shaft speed (not 2 x: misalignment) once the shaft has run at a steady
    speed (it starts from rest and the PI takes about 50 s to get there: before, the harmonic
    is undecided, and no fault alarm is raised)."""
    d = _final(_motor("dc-motor-unbalanced-sim.toml", scenario="unbalanced_shaft",
                      unbalance_amplitude=3.0,
                      unbalance_frequency=7.0, duration=80.0,
                      setpoint=SetpointSchedule(steps=[(0.0, 7.0)])))
    assert d.top == "unbalance" and d.faults[0].probability >= 0.8, d
    text = " ".join(d.faults[0].evidence_for)
    m = re.search(r"sin\(7\.0\d\*t.*: ([\d.]+) rad/s against 1 x ([\d.]+) = ", text)
    assert m, text  # the term's frequency, against the (median) shaft speed it was seen at
    assert abs(float(m[1]) - 7.0) < 0.1 and 5.5 < float(m[2]) < 7.5, text
    mis = next(f for f in d.faults if f.id == "misalignment")
    assert mis.probability < 0.1
    assert d.alarms == ["unbalance"]


def test_an_unbalance_that_follows_the_shaft_is_checked_window_by_window() -> None:
    """The plant's unbalance as a real one (unbalance_follows_shaft: 3 sin(shaft angle), at
    1 x the shaft speed, the shaft held at 7 rad/s from rest, 80 s): the periodic term is
    re-found while the shaft speeds up, its frequency follows it, and once its ratio to the
    window's shaft speed has stayed 1 for 5 windows in a row the unbalance is named. Each
    window fits the term at one frequency while the shaft's speed, and the unbalance's, varies
    within it, so every output's model check keeps failing with the term in place: the
    unknown fault explains that too and keeps a share (issue 34: 0.78, not the 0.8 of an
    unbalance whose term fits)."""
    history = _motor("dc-motor-unbalanced-sim.toml", scenario="unbalanced_shaft",
                     unbalance_amplitude=3.0, unbalance_follows_shaft=True, duration=80.0,
                     setpoint=SetpointSchedule(steps=[(0.0, 7.0)]))
    d = _final(history)
    assert d.top == "unbalance" and d.faults[0].probability >= 0.7, d
    assert any("model check failed in" in e for e in d.faults[0].evidence_for), d
    text = " ".join(d.faults[0].evidence_for)
    m = re.search(r"([\d.]+) rad/s against 1 x ([\d.]+) = .*?; ([\d.]+)-([\d.]+) x the shaft "
                  r"speed over the last 5 windows", text)
    assert m, text
    assert abs(float(m[1]) / float(m[2]) - 1) < 0.02 and 6.5 < float(m[2]) < 7.2, text
    assert 0.97 < float(m[3]) <= float(m[4]) < 1.03, text
    assert next((f.probability for f in d.faults if f.id == "misalignment"), 0.0) < 0.1
    # while the shaft speeds up the term is found at lower frequencies, following it
    early = [t for h in history if h.t_end < 30 for t in h.terms]
    assert any(t.params["b"] < 6.0 for t in early), [t.equation for t in early]


def test_a_nominal_run_finds_no_fault() -> None:
    history = _motor(scenario="nominal", duration=60.0, noise={"ia": 1.0, "omega": 1.0})
    worst = max(f.probability for h in history for f in h.diagnosis.faults)  # type: ignore[union-attr]
    assert worst < 0.2
    assert _final(history).status == "no_fault"


def _hydraulic(scenario: str, **plant: Any) -> list[HealthMessage]:
    cfg = load_config(ROOT / "config" / "hydraulic-modbus-leak-sim.toml")
    # any free port on 127.0.0.1: each xdist worker builds the module's fixtures, and two
    # at once on the example's 5021 failed to listen (3 errors when this file and
    # test_diagnosis_faults.py ran on 2 workers)
    cfg.driver.port = 0  # type: ignore[attr-defined]
    pc = cfg.driver.plant  # type: ignore[union-attr]
    pc.scenario = scenario
    for key, value in plant.items():
        setattr(pc, key, value)
    return _run(cfg)


@pytest.fixture(scope="module")
def leak_history() -> list[HealthMessage]:
    """The leak from 20 s, 40 s: the term is kept from window 11 (24 s), the alarm raised at
    window 13 (28 s); the last 7 windows are the fault's steady state."""
    return _hydraulic("internal_leak", fault_start=20.0, duration=40.0)


def test_the_leak_example_names_the_seal_not_the_fluid(
        leak_history: list[HealthMessage]) -> None:
    """The leak example (config/hydraulic-modbus-leak-sim.toml) with the leak from 20 s: once
    discovery keeps the pressure term, the seal ranks first, the fluid far below."""
    history = leak_history
    d = _final(history)
    assert d.top == "internal_leak" and d.faults[0].probability >= 0.8, d
    fluid = next(f for f in d.faults if f.id == "fluid_degradation")
    assert fluid.probability < 0.1
    assert any("p *= 1 +" in s for s in d.faults[0].evidence_for)
    assert d.alarms == ["internal_leak"]  # [diagnosis] alarm 0.8 for 3 windows


def test_a_suspect_window_is_no_deviation_evidence(leak_history: list[HealthMessage]) -> None:
    """D +50 % in a window whose estimate is suspect (its model check failed) moves nothing:
    the last sound evidence stands; the same value estimated in two windows in a row makes
    the fluid the top fault (one window's jump is not yet the machine's)."""
    from twinwatch.twin.diagnosis import Diagnoser

    lib = shipped_library("hydraulic_actuator")
    assert lib is not None
    sound = leak_history[5]  # before the leak: no term
    assert not sound.terms

    def window(i: int, status: str) -> HealthMessage:
        h = sound.model_copy(deep=True, update={"window": i})
        h.parameters["D"].value = 150.0
        h.parameters["D"].status = status  # type: ignore[assignment]
        return h

    diag = Diagnoser(lib)
    before = diag.update(sound)
    suspect = diag.update(window(6, "suspect"))
    fluid = {d.faults[0].id: d.faults[0].probability for d in (before, suspect)}
    assert before.status == suspect.status == "no_fault" and "fluid_degradation" not in fluid
    text = " ".join(next(f for f in suspect.faults if f.id == "fluid_degradation")
                    .evidence_against)
    assert "last sound window 5" in text, text
    # one sound window's jump waits for the next to confirm it (inference._confirmed)
    once = diag.update(window(7, "estimated"))
    assert once.status == "no_fault", once
    estimated = diag.update(window(8, "estimated"))
    assert estimated.top == "fluid_degradation" and estimated.probability >= 0.8


def test_the_recordings_model_document_opens_with_the_diagnosis(
        leak_history: list[HealthMessage]) -> None:
    """The Rerun recording's active text panel (the model document) starts with the fault,
    its action and evidence: readable without touching the viewer."""
    from twinwatch.sinks.rerun_views import _model_document
    from twinwatch.twin.health import read_health

    text = _model_document("hydraulic-leak", 40.0, read_health(leak_history[-1]))
    head = text.split("**DT''", 1)[0]
    assert head.startswith("**Diagnosis: internal_leak** (piston seal (internal leakage)), "
                           "probability 0.") and "replace the piston seals" in head
    assert "+ term p *= 1 + (0.20)" in head and "next: fluid_degradation" not in head.split(
        "\n")[0]


def test_a_fault_alarm_has_hysteresis(leak_history: list[HealthMessage]) -> None:
    """Raised after 3 windows at >= 0.8, kept while above 0.5, cleared after 3 below 0.5."""
    from twinwatch.daemon.alarms import FaultAlarms

    alarms = FaultAlarms(0.8, 0.5, 3, 3, "m1")
    template = leak_history[-1]
    got = []
    for i, p in enumerate([0.9, 0.95, 0.9, 0.6, 0.55, 0.9, 0.4, 0.45, 0.6, 0.4, 0.3, 0.2]):
        h = template.model_copy(deep=True, update={"window": i})
        assert h.diagnosis is not None
        h.diagnosis.faults[0].probability = p
        diagnosis, events = alarms.update(h.diagnosis, h)
        for e in events:
            got.append((i, e["level"], e["fault"]))
            assert e["kind"] == "diagnosis" and "internal_leak (probability" in e["message"]
        assert diagnosis is not None and diagnosis is not h.diagnosis  # a new one
        assert diagnosis.alarms == (["internal_leak"] if 2 <= i < 11 else [])
    assert got == [(2, "alarm", "internal_leak"), (11, "normal", "internal_leak")]

    # a window the twin did not describe (not trusted) brings no evidence against the fault:
    # it neither clears the alarm nor resets the count (CANopen, Ra at -1 % with a few
    # failing windows, raised and cleared the winding 3 times in 40 s)
    alarms = FaultAlarms(0.8, 0.5, 3, 3, "m1")
    got = []
    for i, (p, sound) in enumerate([(0.9, True)] * 3 + [(0.1, False)] * 5 + [(0.9, True)]
                                   + [(0.3, True), (0.2, False), (0.3, True), (0.3, True)]):
        h = template.model_copy(deep=True, update={"window": i, "trusted": sound})
        assert h.diagnosis is not None
        h.diagnosis.faults[0].probability = p
        _, events = alarms.update(h.diagnosis, h)
        got += [(i, e["level"]) for e in events]
    assert got == [(2, "alarm"), (12, "normal")], got


def test_a_degrading_fluid_is_the_fluid_not_the_seal() -> None:
    """The hydraulic fluid degradation (D rises from 10 s): the fluid ranks first >= 0.8 and
    the seal, with no pressure term, far below."""
    d = _final(_hydraulic("fluid_degradation", fault_start=10.0, duration=70.0))
    assert d.top == "fluid_degradation" and d.faults[0].probability >= 0.8, d
    seal = next(f for f in d.faults if f.id == "internal_leak")
    assert seal.probability < 0.05
    assert any(s.startswith("D = ") and "beyond the 5 % up" in s
               for s in d.faults[0].evidence_for), d.faults[0].evidence_for


def test_explain_prints_the_chain_from_a_state_database(
        leak_history: list[HealthMessage], tmp_path: Path) -> None:
    """`twinwatch explain` on the leak example's state database: the fit, the parameters with
    their intervals, the term, the ranked faults with their evidence and the action."""
    from click.testing import CliRunner

    from twinwatch.cli import main
    from twinwatch.sinks.store import StateStore

    db = tmp_path / "state.sqlite"
    store = StateStore(db)
    try:
        for h in leak_history:
            assert store.save_window(h.as_dict(), None, doc=h.to_json())
    finally:
        store.close()
    result = CliRunner().invoke(main, ["explain", "hydraulic-leak", "--db", str(db),
                                       "--windows", "3"])
    assert result.exit_code == 0, result.output
    out = result.output
    last = leak_history[-1]
    assert f"window {last.window} [" in out and "RMSE x " in out
    assert re.search(r"D +100\.\d+ N/\(m/s\) \+/- [\d.e-]+ \(\+/- [\d.e-]+ %\)", out), out
    assert "p *= 1 + (0.20)" in out
    assert re.search(r"1\. internal_leak \(piston seal \(internal leakage\)\): 0\.[89]", out), out
    assert "action: run an internal-leakage (bypass) test" in out
    assert "2. fluid_degradation" in out
    missing = CliRunner().invoke(main, ["explain", "other", "--db", str(db)])
    assert missing.exit_code == 1 and "holds no window of the machine 'other'" in missing.output


def test_explain_reads_a_newer_daemons_message(leak_history: list[HealthMessage],
                                               tmp_path: Path) -> None:
    """A message with fields this version does not know (a newer daemon's) still gives the
    trend and the diagnosis sections (they were skipped: the strict model refused it)."""
    import json

    from click.testing import CliRunner

    from twinwatch.cli import main
    from twinwatch.sinks.store import StateStore

    db = tmp_path / "state.sqlite"
    store = StateStore(db)
    try:
        for h in leak_history[-3:]:
            d = h.as_dict()
            d["added_later"] = {"x": 1}
            d["parameters"]["D"]["added_later"] = 2.0
            assert store.save_window(d, None, doc=json.dumps(d))
    finally:
        store.close()
    out = CliRunner().invoke(main, ["explain", "hydraulic-leak", "--db", str(db)]).output
    assert "4. trend and remaining useful life" in out or "4. no trend" in out, out
    assert re.search(r"1\. internal_leak \(piston seal", out), out
    assert "no diagnosis in the stored messages" not in out


def test_two_faults_at_once_take_the_first_two_places() -> None:
    """Bearing wear (D +12 %) with an unbalance 3 sin(7 t) at 7 rad/s, 80 s: both ranked
    first and second (the term's offset takes part of the D rise: a constant torque at a
    constant speed is D's)."""
    d = _final(_motor("dc-motor-unbalanced-sim.toml", scenario="unbalanced_shaft", D=0.0016,
                      unbalance_amplitude=3.0, unbalance_frequency=7.0, duration=80.0,
                      setpoint=SetpointSchedule(steps=[(0.0, 7.0)])))
    assert {f.id for f in d.faults[:2]} == {"bearing_wear", "unbalance"}, d
    assert min(f.probability for f in d.faults[:2]) >= 0.5


def test_a_term_the_library_does_not_explain_is_an_unknown_fault_naming_it() -> None:
    """The same path with a configured library that knows no periodic fault (only the winding
    and the bearings, `replace = true`): the unbalance's term is reported as an unknown fault,
    named."""
    from twinwatch.twin.diagnosis import DiagnosisConfig, shipped_library

    cfg = load_config(ROOT / "config" / "dc-motor-unbalanced-sim.toml")
    cfg.estimation.time_budget = 60.0
    lib = shipped_library("dc_motor")
    assert lib is not None
    cfg.diagnosis = DiagnosisConfig(replace=True, faults=[
        f for f in lib.faults if f.id in ("winding_short", "bearing_wear")])
    pc = cfg.driver.plant  # type: ignore[union-attr]
    pc.unbalance_amplitude, pc.unbalance_frequency, pc.duration = 3.0, 7.0, 40.0
    pc.setpoint = SetpointSchedule(steps=[(0.0, 7.0)])
    d = _final(_run(cfg))
    assert d.status == "unknown" and d.unknown >= 0.8, d
    assert len(d.unknown_terms) == 1 and "sin(7.0" in d.unknown_terms[0]
    assert d.library == "dc_motor (configured)"


DEAD_ZONE = 2.0  # V, the plant's (config/dc-motor-deadzone-sim.toml)


def _clip_term(text: str) -> tuple[float, float]:
    """(a, b) of an ``a*clip(Va, b)`` term's equation."""
    m = re.search(r"d\(ia\)/dt \+= (-?[\d.]+)\*clip\(Va, ([\d.]+)\)", text)
    assert m, text
    return float(m[1]), float(m[2])


def test_the_plants_drive_dead_zone_takes_its_band_off_the_voltage() -> None:
    """From the onset the motor receives dz(Va) = Va - 2 V (Va > 2 V): at a steady speed the
    PI's integrator makes up the band, so the drive reports 2 V more than a sound one."""
    from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig

    def va_at(scenario: str, t_end: float) -> float:
        plant = DCMotorPlant(DCMotorPlantConfig(
            scenario=scenario, fault_start=5.0, duration=t_end,  # type: ignore[arg-type]
            setpoint=SetpointSchedule(steps=[(0.0, 10.0)])))
        va = 0.0
        while plant.t <= t_end - 1e-9:
            va = plant.next_sample().values["Va"]
        return va

    # the PI (ki 0.1) settles in tens of seconds: the band made up to 1 % by 200 s
    assert va_at("dead_zone", 200.0) - va_at("nominal", 200.0) == pytest.approx(DEAD_ZONE,
                                                                                rel=0.01)
    assert va_at("dead_zone", 4.0) == va_at("nominal", 4.0)  # nothing before the onset


def test_a_drive_dead_zone_is_an_unknown_fault_naming_the_discovered_term() -> None:
    """Issue 25: a change the library does not know. The reversing drive of
    config/dc-motor-deadzone-sim.toml with its 2 V dead zone from 10 s: discovery keeps
    ``d(ia)/dt += a*clip(Va, b)`` (a = -1/La, b the band) and, the dc_motor library having no
    fault mode with a term on d(ia)/dt, the diagnosis says unknown >= 0.8 and names the term;
    no fault mode of the library rises above 0.2."""
    lib = shipped_library("dc_motor")
    assert lib is not None
    assert not any(t.attach != ["d(omega)/dt"] or "input_dead_zone" in t.kinds
                   for f in lib.faults for t in f.terms)  # the library has no dead zone
    history = _motor("dc-motor-deadzone-sim.toml", fault_start=10.0, duration=30.0)
    before = [h.diagnosis for h in history if h.t_end <= 10.0]
    assert before and all(d is not None and d.status == "no_fault" for d in before)
    d = _final(history)
    assert d.status == "unknown" and d.unknown >= 0.8, d
    assert len(d.unknown_terms) == 1, d.unknown_terms
    a, b = _clip_term(d.unknown_terms[0])
    assert a == pytest.approx(-1 / 0.673, rel=0.05) and b == pytest.approx(DEAD_ZONE, rel=0.05)
    assert max(f.probability for h in history for f in h.diagnosis.faults) < 0.2  # type: ignore[union-attr]

    # Explaining away: at 1 % noise the estimates absorbed part of the dead zone (Ra published
    # +1.1 to +2.8 % in sound windows, before the gate took the term's scale as a nuisance:
    # Ra is held beside the term now). Ra +2 % with the unexplained term on d(ia)/dt (Ra's
    # equation) is model error, not worn brushes; the same Ra in windows where the twin fits
    # without a term (before the dead zone) is the brushes.
    from twinwatch.twin.diagnosis import Diagnoser

    def with_ra(h: HealthMessage, terms: bool) -> HealthMessage:
        h = h.model_copy(deep=True, update={} if terms else {"terms": []})
        ra = h.parameters["Ra"]
        ra.value, ra.status, ra.rel_std_pct = 6.5 * 1.02, "estimated", 0.05  # type: ignore[assignment]
        return h

    fitting = [h for h in history if h.t_end <= 10.0][-3:]
    for terms in (True, False):
        diag = Diagnoser(lib)
        got = [diag.update(with_ra(h, terms)) for h in (history[-3:] if terms else fitting)][-1]
        brushes = next(f for f in got.faults if f.id == "brushes_connections")
        if terms:
            assert got.status == "unknown" and brushes.probability < 0.2, got
            assert any("acts in the same equation, d(ia)/dt" in t
                       for t in brushes.evidence_for), brushes.evidence_for
        else:
            assert got.top == "brushes_connections" and brushes.probability >= 0.8, got


def test_explain_live_over_zenoh_from_a_running_daemon(tmp_path: Path) -> None:
    """No database: `twinwatch explain MACHINE --connect` asks the daemon for its latest
    health and its history (a daemon in process, its own listening endpoint)."""
    from click.testing import CliRunner

    from twinwatch.cli import main

    from .helpers.net import endpoint, free_port

    port = free_port()
    cfg = default_config()
    cfg.driver.plant.duration = 10.0  # type: ignore[union-attr]
    cfg.recording.enabled = False
    cfg.state.path = str(tmp_path / "state.sqlite")
    cfg.zenoh.listen = [endpoint(port)]
    with Daemon(cfg, record=False, persist=True) as daemon:  # the history needs the store
        daemon.run()
        result = CliRunner().invoke(main, ["explain", "dc-motor-sim", "--connect",
                                           endpoint(port), "--windows", "3"])
    assert result.exit_code == 0, result.output
    out = result.output
    assert "the last 3 windows" in out
    assert all(f"window {i} [" in out for i in (2, 3, 4)), out
    assert "5. the diagnosis (dc_motor (shipped)" in out and "diagnosis: no fault" in out
    down = CliRunner().invoke(main, ["explain", "dc-motor-sim", "--connect",
                                     endpoint(free_port())])
    assert down.exit_code == 1 and "nothing answers there" in down.output


# -- the paper's runs (slow lane) -------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("noise", [0.0, 1.0, 2.0])
def test_nominal_runs_of_1200_s_give_no_fault_above_0_2(noise: float) -> None:
    history = _motor(scenario="nominal", duration=1200.0,
                     noise={"ia": noise, "omega": noise} if noise else {})
    worst = max(f.probability for h in history for f in h.diagnosis.faults)  # type: ignore[union-attr]
    assert worst < 0.2
    assert max(h.diagnosis.unknown for h in history) < 0.2  # type: ignore[union-attr]


@pytest.mark.slow
@pytest.mark.parametrize(("scenario", "fault", "size_pct"), [
    ("resistance_degradation", "winding_short", 1.0), ("bearing_wear", "bearing_wear", 3.0)])
def test_the_papers_degradations_are_named_within_60_s_of_being_detectable(
        scenario: str, fault: str, size_pct: float) -> None:
    """The paper's laws from 160 s (Ra falls, D rises): the fault is first with probability
    >= 0.8 (the winding) or >= 0.5 (the bearings) within 60 s of plant time after the plant's
    parameter crosses the library's size (1 % for Ra, 3 % for D: where the evidence becomes
    detectable) and stays first. D rising while Ke is held (never estimated at the default
    set-points) is also what a weaker magnet publishes (Kt tied to the held Ke: issue 34's
    second round dropped the stale "Ke at nameplate" that had ruled the magnet out): the two
    split by their priors, the bearings first; a back-EMF measurement tells them apart (the
    magnet's action says so)."""
    from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig

    history = _motor(scenario=scenario, duration=1200.0)
    plant = DCMotorPlant(DCMotorPlantConfig(scenario=scenario, duration=1200.0))  # type: ignore[arg-type]
    name = "Ra" if fault == "winding_short" else "D"
    nominal = getattr(plant.truth(0.0), name)
    t_detectable = next(h.t_end for h in history if abs(getattr(plant.truth(h.t_end), name)
                                                        / nominal - 1) * 100 >= size_pct)
    named = None
    least = 0.8 if fault == "winding_short" else 0.5
    for h in reversed(history):
        d = h.diagnosis
        if d is None or d.top != fault or d.faults[0].probability < least:
            break
        named = h.t_end
    assert named is not None and named - t_detectable <= 60.0, (named, t_detectable)


@pytest.mark.slow
@pytest.mark.parametrize("noise", [0.0, 1.0])
def test_the_dead_zone_example_is_unknown_within_20_s_and_stays_so(noise: float) -> None:
    """config/dc-motor-deadzone-sim.toml as shipped (120 s, the 2 V dead zone from 30 s), noise
    free and at 1 % noise: the diagnosis says unknown >= 0.8 naming the clip term within 20 s
    of the onset, in at least 90 % of the windows after, and nothing above 0.2 before it."""
    history = _motor("dc-motor-deadzone-sim.toml",
                     noise={"ia": noise, "omega": noise} if noise else {})
    onset = 30.0
    for h in history:
        d = h.diagnosis
        assert d is not None
        if h.t_end <= onset:
            assert d.status == "no_fault" and d.unknown < 0.2, (h.window, d)
    named = [h for h in history if h.diagnosis.status == "unknown"  # type: ignore[union-attr]
             and h.diagnosis.unknown >= 0.8]  # type: ignore[union-attr]
    assert named and named[0].t_end - onset <= 20.0, [h.t_end for h in named[:3]]
    after = [h for h in history if h.t_end >= named[0].t_end]
    assert len(named) >= 0.9 * len(after), (len(named), len(after))
    d = _final(history)
    a, b = _clip_term(d.unknown_terms[0])
    # the term acts in the twin's d(ia)/dt, whose La is estimated: its slope is -1/La of that
    # twin (measured: a = -1.4396, the twin's La 0.6884 H, +2.3 %: 0.9 % off), and within 5 %
    # of the plant's -1/0.673 (3.1 % off: the slope trades with the twin's La, see
    # docs/diagnosis.md's Limits; the equation's 3 digits read -1.44 or -1.45 across numpy
    # builds, a 3 % bound on the plant's La flipped with them)
    la = history[-1].parameters["La"].value
    assert la is not None
    term = next(t for t in history[-1].terms if t.kind == "input_dead_zone")
    assert term.params["a"] == pytest.approx(-1 / la, rel=0.03), (term.params, la)
    assert a == pytest.approx(-1 / 0.673, rel=0.05) and b == pytest.approx(DEAD_ZONE, rel=0.02)


@pytest.mark.slow
def test_an_unbalance_that_follows_the_shaft_is_named_again_after_a_speed_change() -> None:
    """The unbalance following the shaft (3 sin(shaft angle)) with the set-point moved from
    10 to 15 rad/s at 60 s (120 s): before and after the change the unbalance is first at
    >= 0.7 (not 0.8: the outputs' checks keep failing with the term in place, which the
    unknown fault explains too; see the test above) with the term at the shaft's speed of the
    time (not 2 x: misalignment below 0.3); the paper's fixed-frequency Eq. 13 stays the
    plant's default."""
    from twinwatch.plant.dcmotor import DCMotorPlantConfig

    assert DCMotorPlantConfig().unbalance_follows_shaft is False
    history = _motor("dc-motor-unbalanced-sim.toml", scenario="unbalanced_shaft",
                     unbalance_amplitude=3.0, unbalance_follows_shaft=True, duration=120.0,
                     setpoint=SetpointSchedule(steps=[(0.0, 10.0), (60.0, 15.0)]))
    for lo, hi, speed in ((40.0, 60.0, 10.0), (100.0, 120.0, 15.0)):
        named = [h for h in history if lo < h.t_end <= hi and h.diagnosis.top == "unbalance"  # type: ignore[union-attr]
                 and h.diagnosis.faults[0].probability >= 0.7]  # type: ignore[union-attr]
        assert named, [(h.t_end, h.diagnosis.status, h.diagnosis.probability)  # type: ignore[union-attr]
                       for h in history if lo < h.t_end <= hi]
        b = [t.params["b"] for t in named[-1].terms if t.kind == "periodic"]
        assert b and abs(abs(b[0]) / speed - 1) < 0.1, (b, speed)
    # while the shaft changes speed the harmonic is undecided and the failing checks speak
    # for either periodic fault: the misalignment rises to 0.24 there, never near a name
    assert max(f.probability for h in history for f in h.diagnosis.faults  # type: ignore[union-attr]
               if f.id == "misalignment") < 0.3


@pytest.mark.slow  # 400 s of the default plant: about 15 s
def test_a_degradation_inside_the_faults_size_is_named_developing_with_its_rul() -> None:
    """The default run at 400 s: Ra -0.7 % (inside the winding fault's 1 % size, so the
    diagnosis is still "no fault") while its trend reaches the warning in minutes. The summary
    and ``explain`` say both: the parameter, its warning time and the fault its trend is
    evidence for; and the plant's own crossing of the warning falls in the stated interval."""
    from twinwatch.plant.dcmotor import DCMotorPlant
    from twinwatch.twin.health import developing_line

    cfg = default_config()
    cfg.estimation.time_budget = 60.0
    pc = cfg.driver.plant  # type: ignore[union-attr]
    pc.duration = 400.0
    last = _run(cfg)[-1]
    d = _final([last])
    assert d.status == "no_fault", d
    line = developing_line(d, last.parameters)
    assert line is not None and line.startswith("developing: Ra -0."), line
    assert "if it goes on: winding_short" in line, line
    w = last.parameters["Ra"].rul.warning  # type: ignore[union-attr]
    assert w is not None and w.t_low is not None and w.t_high is not None
    plant = DCMotorPlant(pc)
    t = 400.0
    while plant.truth(t).Ra > w.threshold and t < 5000.0:
        t += 1.0
    assert w.t_low - 2.0 <= t <= w.t_high + 2.0, (t, w)
