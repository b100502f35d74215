"""The held-out validation set of issue 55 (item 8): the frozen case table, and per case the
recording and the configuration a plant engineer would write.

**Frozen.** Never change a case, a size, an onset, a seed, a plant or a configuration below
after the freeze commit (README.md beside this file); a new case goes in a new dated table
(a new ``TABLE_<date>`` list and its own name prefix), never an edit. The set's value is that
nothing in the twin was built from it.

Plants (:mod:`benchmarks.heldout.plants`): ``pm`` the paper's motor, ``ind`` an industrial
60 V motor (tau_e 1 ms), ``srvS`` a small servo (tau_e 2 ms), ``srvM`` a mid servo (tau_e
10 ms), ``pwm`` a motor on a 3.9 kHz H-bridge, ``hyd`` the paper's hydraulic actuator. Sizes
are not the tuning set's (benchmarks/bench_diagnosis.py: Ra -4/-12/+4/+12 %, D +8/+25 %, Ke
-3/-10 %, J +15/+50 %, Tc 0.002/0.006 N m, leak 0.05/0.2, q_pump -3/-10 %), noise seeds are
101 and up (the tuning set's: 0, 3, 7).

Each :class:`Case` names what is acceptable at the end (``accept``), what is not wrong while
the fault acts (``tolerate``), the outcome present for the Brier score (``truth``; a mode the
library lacks counts as ``unknown``) and, through :meth:`Case.true_parameters`, the plant's
true parameter values at any time by the twin's parameter names (for interval coverage).
Fault ids are the shipped libraries' (twinwatch/twin/diagnosis/library/*.toml).

Each plant's configuration (:func:`config_toml`) is what an engineer would write for it: the
file driver on the recording, 10 ms samples, 200-sample windows, the twin with the nameplate
as the maker states it (on ``ind``, ``srvM`` and ``pwm`` a few % from the plant's truth:
manufacturing tolerance), ``closed_loop`` with the drive described on the paper's motor (as
the shipped sim configuration does) and ``open_loop`` on the measured voltage elsewhere (the
drive unknown), estimation and discovery as the shipped DC motor and hydraulic configurations
have them (config/dc-motor-unbalanced-sim.toml with the dead-zone and Coulomb candidates
benchmarks/bench_diagnosis.py adds; config/hydraulic-modbus-leak-sim.toml), diagnosis and
prognostics at their defaults, no Zenoh, no recording.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmarks.heldout.plants import (
    PLANTS,
    SAMPLE_PERIOD,
    Array,
    Change,
    DCPlant,
    Scenario,
    SensorFault,
    log_channels,
)

#: The table's date: the freeze.
TABLE = "2026-11-27"
#: Plant time of a faulted run and of a nominal run [s].
DURATION = 200.0
NOMINAL_DURATION = 300.0

#: Answers acceptable at the end of a sensor, supply or off-library case besides its own mode.
SENSOR_OK = ("unknown", "check_function")

#: Channels the controller reads (their sensor faults change the plant): the speed loop's
#: speed, the valve loop's position.
LOOP_CHANNELS = {"dc": ("omega",), "hyd": ("x",)}


# -- the engineers' configurations ------------------------------------------------------------

@dataclass(frozen=True)
class TwinSetup:
    """What the engineer writes for one plant.

    Attributes:
        nameplate: [machine.parameters], the maker's values.
        options: [machine.options] (a ``drive`` table as a nested dict).
        estimate: [estimation] estimate, in priority order.
        bounds: [estimation] bounds.
        columns: the twin's channels (the CSV's columns by the same names) and units.
        noisy: the measured channels (noise goes on these; commands and references are
            exact).
        candidates: [[discovery.candidates]] as (attach, input, kinds, amplitude).
    """

    nameplate: Mapping[str, float]
    options: Mapping[str, object]
    estimate: tuple[str, ...]
    bounds: Mapping[str, tuple[float, float]]
    columns: Mapping[str, str]
    noisy: tuple[str, ...]
    candidates: tuple[tuple[str, str, tuple[str, ...], float], ...]


_TABLE1 = ("linear", "exponential", "negative_exponential", "power", "logarithmic",
           "periodic")


def _dc_bounds(nameplate: Mapping[str, float]) -> dict[str, tuple[float, float]]:
    """Bounds around the nameplate with the shipped configuration's margins (Ra 0.15-4.6x, D
    0.07-7x, Ke 0.26-2.6x, La 0.15-4.5x, J 0.085-8.5x), to 3 significant digits."""
    f = {"Ra": (0.15, 4.6), "D": (0.07, 7.0), "Ke": (0.26, 2.6), "La": (0.15, 4.5),
         "J": (0.085, 8.5)}
    return {k: (float(f"{nameplate[k] * lo:.3g}"), float(f"{nameplate[k] * hi:.3g}"))
            for k, (lo, hi) in f.items()}


def _dc_candidates(omega_dot: float, ia_dot: float) -> tuple[tuple[str, str, tuple[str, ...],
                                                                   float], ...]:
    """Table 1 on the shaft's equation, a dead zone of the voltage on the current's, a
    Coulomb friction on the shaft's; amplitudes: the largest plausible term [rad/s^2, A/s]."""
    return (("d(omega)/dt", "t", _TABLE1, omega_dot),
            ("d(ia)/dt", "Va", ("input_dead_zone",), ia_dot),
            ("d(omega)/dt", "omega", ("coulomb",), omega_dot))


def _dc_setup(plant: DCPlant, nameplate: Mapping[str, float], options: Mapping[str, object],
              omega_dot: float, ia_dot: float) -> TwinSetup:
    cols = {"Va": "V", "ia": "A", "omega": "rad/s"}
    if options.get("structure") == "closed_loop":
        cols["setpoint"] = "rad/s"
    if options.get("load") == "measured":
        cols["Tload"] = "N m"
    noisy = ("ia", "omega") + (("Tload",) if "Tload" in cols else ())
    return TwinSetup(nameplate=dict(nameplate), options=dict(options),
                     estimate=("Ra", "D", "Ke", "La", "J"), bounds=_dc_bounds(nameplate),
                     columns=cols, noisy=noisy, candidates=_dc_candidates(omega_dot, ia_dot))


_PM_NAMEPLATE = {"Ra": 6.5, "La": 0.673, "J": 0.001171, "Ke": 0.038, "Kt": 0.038,
                 "D": 0.00143}

SETUPS: dict[str, TwinSetup] = {
    # the paper's motor: its drive is described (as config/dc-motor-sim.toml does, with the
    # drive's period, limits and integrator as this drive runs them); nameplate exact
    "pm": _dc_setup(
        PLANTS["pm"], _PM_NAMEPLATE,  # type: ignore[arg-type]
        {"structure": "closed_loop", "load": "viscous", "load_coefficient": 0.006,
         "sub_step": 1e-4,
         "drive": {"period": 0.001,
                   "speed": {"kp": 0.3, "ki": 0.1, "output_min": -48.0, "output_max": 48.0,
                             "anti_windup": "clamping",
                             "integrator_method": "backward_euler"}}},
        omega_dot=50.0, ia_dot=50.0),
    # the industrial motor: the maker's nameplate (Ra +5 %, La +5 %, J +4 %, Ke -1.2 %,
    # D +5 % from this machine's truth), its load measured by the flange, the drive unknown
    "ind": _dc_setup(
        PLANTS["ind"],  # type: ignore[arg-type]
        {"Ra": 0.042, "La": 42e-6, "J": 0.0104, "Ke": 0.168, "Kt": 0.168, "D": 0.0021},
        {"structure": "open_loop", "load": "measured", "sub_step": 1e-5,
         "input_hold": "linear", "current_scale": 1.0, "speed_scale": 5.0},
        omega_dot=500.0, ia_dot=50000.0),
    # the small servo: nameplate exact, the drive unknown
    "srvS": _dc_setup(
        PLANTS["srvS"],  # type: ignore[arg-type]
        {"Ra": 1.10, "La": 2.2e-3, "J": 1.6e-5, "Ke": 0.026, "Kt": 0.026, "D": 1.2e-5},
        {"structure": "open_loop", "load": "viscous", "load_coefficient": 1.5e-5,
         "sub_step": 1e-5, "input_hold": "linear", "current_scale": 0.02,
         "speed_scale": 5.0},
        omega_dot=3000.0, ia_dot=1000.0),
    # the mid servo: nameplate off by a few % (Ra +3.3 %, La +5 %, J +3.3 %, Ke -1.8 %,
    # D -5 %), the drive unknown
    "srvM": _dc_setup(
        PLANTS["srvM"],  # type: ignore[arg-type]
        {"Ra": 0.62, "La": 6.3e-3, "J": 6.2e-4, "Ke": 0.108, "Kt": 0.108, "D": 1.9e-4},
        {"structure": "open_loop", "load": "viscous", "load_coefficient": 8e-4,
         "sub_step": 1e-4, "input_hold": "linear", "current_scale": 0.1,
         "speed_scale": 5.0},
        omega_dot=800.0, ia_dot=300.0),
    # the PWM drive: Va is the duty times the supply as the drive reports it; nameplate off
    # by a few % (Ra -3.1 %, La -4.2 %, J -3.3 %, Ke +1.6 %, D +4 %)
    "pwm": _dc_setup(
        PLANTS["pwm"],  # type: ignore[arg-type]
        {"Ra": 1.55, "La": 23e-3, "J": 2.9e-4, "Ke": 0.0508, "Kt": 0.0508, "D": 5.2e-5},
        {"structure": "open_loop", "load": "viscous", "load_coefficient": 1e-3,
         "sub_step": 1e-4, "input_hold": "linear", "current_scale": 0.05,
         "speed_scale": 5.0},
        omega_dot=400.0, ia_dot=150.0),
    # the hydraulic actuator: config/hydraulic-modbus-leak-sim.toml's twin, estimation and
    # discovery, on the file driver
    "hyd": TwinSetup(
        nameplate={"k_spring": 200.0, "D": 100.0, "q_pump": 0.02, "A_max": 1e-4,
                   "A_piston": 0.196349375, "F_resist": 0.0},
        options={"input_hold": "linear", "sub_step": 1e-4, "position_scale": 0.01,
                 "min_speed": 0.0015, "pressure_scale": 1000.0},
        estimate=("q_pump", "D"), bounds={"q_pump": (0.01, 0.04), "D": (20.0, 500.0)},
        columns={"x": "m", "p": "Pa", "A_valve": "m^2", "F_load": "N"},
        noisy=("x", "p"),
        candidates=(("p", "t", _TABLE1, 1.0),)),
}


def _toml_value(v: object) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return str(v)


def config_toml(plant: str, csv_name: str, machine: str) -> str:
    """The configuration of one case's recording (``csv_name``, beside the file)."""
    s = SETUPS[plant]
    model = "hydraulic_actuator" if plant == "hyd" else "dc_motor"
    lines = [f"# twinwatch held-out set ({TABLE}): plant {plant!r}, as its engineer would "
             "configure it", "", "[machine]", f'name = "{machine}"', f'model = "{model}"',
             "", "[machine.parameters]"]
    lines += [f"{k} = {_toml_value(float(v))}" for k, v in s.nameplate.items()]
    lines += ["", "[machine.options]"]
    tables: list[str] = []
    for k, v in s.options.items():
        if isinstance(v, dict):
            tables.append(k)
            continue
        lines.append(f"{k} = {_toml_value(v)}")
    for k in tables:
        sub = s.options[k]
        assert isinstance(sub, dict)
        lines += ["", f"[machine.options.{k}]"]
        nested = [(kk, vv) for kk, vv in sub.items() if isinstance(vv, dict)]
        lines += [f"{kk} = {_toml_value(vv)}" for kk, vv in sub.items()
                  if not isinstance(vv, dict)]
        for kk, vv in nested:
            lines += ["", f"[machine.options.{k}.{kk}]"]
            lines += [f"{a} = {_toml_value(b)}" for a, b in vv.items()]
    lines += ["", "[acquisition]", "sample_period = 0.01", "window = 200", "", "[estimation]",
              f"estimate = {_toml_value(list(s.estimate))}"]
    if plant == "hyd":
        lines += ["tie = {}",
                  "bounds = { " + ", ".join(f"{k} = [{lo!r}, {hi!r}]"
                                            for k, (lo, hi) in s.bounds.items()) + " }",
                  "model_error = 1e-7", "max_rel_std = 0.005", "trust_rel_std = 0.005",
                  "time_budget = 0.5", "seed = 0", "", "[estimation.pso]", "pop_size = 15",
                  "max_generations = 10"]
    else:
        lines += ['tie = { Kt = "Ke" }',
                  "bounds = { " + ", ".join(f"{k} = [{lo!r}, {hi!r}]"
                                            for k, (lo, hi) in s.bounds.items()) + " }",
                  "max_rel_std = 0.01", "time_budget = 0.5", "seed = 0", "",
                  "[estimation.pso]", "pop_size = 15", "max_generations = 20", "w = 0.9",
                  "c1 = 2.0", "c2 = 2.0"]
    lines += ["", "[discovery]", "enabled = true", "trigger_windows = 3", "false_alarm = 1e-6",
              "max_evaluations = 50000"]
    if plant != "hyd":
        lines += ["min_nrmse = 0.002", "bic_threshold = 10.0", "min_improvement = 0.2",
                  "min_significance = 5.0", "max_terms = 3", "drop_after = 3"]
    for attach, inp, kinds, amp in s.candidates:
        lines += ["", "[[discovery.candidates]]", f'attach = "{attach}"', f'input = "{inp}"',
                  f"kinds = {_toml_value(list(kinds))}", f"amplitude = {amp!r}"]
    lines += ["", "[driver]", 'type = "file"', f'path = "{csv_name}"', 'format = "csv"',
              'time_column = "t"', "sample_period = 0.01", "realtime = false", "",
              "[driver.columns]"]
    lines += [f'{ch} = {{ column = "{ch}", unit = "{unit}" }}'
              for ch, unit in s.columns.items()]
    lines += ["", "[zenoh]", "enabled = false", "", "[recording]", "enabled = false", ""]
    return "\n".join(lines)


# -- the cases -----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Case:
    """One held-out case.

    Attributes:
        name: ``<plant>/<fault>/<size and shape>/n<noise>`` (``--only`` matches prefixes).
        plant: a key of :data:`~benchmarks.heldout.plants.PLANTS`.
        category: ``library``, ``sensor_supply``, ``off_library`` or ``nominal``.
        onset: plant time the fault starts [s] (0 for a nominal run).
        accept: answers acceptable at the end (fault ids, ``unknown``, ``check_function``,
            ``no_fault``).
        truth: the outcomes present (Brier score), first the one preferred.
        tolerate: answers not wrong while the fault acts, not acceptable at the end.
        changes: what changes in the plant.
        sensors: the reading faults (those of :data:`LOOP_CHANNELS` act in the loop).
        noise_pct: white Gaussian noise, % of each measured channel's RMS.
        seed: the noise's seed.
        duration: plant time [s].
        note: one line for the reader.
    """

    name: str
    plant: str
    category: str
    onset: float
    accept: frozenset[str]
    truth: tuple[str, ...]
    tolerate: frozenset[str] = frozenset()
    changes: tuple[Change, ...] = ()
    sensors: tuple[SensorFault, ...] = ()
    noise_pct: float = 0.0
    seed: int = 101
    duration: float = DURATION
    note: str = ""

    @property
    def kind(self) -> str:
        """``hyd`` or ``dc``."""
        return "hyd" if self.plant == "hyd" else "dc"

    def scenario(self) -> Scenario:
        """What the plant simulates: the changes and the faults of the readings its
        controller uses."""
        loop = tuple(f for f in self.sensors if f.channel in LOOP_CHANNELS[self.kind])
        return Scenario(changes=self.changes, loop_sensors=loop)

    def true_parameters(self, t: float) -> dict[str, float]:
        """The plant's true parameters at ``t`` by the twin's names (a magnet's change moves
        Ke and Kt; the hydraulic leak is a term, not a parameter)."""
        plant = PLANTS[self.plant]
        base = plant.motor.as_dict() if isinstance(plant, DCPlant) else plant.as_dict()
        out = dict(base)
        for c in self.changes:
            lv = float(c.level(t))
            if c.target in out and c.target not in ("F_resist",):
                out[c.target] += base[c.target] * c.size * lv
                if c.target == "Ke" and "Kt" in out:
                    out["Kt"] += base["Kt"] * c.size * lv
        return out

    def log(self, clean: Mapping[str, Array]) -> dict[str, Array]:
        """The recording: the clean trajectory with its noise, the reading faults outside the
        loop, the logger's resolution (:func:`~benchmarks.heldout.plants.log_channels`)."""
        plant = PLANTS[self.plant]
        setup = SETUPS[self.plant]
        n = int(round(self.duration / SAMPLE_PERIOD))
        clean = {k: np.asarray(v)[:n] for k, v in clean.items()}
        outside = [f for f in self.sensors if f.channel not in LOOP_CHANNELS[self.kind]]
        # the loop's faulted readings are in the plant's trajectory as the true value: the
        # logger reads the same faulted sensor the controller does
        loop = [f for f in self.sensors if f.channel in LOOP_CHANNELS[self.kind]]
        channels = tuple(setup.columns)
        return log_channels(clean, channels, setup.noisy, self.noise_pct, self.seed,
                            sensors=[*outside, *loop], resolution=plant.resolution)

    def write(self, clean: Mapping[str, Array], directory: Path) -> Path:
        """Write the recording (``data.csv``) and the configuration (``twinwatch.toml``) into
        ``directory``; return the configuration's path."""
        directory.mkdir(parents=True, exist_ok=True)
        lg = self.log(clean)
        cols = ["t", *SETUPS[self.plant].columns]
        data = np.column_stack([lg[c] for c in cols])
        np.savetxt(directory / "data.csv", data, delimiter=",", header=",".join(cols),
                   comments="", fmt="%.12g")
        machine = "heldout-" + "".join(ch if ch.isalnum() or ch in "_-" else "-"
                                       for ch in self.name.replace("/", "-"))[:55]
        cfg = directory / "twinwatch.toml"
        cfg.write_text(config_toml(self.plant, "data.csv", machine))
        return cfg


def _ch(target: str, size: float, onset: float, ramp: float = 0.0, **kw: float) -> Change:
    return Change(target, size, onset, ramp, **kw)  # type: ignore[arg-type]


def _sens(channel: str, kind: str, value: float, onset: float, ramp: float = 0.0) -> SensorFault:
    return SensorFault(channel, kind, value, onset, ramp)


def _table() -> list[Case]:
    """The table of :data:`TABLE` (see the module docstring). Frozen."""
    out: list[Case] = []
    seed = iter(range(101, 1000))

    def lib(name: str, plant: str, fid: str, changes: Sequence[Change], noise: float,
            note: str = "", accept: Iterable[str] = ()) -> None:
        onset = min(c.onset for c in changes)
        out.append(Case(name, plant, "library", onset, frozenset([fid, *accept]), (fid,),
                        changes=tuple(changes), noise_pct=noise, seed=next(seed), note=note))

    def sens(name: str, plant: str, mode: str, noise: float, *, sensors: Sequence[SensorFault]
             = (), changes: Sequence[Change] = (), tolerate: Iterable[str] = (),
             note: str = "") -> None:
        onset = min([f.onset for f in sensors] + [c.onset for c in changes])
        out.append(Case(name, plant, "sensor_supply", onset, frozenset([mode, *SENSOR_OK]),
                        (mode,), frozenset(tolerate), tuple(changes), tuple(sensors),
                        noise, next(seed), note=note))

    def off(name: str, plant: str, changes: Sequence[Change], noise: float, note: str = "",
            accept: Iterable[str] = (), truth: str = "unknown") -> None:
        onset = min(c.onset for c in changes)
        out.append(Case(name, plant, "off_library", onset, frozenset([*SENSOR_OK, *accept]),
                        (truth,), changes=tuple(changes), noise_pct=noise, seed=next(seed),
                        note=note))

    def nominal(name: str, plant: str, noise: float) -> None:
        out.append(Case(name, plant, "nominal", 0.0, frozenset(["no_fault"]), ("no_fault",),
                        noise_pct=noise, seed=next(seed), duration=NOMINAL_DURATION))

    # (a) the paper's motor, closed loop ----------------------------------------------------
    p = "pm"
    lib("pm/winding_short/Ra-6%ramp/n0.5", p, "winding_short", [_ch("Ra", -0.06, 64, 60)], 0.5)
    lib("pm/brushes_connections/Ra+9%step/n1", p, "brushes_connections",
        [_ch("Ra", 0.09, 72)], 1.0)
    lib("pm/bearing_wear/D+18%ramp/n0", p, "bearing_wear", [_ch("D", 0.18, 50, 80)], 0.0)
    lib("pm/bearing_wear/D+40%ramp/n1", p, "bearing_wear", [_ch("D", 0.40, 56, 70)], 1.0)
    lib("pm/magnet_weakening/Ke-6%ramp/n0.5", p, "magnet_weakening",
        [_ch("Ke", -0.06, 60, 90)], 0.5)
    lib("pm/load_inertia_change/J+30%step/n0", p, "load_inertia_change",
        [_ch("J", 0.30, 80)], 0.0)
    lib("pm/load_inertia_change/J+30%step/n1", p, "load_inertia_change",
        [_ch("J", 0.30, 80)], 1.0)
    lib("pm/dry_friction/Tc0.004step/n0.5", p, "dry_friction", [_ch("Tc", 0.004, 70)], 0.5)
    sens("pm/current_sensor_high/ia_gain1.07/n0.5", p, "current_sensor_high", 0.5,
         sensors=[_sens("ia", "gain", 1.07, 62, 40)], note="ia reads 1.07x, over 40 s")
    sens("pm/speed_sensor_low/omega_gain0.95/n0.5", p, "speed_sensor_low", 0.5,
         sensors=[_sens("omega", "gain", 0.95, 58, 30)],
         note="the drive's own speed sensor reads 0.95x (the loop regulates the reading)")
    sens("pm/supply_sag/0.92/n0.5", p, "supply_sag", 0.5,
         changes=[_ch("supply", -0.08, 66, 50)],
         note="the motor receives 0.92 of the reported Va")
    off("pm/off/La+40%/n0.5", p, [_ch("La", 0.40, 60, 40)], 0.5,
        note="the armature inductance +40 %: no library mode")
    off("pm/off/load_osc4.1Hz/n0.5", p, [_ch("load_osc", 0.0025, 70, frequency=4.1)], 0.5,
        note="a load torque of 0.0025 N m at 4.1 Hz, not a shaft harmonic")
    off("pm/off/load_intermittent/n0.5", p,
        [_ch("load_step", 0.02, 64, period=15.0, duty=0.4)], 0.5,
        note="an extra 0.02 N m load 6 s of every 15 s")
    nominal("pm/nominal/n0", p, 0.0)
    nominal("pm/nominal/n1", p, 1.0)
    # (b) the industrial 60 V motor, open loop, maker's nameplate ------------------------------
    p = "ind"
    lib("ind/brushes_connections/Ra+9%step/n0", p, "brushes_connections",
        [_ch("Ra", 0.09, 70)], 0.0)
    lib("ind/brushes_connections/Ra+9%step/n1", p, "brushes_connections",
        [_ch("Ra", 0.09, 70)], 1.0)
    lib("ind/winding_short/Ra-6%ramp/n0.5", p, "winding_short", [_ch("Ra", -0.06, 56, 60)],
        0.5)
    lib("ind/bearing_wear/D+40%ramp/n0.5", p, "bearing_wear", [_ch("D", 0.40, 60, 60)], 0.5)
    lib("ind/bearing_wear/D+18%ramp/n1", p, "bearing_wear", [_ch("D", 0.18, 52, 70)], 1.0)
    lib("ind/magnet_weakening/Ke-6%ramp/n0.5", p, "magnet_weakening",
        [_ch("Ke", -0.06, 64, 60)], 0.5)
    lib("ind/load_inertia_change/J+30%step/n0.5", p, "load_inertia_change",
        [_ch("J", 0.30, 76)], 0.5)
    lib("ind/dry_friction/Tc0.3step/n0.5", p, "dry_friction", [_ch("Tc", 0.3, 68)], 0.5)
    sens("ind/current_sensor_high/ia_gain1.07/n0.5", p, "current_sensor_high", 0.5,
         sensors=[_sens("ia", "gain", 1.07, 60, 30)])
    sens("ind/current_sensor_low/ia_gain0.93/n1", p, "current_sensor_low", 1.0,
         sensors=[_sens("ia", "gain", 0.93, 70, 30)])
    sens("ind/current_sensor_high/ia_offset0.6A/n0.5", p, "current_sensor_high", 0.5,
         sensors=[_sens("ia", "offset", 0.6, 66)], note="ia reads +0.6 A (step)")
    sens("ind/speed_sensor_low/omega_gain0.95/n0.5", p, "speed_sensor_low", 0.5,
         sensors=[_sens("omega", "gain", 0.95, 62, 30)])
    sens("ind/supply_sag/0.92/n0.5", p, "supply_sag", 0.5,
         changes=[_ch("supply", -0.08, 58, 40)])
    off("ind/off/La+40%/n0.5", p, [_ch("La", 0.40, 60, 30)], 0.5)
    off("ind/off/brake_intermittent/n0.5", p,
        [_ch("load_step", 0.8, 62, period=11.0, duty=0.45)], 0.5,
        note="a dragging brake, 0.8 N m the flange does not see, 5 s of every 11 s")
    nominal("ind/nominal/n0.5", p, 0.5)
    nominal("ind/nominal/n1", p, 1.0)
    # (c) the small servo, open loop ------------------------------------------------------------
    p = "srvS"
    lib("srvS/winding_short/Ra-6%ramp/n0.5", p, "winding_short", [_ch("Ra", -0.06, 60, 50)],
        0.5)
    lib("srvS/brushes_connections/Ra+9%step/n1", p, "brushes_connections",
        [_ch("Ra", 0.09, 74)], 1.0)
    lib("srvS/bearing_wear/D+40%ramp/n0.5", p, "bearing_wear", [_ch("D", 0.40, 54, 60)], 0.5)
    lib("srvS/magnet_weakening/Ke-6%ramp/n1", p, "magnet_weakening", [_ch("Ke", -0.06, 66, 60)],
        1.0)
    lib("srvS/load_inertia_change/J+30%step/n0.5", p, "load_inertia_change",
        [_ch("J", 0.30, 70)], 0.5)
    lib("srvS/dry_friction/Tc0.0025step/n0.5", p, "dry_friction", [_ch("Tc", 0.0025, 62)],
        0.5)
    sens("srvS/sensor_fault/ia_frozen/n0.5", p, "sensor_fault", 0.5,
         sensors=[_sens("ia", "frozen", 0.0, 68)], note="the current reading freezes")
    sens("srvS/speed_sensor_high/omega_offset3/n0.5", p, "speed_sensor_high", 0.5,
         sensors=[_sens("omega", "offset", 3.0, 64)],
         note="the drive's speed reading +3 rad/s (the loop regulates the reading)")
    sens("srvS/supply_sag/0.92/n1", p, "supply_sag", 1.0,
         changes=[_ch("supply", -0.08, 60, 40)])
    off("srvS/off/dead_zone0.8V/n0.5", p, [_ch("dead_zone", 0.8, 66)], 0.5,
        note="the power stage delivers nothing below 0.8 V")
    nominal("srvS/nominal/n0", p, 0.0)
    nominal("srvS/nominal/n1", p, 1.0)
    # (d) the mid servo, open loop, maker's nameplate -------------------------------------------
    p = "srvM"
    lib("srvM/brushes_connections/Ra+9%ramp/n0.5", p, "brushes_connections",
        [_ch("Ra", 0.09, 58, 50)], 0.5)
    lib("srvM/bearing_wear/D+18%ramp/n0.5", p, "bearing_wear", [_ch("D", 0.18, 62, 60)], 0.5)
    lib("srvM/magnet_weakening/Ke-6%step/n0.5", p, "magnet_weakening", [_ch("Ke", -0.06, 70)],
        0.5)
    lib("srvM/load_inertia_change/J+30%step/n1", p, "load_inertia_change",
        [_ch("J", 0.30, 66)], 1.0)
    lib("srvM/dry_friction/Tc0.02step/n0.5", p, "dry_friction", [_ch("Tc", 0.02, 64)], 0.5)
    sens("srvM/current_sensor_low/ia_gain0.93/n0.5", p, "current_sensor_low", 0.5,
         sensors=[_sens("ia", "gain", 0.93, 60, 40)])
    sens("srvM/speed_sensor_high/omega_gain1.05/n0.5", p, "speed_sensor_high", 0.5,
         sensors=[_sens("omega", "gain", 1.05, 66, 30)])
    off("srvM/off/load_osc7.3Hz/n0.5", p, [_ch("load_osc", 0.05, 62, frequency=7.3)], 0.5,
        note="a load torque of 0.05 N m at 7.3 Hz, not a shaft harmonic")
    off("srvM/off/La+40%/n0.5", p, [_ch("La", 0.40, 56, 40)], 0.5)
    nominal("srvM/nominal/n0.5", p, 0.5)
    nominal("srvM/nominal/n1", p, 1.0)
    # (e) the PWM drive, open loop on the reported duty x supply --------------------------------
    p = "pwm"
    lib("pwm/brushes_connections/Ra+9%step/n0.5", p, "brushes_connections",
        [_ch("Ra", 0.09, 68)], 0.5)
    lib("pwm/winding_short/Ra-6%ramp/n1", p, "winding_short", [_ch("Ra", -0.06, 60, 60)], 1.0)
    lib("pwm/bearing_wear/D+40%ramp/n0.5", p, "bearing_wear", [_ch("D", 0.40, 56, 60)], 0.5)
    lib("pwm/magnet_weakening/Ke-6%ramp/n0.5", p, "magnet_weakening",
        [_ch("Ke", -0.06, 62, 60)], 0.5)
    lib("pwm/load_inertia_change/J+30%step/n0.5", p, "load_inertia_change",
        [_ch("J", 0.30, 72)], 0.5)
    sens("pwm/current_sensor_high/ia_gain1.07/n0.5", p, "current_sensor_high", 0.5,
         sensors=[_sens("ia", "gain", 1.07, 64, 30)])
    sens("pwm/speed_sensor_low/omega_gain0.95/n0", p, "speed_sensor_low", 0.0,
         sensors=[_sens("omega", "gain", 0.95, 60, 30)])
    sens("pwm/supply_sag/0.92/n0.5", p, "supply_sag", 0.5,
         changes=[_ch("supply", -0.08, 58, 40)],
         note="the bridge's supply 24 -> 22.1 V, the drive reports duty x 24 V")
    off("pwm/off/La+40%/n0.5", p, [_ch("La", 0.40, 62, 40)], 0.5)
    off("pwm/off/load_intermittent/n0.5", p,
        [_ch("load_step", 0.03, 66, period=13.0, duty=0.5)], 0.5,
        note="an extra 0.03 N m load 6.5 s of every 13 s")
    nominal("pwm/nominal/n0.5", p, 0.5)
    nominal("pwm/nominal/n1", p, 1.0)
    # (f) the hydraulic actuator, open loop ---------------------------------------------------
    p = "hyd"
    lib("hyd/fluid_degradation/D+15%ramp/n0", p, "fluid_degradation", [_ch("D", 0.15, 60, 80)],
        0.0)
    lib("hyd/fluid_degradation/D+40%ramp/n0", p, "fluid_degradation", [_ch("D", 0.40, 54, 70)],
        0.0)
    lib("hyd/fluid_degradation/D+40%ramp/n0.5", p, "fluid_degradation",
        [_ch("D", 0.40, 54, 70)], 0.5)
    lib("hyd/internal_leak/C0.1step/n0", p, "internal_leak", [_ch("leak", 0.1, 66)], 0.0)
    lib("hyd/internal_leak/C0.1step/n0.5", p, "internal_leak", [_ch("leak", 0.1, 66)], 0.5)
    lib("hyd/pump_wear/q-6%ramp/n0", p, "pump_wear", [_ch("q_pump", -0.06, 62, 60)], 0.0)
    lib("hyd/pump_wear/q-6%ramp/n0.5", p, "pump_wear", [_ch("q_pump", -0.06, 62, 60)], 0.5)
    sens("hyd/sensor_fault/p_frozen/n0", p, "sensor_fault", 0.0,
         sensors=[_sens("p", "frozen", 0.0, 70)], note="the pressure reading freezes")
    sens("hyd/pressure_sensor/p_offset600Pa/n0", p, "pressure_sensor", 0.0,
         sensors=[_sens("p", "offset", 600.0, 64)],
         note="p reads +600 Pa (no pressure-sensor mode in the library: unknown)")
    sens("hyd/position_sensor/x_gain1.04/n0.5", p, "position_sensor", 0.5,
         sensors=[_sens("x", "gain", 1.04, 60, 30)],
         note="the valve loop's own position sensor reads 1.04x")
    off("hyd/off/force_osc0.37Hz/n0", p, [_ch("F_osc", 300.0, 64, frequency=0.37)], 0.0,
        note="an unmeasured 300 N force at 0.37 Hz on the rod")
    off("hyd/off/force_intermittent/n0.5", p,
        [_ch("F_resist", 800.0, 60, period=17.0, duty=0.35)], 0.5,
        note="an unmeasured 800 N force, 6 s of every 17 s")
    nominal("hyd/nominal/n0", p, 0.0)
    nominal("hyd/nominal/n1", p, 1.0)
    return out


#: The frozen table of 2026-11-27.
TABLE_2026_11_27: list[Case] = _table()


def cases() -> list[Case]:
    """Every case of every table (today: :data:`TABLE_2026_11_27`)."""
    return list(TABLE_2026_11_27)


def batches(all_cases: Sequence[Case]) -> dict[str, tuple[list[Scenario], list[float]]]:
    """Per plant, its scenarios in the order the table first names them and each one's
    duration (the longest of its cases): the batch the plant is simulated as. Computed from
    the whole table (never from a selection), so that a case's data never depend on which
    cases run."""
    out: dict[str, tuple[list[Scenario], list[float]]] = {}
    for c in all_cases:
        scs, durs = out.setdefault(c.plant, ([], []))
        sc = c.scenario()
        if sc in scs:
            k = scs.index(sc)
            durs[k] = max(durs[k], c.duration)
        else:
            scs.append(sc)
            durs.append(c.duration)
    return out


def validate(all_cases: Sequence[Case]) -> None:
    """The table's own rules: unique names, seeds >= 101 and unique, known plants."""
    names = [c.name for c in all_cases]
    if len(set(names)) != len(names):
        raise ValueError("case names repeat")
    seeds = [c.seed for c in all_cases]
    if min(seeds) < 101 or len(set(seeds)) != len(seeds):
        raise ValueError("seeds must be unique and >= 101")
    for c in all_cases:
        if c.plant not in PLANTS:
            raise ValueError(f"{c.name}: unknown plant {c.plant}")
        if not math.isfinite(c.onset):
            raise ValueError(f"{c.name}: onset")


validate(TABLE_2026_11_27)

__all__ = ["DURATION", "NOMINAL_DURATION", "SETUPS", "TABLE", "TABLE_2026_11_27", "Case",
           "TwinSetup", "batches", "cases", "config_toml", "validate"]
