"""Commissioning on the real MotoShield recordings (issue 9 item 4, issue 15 item 7):
``twinwatch identify`` says what the recording determines, holds the rest at stated values,
pastes only the determined parameters, and stays above the held-out targets; on the second
board's recording its report is honest; the daemon, run with the first board's baseline,
publishes per-window estimates consistent with the commissioning intervals.

The recordings are ../shared/data/motoshield/{aprbsResult,identification_data}.mat (CC BY-NC-ND
4.0, read in place); the tests skip when they are absent."""

from __future__ import annotations

import math
import tomllib
from typing import Any

import numpy as np
import pytest

from twinwatch.commissioning.commission import commission
from twinwatch.commissioning.identify import Identification, parameters_block
from twinwatch.commissioning.report import report
from twinwatch.config.identify import AS_CONFIGURED, merge_options
from twinwatch.config.loader import load_config
from twinwatch.daemon.runner import Daemon

from .helpers.paths import ROOT, shared_path

CONFIG = ROOT / "config" / "dc-motor-motoshield.toml"
RAW = ROOT / "config" / "dc-motor-motoshield-raw.toml"
BOARD2 = ROOT / "config" / "dc-motor-motoshield-board2.toml"
#: Held-out fit % of the grey-box linear reference (DE + least squares, issue 9): speed, current.
REFERENCE = {"omega": 71.5, "ia": 36.4}
#: The issue's targets on the held-out half.
TARGET = {"omega": 80.0, "ia": 50.0}


def _cold(path: Any, **identify: Any) -> Any:
    """The configuration started from the model's generic values ([machine.parameters] left
    out: the config's values came from this command, starting there would prove nothing)."""
    cfg = load_config(path)
    return cfg, cfg.model_copy(update={
        "machine": cfg.machine.model_copy(update={"parameters": {}}),
        "identify": cfg.identify.model_copy(update=identify)})


def _pasted(block: str) -> dict[str, float]:
    return tomllib.loads(block)["machine"]["parameters"]


@pytest.fixture(scope="module")
def commissioned() -> tuple[Any, Identification]:
    """Board 1 as a user commissions it, with one of the config's four starts (a quarter of
    its search budget) and its structure only (the candidates: test below, slow)."""
    shared_path("data", "motoshield", "aprbsResult.mat")
    cfg, cold = _cold(CONFIG, starts=1, candidates=[])
    assert cfg.identify.starts == 4 and cfg.identify.pso.pop_size == 20
    found = commission(cold, CONFIG.parent)
    assert found.data.t.size == 4801 and found.data.dropped == 0
    return cfg, found.result


@pytest.mark.slow  # about 22 s on the shared 2-core box: out of the fast lane
def test_identify_pastes_only_what_the_recording_determines(commissioned):
    """The filtered current does not determine the current pulse, the sensing's hypotheses,
    the dry friction or the warm-up: with every parameter free only Ke is within 10 %, and
    the report names the combinations. Held at the raw samples' values ([identify.fixed],
    their intervals propagated), Ra, Ke, J and D are determined within 10 % and only those
    are pasted; the warm-up, which nothing states, is named and not pasted."""
    cfg, r = commissioned
    a = r.identifiability
    assert a is not None and r.full is not None
    # all free (the figures): Ke +-8.1 %, the rest +-55 to 222 %, Ra +-118 %
    assert r.full.rel_std["Ke"] < 0.1
    assert all(0.5 < r.full.rel_std[n] < 2.5 for n in r.estimated if n != "Ke")
    assert a.rank == 11 and a.condition > 1e6 and a.determined_rank < 11
    # the weakest combination: the pulse's rise against the friction and the current's scale
    weakest = a.undetermined[0]
    assert weakest.std > 1.0 and abs(weakest.weights["tau_e"]) == 1.0
    pairs = {(x, y): rho for x, y, rho in a.strong_pairs}
    assert pairs[("Ra", "J")] < -0.95 and pairs[("Ra", "D")] < -0.95
    assert not a.at_bound
    # held at the stated values, with the reason; re-fitted: Ra, Ke, J, D within 10 %
    assert sorted(r.held) == ["Iq", "Tc", "a_adc", "tau_e"]
    for name, h in r.held.items():
        assert h.source == "[identify.fixed]" and h.value == cfg.identify.fixed[name].value
        assert "raw samples" in h.stated and h.why.startswith("in ")
        assert h.rel_std == cfg.identify.fixed[name].rel_std > 0
    assert sorted(r.determined) == ["D", "J", "Ke", "Ra"]
    assert all(r.rel_std[n] <= 0.1 for n in r.determined)
    # measured: Ra 82.3 +- 7.9 %, Ke 0.00421 +- 1.7 %, J 1.53e-8 +- 9.0 %, D 4.92e-8 +- 8.7 %
    assert r.values["Ra"] == pytest.approx(82.3, rel=0.02)
    assert r.values["Ke"] == pytest.approx(0.00421, rel=0.01)
    assert sorted(r.undetermined) == ["c_warm", "r_warm", "tau_warm"]
    assert all(r.rel_std[n] > 0.1 and "state a value of" in why
               for n, why in r.undetermined.items())
    # the block: exactly the determined ones (and Kt, tied to Ke); the others commented
    block = parameters_block(r, "the MotoShield recording")
    assert sorted(_pasted(block)) == ["D", "J", "Ke", "Kt", "Ra"]
    for name in [*r.held, *r.undetermined]:
        line = next(li for li in block.splitlines() if li.startswith(f"# {name} = "))
        assert "not determined" in line
    # the monitoring's baseline is what this command gives
    for name in r.determined:
        assert r.values[name] == pytest.approx(cfg.machine.parameters[name], rel=0.01), name
    text = report(r)
    assert "4 of 11 determined within 10 %" in text and "NOT DETERMINED" in text


def test_identify_beats_the_reference_on_the_held_out_half(commissioned):
    _, r = commissioned
    assert r.train.samples == 2400 and r.validation.samples == 2401
    full = r.full
    assert full is not None
    for out in ("omega", "ia"):
        # what is pasted (re-fitted with the held values) and the fit with all free
        for score in (r.validation, full.validation):
            held_out = score.fit_pct[out]
            assert held_out >= TARGET[out] and held_out > REFERENCE[out] + 10, (out, held_out)
        assert r.train.fit_pct[out] >= TARGET[out]
    # measured: all free 91.2 / 89.7 % speed, 51.9 / 53.3 % current (training / held out);
    # pasted 90.9 / 90.2 and 51.0 / 50.7
    assert full.validation.fit_pct["omega"] == pytest.approx(89.7, abs=1.0)
    assert full.validation.fit_pct["ia"] == pytest.approx(53.3, abs=1.0)
    assert r.validation.fit_pct["ia"] == pytest.approx(50.7, abs=0.5)
    # Both ranges are within the model error the monitoring accepts.
    assert r.train.check.passed and r.validation.check.passed
    # the information criteria of the fit with all free
    assert full.criteria.parameters == 12 and full.criteria.samples == 2399
    assert full.criteria.bic > full.criteria.aic


def test_monitoring_with_the_baseline_is_consistent_with_the_commissioning(commissioned):
    """The daemon on the recording with the identified baseline: every window processed and
    trusted; each parameter a window estimates differs from the commissioned value by less
    than two standard errors of the difference, and the window's own 2-sigma interval covers
    the commissioned value; the fused value ends within the commissioning's 2-sigma interval.
    (The commissioning's intervals are of the mean over 48 s given the held values: a 4 s
    window of a motor warming up moves by more than they, less than its own.)"""
    cfg, r = commissioned
    with Daemon(cfg, base_dir=CONFIG.parent, publish=False, record=False) as daemon:
        daemon.run()
        hist = list(daemon.history)
        counters = daemon.counters()
    assert len(hist) == 24
    assert counters["windows_abandoned"] == 0 and counters["numeric_failures"] == 0
    assert all(h["trusted"] for h in hist)
    counts = {}
    for name in cfg.estimation.estimate:
        base = cfg.machine.parameters[name]
        sigma = r.rel_std[name]
        est = [h["parameters"][name] for h in hist
               if h["parameters"][name]["status"] == "estimated"]
        counts[name] = len(est)
        for p in est:
            dev = abs(math.log(p["value"] / base))
            window = p["rel_std_pct"] / 100
            assert dev <= 2 * math.hypot(window, sigma), (name, p["value"], base, sigma)
            assert dev <= 2 * window, (name, p["value"], p["rel_std_pct"])
        fused = hist[-1]["parameters"][name]["fused"]
        assert abs(math.log(fused["value"] / base)) <= 2 * sigma
    # measured: Ke estimated in 22 windows (-4.9 .. +4.9 % of the baseline, fused -1.2 %),
    # D in 15 (-4.2 .. +3.6 %, fused +2.4 %), J in 1, Ra in none (fused +1.2 %)
    assert counts["Ke"] >= 18 and counts["D"] >= 8, counts
    ke = np.array([h["parameters"]["Ke"]["value"] for h in hist
                   if h["parameters"]["Ke"]["status"] == "estimated"])
    assert np.all(np.abs(ke / cfg.machine.parameters["Ke"] - 1) < 0.06)


@pytest.mark.slow
def test_the_raw_samples_determine_what_the_filtered_current_cannot(commissioned):
    """``config/dc-motor-motoshield-raw.toml`` (the raw ADC samples of the same recording,
    its four starts) determines tau_e and a_adc, which [identify.fixed] states for the
    filtered current with these values and intervals, and agrees with the filtered current's
    re-fit on Ra, Ke, J and D within one standard error of their difference."""
    shared_path("data", "motoshield", "aprbsResult.mat")
    _, filtered = commissioned
    _, cold = _cold(RAW)
    r = commission(cold, RAW.parent).result
    main = load_config(CONFIG)
    for name in ("tau_e", "a_adc"):
        assert name in r.determined
        stated = main.identify.fixed[name]
        assert r.values[name] == pytest.approx(stated.value, rel=1e-3)
        assert r.rel_std[name] == pytest.approx(stated.rel_std, rel=0.05)
    for name in ("Iq", "Tc"):  # stated with the raw samples' (wider) intervals
        assert r.rel_std[name] == pytest.approx(main.identify.fixed[name].rel_std, rel=0.05)
    # measured: Ra 83.7 +- 3.7 %, Ke 0.00420 +- 1.7 %, J 1.42e-8 +- 4.1 %, D 4.89e-8 +- 6.2 %
    for name in ("Ra", "Ke", "J", "D"):
        assert name in r.determined
        both = math.hypot(r.rel_std[name], filtered.rel_std[name])
        assert abs(math.log(r.values[name] / filtered.values[name])) <= both, name
    # measured: 59.5 / 62.4 % (raw) current, 90.2 / 90.1 % speed
    assert r.validation.fit_pct["ia"] > 60 and r.validation.fit_pct["omega"] > 85


@pytest.mark.slow
def test_candidate_structures_are_compared_on_board_1():
    """The config's candidates (no slow fall of the friction, no ADC-edge artefact) fit the
    held-out half worse and lose on BIC: the configured structure wins."""
    shared_path("data", "motoshield", "aprbsResult.mat")
    _, cold = _cold(CONFIG, starts=1)
    found = commission(cold, CONFIG.parent)
    comp = found.comparison
    assert comp is not None and len(comp.results) == 3
    assert comp.best.structure == AS_CONFIGURED and found.result is comp.best
    bic = {r.structure: r.full.criteria.bic for r in comp.results}
    assert bic[AS_CONFIGURED] == min(bic.values())
    n_p = {r.structure: r.full.criteria.parameters for r in comp.results}
    assert n_p == {AS_CONFIGURED: 12, "warm-up without its slow fall": 11,
                   "no ADC-edge artefact": 11}
    text = report(found.result, comp)
    assert "winner: as configured" in text


@pytest.mark.slow  # about 17 s on the shared 2-core box: out of the fast lane
def test_second_board_as_first_pointed_at_is_reported_honestly():
    """The example config pointed at the second recording as the issue did (board 1's
    firmware filter on this board's raw current; the speed scaled to rad/s): the current is
    fitted worse than its mean, so the model check fails whatever the residual tests say and
    nothing is pasted; the parameters the search left at a bound are flagged and held."""
    shared_path("data", "motoshield", "identification_data.mat")
    cfg, cold = _cold(BOARD2, starts=1, candidates=[])
    naive = next(c for c in cfg.identify.candidates if c.name == "board 1's current filter")
    cold = cold.model_copy(update={"machine": cold.machine.model_copy(update={
        "options": merge_options(cfg.machine.options, naive.options)})})
    r = commission(cold, BOARD2.parent).result
    # measured: -10.4 % training, -17.1 % validation (the issue: -11.5 / -18.2)
    assert r.train.fit_pct["ia"] < 0 and r.validation.fit_pct["ia"] < 0
    for score in (r.train, r.validation, r.full.train, r.full.validation):
        assert not score.check.passed
        assert any("ia fitted worse than its mean" in why for why in score.check.reasons)
    text = report(r)
    for what in ("training", "validation"):
        line = next(li for li in text.splitlines() if li.startswith(f"model check ({what})"))
        assert "FAILED" in line and "passed" not in line
    assert r.at_bound and all(r.held[n].source == "bound" for n in r.at_bound)
    assert all(f"AT A BOUND: {n}" in text for n in r.at_bound)
    block = parameters_block(r, "board 2")
    assert r.pasted == [] and _pasted(block) == {}
    assert "NOTHING TO PASTE" in block


@pytest.mark.slow
def test_second_board_adapted_config_wins_and_pastes_only_what_is_determined():
    """The adapted config's comparison: the structure as first pointed at the file cannot win
    (a negative fit); the adapted one wins; the parameters at a bound are flagged and held;
    only the determined ones are pasted."""
    shared_path("data", "motoshield", "identification_data.mat")
    cfg, cold = _cold(BOARD2, starts=1)
    found = commission(cold, BOARD2.parent)
    assert found.data.t.size == 4801
    comp = found.comparison
    assert comp is not None
    naive = next(r for r in comp.results if r.structure == "board 1's current filter")
    f = naive.full
    assert f is not None
    assert f.validation.fit_pct["ia"] < 0 and not f.validation.check.passed
    r = comp.best
    assert r is found.result and r.structure == AS_CONFIGURED
    # measured: 66.0 / 66.1 % current, 95.5 / 94.7 % speed
    assert r.validation.fit_pct["ia"] > 60 and r.validation.fit_pct["omega"] > 90
    assert r.validation.check.passed
    # a_adc and r_warm at their lower bounds: flagged and held there, not pasted
    assert r.at_bound == {"a_adc": "lower", "r_warm": "lower"}
    assert {n: h.source for n, h in r.held.items()} == {"a_adc": "bound", "r_warm": "bound"}
    block = parameters_block(r, "board 2")
    pasted = _pasted(block)
    assert set(pasted) == {*r.determined, "Kt"} and "Ke" in pasted
    assert all(r.rel_std[n] <= 0.1 for n in r.determined)
    assert not set(pasted) & {*r.held, *r.undetermined}
    # nothing is known about this motor: what the data do not pin is said, not pasted
    assert "Ra" in r.undetermined
