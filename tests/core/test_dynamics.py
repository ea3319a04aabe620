"""Spec 9, section 4: finite differences of eta_e(t) along a simulated flight match f.

The flight is analytic: the target moves and turns on a horizontal plane; the quadrotor
translates, yaws at a varying rate and rolls/pitches independently of its acceleration (the
virtual camera must cancel any roll/pitch). eta_e(t) is measured the way the companion
measures it (real-image projection of the target's corners, virtual mapping, moments,
velocities in v); f is companion.core.dynamics.error_dynamics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import casadi as ca
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.core.dynamics import (
    error_dynamics,
    euler_step,
    input_error,
    terminal_feedforward,
)
from companion.core.geometry import (
    project_points,
    rectangle_corners_m,
    rot_z,
    rotation_zyx,
    world_to_camera,
)
from companion.core.moments import a_star
from companion.core.state import build_error_state, target_motion_in_virtual

LAM = 2.8e-3
Z_STAR = 2.0
AGV = rectangle_corners_m(0.5, 0.4)
A_STAR = a_star(AGV, Z_STAR, LAM)


@dataclass(frozen=True)
class Flight:
    # Target: p_a = c + V t + A [cos(wa t + ph), sin(wa t + ph), 0]; yaw psi_a0 + wpsi t.
    c: np.ndarray
    v_lin: np.ndarray
    amp: float
    wa: float
    ph: float
    psi_a0: float
    wpsi: float
    # Quad relative to the target: d = d0 + B sin(wq t); yaw psi0 + wy t + cy sin(t).
    d0: np.ndarray
    b: np.ndarray
    wq: float
    psi0: float
    wy: float
    cy: float
    # Roll/pitch (not tied to the acceleration): phi0 + 0.1 sin(2t), theta0 + 0.1 cos(3t).
    phi0: float
    theta0: float

    def target(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
        w, a = self.wa, self.amp
        arg = w * t + self.ph
        p = self.c + self.v_lin * t + a * np.array([math.cos(arg), math.sin(arg), 0.0])
        v = self.v_lin + a * w * np.array([-math.sin(arg), math.cos(arg), 0.0])
        acc = -a * w * w * np.array([math.cos(arg), math.sin(arg), 0.0])
        return p, v, acc, self.psi_a0 + self.wpsi * t, self.wpsi

    def quad(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[float, ...], float]:
        pa, va, aa, _, _ = self.target(t)
        s = math.sin(self.wq * t)
        c = math.cos(self.wq * t)
        p = pa + self.d0 + self.b * s
        v = va + self.b * self.wq * c
        acc = aa - self.b * self.wq**2 * s
        psi = self.psi0 + self.wy * t + self.cy * math.sin(t)
        psidot = self.wy + self.cy * math.cos(t)
        att = (self.phi0 + 0.1 * math.sin(2 * t), self.theta0 + 0.1 * math.cos(3 * t), psi)
        return p, v, acc, att, psidot


def measure(fl: Flight, t: float, s4_prev: float | None = None) -> tuple[np.ndarray, ...]:
    """eta_e(t), the input u(t) that produced the motion, and the target parameters."""
    pa, va, aa, psi_a, psidot_a = fl.target(t)
    pq, vq, aq, att, psidot_q = fl.quad(t)
    xy = AGV @ rot_z(psi_a)[:2, :2].T + pa[:2]
    corners = np.column_stack([xy, np.full(4, pa[2])])
    real = project_points(world_to_camera(corners, pq, rotation_zyx(*att)), LAM)
    st_ = build_error_state(
        real, roll_rad=att[0], pitch_rad=att[1], yaw_rad=att[2], yaw_rate_rad_s=psidot_q,
        v_q_ned_m_s=vq, v_a_ned_m_s=va, a_a_ned_m_s2=aa, psidot_a_rad_s=psidot_a,
        a_star=A_STAR, lam=LAM, s4_prev_rad=s4_prev,
    )
    r = rot_z(att[2]).T @ aq  # commanded acceleration in v = the acceleration flown
    u = np.array([r[0], r[1], r[2], psidot_q])
    m = st_.motion
    return st_.eta_e, u, m.v_a_m_s, m.vdot_a_m_s2, np.array([m.psidot_a_rad_s])


fin = st.floats


@st.composite
def flights(draw: st.DrawFn) -> Flight:
    return Flight(
        c=np.array([draw(fin(-5, 5)), draw(fin(-5, 5)), 0.0]),
        v_lin=np.array([draw(fin(-1, 1)), draw(fin(-1, 1)), 0.0]),
        amp=draw(fin(0, 3)), wa=draw(fin(-0.5, 0.5)), ph=draw(fin(-3, 3)),
        psi_a0=draw(fin(-3, 3)), wpsi=draw(fin(-0.5, 0.5)),
        d0=np.array([draw(fin(-0.8, 0.8)), draw(fin(-0.8, 0.8)), draw(fin(-4, -2.2))]),
        b=np.array([draw(fin(-0.3, 0.3)), draw(fin(-0.3, 0.3)), draw(fin(-0.2, 0.2))]),
        wq=draw(fin(0, 2)), psi0=draw(fin(-3, 3)), wy=draw(fin(-0.6, 0.6)),
        cy=draw(fin(-0.3, 0.3)), phi0=draw(fin(-0.25, 0.25)), theta0=draw(fin(-0.25, 0.25)),
    )


H = 1e-4  # central differences: truncation ~ H^2 |eta'''| / 6 ~ 1e-8, rounding ~ 1e-12 / H


@settings(max_examples=60, deadline=None)
@given(fl=flights(), t=fin(0, 20))
def test_finite_differences_of_measured_state_match_f(fl: Flight, t: float) -> None:
    eta0, u, v_a, vdot_a, psidot_a = measure(fl, t)
    eta_p = measure(fl, t + H, s4_prev=float(eta0[3]))[0]
    eta_m = measure(fl, t - H, s4_prev=float(eta0[3]))[0]
    fd = (eta_p - eta_m) / (2 * H)
    f = error_dynamics(eta0, u, v_a, vdot_a, float(psidot_a[0]), Z_STAR)
    np.testing.assert_allclose(f, fd, rtol=1e-6, atol=2e-7)


def test_the_check_is_sensitive_to_the_rotation_terms() -> None:
    """On a turning flight, dropping the psidot terms of f would break the FD match."""
    fl = Flight(
        c=np.zeros(3), v_lin=np.array([0.3, 0.1, 0.0]), amp=2.0, wa=0.3, ph=0.2, psi_a0=0.5,
        wpsi=0.2, d0=np.array([0.5, -0.4, -3.0]), b=np.array([0.2, 0.1, 0.1]), wq=1.0,
        psi0=0.3, wy=0.4, cy=0.1, phi0=0.1, theta0=-0.1,
    )
    eta0, u, v_a, vdot_a, psidot_a = measure(fl, 1.3)
    fd = (measure(fl, 1.3 + H, float(eta0[3]))[0] - measure(fl, 1.3 - H, float(eta0[3]))[0])
    fd = fd / (2 * H)
    f = error_dynamics(eta0, u, v_a, vdot_a, float(psidot_a[0]), Z_STAR)
    np.testing.assert_allclose(f, fd, rtol=1e-6, atol=2e-7)
    u_no_yaw = u.copy()
    u_no_yaw[3] = 0.0
    f_wrong = error_dynamics(eta0, u_no_yaw, v_a, vdot_a, float(psidot_a[0]), Z_STAR)
    assert np.max(np.abs(f_wrong - fd)) > 1e-2


def test_paper_path_from_the_paper_start() -> None:
    """The paper's AGV path (heading = direction of travel) and start, hovering quad."""

    def agv(t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
        p = np.array([0.1 * t, 4 * math.sin(0.025 * t), 0.0])
        v = np.array([0.1, 0.1 * math.cos(0.025 * t), 0.0])
        a = np.array([0.0, -0.0025 * math.sin(0.025 * t), 0.0])
        psidot = (v[0] * a[1] - v[1] * a[0]) / (v[0] ** 2 + v[1] ** 2)
        return p, v, a, math.atan2(v[1], v[0]), psidot

    pq, vq, aq, att = np.array([-0.2, 0.4, -3.2]), np.zeros(3), np.zeros(3), (0, 0, math.pi / 8)
    for t in (0.0, 30.0, 70.0):

        def eta_at(tt: float, prev: float | None) -> tuple[np.ndarray, object]:
            pa, va, aa, psi_a, psidot_a = agv(tt)
            xy = AGV @ rot_z(psi_a)[:2, :2].T + pa[:2]
            corners = np.column_stack([xy, np.zeros(4)])
            # The quad hovers: it stays put.
            real = project_points(world_to_camera(corners, pq, rotation_zyx(*att)), LAM)
            st_ = build_error_state(
                real, roll_rad=0, pitch_rad=0, yaw_rad=att[2], yaw_rate_rad_s=0.0,
                v_q_ned_m_s=vq, v_a_ned_m_s=va, a_a_ned_m_s2=aa, psidot_a_rad_s=psidot_a,
                a_star=A_STAR, lam=LAM, s4_prev_rad=prev,
            )
            return st_.eta_e, st_.motion

        eta0, motion = eta_at(t, None)
        fd = (eta_at(t + H, eta0[3])[0] - eta_at(t - H, eta0[3])[0]) / (2 * H)
        f = error_dynamics(eta0, np.array([*aq, 0.0]), motion.v_a_m_s, motion.vdot_a_m_s2,
                           motion.psidot_a_rad_s, Z_STAR)
        np.testing.assert_allclose(f, fd, rtol=1e-6, atol=2e-7)


def test_numpy_and_casadi_agree() -> None:
    rng = np.random.default_rng(3)
    eta, u = rng.normal(size=7), rng.normal(size=4)
    v_a, vdot_a, psidot_a = rng.normal(size=2), rng.normal(size=2), 0.3
    x, uu = ca.SX.sym("x", 7), ca.SX.sym("u", 4)
    fun = ca.Function("f", [x, uu], [error_dynamics(x, uu, v_a, vdot_a, psidot_a, Z_STAR)])
    np.testing.assert_allclose(
        np.asarray(fun(eta, u)).ravel(), error_dynamics(eta, u, v_a, vdot_a, psidot_a, Z_STAR),
        rtol=1e-14,
    )
    np.testing.assert_allclose(
        euler_step(eta, u, v_a, vdot_a, psidot_a, Z_STAR, 0.05),
        eta + 0.05 * error_dynamics(eta, u, v_a, vdot_a, psidot_a, Z_STAR), rtol=1e-15,
    )


@given(psi=fin(-3, 3), psidot_q=fin(-1, 1), v=st.tuples(fin(-2, 2), fin(-2, 2), fin(-1, 1)),
       a=st.tuples(fin(-2, 2), fin(-2, 2), fin(-1, 1)),
       r=st.tuples(fin(-1.5, 1.5), fin(-1.5, 1.5), fin(-1.5, 1.5)))
def test_input_error_is_acceleration_relative_to_the_target(
    psi: float, psidot_q: float, v: tuple[float, float, float], a: tuple[float, float, float],
    r: tuple[float, float, float],
) -> None:
    """With vdot_a built at the commanded yaw rate, u_e[:2] = r - [Rz^T a_a]_xy (no psidot
    left), and the terminal feed-forward Gamma gives u_e = 0 when psidot_q = psidot_a."""
    m = target_motion_in_virtual(v, a, psidot_q, psi, psidot_q)
    u = np.array([*r, psidot_q])
    ue = input_error(u, m.v_a_m_s, m.vdot_a_m_s2, psidot_q)
    np.testing.assert_allclose(ue[:2], np.asarray(r[:2]) - m.accel_a_v_m_s2, atol=1e-12)
    assert ue[2] == r[2] and ue[3] == 0.0
    gamma = terminal_feedforward(m.v_a_m_s, m.vdot_a_m_s2, psidot_q, psidot_q)
    ue_g = input_error(gamma, m.v_a_m_s, m.vdot_a_m_s2, psidot_q)
    np.testing.assert_allclose(ue_g, np.zeros(4), atol=1e-12)
