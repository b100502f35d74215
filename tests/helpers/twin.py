"""Drive descriptions and estimation settings that several twin tests share."""

from __future__ import annotations

from twinwatch.io.drive import DriveConfig, LoopConfig
from twinwatch.plant.dcmotor import SetpointSchedule
from twinwatch.twin.estimation.estimator import PSOSettings

#: Set-points that drive the 18 V limit into saturation (20 rad/s needs about 26 V) and out.
STEPS = SetpointSchedule(steps=[(0.0, 5.0), (6.0, 20.0), (22.0, 10.0), (30.0, 0.0),
                                (36.0, 15.0)])


BOUNDS = {"Ra": (1.0, 30.0), "D": (1e-4, 1e-2), "Ke": (0.01, 0.1), "La": (0.1, 3.0),
          "J": (1e-4, 1e-2)}


#: A stiff drive updating every 1 ms with the voltage held and clamped to [0, 24] V.
DRIVE = DriveConfig(period=0.001, speed=LoopConfig(kp=2.0, ki=2.0, output_min=0.0,
                                                   output_max=24.0))


#: The estimation settings this machine needs: model_error 1e-7 is the measured twin-vs-plant
#: floor (D drifting within a window; with the default 1e-4, D's 1.4e-4 share of the pressure
#: is never determined); max_rel_std 0.005 then holds exactly the windows touching a reversal.
#: q_pump comes first so that a reversal holds D alone (the priority list is a hierarchy).
HYDRAULIC_ESTIMATION = dict(estimate=["q_pump", "D"], tie={},
                            bounds={"D": (20.0, 500.0), "q_pump": (0.01, 0.04)},
                            model_error=1e-7, max_rel_std=0.005, trust_rel_std=0.005,
                            pso=PSOSettings(max_generations=10), seed=0)
