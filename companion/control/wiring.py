"""What a flight (live or replayed) is built from, for one config: the pipeline, the telemetry
store, the link's allow rules, and who the autopilot is."""

from __future__ import annotations

from typing import Any

from companion.config import Config
from companion.control.pipeline import ControlPipeline
from companion.control.telemetry import TelemetryStore
from companion.link import AllowRule, default_allow_rules
from companion.perception.pipeline import Perception


def new_pipeline(cfg: Config, timer: Any = None) -> ControlPipeline:
    """The pipeline a flight (live or replayed) uses for this config."""
    perception = Perception(cfg.camera, cfg.target, perception=cfg.perception)
    return ControlPipeline(cfg, perception, timer=timer)


def new_store(cfg: Config) -> TelemetryStore:
    t = cfg.target
    return TelemetryStore(t.mavlink_sysid, t.origin_lat_deg, t.origin_lon_deg, t.origin_alt_m,
                          autopilot_sysid=cfg.mavlink.target_system)


def allow_rules(cfg: Config) -> tuple[AllowRule, ...]:
    """What the link delivers: the autopilot's telemetry the companion uses (plus HIGHRES_IMU
    when the estimator fuses the accelerometer) and FOLLOW_TARGET from the AGV."""
    extra = ("HIGHRES_IMU",) if cfg.control.estimator.accelerometer else ()
    return default_allow_rules(cfg.mavlink.target_system, cfg.mavlink.target_component,
                               cfg.target.mavlink_sysid, cfg.target.mavlink_compid, extra)


def is_autopilot(cfg: Config, sysid: int, compid: int) -> bool:
    return sysid == cfg.mavlink.target_system and (
        cfg.mavlink.target_component in (0, compid)
    )
