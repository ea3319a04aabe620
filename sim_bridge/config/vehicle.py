"""``[sim.vehicle]``, ``[sim.battery]``, ``[sim.disturbance]``, ``[sim.px4]`` and
``[sim.px4_control]``: the vehicle the emulator flies and the PX4 parameters it imitates."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from sim_bridge import ConfigError
from sim_bridge.config.checks import checked, nonneg, one_of, open_unit, positive

# --------------------------------------------------------------------------------------------
# [sim.*]
# Named levels of the vehicle's own imperfections ([sim.vehicle], [sim.battery],
# [sim.disturbance]); explicit keys win over the level (docs/reference/emulator.md).
VEHICLE_LEVELS: dict[str, dict[str, Any]] = {
    "ideal": {},
    "mild": {"hover_thrust_error": 0.05, "mass_error": 0.02, "drag_error": 0.5,
             "motor_curve_factor": 0.1},
    "realistic": {"hover_thrust_error": 0.1, "mass_error": 0.05, "drag_error": 1.0,
                  "motor_curve_factor": 0.3},
    "harsh": {"hover_thrust_error": 0.3, "mass_error": 0.1, "drag_error": 2.0,
              "motor_curve_factor": 0.5},
}
BATTERY_LEVELS: dict[str, dict[str, Any]] = {
    "ideal": {},
    "mild": {"thrust_loss_per_min": 0.008, "max_thrust_loss": 0.15},
    "realistic": {"thrust_loss_per_min": 0.015, "max_thrust_loss": 0.25},
    "harsh": {"thrust_loss_per_min": 0.04, "max_thrust_loss": 0.3},
}
DISTURBANCE_LEVELS: dict[str, dict[str, Any]] = {
    "ideal": {},
    "mild": {"turbulence_std_m_s2": 0.02, "turbulence_tau_s": 2.0},
    "realistic": {"turbulence_std_m_s2": 0.05, "turbulence_tau_s": 2.0},
    "harsh": {"turbulence_std_m_s2": 0.15, "turbulence_tau_s": 1.0},
}


@dataclass(frozen=True)
class VehicleConfig:
    """Quadrotor model: ``attitude_model = "first-order"`` (``sim_bridge.physics.vehicle``) or
    ``"px4"`` (PX4's cascade on a rigid body, ``sim_bridge.physics.rigid_body``, gains in
    ``[sim.px4_control]``).

    ``hover_thrust`` is PX4's ``MPC_THR_HOVER`` parameter (what the autopilot believes and the
    parameter a ground station reads). The vehicle itself may differ: ``true_hover_thrust`` (0:
    ``hover_thrust (1 + hover_thrust_error)``) hovers it at full battery; ``mass_error``
    (payload, relative: raises the true hover thrust and the inertia), ``drag_error`` (true
    drag = ``drag_per_s (1 + drag_error)``), ``motor_curve_factor`` (the motors' true thrust
    curve, px4 model only; PX4 assumes ``thr_mdl_fac``). ``level`` presets them.
    """

    hover_thrust: float = field(metadata=checked(open_unit))
    attitude_tau_s: float = field(metadata=checked(positive))
    max_tilt_rate_rad_s: float = field(metadata=checked(positive))
    max_yaw_rate_rad_s: float = field(metadata=checked(positive))
    drag_per_s: float = field(metadata=checked(nonneg))
    max_tilt_rad: float = field(metadata=checked(lambda x: None if 0 < x < math.pi / 2 else
                                            "must be in (0, pi/2)"))
    attitude_model: str = field(default="first-order",
                                metadata=checked(one_of("first-order", "px4", "rotorpy")))
    level: str = field(default="ideal", metadata=checked(one_of(*VEHICLE_LEVELS)))
    true_hover_thrust: float = field(default=0.0, metadata=checked(
        lambda x: None if 0 <= x < 1 else "must be in (0, 1), or 0 (derived)"))
    hover_thrust_error: float = field(default=0.0, metadata=checked(
        lambda x: None if -0.5 < x < 1 else "must be in (-0.5, 1)"))
    mass_error: float = field(default=0.0, metadata=checked(
        lambda x: None if -0.5 < x < 1 else "must be in (-0.5, 1)"))
    drag_error: float = field(default=0.0, metadata=checked(
        lambda x: None if x >= -1 else "must be >= -1"))
    motor_curve_factor: float = field(default=0.0, metadata=checked(
        lambda x: None if 0 <= x <= 1 else "must be in [0, 1]"))

    def __post_init__(self) -> None:
        if self.true_hover_thrust_full_battery * (1 + self.mass_error) >= 0.95:
            raise ConfigError("sim.vehicle.true_hover_thrust: the true hover thrust "
                              "(with hover_thrust_error and mass_error) must stay below 0.95")

    @property
    def true_hover_thrust_full_battery(self) -> float:
        """Collective thrust that hovers the nominal vehicle (no payload) at full battery."""
        if self.true_hover_thrust > 0:
            return self.true_hover_thrust
        return self.hover_thrust * (1.0 + self.hover_thrust_error)

    @property
    def true_drag_per_s(self) -> float:
        return self.drag_per_s * (1.0 + self.drag_error)


@dataclass(frozen=True)
class BatteryConfig:
    """Battery sag: the maximum thrust falls by ``thrust_loss_per_min`` (fraction per minute of
    simulated time) down to ``1 - max_thrust_loss``, so the true hover thrust rises during the
    flight (PX4's ``MC_BAT_SCALE_EN`` is off by default)."""

    level: str = field(default="ideal", metadata=checked(one_of(*BATTERY_LEVELS)))
    thrust_loss_per_min: float = field(default=0.0, metadata=checked(nonneg))
    max_thrust_loss: float = field(default=0.0, metadata=checked(
        lambda x: None if 0 <= x <= 0.5 else "must be in [0, 0.5]"))


def _deg_s(x: float) -> str | None:
    return None if 0 < x <= 1800 else "must be in (0, 1800] deg/s"


@dataclass(frozen=True)
class Px4ControlConfig:
    """PX4's attitude and rate controller parameters (names after PX4's, lower case; defaults
    are PX4's, docs/reference/emulator.md) and the airframe the ``px4`` model flies."""

    mc_roll_p: float = field(default=6.5, metadata=checked(nonneg))
    mc_pitch_p: float = field(default=6.5, metadata=checked(nonneg))
    mc_yaw_p: float = field(default=2.8, metadata=checked(nonneg))
    mc_yaw_weight: float = field(default=0.4, metadata=checked(
        lambda x: None if 0 <= x <= 1 else "must be in [0, 1]"))
    mc_rollrate_max_deg_s: float = field(default=220.0, metadata=checked(_deg_s))
    mc_pitchrate_max_deg_s: float = field(default=220.0, metadata=checked(_deg_s))
    mc_yawrate_max_deg_s: float = field(default=200.0, metadata=checked(_deg_s))
    mc_rollrate_p: float = field(default=0.15, metadata=checked(nonneg))
    mc_rollrate_i: float = field(default=0.2, metadata=checked(nonneg))
    mc_rollrate_d: float = field(default=0.003, metadata=checked(nonneg))
    mc_rollrate_ff: float = field(default=0.0, metadata=checked(nonneg))
    mc_rollrate_k: float = field(default=1.0, metadata=checked(positive))
    mc_rr_int_lim: float = field(default=0.3, metadata=checked(nonneg))
    mc_pitchrate_p: float = field(default=0.15, metadata=checked(nonneg))
    mc_pitchrate_i: float = field(default=0.2, metadata=checked(nonneg))
    mc_pitchrate_d: float = field(default=0.003, metadata=checked(nonneg))
    mc_pitchrate_ff: float = field(default=0.0, metadata=checked(nonneg))
    mc_pitchrate_k: float = field(default=1.0, metadata=checked(positive))
    mc_pr_int_lim: float = field(default=0.3, metadata=checked(nonneg))
    mc_yawrate_p: float = field(default=0.2, metadata=checked(nonneg))
    mc_yawrate_i: float = field(default=0.1, metadata=checked(nonneg))
    mc_yawrate_d: float = field(default=0.0, metadata=checked(nonneg))
    mc_yawrate_ff: float = field(default=0.0, metadata=checked(nonneg))
    mc_yawrate_k: float = field(default=1.0, metadata=checked(positive))
    mc_yr_int_lim: float = field(default=0.3, metadata=checked(nonneg))
    thr_mdl_fac: float = field(default=0.0, metadata=checked(
        lambda x: None if 0 <= x <= 1 else "must be in [0, 1]"))
    imu_dgyro_cutoff_hz: float = field(default=30.0, metadata=checked(nonneg))
    # the airframe (x500-like quad X)
    mass_kg: float = field(default=2.0, metadata=checked(positive))
    inertia_kg_m2: tuple[float, float, float] = field(
        default=(0.0217, 0.0217, 0.04),
        metadata=checked(lambda x: None if all(v > 0 for v in x) else "every entry must be > 0"))
    arm_xy_m: float = field(default=0.174, metadata=checked(positive))
    km_m: float = field(default=0.05, metadata=checked(nonneg))
    motor_tau_s: float = field(default=0.02, metadata=checked(positive))


@dataclass(frozen=True)
class DisturbanceConfig:
    """Additive acceleration disturbance (the wind's effect on the vehicle): constant wind +
    sinusoidal gust + seeded bounded random + seeded turbulence (first-order Gauss-Markov,
    stationary std ``turbulence_std_m_s2`` horizontally and half of it vertically, correlation
    time ``turbulence_tau_s``). ``level`` presets the turbulence."""

    wind_accel_ned_m_s2: tuple[float, float, float]
    gust_amplitude_m_s2: float = field(metadata=checked(nonneg))
    gust_period_s: float = field(metadata=checked(positive))
    random_bound_m_s2: float = field(metadata=checked(nonneg))
    level: str = field(default="ideal", metadata=checked(one_of(*DISTURBANCE_LEVELS)))
    turbulence_std_m_s2: float = field(default=0.0, metadata=checked(nonneg))
    turbulence_tau_s: float = field(default=2.0, metadata=checked(positive))


@dataclass(frozen=True)
class Px4Config:
    """The PX4 parameters the emulator imitates (names after PX4's)."""

    com_of_loss_t_s: float = field(metadata=checked(positive))
    com_obl_rc_act: int = field(metadata=checked(one_of(0, 1, 2, 3, 4, 5, 6, 7)))
    com_disarm_prflt_s: float = field(metadata=checked(nonneg))

