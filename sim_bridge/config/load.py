"""The whole emulator config (:class:`SimConfig`, :class:`EmulatorConfig`) and its loading: TOML
files with ``base`` chains, deep merge, per-key conversion and checks."""

from __future__ import annotations

import dataclasses
import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sim_bridge import ConfigError
from sim_bridge.config.checks import checked, nonneg, one_of, positive
from sim_bridge.config.links import FaultsConfig, ImpairmentConfig, LinkConfig, SigningConfig
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
from sim_bridge.impairment import ImpairmentParams
from sim_bridge.px4_params import check_overrides

DEFAULT_CONFIG = Path(__file__).resolve().parents[2] / "config" / "paper.toml"


@dataclass(frozen=True)
class SimConfig:
    time_mode: str = field(metadata=checked(one_of("realtime", "lockstep")))
    lockstep_timeout_s: float = field(metadata=checked(positive))
    physics_dt_s: float = field(metadata=checked(positive))
    step_dt_s: float = field(metadata=checked(positive))
    seed: int
    start: str = field(metadata=checked(one_of("airborne", "ground")))
    scenario: str
    duration_s: float = field(metadata=checked(positive))
    vehicle: VehicleConfig
    disturbance: DisturbanceConfig
    px4: Px4Config
    link: LinkConfig
    agv: AgvConfig
    camera: SimCameraConfig
    faults: FaultsConfig = field(default_factory=FaultsConfig)
    impairment: ImpairmentConfig = field(default_factory=ImpairmentConfig)
    signing: SigningConfig = field(default_factory=SigningConfig)
    camera_model: CameraModelConfig = field(default_factory=CameraModelConfig)
    telemetry: TelemetryConfig = field(default_factory=TelemetryConfig)
    battery: BatteryConfig = field(default_factory=BatteryConfig)
    px4_control: Px4ControlConfig = field(default_factory=Px4ControlConfig)
    #: lockstep: wall time the first frame a client gets waits for its answer (a client that
    #: compiles its controller for the vehicle's limits first); 0: lockstep_timeout_s
    lockstep_start_timeout_s: float = field(default=0.0, metadata=checked(nonneg))
    #: [sim.params]: PX4 parameters served with other than PX4's defaults (sim_bridge.px4_params)
    params: tuple[tuple[str, float], ...] = ()

    def __post_init__(self) -> None:
        if self.physics_dt_s > self.step_dt_s:
            raise ConfigError("sim.physics_dt_s: must be <= sim.step_dt_s")
        # In lockstep the camera fires once per step: a rate that says otherwise would be
        # silently ignored (a "30 Hz" flight flying at 20 Hz), so it is refused by name.
        step_hz = 1.0 / self.step_dt_s
        if self.time_mode == "lockstep" and abs(self.camera.rate_hz - step_hz) > 1e-6 * step_hz:
            raise ConfigError(
                f"sim.camera.rate_hz: {self.camera.rate_hz:g} Hz has no effect in lockstep, "
                f"where the camera fires once per sim.step_dt_s = {self.step_dt_s:g} s "
                f"({step_hz:g} Hz): set sim.step_dt_s = 1 / rate_hz, or rate_hz = {step_hz:g}")


@dataclass(frozen=True)
class EmulatorConfig:
    """Everything the emulator reads: ``[sim]``, ``[camera]``, ``[target]`` and the chosen
    ``[sim.scenarios.<name>]``."""

    sim: SimConfig
    camera: CameraConfig
    target: TargetConfig
    scenario: ScenarioConfig
    source: str = ""

    @property
    def ground_z_m(self) -> float:
        """NED z of the ground: the AGV top (``sim.agv.top_z_m``) is ``target.height_m`` above
        it."""
        return self.sim.agv.top_z_m + self.target.height_m


# --------------------------------------------------------------------------------------------
# Loading
def deep_merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """Tables merge key by key (recursively); any other value in ``over`` replaces."""
    out: dict[str, Any] = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = v
    return out


def read_toml(path: str | Path, _seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """Read a TOML file, resolving ``base = "file.toml"`` chains (relative to the file)."""
    p = Path(path).expanduser().resolve()
    if p in _seen:
        raise ConfigError(f"{p}: 'base' chain loops back to itself")
    try:
        with p.open("rb") as f:
            data = tomllib.load(f)
    except OSError as e:
        raise ConfigError(f"{p}: cannot read ({e.strerror})") from e
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{p}: not valid TOML ({e})") from e
    base = data.pop("base", None)
    if base is None:
        return data
    if not isinstance(base, str):
        raise ConfigError(f"{p}: base: must be a file name (string)")
    return deep_merge(read_toml(p.parent / base, (*_seen, p)), data)


def _convert(value: Any, tp: Any, key: str) -> Any:
    """Check ``value`` against the annotation string ``tp`` and convert it."""
    tp = str(tp)
    if tp == "float":
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{key}: must be a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{key}: must be finite")
        return float(value)
    if tp == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: must be an integer, got {value!r}")
        return value
    if tp == "bool":
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: must be true or false, got {value!r}")
        return value
    if tp == "tuple[str, ...]":
        if not isinstance(value, list) or not all(isinstance(x, str) for x in value):
            raise ConfigError(f"{key}: must be a list of strings")
        return tuple(value)
    if tp == "str":
        if not isinstance(value, str):
            raise ConfigError(f"{key}: must be a string, got {value!r}")
        return value
    if tp.startswith("tuple[tuple[float, float], ...]"):
        if not isinstance(value, list):
            raise ConfigError(f"{key}: must be a list of [start, end] pairs")
        out = []
        for i, pair in enumerate(value):
            if not isinstance(pair, list) or len(pair) != 2:
                raise ConfigError(f"{key}[{i}]: must be [start_s, end_s]")
            a, b = (_convert(x, "float", f"{key}[{i}]") for x in pair)
            if b < a:
                raise ConfigError(f"{key}[{i}]: end must be >= start")
            out.append((a, b))
        return tuple(out)
    if tp.startswith("tuple[float"):
        n = tp.count("float")
        if not isinstance(value, list) or len(value) != n:
            raise ConfigError(f"{key}: must be a list of {n} numbers")
        return tuple(_convert(x, "float", f"{key}[{i}]") for i, x in enumerate(value))
    raise ConfigError(f"{key}: unsupported type {tp}")  # pragma: no cover - programming error


def _build(cls: Any, table: Any, prefix: str, extra: Mapping[str, Any] | None = None) -> Any:
    if not isinstance(table, Mapping):
        raise ConfigError(f"{prefix}: must be a table")
    kwargs: dict[str, Any] = dict(extra or {})
    known = {f.name for f in dataclasses.fields(cls)}
    for f in dataclasses.fields(cls):
        if f.name in kwargs:
            continue
        key = f"{prefix}.{f.name}"
        if f.name not in table:
            if f.default is not dataclasses.MISSING:
                continue
            raise ConfigError(f"{key}: missing")
        value = _convert(table[f.name], f.type, key)
        check = f.metadata.get("check")
        if check is not None and (msg := check(value)) is not None:
            raise ConfigError(f"{key}: {msg}")
        kwargs[f.name] = value
    unknown = set(table) - known - set(extra or {})
    if unknown:
        raise ConfigError(f"{prefix}: unknown key(s) {', '.join(sorted(unknown))}")
    try:
        return cls(**kwargs)
    except ValueError as e:  # a value type's own check (``__post_init__``) names the field
        raise ConfigError(f"{prefix}.{e}") from None


_SIM_SUBTABLES = {
    "vehicle": VehicleConfig,
    "disturbance": DisturbanceConfig,
    "px4": Px4Config,
    "link": LinkConfig,
    "agv": AgvConfig,
    "camera": SimCameraConfig,
    "faults": FaultsConfig,
    "impairment": ImpairmentConfig,
    "signing": SigningConfig,
    "camera_model": CameraModelConfig,
    "telemetry": TelemetryConfig,
    "battery": BatteryConfig,
    "px4_control": Px4ControlConfig,
}
_OPTIONAL_SUBTABLES = frozenset({"faults", "impairment", "signing", "camera_model", "telemetry",
                                 "battery", "px4_control"})
_IMPAIRMENT_DIRECTIONS = ("vehicle_to_companion", "companion_to_vehicle")


def _build_impairment(table: Any) -> ImpairmentConfig:
    if not isinstance(table, Mapping):
        raise ConfigError("sim.impairment: must be a table")
    dirs = {d: _build(ImpairmentParams, table.get(d, {}), f"sim.impairment.{d}")
            for d in _IMPAIRMENT_DIRECTIONS}
    cfg: ImpairmentConfig = _build(ImpairmentConfig, table, "sim.impairment", extra=dirs)
    return cfg


_LEVELS: dict[str, dict[str, dict[str, Any]]] = {
    "camera_model": CAMERA_LEVELS, "telemetry": TELEMETRY_LEVELS, "vehicle": VEHICLE_LEVELS,
    "battery": BATTERY_LEVELS, "disturbance": DISTURBANCE_LEVELS}


def _with_level(name: str, table: Any) -> Any:
    """``table`` with its ``level``'s preset filled in under the explicit keys."""
    levels = _LEVELS.get(name)
    if levels is None or not isinstance(table, Mapping):
        return table
    level = table.get("level", "ideal")
    if not isinstance(level, str) or level not in levels:
        raise ConfigError(f"sim.{name}.level: must be one of {', '.join(map(repr, levels))}")
    return {**levels[level], **table}


def _params(table: Any) -> tuple[tuple[str, float], ...]:
    """``[sim.params]``: ``NAME = number`` pairs, checked by :mod:`sim_bridge.px4_params`."""
    if not isinstance(table, Mapping):
        raise ConfigError("sim.params: must be a table")
    pairs = tuple((str(k), _convert(v, "float", f"sim.params.{k}")) for k, v in table.items())
    check_overrides(pairs)
    return pairs


def config_from_dict(data: Mapping[str, Any], scenario: str | None = None,
                     source: str = "") -> EmulatorConfig:
    """Validate a merged TOML document. ``scenario`` overrides ``sim.scenario``."""
    for t in ("sim", "camera", "target"):
        if t not in data:
            raise ConfigError(f"{t}: missing table")
    sim_t = data["sim"]
    if not isinstance(sim_t, Mapping):
        raise ConfigError("sim: must be a table")
    subs = {}
    for name, cls in _SIM_SUBTABLES.items():
        if name not in sim_t:
            if name in _OPTIONAL_SUBTABLES:
                subs[name] = cls()
                continue
            raise ConfigError(f"sim.{name}: missing table")
        if name == "impairment":
            subs[name] = _build_impairment(sim_t[name])
        else:
            subs[name] = _build(cls, _with_level(name, sim_t[name]), f"sim.{name}")
    sig = subs["signing"]
    if sig.key_file and source and not Path(sig.key_file).expanduser().is_absolute():
        subs["signing"] = dataclasses.replace(
            sig, key_file=str(Path(source).resolve().parent / sig.key_file))
    subs["params"] = _params(sim_t.get("params", {}))
    scenarios = sim_t.get("scenarios", {})
    sim_flat = {k: v for k, v in sim_t.items() if k not in ("scenarios", "params")}
    sim = _build(SimConfig, sim_flat, "sim", extra=subs)
    name = scenario if scenario is not None else sim.scenario
    if not isinstance(scenarios, Mapping) or name not in scenarios:
        have = ", ".join(sorted(scenarios)) if isinstance(scenarios, Mapping) else ""
        raise ConfigError(f"sim.scenarios.{name}: no such scenario (have: {have})")
    scen = _build(ScenarioConfig, scenarios[name], f"sim.scenarios.{name}",
                  extra={"name": name})
    if scenario is not None:
        sim = dataclasses.replace(sim, scenario=name)
    camera = _build(CameraConfig, data["camera"], "camera")
    target = _build(TargetConfig, data["target"], "target")
    return EmulatorConfig(sim=sim, camera=camera, target=target, scenario=scen, source=source)


def load_config(path: str | Path | None = None, scenario: str | None = None) -> EmulatorConfig:
    """Load and validate the emulator's part of a scenario file (default ``config/paper.toml``)."""
    p = Path(path) if path is not None else DEFAULT_CONFIG
    return config_from_dict(read_toml(p), scenario=scenario, source=str(p))


def with_link(cfg: EmulatorConfig, **changes: Any) -> EmulatorConfig:
    """A copy of ``cfg`` with ``sim.link`` fields replaced (validated like the file's)."""
    link = cfg.sim.link
    for k, v in changes.items():
        f = next((f for f in dataclasses.fields(LinkConfig) if f.name == k), None)
        if f is None:
            raise ConfigError(f"sim.link.{k}: unknown key")
        v = _convert(v, f.type, f"sim.link.{k}")
        check = f.metadata.get("check")
        if check is not None and (msg := check(v)) is not None:
            raise ConfigError(f"sim.link.{k}: {msg}")
        link = dataclasses.replace(link, **{k: v})
    return dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, link=link))


def with_sim(cfg: EmulatorConfig, **changes: Any) -> EmulatorConfig:
    """A copy of ``cfg`` with top-level ``sim`` fields (or whole sub-configs) replaced."""
    return dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, **changes))
