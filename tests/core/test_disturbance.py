"""The offset-free estimator (companion/core/disturbance.py) against a simulated vehicle.

The oracle is the emulator's translational model written out here (PX4's thrust mapping,
``a = g e_z - g T / h_true R e_z + d``): the filter must find ``h_true`` and ``d``, reject bad
data without touching its estimate, and stay inside its bounds.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion import ConfigError
from companion.config import load_config
from companion.core.disturbance import (
    DisturbanceEstimator,
    EstimatorParams,
    compensated_input,
)
from companion.core.errors import ParamError
from companion.core.geometry import rot_z, rotation_from_quat
from companion.core.setpoint import attitude_setpoint

G = 9.81
DT = 0.05


def fly(est: DisturbanceEstimator, h_true: float, d_true: np.ndarray, steps: int,
        seed: int = 0, noise: float = 0.005) -> np.ndarray:
    """Hover the simulated vehicle with the estimate's compensation (u = 0, slowly yawing
    and tilting a little so every axis is excited); returns the true velocity at the end."""
    rng = np.random.default_rng(seed)
    v = np.zeros(3)
    t = 0.0
    for k in range(steps):
        e = est.estimate()
        u = np.array([0.3 * math.sin(0.7 * k * DT), 0.3 * math.cos(0.5 * k * DT), 0.0, 0.0])
        yaw = 0.1 * k * DT
        sp = attitude_setpoint(compensated_input(u, e.d_ned_m_s2, yaw), yaw, 0.0,
                               hover_thrust=e.hover_thrust, thrust_min=0.05, thrust_max=0.95)
        b = rotation_from_quat(sp.q_wxyz)[:, 2]
        a = np.array([0.0, 0.0, G]) - G * sp.thrust_norm / h_true * b + d_true
        v = v + a * DT
        t += DT
        est.update(t, v + rng.normal(0.0, noise, 3), sp.thrust_norm, b)
    return v


@pytest.mark.parametrize("h_cfg", [0.35, 0.5, 0.65])
def test_finds_the_true_hover_thrust_and_a_wind(h_cfg: float) -> None:
    d = np.array([0.4, -0.3, 0.0])
    est = DisturbanceEstimator(EstimatorParams(), h_cfg)
    fly(est, 0.5, d, 200)
    e = est.estimate()
    assert e.hover_thrust == pytest.approx(0.5, abs=0.005)
    assert np.allclose(e.d_ned_m_s2[:2], d[:2], atol=0.05)
    assert e.rejected == 0 and e.updates == 199


def test_hover_converges_within_a_second() -> None:
    est = DisturbanceEstimator(EstimatorParams(), 0.35)
    fly(est, 0.5, np.zeros(3), 20)  # 1 s
    assert est.estimate().hover_thrust == pytest.approx(0.5, abs=0.01)


def test_compensated_input_realises_the_acceleration_asked_for() -> None:
    """With the true hover thrust and disturbance, the setpoint built from the compensated
    input gives the vehicle exactly the acceleration ``u[0:3]`` (in the virtual frame)."""
    h, d, yaw = 0.62, np.array([0.5, -0.2, 0.3]), 0.8
    u = np.array([0.7, -0.4, 0.5, 0.1])
    sp = attitude_setpoint(compensated_input(u, d, yaw), yaw, 0.0, hover_thrust=h,
                           thrust_min=0.05, thrust_max=0.95)
    b = rotation_from_quat(sp.q_wxyz)[:, 2]
    a_ned = np.array([0.0, 0.0, G]) - G * sp.thrust_norm / h * b + d
    assert np.allclose(rot_z(yaw).T @ a_ned, u[:3], atol=1e-9)


bad = st.sampled_from([math.nan, math.inf, -math.inf])


@settings(max_examples=30, deadline=None)
@given(which=st.integers(0, 3), value=bad)
def test_bad_data_never_changes_the_estimate(which: int, value: float) -> None:
    est = DisturbanceEstimator(EstimatorParams(), 0.35)
    fly(est, 0.5, np.array([0.2, 0.1, 0.0]), 40)
    before = est.estimate()
    x_before = est.x.copy()
    v = [0.0, 0.0, 0.0]
    thrust = 0.5
    b = [0.0, 0.0, 1.0]
    t = (est.t_s or 0.0) + DT
    if which == 0:
        v[1] = value
    elif which == 1:
        thrust = value
    elif which == 2:
        b[2] = value
    else:
        t = value
    assert not est.update(t, v, thrust, b)
    after = est.estimate()
    assert after.rejected == before.rejected + 1
    assert np.array_equal(est.x, x_before)
    assert math.isfinite(after.hover_thrust) and all(map(math.isfinite, after.d_ned_m_s2))


def test_an_outlier_velocity_is_rejected() -> None:
    est = DisturbanceEstimator(EstimatorParams(), 0.5)
    fly(est, 0.5, np.zeros(3), 40)
    h = est.estimate().hover_thrust
    assert not est.update((est.t_s or 0) + DT, [0.0, 0.0, 50.0], 0.5, [0.0, 0.0, 1.0])
    assert "outlier" in est.reason
    assert est.estimate().hover_thrust == h


def test_estimate_stays_within_its_bounds() -> None:
    """A vehicle that would need 0.9 (beyond hover_max 0.8): the estimate stops at the bound,
    the disturbance at its own."""
    est = DisturbanceEstimator(EstimatorParams(), 0.5)
    fly(est, 0.9, np.array([5.0, 0.0, 0.0]), 100)
    e = est.estimate()
    assert e.hover_thrust == pytest.approx(0.8)
    assert max(abs(x) for x in e.d_ned_m_s2) <= 3.0 + 1e-12


def test_without_a_command_only_the_velocity_is_anchored() -> None:
    est = DisturbanceEstimator(EstimatorParams(), 0.4)
    for k in range(10):
        assert est.update(k * DT, [0.0, 0.0, 1.0 * k], None, None)
    assert est.estimate().hover_thrust == pytest.approx(0.4)
    assert est.estimate().updates == 0


def test_config_keys_are_validated() -> None:
    cfg = load_config()
    assert cfg.control.estimator.enabled and cfg.control.latency.enabled
    with pytest.raises(ConfigError, match="hover_min"):
        load_config(overrides=["control.estimator.hover_min=0.9"])
    with pytest.raises(ConfigError, match="hover_thrust"):
        load_config(overrides=["control.hover_thrust=0.85"])
    with pytest.raises(ConfigError, match="velocity_noise_m_s"):
        load_config(overrides=["control.estimator.velocity_noise_m_s=0"])
    with pytest.raises(ConfigError, match="actuation_delay_s"):
        load_config(overrides=["control.latency.actuation_delay_s=-1"])
    with pytest.raises(ParamError):
        EstimatorParams(hover_noise_per_sqrt_s=math.nan)
