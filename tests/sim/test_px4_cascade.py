"""The emulator's PX4 attitude response (sim.vehicle.attitude_model = "px4") against independent
implementations of PX4's equations with the same gains: the attitude law through scipy's
rotations, the closed roll loop as a finely integrated linear single-axis model, the thrust
mapping and the allocator's saturation by hand."""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from sim_bridge import ConfigError
from sim_bridge.config import config_from_dict, load_config, read_toml
from sim_bridge.physics.px4_control import (
    Px4Gains,
    RateState,
    allocate,
    attitude_control,
    rate_control,
    saturation_flags,
    thrust_curve,
    thrust_curve_inverse,
)
from sim_bridge.physics.rigid_body import AirframeParams, Px4VehicleModel
from sim_bridge.physics.vehicle import (
    AttitudeCommand,
    Disturbance,
    DisturbanceParams,
    initial_state,
)
from sim_bridge.vehicle_model import build_vehicle_model

ROOT = Path(__file__).resolve().parents[2]
G = 9.81


def _rot(q_wxyz: tuple[float, ...]) -> Rotation:
    w, x, y, z = q_wxyz
    return Rotation.from_quat([x, y, z, w])


def _oracle_rate_sp(
    q: tuple[float, ...], qd: tuple[float, ...], ff: float, gains: Px4Gains
) -> np.ndarray:
    """PX4's attitude law (Brescianini et al. 2013 as in AttitudeControl.cpp) with scipy."""
    r, rd = _rot(q), _rot(qd)
    ez, ezd = r.as_matrix()[:, 2], rd.as_matrix()[:, 2]
    axis = np.cross(ez, ezd)
    ang = math.atan2(np.linalg.norm(axis), float(ez @ ezd))
    tilt = (
        Rotation.from_rotvec(axis / np.linalg.norm(axis) * ang)
        if np.linalg.norm(axis) > 1e-12
        else Rotation.identity()
    )
    red = tilt * r  # reduced attitude: current yaw, desired tilt
    dyaw = (red.inv() * rd).as_rotvec()  # a rotation about the body z axis
    assert abs(dyaw[0]) < 1e-9 and abs(dyaw[1]) < 1e-9
    target = red * Rotation.from_rotvec([0.0, 0.0, gains.yaw_weight * dyaw[2]])
    err = (r.inv() * target).as_rotvec()  # angle <= pi
    th = float(np.linalg.norm(err))
    eq = err / th * 2 * math.sin(th / 2) if th > 0 else np.zeros(3)
    p = np.array([gains.att_p[0], gains.att_p[1], gains.att_p[2] / gains.yaw_weight])
    rate = eq * p + r.as_matrix().T[:, 2] * ff
    lim = np.array(gains.rate_max_rad_s)
    return np.asarray(np.clip(rate, -lim, lim))


_angle = st.floats(-1.2, 1.2)


@settings(max_examples=200, deadline=None)
@given(
    _angle, _angle, st.floats(-3.1, 3.1), _angle, _angle, st.floats(-3.1, 3.1), st.floats(-1.0, 1.0)
)
def test_attitude_law_matches_px4_equations(
    r: float, p: float, y: float, rd: float, pd: float, yd: float, ff: float
) -> None:
    gains = Px4Gains()
    q = tuple(Rotation.from_euler("ZYX", [y, p, r]).as_quat()[[3, 0, 1, 2]])
    qd = tuple(Rotation.from_euler("ZYX", [yd, pd, rd]).as_quat()[[3, 0, 1, 2]])
    got = np.array(attitude_control(q, qd, ff, gains))  # type: ignore[arg-type]
    assert np.allclose(got, _oracle_rate_sp(q, qd, ff, gains), atol=1e-9)


def test_attitude_p_step_is_p_times_error_then_limited() -> None:
    gains = Px4Gains()
    level = (1.0, 0.0, 0.0, 0.0)
    for roll in (0.05, 0.3, 1.0):
        qd = tuple(Rotation.from_euler("x", roll).as_quat()[[3, 0, 1, 2]])
        sp = attitude_control(level, qd, 0.0, gains)  # type: ignore[arg-type]
        want = min(6.5 * 2 * math.sin(roll / 2), math.radians(220))
        assert sp[0] == pytest.approx(want, rel=1e-12) and abs(sp[1]) < 1e-12


def test_rate_controller_pid_integrator_and_saturation() -> None:
    gains = Px4Gains()
    dt = 0.0025
    s = RateState(integral=(0.1, -0.05, 0.0))
    torque, s2 = rate_control((0.0, 0.0, 0.0), (1.0, -0.5, 0.2), s, dt, False, gains)
    # no angular acceleration yet: P e + I (PX4 RateControl::update)
    assert torque == pytest.approx((0.15 * 1.0 + 0.1, 0.15 * -0.5 - 0.05, 0.2 * 0.2))
    f = 1 - (1.0 / math.radians(400)) ** 2  # PX4's i_factor
    assert s2.integral[0] == pytest.approx(0.1 + f * 0.2 * 1.0 * dt)
    _, landed = rate_control((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), s, dt, True, gains)
    assert landed.integral == s.integral  # frozen on the ground
    sat = dataclasses.replace(s, sat_pos=(True, False, False))
    _, frozen = rate_control((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), sat, dt, False, gains)
    assert frozen.integral[0] == s.integral[0]  # no wind-up into the saturated direction
    big = RateState()
    for _ in range(10000):
        _, big = rate_control((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), big, dt, False, gains)
    assert big.integral == pytest.approx((0.3, 0.3, 0.3))  # MC_*R_INT_LIM


def _linear_roll_loop(
    gains: Px4Gains, air: AirframeParams, step_rad: float, duration_s: float, h: float = 1e-4
) -> tuple[np.ndarray, np.ndarray]:
    """Single-axis roll loop of PX4's cascade, continuous-time, integrated at ``h``: attitude
    P on 2 sin(e/2), rate PID with the D term on the filtered gyro derivative, motor lag on the
    torque (linear thrust curve), inertia."""
    f_max = air.mass_kg * G / (4 * air.true_hover_thrust)
    torque_per_unit = 4 * air.arm_xy_m * math.sqrt(0.5) * f_max  # N m per normalised torque
    wc = 2 * math.pi * gains.dgyro_cutoff_hz
    th = w = integ = acc_f = tau_m = 0.0
    w_prev = 0.0
    ts, out = [], []
    for k in range(int(duration_s / h)):
        w_sp = gains.att_p[0] * 2 * math.sin((step_rad - th) / 2)
        w_sp = max(-gains.rate_max_rad_s[0], min(gains.rate_max_rad_s[0], w_sp))
        acc_f += (1 - math.exp(-wc * h)) * ((w - w_prev) / h - acc_f)
        w_prev = w
        e = w_sp - w
        u = gains.rate_p[0] * e + integ - gains.rate_d[0] * acc_f
        integ += gains.rate_i[0] * e * h
        tau_m += (u * torque_per_unit - tau_m) * (1 - math.exp(-h / air.motor_tau_s))
        w += tau_m / air.inertia_kg_m2[0] * h
        th += w * h
        ts.append((k + 1) * h)
        out.append(th)
    return np.array(ts), np.array(out)


def _rise_time(t: np.ndarray, y: np.ndarray, final: float) -> float:
    return float(t[np.argmax(y >= 0.9 * final)] - t[np.argmax(y >= 0.1 * final)])


def test_closed_loop_roll_step_matches_the_linear_px4_loop() -> None:
    gains, air = Px4Gains(), AirframeParams(ground_z_m=10.0)
    model = Px4VehicleModel(gains, air, dt_s=0.0025)
    step = math.radians(10)
    s = initial_state((0.0, 0.0, -3.0))
    cmd = AttitudeCommand(step, 0.0, 0.0, air.true_hover_thrust)
    ts, roll = [], []
    for k in range(400):
        s = model.step(s, cmd, 0.0025)
        ts.append((k + 1) * 0.0025)
        roll.append(s.roll_rad)
    t_o, y_o = _linear_roll_loop(gains, air, step, 1.0)
    t_e, y_e = np.array(ts), np.array(roll)
    rise_e, rise_o = _rise_time(t_e, y_e, step), _rise_time(t_o, y_o, step)
    print(
        f"roll 10 deg step: rise 10-90 % {rise_e * 1e3:.1f} ms (emulator, 400 Hz) vs "
        f"{rise_o * 1e3:.1f} ms (linear oracle); overshoot {y_e.max() / step - 1:.3%} vs "
        f"{y_o.max() / step - 1:.3%}"
    )
    assert rise_e == pytest.approx(rise_o, rel=0.1)
    assert y_e.max() / step - 1 == pytest.approx(y_o.max() / step - 1, abs=0.02)
    assert abs(y_e[-1] - step) < math.radians(0.1)  # integrator: no steady error
    # and not a first-order lag with the attitude gain alone (the rate loop and motors count)
    assert rise_e < 2.197 / gains.att_p[0]


@pytest.mark.parametrize(("thr_mdl_fac", "true_curve"), [(0.0, 0.0), (0.3, 0.3), (0.0, 0.3)])
def test_thrust_mapping_hover_and_off_hover(thr_mdl_fac: float, true_curve: float) -> None:
    gains = Px4Gains(thr_mdl_fac=thr_mdl_fac)
    air = AirframeParams(true_hover_thrust=0.56, motor_curve_factor=true_curve, drag_per_s=0.0)
    model = Px4VehicleModel(gains, air, dt_s=0.0025)

    def vertical_acc(thrust: float) -> float:
        s = initial_state((0.0, 0.0, -50.0))
        s = model.step(s, AttitudeCommand(0.0, 0.0, 0.0, thrust), 0.5)  # motors settle
        return float(s.acc_ned_m_s2[2])

    assert abs(vertical_acc(0.56)) < 1e-6
    # off hover: the true relative thrust through PX4's inversion and the true curve
    rel = [thrust_curve(thrust_curve_inverse(t, thr_mdl_fac), true_curve) for t in (0.5, 0.56)]
    assert vertical_acc(0.5) == pytest.approx(G * (1 - rel[0] / rel[1]), rel=1e-3)
    assert model.true_hover_thrust(0.0) == pytest.approx(0.56, abs=1e-12)


def test_allocation_keeps_roll_and_reduces_thrust_at_saturation() -> None:
    u, unalloc = allocate((0.3, 0.0, 0.0), 0.95)
    d = 0.3 * math.sqrt(0.5)
    # airmode off: the top motors would reach 0.95 + d > 1: thrust drops so roll is kept
    assert sorted(u) == pytest.approx([1 - 2 * d, 1 - 2 * d, 1.0, 1.0])
    assert max(abs(v) for v in unalloc) < 1e-9
    u, unalloc = allocate((3.0, 0.0, 0.0), 0.5)  # more roll than the motors have
    assert all(0.0 <= v <= 1.0 for v in u) and sorted(u) == pytest.approx([0, 0, 1, 1])
    pos, neg = saturation_flags(unalloc)
    assert pos == (True, False, False) and neg == (False, False, False)


def test_full_thrust_saturates_the_motors() -> None:
    air = AirframeParams(true_hover_thrust=0.5, drag_per_s=0.0)
    model = Px4VehicleModel(Px4Gains(), air, dt_s=0.0025)
    s = model.step(initial_state((0.0, 0.0, -50.0)), AttitudeCommand(0.5, 0.0, 0.0, 1.0), 1.0)
    assert s.cascade is not None and all(0.0 <= f <= 1.0 + 1e-12 for f in s.cascade.motors)
    assert np.linalg.norm(s.acc_ned_m_s2 - [0, 0, G]) <= 2 * G + 1e-6  # 4 F_max / m = 2 g


def test_battery_sag_raises_the_hover_thrust() -> None:
    air = AirframeParams(true_hover_thrust=0.5, battery_loss_per_s=0.001, battery_max_loss=0.1)
    model = Px4VehicleModel(Px4Gains(), air)
    assert model.true_hover_thrust(0.0) == pytest.approx(0.5)
    assert model.true_hover_thrust(50.0) == pytest.approx(0.5 / 0.95)
    assert model.true_hover_thrust(1000.0) == pytest.approx(0.5 / 0.9)


def test_realistic_config_loads_and_builds_the_px4_world() -> None:
    cfg = load_config(ROOT / "config" / "realistic.toml")
    sim = cfg.sim
    assert sim.vehicle.attitude_model == "px4" and sim.vehicle.level == "realistic"
    assert sim.vehicle.hover_thrust == 0.5  # what the autopilot (and the companion) believe
    assert sim.camera_model.level == "realistic" and sim.telemetry.level == "realistic"
    assert sim.battery.thrust_loss_per_min > 0 and sim.disturbance.turbulence_std_m_s2 > 0
    assert cfg.camera.calibration_file
    model = build_vehicle_model(cfg)
    assert isinstance(model, Px4VehicleModel)
    h0, h_end = model.true_hover_thrust(0.0), model.true_hover_thrust(sim.duration_s)
    assert 0.55 < h0 < h_end < 0.65
    paper = load_config(ROOT / "config" / "paper.toml")
    assert paper.sim.vehicle.attitude_model == "first-order"
    assert build_vehicle_model(paper).true_hover_thrust(100.0) == 0.5


@pytest.mark.parametrize(
    ("key", "value", "msg"),
    [
        ("attitude_model", "pid", "sim.vehicle.attitude_model"),
        ("level", "bad", "sim.vehicle.level"),
        ("mass_error", 2.0, "sim.vehicle.mass_error"),
        ("true_hover_thrust", 0.97, "sim.vehicle.true_hover_thrust"),
    ],
)
def test_bad_vehicle_keys_name_themselves(key: str, value: object, msg: str) -> None:
    data = read_toml(ROOT / "config" / "paper.toml")
    data["sim"]["vehicle"][key] = value
    with pytest.raises(ConfigError, match=re.escape(msg)):
        config_from_dict(data)


def test_bad_px4_control_key() -> None:
    data = read_toml(ROOT / "config" / "paper.toml")
    data["sim"]["px4_control"] = {"mc_yaw_weight": 1.5}
    with pytest.raises(ConfigError, match=re.escape("sim.px4_control.mc_yaw_weight")):
        config_from_dict(data)
    data["sim"]["px4_control"] = {"mc_rol_p": 1.0}
    with pytest.raises(ConfigError, match="unknown key"):
        config_from_dict(data)


def test_body_rate_setpoint_goes_to_the_rate_loop() -> None:
    model = Px4VehicleModel(Px4Gains(), AirframeParams(ground_z_m=10.0), dt_s=0.0025)
    s = initial_state((0.0, 0.0, -3.0))
    cmd = AttitudeCommand(0.0, 0.0, 0.0, 0.5, body_rates_frd_rad_s=(0.5, 0.0, -0.3))
    s = model.step(s, cmd, 2.0)  # (the gyroscopic coupling p r is for the integrators)
    assert s.rates_frd_rad_s == pytest.approx([0.5, 0.0, -0.3], abs=0.01)


def test_turbulence_is_seeded_stationary_and_independent_of_the_step() -> None:
    params = DisturbanceParams(
        turbulence_std_m_s2=0.2, turbulence_tau_s=1.0, random_hold_s=0.05, seed=5
    )
    a, b = Disturbance(params), Disturbance(params)
    ts = np.arange(0.0, 1000.0, 0.05)
    xs = np.array([a.accel_ned_m_s2(t) for t in ts])
    # another evaluation pattern (fine steps, a jump back) gives the same function of time
    for t in (0.0, 0.0125, 3.7, 1.2, 999.97):
        assert np.array_equal(b.accel_ned_m_s2(t), xs[math.floor(t / 0.05)])
    std = xs.std(axis=0)
    assert std == pytest.approx([0.2, 0.2, 0.1], rel=0.15)
    lag = round(1.0 / 0.05)  # one correlation time: autocorrelation e^-1
    r = np.corrcoef(xs[:-lag, 0], xs[lag:, 0])[0, 1]
    assert r == pytest.approx(math.exp(-1), abs=0.1)
    other = Disturbance(dataclasses.replace(params, seed=6))
    assert not np.array_equal(xs[:100], [other.accel_ned_m_s2(t) for t in ts[:100]])


def test_first_order_model_flies_the_imperfect_vehicle() -> None:
    data = read_toml(ROOT / "config" / "paper.toml")
    data["sim"]["vehicle"]["level"] = "realistic"
    data["sim"]["battery"] = {"level": "realistic"}
    cfg = config_from_dict(data)
    model = build_vehicle_model(cfg)
    true0 = 0.5 * 1.1 * 1.05  # hover_thrust_error 0.1, mass_error 0.05
    assert model.true_hover_thrust(0.0) == pytest.approx(true0)
    assert model.true_hover_thrust(120.0) == pytest.approx(true0 / (1 - 0.03))  # 1.5 %/min
    s = initial_state((0.0, 0.0, -3.0))
    s = model.step(s, AttitudeCommand(0.0, 0.0, 0.0, true0), 1.0)
    assert abs(s.pos_ned_m[2] + 3.0) < 1e-3  # (the sag over 1 s moves it < 1 mm)
    s = model.step(initial_state((0.0, 0.0, -3.0)), AttitudeCommand(0.0, 0.0, 0.0, 0.5), 1.0)
    assert s.pos_ned_m[2] + 3.0 > 0.3  # the configured MPC_THR_HOVER sinks
