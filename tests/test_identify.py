"""Commissioning (issue 9 item 4): ``twinwatch identify`` fits the baseline on a training range
of a recording and scores it on a validation range it was not fitted to."""

from __future__ import annotations

import csv
import math
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from twinwatch.commissioning.identify import (
    Combination,
    Identifiability,
    _Holds,
    _weakest_stated,
    analyse,
    compare_structures,
    fit_percent,
    identify,
    information_criteria,
    parameters_block,
)
from twinwatch.commissioning.record import identify_blueprint, residual_tests
from twinwatch.commissioning.report import report
from twinwatch.config.identify import AS_CONFIGURED, FixedValue, IdentifyConfig
from twinwatch.io.drive import DriveConfig
from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig, SetpointSchedule
from twinwatch.twin.estimation.estimator import EstimationConfig, PSOSettings
from twinwatch.twin.estimation.statistics import ModelCheck, OutputCheck
from twinwatch.twin.model import WindowData
from twinwatch.twin.models.dcmotor import DCMotorTwin

TRUE = {"Ra": 7.2, "Ke": 0.041}


def _recording(seconds: float, noise: dict[str, float], **plant: object) -> WindowData:
    plant = DCMotorPlant(DCMotorPlantConfig(scenario="nominal", duration=seconds, Ra=TRUE["Ra"],
                                            Ke=TRUE["Ke"], Kt=TRUE["Ke"], noise=noise, seed=2,
                                            **plant))
    ss = []
    while True:
        try:
            ss.append(plant.next_sample())
        except Exception:  # noqa: BLE001 - EndOfStream ends the plant
            break
    return WindowData(t=np.array([s.t for s in ss]),
                      channels={c: np.array([s.values[c] for s in ss]) for c in ss[0].values})


def _split(w: WindowData) -> tuple[WindowData, WindowData]:
    h = w.n // 2
    cut = [WindowData(t=w.t[a:b], channels={c: v[a:b] for c, v in w.channels.items()})
           for a, b in ((0, h), (h, w.n))]
    return cut[0], cut[1]


def test_fit_percent_is_matlab_compare() -> None:
    y = np.sin(np.linspace(0, 6, 100))
    assert fit_percent(y, y) == pytest.approx(100.0)
    assert fit_percent(y, np.full_like(y, y.mean())) == pytest.approx(0.0)
    assert fit_percent(y, y + 0.1 * (y - y.mean())) == pytest.approx(90.0)


@pytest.mark.slow  # about 15 s on the shared 2-core box: out of the fast lane
def test_identified_baseline_covers_the_truth_and_fits_the_held_out_half() -> None:
    """A motor unlike the nameplate (Ra +11 %, Ke +8 %), 1 % noise: the training half gives Ra
    and Ke whose intervals cover the plant's values, and the twin fits the validation half."""
    w = _recording(80.0, {"ia": 1.0, "omega": 1.0})
    train, validation = _split(w)
    est = EstimationConfig(estimate=["Ra", "Ke"], tie={"Kt": "Ke"},
                           bounds={"Ra": (1.0, 30.0), "Ke": (0.01, 0.1)})
    cfg = IdentifyConfig(pso=PSOSettings(pop_size=10, max_generations=10), time_budget=5.0)
    r = identify(DCMotorTwin(), est, cfg, train, validation)
    for name, truth in TRUE.items():
        assert abs(math.log(r.values[name] / truth)) <= 3 * r.rel_std[name], (name, r.values)
        assert r.values[name] == pytest.approx(truth, rel=0.02)
    assert r.values["Kt"] == r.values["Ke"]
    for out in ("ia", "omega"):
        assert r.validation.fit_pct[out] > 80.0 and r.train.fit_pct[out] > 80.0  # 1 % noise
    # both determined: nothing held, the analysis full rank and well conditioned
    assert r.determined == ["Ra", "Ke"] and not r.held and not r.undetermined
    assert r.identifiability is not None and r.identifiability.rank == 2
    assert r.identifiability.determined_rank == 2 and not r.identifiability.undetermined
    block = parameters_block(r, "a test recording")
    assert "[machine.parameters]" in block and f"Ra = {r.values['Ra']:.6g}" in block
    assert "bounds = { Ra = [1, 30], Ke = [0.01, 0.1] }" in block
    assert set(tomllib.loads(block)["machine"]["parameters"]) == {"Ra", "Ke", "Kt"}


@pytest.mark.slow  # about 15 s on the shared 2-core box: out of the fast lane
def test_undetermined_combination_is_named_and_held_at_its_stated_value() -> None:
    """Kt untied: with a viscous load Tload = c*omega, (J, Kt, D) -> (sJ, sKt, s(D + c) - c)
    leaves every output unchanged (docs/architecture.md, known ill-posedness), a direction
    d ln J = d ln Kt = d ln D * D/(D + c). Identify names that combination, pastes Ra and Ke
    only; with J stated in [identify.fixed] it holds J there and determines Kt and D."""
    w = _recording(40.0, {"ia": 0.5, "omega": 0.5})
    train, validation = _split(w)
    est = EstimationConfig(estimate=["Ra", "Ke", "Kt", "J", "D"], tie={},
                           bounds={"Ra": (1.0, 30.0), "Ke": (0.01, 0.1), "Kt": (0.01, 0.1),
                                   "J": (1e-4, 1e-2), "D": (1e-4, 1e-2)})
    cfg = IdentifyConfig(pso=PSOSettings(pop_size=10, max_generations=10), time_budget=5.0)
    r = identify(DCMotorTwin(), est, cfg, train, validation)
    a = r.identifiability
    assert a is not None
    weakest = a.undetermined[0]
    d = r.full.values["D"] if r.full else math.nan  # anywhere along the direction
    ratio = (d + 0.006) / d
    assert weakest.std > 1.0  # the outputs cannot tell it from no change
    assert weakest.weights["D"] == pytest.approx(1.0)
    for name in ("J", "Kt"):
        assert weakest.weights[name] == pytest.approx(1 / ratio, abs=0.02)
    for name in ("Ra", "Ke"):
        assert abs(weakest.weights.get(name, 0.0)) < 0.01
    assert weakest.label().startswith(f"D + {1 / ratio:.2g} ")
    assert a.rank == 4 and math.isinf(a.condition)
    # nothing stated: Ra determined and pasted; Kt, J and D named, free, not pasted (and Ke,
    # which trades off with Ra once Kt is free: in steady state only Ra (D + c)/Kt + Ke shows)
    assert r.determined == ["Ra"] and not r.held
    assert sorted(r.undetermined) == ["D", "J", "Ke", "Kt"]
    assert "state a value of" in r.undetermined["D"] and "J" in r.undetermined["D"]
    pasted = tomllib.loads(parameters_block(r, "x"))["machine"]["parameters"]
    assert set(pasted) == {"Ra"}
    assert r.values["Ra"] == pytest.approx(TRUE["Ra"], rel=0.01)  # the null direction aside
    # J stated (its datasheet value, exact): held there; Kt and D determined, at the plant's
    stated = cfg.model_copy(update={"fixed": {"J": FixedValue(value=0.001171,
                                                             reason="the rotor's datasheet")}})
    r2 = identify(DCMotorTwin(), est, stated, train, validation)
    assert list(r2.held) == ["J"] and r2.held["J"].source == "[identify.fixed]"
    assert r2.held["J"].stated == "the rotor's datasheet" and r2.held["J"].why.startswith("in D")
    assert sorted(r2.determined) == ["D", "Kt", "Ra"]
    # measured: Kt 0.04095 +- 0.84 %, D 0.001421 +- 4.4 %
    assert r2.values["Kt"] == pytest.approx(TRUE["Ke"], rel=0.01)
    assert r2.values["D"] == pytest.approx(0.00143, rel=0.05)
    block = parameters_block(r2, "x")
    assert set(tomllib.loads(block)["machine"]["parameters"]) == {"Ra", "Kt", "D"}
    assert "# J = 0.001171" in block and "the rotor's datasheet" in block
    # a stated value's own uncertainty is propagated: Kt follows J one to one
    loose = stated.model_copy(update={"fixed": {"J": FixedValue(value=0.001171,
                                                               rel_std=0.05)}})
    r3 = identify(DCMotorTwin(), est, loose, train, validation)
    assert r3.rel_std["Kt"] == pytest.approx(math.hypot(0.05, r2.rel_std["Kt"]), rel=0.1)
    assert r3.rel_std["D"] > r2.rel_std["D"] + 0.1


def test_a_stated_value_of_a_parameter_not_identified_is_its_value_in_the_fit() -> None:
    w = _recording(10.0, {})
    train, validation = _split(w)
    est = EstimationConfig(estimate=["Ra"], tie={"Kt": "Ke"}, bounds={"Ra": (1.0, 30.0)})
    cfg = IdentifyConfig(pso=PSOSettings(pop_size=6, max_generations=3), time_budget=2.0,
                         fixed={"Ke": FixedValue(value=0.041, reason="nameplate")})
    r = identify(DCMotorTwin(), est, cfg, train, validation, {"Ke": 0.038})
    assert r.values["Ke"] == r.values["Kt"] == 0.041 and "Ke" not in r.held
    assert r.values["Ra"] == pytest.approx(TRUE["Ra"], rel=1e-3)  # noise-free, Ke as stated


def test_a_negative_fit_never_passes() -> None:
    """An output the twin fits worse than its mean fails the model check, with the reason,
    even where the residual tests alone pass (a noisy output's scatter looks white)."""
    from twinwatch.commissioning.identify import _honest_check

    ok = OutputCheck(rms=0.01, noise=0.01, whiteness_p=0.5, cross_p=0.5, passed=True)
    check = ModelCheck(passed=True, outputs={"ia": ok, "omega": ok})
    out = _honest_check(check, {"ia": -11.5, "omega": 80.0})
    assert not out.passed and not out.outputs["ia"].passed and out.outputs["omega"].passed
    assert out.reasons == ["ia fitted worse than its mean (fit -11.5 %): the twin does not "
                           "explain its variation"]
    assert _honest_check(check, {"ia": 0.0, "omega": 80.0}) is check


def test_information_criteria_are_matlab_aic() -> None:
    rng = np.random.default_rng(0)
    y = rng.normal(size=(101, 2))
    sim = y + rng.normal(scale=0.1, size=(101, 2))
    ic = information_criteria(y, sim, 3)
    e = (sim - y)[1:]
    n = 100
    base = n * math.log(np.linalg.det(e.T @ e / n)) + n * 2 * (math.log(2 * math.pi) + 1)
    assert ic.aic == pytest.approx(base + 6) and ic.bic == pytest.approx(base + 3 * math.log(n))
    assert ic.samples == 100 and ic.parameters == 3


def test_candidate_structures_are_compared_and_the_drives_period_wins() -> None:
    """A drive that updates its PI every 5 ms with its output clamped (a candidate structure
    the configuration lists) against the twin configured with an ideal drive: the matching
    structure fits the held-out half better, passes the model check and has the lowest BIC;
    it wins."""
    drive = {"period": 0.005, "speed": {"kp": 2.0, "ki": 2.0, "output_min": 0.0,
                                        "output_max": 24.0}}
    steps = [(0.0, 10.0), (3.0, 20.0), (6.0, 5.0), (9.0, 15.0), (12.0, 25.0), (15.0, 5.0),
             (18.0, 12.0)]
    w = _recording(20.0, {"ia": 0.2, "omega": 0.2, "Va": 0.2},
                   drive=DriveConfig.model_validate(drive),
                   setpoint=SetpointSchedule(steps=steps))
    train, validation = _split(w)
    est = EstimationConfig(estimate=["Ra", "Ke"], tie={"Kt": "Ke"},
                           bounds={"Ra": (1.0, 30.0), "Ke": (0.01, 0.1)})
    cfg = IdentifyConfig(pso=PSOSettings(pop_size=8, max_generations=6), time_budget=5.0)
    ideal = DCMotorTwin(kp=2.0, ki=2.0)
    matched = DCMotorTwin(drive=drive)
    results = [identify(ideal, est, cfg, train, validation),
               identify(matched, est, cfg, train, validation, structure="drive as it runs",
                        options={"drive": drive})]
    comp = compare_structures(results)
    assert comp.best.structure == "drive as it runs"
    ideal_r, matched_r = comp.results
    assert ideal_r.structure == AS_CONFIGURED
    assert matched_r.full.criteria.bic < ideal_r.full.criteria.bic
    assert matched_r.validation.check.passed
    for name in ("Ra", "Ke"):
        assert matched_r.values[name] == pytest.approx(TRUE[name], rel=0.01)
    text = report(comp.best, comp)
    assert "winner: drive as it runs" in text
    block = parameters_block(comp.best, "x")
    assert "# structure: drive as it runs; in [machine.options] set:" in block
    # the commissioning view: one fit plot per output with the fit % in the title, the
    # residual tests (autocorrelation, cross-correlation with the set-point) per output
    tests = residual_tests(comp.best, "omega")
    assert tests.lags.size == 51 and tests.autocorrelation["validation"][0] == pytest.approx(1)
    assert set(tests.cross_correlation) == {"setpoint"}
    assert tests.band == pytest.approx(2.58 / math.sqrt(validation.n - 1))
    bp = identify_blueprint("bench", comp.best, comp)
    names = _view_names(bp)
    for out in ("ia", "omega", "Va"):
        fit = comp.best.validation.fit_pct[out]
        assert any(n.startswith(f"{out} [") and f"{fit:.1f} % validation" in n for n in names)
        assert f"{out} residual: autocorrelation, lag [0.01 s]" in names
        assert f"{out} residual x setpoint: cross-correlation (validation), lag [0.01 s]" \
            in names
    assert "bench: parameters and fit" in names


def _view_names(bp: object) -> list[str]:
    """Every view's name in a blueprint (containers walked)."""
    out: list[str] = []

    def walk(part: object) -> None:
        if hasattr(part, "origin"):  # a view
            out.append(str(part.name))
            return
        for child in getattr(part, "contents", None) or []:
            walk(child)

    walk(bp.root_container)  # type: ignore[attr-defined]
    return out


def test_ranges_are_checked() -> None:
    with pytest.raises(ValueError, match="train: need 0 <= start < end <= 1"):
        IdentifyConfig(train=(0.5, 0.2))
    with pytest.raises(ValueError, match="weights.ia: must be a finite number"):
        IdentifyConfig(weights={"ia": -1.0})


@pytest.mark.slow  # about 10 s on the shared 2-core box: out of the fast lane
def test_identify_command_on_a_csv_recording(tmp_path: Path) -> None:
    """The command as a user runs it, on a CSV file replayed by the file driver: the report,
    the block with the bounds, the Rerun file of both fits; a gap in a range is refused."""
    w = _recording(30.0, {})
    path = tmp_path / "run.csv"
    with path.open("w", newline="") as f:
        out = csv.writer(f)
        out.writerow(["time", "setpoint", "Va", "ia", "omega"])
        for k in range(w.n):
            out.writerow([f"{w.t[k]:.2f}", w["setpoint"][k], w["Va"][k], w["ia"][k],
                          w["omega"][k]])
    cfg = tmp_path / "machine.toml"
    cfg.write_text(f"""
[machine]
name = "bench"
[machine.parameters]
Ra = 6.5
[estimation]
estimate = ["Ra", "Ke"]
bounds = {{ Ra = [1.0, 30.0], Ke = [0.01, 0.1] }}
[identify]
time_budget = 3.0
pso = {{ pop_size = 8, max_generations = 5 }}
[driver]
type = "file"
path = "{path.name}"
format = "csv"
time_column = "time"
sample_period = 0.01
[driver.columns]
setpoint = {{ column = "setpoint" }}
Va = {{ column = "Va" }}
ia = {{ column = "ia" }}
omega = {{ column = "omega" }}
[zenoh]
enabled = false
[recording]
enabled = false
[state]
enabled = false
""")
    rrd = tmp_path / "fit.rrd"
    block = tmp_path / "params.toml"
    res = subprocess.run([sys.executable, "-m", "twinwatch", "identify", str(cfg),
                          "--record", str(rrd), "--output", str(block)],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert "fit % (100 (1 - |y - y_hat| / |y - mean(y)|))" in res.stdout
    assert "validation" in res.stdout and "[machine.parameters]" in res.stdout
    text = block.read_text()
    ra = float(text.split("Ra = ")[1].split()[0])
    assert ra == pytest.approx(TRUE["Ra"], rel=1e-3)  # noise-free: exact
    assert rrd.stat().st_size > 1000
    # the file holds the commissioning view's entities (the blueprint: test above)
    import rerun.chunk

    entities = rerun.chunk.RrdReader(rrd).store().schema().entity_paths()
    for out in ("ia", "omega", "Va"):
        assert {f"/identify/fit/{out}/measured", f"/identify/fit/{out}/twin",
                f"/acf/{out}/training", f"/acf/{out}/validation",
                f"/xcorr/{out}_setpoint/validation"} <= set(entities)
    assert {"/identify/report/parameters", "/identify/report/analysis"} <= set(entities)
    bad = subprocess.run([sys.executable, "-m", "twinwatch", "identify", str(cfg),
                          "--train", "0.6:0.2"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 78 and "train: need 0 <= start < end <= 1" in bad.stderr
    # a candidate structure's option and a stated value are checked with the configuration
    for extra, message in (
            ('[[identify.candidates]]\nname = "fast drive"\noptions = { drive_period = 1 }',
             "identify.candidates[0] (fast drive).options: unknown option 'drive_period'"),
            ("[identify.fixed]\nRb = 6.5", "identify.fixed: unknown parameter 'Rb'")):
        bad_cfg = tmp_path / "bad.toml"
        bad_cfg.write_text(cfg.read_text().replace("[driver]", extra + "\n[driver]", 1))
        res = subprocess.run([sys.executable, "-m", "twinwatch", "identify", str(bad_cfg)],
                             capture_output=True, text=True, timeout=120)
        assert res.returncode == 78 and message in res.stderr, res.stderr


def _analysis(undetermined: list[Combination]) -> Identifiability:
    """An identifiability with only what the hold choice reads: its undetermined
    combinations."""
    n = 3
    return Identifiability(names=["Ra", "J", "D"], information=np.eye(n), eigenvalues=np.ones(n),
                           rank=n, determined_rank=n - len(undetermined), condition=1.0,
                           rel_std={}, correlation=np.eye(n), strong_pairs=[],
                           undetermined=undetermined, at_bound={}, max_rel_std=0.1)


def _holds(fixed: dict[str, FixedValue], configured: dict[str, float]) -> _Holds:
    names = ["Ra", "J", "D"]
    return _Holds(names, {"Ra": (1.0, 30.0), "J": (1e-4, 1e-2), "D": (1e-4, 1e-2)},
                  IdentifyConfig(fixed=fixed), configured,
                  {"Ra": 7.0, "J": 0.002, "D": 0.0015}, np.zeros(4), [0, 1, 2])


def test_hold_choice_takes_the_weakest_combinations_stated_main_parameter() -> None:
    """The next parameter held (identify's re-fit, without a swarm): the weakest combination
    that a stated value resolves, its largest share with one; a value of [identify.fixed]
    before a configured one; why it is held, in words; None when nobody stated one."""
    comb = Combination(weights={"D": 1.0, "J": 0.6, "Ra": 0.05}, std=2.0)
    # nothing stated: the combination stays free
    assert _weakest_stated(_analysis([comb]), _holds({}, {})) is None
    # configured values of D and J: D, the larger share
    name, why = _weakest_stated(_analysis([comb]), _holds({}, {"D": 0.0014, "J": 0.001}))
    assert name == "D" and why == "in D + 0.6 J (+-200 %)"
    # J stated in [identify.fixed]: J first, whatever its share
    fixed = {"J": FixedValue(value=0.001171, reason="datasheet")}
    assert _weakest_stated(_analysis([comb]), _holds(fixed, {"D": 0.0014}))[0] == "J"
    # a parameter alone in its combination: the outputs barely respond to it
    alone = Combination(weights={"Ra": 1.0, "J": 0.01}, std=0.5)
    assert _weakest_stated(_analysis([alone]), _holds({}, {"Ra": 6.5})) == (
        "Ra", "the outputs barely respond to it (+-50 % alone)")
    # a combination of parameters nobody stated is passed over for the next
    assert _weakest_stated(_analysis([alone, comb]), _holds({}, {"J": 0.001}))[0] == "J"


def test_a_held_parameter_is_clipped_to_its_bounds_and_leaves_the_search() -> None:
    """Holding: at a bound where the search left it (exact), else at the stated value clipped
    to the bounds, its logarithm in the search vector, its position no longer free; a value
    of [identify.fixed] keeps its stated uncertainty."""
    h = _holds({"J": FixedValue(value=0.05, rel_std=0.02, reason="datasheet")}, {"D": 0.0014})
    h.hold(0, "at its upper bound", at=30.0)
    h.hold(1, "in D + J")
    h.hold(2, "in D + J")
    assert h.free == [] and list(h.held) == ["Ra", "J", "D"]
    assert h.held["Ra"].source == "bound" and h.held["Ra"].value == 30.0
    assert h.held["J"].value == 1e-2 and h.held["J"].source == "[identify.fixed]"  # clipped
    assert h.held["J"].stated == "datasheet" and h.held["J"].full_value == 0.002
    assert h.held["D"].source == "[machine.parameters]" and h.held["D"].rel_std == 0.0
    assert h.v[:3] == pytest.approx(np.log([30.0, 1e-2, 0.0014]))
    assert h.rel_sd() == {1: 0.02}


def test_identify_refuses_a_stretch_it_cannot_fit() -> None:
    """Too short, a channel missing, a NaN: refused before any search, naming the range."""
    w = _recording(1.0, {})
    train, validation = _split(w)
    est = EstimationConfig(estimate=["Ra"])
    short = WindowData(t=w.t[:5], channels={c: v[:5] for c, v in w.channels.items()})
    with pytest.raises(ValueError, match="the validation range holds 5 samples"):
        identify(DCMotorTwin(), est, IdentifyConfig(), train, short)
    missing = WindowData(t=train.t, channels={c: v for c, v in train.channels.items()
                                              if c != "ia"})
    with pytest.raises(ValueError, match="no channel 'ia' \\(training range\\)"):
        identify(DCMotorTwin(), est, IdentifyConfig(), missing, validation)
    bad = WindowData(t=train.t, channels={**train.channels, "omega": train["omega"].copy()})
    bad.channels["omega"][3] = np.nan
    with pytest.raises(ValueError, match="channel 'omega' holds NaN or inf in the training"):
        identify(DCMotorTwin(), est, IdentifyConfig(), bad, validation)


def test_analysis_names_the_null_direction_the_weak_combination_and_the_strong_pair() -> None:
    """The identifiability of a covariance built to be read (no fit): Ra determined to 1 %
    (and at its upper bound), J and D correlated 0.999 (J - D determined, J + D to 200 %), Ke
    in an exact null direction (infinite variance)."""
    inf = math.inf
    cov = np.array([[1e-4, 0.0, 0.0, 0.0],
                    [0.0, 1.0, 0.999, 0.0],
                    [0.0, 0.999, 1.0, 0.0],
                    [0.0, 0.0, 0.0, inf]])
    cov[3, :] = cov[:, 3] = inf
    null = np.array([[0.0], [0.0], [0.0], [-1.0]])
    values = {"Ra": 7.0, "J": 1e-3, "D": 1e-3, "Ke": 0.04}
    bounds = {"Ra": (1.0, 7.0), "J": (1e-4, 1e-2), "D": (1e-4, 1e-2), "Ke": (0.01, 0.1)}
    a = analyse(["Ra", "J", "D", "Ke"], cov, values, bounds, 0.05, null=null)
    assert a.at_bound == {"Ra": "upper"}
    assert a.rank == 3 and a.determined_rank == 2 and math.isinf(a.condition)
    assert a.rel_std["Ra"] == pytest.approx(0.01) and math.isinf(a.rel_std["Ke"])
    # the null direction first (its sign: the largest component +1), then the weak one
    assert [c.weights for c in a.undetermined][0] == {"Ke": 1.0}
    assert math.isinf(a.undetermined[0].std) and len(a.undetermined) == 2
    weak = a.undetermined[1]
    assert weak.weights == pytest.approx({"Ra": 0.0, "J": 1.0, "D": 1.0}, abs=1e-9)
    assert weak.std == pytest.approx(math.sqrt(1.999 * 2))
    assert a.strong_pairs == [("J", "D", pytest.approx(0.999))]
    assert np.all(np.isnan(a.correlation[3])) and np.all(a.information[3] == 0.0)
    assert list(a.eigenvalues) == pytest.approx([0.0, 1 / 1.999, 1 / 0.001, 1e4])
    # at threshold 0 every pair with a correlation is listed (Ke's are nan: not determined)
    assert len(analyse(["Ra", "J", "D", "Ke"], cov, values, bounds, 0.05, strong=0.0,
                       null=null).strong_pairs) == 3
