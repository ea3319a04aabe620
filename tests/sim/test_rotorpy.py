"""The rotorpy vehicle (sim.vehicle.attitude_model = "rotorpy", config/rotorpy.toml): frames,
rotorpy's own integrator and Dryden filter as oracles, hover at the vehicle's hover thrust, an
attitude step beside our rigid body, the wind's acceleration, over the interface the emulator
uses (``build_vehicle_model`` from the config file, ``step`` with an ``AttitudeCommand``)."""

from __future__ import annotations

import ast
import dataclasses
import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("rotorpy")

import rotorpy
from rotorpy.vehicles.multirotor import Multirotor

from sim_bridge.config import load_config, with_sim
from sim_bridge.physics.px4_control import Px4Gains
from sim_bridge.physics.rigid_body import Px4VehicleModel
from sim_bridge.physics.rotorpy_vehicle import (
    RotorpyAirframe,
    RotorpyVehicleModel,
    enu_from_ned,
    ned_from_enu,
    quad_params,
)
from sim_bridge.physics.rotorpy_wind import (
    DrydenParams,
    DrydenWind,
    GustCoefficients,
    dryden_length_scales_m,
)
from sim_bridge.physics.vehicle import (
    AttitudeCommand,
    DisturbanceParams,
    VehicleState,
    euler_from_quat,
    initial_state,
    quat_from_euler,
)
from sim_bridge.vehicle_model import build_vehicle_model

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "rotorpy.toml"


def _rotorpy_dryden_classes() -> dict[str, Any]:
    """rotorpy's own ``GustModelBase`` and ``DrydenWind`` from its installed source (the module
    imports torch at the top, which the extra does not install; the two classes use numpy)."""
    src = (Path(rotorpy.__file__).parent / "wind" / "dryden_utils.py").read_text()
    with warnings.catch_warnings():  # its __main__ block has a '\\s' escape (a warning)
        warnings.simplefilter("ignore")
        tree = ast.parse(src)
    body = [n for n in tree.body if isinstance(n, ast.ClassDef)
            and n.name in ("GustModelBase", "DrydenWind")]
    ns: dict[str, Any] = {"np": np}
    exec(compile(ast.Module(body=body, type_ignores=[]), "rotorpy/wind/dryden_utils.py", "exec"),
         ns)
    return ns


def _ideal_world() -> Any:
    cfg = load_config(CONFIG, scenario="paper")
    sim = cfg.sim
    vehicle = dataclasses.replace(sim.vehicle, hover_thrust_error=0.0, mass_error=0.0,
                                  motor_curve_factor=0.0)
    battery = dataclasses.replace(sim.battery, thrust_loss_per_min=0.0, max_thrust_loss=0.0)
    still = dataclasses.replace(sim.disturbance, wind_accel_ned_m_s2=(0.0, 0.0, 0.0),
                                turbulence_std_m_s2=0.0)
    return with_sim(cfg, vehicle=vehicle, battery=battery, disturbance=still)


def _airborne(cfg: Any) -> VehicleState:
    x, y, z, r, p, yaw = cfg.scenario.uav_pose
    return initial_state((x, y, z), r, p, yaw)


# ------------------------------------------------------------------------------------------ frames
@pytest.mark.parametrize("euler", [(0.1, 0.2, 0.3), (-0.5, 0.1, 2.5), (0.0, 0.0, -3.0)])
def test_attitude_round_trips_between_ned_frd_and_enu_flu(euler: tuple[float, float, float]
                                                          ) -> None:
    q = tuple(float(v) for v in quat_from_euler(*euler))
    back = euler_from_quat(np.array(ned_from_enu(np.array(enu_from_ned(q)))))  # type: ignore[arg-type]
    assert back == pytest.approx(euler, abs=1e-12)
    # the body z axis (FRD down) is minus rotorpy's body z (FLU up), in the other world frame
    x, y, z, w = enu_from_ned(q)  # type: ignore[arg-type]
    r_enu = Multirotor.rotate_k(np.array([x, y, z, w]))
    r_ned = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1.0]]) @ r_enu
    w0, x0, y0, z0 = q
    down_ned = [2 * (x0 * z0 + w0 * y0), 2 * (y0 * z0 - w0 * x0), w0**2 - x0**2 - y0**2 + z0**2]
    assert r_ned == pytest.approx(-np.array(down_ned), abs=1e-12)


def test_rotor_layout_is_px4_quad_x_and_hovers_at_the_true_hover_thrust() -> None:
    for thr_mdl_fac, curve in ((0.0, 0.0), (0.0, 0.3), (0.4, 0.3)):
        p = quad_params(RotorpyAirframe(true_hover_thrust=0.573, motor_curve_factor=curve),
                        thr_mdl_fac)
        # PX4's motor 1 is front-right: x forward, y right = FLU y negative; spins so that its
        # yaw torque is about FRD +z (FLU -z)
        assert p["rotor_pos"]["r1"][:2] == pytest.approx([0.1202, -0.1202], abs=1e-4)
        assert list(p["rotor_directions"]) == [-1, -1, 1, 1]
        m = RotorpyVehicleModel(Px4Gains(thr_mdl_fac=thr_mdl_fac),
                                RotorpyAirframe(true_hover_thrust=0.573, motor_curve_factor=curve))
        assert m.true_hover_thrust(0.0) == pytest.approx(0.573, abs=1e-12)


def test_true_hover_thrust_over_the_flight_equals_the_rigid_bodys() -> None:
    """Payload, motor curve and battery sag: the same hover thrust as our rigid body's in the
    same world (what PX4's modes fly with before OFFBOARD)."""
    cfg_r = load_config(CONFIG, scenario="paper")
    cfg_p = load_config(ROOT / "config" / "realistic.toml", scenario="paper")
    mr, mp = build_vehicle_model(cfg_r), build_vehicle_model(cfg_p)
    assert isinstance(mr, RotorpyVehicleModel) and isinstance(mp, Px4VehicleModel)
    for t in (0.0, 60.0, 251.0, 2000.0):
        assert mr.true_hover_thrust(t) == pytest.approx(mp.true_hover_thrust(t), abs=1e-9)
    assert mr.true_hover_thrust(251.0) > mr.true_hover_thrust(0.0) + 0.03


# --------------------------------------------------------------------------- rotorpy as the oracle
def test_rk4_integration_matches_rotorpys_own_step() -> None:
    """Our fixed-step RK4 of rotorpy's derivative against rotorpy's ``Multirotor.step``
    (scipy RK45) on the same rotor commands: a roll-and-yaw manoeuvre with wind and aero."""
    m = RotorpyVehicleModel(Px4Gains(), RotorpyAirframe(true_hover_thrust=0.5))
    x: np.ndarray = np.array(m.initial_cascade(initial_state((0.0, 0.0, -3.0))).rotorpy_state)
    x[13:16] = (0.5, -0.3, 0.1)
    state = Multirotor._unpack_state(x.copy())
    oracle = Multirotor(m.quad, control_abstraction="cmd_motor_speeds", aero=True,
                        enable_ground=True,
                        integrator_kwargs={"method": "RK45", "rtol": 1e-9, "atol": 1e-12})
    wh = m.w_hover_rad_s
    for i in range(200):  # 0.5 s
        cmd = np.array([wh * 1.03, wh * 0.97, wh * 0.99, wh * 1.01]) if i < 60 else np.full(4, wh)
        x = m._rk4(x, cmd)  # the float transcription of rotorpy's derivative, RK4
        state = oracle.step(state, {"cmd_motor_speeds": cmd}, m.dt_s)
    ref = Multirotor._pack_state(state)
    assert abs(x[3] - ref[3]) + abs(x[4] - ref[4]) > 0  # it moved: a real comparison
    assert np.linalg.norm(x[:3] - ref[:3]) < 1e-5
    assert np.linalg.norm(x[3:6] - ref[3:6]) < 1e-5
    assert np.linalg.norm(x[6:10] - ref[6:10]) < 1e-6
    assert np.linalg.norm(x[16:] - ref[16:]) < 1e-3  # rad/s of ~470


def test_dryden_port_equals_rotorpys_filter() -> None:
    """rotorpy's ``DrydenWind.getWind`` (its source, global numpy noise) and our recursion on the
    same noise sequence give the same wind."""
    ns = _rotorpy_dryden_classes()
    altitude, dt, sigma, mean = 3.5, 0.05, (0.7, 1.3, 0.4), (0.2, -0.1, 0.05)
    theirs = ns["DrydenWind"](*mean, *sigma, altitude)
    n = 400
    np.random.seed(7)
    noise = np.random.uniform(-1.0, 1.0, size=(n, 3))  # the order getWind draws them: x, y, z
    np.random.seed(7)
    ref = np.array([theirs.getWind(dt) for _ in range(n)])
    coef = [GustCoefficients.of(L, s, dt)
            for L, s in zip(dryden_length_scales_m(altitude), sigma, strict=True)]
    mem = [(0.0, 0.0, 0.0, 0.0)] * 3
    ours = np.zeros((n, 3))
    for k in range(n):
        for i in range(3):
            y, mem[i] = coef[i].run(mem[i], float(noise[k, i]))
            ours[k, i] = mean[i] + y
    assert np.abs(ref - np.array(mean)).max() > 0.05  # turbulent: a real comparison
    assert ours == pytest.approx(ref, abs=1e-12)


def test_dryden_wind_has_the_configured_std_and_is_seeded() -> None:
    """rotorpy's sigma is not the wind's std (it depends on the step); ours is."""
    p = DrydenParams(mean_m_s=(0.3, 0.0, 0.0), std_m_s=(0.0, 0.0, 0.1), altitude_m=2.0,
                     dt_s=0.05, seed=3)
    w = DrydenWind(p)
    s = w.initial()
    s = w.at(s, 30.0)  # past the filter's start-up (L_z / V = 2 s)
    zs, xs = [], []
    for k in range(s.k + 1, s.k + 40_001):
        s = w.advance_from(s, k)
        xs.append(s.wind_m_s[0])
        zs.append(s.wind_m_s[2])
    assert np.std(zs) == pytest.approx(0.1, rel=0.1)
    assert np.mean(zs) == pytest.approx(0.0, abs=0.02)
    assert set(xs) == {0.3}  # no turbulence asked on x: the mean alone
    again = DrydenWind(p).at(DrydenWind(p).initial(), 30.0)
    assert again == w.at(w.initial(), 30.0)
    other = DrydenWind(dataclasses.replace(p, seed=4))
    assert other.at(other.initial(), 30.0).wind_m_s != again.wind_m_s


# --------------------------------------------------------------- over the emulator's interface
def test_config_switch_builds_rotorpy_and_names_the_missing_extra(
        monkeypatch: pytest.MonkeyPatch) -> None:
    from sim_bridge import ConfigError

    cfg = load_config(CONFIG, scenario="edge")
    assert cfg.sim.vehicle.attitude_model == "rotorpy"
    assert cfg.sim.vehicle.level == "realistic"  # the realistic world underneath
    assert isinstance(build_vehicle_model(cfg), RotorpyVehicleModel)
    monkeypatch.setitem(__import__("sys").modules, "sim_bridge.physics.rotorpy_vehicle", None)
    with pytest.raises(ConfigError, match=r"pip install '\.\[rotorpy\]'"):
        build_vehicle_model(cfg)


def test_hover_holds_altitude_at_the_hover_thrust() -> None:
    """The ideal vehicle hovers at MPC_THR_HOVER; the realistic one at its true hover thrust
    (0.573 at the start), and at MPC_THR_HOVER (0.5) it sinks."""
    cfg = _ideal_world()
    m = build_vehicle_model(cfg)
    s0 = _airborne(cfg)
    s = s0
    for _ in range(200):  # 10 s
        s = m.step(s, AttitudeCommand(0.0, 0.0, s0.yaw_rad, cfg.sim.vehicle.hover_thrust), 0.05)
    assert cfg.sim.vehicle.hover_thrust == 0.5
    assert np.linalg.norm(s.pos_ned_m - s0.pos_ned_m) < 1e-3
    assert abs(s.yaw_rad - s0.yaw_rad) < 1e-4 and abs(s.roll_rad) < 1e-4
    assert not s.on_ground

    real = load_config(CONFIG, scenario="paper")
    still = dataclasses.replace(real.sim.disturbance, wind_accel_ned_m_s2=(0.0, 0.0, 0.0),
                                turbulence_std_m_s2=0.0)
    real = with_sim(real, disturbance=still)
    m = build_vehicle_model(real)
    held = sunk = _airborne(real)
    for _ in range(200):
        held = m.step(held, AttitudeCommand(0.0, 0.0, s0.yaw_rad,
                                            m.true_hover_thrust(held.t_s)), 0.05)
        sunk = m.step(sunk, AttitudeCommand(0.0, 0.0, s0.yaw_rad,
                                            real.sim.vehicle.hover_thrust), 0.05)
    assert m.true_hover_thrust(0.0) == pytest.approx(0.573, abs=1e-3)
    assert abs(held.pos_ned_m[2] - s0.pos_ned_m[2]) < 0.01
    assert sunk.pos_ned_m[2] - s0.pos_ned_m[2] > 1.0  # 0.5 of 0.573: -1.25 m/s^2


def _roll_step(model: Any, s: VehicleState, step_rad: float, thrust: float
               ) -> tuple[np.ndarray, np.ndarray]:
    ts, ys = [], []
    cmd = AttitudeCommand(step_rad, 0.0, s.yaw_rad, thrust / math.cos(step_rad))
    t0 = s.t_s
    for _ in range(400):  # 1 s at the physics step
        s = model.step(s, cmd, model.dt_s)
        ts.append(s.t_s - t0)
        ys.append(s.roll_rad)
    return np.array(ts), np.array(ys)


def _rise_s(t: np.ndarray, y: np.ndarray, final: float) -> float:
    return float(t[np.argmax(y >= 0.9 * final)] - t[np.argmax(y >= 0.1 * final)])


def test_roll_step_follows_like_our_rigid_body() -> None:
    """A 10 deg roll setpoint step through PX4's cascade: rotorpy's Hummingbird against our
    x500-like rigid body with the same gains (both scaled to the same hover thrust)."""
    cfg = _ideal_world()
    rp = build_vehicle_model(cfg)
    rb = build_vehicle_model(with_sim(cfg, vehicle=dataclasses.replace(
        cfg.sim.vehicle, attitude_model="px4")))
    assert isinstance(rb, Px4VehicleModel)
    step = math.radians(10.0)
    s0 = _airborne(cfg)
    t, y_rp = _roll_step(rp, s0, step, 0.5)
    _, y_rb = _roll_step(rb, s0, step, 0.5)
    rise_rp, rise_rb = _rise_s(t, y_rp, step), _rise_s(t, y_rb, step)
    print(f"roll 10 deg step: rise 10-90 % {rise_rp * 1e3:.1f} ms (rotorpy Hummingbird) vs "
          f"{rise_rb * 1e3:.1f} ms (rigid body x500); overshoot {y_rp.max() / step - 1:.3%} vs "
          f"{y_rb.max() / step - 1:.3%}")
    gains = Px4Gains()
    assert rise_rp < 2.197 / gains.att_p[0]  # no slower than the attitude P alone
    assert rise_rp == pytest.approx(rise_rb, rel=0.25)
    assert y_rp.max() < step * 1.05
    assert y_rp[-1] == pytest.approx(step, abs=math.radians(0.2))


def test_pitch_up_accelerates_south_and_the_wind_pushes_downwind() -> None:
    cfg = _ideal_world()
    m = build_vehicle_model(cfg)
    s = _airborne(cfg)
    for _ in range(10):
        s = m.step(s, AttitudeCommand(0.0, math.radians(5.0), s.yaw_rad, 0.5), 0.05)
    back = -np.array([math.cos(s.yaw_rad), math.sin(s.yaw_rad)])  # nose up: backwards
    assert s.vel_ned_m_s[:2] @ back > 0.2
    assert abs(s.vel_ned_m_s[0] * back[1] - s.vel_ned_m_s[1] * back[0]) < 1e-3
    assert s.acc_ned_m_s2[:2] @ back > 0.3

    windy = with_sim(cfg, disturbance=dataclasses.replace(
        cfg.sim.disturbance, wind_accel_ned_m_s2=(0.1, -0.05, 0.0)))
    m = build_vehicle_model(windy)
    assert isinstance(m, RotorpyVehicleModel)
    s0 = _airborne(windy)
    s = m.step(s0, AttitudeCommand(0.0, 0.0, s0.yaw_rad, 0.5), 0.05)
    # at rest in a steady wind the drag of the air speed is the configured acceleration
    assert s.disturbance_ned_m_s2[:2] == pytest.approx([0.1, -0.05], abs=3e-3)
    for _ in range(400):  # 20 s: it drifts to the wind's speed
        s = m.step(s, AttitudeCommand(0.0, 0.0, s0.yaw_rad, 0.5), 0.05)
    cx, _ = m.drag_per_s
    assert s.vel_ned_m_s[:2] == pytest.approx([0.1 / cx, -0.05 / cx], rel=0.05)


def test_step_is_a_pure_function_of_its_inputs() -> None:
    cfg = load_config(CONFIG, scenario="yaw-offset")  # realistic: battery, wind, turbulence
    m = build_vehicle_model(cfg)
    s0 = _airborne(cfg)
    cmd = AttitudeCommand(0.05, -0.03, 0.2, 0.6)
    a = m.step(m.step(s0, cmd, 0.05), cmd, 0.05)
    b = m.step(m.step(s0, cmd, 0.05), cmd, 0.05)
    assert np.array_equal(a.pos_ned_m, b.pos_ned_m) and a.cascade == b.cascade
    # a second model from the same config flies the same (seeded wind)
    c = build_vehicle_model(cfg).step(m.step(s0, cmd, 0.05), cmd, 0.05)
    assert np.array_equal(a.pos_ned_m, c.pos_ned_m)


def test_turbulence_becomes_dryden_wind_of_the_configured_strength() -> None:
    cfg = load_config(CONFIG, scenario="paper")
    m = build_vehicle_model(cfg)
    assert isinstance(m, RotorpyVehicleModel)
    cx, cz = m.drag_per_s
    std = cfg.sim.disturbance.turbulence_std_m_s2
    assert std == 0.05
    assert m.dryden.params.std_m_s == pytest.approx((std / cx, std / cx, 0.5 * std / cz))
    assert 0.4 < cx < 0.5  # rotorpy's Hummingbird rotor drag at hover, 1/s
    off = RotorpyVehicleModel(Px4Gains(), RotorpyAirframe(), DisturbanceParams())
    assert off.dryden.params.std_m_s == (0.0, 0.0, 0.0)


def test_float_derivative_equals_rotorpys() -> None:
    """The float transcription against rotorpy's ``Multirotor._s_dot_fn`` on random states:
    tilted, spinning, in wind, non-unit quaternions (RK4's stages), on and above the ground."""
    m = RotorpyVehicleModel(Px4Gains(), RotorpyAirframe(true_hover_thrust=0.5, mass_error=0.05))
    quad = dict(m.quad)
    quad["k_flap"] = 2e-5  # the Hummingbird has none: give the flapping term something to do
    quad["Ixy"], quad["Ixz"] = 1e-4, -2e-4  # and a full inertia matrix
    from sim_bridge.physics.rotorpy_dynamics import RotorpyDerivative

    for aero in (True, False):
        ours = RotorpyDerivative(quad, aero=aero, enable_ground=True)
        theirs = Multirotor(quad, control_abstraction="cmd_motor_speeds", aero=aero,
                            enable_ground=True)
        rng = np.random.default_rng(11)
        for i in range(200):
            x = np.concatenate([rng.normal(size=3), rng.normal(size=3) * 3,
                                rng.normal(size=4), rng.normal(size=3) * 4,
                                rng.normal(size=3) * 2, rng.uniform(0, 700, size=4)])
            if i % 4 == 0:
                x[2] = 0.0  # on the ground: the normal force
            cmd = rng.uniform(0, 700, size=4)
            ref = theirs._s_dot_fn(0.0, x, cmd)
            got = ours(x, cmd)
            assert got == pytest.approx(ref, rel=1e-9, abs=1e-9), i


def test_ground_contact_equals_rotorpys() -> None:
    m = RotorpyVehicleModel(Px4Gains(), RotorpyAirframe(true_hover_thrust=0.5))
    theirs = Multirotor(m.quad, control_abstraction="cmd_motor_speeds", aero=True,
                        enable_ground=True)
    rng = np.random.default_rng(2)
    for _ in range(50):
        x = rng.normal(size=20)
        x[2] = -abs(x[2]) * 1e-3
        x[6:10] /= np.linalg.norm(x[6:10])
        assert m.derivative.on_ground(x) and theirs._on_ground(Multirotor._unpack_state(x))
        ref = Multirotor._pack_state(theirs._handle_vehicle_on_ground(
            Multirotor._unpack_state(x.copy())))
        got = m.derivative.ground_contact(x)
        assert got[:6] == pytest.approx(ref[:6], abs=1e-12)
        assert got[10:] == pytest.approx(ref[10:], abs=1e-12)
        # the same rotation (q and -q alike)
        assert abs(float(got[6:10] @ ref[6:10])) == pytest.approx(1.0, abs=1e-12)


def test_lifts_off_from_the_ground_and_lands_back() -> None:
    cfg = _ideal_world()
    m = build_vehicle_model(cfg)
    s = initial_state((0.0, 0.0, cfg.ground_z_m), on_ground=True)
    s = m.step(s, AttitudeCommand(0.0, 0.0, 0.0, 0.3), 1.0)  # below hover: stays put
    assert s.on_ground and s.pos_ned_m[2] == pytest.approx(cfg.ground_z_m)
    s = m.step(s, AttitudeCommand(0.0, 0.0, 0.0, 0.7), 1.0)
    assert not s.on_ground and s.pos_ned_m[2] < cfg.ground_z_m - 0.5
    s = m.step(s, AttitudeCommand(0.0, 0.0, 0.0, 0.3), 3.0)
    assert s.on_ground and s.pos_ned_m[2] == pytest.approx(cfg.ground_z_m)
