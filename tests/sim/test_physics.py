"""Quadrotor model against analytical oracles."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from sim_bridge.physics.vehicle import (
    AttitudeCommand,
    Disturbance,
    DisturbanceParams,
    VehicleModel,
    VehicleParams,
    clip_tilt,
    euler_from_quat,
    initial_state,
    quat_from_euler,
    rot_from_euler,
)

G = 9.81
angles = st.floats(-0.5, 0.5)


def _model(**kw: float) -> VehicleModel:
    p = VehicleParams(**{"ground_z_m": 0.3, **kw})
    return VehicleModel(p, dt_s=0.0025)


def test_hover_at_hover_thrust_is_an_equilibrium() -> None:
    m = _model()
    s0 = initial_state((-0.2, 0.4, -3.2), yaw_rad=0.39)
    s = m.step(s0, AttitudeCommand(0.0, 0.0, 0.39, 0.5), 10.0)
    assert math.isclose(s.t_s, 10.0, abs_tol=1e-9)
    np.testing.assert_allclose(s.pos_ned_m, s0.pos_ned_m, atol=1e-12)
    np.testing.assert_allclose(s.vel_ned_m_s, 0.0, atol=1e-12)
    assert not s.on_ground


@settings(max_examples=60, deadline=None)
@given(roll=angles, pitch=angles, yaw=st.floats(-3.1, 3.1))
def test_tilt_with_compensated_thrust_gives_g_tan_tilt(roll: float, pitch: float,
                                                       yaw: float) -> None:
    roll, pitch = clip_tilt(roll, pitch, 0.6)
    m = _model(drag_per_s=0.0)
    s0 = initial_state((0, 0, -5), roll, pitch, yaw)
    thrust = 0.5 / (math.cos(roll) * math.cos(pitch))
    s = m.step(s0, AttitudeCommand(roll, pitch, yaw, thrust), 0.0025)
    # g tan(tilt), tilt = acos(cos(roll) cos(pitch)), written without the ill-conditioned acos
    sin_tilt = math.hypot(math.sin(pitch) * math.cos(roll), math.sin(roll))
    tan_tilt = sin_tilt / (math.cos(roll) * math.cos(pitch))
    a = s.acc_ned_m_s2
    assert abs(a[2]) < 1e-9  # altitude held
    assert math.isclose(float(np.hypot(a[0], a[1])), G * tan_tilt, rel_tol=1e-9, abs_tol=1e-12)
    # exactly the model: R(q) [0, 0, -g T / T_hover] + [0, 0, g]
    expect = rot_from_euler(roll, pitch, yaw) @ np.array([0, 0, -G * thrust / 0.5]) + [0, 0, G]
    np.testing.assert_allclose(a, expect, atol=1e-9)


def test_pitch_down_accelerates_forward() -> None:
    m = _model(drag_per_s=0.0)
    th = -0.2  # nose down (FRD)
    s = m.step(initial_state((0, 0, -5), 0.0, th, 0.0),
               AttitudeCommand(0.0, th, 0.0, 0.5 / math.cos(th)), 1.0)
    assert math.isclose(s.vel_ned_m_s[0], G * math.tan(-th) * 1.0, rel_tol=1e-6)
    assert abs(s.vel_ned_m_s[1]) < 1e-12 and abs(s.vel_ned_m_s[2]) < 1e-9


def test_attitude_is_a_first_order_response() -> None:
    m = _model(attitude_tau_s=0.08)
    s = m.step(initial_state((0, 0, -5)), AttitudeCommand(0.05, 0.0, 0.0, 0.5), 0.08)
    # small step: no rate limit, exact discrete first-order lag
    assert math.isclose(s.roll_rad, 0.05 * (1 - math.exp(-1.0)), rel_tol=1e-9)


def test_rate_and_tilt_limits() -> None:
    m = _model(max_tilt_rate_rad_s=3.0, max_tilt_rad=0.6, max_yaw_rate_rad_s=1.5)
    s1 = m.step(initial_state((0, 0, -50)), AttitudeCommand(1.2, 0.0, 1.0, 0.5), 0.1)
    assert math.isclose(s1.roll_rad, 0.3, rel_tol=1e-9)  # 3 rad/s for 0.1 s
    assert math.isclose(s1.yaw_rad, 0.15, rel_tol=1e-9)  # 1.5 rad/s for 0.1 s
    s2 = m.step(s1, AttitudeCommand(1.2, 0.0, 1.0, 0.5), 2.0)
    assert math.isclose(s2.roll_rad, 0.6, abs_tol=1e-9)  # clipped to max tilt
    r, p = clip_tilt(0.7, 0.7, 0.6)
    assert math.isclose(math.acos(math.cos(r) * math.cos(p)), 0.6, abs_tol=1e-9)
    assert math.isclose(r, p)


@settings(max_examples=50, deadline=None)
@given(roll=angles, pitch=angles, yaw=st.floats(-3.1, 3.1))
def test_quaternion_round_trip(roll: float, pitch: float, yaw: float) -> None:
    q = quat_from_euler(roll, pitch, yaw)
    assert math.isclose(float(np.linalg.norm(q)), 1.0, rel_tol=1e-12)
    np.testing.assert_allclose(euler_from_quat(q), (roll, pitch, yaw), atol=1e-9)
    # the quaternion's rotation matrix is rot_from_euler
    w, x, y, z = q
    rq = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                   [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                   [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    np.testing.assert_allclose(rq, rot_from_euler(roll, pitch, yaw), atol=1e-12)


def _fly(seed: int) -> np.ndarray:
    dist = Disturbance(DisturbanceParams(wind_accel_ned_m_s2=(0.1, -0.05, 0.0),
                                         gust_amplitude_m_s2=0.2, gust_period_s=3.0,
                                         random_bound_m_s2=0.5, random_hold_s=0.05, seed=seed))
    m = VehicleModel(VehicleParams(ground_z_m=0.3), dist, dt_s=0.0025)
    s = initial_state((0, 0, -3))
    out = []
    for k in range(200):
        cmd = AttitudeCommand(0.1 * math.sin(0.3 * k), 0.05, 0.2, 0.5)
        s = m.step(s, cmd, 0.05)
        out.append(np.r_[s.pos_ned_m, s.vel_ned_m_s, s.roll_rad, s.disturbance_ned_m_s2])
    return np.array(out)


def test_deterministic_replay_of_a_seed() -> None:
    a, b, c = _fly(7), _fly(7), _fly(8)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 1e-3


@settings(max_examples=100, deadline=None)
@given(t=st.floats(0, 1000), seed=st.integers(0, 2**31))
def test_random_disturbance_is_bounded_and_a_function_of_time(t: float, seed: int) -> None:
    p = DisturbanceParams(random_bound_m_s2=0.3, seed=seed)
    d1, d2 = Disturbance(p), Disturbance(p)
    d2.accel_ned_m_s2(t + 17.0)  # evaluation history does not matter
    v = d1.accel_ned_m_s2(t)
    assert np.linalg.norm(v) <= 0.3 + 1e-12
    np.testing.assert_array_equal(v, d2.accel_ned_m_s2(t))


def test_ground_contact() -> None:
    m = _model()
    s = m.step(initial_state((1.0, 2.0, -1.0)), AttitudeCommand(0, 0, 0, 0.2), 3.0)
    assert s.on_ground and s.pos_ned_m[2] == 0.3
    np.testing.assert_array_equal(s.vel_ned_m_s, 0.0)
    s2 = m.step(s, AttitudeCommand(0.2, 0, 0, 0.45), 2.0)  # below lift-off: stays, no sliding
    assert s2.on_ground and s2.pos_ned_m[0] == s.pos_ned_m[0] and s2.pos_ned_m[1] == 2.0
    s3 = m.step(s2, AttitudeCommand(0, 0, 0, 0.6), 1.0)  # above hover thrust: lifts off
    assert not s3.on_ground and s3.pos_ned_m[2] < 0.3 - 0.5 * 0.15 * G * 0.8
