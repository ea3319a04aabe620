"""Emulator configuration: ``[sim]``, ``[camera]`` and ``[target]`` of a scenario TOML file,
loaded once into validated, frozen dataclasses.

The emulator parses the file itself (it shares no code with the companion). A file may start
with ``base = "other.toml"`` (relative to itself): the base is loaded first, then this file's
tables and keys override it (deep merge; tables merge key by key, every other value replaces).
A bad value raises :class:`sim_bridge.ConfigError` naming the key (``sim.vehicle.hover_thrust:
must be in (0, 1)``). The scenario (initial UAV pose) is picked by name from
``[sim.scenarios.<name>]``.

One module per group of tables: ``world`` (camera, target, AGV, scenarios), ``vehicle``
(vehicle, battery, disturbance, PX4 parameters and control gains), ``links`` (sockets, faults,
impairment, signing), ``sensors`` (camera model, telemetry), ``load`` (the whole and its
loading), ``checks`` (the field checks).
"""

from __future__ import annotations

from sim_bridge.config.checks import parse_address
from sim_bridge.config.links import (
    LINK_NAMES,
    FaultsConfig,
    ImpairmentConfig,
    LinkConfig,
    SigningConfig,
)
from sim_bridge.config.load import (
    DEFAULT_CONFIG,
    EmulatorConfig,
    SimConfig,
    config_from_dict,
    deep_merge,
    load_config,
    read_toml,
    with_link,
    with_sim,
)
from sim_bridge.config.sensors import (
    CAMERA_LEVELS,
    TELEMETRY_LEVELS,
    CameraModelConfig,
    TelemetryConfig,
)
from sim_bridge.config.vehicle import (
    BATTERY_LEVELS,
    DISTURBANCE_LEVELS,
    VEHICLE_LEVELS,
    BatteryConfig,
    DisturbanceConfig,
    Px4Config,
    Px4ControlConfig,
    VehicleConfig,
)
from sim_bridge.config.world import (
    AgvConfig,
    CameraConfig,
    ScenarioConfig,
    SimCameraConfig,
    TargetConfig,
)

__all__ = [
    "BATTERY_LEVELS", "CAMERA_LEVELS", "DEFAULT_CONFIG", "DISTURBANCE_LEVELS", "LINK_NAMES",
    "TELEMETRY_LEVELS", "VEHICLE_LEVELS", "AgvConfig", "BatteryConfig", "CameraConfig",
    "CameraModelConfig", "DisturbanceConfig", "EmulatorConfig", "FaultsConfig",
    "ImpairmentConfig", "LinkConfig", "Px4Config", "Px4ControlConfig", "ScenarioConfig",
    "SigningConfig", "SimCameraConfig", "SimConfig", "TargetConfig", "TelemetryConfig",
    "VehicleConfig", "config_from_dict", "deep_merge", "load_config", "parse_address",
    "read_toml", "with_link", "with_sim",
]
