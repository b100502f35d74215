"""A kept meta-model term is refined on the evidence of every window it has explained (issue 9
item 5, "Done when": the unbalanced shaft with 1 % noise and an unbalance unlike the paper's).

One 2 s window pins a periodic term's frequency to about 1 % on noisy data, so a term re-fitted
on each window alone jitters by that much. Combined across windows (an information-weighted
estimate, frequency and phase jointly in absolute time), the frequency's precision grows with
the time span explained: after 30 windows it is within 0.1 % and the amplitude within 2 %, and
the published intervals (``params_std``) cover the truth.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from twinwatch.config.loader import load_config
from twinwatch.plant.dcmotor import DCMotorPlantConfig
from twinwatch.twin.adaptation import TwinAdapter
from twinwatch.twin.discovery.metamodels import get_meta_model
from twinwatch.twin.discovery.search import RefinementConfig
from twinwatch.twin.discovery.terms import Term
from twinwatch.twin.models.dcmotor import DCMotorTwin

from .helpers.paths import ROOT
from .helpers.plant import plant_windows

CONFIG = ROOT / "config" / "dc-motor-unbalanced-sim.toml"
#: Unlike the paper's 5 rad/s^2 at 10 rad/s.
AMPLITUDE, FREQUENCY = 3.0, 7.0


def _run(n_windows: int, refinement: RefinementConfig | None = None
         ) -> tuple[list[list[Term]], TwinAdapter]:
    cfg = load_config(CONFIG)
    disc = cfg.discovery
    if refinement is not None:
        disc = disc.model_copy(update={"refinement": refinement})
    twin = DCMotorTwin(**cfg.machine.options)
    adapter = TwinAdapter(twin, cfg.estimation, disc)
    _, wins = plant_windows(DCMotorPlantConfig(
        scenario="unbalanced_shaft", duration=2.0 * n_windows + 5,
        unbalance_amplitude=AMPLITUDE, unbalance_frequency=FREQUENCY,
        noise={"ia": 1.0, "omega": 1.0}, seed=11), n_windows)
    history = []
    for w in wins:
        history.append([Term.from_dict(t.state_dict(), twin) for t in adapter.process(w).terms])
    return history, adapter


def test_unbalanced_shaft_term_converges_with_intervals_that_cover_the_truth() -> None:
    history, adapter = _run(34)
    first = next(k for k, terms in enumerate(history) if terms)
    assert first <= 4  # found after the K = 3 windows whose residual stays too large
    assert all(len(terms) == 1 and terms[0].meta.kind == "periodic" for terms in history[first:])
    (term,) = history[-1]
    d = term.as_dict()
    assert len(history) - first >= 30 and d["evidence_windows"] >= 29
    a, b, c = term.params[:3]
    sd = d["params_std"]
    # after 30 windows: frequency within 0.1 %, amplitude within 2 %
    assert abs(b - FREQUENCY) / FREQUENCY < 1e-3
    assert abs(a - AMPLITUDE) / AMPLITUDE < 0.02
    # ... and the 2-sigma intervals cover the truth (the plant's forcing is 3*sin(7*t + 0))
    assert abs(b - FREQUENCY) <= 2 * sd["b"] and abs(a - AMPLITUDE) <= 2 * sd["a"]
    assert abs(math.remainder(c, 2 * math.pi)) <= 2 * sd["c"]
    # the intervals are not vacuous: the frequency is known to better than 0.05 %
    assert sd["b"] / FREQUENCY < 5e-4 and sd["a"] / AMPLITUDE < 0.01
    # the phase carries from window to window: the term is the plant's forcing in absolute time
    t = np.linspace(60.0, 70.0, 1000)
    truth = AMPLITUDE * np.sin(FREQUENCY * t)
    assert np.max(np.abs(term.meta.evaluate(term.params, t)[0] - truth)) < 0.05 * AMPLITUDE
    # the frequency converges instead of jittering: the last ten windows agree within 0.02 %
    late = np.array([h[0].params[1] for h in history[-10:]])
    assert np.ptp(late) / FREQUENCY < 2e-4
    # the refined state survives a restart (TwinAdapter.state / restore)
    other = TwinAdapter(adapter.model, adapter.estimator.config, adapter.config)
    other.restore(adapter.state())
    assert other.terms[0].as_dict() == adapter.terms[0].as_dict()
    np.testing.assert_array_equal(other.terms[0].refinement.cov,  # type: ignore[union-attr]
                                  adapter.terms[0].refinement.cov)  # type: ignore[union-attr]


def test_without_refinement_each_window_re_fits_and_the_frequency_jitters() -> None:
    """The same run re-polished on each window alone (``enabled = false``): the frequency
    wanders by about 1 % from window to window, the intervals are one window's."""
    history, _ = _run(12, RefinementConfig(enabled=False))
    kept = [h[0] for h in history if h]
    assert len(kept) >= 8
    freqs = np.array([t.params[1] for t in kept])
    assert np.ptp(freqs) / FREQUENCY > 5e-3
    assert all(t.as_dict()["evidence_windows"] == 1.0 for t in kept)


# -- the refinement's arithmetic, on a term of a channel ------------------------------------
def _const_term() -> Term:
    twin = DCMotorTwin()
    return Term(get_meta_model("linear"), twin.attach_point("d(omega)/dt"), "omega",
                np.array([0.0, 1.0]), (False, True))


def test_refinement_is_the_information_weighted_mean_and_a_window_counts_once() -> None:
    term = _const_term()
    rng = np.random.default_rng(0)
    ys = 1.0 + 0.1 * rng.standard_normal(50)
    for k, y in enumerate(ys):
        term.refine(np.array([0.0, y]), np.array([[0.01]]), None, 2.0 * k, k,
                    memory=1e9, jump_threshold=25.0)
        if k == 10:  # a second polish of the same window replaces its evidence
            term.refine(np.array([0.0, y]), np.array([[0.01]]), None, 2.0 * k, k,
                        memory=1e9, jump_threshold=25.0)
    assert term.params[1] == pytest.approx(np.mean(ys), abs=1e-9)
    assert term.params_std[0] == pytest.approx(0.1 / math.sqrt(50), rel=1e-6)  # type: ignore[index]
    assert term.refinement.windows == pytest.approx(50.0)  # type: ignore[union-attr]


def test_refinement_forgets_holds_out_a_transient_and_follows_a_change() -> None:
    """Forgetting bounds the evidence (about memory / window length windows). A window far
    outside the refined interval is held out (a transient); a second one in a row that agrees
    with it is a change, and the term follows it at once."""
    term = _const_term()

    def feed(k: int, y: float) -> None:
        term.refine(np.array([0.0, y]), np.array([[0.01]]), None, 2.0 * k, k,
                    memory=60.0, jump_threshold=25.0)

    for k in range(200):
        feed(k, 1.0)
    assert term.refinement.windows == pytest.approx(1 / (1 - math.exp(-2 / 60)), rel=0.01)  # type: ignore[union-attr]
    feed(200, 3.0)  # one transient window: held out
    assert term.params[1] == pytest.approx(1.0)
    feed(201, 1.0)
    assert term.params[1] == pytest.approx(1.0)
    feed(202, 2.0)  # a change: the first window is held out, the second agrees with it
    assert term.params[1] == pytest.approx(1.0)
    feed(203, 2.0)
    assert term.params[1] == pytest.approx(2.0)
    assert term.refinement.windows == 2.0  # type: ignore[union-attr]


def test_a_term_restored_from_its_health_entry_restarts_from_its_intervals() -> None:
    """From ``as_dict`` alone (no correlations), the refinement restarts from the published
    standard errors; from ``state_dict``, exactly where it was."""
    twin = DCMotorTwin()
    term = Term(get_meta_model("periodic"), twin.attach_point("d(omega)/dt"), "t",
                np.array([3.0, 7.0, 0.5, 0.0]), (True, True, True, False))
    cov = np.diag([1e-4, 1e-6, 1e-4])
    term.refine(np.array([3.0, 7.0, 0.5 + 7.0 * 100.0, 0.0]), cov, 100.0, 100.0, 50,
                memory=600.0, jump_threshold=25.0)
    assert term.params[2] == pytest.approx(0.5)  # published in absolute time
    sd = term.as_dict()["params_std"]
    # the local phase at t = 100 s has std 0.01; in absolute time 0.01 + 100 * 0.001
    assert sd["c"] == pytest.approx(math.hypot(0.01, 100 * 1e-3), rel=1e-6)
    exact = Term.from_dict(term.state_dict(), twin)
    assert exact.as_dict() == term.as_dict()
    approx = Term.from_dict(term.as_dict(), twin)
    assert approx.as_dict()["params_std"] == pytest.approx(sd)
    assert approx.refinement is not None and approx.refinement.origin == 0.0
