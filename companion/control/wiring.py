"""What a flight (live or replayed) is built from, for one config: the pipeline, the telemetry
store, the link's allow rules, and who the autopilot is."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from companion.config import Config
from companion.control.pipeline import ControlPipeline
from companion.control.telemetry import TelemetryStore
from companion.perception.pipeline import Perception

if TYPE_CHECKING:  # (the link package is loaded by a flight only: a replay needs none of it)
    from companion.link import AllowRule


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
    from companion.link import default_allow_rules

    extra = ("HIGHRES_IMU",) if cfg.control.estimator.accelerometer else ()
    return default_allow_rules(cfg.mavlink.target_system, cfg.mavlink.target_component,
                               cfg.target.mavlink_sysid, cfg.target.mavlink_compid, extra)


def is_autopilot(cfg: Config, sysid: int, compid: int) -> bool:
    return sysid == cfg.mavlink.target_system and (
        cfg.mavlink.target_component in (0, compid)
    )
