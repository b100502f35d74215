"""The diagnosis outside its library (issue 34): graded deviation evidence, sensor and supply
faults read as one fault, the check function when the twin no longer fits, and why a plausible
fault was ruled out.

The end-to-end cases run the simulated DC motor with a fault injected into what it reports
(``[[driver.plant.sensor_faults]]``) or into the plant (``parameter_faults``); the unit cases
feed the :class:`~twinwatch.twin.diagnosis.Diagnoser` messages of a short nominal run with one
field changed.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from twinwatch.config.loader import default_config
from twinwatch.daemon.alarms import CHECK_FUNCTION, FaultAlarms
from twinwatch.daemon.runner import Daemon
from twinwatch.daemon.summary import window_lines
from twinwatch.twin.diagnosis import Diagnoser, shipped_library
from twinwatch.twin.diagnosis.deviation import likelihood, moved_density
from twinwatch.twin.health import HealthMessage, ModelCheckHealth, diagnosis_line


def _run(duration: float, **plant: Any) -> tuple[list[HealthMessage], list[list[str]]]:
    """The default motor, healthy but for ``plant``'s faults: every window's message and what
    STATUS said of the machine after it (:meth:`Daemon.problems`)."""
    cfg = default_config()
    cfg.estimation.time_budget = 60.0  # no wall-clock cap: the same result under load
    pc = cfg.driver.plant
    cfg.driver.plant = type(pc).model_validate({**pc.model_dump(), "scenario": "nominal",
                                                "duration": duration, **plant})
    problems: list[list[str]] = []
    with Daemon(cfg, publish=False, record=False) as daemon:
        daemon.add_callback(lambda h: problems.append(daemon.problems()))
        daemon.run()
    assert daemon.numeric_failures == 0
    return list(daemon.health_history), problems


# -- the graded deviation evidence (twinwatch/twin/diagnosis/deviation.py) --------------------

def test_a_fault_s_deviation_density_is_a_density() -> None:
    """The log-uniform magnitude observed through N(m, sd^2) integrates to 1 over the
    deviation: within 2 % for a standard error small against the size, within 10 % for one
    twice it (the closed form takes 1/m at max(|x|, size): measured 1.065)."""
    x = np.linspace(-400.0, 400.0, 400001)
    for sd in (0.05, 2.0):
        for up in (True, False):
            p = np.array([float(moved_density(float(v), sd, 1.0, up)) for v in x[::50]])
            mass = float(np.trapezoid(p, x[::50]))
            assert mass == pytest.approx(1.0, abs=0.02 if sd < 1.0 else 0.1), (sd, up, mass)


def test_a_tight_small_move_is_evidence_against_a_fault_that_leaves_the_parameter() -> None:
    """Ra -0.8 % +- 0.03 %: a fault moving Ra down by at least 0.3 % explains it far better
    than one that does not move Ra (a bearing) or one whose size is 1 % (a winding)."""
    one = np.ones(1)
    zero = np.zeros(1)

    def lik(p_down: float, size: float) -> float:
        return float(likelihood(-0.8, 0.03, zero, one * 150, one * p_down, one * size,
                                0.002)[0])

    sensor, winding, untouched = lik(0.9, 0.3), lik(0.95, 1.0), lik(0.0, 150.0)
    assert sensor > 10 * untouched
    assert sensor > 20 * winding
    # and Ra -14 % is the winding's as much as the sensor's, nothing like no fault's
    big = [float(likelihood(-14.0, 0.05, zero, one * 150, one * p, one * a, 0.002)[0])
           for p, a in ((0.9, 0.3), (0.95, 1.0), (0.0, 150.0))]
    assert big[0] == pytest.approx(big[1], rel=0.3) and big[1] > 500 * big[2]


# -- the check function ----------------------------------------------------------------------

@pytest.fixture(scope="module")
def nominal_messages() -> list[HealthMessage]:
    history, _ = _run(20.0)
    return history


def _failing(h: HealthMessage, window: int, passed: bool) -> HealthMessage:
    """``h`` as window ``window`` (2 s each) with its model check ``passed`` or failed."""
    assert h.model_check is not None
    check = ModelCheckHealth.model_validate({**h.model_check.model_dump(), "passed": passed,
                                            "reasons": [] if passed else ["ia not white"]})
    return h.model_copy(update={"window": window, "t_start": 2.0 * window,
                                "t_end": 2.0 * window + 1.99, "model_check": check})


def test_failed_checks_accumulate_into_check_function_and_it_ends(
        nominal_messages: list[HealthMessage]) -> None:
    """80 % of the last 60 s failing: check_function from the first failed window, with the
    record; never "no fault" meanwhile; 3 passing windows end it; raised and cleared as the
    diagnosis alarm check_function."""
    base = nominal_messages[-1]
    d = Diagnoser(shipped_library("dc_motor"))  # type: ignore[arg-type]
    alarms = FaultAlarms(0.8, 0.5, 3, 3, machine="m1")
    statuses, events = [], []
    for w in range(70):
        passed = w < 10 or w >= 50
        msg = _failing(base, w, passed)
        diag = d.update(msg, None)
        statuses.append(diag.status)
        _, raised = alarms.update(diag, msg)
        events += raised
        if w == 45:
            assert diag.status == "check_function" and diag.top is None
            assert diag.check_function_since == pytest.approx(20.0)
            assert diag.check_failed == "the model check failed in 30 of the last 30 windows " \
                                        "(60 s)"
            assert "check function: the twin does not describe this machine since plant " \
                   "time 20 s" in (diagnosis_line(diag) or "")
    # entered once 80 % of the last 60 s failed (window 33: windows 10-33 of 4-33), left
    # after 3 passing windows (50-52)
    assert statuses[:33] == ["no_fault"] * 33
    assert set(statuses[33:52]) == {"check_function"}
    assert statuses[52:] == ["no_fault"] * 18
    assert [(e["fault"], e["level"]) for e in events] == [(CHECK_FUNCTION, "alarm"),
                                                          (CHECK_FUNCTION, "normal")]
    assert "CHECK FUNCTION: the twin does not describe this machine" in events[0]["message"]


def test_a_few_failed_checks_are_not_check_function(
        nominal_messages: list[HealthMessage]) -> None:
    """One window in three failing (below the 80 % share) never makes it."""
    base = nominal_messages[-1]
    d = Diagnoser(shipped_library("dc_motor"))  # type: ignore[arg-type]
    out = [d.update(_failing(base, w, w % 3 != 0), None) for w in range(60)]
    assert all(x.status != "check_function" for x in out)
    assert out[-1].check_failed == "the model check failed in 10 of the last 30 windows (60 s)"


def test_a_sensor_that_clips_now_and_then_explains_the_term_fitted_to_it(
        nominal_messages: list[HealthMessage]) -> None:
    """Issue 34: a reading that clips only while it crosses its range (the hydraulic p at
    50 400 Pa: 8 of 70 windows) stays the sensor's evidence for 300 windows (10 min; it ended
    on "no fault" with 60: the matrix's clipped pressure readings were last flagged 62 and 64
    windows before their end), and a term the
    twin fits on that channel meanwhile is the sensor's, not a fault of the process: before,
    the windows between read the term as the leak (0.86) and the sensor fell to 0.13. A
    frozen reading is evidence for the sensor although it is not also saturated (the two
    kinds counted as two variables held the frozen position reading at 0.54)."""
    from twinwatch.twin.health import SensorHealth, TermHealth

    base = nominal_messages[-1]
    stuck = SensorHealth(channel="ia", kind="saturated", value=1.5, t_start=0.0,
                         duration_s=1.0, samples=100)
    term = TermHealth(kind="linear", attach="d(ia)/dt", mode="additive", input="ia",
                      t_ref=0.0, params={"a": -0.02}, params_std={"a": 0.001}, weight=-0.02,
                      significance=20.0, evidence_windows=5.0,
                      equation="d(ia)/dt += -0.02*ia", meaning="", since_window=3)
    d = Diagnoser(shipped_library("dc_motor"))  # type: ignore[arg-type]
    out = []
    for w in range(320):
        msg = base.model_copy(update={"window": w, "t_start": 2.0 * w, "t_end": 2.0 * w + 1.99,
                                      "sensors": [stuck] if w in (2, 9) else [],
                                      "terms": [term] if w >= 3 else []})
        out.append(d.update(msg, None))
    for w in (2, 5, 40, 69, 200, 309):   # flagged at 2 and 9: the evidence lasts to 309
        assert out[w].top == "sensor_fault" and out[w].probability >= 0.8, (w, out[w])
        assert out[w].unknown < 0.2, (w, out[w])
    assert "ia saturated at 1.5 for 1.0 s (window 9)" in " ".join(out[40].faults[0].evidence_for)
    # 300 windows after the last flag the term is no longer the sensor's: a fault the
    # library does not know
    assert out[319].top != "sensor_fault" and out[319].unknown >= 0.5, out[319]


def test_a_fault_no_window_can_see_is_said_unobserved_not_ruled_out(
        nominal_messages: list[HealthMessage]) -> None:
    """Issue 34 (say what is not identifiable): on the default motor J is held in every
    window, so a load inertia change cannot be seen: "no fault" is its prior, not a finding,
    and the diagnosis says so naming J; once a window determines J it is seen again (a
    load inertia step of 50 % read "no fault 0.98" and nothing said why)."""
    from twinwatch.twin.diagnosis.explain import explain_lines

    assert all(h.parameters["J"].status == "held" for h in nominal_messages)
    d = Diagnoser(shipped_library("dc_motor"))  # type: ignore[arg-type]
    # without J's alias in the messages (no set-point step: the inertia's torque never shows
    # in D), J is not read across windows either
    nominal_messages = [h.model_copy(update={"aliases": {}}) for h in nominal_messages]
    for h in nominal_messages:
        out = d.update(h, None)
    assert out.status == "no_fault"
    assert out.unobserved == ["load_inertia_change (coupled load) cannot be seen now: J held, "
                              "never determined by a window"], out.unobserved
    last = nominal_messages[-1].model_copy(update={"diagnosis": out})
    assert out.unobserved[0] in "\n".join(explain_lines([last]))  # type: ignore[list-item]
    j = last.parameters["J"].model_copy(update={"status": "estimated", "rel_std_pct": 0.5})
    seen = last.model_copy(update={"window": last.window + 1,
                                   "parameters": {**last.parameters, "J": j}})
    assert d.update(seen, None).unobserved == []


def test_a_decided_harmonic_is_kept_across_a_speed_change(
        nominal_messages: list[HealthMessage]) -> None:
    """Issue 34: a periodic term on d(omega)/dt at 2x the shaft speed for 8 windows decides
    the misalignment; after a set-point change the term is re-found at the new speed and its
    new track is undecided for 5 windows: the decided harmonic is recalled (0.8 against 0.2),
    so the misalignment stays first, where the priors put the unbalance first (0.45 against
    0.22 in the fault matrix after each set-point change)."""
    from twinwatch.twin.health import TermHealth

    def periodic(b: float, since: int) -> TermHealth:
        return TermHealth(kind="periodic", attach="d(omega)/dt", mode="additive", input="t",
                          t_ref=0.0, params={"a": 5.0, "b": b, "c": 0.0},
                          params_std={"a": 0.05, "b": 0.01, "c": 0.01}, weight=5.0,
                          significance=100.0, evidence_windows=5.0,
                          equation=f"d(omega)/dt += 5*sin({b:g}*t)", meaning="", since_window=since)

    base = nominal_messages[-1]
    d = Diagnoser(shipped_library("dc_motor"))  # type: ignore[arg-type]
    tops = []
    for w in range(15):
        # the shaft at 10 rad/s, then at 15 from window 8: the term of time is still at 20
        # rad/s there (1.33 x the new speed: its track ends), re-found at 30 from window 9
        speed = 10.0 if w < 8 else 15.0
        b, since = (20.0, 0) if w < 9 else (30.0, 9)
        msg = base.model_copy(update={"window": w, "t_start": 2.0 * w, "t_end": 2.0 * w + 1.99,
                                      "terms": [periodic(b, since)]})
        out = d.update(msg, (speed, 0.05))
        tops.append((w, out.top, round(out.faults[0].probability, 2)))
        if w >= 5:   # decided at 2x from the fifth window on, and kept after the change
            assert out.top == "misalignment", tops
        if w == 10:
            assert any("its track was 2 x the shaft speed in window 7" in e
                       for e in out.faults[0].evidence_for), out.faults[0].evidence_for
    mis = next(f for f in out.faults if f.id == "misalignment")
    assert not any("undecided since the shaft's speed changed" in e for e in mis.evidence_for)
    d2 = Diagnoser(shipped_library("dc_motor"))  # type: ignore[arg-type]
    for w in range(9, 11):   # the same undecided windows without the decided track before
        msg = base.model_copy(update={"window": w, "terms": [periodic(30.0, 9)]})
        fresh = d2.update(msg, (15.0, 0.05))
    assert fresh.top != "misalignment" or fresh.faults[0].probability < 0.5, fresh


def test_a_deviation_beyond_every_fault_s_largest_size_is_unknown(
        nominal_messages: list[HealthMessage]) -> None:
    """Issue 34: a fault's ``max_pct`` bounds what it can make. The hydraulic fluid's
    degradation moves D by at most +100 % (an oil is condemned at about 10 % of viscosity
    change): D four times its nameplate in every window (a position reading offset by 2 cm,
    fitted at nRMSE 2e-6) read ``fluid_degradation`` 0.99. Here on the DC motor's library
    with every fault that moves D up bounded alike: D +283 % is not the bearings but a fault
    the library does not know, naming the bound; D +25 % is still the bearings."""
    import pydantic

    from twinwatch.twin.diagnosis.library import DeviationSign, FaultLibrary

    lib = shipped_library("dc_motor")
    assert lib is not None
    data = lib.model_dump()
    for f in data["faults"]:   # every fault that moves D up: at most +100 %
        for dev in f["deviations"]:
            if dev["parameter"] == "D" and dev["direction"] == "up":
                dev["max_pct"] = 100.0
    bounded = FaultLibrary.model_validate(data)
    with pytest.raises(pydantic.ValidationError, match="max_pct 3 must exceed min_pct 5"):
        DeviationSign(parameter="D", direction="up", min_pct=5.0, max_pct=3.0)

    def run(change_pct: float) -> Any:
        d = Diagnoser(bounded)
        for h in nominal_messages[-10:]:
            p = h.parameters["D"]
            moved = p.model_copy(update={"value": p.nominal * (1 + change_pct / 100),
                                         "status": "estimated", "rel_std_pct": 0.5})
            out = d.update(h.model_copy(update={"parameters": {**h.parameters, "D": moved}}),
                           None)
        return out

    far = run(283.0)
    bearings = next((f.probability for f in far.faults if f.id == "bearing_wear"), 0.0)
    # the unknown fault's link to a deviation no fault explains is 0.2 (UNKNOWN_DEV_LINK): it
    # rises from 0.01 to about 0.4, no part is named
    assert far.top is None and bearings < 0.2 and far.unknown >= 0.3, far
    assert any("beyond the 100 % any fault of the library moves D up" in u
               for u in far.unexplained), far.unexplained
    near = run(25.0)
    assert near.top == "bearing_wear" and near.probability >= 0.8, near


def _with_d(h: HealthMessage, window: int, change_pct: float,
            rel_std_pct: float = 2.0) -> HealthMessage:
    """``h`` as window ``window`` (2 s each) with D estimated ``change_pct`` % from its
    nameplate (its relative standard error ``rel_std_pct`` %)."""
    p = h.parameters["D"]
    moved = p.model_copy(update={"value": p.nominal * (1 + change_pct / 100),
                                 "status": "estimated", "rel_std_pct": rel_std_pct})
    return h.model_copy(update={"window": window, "t_start": 2.0 * window,
                                "t_end": 2.0 * window + 1.99,
                                "parameters": {**h.parameters, "D": moved}})


def test_a_change_that_comes_and_goes_is_a_fault_the_library_does_not_know(
        nominal_messages: list[HealthMessage]) -> None:
    """Issue 34 (off-library): an intermittent load (+40 % on 10 s of every 20 s in the fault
    matrix) publishes D +168 % and its nameplate by turns with every check passing; no wear
    fault of the library comes back by itself, so once D has come back twice it is the
    unknown fault's evidence, named in ``unexplained``, in the windows at the nameplate
    too (before: "no fault" 0.98 at the end). A repaired step comes back once: no fault."""
    base = nominal_messages[-1]

    def run(profile: list[float], rel_std_pct: float = 2.0) -> list[Any]:
        d = Diagnoser(shipped_library("dc_motor"))  # type: ignore[arg-type]
        return [d.update(_with_d(base, w, c, rel_std_pct), None)
                for w, c in enumerate(profile)]

    swings = [0.0] * 10 + ([150.0] * 5 + [0.0] * 5) * 3 + [0.0] * 4
    out = run(swings)
    last = out[-1]   # D at its nameplate for 9 windows
    assert last.status == "unknown" and last.unknown >= 0.8, last
    assert any("D went +150 % from its nameplate and came back to it 3 times in the last "
               "44 windows (since window 10): a change that comes and goes" in u
               for u in last.unexplained), last.unexplained
    assert all(f.probability < 0.8 for f in last.faults), last.faults
    # before the second return it is a deviation: the bearings' (D +150 %)
    assert out[22].unknown < 0.2 and not any("came back" in u for u in out[22].unexplained)
    repaired = run([0.0] * 10 + [150.0] * 10 + [0.0] * 20)[-1]
    assert repaired.status == "no_fault" and repaired.unknown < 0.2, repaired
    assert not any("came back" in u for u in repaired.unexplained)
    # the PWM drive's scatter (standard errors of 9 %) about a D +25 % step is not a change
    # that comes and goes: it does not come back to a quarter of the step
    noisy = run([0.0] * 10 + [25.0, 16.0, 34.0, 21.0, 30.0, 13.0, 27.0, 19.0, 31.0, 24.0] * 4,
                rel_std_pct=9.0)[-1]
    assert not any("came back" in u for u in noisy.unexplained), noisy.unexplained


def test_a_twin_failing_in_bursts_is_a_fault_the_library_does_not_know(
        nominal_messages: list[HealthMessage]) -> None:
    """Issue 34 (off-library): an unmeasured force on the hydraulic rod on 10 s of every 20 s
    made the check fail in 39 of the last 60 windows, in 7 runs, and ended on "no fault" 0.82
    (below the check function's 80 %). Bursts of failures (30 % of the last 60 windows or more, in 3
    runs or more, 30 % passing) are the unknown fault's evidence; the faults that may leave
    a check failing or passing (the unbalance's ``may_pass``) explain it as well, a fault
    whose check fails throughout (a speed reading's gain) does not. Failing throughout is
    check function, not this."""
    base = nominal_messages[-1]

    def run(passed: list[bool]) -> Any:
        d = Diagnoser(shipped_library("dc_motor"))  # type: ignore[arg-type]
        for w, ok in enumerate(passed):
            out = d.update(_failing(base, w, ok), None)
        return out

    bursts = run([True] * 10 + ([False] * 5 + [True] * 5) * 6)
    # 0.806 before the DC motor's dry friction, which leaves the ia and omega checks failing
    # in part of the windows before its term is found (may_pass), explained the bursts too:
    # with D at its nameplate it takes 0.009 of them, the unknown fault 0.799
    assert bursts.status == "unknown" and bursts.unknown >= 0.75, bursts
    assert all(f.probability < 0.06 for f in bursts.faults), bursts.faults
    assert ("the model check failed in 30 of the last 60 windows, in 6 separate runs: "
            "something that comes and goes") in bursts.unexplained, bursts.unexplained
    assert all(f.id not in ("speed_sensor_high", "speed_sensor_low") or f.probability < 0.2
               for f in bursts.faults), bursts.faults
    throughout = run([True] * 10 + [False] * 60)
    assert throughout.status == "check_function", throughout
    assert not any("separate runs" in u for u in throughout.unexplained)
    scattered = run([True] * 10 + ([False] + [True] * 9) * 6)   # 10 %: a noisy healthy twin
    assert scattered.status == "no_fault", scattered


# -- end to end ------------------------------------------------------------------------------

def test_a_current_sensor_reading_high_is_the_sensor_not_the_winding_and_the_bearings() -> None:
    """The default motor, healthy, its current reading drifting to 1.1x over 20 s from 20 s
    (issue 34: it read as winding_short 0.96 and bearing_wear 0.96, both alarms raised): the
    winding and the bearings never reach 0.8; the current sensor (reads high) is named first
    by 60 s after the drift ends (measured: 44 s, the first window the estimates move), and
    the winding is ruled out with the reason, to the end of a 100 s run (the reading check's
    linear step left nRMSE 7e-4 on this noise-free motor, its correction not simulated
    exactly: from 90 s it read winding_short 0.87, its alarm raised)."""
    history, _ = _run(100.0, sensor_faults=[{"channel": "ia", "kind": "gain", "gain": 1.1,
                                             "start": 20.0, "ramp": 20.0}])
    worst = max((f.probability, f.id, h.window) for h in history
                for f in h.diagnosis.faults  # type: ignore[union-attr]
                if f.id in ("winding_short", "bearing_wear"))
    assert worst[0] < 0.8, worst
    named = [h.t_end for h in history if h.diagnosis is not None
             and h.diagnosis.top == "current_sensor_high"
             and h.diagnosis.probability >= 0.8]
    assert named and named[0] <= 100.0, named[:3]
    last = history[-1].diagnosis
    assert last is not None and last.top == "current_sensor_high", last
    assert any(r.startswith("winding_short") and "current_sensor_high" in r
               for r in last.ruled_out), last.ruled_out


def test_a_shorted_winding_with_worn_bearings_is_not_a_current_reading() -> None:
    """Ra -12 % and D +25 % from 20 s over 20 s (issue 34's fault matrix: it read as
    current_sensor_high 0.95, the two faults' directions being the reading's): the reading
    check finds that the healthy motor with its current reading corrected leaves several
    times the fit's nRMSE, so the current sensor never reaches 0.5 and a part is named."""
    faults = [{"parameter": "Ra", "change": -12.0, "start": 20.0, "ramp": 20.0},
              {"parameter": "D", "change": 25.0, "start": 20.0, "ramp": 20.0}]
    history, _ = _run(70.0, parameter_faults=faults)
    worst = max((f.probability, h.window) for h in history
                for f in h.diagnosis.faults  # type: ignore[union-attr]
                if f.id == "current_sensor_high")
    assert worst[0] < 0.5, worst
    last = history[-1].diagnosis
    assert last is not None and last.top in ("winding_short", "bearing_wear"), last
    sensor = [f for f in last.faults if f.id == "current_sensor_high"]
    against = sensor[0].evidence_against if sensor else []
    assert not sensor or any("no ia reading too high explains the window" in e
                             for e in against), against


@pytest.mark.slow
def test_a_twin_that_does_not_fit_is_check_function_and_a_step_under_it_is_named_after() -> None:
    """The speed reading 1.1x from 20 s to 110 s (the twin cannot follow it: its model check
    fails) and Ra -6 % from 60 s, under it: check function in the health message and STATUS
    within the 60 s horizon, never "no fault" with confidence meanwhile, the winding named
    (>= 0.8) within 60 s of the twin fitting again, and the recording's model panel says
    CHECK FUNCTION while it lasts."""
    from twinwatch.sinks.rerun_views import _diagnosis_lines
    from twinwatch.twin.health import read_health

    history, problems = _run(200.0, sensor_faults=[
        {"channel": "omega", "kind": "gain", "gain": 1.1, "start": 20.0, "duration": 90.0}],
        parameter_faults=[{"parameter": "Ra", "change": -6.0, "start": 60.0}])
    cf = [i for i, h in enumerate(history)
          if h.diagnosis is not None and h.diagnosis.status == "check_function"]
    assert cf, [h.diagnosis.status for h in history]  # type: ignore[union-attr]
    first = history[cf[0]]
    assert first.t_end <= 20.0 + 60.0 + 2 * 2.0, first.t_end
    assert first.diagnosis.check_function_since == pytest.approx(20.0, abs=4.0)  # type: ignore[union-attr]
    assert any(p.startswith("CHECK FUNCTION: the twin does not describe this machine")
               for p in problems[cf[0]]), problems[cf[0]]
    view = "\n".join(_diagnosis_lines(read_health(first).diagnosis))
    assert "CHECK FUNCTION: the twin does not describe this machine" in view, view
    # while the speed reading is wrong, no window says "no fault" with confidence
    during = [h for h in history if 80.0 <= h.t_end <= 110.0]
    assert all(h.diagnosis.status != "no_fault" for h in during)  # type: ignore[union-attr]
    named = [h.t_end for h in history if h.t_end > 110.0 and h.diagnosis is not None
             and h.diagnosis.top == "winding_short" and h.diagnosis.probability >= 0.8]
    assert named and named[0] <= 110.0 + 60.0, named[:3]
    assert history[-1].diagnosis.top == "winding_short"  # type: ignore[union-attr]


def test_a_voltage_reading_low_is_the_reading_not_the_winding() -> None:
    """The default motor, healthy, its voltage reading drifting to 0.9x over 20 s from 20 s:
    the estimates move as a shorted winding moves them (Ra -10 %, every other parameter held
    or flat; measured in the fault matrix: winding_short 0.94, its alarm raised, before issue
    34's second round), but the reading, compared as an output, leaves Va's residual coloured
    window after window while a winding passes every check: the winding never reaches 0.8 and
    the voltage reading is named at the end."""
    history, _ = _run(90.0, sensor_faults=[{"channel": "Va", "kind": "gain", "gain": 0.9,
                                            "start": 20.0, "ramp": 20.0}])
    worst = max((f.probability, h.window) for h in history
                for f in h.diagnosis.faults  # type: ignore[union-attr]
                if f.id == "winding_short")
    assert worst[0] < 0.8, worst
    last = history[-1].diagnosis
    assert last is not None and last.faults[0].id == "voltage_sensor_low", last
    assert any("Va's model check failed in" in e for e in last.faults[0].evidence_for), last


@pytest.mark.slow
def test_a_sagging_supply_is_never_named_as_the_brushes_with_confidence() -> None:
    """A supply delivering 0.9 of the commanded voltage from 20 s (ramp 20 s), 120 s: Ra
    appears 11 % up exactly as worn brushes make it, every check passing: the motor's data
    cannot tell the two apart, so neither is named at 0.8 (before: brushes 0.94, its alarm
    raised) and both are listed. Until Ra's trend dates the change, the change's onset is
    the last window Ra was within its interval: Ke, read in window 0 and held since, is from
    before it and does not count against the supply (it did: brushes 0.81 in two windows)."""
    history, _ = _run(120.0, supply_fault={"ratio": 0.9, "start": 20.0, "ramp": 20.0})
    worst = max(f.probability for h in history
                for f in h.diagnosis.faults  # type: ignore[union-attr]
                if f.id == "brushes_connections")
    assert worst < 0.8, worst
    last = history[-1].diagnosis
    assert last is not None
    ids = [f.id for f in last.faults[:2]]
    assert set(ids) == {"brushes_connections", "supply_sag"}, last.faults


def test_a_signature_seen_through_a_held_parameter_applies_only_while_it_is_held() -> None:
    """A weaker magnet moves D (through Kt, tied to the held Ke) only while Ke is held; once a
    window estimates Ke it moves Ke and leaves D (the twin's Eq. 12 with Kt = Ke)."""
    lib = shipped_library("dc_motor")
    assert lib is not None
    d = Diagnoser(lib)
    i = 1 + [f.id for f in d.faults].index("magnet_weakening")   # the hypothesis {magnet}
    held = d._components("D", frozenset({"Ra", "D"}))
    free = d._components("D", frozenset({"Ra", "D", "Ke", "La", "J"}))
    assert held.p_up[i] == pytest.approx(0.9) and free.p_up[i] == 0.0


def test_a_check_a_fault_may_leave_passing_is_no_evidence_against_it(
        nominal_messages: list[HealthMessage]) -> None:
    """The unbalance may leave the outputs' checks failing (its term at one frequency a window
    against a shaft whose speed varies) or passing (a term that fits): twenty passing windows
    are no evidence against it, while they are against a speed reading's error (Va's check
    fails with it in 39 to 40 of 40 windows)."""
    base = nominal_messages[-1]
    d = Diagnoser(shipped_library("dc_motor"))  # type: ignore[arg-type]
    for w in range(20):
        out = d.update(_failing(base, w, True), None)
    against = {f.id: " ".join(f.evidence_against) for f in out.faults}
    listed = {f.id for f in out.faults}
    assert "model check failed in 0 of the last 10" not in against.get("unbalance", "")
    assert ("speed_sensor_high" not in listed
            or "Va's model check failed in 0 of the last 10" in against["speed_sensor_high"])


def _with_readings(h: HealthMessage, nominal: float, fit: float,
                   ia: tuple[float, float]) -> HealthMessage:
    """``h`` with a reading check: the nameplate twin's and the fit's nRMSE, and the ia
    reading's best correction (gain, the nRMSE it leaves); the other outputs explain nothing."""
    from twinwatch.twin.health import ReadingsHealth

    far = {"gain": 1.0, "gain_nrmse": nominal, "offset": 0.0, "offset_nrmse": nominal,
           "mean": 5.0}
    outputs = {"omega": far, "Va": far,
               "ia": {"gain": ia[0], "gain_nrmse": ia[1], "offset": 0.0,
                      "offset_nrmse": nominal, "mean": 1.2}}
    return h.model_copy(update={"readings": ReadingsHealth.model_validate(
        {"nominal_nrmse": nominal, "fit_nrmse": fit, "outputs": outputs})})


def test_the_reading_evidence_is_graded_by_what_the_corrected_reading_leaves(
        nominal_messages: list[HealthMessage]) -> None:
    """The reading kind's variable (twinwatch/twin/diagnosis/evidence.py): none while the
    nameplate twin fits as the estimate does; for the reading's direction strong when the
    corrected reading leaves the fit's nRMSE, weak when it leaves 1.5 times it, nothing for
    the other direction; half strength halfway up the anomaly's fade-in."""
    from twinwatch.twin.diagnosis.evidence import S_MIN, reading_variable

    h = nominal_messages[-1]
    assert reading_variable(_with_readings(h, 0.0105, 0.01, (1.0, 0.0105)), "k", "ia",
                            "high") is None
    explained = _with_readings(h, 0.05, 0.01, (1.1, 0.01005))
    high = reading_variable(explained, "k", "ia", "high")
    low = reading_variable(explained, "k", "ia", "low")
    assert high is not None and high.s > 0.97 and "1.1 x (gain)" in high.present
    assert low is not None and low.s <= S_MIN
    left = reading_variable(_with_readings(h, 0.05, 0.01, (1.1, 0.015)), "k", "ia", "high")
    assert left is not None and left.s <= S_MIN
    half = reading_variable(_with_readings(h, 0.013, 0.01, (1.1, 0.01005)), "k", "ia", "high")
    assert half is not None and half.s == pytest.approx(0.5 + 0.5 * (high.s - 0.5), abs=0.01)


def _with(h: HealthMessage, window: int, **params: tuple[str, float, float | None]
          ) -> HealthMessage:
    """``h`` as window ``window`` (2 s each) with each named parameter's (status, change from
    its nameplate [%], relative standard error [%] or None)."""
    new = dict(h.parameters)
    for name, (status, change_pct, rel_std_pct) in params.items():
        p = h.parameters[name]
        new[name] = p.model_copy(update={
            "value": p.nominal * (1 + change_pct / 100), "status": status,
            "held": status != "estimated", "rel_std_pct": rel_std_pct,
            "deviation_pct": change_pct, "trend": None})
    return h.model_copy(update={"window": window, "t_start": 2.0 * window,
                                "t_end": 2.0 * window + 1.99, "parameters": new})


def test_a_seldom_estimated_change_the_estimator_holds_since_is_confirmed_by_it(
        nominal_messages: list[HealthMessage]) -> None:
    """Issue 34: the DC motor's Ke is determined by about one window in forty (after a
    set-point step). A field weakened 3 % was estimated once at -3.00 % +- 0.02 % and held
    at -3.00 % (trusted) since, D back at its nameplate: the jump had no next sound window
    to confirm it (inference._confirmed), and "D up while Ke is held" argued against the
    field, so the fault matrix's case ended on no fault 0.98. The estimator's holding the
    new value confirms the jump, and a Ke held at its changed value no longer expects D to
    move. A jump the estimator does not take in (Ke held at its nameplate after it) is
    still one odd window."""
    base = nominal_messages[-1]
    lib = shipped_library("dc_motor")
    assert lib is not None

    def run(held_at: float) -> Any:
        d = Diagnoser(lib)
        out = None
        for w in range(30):
            ke = (("estimated", 0.0, 0.05) if w < 10 else
                  ("estimated", -3.0, 0.02) if w == 10 else ("held", held_at, None))
            out = d.update(_with(base, w, Ke=ke, Ra=("estimated", 0.0, 0.05),
                                 D=("estimated", 0.0, 0.5)), None)
        return out

    taken = run(-3.0)
    assert taken.top == "magnet_weakening" and taken.faults[0].probability >= 0.5, taken
    assert any("Ke = " in e and "-3.00 %" in e for e in taken.faults[0].evidence_for), \
        taken.faults[0].evidence_for
    assert not any("D = " in e for e in taken.faults[0].evidence_against), \
        taken.faults[0].evidence_against
    odd = run(0.0)
    assert odd.status == "no_fault" and all(f.probability < 0.2 for f in odd.faults), odd


def test_a_braking_constant_with_the_twin_fitting_is_dry_friction_not_the_speed_reading(
        nominal_messages: list[HealthMessage]) -> None:
    """Issue 34: Coulomb friction at a speed of one sign is a constant braking torque, which
    discovery finds as a constant on d(omega)/dt (-4.2 rad/s^2 for Tc 0.006 N m in the fault
    matrix, Va's check passing): it ended on a fault the library does not know (0.85). A
    speed reading's gain leaves the same kind of term and Va's check failing in most
    windows: the speed sensor explains both, so it is never dry friction with confidence."""
    from twinwatch.twin.health import ModelCheckHealth, TermHealth

    base = nominal_messages[-1]
    assert base.model_check is not None
    constant = TermHealth(kind="linear", attach="d(omega)/dt", mode="additive", input="t",
                          t_ref=0.0, params={"b": -4.2}, params_std={"b": 0.04}, weight=4.2,
                          significance=100.0, evidence_windows=10.0,
                          equation="d(omega)/dt += -4.20 rad/s^2", meaning="", since_window=0)

    def run(va_passes: bool) -> Any:
        d = Diagnoser(shipped_library("dc_motor"))  # type: ignore[arg-type]
        check = base.model_check.model_dump()
        check["outputs"]["Va"]["passed"] = va_passes
        check["passed"] = va_passes
        check["reasons"] = [] if va_passes else ["residual of Va not white"]
        out = None
        for w in range(20):
            msg = base.model_copy(update={
                "window": w, "t_start": 2.0 * w, "t_end": 2.0 * w + 1.99,
                "terms": [constant], "model_check": ModelCheckHealth.model_validate(check)})
            out = d.update(msg, (12.0, 0.1))
        return out

    friction = run(True)
    assert friction.top == "dry_friction" and friction.faults[0].probability >= 0.5, friction
    assert friction.unknown < 0.3, friction
    reading = run(False)
    dry = next(f for f in reading.faults if f.id == "dry_friction")
    assert dry.probability < 0.5 and reading.top != "dry_friction", reading


def test_a_decided_harmonic_stays_the_fault_s_evidence_while_the_twin_fails_without_it(
        nominal_messages: list[HealthMessage]) -> None:
    """Issue 34: a misalignment's 2x term, decided at a low speed, is not found again at
    higher speeds with 1 % noise (the fault matrix: misalignment 0.93, then check function
    0.97 or unknown 0.94 at the end). A coupling does not mend itself: while the twin keeps
    failing its check, the decided harmonic stays the fault's evidence for 60 windows; with
    the check passing (the forcing gone) its absence counts against it, as before."""
    from twinwatch.twin.diagnosis.inference import TERM_MEMORY_WINDOWS
    from twinwatch.twin.health import ModelCheckHealth, TermHealth

    base = nominal_messages[-1]
    assert base.model_check is not None
    term = TermHealth(kind="periodic", attach="d(omega)/dt", mode="additive", input="t",
                      t_ref=0.0, params={"a": 5.0, "b": 11.0, "c": 0.0},
                      params_std={"a": 0.05, "b": 0.01, "c": 0.01}, weight=5.0,
                      significance=100.0, evidence_windows=5.0,
                      equation="d(omega)/dt += 5*sin(11*t)", meaning="", since_window=0)

    def check(passed: bool) -> ModelCheckHealth:
        doc = base.model_check.model_dump()  # type: ignore[union-attr]
        doc["passed"] = doc["outputs"]["Va"]["passed"] = passed
        doc["reasons"] = [] if passed else ["residual of Va not white"]
        return ModelCheckHealth.model_validate(doc)

    def run(after: int, passed: bool) -> Any:
        d = Diagnoser(shipped_library("dc_motor"))  # type: ignore[arg-type]
        out = None
        for w in range(8 + after):
            found = w < 8   # decided at 2 x 5.5 rad/s, then lost at 15 rad/s
            msg = base.model_copy(update={
                "window": w, "t_start": 2.0 * w, "t_end": 2.0 * w + 1.99,
                "terms": [term] if found else [], "model_check": check(found or passed)})
            out = d.update(msg, (5.5, 0.05) if found else (15.0, 0.1))
            if w == 7:
                assert out.top == "misalignment", out
        return out

    kept = run(20, passed=False)
    assert kept.top == "misalignment" and kept.faults[0].probability >= 0.8, kept
    assert any("decided in window 7 and not found again since" in e
               for e in kept.faults[0].evidence_for), kept.faults[0].evidence_for
    gone = run(20, passed=True)
    assert gone.top != "misalignment", gone
    forgotten = run(TERM_MEMORY_WINDOWS + 5, passed=False)
    assert forgotten.top != "misalignment" or forgotten.faults[0].probability < 0.5, forgotten


def test_a_deviation_that_scales_as_one_over_the_speed_is_dry_friction_not_the_bearings(
        nominal_messages: list[HealthMessage]) -> None:
    """Issue 34: before discovery finds its term, Coulomb friction at a speed of one sign is
    absorbed into the viscous friction, D reading D + Tc/omega: across set-points its
    deviation scales as 1/omega (the fault matrix, Tc 0.002 N m: +25 % at 5.5 rad/s, +8 % at
    17.7), where worn bearings' D stays put. The first read bearing_wear 0.58-0.60."""
    base = nominal_messages[-1]
    speeds = [14.2, 14.6, 17.4, 18.8, 9.9, 7.3, 6.1, 5.5, 15.1, 17.7] * 2

    def run(dev_at: Any) -> Any:
        d = Diagnoser(shipped_library("dc_motor"))  # type: ignore[arg-type]
        out = None
        for w in range(30):
            sp = speeds[w - 10] if w >= 10 else 12.0
            dev = dev_at(sp) if w >= 10 else 0.0
            out = d.update(_with(base, w, D=("estimated", dev, 0.3),
                                 Ra=("estimated", 0.0, 0.05)), (sp, 0.1))
        return out

    friction = run(lambda sp: 140.0 / sp)
    assert friction.top == "dry_friction" and friction.faults[0].probability >= 0.5, friction
    assert any("D's deviation scales as the shaft speed to the power -1.00" in e
               for e in friction.faults[0].evidence_for), friction.faults[0].evidence_for
    bearings = run(lambda sp: 12.0)
    assert bearings.top == "bearing_wear", bearings
    dry = next(f for f in bearings.faults if f.id == "dry_friction")
    assert dry.probability < 0.3, bearings


def test_a_small_change_every_window_estimates_is_read_from_the_windows_pooled(
        nominal_messages: list[HealthMessage]) -> None:
    """Issue 34: the PWM drive at 1 % noise estimates every parameter in most windows, a field
    weakened 3 % at Ke -3 % +- 1.3 % (1 sigma) a window: one window at a time it read "no
    fault" 0.92. Ten such windows pooled name the field. Windows that held a parameter are
    not pooled: their estimates carry the held value's lag, the same in each (the current
    reading 1.1 times too high: Ra fused at -6 % while it read -10 %, Ke -2 % beside it in
    every such window, named dry friction 0.88 when pooled)."""
    base = nominal_messages[-1]
    lib = shipped_library("dc_motor")
    assert lib is not None
    quiet = {n: ("estimated", 0.0, 0.05) for n in ("Ra", "La", "J", "D")}
    ke = [-1.4, -4.1, -2.6, -3.9, -1.9, -3.3, -4.4, -2.2, -3.0, -3.2]  # mean -3.0 %

    def run(pool_windows: int, **held: tuple[str, float, float | None]) -> Any:
        d = Diagnoser(lib, pool_windows=pool_windows)
        out = None
        for w in range(30):
            dev = ke[w % 10] if w >= 10 else 0.0
            out = d.update(_with(base, w, **{**quiet, **held,
                                             "Ke": ("estimated", dev, 1.3)}), None)
        return out

    pooled = run(10)
    top = pooled.faults[0]
    assert pooled.top == "magnet_weakening" and top.probability >= 0.8, pooled
    assert any("10 windows' estimates pooled" in e and "is -3.0" in e
               for e in top.evidence_for), top.evidence_for
    alone = run(1)
    assert all(f.probability < 0.5 for f in alone.faults), alone
    beside_held = run(10, La=("held", 0.0, None))
    assert all(f.probability < 0.5 for f in beside_held.faults), beside_held
    # a change under way (Ke falling 0.5 % a window, each to +- 0.2 %): the windows disagree
    # beyond their errors and their mean lags; the evidence is the last window's
    d = Diagnoser(lib, pool_windows=10)
    for w in range(30):
        ramp = ("estimated", -0.5 * (w - 9) if w >= 10 else 0.0, 0.2)
        falling = d.update(_with(base, w, **{**quiet, "Ke": ramp}), None)
    said = [e for f in falling.faults for e in f.evidence_for if e.startswith("Ke = ")]
    assert said and all("is -10.00 %" in e and "this window's estimate" in e for e in said), said


def test_a_load_inertia_the_windows_hold_is_read_across_windows_from_d_s_response() -> None:
    """J +50 % (from 60 s, full by 120 s) on the default motor without noise: no window
    determines J beside D (held in every window), but after each set-point step D absorbs the
    inertia's torque with the sign of the acceleration, J's alias in that window
    (:mod:`twinwatch.twin.estimation.aliases`). Read across the windows (the differences of
    D against those of the alias), J is named: ``load_inertia_change`` first at the end, its
    evidence J read up beyond three standard errors; no other library fault at 0.8 in any
    window. Without the read across windows this case ended on "no fault" 0.98 (fault matrix,
    2026-11-26); it fails with the read removed, or with the adapter not asked J's alias in
    every window."""
    history, _ = _run(200.0, noise={}, parameter_faults=[
        {"parameter": "J", "change": 50.0, "start": 60.0, "ramp": 60.0}])
    assert all(h.parameters["J"].status != "estimated" for h in history)
    last = history[-1].diagnosis
    assert last is not None and last.faults[0].id == "load_inertia_change", last
    said = " ".join(last.faults[0].evidence_for)
    assert "read across" in said and "J = " in said, said
    # the read is published as a number with its interval, which covers the truth (2 sigma),
    # and the summary's parameter line says it beside the fusion's "not determined"
    read = last.read_across["J"]
    assert read.over_windows >= 6 and abs(read.deviation_pct - 50.0) <= 2.0 * read.std_pct, read
    line = next(x for x in window_lines(history[-1]) if x.lstrip().startswith("J "))
    assert f"read across {read.over_windows} windows" in line and "(diagnosis)" in line, line
    before = [h.diagnosis.read_across["J"] for h in history if h.t_end < 60.0
              and h.diagnosis is not None and "J" in h.diagnosis.read_across]
    assert before and all(abs(r.deviation_pct) <= 2.0 * r.std_pct for r in before), before
    # a weaker field with Ke held also reads J up (J/Kt), but it moves D up with it: D's
    # estimate net of J's part and D's trend (J's part, which changes sign with each step)
    # leave it well behind (0.39 with D's trend read as degrading)
    assert last.faults[1].probability < 0.3, last.faults[1]
    for h in history:
        d = h.diagnosis
        assert d is not None
        wrong = [(f.id, f.probability) for f in d.faults
                 if f.id != "load_inertia_change" and f.probability >= 0.8]
        assert not wrong, (h.window, wrong)


def _trend(onset: float | None) -> Any:
    """A flat trend whose change point is ``onset`` [s] (None: its model dates none)."""
    from twinwatch.twin.health import TrendHealth

    return TrendHealth.model_validate({
        "model": "linear", "onset": onset, "since_t": onset, "evidence": 10, "level": None,
        "level_std": None, "rate": None, "rate_low": None, "rate_high": None,
        "rate_pct_per_h": None, "growth": None, "degrading": False, "model_weight": None,
        "monotonicity": None, "trendability": None, "restarted": False, "restart": None,
        "restarts": 0, "window_evidence": None})


def test_another_parameter_s_later_change_point_leaves_this_one_s_evidence(
        nominal_messages: list[HealthMessage]) -> None:
    """Evidence on a parameter is read after its own trend's change point. On the PWM drive
    (fault matrix, 2026-11-27) a winding -4 % was estimated -4.0 % in every window that
    determined Ra, Ra's trend dated the change at 57 s and later dropped it; then J's trend,
    drifting with the fusion, dated a change at 178 s, and every Ra estimate before it was set
    aside: winding 0.81, then no fault 0.96. Here Ra -4 % +- 0.5 % (trend onset 20 s) in
    windows 10-20, then held while J's trend dates a change at 50 s: the winding stays first;
    a change point of Ra's own after its estimates (a repair) sets them aside."""
    base = nominal_messages[-1]

    def run(j_onset: float | None, ra_later: float | None) -> Any:
        d = Diagnoser(shipped_library("dc_motor"))  # type: ignore[arg-type]
        out = None
        for w in range(10, 36):
            h = _with(base, w, Ra=("estimated", -4.0, 0.5) if w <= 20 else ("held", -4.0, None))
            trends = {"Ra": _trend(20.0)} if w <= 20 else {"Ra": _trend(ra_later),
                                                           "J": _trend(j_onset)}
            h = h.model_copy(update={"parameters": {
                **h.parameters, **{n: h.parameters[n].model_copy(update={"trend": t})
                                   for n, t in trends.items()}}})
            out = d.update(h, None)
        return out

    kept = run(j_onset=50.0, ra_later=None)
    assert kept.faults[0].id == "winding_short" and kept.faults[0].probability >= 0.8, kept
    repaired = run(j_onset=None, ra_later=60.0)
    assert repaired.faults[0].id != "winding_short" or repaired.faults[0].probability < 0.2, \
        repaired.faults[0]
