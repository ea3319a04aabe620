"""The first-order model's fused sub-step loop (``VehicleModel._substeps``) against the
per-sub-step form it replaced (kept here as the reference): the same state to the bit over
flights that cross every branch (motors off, resting on and lifting off the ground, rate and
tilt limits, yaw wrap, battery sag, gusts and random disturbance)."""

from __future__ import annotations

import math
import struct

import numpy as np

from sim_bridge.physics.vehicle import (
    AttitudeCommand,
    Disturbance,
    DisturbanceParams,
    VehicleModel,
    VehicleParams,
    VehicleState,
    initial_state,
    wrap_pi,
)


def _clamp(x: float, lim: float) -> float:
    return -lim if x < -lim else (lim if x > lim else float(x))


def _reference_step(m: VehicleModel, s: VehicleState, cmd: AttitudeCommand,
                    duration_s: float) -> VehicleState:
    """The per-sub-step integrator as it was (one call, one tuple per sub-step)."""
    p, dt = m.params, m.dt_s
    h = m._held(cmd)
    alpha, thrust = h.alpha, h.thrust
    t = s.t_s
    px, py, pz = (float(v) for v in s.pos_ned_m)
    vx, vy, vz = (float(v) for v in s.vel_ned_m_s)
    roll, pitch, yaw, on_ground = s.roll_rad, s.pitch_rad, s.yaw_rad, s.on_ground
    out = None
    for _ in range(max(1, round(duration_s / dt))):
        d_roll = d_pitch = d_yaw = 0.0
        if cmd.motors_on:
            d_roll = _clamp(alpha * wrap_pi(h.roll_sp - roll), p.max_tilt_rate_rad_s * dt)
            d_pitch = _clamp(alpha * wrap_pi(h.pitch_sp - pitch), p.max_tilt_rate_rad_s * dt)
            d_yaw = _clamp(alpha * wrap_pi(cmd.yaw_rad - yaw) + cmd.yaw_rate_ff_rad_s * dt,
                           p.max_yaw_rate_rad_s * dt)
        hover = m.true_hover_thrust(t)
        if on_ground and (thrust <= hover or not cmd.motors_on):
            d_roll, d_pitch = -roll * alpha, -pitch * alpha
        x_roll, x_pitch, x_yaw = roll, pitch, yaw
        roll, pitch, yaw = x_roll + d_roll, x_pitch + d_pitch, wrap_pi(x_yaw + d_yaw)
        dist = m.disturbance.accel_ned_m_s2(t)
        dx, dy, dz = (float(v) for v in dist)
        t = t + dt
        c = -p.g_m_s2 * thrust / hover
        cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
        cy, sy = math.cos(yaw), math.sin(yaw)
        sx, sy_, sz = (cy * sp * cr + sy * sr) * c, (sy * sp * cr - cy * sr) * c, (cp * cr) * c
        ax = ((sx + 0.0) - p.drag_per_s * vx) + dx
        ay = ((sy_ + 0.0) - p.drag_per_s * vy) + dy
        az = ((sz + p.g_m_s2) - p.drag_per_s * vz) + dz
        x_px, x_py, x_on = px, py, on_ground
        vx, vy, vz = vx + ax * dt, vy + ay * dt, vz + az * dt
        px, py, pz = px + vx * dt, py + vy * dt, pz + vz * dt
        on_ground = False
        if pz >= p.ground_z_m:
            if az >= 0 or vz >= 0:
                if x_on:
                    px, py = x_px, x_py
                pz = p.ground_z_m
                vx = vy = vz = ax = ay = az = 0.0
                on_ground = True
            else:
                pz = p.ground_z_m
        out = ((d_roll / dt, d_pitch / dt, d_yaw / dt), (ax, ay, az), dist, hover)
    assert out is not None
    return VehicleState(t_s=t, pos_ned_m=np.array([px, py, pz]), vel_ned_m_s=np.array([vx, vy, vz]),
                        roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw,
                        euler_rates_rad_s=np.array(out[0]), acc_ned_m_s2=np.array(out[1]),
                        thrust_norm=thrust, on_ground=on_ground, disturbance_ned_m_s2=out[2],
                        hover_thrust_true=out[3])


def _bits(s: VehicleState) -> bytes:
    """Every number of the state, as its IEEE bytes (so -0.0 and NaN count too)."""
    nums = [s.t_s, *s.pos_ned_m.tolist(), *s.vel_ned_m_s.tolist(), s.roll_rad, s.pitch_rad,
            s.yaw_rad, *s.euler_rates_rad_s.tolist(), *s.acc_ned_m_s2.tolist(), s.thrust_norm,
            *s.disturbance_ned_m_s2.tolist(), s.hover_thrust_true]
    return struct.pack(f"<{len(nums)}d", *nums) + bytes([s.on_ground])


def _models() -> list[VehicleModel]:
    gusty = Disturbance(DisturbanceParams(wind_accel_ned_m_s2=(0.3, -0.2, 0.05),
                                          gust_amplitude_m_s2=0.4, gust_period_s=3.0,
                                          random_bound_m_s2=0.3, seed=5))
    return [
        VehicleModel(VehicleParams()),
        VehicleModel(VehicleParams(hover_thrust=0.55, battery_loss_per_s=0.002,
                                   battery_max_loss=0.2, drag_per_s=0.1), gusty),
    ]


def _commands(rng: np.random.Generator, k: int) -> AttitudeCommand:
    if k % 17 == 0:
        return AttitudeCommand(0.0, 0.0, 0.0, 0.0, motors_on=False)
    roll, pitch = rng.normal(0.0, 0.5, 2)  # beyond max_tilt_rad now and then
    yaw = rng.uniform(-math.pi, math.pi)
    thrust = rng.uniform(-0.1, 1.1) if k % 5 else rng.uniform(0.0, 0.3)  # some sink
    return AttitudeCommand(float(roll), float(pitch), float(yaw), float(thrust),
                           yaw_rate_ff_rad_s=float(rng.normal(0.0, 1.0)))


def test_fused_substeps_equal_the_per_substep_reference() -> None:
    rng = np.random.default_rng(3)
    crossed = {"ground": 0, "air": 0}
    for model in _models():
        for start in ((0.0, 0.0, 0.0), (1.0, -2.0, -0.5)):
            on_ground = start[2] == 0.0
            s = initial_state(start, 0.05, -0.02, 3.1, on_ground=on_ground)
            ref = s
            for k in range(400):
                cmd = _commands(rng, k)
                dur = 0.05 if k % 7 else 0.0125
                s = model.step(s, cmd, dur)
                ref = _reference_step(model, ref, cmd, dur)
                assert _bits(s) == _bits(ref), f"step {k}"
                crossed["ground" if s.on_ground else "air"] += 1
    assert crossed["ground"] > 10 and crossed["air"] > 10  # both regimes were flown
