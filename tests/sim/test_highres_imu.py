"""HIGHRES_IMU (docs/reference/wire.md): the accelerometer reads the true specific force in body
FRD, i.e. everything acting on the vehicle but gravity (thrust, drag, wind, turbulence); 50 Hz on
the
offboard link as PX4's "onboard" MAVLink mode streams it, stamped on the autopilot clock; in the
realistic telemetry with a constant bias and white noise."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from sim_bridge.app import SimBridge
from sim_bridge.config import TelemetryConfig
from sim_bridge.physics.px4_control import Px4Gains
from sim_bridge.physics.rigid_body import AirframeParams, Px4VehicleModel
from sim_bridge.physics.vehicle import (
    AttitudeCommand,
    Disturbance,
    DisturbanceParams,
    VehicleModel,
    VehicleParams,
    initial_state,
)
from tests.sim.harness import MavClient, sim_with_client

G = 9.81


def test_hover_reads_minus_g_along_body_z() -> None:
    """At rest in a level hover the accelerometer reads (0, 0, -g) whatever the yaw."""
    m = VehicleModel(VehicleParams(hover_thrust=0.5), dt_s=0.0025)
    s = m.step(initial_state((0.0, 0.0, -3.0), yaw_rad=1.1), AttitudeCommand(0, 0, 1.1, 0.5), 1.0)
    np.testing.assert_allclose(SimBridge.specific_force_frd(s), [0.0, 0.0, -G], atol=1e-9)


def test_tilted_accelerating_vehicle_with_drag_and_wind() -> None:
    """Tilted 0.3 rad, thrust above hover, flying (drag) in a wind: in body axes the thrust
    has no x/y part, so f_xy is the rotated sum of drag and wind alone, and f_z adds the
    thrust, -g T / T_hover. The vehicle's acceleration (what a differentiated velocity gives)
    is f rotated to NED plus gravity. (The reading is the last 2.5 ms physics step's force,
    whose drag acts on the velocity at the start of that step: 1e-3 m/s^2 here.)"""
    wind = (0.4, -0.3, 0.1)
    m = VehicleModel(VehicleParams(hover_thrust=0.5, drag_per_s=0.2, max_tilt_rate_rad_s=10),
                     Disturbance(DisturbanceParams(wind_accel_ned_m_s2=wind)), dt_s=0.0025)
    cmd = AttitudeCommand(0.3, -0.2, 0.7, 0.6)
    s = m.step(initial_state((0.0, 0.0, -30.0), yaw_rad=0.7), cmd, 2.0)
    rot = s.rot_body_to_ned
    other = np.asarray(wind) - 0.2 * s.vel_ned_m_s  # everything but thrust and gravity
    assert np.linalg.norm(s.vel_ned_m_s) > 1.0  # it is moving: drag matters
    f = SimBridge.specific_force_frd(s)
    np.testing.assert_allclose(f[:2], (rot.T @ other)[:2], atol=2e-3)
    assert math.isclose(f[2], -G * 0.6 / 0.5 + (rot.T @ other)[2], abs_tol=2e-3)
    # the accelerometer is the vehicle's acceleration less gravity
    v0 = s.vel_ned_m_s
    s2 = m.step(s, cmd, 0.0025)
    np.testing.assert_allclose(rot @ f + [0, 0, G], (s2.vel_ned_m_s - v0) / 0.0025, atol=0.02)


def test_px4_model_turbulence_reaches_the_accelerometer() -> None:
    """PX4's cascade holding a level attitude in turbulence: the body x/y specific force is the
    turbulence (and drag) rotated into body axes, at every sampled instant."""
    dist = Disturbance(DisturbanceParams(turbulence_std_m_s2=0.3, seed=4, random_hold_s=0.05))
    m = Px4VehicleModel(Px4Gains(), AirframeParams(drag_per_s=0.1), dist, dt_s=0.0025)
    s = initial_state((0.0, 0.0, -10.0), yaw_rad=0.5)
    seen = []
    for _ in range(40):
        s = m.step(s, AttitudeCommand(0.0, 0.0, 0.5, 0.5), 0.05)
        f = SimBridge.specific_force_frd(s)
        other = s.disturbance_ned_m_s2 - 0.1 * s.vel_ned_m_s
        np.testing.assert_allclose(f[:2], (s.rot_body_to_ned.T @ other)[:2], atol=2e-3)
        seen.append(np.linalg.norm(f[:2]))
    assert max(seen) > 0.1  # the turbulence is there to be read


def _imu(msgs: list) -> list:
    return [m for m in msgs if m.get_type() == "HIGHRES_IMU"]


def test_highres_imu_on_the_wire_hovering(client: MavClient) -> None:
    """Real UDP, the default world: ~50 Hz, stamped on the autopilot clock (time_usec next to
    ATTITUDE's time_boot_ms), reading the true specific force of the hovering vehicle."""
    with sim_with_client(client) as rs:
        msgs = client.collect(1.0)
        truth = rs.call(lambda: SimBridge.specific_force_frd(rs.sim.state))
    imu = _imu(msgs)
    assert len(imu) >= 15, len(imu)
    assert all(m.fields_updated & 0b111 == 0b111 for m in imu)
    att_ms = [m.time_boot_ms for m in msgs if m.get_type() == "ATTITUDE"]
    assert abs(imu[-1].time_usec / 1000 - att_ms[-1]) < 50
    stamps = [m.time_usec for m in imu]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
    # 50 Hz on the autopilot clock (the stamps, not the wall clock of a loaded machine)
    assert 19_000 <= float(np.median(np.diff(stamps))) <= 25_000, np.diff(stamps)
    for m in imu[5:]:
        np.testing.assert_allclose([m.xacc, m.yacc, m.zacc], [0.0, 0.0, -G], atol=0.05)
    np.testing.assert_allclose([imu[-1].xacc, imu[-1].yacc, imu[-1].zacc], truth, atol=0.05)


def test_realistic_accelerometer_has_its_bias_and_noise(client: MavClient) -> None:
    """``[sim.telemetry]`` with PX4's rates, a bias and 0.35 m/s^2 of noise: 50 Hz on the
    offboard link (PX4's onboard mode), and the samples scatter about truth + bias with that
    std."""
    bias = (0.1, -0.08, 0.15)
    tm = dataclasses.replace(TelemetryConfig(), rates="px4", accel_noise_m_s2=0.35,
                             accel_bias_m_s2=bias)
    with sim_with_client(client, telemetry=tm):
        imu = _imu(client.collect(3.0))
    assert len(imu) >= 40, len(imu)
    assert 19_000 <= float(np.median(np.diff([m.time_usec for m in imu]))) <= 25_000
    a = np.array([[m.xacc, m.yacc, m.zacc] for m in imu]) - [0.0, 0.0, -G]
    n = len(a)
    err = a.mean(axis=0) - bias
    assert np.all(np.abs(err) < 4 * 0.35 / math.sqrt(n)), err  # hovering: truth ~ (0, 0, -g)
    std = a.std(axis=0)
    assert np.all((std > 0.25) & (std < 0.45)), std


def test_velocity_noise_scatters_local_position_ned_only(client: MavClient) -> None:
    """``sim.telemetry.velocity_noise_m_s``: LOCAL_POSITION_NED's velocity scatters about the
    truth (a hovering vehicle: ~0) with that std; its position and the other streams do not."""
    tm = dataclasses.replace(TelemetryConfig(), velocity_noise_m_s=0.05)
    with sim_with_client(client, telemetry=tm):
        msgs = client.collect(3.0)
    lp = [m for m in msgs if m.get_type() == "LOCAL_POSITION_NED"]
    assert len(lp) >= 40, len(lp)
    v = np.array([[m.vx, m.vy, m.vz] for m in lp])
    std = v.std(axis=0)
    assert np.all((std > 0.035) & (std < 0.065)), std
    assert np.all(np.abs(v.mean(axis=0)) < 4 * 0.05 / math.sqrt(len(lp)) + 0.01), v.mean(axis=0)
    pos = np.array([[m.x, m.y, m.z] for m in lp])
    assert np.all(pos.std(axis=0) < 0.01), pos.std(axis=0)  # a hover: the position is still
    imu = _imu(msgs)
    a = np.array([[m.xacc, m.yacc, m.zacc] for m in imu])
    assert np.all(a.std(axis=0) < 0.05), a.std(axis=0)  # the accelerometer stays noise-free
