"""Ring buffer and adaptation worker: windows, gaps, NaN, overruns, contained failures."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from twinwatch.config.loader import default_config
from twinwatch.daemon.ringbuffer import RingBuffer
from twinwatch.daemon.runner import Daemon
from twinwatch.drivers.base import Driver, EndOfStream
from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig

CH = ("a", "b")


def _feed(rb: RingBuffer, ts, bad_at=()):
    wins = []
    for k, t in enumerate(ts):
        v = {"a": float(k), "b": math.nan if k in bad_at else 2.0 * k}
        w = rb.append(t, v)
        if w is not None:
            wins.append(w)
    return wins


def test_ring_buffer_cuts_consecutive_windows():
    rb = RingBuffer(CH, window=10, sample_period=0.01, capacity=25)
    wins = _feed(rb, np.arange(55) * 0.01)
    assert [w.index for w in wins] == [0, 1, 2, 3, 4]
    for j, w in enumerate(wins):  # the ring wraps (capacity 25) without mixing samples
        np.testing.assert_array_equal(w["a"], np.arange(10 * j, 10 * j + 10))
        np.testing.assert_allclose(w.t, np.arange(10 * j, 10 * j + 10) * 0.01)
    assert sum(rb.discarded.values()) == 0


def test_gap_nan_and_backwards_time_abandon_the_partial_window(caplog):
    rb = RingBuffer(CH, window=10, sample_period=0.01)
    t = list(np.arange(15) * 0.01) + list(0.5 + np.arange(30) * 0.01)  # gap after 15
    wins = _feed(rb, t, bad_at={25})  # NaN in the second stretch
    # 15 samples: one window + 5 abandoned by the gap; then 10 good, NaN abandons 0 (window
    # just completed), then 19 samples -> one window + 9 pending.
    assert rb.discarded["time stamp gap"] == 1
    assert rb.bad_samples == 1
    assert len(wins) == 3
    for w in wins:  # no window straddles a gap or holds a NaN
        assert np.all(np.diff(w.t) < 0.015) and np.all(np.isfinite(w["b"]))
    assert sum("time stamp gap" in r.message for r in caplog.records) == 1  # logged once
    rb.append(0.0, {"a": 0.0, "b": 0.0})  # jump backwards
    assert rb.discarded["time stamp jumped backwards"] == 1


def test_a_nan_or_inf_time_stamp_is_a_bad_sample_not_a_window_sample(caplog):
    """A stamp that is not a number (a decoder's NaN, an inf) has no slot on the grid: the
    sample is counted bad, the partial window abandoned (logged once), and the windows after
    it are whole and finite."""
    rb = RingBuffer(CH, window=10, sample_period=0.01)
    ts = list(np.arange(45) * 0.01)
    ts[5], ts[27] = math.nan, math.inf
    wins = _feed(rb, ts)
    assert rb.bad_samples == 2 and rb.causes["bad_value"] == 2
    assert [len(w.t) for w in wins] == [10, 10, 10]   # 6-15, 16-25, 28-37
    for w in wins:
        assert np.all(np.isfinite(w.t)) and np.all(np.diff(w.t) < 0.015)
    assert sum("time stamp NaN or inf" in r.message for r in caplog.records) == 1


class _PlantDriver(Driver):
    """The plant without a bus, as a *live* source that cannot wait."""

    live = True
    channels = ("Va", "ia", "omega", "Tload", "setpoint")

    @classmethod
    def from_config(cls, config, *, base_dir=None):  # type: ignore[no-untyped-def]
        raise NotImplementedError("built by the test, not from a configuration")

    def __init__(self, duration: float, nan_at: float | None = None,
                 pace: float = 0.0) -> None:
        super().__init__()
        self.plant = DCMotorPlant(DCMotorPlantConfig(scenario="nominal", duration=duration))
        self.nan_at = nan_at
        self.pace = pace  # wall seconds per sample (0: as fast as the plant runs)
        self.finished = threading.Event()

    def _read_internal(self, timeout):
        if self.pace:
            time.sleep(self.pace)
        try:
            s = self.plant.next_sample()
        except EndOfStream:
            self.finished.set()
            raise
        if self.nan_at is not None and abs(s.t - self.nan_at) < 1e-9:
            s.values["ia"] = math.nan
        return s


def test_live_source_counts_overruns_and_never_drops_silently(caplog):
    cfg = default_config()
    cfg.acquisition.queue = 1
    driver = _PlantDriver(duration=20.0)
    with Daemon(cfg, driver=driver, publish=False, record=False) as daemon:
        orig = daemon.process_window

        def slow(window):  # the estimator stalls until acquisition has finished
            driver.finished.wait(timeout=30)
            return orig(window)

        daemon.process_window = slow  # type: ignore[method-assign]
        daemon.run()
    driver.close()
    assert daemon.ring.windows == 10
    assert daemon.overruns > 0
    assert daemon.windows_estimated + daemon.overruns == 10
    said = [r for r in caplog.records if "estimation overrun" in r.message]
    # said once (and again at the 10th, 100th, ...), counted in every window
    assert daemon.overruns >= 2 and len(said) == 1, (daemon.overruns, len(said))
    assert daemon.latest is not None and daemon.latest["counters"]["overruns"] >= 0


def test_a_failing_window_is_contained_and_counted():
    cfg = default_config()
    driver = _PlantDriver(duration=8.0)
    with Daemon(cfg, driver=driver, publish=False, record=False) as daemon:
        orig = daemon.estimator.estimate
        calls = []

        def flaky(window, terms=None, **kwargs):
            calls.append(window.index)
            if window.index == 1:
                raise FloatingPointError("simulated numeric failure")
            return orig(window, terms, **kwargs)

        daemon.estimator.estimate = flaky  # type: ignore[method-assign]
        daemon.run()
    driver.close()
    assert calls == [0, 1, 2, 3]
    assert daemon.numeric_failures == 1
    assert [h["window"] for h in daemon.history] == [0, 2, 3]


def test_nan_sample_is_never_estimated():
    cfg = default_config()
    driver = _PlantDriver(duration=8.0, nan_at=3.0)
    with Daemon(cfg, driver=driver, publish=False, record=False) as daemon:
        daemon.run()
    driver.close()
    assert daemon.ring.bad_samples == 1
    assert daemon.counters()["windows_abandoned"] == 1
    assert all(np.isfinite(h["nrmse"]) for h in daemon.history)
    # [0, 2) s, then [2, 3) s abandoned at the NaN, then [3.01, 5.01) and [5.01, 7.01) s
    assert [h["t_start"] for h in daemon.history] == pytest.approx([0.0, 3.01, 5.01])


def test_an_overrun_caused_by_a_slow_output_names_it(caplog, monkeypatch):
    """Issue 26 item 4: an overrun names its real cause. An output that holds every window
    (here until acquisition has ended) fills the outputs' queue; the estimation then waits
    and the live source's windows overflow: the message names that output, not
    ``max_generations`` (which it advised before, whatever the cause)."""
    from twinwatch.daemon import pipeline
    from twinwatch.sinks.base import Sink, SinkConfig

    monkeypatch.setattr(pipeline, "OUTPUT_QUEUE", 1)
    cfg = default_config()
    cfg.acquisition.queue = 1
    # a window every 0.1-0.2 s of wall time: the source still delivers once the output holds
    # the worker (unpaced, a 3 ms estimation let the whole source end during the first
    # window, every overrun the estimation's own)
    driver = _PlantDriver(duration=20.0, pace=0.0005)

    class Slow(Sink):
        config_class = SinkConfig
        role = "publisher"

        @classmethod
        def from_config(cls, config, context):  # type: ignore[no-untyped-def]
            return cls()

        def write(self, out):  # type: ignore[no-untyped-def]
            driver.finished.wait(timeout=30)

        def close(self) -> None:
            self._closed = True

    slow = Slow()
    slow.name = "slowpoke"
    with Daemon(cfg, driver=driver, publish=False, record=False) as daemon:
        daemon.pipeline.sinks = [slow]
        daemon.run()
    driver.close()
    overruns = [r.message for r in caplog.records if "estimation overrun" in r.message]
    assert daemon.overruns > 0 and overruns
    # the plant runs faster than real time: the first overruns are the estimation's own;
    # once the output holds the worker, they name it
    named = [m for m in overruns if "slowpoke output" in m]
    assert named and not any("max_generations" in m for m in named), overruns
    assert "max_generations" not in overruns[-1], overruns
