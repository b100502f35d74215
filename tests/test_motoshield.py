"""The DC motor twin on a real recording: AutomationShield MotoShield, aprbsResult.mat
(../shared/data/motoshield, CC BY-NC-ND 4.0, read in place), through
config/dc-motor-motoshield.toml and the file driver."""

from __future__ import annotations

import numpy as np
import pytest

from twinwatch.config.loader import load_config
from twinwatch.daemon.runner import Daemon

from .helpers.paths import ROOT, shared_path


def test_motoshield_pwm_twin_passes_the_model_check_and_tracks_ke_in_every_window():
    shared_path("data", "motoshield", "aprbsResult.mat")
    cfg_path = ROOT / "config" / "dc-motor-motoshield.toml"
    cfg = load_config(cfg_path)
    with Daemon(cfg, base_dir=cfg_path.parent, publish=False, record=False) as daemon:
        daemon.run()
        hist = list(daemon.history)
        counters = daemon.counters()
    # 4801 samples at 0.02 s in windows of 200: 24 windows, none lost, none failed.
    assert len(hist) == 24
    assert counters["numeric_failures"] == 0 and counters["windows_abandoned"] == 0
    # The PWM twin with the identified baseline describes the motor to the commissioning's model
    # error in every window (the linear twin failed the check in every window: issue 9), so
    # every window is trusted, and nothing is published as an estimate above the 10 % gate.
    for h in hist:
        assert h["model_check"]["passed"] and h["trusted"], h["model_check"]["reasons"]
        for p in h["parameters"].values():
            assert p["status"] != "estimated" or p["rel_std_pct"] <= \
                cfg.estimation.max_rel_std * 100
    # Ke (the speed's gain) is determined by most 4 s windows (21 of 24 measured).
    assert sum(h["parameters"]["Ke"]["status"] == "estimated" for h in hist) >= 18
    nrmse = np.array([h["nrmse"] for h in hist])
    assert np.all(np.isfinite(nrmse)) and np.max(nrmse) < 0.03  # linear twin: median 0.13
    for h in hist:
        assert set(h["rmse"]) == {"ia", "omega"}
        for p in h["parameters"].values():
            assert p["value"] > 0  # every published parameter is physical
    # The diagnosis (the dc_motor_pwm library) on the healthy motor warming from a cold start:
    # no part named with confidence in any window. The field's constant Ke moves about -2 % over
    # the recording (a ferrite magnet loses about 0.2 %/K as the motor warms): the windows after
    # the baseline read a change the data split between the magnets and the speed reading
    # (measured: at most 0.55, 0.46 at the end; docs/diagnosis.md, "Limits").
    for h in hist:
        d = h["diagnosis"]
        assert d["library"] == "dc_motor_pwm (shipped)", d
        assert all(f["probability"] < 0.8 for f in d["faults"]), d


@pytest.mark.slow
def test_motoshield_discovery_fit_first_half_validate_second():
    """Issue 9 item 5 on real data: discovery runs on the windows of the first half (forced:
    the linear twin's residual is always 'too large' here) with the config's candidates, the
    six of Table 1 and the terms real drives need (a rectifier and a dead zone of the voltage, a
    rectifier of the speed for a current that cannot reverse, Coulomb friction, saturation),
    with a budget that lets it try every candidate; whatever it keeps is frozen, with the
    first half's median parameters, and scored on the second half against the physical twin
    alone. Finding (README): no candidate earns its place; each search says so, naming the
    closest candidate and the criteria it fails."""
    shared_path("data", "motoshield", "aprbsResult.mat")
    cfg_path = ROOT / "config" / "dc-motor-motoshield-linear.toml"
    cfg = load_config(cfg_path)
    kinds = {k for c in cfg.discovery.candidates for k in c.kinds}
    assert {"rectifier", "dead_zone", "coulomb", "saturation"} <= kinds
    disc = cfg.discovery.model_copy(update={"enabled": True, "trigger_windows": 1,
                                            "retry_after": 1, "time_budget": 120.0})
    # no wall-clock cap on the estimation either: the run is the same on a loaded machine
    est = cfg.estimation.model_copy(update={"time_budget": 60.0})
    cfg = cfg.model_copy(update={"discovery": disc, "estimation": est})
    with Daemon(cfg, base_dir=cfg_path.parent, publish=False, record=False) as daemon:
        windows = []
        reports = []
        orig = daemon.process_window
        search = daemon.adapter.discovery
        assert search is not None
        orig_discover = search.discover

        def discover(*args, **kwargs):  # type: ignore[no-untyped-def]
            out = orig_discover(*args, **kwargs)
            reports.append(out[1])
            return out

        search.discover = discover  # type: ignore[method-assign]

        def capture(w):  # type: ignore[no-untyped-def]
            windows.append(w)
            if w.index >= 12:  # the second half is held out: no adaptation
                return None
            return orig(w)

        daemon.process_window = capture  # type: ignore[method-assign]
        daemon.run()
        first = list(daemon.history)
        adapter = daemon.adapter
    assert len(first) == 12 and len(windows) == 24
    assert len(reports) >= 6  # the search really ran on every other window of the first half
    n_candidates = sum(len(c.kinds) for c in cfg.discovery.candidates)
    for rep in reports:
        # every candidate was fitted (a second round, after a kept term, tries the others again)
        assert rep.candidates == n_candidates and rep.tried >= n_candidates
    model = adapter.model
    theta = np.median([[h["parameters"][n]["value"] for n in model.parameter_names]
                       for h in first], axis=0)
    ever = [t for h in first for t in h["terms"]]

    def nrmse(w, terms) -> float:  # type: ignore[no-untyped-def]
        from twinwatch.twin.discovery.terms import Term, compose

        objs = [Term.from_dict(t, model) for t in terms]
        fit = adapter.estimator.window_fit(w)
        y = fit.simulate(theta[None], compose(objs, w) if objs else None)[0]
        return fit.residual(y).nrmse

    held_out = windows[12:]
    without = np.median([nrmse(w, []) for w in held_out])
    assert 0.05 < without < 0.25  # the physical twin alone: ~0.13 (README)
    if ever:  # what was kept must explain the held-out half too, else it was fitting noise
        with_term = np.median([nrmse(w, ever[-1:]) for w in held_out])
        assert with_term < without * 0.9, (ever[-1]["equation"], with_term, without)
    else:  # nothing kept: the search says plainly that no meta-model it knows fits
        for rep in reports:
            assert rep.verdict.startswith(
                f"no candidate meta-model earns its place ({n_candidates} of {n_candidates} "
                "tried); closest: "), rep.verdict
            assert "standard errors from zero (needs 5)" in rep.verdict
