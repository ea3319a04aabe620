"""Builds the emulator's vehicle dynamics from the configuration: the first-order attitude model
or PX4's control cascade on a rigid body (``sim.vehicle.attitude_model``), with the vehicle's
imperfections (``[sim.vehicle]`` errors, ``[sim.battery]``, ``[sim.disturbance]``) applied to
either. docs/reference/emulator.md describes both.
"""

from __future__ import annotations

import math
from typing import Protocol

from sim_bridge import ConfigError
from sim_bridge.config import EmulatorConfig
from sim_bridge.physics.px4_control import Px4Gains
from sim_bridge.physics.rigid_body import AirframeParams, Px4VehicleModel
from sim_bridge.physics.vehicle import (
    AttitudeCommand,
    Disturbance,
    DisturbanceParams,
    VehicleModel,
    VehicleParams,
    VehicleState,
)


class VehicleDynamics(Protocol):
    """What the runtime needs of a vehicle model."""

    dt_s: float

    def step(self, s: VehicleState, cmd: AttitudeCommand, duration_s: float) -> VehicleState:
        """Advance ``s`` by ``duration_s`` (whole ``dt_s`` sub-steps) with ``cmd`` held."""
        ...

    def true_hover_thrust(self, t_s: float) -> float:
        """The collective thrust that hovers the vehicle at ``t_s``."""
        ...


def px4_gains(cfg: EmulatorConfig) -> Px4Gains:
    """``[sim.px4_control]`` as the cascade's gains (rates in rad/s)."""
    c = cfg.sim.px4_control
    return Px4Gains(
        att_p=(c.mc_roll_p, c.mc_pitch_p, c.mc_yaw_p),
        yaw_weight=c.mc_yaw_weight,
        rate_max_rad_s=(
            math.radians(c.mc_rollrate_max_deg_s),
            math.radians(c.mc_pitchrate_max_deg_s),
            math.radians(c.mc_yawrate_max_deg_s),
        ),
        rate_p=(c.mc_rollrate_p, c.mc_pitchrate_p, c.mc_yawrate_p),
        rate_i=(c.mc_rollrate_i, c.mc_pitchrate_i, c.mc_yawrate_i),
        rate_d=(c.mc_rollrate_d, c.mc_pitchrate_d, c.mc_yawrate_d),
        rate_ff=(c.mc_rollrate_ff, c.mc_pitchrate_ff, c.mc_yawrate_ff),
        rate_k=(c.mc_rollrate_k, c.mc_pitchrate_k, c.mc_yawrate_k),
        rate_int_lim=(c.mc_rr_int_lim, c.mc_pr_int_lim, c.mc_yr_int_lim),
        thr_mdl_fac=c.thr_mdl_fac,
        dgyro_cutoff_hz=c.imu_dgyro_cutoff_hz,
    )


def disturbance(cfg: EmulatorConfig) -> Disturbance:
    sim = cfg.sim
    d = sim.disturbance
    return Disturbance(
        DisturbanceParams(
            wind_accel_ned_m_s2=d.wind_accel_ned_m_s2,
            gust_amplitude_m_s2=d.gust_amplitude_m_s2,
            gust_period_s=d.gust_period_s,
            random_bound_m_s2=d.random_bound_m_s2,
            random_hold_s=sim.step_dt_s,
            seed=sim.seed,
            turbulence_std_m_s2=d.turbulence_std_m_s2,
            turbulence_tau_s=d.turbulence_tau_s,
        )
    )


def build_vehicle_model(cfg: EmulatorConfig) -> VehicleDynamics:
    """The vehicle model ``cfg`` asks for."""
    sim = cfg.sim
    v, b = sim.vehicle, sim.battery
    loss_per_s = b.thrust_loss_per_min / 60.0
    if v.attitude_model == "rotorpy":
        return _rotorpy_vehicle(cfg)
    if v.attitude_model == "px4":
        c = sim.px4_control
        return Px4VehicleModel(
            px4_gains(cfg),
            AirframeParams(
                mass_kg=c.mass_kg,
                inertia_kg_m2=c.inertia_kg_m2,
                arm_xy_m=c.arm_xy_m,
                km_m=c.km_m,
                motor_tau_s=c.motor_tau_s,
                true_hover_thrust=v.true_hover_thrust_full_battery,
                motor_curve_factor=v.motor_curve_factor,
                mass_error=v.mass_error,
                drag_per_s=v.true_drag_per_s,
                battery_loss_per_s=loss_per_s,
                battery_max_loss=b.max_thrust_loss,
                ground_z_m=cfg.ground_z_m,
            ),
            disturbance(cfg),
            dt_s=sim.physics_dt_s,
        )
    return VehicleModel(
        VehicleParams(
            hover_thrust=v.true_hover_thrust_full_battery * (1.0 + v.mass_error),
            attitude_tau_s=v.attitude_tau_s,
            max_tilt_rate_rad_s=v.max_tilt_rate_rad_s,
            max_yaw_rate_rad_s=v.max_yaw_rate_rad_s,
            drag_per_s=v.true_drag_per_s,
            max_tilt_rad=v.max_tilt_rad,
            ground_z_m=cfg.ground_z_m,
            battery_loss_per_s=loss_per_s,
            battery_max_loss=b.max_thrust_loss,
        ),
        disturbance(cfg),
        dt_s=sim.physics_dt_s,
    )


def _rotorpy_vehicle(cfg: EmulatorConfig) -> VehicleDynamics:
    """PX4's cascade on rotorpy's vehicle (optional extra ``.[rotorpy]``;
    docs/reference/rotorpy.md)."""
    try:
        from sim_bridge.physics.rotorpy_vehicle import RotorpyAirframe, RotorpyVehicleModel
    except ImportError as e:
        raise ConfigError("sim.vehicle.attitude_model = \"rotorpy\" needs the optional extra: "
                          f"pip install '.[rotorpy]' ({e})") from e
    sim = cfg.sim
    v, b = sim.vehicle, sim.battery
    airframe = RotorpyAirframe(
        true_hover_thrust=v.true_hover_thrust_full_battery, motor_curve_factor=v.motor_curve_factor,
        mass_error=v.mass_error, battery_loss_per_s=b.thrust_loss_per_min / 60.0,
        battery_max_loss=b.max_thrust_loss, ground_z_m=cfg.ground_z_m)
    return RotorpyVehicleModel(px4_gains(cfg), airframe, disturbance(cfg).params,
                               dt_s=sim.physics_dt_s,
                               wind_altitude_m=max(0.5, cfg.ground_z_m - cfg.scenario.uav_pose[2]))


def vehicle_is_ideal(cfg: EmulatorConfig) -> bool:
    """Whether the vehicle is exactly what its parameters say (no imperfection configured)."""
    v, b = cfg.sim.vehicle, cfg.sim.battery
    return (
        v.true_hover_thrust_full_battery == v.hover_thrust
        and v.mass_error == 0
        and v.drag_error == 0
        and v.motor_curve_factor == 0
        and b.thrust_loss_per_min == 0
    )
