"""A fleet staggers its machines' windows (``[acquisition] stagger``, issue 22): machines started
together would complete their windows at the same moment and wait for each other; each one's
first window is lengthened by a phase from its name, the next ones have the configured length,
and no sample is lost."""

from __future__ import annotations

from pathlib import Path

from twinwatch.config.loader import default_config
from twinwatch.daemon.acquisition import Acquisition
from twinwatch.twin.models import create_model


def _windows(name: str | None, seconds: float = 9.0) -> tuple[list[int], int, int]:
    cfg = default_config()
    cfg = cfg.model_copy(update={"driver": cfg.driver.model_copy(
        update={"plant": cfg.driver.plant.model_copy(update={"duration": seconds})})})
    model = create_model(cfg.machine.model, cfg.machine.options)
    acq = Acquisition(cfg, model, own_driver=True)
    phase = acq.stagger(name) if name is not None else 0
    acq.open(None, base_dir=Path.cwd(), wait=False)
    lengths: list[int] = []
    try:
        acq.run(None, lambda w, block: lengths.append(len(w.t)), lambda n: None)
    finally:
        acq.release()
    return lengths, phase, acq.ring.samples


def test_each_machine_s_first_window_is_longer_by_its_phase_and_nothing_is_lost() -> None:
    plain, _, n = _windows(None)
    assert set(plain) == {200} and len(plain) == n // 200
    phases = set()
    for name in ("press-1", "press-2", "lathe-7"):
        lengths, phase, n = _windows(name)
        phases.add(phase)
        assert 0 <= phase < 200
        assert lengths[0] == 200 + phase and set(lengths[1:]) == {200}, (name, lengths)
        # every sample is in a window but the last partial one
        assert n - sum(lengths) < 200
    assert len(phases) == 3  # the names spread the machines
    # the same name, the same phase (a restart keeps it)
    assert _windows("press-1")[1] == _windows("press-1")[1]


def test_each_machine_s_guard_swarm_comes_at_its_own_window() -> None:
    """Machines started together ran their guard swarm (every ``swarm_every`` windows) in the
    same window: with 200 machines about 200 swarms came due within 2 s every minute, and
    the windows behind them were up to 2.2 s late. In a fleet the first guard comes early by a
    phase from the machine's name, then every ``swarm_every`` windows as before."""
    import itertools
    import zlib

    from twinwatch.plant.dcmotor import DCMotorPlantConfig
    from twinwatch.twin.estimation.estimator import EstimationConfig, Estimator
    from twinwatch.twin.models.dcmotor import DCMotorTwin

    from .helpers.plant import plant_windows

    _, wins = plant_windows(DCMotorPlantConfig(noise={"ia": 0.5, "omega": 0.5}), 16)
    phases = {}
    for name in ("press-1", "lathe-7", None):
        est = Estimator(DCMotorTwin(), EstimationConfig(swarm_every=8))
        phase = est.stagger_guard(name) if name is not None else 0
        if name is not None:
            assert phase == zlib.crc32(name.encode()) % 8
        reasons = [est.estimate(w).search_reason for w in wins]
        guards = [k for k, why in enumerate(reasons) if why == "guard"]
        assert reasons[0] == "start"
        # the first guard at window 8 - phase (none before), then every 8 windows
        assert guards[0] == 8 - phase and all(b - a == 8 for a, b in itertools.pairwise(guards))
        phases[name] = phase
    assert phases["press-1"] != phases["lathe-7"]
