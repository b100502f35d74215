"""The configuration schema: one TOML file per machine, validated strictly (every key:
docs/configuration.md).

Every table refuses unknown keys (pydantic ``extra = "forbid"``): a misspelt key stops the
daemon at start-up with the key's path. The ``[driver]`` table is validated by the driver its
``type`` names (:func:`twinwatch.drivers.validate_driver_config`, importing only that
driver's module), the output tables by the sink registry (:data:`twinwatch.sinks.SINKS`:
``[state]``, ``[zenoh]``, ``[recording]`` and ``[outputs.<name>]``), the estimation table by the
estimator, the plant by its simulated driver. Importing this module loads none of the backends
nor the outputs' modules.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from typing import TYPE_CHECKING, Annotated, Any, Literal, NamedTuple

from pydantic import (
    BeforeValidator,
    ConfigDict,
    Field,
    SerializeAsAny,
    StrictFloat,
    StrictInt,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic_core import InitErrorDetails, PydanticCustomError

from twinwatch._lazy import lazy_module
from twinwatch._table import StrictTable
from twinwatch.config.alarms import AlarmConfig
from twinwatch.drivers import (
    DriverConfig,
    DriverInitializationError,
    get_driver_class,
    validate_driver_config,
)
from twinwatch.errors import PluginError
from twinwatch.sinks import HISTORIC_TABLES, SINKS, output_key, sink_class

_NAME = re.compile(r"^[A-Za-z0-9_-]+$")

MAX_WINDOW = 100_000
"""Most samples per window: the ring buffer holds 4 windows of every channel, and the twin
simulates a window per candidate (100,000 samples is 1000 s at 10 ms)."""

MAX_MISSING_DEFAULT = 0.1
"""``[acquisition] max_missing``: a window keeps its samples when up to this fraction of them
is missing (20 of 200; see :mod:`twinwatch.daemon.ringbuffer`)."""
MAX_MISSING_RUN_DEFAULT = 3
"""``[acquisition] max_missing_run``: at most this many missing samples in a row are filled."""


def _table_model(target: str) -> Callable[[], type[Any]]:
    """The table model ``"module:Class"`` that the twin owns (or the identification), as a
    function that imports it when called: when a configuration is validated, not when this
    module is imported (the twin's modules load pymoo, scipy and numba)."""
    module, _, name = target.partition(":")

    def model() -> type[Any]:
        cls: type[Any] = getattr(lazy_module(module), name)
        return cls

    return model


_estimation_config = _table_model("twinwatch.twin.estimation.estimator:EstimationConfig")
_discovery_config = _table_model("twinwatch.twin.discovery.search:DiscoveryConfig")
_prognostics_config = _table_model("twinwatch.twin.prognostics.config:PrognosticsConfig")
_adaptive_config = _table_model("twinwatch.twin.prognostics.config:AdaptiveWindowConfig")
_diagnosis_config = _table_model("twinwatch.twin.diagnosis.library:DiagnosisConfig")
_identify_config = _table_model("twinwatch.config.identify:IdentifyConfig")


def _twin_table(model: Callable[[], type[Any]]) -> Any:
    """A table whose model the twin owns (imported late: :func:`_table_model`); errors keep
    their location in the table."""

    def validate(value: Any) -> Any:
        cls = model()
        return value if isinstance(value, cls) else cls.model_validate(value)

    return Annotated[Any, BeforeValidator(validate)]


def _sink_config(name: str) -> type[Any]:
    """The table model (a ``SinkConfig`` subclass) of the output registered as ``name`` (its
    module imported now)."""
    return sink_class(name).config_class


if TYPE_CHECKING:
    from twinwatch.config.identify import IdentifyConfig
    from twinwatch.sinks.base import SinkConfig
    from twinwatch.sinks.rerun import RecordingConfig
    from twinwatch.sinks.store import StateConfig
    from twinwatch.sinks.zenoh import ZenohConfig
    from twinwatch.twin.diagnosis.library import DiagnosisConfig
    from twinwatch.twin.discovery.search import DiscoveryConfig
    from twinwatch.twin.estimation.estimator import EstimationConfig
    from twinwatch.twin.prognostics.config import AdaptiveWindowConfig, PrognosticsConfig

    EstimationTable = EstimationConfig
    PrognosticsTable = PrognosticsConfig
    AdaptiveTable = AdaptiveWindowConfig
    DiscoveryTable = DiscoveryConfig
    DiagnosisTable = DiagnosisConfig
    IdentifyTable = IdentifyConfig
    ZenohTable = ZenohConfig
    RecordingTable = RecordingConfig
    StateTable = StateConfig
else:
    EstimationTable = _twin_table(_estimation_config)
    DiscoveryTable = _twin_table(_discovery_config)
    DiagnosisTable = _twin_table(_diagnosis_config)
    IdentifyTable = _twin_table(_identify_config)
    PrognosticsTable = _twin_table(_prognostics_config)
    AdaptiveTable = _twin_table(_adaptive_config)
    # the built-in outputs' historic tables, validated by the registry's classes
    ZenohTable = _twin_table(lambda: _sink_config("zenoh"))
    RecordingTable = _twin_table(lambda: _sink_config("rerun"))
    StateTable = _twin_table(lambda: _sink_config("store"))


class OutputTable(NamedTuple):
    """One configured output: its registry name, the table's dotted path in the file and the
    validated table."""

    name: str
    key: str
    config: SinkConfig


def _output_model(name: str) -> type[SinkConfig]:
    """The table model of ``[outputs.<name>]``.

    Raises:
        PluginError: a built-in configured in its historic table, an unknown name (the
            message lists the known ones) or an output that cannot be imported.
    """
    if name in HISTORIC_TABLES:
        raise PluginError(f"the {name!r} output is configured in [{HISTORIC_TABLES[name]}]")
    if name not in SINKS:
        known = [n for n in SINKS if n not in HISTORIC_TABLES]
        raise PluginError(
            f"unknown output {name!r}; known outputs: {', '.join(known) or 'none installed'} "
            f"(the built-ins are configured in "
            f"{', '.join(f'[{t}]' for t in HISTORIC_TABLES.values())})")
    return sink_class(name).config_class


class MachineConfig(StrictTable):
    """``[machine]``: what is monitored."""

    name: str = Field(max_length=64,
                      description="machine name: the Zenoh key segment (letters, digits, _ -; "
                      "at most 64)")
    model: str = Field("dc_motor", description="twin model (registry name)")
    parameters: dict[str, StrictFloat] = Field(
        default_factory=dict, description="nominal (nameplate) values [SI] overriding the "
        "model's defaults; deviations are reported against them")
    options: dict[str, Any] = Field(default_factory=dict,
                                    description="model options (structure, load, gains, ...)")
    purpose: Literal["monitoring", "commissioning"] = Field(
        "monitoring", description="commissioning: the file is for `twinwatch identify` (its "
        "nominal values are generic, not this machine's); `twinwatch run` refuses it without "
        "--force and then warns before it publishes anything")

    @field_validator("name")
    @classmethod
    def _name(cls, v: str) -> str:
        if not _NAME.match(v):
            raise ValueError("use letters, digits, '_' and '-' only (it is a Zenoh key segment)")
        return v

    @field_validator("parameters")
    @classmethod
    def _physical(cls, v: dict[str, float]) -> dict[str, float]:
        for name, value in v.items():
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"{name} = {value}: a nameplate value must be a finite "
                                 f"number >= 0 (the deviation and the alarms are measured "
                                 f"from it)")
        return v


class AcquisitionConfig(StrictTable):
    """``[acquisition]``: windows and buffering (paper: 200 samples every 10 ms)."""

    model_config = ConfigDict(allow_inf_nan=False)

    sample_period: StrictFloat = Field(0.01, gt=0, le=3600, description="nominal sample period [s]")
    window: StrictInt = Field(
        200, ge=10, le=MAX_WINDOW, description="samples per estimation window")
    max_gap: StrictFloat = Field(
        1.5, gt=1, description="largest time-stamp step within a range "
        "`twinwatch identify` fits, in sample periods (the daemon's windows "
        "match stamps to the grid: jitter_tolerance)")
    jitter_tolerance: StrictFloat = Field(
        0.5, gt=0, le=0.5, description="half the widest band the time stamps of one window may "
        "span around their slots on the nominal grid, in sample periods (0.5: narrower than a "
        "period, each stamp in its own slot; the samples are placed on the grid; a stamp "
        "beyond it is a gap or jitter beyond tolerance and abandons the window)")
    max_missing: StrictFloat = Field(
        MAX_MISSING_DEFAULT, ge=0, lt=0.5, description="the largest fraction of a window's "
        "samples that may be missing (a lossy bus: a frame lost or malformed, a poll missed): "
        "their slots hold the previous sample's values and the window is estimated (counted in "
        "samples_missing); beyond it, or beyond max_missing_run in a row, the window is "
        "abandoned (0: every missing sample abandons its window)")
    max_missing_run: StrictInt = Field(
        MAX_MISSING_RUN_DEFAULT, ge=0, le=100, description="the most missing samples in a row "
        "that are filled (a longer gap abandons the window)")
    reopen_max: StrictFloat = Field(30.0, ge=0.5, le=3600, description="cap of the delay [s] "
                                    "between attempts to open a live source that is absent or "
                                    "failed (a bus, a device: waited for, never an exit)")
    queue: StrictInt = Field(4, ge=1, le=1000, description="windows waiting for the estimator")
    history: StrictInt = Field(1000, ge=1, le=100_000, description="health messages a daemon "
                               "keeps for its readers (with a state store only the last 80 in "
                               "memory, the rest read back from it)")
    stall_timeout: StrictFloat = Field(5.0, gt=0, description="seconds without a sample before a "
                                       "stall is reported")
    watchdog: Literal["windows", "alive"] = Field(
        "windows", description="when systemd's watchdog is pinged: 'windows' while windows are "
        "processed (a source silent for WatchdogSec= restarts the service), 'alive' while the "
        "daemon is alive (for machines idle for long: a silent source is reported, not "
        "restarted)")
    shutdown_timeout: StrictFloat = Field(
        10.0, gt=0, description="seconds to finish queued windows")
    stalled_restart: StrictFloat = Field(
        30.0, ge=0, le=86400, description="a gateway's worker process (`run DIR --workers N`) "
        "that sent its host nothing for one window plus 5 s (stopped, frozen) is reported "
        "stalled at once (STATUS, summary, exit status 74); after this many seconds [s] "
        "stalled it is killed and started again, its machines resuming from their state "
        "databases, as systemd's watchdog would (the smallest of the worker's machines' "
        "applies; 0: never, it stays reported stalled)")
    abandon_on_stop: bool = Field(False, description="on stop, drop queued windows instead "
                                  "of estimating them")
    stagger: bool = Field(True, description="in a fleet (a directory of machines), lengthen "
                          "each machine's first window by a phase from its name (0 to one "
                          "window), so machines started together do not complete their "
                          "windows at the same moment and wait for each other; nothing is "
                          "lost (one longer window)")
    adaptive: AdaptiveTable = Field(
        default_factory=lambda: _adaptive_config()(),
        description="[acquisition.adaptive]: a window that follows the change (off by "
        "default)")

    @model_validator(mode="after")
    def _adaptive_bounds(self) -> AcquisitionConfig:
        a = self.adaptive
        if a.enabled:
            if a.max_window > MAX_WINDOW:
                raise ValueError(f"adaptive.max_window: at most {MAX_WINDOW} samples")
            if not a.min_window <= self.window <= a.max_window:
                raise ValueError(f"window: {self.window} samples is outside the adaptive "
                                 f"window's bounds [adaptive.min_window, adaptive.max_window] "
                                 f"= [{a.min_window}, {a.max_window}]")
        return self


class TwinwatchConfig(StrictTable):
    """The whole configuration file."""

    machine: MachineConfig
    acquisition: AcquisitionConfig = Field(default_factory=AcquisitionConfig)
    estimation: EstimationTable = Field(default_factory=lambda: _estimation_config()())
    discovery: DiscoveryTable = Field(default_factory=lambda: _discovery_config()())
    identify: IdentifyTable = Field(default_factory=lambda: _identify_config()())
    prognostics: PrognosticsTable = Field(default_factory=lambda: _prognostics_config()())
    diagnosis: DiagnosisTable = Field(default_factory=lambda: _diagnosis_config()())
    driver: SerializeAsAny[DriverConfig]
    zenoh: ZenohTable = Field(default_factory=lambda: _sink_config("zenoh")())
    recording: RecordingTable = Field(default_factory=lambda: _sink_config("rerun")())
    alarms: AlarmConfig = Field(default_factory=AlarmConfig)
    state: StateTable = Field(default_factory=lambda: _sink_config("store")())
    outputs: dict[str, SerializeAsAny[Any]] = Field(
        default_factory=dict, description="[outputs.<name>]: the other outputs (plug-ins)")

    @field_validator("driver", mode="before")
    @classmethod
    def _driver(cls, value: Any) -> DriverConfig:
        """``[driver]``: validated by the model of the driver its ``type`` names.

        Errors keep their location inside the table (``driver.signals.ia.message``); an unknown
        or unavailable driver is reported at ``driver.type`` with the known names.
        """
        if not isinstance(value, DriverConfig | dict):
            raise ValueError("must be a table with a 'type' key naming the driver")
        try:
            return validate_driver_config(value)
        except DriverInitializationError as exc:
            raise ValidationError.from_exception_data("driver", [InitErrorDetails(
                type=PydanticCustomError("driver_type", "{reason}", {"reason": str(exc)}),
                loc=("type",), input=value.get("type") if isinstance(value, dict) else value,
            )]) from None

    @field_validator("outputs", mode="before")
    @classmethod
    def _outputs(cls, value: Any) -> dict[str, SinkConfig]:
        """``[outputs.<name>]``: each table validated by the model of the output ``name`` names
        in the sink registry (only that output's module is imported). Errors keep their location
        (``outputs.mqtt.port``); an unknown name is reported with the known ones; a built-in with
        a historic table is pointed to it."""
        if not isinstance(value, dict):
            raise ValueError("must be a table of [outputs.<name>] tables")
        errors: list[InitErrorDetails] = []
        validated: dict[str, SinkConfig] = {}
        for name, table in value.items():
            try:
                validated[name] = _output_model(name).model_validate(table)
            except PluginError as exc:
                errors.append(InitErrorDetails(
                    type=PydanticCustomError("output_name", "{reason}", {"reason": str(exc)}),
                    loc=(name,), input=table))
            except ValidationError as exc:  # its own keys: located inside [outputs.<name>]
                errors.extend(InitErrorDetails(
                    type=PydanticCustomError(e["type"], e["msg"]), loc=(name, *e["loc"]),
                    input=e["input"]) for e in exc.errors(include_url=False))
        if errors:
            raise ValidationError.from_exception_data("outputs", errors)
        return validated

    def output_tables(self) -> list[OutputTable]:
        """Every output's table, in the sink registry's order (the order windows are written;
        the gate, the state store, first whatever its place): the built-ins' historic tables,
        then ``[outputs.<name>]``. Disabled tables (``enabled = false``) are included."""
        found = []
        for name in SINKS:
            if name in HISTORIC_TABLES:
                found.append(OutputTable(name, output_key(name),
                                         getattr(self, HISTORIC_TABLES[name])))
            elif name in self.outputs:
                found.append(OutputTable(name, output_key(name), self.outputs[name]))
        return found

    @model_validator(mode="after")
    def _cross_checks(self) -> TwinwatchConfig:
        from twinwatch.twin.models import create_model

        try:
            model = create_model(self.machine.model, self.machine.options)
        except (ValueError, ArithmeticError, TypeError) as exc:
            # a model option out of range may fail in arithmetic, not only in validation
            raise ValueError(f"machine: {exc or type(exc).__name__}") from exc
        for name in self.machine.parameters:
            if name not in model.parameter_names:
                raise ValueError(f"machine.parameters.{name}: unknown parameter; the "
                                 f"{self.machine.model} model has {list(model.parameter_names)}")
        self.estimation = self.estimation.resolved(model)  # estimate/tie: the model's default
        self.discovery.check_against(model)
        self.identify.check_against(model)
        self.diagnosis.check_against(self.machine.model, model.parameter_names,
                                     [a.name for a in model.attach_points],
                                     channels=model.required_channels(),
                                     outputs=model.output_names)
        self.alarms.check_against(model.parameter_names,
                                  estimated=self.estimation.estimate or [])
        try:
            model.check_sample_period(self.acquisition.sample_period)
        except ValueError as exc:
            raise ValueError(f"acquisition.sample_period: {exc}") from exc
        driver_period = get_driver_class(self.driver.type).nominal_sample_period(self.driver)
        acq_period = self.acquisition.sample_period
        if driver_period is not None and abs(driver_period - acq_period) > 1e-12:
            raise ValueError(
                f"driver sample period {driver_period} s differs from acquisition.sample_period "
                f"{self.acquisition.sample_period} s")
        return self
