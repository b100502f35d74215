"""A third-party package's driver, as source: the plug-in tests install it through an entry
point."""

from __future__ import annotations

DRIVER_PLUGIN = '''
"""A third-party driver: the DC motor plant delivered directly (no bus)."""
from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import ConfigDict, Field

from twinwatch.drivers.base import (
    Driver, DriverConfig, DriverInitializationError, validated_config,
)
from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig


class DirectConfig(DriverConfig):
    model_config = ConfigDict(extra="forbid")

    type: Literal["plant_direct"]
    plant: DCMotorPlantConfig = Field(default_factory=DCMotorPlantConfig)
    licence_file: str | None = None   # checked when the driver opens (check-config probes)


class PlantDirectDriver(Driver):
    config_class = DirectConfig
    channels = ("Va", "ia", "omega", "Tload", "setpoint")

    @classmethod
    def nominal_sample_period(cls, config: DriverConfig) -> float | None:
        assert isinstance(config, DirectConfig)
        return config.plant.sample_period

    @classmethod
    def duration(cls, config: DriverConfig) -> float | None:
        assert isinstance(config, DirectConfig)
        return config.plant.duration

    @classmethod
    def safe_to_probe(cls, config: DriverConfig) -> bool:
        return True

    @classmethod
    def from_config(cls, config, *, base_dir: Path | None = None) -> PlantDirectDriver:
        cfg = validated_config(DirectConfig, config, "plant_direct")
        if cfg.licence_file and not ((base_dir or Path.cwd()) / cfg.licence_file).exists():
            raise DriverInitializationError(f"licence_file {cfg.licence_file} not found")
        return cls(cfg)

    def __init__(self, cfg: DirectConfig) -> None:
        super().__init__()
        self.plant = DCMotorPlant(cfg.plant)
        self.sample_period = cfg.plant.sample_period

    def _read_internal(self, timeout):
        return self.plant.next_sample()   # EndOfStream at the plant's duration
'''
