"""The emulated PX4's parameters: what a client reads with PARAM_REQUEST_READ / _LIST.

The values describe the emulated vehicle (docs/guides/vehicle-limits.md):

* where the emulator models a quantity, the parameter is that model's value, set through the
  model's own key: ``MPC_THR_HOVER`` = ``sim.vehicle.hover_thrust`` (what the autopilot
  believes), ``MPC_TILTMAX_AIR`` = ``sim.vehicle.max_tilt_rad`` (the commander's tilt clamp),
  the attitude and rate controller's gains and rate limits (``MC_*``, ``THR_MDL_FAC``,
  ``IMU_DGYRO_CUTOFF``) = ``[sim.px4_control]`` with ``attitude_model = "px4"``; with the
  first-order model the rate limits are its ``max_tilt_rate_rad_s`` / ``max_yaw_rate_rad_s``;
* the position controller's limits the emulator does not fly (it has no position controller:
  the companion flies attitude + thrust) are PX4's defaults (PX4-Autopilot main, 2026:
  ``src/modules/mc_pos_control/*_params.yaml``), overridable in ``[sim.params]``
  (``MPC_XY_VEL_MAX = 5.0``) so that a test can give the vehicle other limits.

A ``[sim.params]`` key that names a modelled parameter is refused with the key that sets it
(so the parameter a client reads is always what the vehicle flies).

The protocol itself (encoding, unknown names) is :mod:`sim_bridge.gcs`: as PX4's
``mavlink_parameters.cpp``, an INT32 travels byte-wise in the float field (``param_type``
MAV_PARAM_TYPE_INT32) and an unknown name gets no answer at all.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import TYPE_CHECKING

from sim_bridge import ConfigError
from sim_bridge.gcs import PARAM_TYPE_INT32, PARAM_TYPE_REAL32, ParamSpec

if TYPE_CHECKING:
    from sim_bridge.config import EmulatorConfig

__all__ = ["MODELLED", "POSITION_LIMITS", "check_overrides", "px4_param_specs"]

_R, _I = PARAM_TYPE_REAL32, PARAM_TYPE_INT32

#: PX4's position-controller limits (default, min, max; units in the comments): not flown by
#: the emulator, served so that a companion can bound its own commands by them.
POSITION_LIMITS: tuple[ParamSpec, ...] = (
    ParamSpec("MPC_XY_VEL_MAX", _R, 12.0, 0.0, 20.0),     # m/s
    ParamSpec("MPC_Z_VEL_MAX_UP", _R, 3.0, 0.5, 8.0),     # m/s
    ParamSpec("MPC_Z_VEL_MAX_DN", _R, 1.5, 0.5, 4.0),     # m/s
    ParamSpec("MPC_ACC_HOR", _R, 3.0, 2.0, 15.0),         # m/s^2 (autonomous modes)
    ParamSpec("MPC_ACC_HOR_MAX", _R, 5.0, 2.0, 15.0),     # m/s^2
    ParamSpec("MPC_ACC_UP_MAX", _R, 4.0, 2.0, 15.0),      # m/s^2
    ParamSpec("MPC_ACC_DOWN_MAX", _R, 3.0, 2.0, 15.0),    # m/s^2
    ParamSpec("MPC_YAWRAUTO_MAX", _R, 60.0, 5.0, 360.0),  # deg/s (autonomous modes)
    ParamSpec("MPC_XY_CRUISE", _R, 5.0, 3.0, 20.0),       # m/s
    ParamSpec("MPC_THR_MIN", _R, 0.12, 0.05, 0.5),        # norm
    ParamSpec("MPC_THR_MAX", _R, 1.0, 0.0, 1.0),          # norm
)

#: Parameters the emulator models, and the config key that sets each.
MODELLED: dict[str, str] = {
    "MPC_THR_HOVER": "sim.vehicle.hover_thrust",
    "MPC_TILTMAX_AIR": "sim.vehicle.max_tilt_rad",
    "COM_OF_LOSS_T": "sim.px4.com_of_loss_t_s",
    "COM_OBL_RC_ACT": "sim.px4.com_obl_rc_act",
    "COM_DISARM_PRFLT": "sim.px4.com_disarm_prflt_s",
    "MAV_SYS_ID": "sim.link.sysid",
    "MAV_COMP_ID": "sim.link.compid",
    **{n: f"sim.px4_control.{n.lower()}" for n in (
        "MC_ROLL_P", "MC_PITCH_P", "MC_YAW_P", "MC_YAW_WEIGHT", "MC_ROLLRATE_P",
        "MC_ROLLRATE_I", "MC_ROLLRATE_D", "MC_ROLLRATE_FF", "MC_ROLLRATE_K", "MC_RR_INT_LIM",
        "MC_PITCHRATE_P", "MC_PITCHRATE_I", "MC_PITCHRATE_D", "MC_PITCHRATE_FF",
        "MC_PITCHRATE_K", "MC_PR_INT_LIM", "MC_YAWRATE_P", "MC_YAWRATE_I", "MC_YAWRATE_D",
        "MC_YAWRATE_FF", "MC_YAWRATE_K", "MC_YR_INT_LIM", "THR_MDL_FAC")},
    "IMU_DGYRO_CUTOFF": "sim.px4_control.imu_dgyro_cutoff_hz",
    "MC_ROLLRATE_MAX": "sim.px4_control.mc_rollrate_max_deg_s (px4 model) or "
                       "sim.vehicle.max_tilt_rate_rad_s (first-order)",
    "MC_PITCHRATE_MAX": "sim.px4_control.mc_pitchrate_max_deg_s (px4 model) or "
                        "sim.vehicle.max_tilt_rate_rad_s (first-order)",
    "MC_YAWRATE_MAX": "sim.px4_control.mc_yawrate_max_deg_s (px4 model) or "
                      "sim.vehicle.max_yaw_rate_rad_s (first-order)",
}


def check_overrides(pairs: Iterable[tuple[str, float]]) -> None:
    """Refuse a ``[sim.params]`` entry that is modelled (naming its key), unknown, or out of
    PX4's range."""
    specs = {s.name: s for s in POSITION_LIMITS}
    for name, value in pairs:
        if name in MODELLED:
            raise ConfigError(f"sim.params.{name}: the emulator models it; set "
                              f"{MODELLED[name]} instead")
        spec = specs.get(name)
        if spec is None:
            raise ConfigError(f"sim.params.{name}: not a parameter the emulator serves "
                              f"(settable: {', '.join(sorted(specs))})")
        if not spec.min_value <= value <= spec.max_value:
            raise ConfigError(f"sim.params.{name}: {value} outside PX4's range "
                              f"[{spec.min_value}, {spec.max_value}]")


def _cascade(cfg: EmulatorConfig) -> tuple[ParamSpec, ...]:
    """The attitude and rate controller's parameters, as the emulated vehicle flies them."""
    v, pc = cfg.sim.vehicle, cfg.sim.px4_control
    if v.attitude_model == "px4":
        rates = (pc.mc_rollrate_max_deg_s, pc.mc_pitchrate_max_deg_s, pc.mc_yawrate_max_deg_s)
    else:  # the first-order model's rate limits
        tilt = math.degrees(v.max_tilt_rate_rad_s)
        rates = (tilt, tilt, math.degrees(v.max_yaw_rate_rad_s))
    gains = tuple(ParamSpec(n, _R, float(getattr(pc, n.lower())), 0.0, 100.0) for n in (
        "MC_ROLL_P", "MC_PITCH_P", "MC_YAW_P", "MC_YAW_WEIGHT", "MC_ROLLRATE_P",
        "MC_ROLLRATE_I", "MC_ROLLRATE_D", "MC_ROLLRATE_FF", "MC_ROLLRATE_K", "MC_RR_INT_LIM",
        "MC_PITCHRATE_P", "MC_PITCHRATE_I", "MC_PITCHRATE_D", "MC_PITCHRATE_FF",
        "MC_PITCHRATE_K", "MC_PR_INT_LIM", "MC_YAWRATE_P", "MC_YAWRATE_I", "MC_YAWRATE_D",
        "MC_YAWRATE_FF", "MC_YAWRATE_K", "MC_YR_INT_LIM", "THR_MDL_FAC"))
    return (
        ParamSpec("MC_ROLLRATE_MAX", _R, round(rates[0], 3), 0.0, 1800.0),   # deg/s
        ParamSpec("MC_PITCHRATE_MAX", _R, round(rates[1], 3), 0.0, 1800.0),  # deg/s
        ParamSpec("MC_YAWRATE_MAX", _R, round(rates[2], 3), 0.0, 1800.0),    # deg/s
        *gains,
        ParamSpec("IMU_DGYRO_CUTOFF", _R, pc.imu_dgyro_cutoff_hz, 0.0, 1000.0),  # Hz
    )


def px4_param_specs(cfg: EmulatorConfig) -> tuple[ParamSpec, ...]:
    """Every parameter the emulator serves, in protocol index order (module docstring)."""
    sim, link = cfg.sim, cfg.sim.link
    over = dict(sim.params)
    limits = tuple(ParamSpec(s.name, s.type_id, over.get(s.name, s.default), s.min_value,
                             s.max_value) for s in POSITION_LIMITS)
    return (
        ParamSpec("MAV_SYS_ID", _I, link.sysid, 1, 250),
        ParamSpec("MAV_COMP_ID", _I, link.compid, 1, 250),
        ParamSpec("MAV_TYPE", _I, 2, 0, 50),                  # quadrotor
        ParamSpec("SYS_AUTOSTART", _I, 4001, 0, 9_999_999),   # generic quadrotor x
        ParamSpec("MPC_THR_HOVER", _R, sim.vehicle.hover_thrust, 0.1, 0.8),
        ParamSpec("MPC_TILTMAX_AIR", _R, round(math.degrees(sim.vehicle.max_tilt_rad), 3),
                  20.0, 89.0),                                # deg
        *limits,
        *_cascade(cfg),
        ParamSpec("MPC_LAND_SPEED", _R, 0.7, 0.6, 10.0),     # m/s (the emulator's fixed value)
        ParamSpec("MPC_TKO_SPEED", _R, 1.5, 1.0, 5.0),       # m/s (fixed)
        ParamSpec("MIS_TAKEOFF_ALT", _R, 2.5, 0.0, 80.0),    # m (fixed)
        ParamSpec("COM_OF_LOSS_T", _R, sim.px4.com_of_loss_t_s, 0.0, 60.0),  # s
        ParamSpec("COM_OBL_RC_ACT", _I, sim.px4.com_obl_rc_act, 0, 7),
        ParamSpec("COM_DISARM_PRFLT", _R, sim.px4.com_disarm_prflt_s, -1.0, 20.0),  # s
        ParamSpec("COM_DISARM_LAND", _R, 2.0, -1.0, 20.0),   # s
        ParamSpec("COM_RC_IN_MODE", _I, 4, 0, 4),             # 4: no RC (companion flight)
        ParamSpec("NAV_DLL_ACT", _I, 0, 0, 6),                # GCS loss: disabled
        ParamSpec("NAV_RCL_ACT", _I, 2, 0, 6),                # RC loss: Return
    )
