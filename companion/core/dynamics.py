"""IBVS error dynamics of spec section 4 (the paper's eq. (1), corrected: z* in denominators).

State ``eta_e = col(s_e, v_e)`` (7): image-moment error ``s_e = s - [0, 0, 1, 0]`` and velocity
error ``v_e = v_q - v_a`` in the virtual frame (m/s, z down).
Input ``u = col(r, psidot_q)`` (4): commanded acceleration in the virtual frame (m/s^2) and yaw
rate (rad/s). Target motion (parameters): ``v_a = [v_ax, v_ay]`` (m/s, in v),
``vdot_a = [vdot_ax, vdot_ay]`` (m/s^2, derivatives of those components as seen in the rotating
frame v), ``psidot_a`` (rad/s).
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

from companion.core._backend import is_symbolic

S_REF = (0.0, 0.0, 1.0, 0.0)


def input_error(u: Any, v_a: Any, vdot_a: Any, psidot_a: Any) -> Any:
    """``u_e`` of spec 4: ``[r1 + psidot v_ay - vdot_ax, r2 - psidot v_ax - vdot_ay, r3,
    psidot - psidot_a]``."""
    vals = [
        u[0] + u[3] * v_a[1] - vdot_a[0],
        u[1] - u[3] * v_a[0] - vdot_a[1],
        u[2],
        u[3] - psidot_a,
    ]
    return _stack(vals, u)


def error_dynamics(
    eta: Any, u: Any, v_a: Any, vdot_a: Any, psidot_a: Any, z_star: float
) -> Any:
    """``f(eta_e, u)`` of spec 4: the time derivative of ``eta_e`` (shape (7,))."""
    se1, se2, se3, se4, ve1, ve2, ve3 = (eta[i] for i in range(7))
    s1, s2 = se1, se2  # s_r has zeros in components 1, 2
    psidot = u[3]
    ue = input_error(u, v_a, vdot_a, psidot_a)
    vals = [
        -ve1 / z_star + s2 * psidot,
        -ve2 / z_star - s1 * psidot,
        -ve3 / z_star,
        -psidot + psidot_a,
        psidot * ve2 + ue[0],
        -psidot * ve1 + ue[1],
        ue[2],
    ]
    del se3, se4
    return _stack(vals, eta, u)


def euler_step(
    eta: Any, u: Any, v_a: Any, vdot_a: Any, psidot_a: Any, z_star: float, dt: float
) -> Any:
    """Explicit Euler: ``eta(k+1) = eta(k) + f(eta(k), u(k)) dt``."""
    return eta + error_dynamics(eta, u, v_a, vdot_a, psidot_a, z_star) * dt


def terminal_feedforward(v_a: Any, vdot_a: Any, psidot_a: Any, psidot_q: Any) -> Any:
    """``Gamma`` of spec 7: ``[vdot_ax - psidot_q v_ay, psidot_q v_ax + vdot_ay, 0, psidot_a]``.

    With ``u = K eta + Gamma`` the input error is ``u_e = K eta`` when ``psidot_q`` is the yaw
    rate actually commanded.
    """
    vals = [vdot_a[0] - psidot_q * v_a[1], psidot_q * v_a[0] + vdot_a[1], 0.0, psidot_a]
    return _stack(vals, v_a, vdot_a)


def _stack(vals: list[Any], *like: Any) -> Any:
    if is_symbolic(*like, *vals):
        return ca.vertcat(*vals)
    return np.array([float(v) for v in vals])
