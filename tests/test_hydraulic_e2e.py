"""The hydraulic actuator (paper Sections 4.2, 5.3) end to end over Modbus, through the daemon.

simulated plant (Eq. 14-18, PID Eq. 17 every 1e-4 s) -> PlantModbusServer on 127.0.0.1 ->
Modbus TCP (or RTU over a pseudo-terminal pair) -> ModbusDriver -> ring buffer -> adaptation
worker (estimation, discovery) -> health messages. The daemon is the DC motor's, unchanged.
The assertions carry the paper's and the issue's numbers.

Run lengths are cut to what shows each claim (2 cores shared, the file well under 3 minutes);
each cut is stated where it is made. The full 600 s fluid-degradation run is measured in the
report of issue 4 (same figures).
"""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from twinwatch.config.loader import load_config
from twinwatch.config.schema import TwinwatchConfig
from twinwatch.daemon.runner import Daemon
from twinwatch.drivers.modbus import ModbusDriver, ModbusDriverConfig
from twinwatch.drivers.simulated_modbus import (
    DEFAULT_COUNTER,
    DEFAULT_REGISTERS,
    SimulatedModbusDriver,
    SimulatedModbusDriverConfig,
)
from twinwatch.plant.hydraulic import HydraulicPlant, HydraulicPlantConfig
from twinwatch.plant.modbus_server import PlantModbusServer, PtyLink

from .helpers.paths import ROOT

SIM = ROOT / "config" / "hydraulic-modbus-sim.toml"
LEAK = ROOT / "config" / "hydraulic-modbus-leak-sim.toml"

#: The reference 0.5 + 0.45 sin(2 pi 0.005 t) reverses (v = 0) at t = 50 + 100 n s.
REVERSALS = tuple(50.0 + 100.0 * n for n in range(6))


def _config(path: Path, **plant: Any) -> TwinwatchConfig:
    """The example config, its simulated device on a free port, no Zenoh, no recording."""
    cfg = load_config(path)
    assert isinstance(cfg.driver, SimulatedModbusDriverConfig)
    cfg.driver.port = 0  # any free port on 127.0.0.1
    for k, v in plant.items():
        setattr(cfg.driver.plant, k, v)
    return cfg


def _run(cfg: TwinwatchConfig) -> tuple[HydraulicPlant, Daemon]:
    assert isinstance(cfg.driver, SimulatedModbusDriverConfig)
    with SimulatedModbusDriver(cfg.driver) as driver:
        with Daemon(cfg, driver=driver, publish=False, record=False) as daemon:
            daemon.run()
    assert daemon.overruns == 0 and daemon.numeric_failures == 0
    # lock-step: every sample crossed Modbus exactly once, nothing lost. A request that timed out
    # on a loaded machine is retried after a reconnect (counted, not lost): the plant only
    # advances when its sample has been read, so the record stays whole either way.
    n = round(cfg.driver.plant.duration / cfg.driver.plant.sample_period)
    assert daemon.windows_estimated == n // cfg.acquisition.window
    assert driver.stats.samples >= n and driver.stats.gaps == 0
    assert driver.stats.errors == driver.stats.extra["timeouts"]
    assert driver.stats.bad_frames == 0 and driver.stats.bad_values == 0
    return driver.plant, daemon


def _touches_reversal(h: dict[str, Any]) -> bool:
    """The window holds a reversal (v = 0) or ends one sample before it."""
    return any(h["t_start"] - 0.015 <= r <= h["t_end"] + 0.015 for r in REVERSALS)


# -- fluid degradation (paper Section 5.3.1) ----------------------------------------------------


@pytest.mark.slow
def test_fluid_degradation_over_modbus_d_within_three_percent():
    """Paper: the estimated D follows the fluid degradation within 3 %, with spikes where the
    piston reverses. Cut: the ramp D(t) = 100 + 36.5 (exp(0.003 (t - t0)) - 1) starts at
    t0 = 0 s instead of 160 s and the run lasts 240 s (120 windows, 100 -> 138 N/(m/s), two
    reversals at 50 s and 150 s) instead of 600 s: the same ramp shape and the same number of
    reversals per window, without 160 s of fault-free plant first. Measured on the full 600 s
    run over Modbus: 220 of 220 windows from 160 s published, median error 0.003 %, max 0.12 %.

    Windows where the piston reverses give D little excitation (D*v is a fraction of a pascal):
    they are flagged and D is held there with the reason, rather than published. (Over Modbus
    the float32 pressure's 0.004 Pa resolution leaves a white residual, so the statistical gate
    alone would call D determined there; the twin's excitation test, RMS piston speed below
    ``min_speed``, is what holds it.) All windows count for the 95 %: a held value must still
    be within 3 % of the plant's D.
    """
    cfg = _config(SIM, duration=240.0, fault_start=0.0)
    plant, daemon = _run(cfg)
    hist = list(daemon.history)
    assert len(hist) == 120
    errors, held = [], []
    for h in hist:
        d = h["parameters"]["D"]
        true_d = plant.truth(0.5 * (h["t_start"] + h["t_end"])).D
        errors.append(abs(d["value"] / true_d - 1.0) * 100.0)
        if d["held"]:  # held or fused: not this window's estimate
            held.append(h)
            assert d["reason"]
            if d["status"] == "held":
                assert d["rel_std_pct"] is None
        if d["status"] == "estimated":
            assert d["rel_std_pct"] is not None and d["rel_std_pct"] <= 0.5  # max_rel_std
        if d["status"] == "fused":  # the fusion's own gate, [estimation.fusion] max_rel_std
            assert d["rel_std_pct"] is not None and d["rel_std_pct"] <= 2.0
    err = np.asarray(errors)
    # the paper's 3 % in at least 95 % of the windows, held ones included
    assert np.sum(err <= 3.0) >= 0.95 * len(hist), np.percentile(err, [50, 95, 100])
    published = np.asarray([e for e, h in zip(errors, hist, strict=True)
                            if not h["parameters"]["D"]["held"]])
    assert np.percentile(published, 95) < 0.1  # measured 0.03 %
    # the ramp really moved D (+38 %) and the twin followed it
    assert hist[-1]["parameters"]["D"]["value"] == pytest.approx(plant.truth(239.0).D, rel=0.01)
    assert plant.truth(239.0).D > 135.0
    # every window touching a reversal is flagged and held, with the excitation reason ...
    at_reversal = [h for h in hist if _touches_reversal(h)]
    assert at_reversal
    for h in at_reversal:
        d = h["parameters"]["D"]
        assert d["held"] and "too little excitation" in d["reason"], (h["t_start"], d)
    # ... and D is held only near the reversals (within 4 s), while q_pump is always estimated
    assert all(min(abs(0.5 * (h["t_start"] + h["t_end"]) - r) for r in REVERSALS) < 4.0
               for h in held)
    assert len(held) <= 0.1 * len(hist)
    # q_pump is estimated wherever the model check passed; where it failed (the window just
    # after a reversal), the window is not sound and q_pump is published fused or suspect
    assert all(h["parameters"]["q_pump"]["status"] == "estimated" for h in hist
               if h["model_check"]["passed"])
    assert all(h["parameters"]["q_pump"]["status"] in ("fused", "suspect") for h in hist
               if not h["model_check"]["passed"])


def test_windows_without_excitation_are_held_not_published():
    """The piston at rest (no reference motion: v = 0, D*v = 0) gives D no excitation at all:
    every window holds D with a reason and publishes q_pump, over the same Modbus path."""
    cfg = _config(SIM, duration=8.0, ref_frequency=0.0, scenario="nominal")
    _, daemon = _run(cfg)
    hist = list(daemon.history)
    assert len(hist) == 4
    for h in hist:
        d = h["parameters"]["D"]
        assert d["held"] and d["reason"] and d["rel_std_pct"] is None, d
        assert not h["parameters"]["q_pump"]["held"]


# -- internal leak and discovery (paper Section 5.3.2, Eq. 18-20) -------------------------------


def test_internal_leak_discovery_finds_the_pressure_term_of_0p2():
    """Eq. 18, C = 0.2: discovery keeps a multiplicative term on the pressure, p = (1 + U) p'
    (the paper's Eq. 20 prints p = p' - 0.19999991 p' in its own sign convention), whose
    coefficient is within 2 % of 0.2, and the pressure error of DT'' falls below 1 % of the
    pressure. Cut: the leak starts at 20 s instead of 160 s and the run lasts 50 s (the term is
    kept from 24 s: the 10 windows from 30 s on are checked)."""
    cfg = _config(LEAK, duration=50.0, fault_start=20.0)
    _, daemon = _run(cfg)
    hist = list(daemon.history)
    assert len(hist) == 25
    before = [h for h in hist if h["t_end"] < 20.0]
    assert before and all(not h["terms"] for h in before)
    after = [h for h in hist if h["t_start"] >= 30.0]  # 3 trigger windows + search after onset
    assert after
    for h in after:
        terms = [t for t in h["terms"] if t["attach"] == "p"]
        assert len(terms) == 1, h["terms"]
        term = terms[0]
        assert term["mode"] == "multiplicative"
        assert term["weight"] == pytest.approx(0.2, rel=0.02), term["equation"]
        # The term is a constant factor over the window (a power or linear meta-model whose
        # shape parameter is ~0): U stays within 2 % of 0.2 across the run.
        assert h["residual"]["dt_second"] is not None
        p_err = h["residual"]["dt_second"]["max_abs"]["p"]
        assert p_err / 50.0e3 < 0.01  # below 1 % of the pressure (>= 50 kPa; measured 1e-7)
    # the term has settled to a constant, read as the paper reads it: a leak
    (last,) = [t for t in after[-1]["terms"] if t["attach"] == "p"]
    assert last["equation"] == "p *= 1 + (0.20)", last["equation"]
    assert last["meaning"].startswith("constant on pressure: a steady gain (a leak")
    # without the term the twin is ~20 % off: the DT' residual shows the leak
    assert after[-1]["residual"]["dt_prime"]["max_abs"]["p"] > 0.15 * 50.0e3
    # the leak is not a fluid degradation: the plant's D never changes, and every D published
    # as this window's or the fused value stays within 3 % of it (issue 23; before the joint
    # refinement of the term, D was published +36 to +70 % after the discovery)
    _assert_d_is_the_plants(hist)


def _assert_d_is_the_plants(hist: list[dict[str, Any]]) -> None:
    worst = max(abs(h["parameters"]["D"]["value"] / 100.0 - 1.0) * 100.0 for h in hist
                if h["parameters"]["D"]["status"] in ("estimated", "fused"))
    assert worst < 3.0, worst


@pytest.mark.slow
def test_the_leak_example_publishes_the_plants_d_and_raises_no_fluid_alarm():
    """The shipped leak example as it is (leak from 160 s, 300 s): the leak is discovered
    (C within 1 % of 0.2), every published D is within 3 % of the plant's 100 N/(m/s) over the
    whole run (measured 0.26 % at worst; before: +36 to +70 % for 33 windows after the
    discovery at 186 s), and the fluid example's alarm rule on D (warning at +25 %) would
    raise nothing."""
    cfg = _config(LEAK)
    _, daemon = _run(cfg)
    hist = list(daemon.history)
    assert len(hist) == 150
    terms = [t for t in hist[-1]["terms"] if t["attach"] == "p"]
    assert len(terms) == 1 and terms[0]["weight"] == pytest.approx(0.2, rel=0.01)
    _assert_d_is_the_plants(hist)
    rule = load_config(SIM).alarms
    assert "D" in rule.parameters
    worst = max(h["parameters"]["D"]["deviation_pct"] for h in hist
                if h["parameters"]["D"]["status"] in ("estimated", "fused"))
    assert worst < rule.parameters["D"].warning_high  # no warning, let alone an alarm


# -- the data path: reconnects, RTU, the command line -------------------------------------------


@pytest.mark.slow
def test_realtime_modbus_server_restart_daemon_reconnects_and_reports_the_gap():
    """Real-time pacing over Modbus TCP on loopback: the Modbus server stops mid-run for 1.5 s
    and starts again on the same port. The daemon keeps running, the driver counts the outage
    and reconnects, the plant's clock ran on (the counter jumps: a gap of ~150 samples), the
    ring buffer abandons the window the gap falls in, and windows are estimated again.

    Measured (2 cores, loaded): down 1.6 s, 7 refused connects, 1 outage, 1 reconnect, ~187
    samples counted as gaps: ~150 from the outage, the rest real-time jitter (plant server, poll
    thread and estimator share one process and its GIL here; a late server tick serves only the
    latest sample)."""
    cfg = _config(SIM, duration=60.0, scenario="nominal")
    assert isinstance(cfg.driver, SimulatedModbusDriverConfig)
    cfg.driver.pacing = "realtime"
    cfg.driver.timeout = 0.3
    cfg.driver.backoff_max = 0.4
    # Plant server, poll thread and estimator share this process: the twin's compiled kernel
    # holds the GIL for a whole swarm call (~8 ms for 15 particles, near the 10 ms sample
    # period), and a late poll misses a sample, which abandons the window. A swarm of 5 keeps
    # the GIL holds short; this test is about the data path, not the estimate.
    cfg.estimation.pso.pop_size = 5
    cfg.estimation.pso.max_generations = 3
    errors: list[BaseException] = []
    with SimulatedModbusDriver(cfg.driver) as driver:
        assert driver.live
        with Daemon(cfg, driver=driver, publish=False, record=False) as daemon:

            def run() -> None:
                try:
                    daemon.run()
                except BaseException as exc:  # noqa: BLE001 - reported below
                    errors.append(exc)

            runner = threading.Thread(target=run, name="test-daemon-run")
            runner.start()
            try:
                _wait(lambda: daemon.windows_estimated >= 2, 45.0, lambda: daemon.counters())
                t_down = driver.server.last_sample.t  # type: ignore[union-attr]
                driver.server.stop()
                time.sleep(1.5)
                driver.server.start()  # same port
                t_back = driver.server.last_sample.t  # type: ignore[union-attr]
                # jitter on a loaded machine abandons some windows too: allow time for one
                _wait(lambda: any(h["t_start"] >= t_back for h in list(daemon.history)[-2:]),
                      45.0, lambda: daemon.counters())
            finally:
                daemon.stop()
                runner.join(15.0)
        assert not runner.is_alive() and not errors, errors
        stats = driver.stats.as_dict()
    assert stats["outages"] == 1 and stats["reconnects"] == 1
    assert stats["errors"] >= 1
    assert stats["gaps"] >= 100  # 1.5 s at 10 ms: ~150 samples not served
    c = daemon.counters()
    assert c["windows_abandoned"] >= 1 and c["numeric_failures"] == 0
    last = daemon.latest
    assert last is not None and last["t_start"] >= t_back
    # the gap is reported in the health message's counters
    hc = last["counters"]
    assert hc["driver_gaps"] >= 100 and hc["driver_reconnects"] == 1
    assert hc["windows_abandoned"] >= 1
    # no window spans the outage: the one it fell in was abandoned, not estimated
    assert not [h for h in daemon.history if h["t_start"] <= t_down and h["t_end"] >= t_back]
    assert not last["parameters"]["q_pump"]["held"]


def test_the_simulated_device_says_what_it_waits_for_while_it_does_not_answer():
    """The simulated Modbus plant reports what its Modbus driver reports (STATUS and the
    health message read ``waiting``): the device not answering while its server is stopped,
    nothing once it answers again."""
    cfg = _config(SIM, duration=20.0, scenario="nominal")
    assert isinstance(cfg.driver, SimulatedModbusDriverConfig)
    cfg.driver.timeout = 0.3
    cfg.driver.backoff_max = 0.4
    with SimulatedModbusDriver(cfg.driver) as driver:
        assert driver.read(5.0) is not None and driver.waiting is None
        driver.server.stop()
        _wait(lambda: driver.read(0.2) is None and driver.waiting is not None, 10.0,
              lambda: driver.stats.as_dict())
        assert "not answering" in str(driver.waiting)
        driver.server.start()  # same port
        _wait(lambda: driver.read(0.2) is not None and driver.waiting is None, 15.0,
              lambda: (driver.waiting, driver.stats.as_dict()))


def _wait(cond: Any, timeout: float, state: Any = None) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, f"timed out; {state() if state else ''}"
        time.sleep(0.05)


def test_modbus_rtu_over_a_pseudo_terminal_pair_through_the_daemon():
    """Modbus RTU (115200 baud 8N1, device 3) over a pty pair, lock-step, the default register
    map: three windows estimated, every sample delivered once."""
    cfg = _config(SIM, scenario="nominal")
    assert isinstance(cfg.driver, SimulatedModbusDriverConfig)
    plant = HydraulicPlant(HydraulicPlantConfig(scenario="nominal", duration=60.0))
    with PtyLink() as link:
        with PlantModbusServer(plant, DEFAULT_REGISTERS, counter=DEFAULT_COUNTER,
                               pacing="lockstep", serial_port=link.port_a, baudrate=115200,
                               device_id=3):
            rtu = ModbusDriverConfig(
                type="modbus", transport="rtu", serial_port=link.port_b, baudrate=115200,
                device_id=3, timeout=0.5, sample_period=0.01, time_source="counter",
                counter=DEFAULT_COUNTER, lockstep=True, registers=dict(DEFAULT_REGISTERS))
            with ModbusDriver(rtu) as driver:
                with Daemon(cfg, driver=driver, publish=False, record=False) as daemon:
                    daemon.run(duration=6.0)
                stats = driver.stats.as_dict()
    assert daemon.windows_estimated == 3
    assert stats["samples"] == 601 and stats["gaps"] == 0 and stats["errors"] == 0
    for h in daemon.history:
        assert h["parameters"]["D"]["value"] == pytest.approx(100.0, rel=0.03)
        assert h["parameters"]["q_pump"]["value"] == pytest.approx(0.02, rel=1e-4)


def _port_free(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) != 0


@pytest.mark.slow
def test_twinwatch_run_the_example_config_exits_0(tmp_path: Path):
    """``twinwatch run config/hydraulic-modbus-sim.toml --duration 20``, as a user runs it.
    If the example's ports (Modbus 5020, Zenoh 7448) are taken, a copy on free ports runs."""
    config = SIM
    if not (_port_free(5020) and _port_free(7448)):
        from twinwatch.plant.modbus_server import free_tcp_port

        text = SIM.read_text().replace("port = 5020", f"port = {free_tcp_port()}")
        text = text.replace("tcp/127.0.0.1:7448", f"tcp/127.0.0.1:{free_tcp_port()}")
        config = tmp_path / "hydraulic-modbus-sim.toml"
        config.write_text(text)
    exe = Path(sys.executable).parent / "twinwatch"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "twinwatch"]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([*cmd, "run", str(config), "--duration", "20", "--no-progress"],
                         cwd=tmp_path, env=env, capture_output=True, text=True, timeout=240)
    assert out.returncode == 0, out.stderr
    assert "10 windows estimated, 0 overruns, 0 windows abandoned" in out.stdout
    assert re.search(r"^  D +=", out.stdout, re.M) and "estimated" in out.stdout
    assert (tmp_path / "twinwatch-hydraulic.rrd").stat().st_size > 0
