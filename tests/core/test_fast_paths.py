"""The control step's plain-float paths give the array forms' values bit for bit (the
disturbance filter's compiled step: to rounding). Replay exactness across the change rests on
this: a flight logged before must replay to the same commands."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.control.telemetry import _slerp
from companion.core.disturbance import DisturbanceEstimator, EstimatorParams
from companion.core.dynamics import error_dynamics
from companion.core.geometry import (
    body_z_from_quat,
    euler_zyx_from_quat,
    euler_zyx_from_rotation,
    real_lists_to_virtual,
    real_points_to_virtual,
    rotation_from_quat,
)
from companion.core.latency import _euler
from companion.core.moments import image_moments, image_moments_xy
from companion.core.state import build_error_state, virtual_image_points

RNG = np.random.default_rng(7)
LAM = 2.8e-3


def _unit(q: np.ndarray) -> tuple[float, float, float, float]:
    q = q / np.linalg.norm(q)
    return (float(q[0]), float(q[1]), float(q[2]), float(q[3]))


def test_quaternion_paths_are_the_matrix_paths() -> None:
    for _ in range(2000):
        q = _unit(RNG.normal(size=4))
        assert euler_zyx_from_quat(q) == euler_zyx_from_rotation(rotation_from_quat(np.array(q)))
        assert body_z_from_quat(q) == tuple(rotation_from_quat(np.array(q))[:, 2].tolist())


def test_slerp_is_numpys() -> None:
    for i in range(2000):
        q0 = np.array(_unit(RNG.normal(size=4)))
        q1 = np.array(_unit(q0 + RNG.normal(size=4) * (1e-3 if i % 2 else 0.5)))
        w = float(RNG.random())
        dot = float(q0 @ q1)
        b = -q1 if dot < 0 else q1
        dot = abs(dot)
        if dot > 0.9995:
            want = q0 + w * (b - q0)
        else:
            th = math.acos(dot)
            want = (math.sin((1 - w) * th) * q0 + math.sin(w * th) * b) / math.sin(th)
        want = want / np.linalg.norm(want)
        assert _slerp(tuple(q0.tolist()), tuple(q1.tolist()), w) == tuple(want.tolist())


def test_virtual_points_and_moments_on_floats_are_the_array_forms() -> None:
    for _ in range(1000):
        pts = RNG.normal(size=(4, 2)) * 5e-4
        phi, theta = (float(x) for x in RNG.normal(size=2) * 0.2)
        arr = real_points_to_virtual(pts, phi, theta, LAM)
        uv, nv = real_lists_to_virtual(pts[:, 0].tolist(), pts[:, 1].tolist(), phi, theta, LAM)
        assert np.array_equal(arr, np.column_stack([uv, nv]))
        for heading in (False, True):
            a = image_moments(arr, 8.036e-7, LAM, 0.3, heading_from_corners=heading)
            b = image_moments_xy(uv, nv, 8.036e-7, LAM, 0.3, heading_from_corners=heading)
            assert np.array_equal(a.s, b.s)
            assert (a.mu20, a.mu02, a.mu11, a.a) == (b.mu20, b.mu02, b.mu11, b.a)


def test_error_state_of_four_corners_is_the_generic_one() -> None:
    """The corner path of build_error_state against the array path (eight points, the same
    four twice, take the array route: compared on the parts that do not depend on N)."""
    for _ in range(500):
        pts = RNG.normal(size=(4, 2)) * 5e-4
        roll, pitch, yaw = (float(x) for x in RNG.normal(size=3) * 0.2)
        kw = dict(roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw, yaw_rate_rad_s=0.1,
                  v_q_ned_m_s=tuple(RNG.normal(size=3).tolist()),
                  v_a_ned_m_s=RNG.normal(size=3), a_a_ned_m_s2=RNG.normal(size=3),
                  psidot_a_rad_s=0.05, a_star=8.036e-7, lam=LAM, s4_prev_rad=0.1)
        es = build_error_state(pts, **kw)  # type: ignore[arg-type]
        mom = image_moments(virtual_image_points(pts, roll, pitch, LAM), 8.036e-7, LAM, 0.1)
        assert np.array_equal(es.s, mom.s)
        c, s = math.cos(yaw), math.sin(yaw)
        rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        v_q = rz.T @ np.asarray(kw["v_q_ned_m_s"], dtype=float)
        v_a = (rz.T @ kw["v_a_ned_m_s"])[:2]  # type: ignore[operator]
        want = np.concatenate([mom.s - np.array([0.0, 0.0, 1.0, 0.0]),
                               v_q - np.array([v_a[0], v_a[1], 0.0])])
        assert np.array_equal(es.eta_e, want)
        assert not es.eta_e.flags.writeable and not es.s.flags.writeable


def test_latency_euler_step_is_error_dynamics() -> None:
    for _ in range(2000):
        eta, u = RNG.normal(size=7), RNG.normal(size=4)
        va, vda = RNG.normal(size=2), RNG.normal(size=2)
        h = float(RNG.random()) * 0.01
        want = eta + h * np.asarray(error_dynamics(eta, u, va, vda, 0.2, 2.0))
        got = _euler(eta.tolist(), u.tolist(), va.tolist(), vda.tolist(), 0.2, 2.0, h)
        assert got == want.tolist()


@pytest.mark.parametrize("accelerometer", [False, True])
def test_compiled_velocity_step_is_the_numpy_filter(accelerometer: bool) -> None:
    """The velocity step against the filter's own numpy predict and general correction."""
    est = DisturbanceEstimator(EstimatorParams(accelerometer=accelerometer), 0.5)
    est.update(0.0, (0.0, 0.0, 0.0), 0.5, (0.0, 0.0, 1.0))
    for k in range(1, 200):
        t = 0.02 * k
        v = tuple((0.1 * math.sin(t), 0.05 * t, -0.02).__iter__())
        b = np.array(_unit(np.array([1.0, 0.02 * math.sin(t), 0.01, 0.0])))
        bz = rotation_from_quat(b)[:, 2]
        thrust = 0.5 + 0.01 * math.cos(t)
        x_pred, p_pred = est._predict(t, t - est.t_s, thrust, bz)  # type: ignore[operator]
        h = np.zeros((3, est.n))
        h[:, :3] = np.eye(3)
        r = est.params.velocity_noise_m_s**2
        s = h @ p_pred @ h.T + r * np.eye(3)
        k_gain = p_pred @ h.T @ np.linalg.inv(s)
        x_want = x_pred + k_gain @ (np.array(v) - x_pred[:3])
        i_kh = np.eye(est.n) - k_gain @ h
        p_want = i_kh @ p_pred @ i_kh.T + r * k_gain @ k_gain.T
        assert est.update(t, v, thrust, tuple(bz.tolist()))
        np.testing.assert_allclose(est.x, est._clip(x_want), rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(est.p, 0.5 * (p_want + p_want.T), rtol=1e-9, atol=1e-18)
        assert np.array_equal(est.p, est.p.T)
