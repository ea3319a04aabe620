"""The paper's scenario for the RMPC on the nominal error model (spec section 8).

Pure helpers shared by the RMPC tests and ``bench/solver.py``: the AGV path
``x_a = 0.1 t, y_a = 4 sin(0.025 t)``, ``psi_a = atan2(ydot_a, xdot_a)`` (NED, z of the top 0),
the error state ``eta_e(0)`` of a hovering quadrotor above it, the target motion over the
horizon in the virtual frame, and a closed loop ``eta(k+1) = euler_step(eta, u0) + rho(k)``.

Assumption (for ``vdot_a`` over the horizon): the quadrotor's yaw follows the AGV's heading,
``psi_q(t + tau) = psi_q(t) + psi_a(t + tau) - psi_a(t)``, so ``vdot_a = Rz^T a_a +
psidot_a [v_ay, -v_ax]`` (the derivative of ``Rz(psi_q)^T v_a_ned`` with ``psidot_q = psidot_a``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from companion.core.dynamics import euler_step
from companion.core.rmpc import Rmpc, RmpcResult, TargetMotion

AGV_SPEED_X_M_S = 0.1
AGV_AMPL_M = 4.0
AGV_OMEGA_RAD_S = 0.025


@dataclass(frozen=True)
class AgvState:
    """The AGV top at time ``t``: NED position/velocity/acceleration (x, y) and heading."""

    pos_m: np.ndarray
    vel_m_s: np.ndarray
    acc_m_s2: np.ndarray
    yaw_rad: float
    yaw_rate_rad_s: float


def paper_agv(t_s: float) -> AgvState:
    """The paper's AGV path and its derivatives (closed form)."""
    w = AGV_OMEGA_RAD_S
    x, y = AGV_SPEED_X_M_S * t_s, AGV_AMPL_M * np.sin(w * t_s)
    xd, yd = AGV_SPEED_X_M_S, AGV_AMPL_M * w * np.cos(w * t_s)
    xdd, ydd = 0.0, -AGV_AMPL_M * w * w * np.sin(w * t_s)
    yaw = float(np.arctan2(yd, xd))
    yaw_rate = float((xd * ydd - yd * xdd) / (xd * xd + yd * yd))
    return AgvState(np.array([x, y]), np.array([xd, yd]), np.array([xdd, ydd]), yaw, yaw_rate)


def _rz_t(psi: float, v: np.ndarray) -> np.ndarray:
    c, s = np.cos(psi), np.sin(psi)
    return np.array([c * v[0] + s * v[1], -s * v[0] + c * v[1]])


def initial_error(
    uav_xyz_m: tuple[float, float, float], uav_yaw_rad: float, t_s: float = 0.0,
    z_star_m: float = 2.0, agv: Callable[[float], AgvState] = paper_agv,
) -> np.ndarray:
    """``eta_e`` of a level, hovering (zero velocity) UAV above the AGV top (top at z = 0).

    ``s1, s2 = (x_v, y_v)/z*`` of the top's centre relative to the camera in the virtual frame,
    ``s3 = depth/z*``, ``s4 = psi_a - psi_q``; ``v_e = 0 - v_a`` (7,).
    """
    a = agv(t_s)
    d = _rz_t(uav_yaw_rad, a.pos_m - np.asarray(uav_xyz_m[:2], dtype=float))
    depth = 0.0 - uav_xyz_m[2]
    v_a = _rz_t(uav_yaw_rad, a.vel_m_s)
    return np.array([d[0] / z_star_m, d[1] / z_star_m, depth / z_star_m - 1.0,
                     a.yaw_rad - uav_yaw_rad, -v_a[0], -v_a[1], 0.0])


def horizon_motion(
    t_s: float, uav_yaw_rad: float, horizon: int, dt_s: float,
    agv: Callable[[float], AgvState] = paper_agv,
) -> TargetMotion:
    """The target motion over the horizon from time ``t_s`` for a UAV at yaw ``uav_yaw_rad``."""
    a0 = agv(t_s)
    v = np.zeros((horizon, 2))
    vd = np.zeros((horizon, 2))
    pd = np.zeros(horizon)
    for n in range(horizon):
        a = agv(t_s + n * dt_s)
        psi_q = uav_yaw_rad + a.yaw_rad - a0.yaw_rad
        v[n] = _rz_t(psi_q, a.vel_m_s)
        vd[n] = _rz_t(psi_q, a.acc_m_s2) + a.yaw_rate_rad_s * np.array([v[n][1], -v[n][0]])
        pd[n] = a.yaw_rate_rad_s
    return TargetMotion(v_a_m_s=v, vdot_a_m_s2=vd, psidot_a_rad_s=pd)


@dataclass(frozen=True)
class LoopStep:
    """One closed-loop step: time, the error before the step, the RMPC's result."""

    t_s: float
    eta: np.ndarray
    result: RmpcResult


def closed_loop(
    mpc: Rmpc, eta0: np.ndarray, steps: int, rho: float, seed: int, t0_s: float = 0.0,
    agv: Callable[[float], AgvState] = paper_agv,
    solve: Callable[[Rmpc, np.ndarray, TargetMotion], RmpcResult] | None = None,
) -> list[LoopStep]:
    """Run the RMPC on the nominal model plus a random disturbance with ``|rho(k)|_2 <= rho``.

    The UAV yaw is tracked through ``se4 = psi_a - psi_q``. ``solve`` (default
    ``mpc.solve``) lets a caller wrap the call (e.g. to time it).
    """
    cfg = mpc.cfg
    rng = np.random.default_rng(seed)
    eta = np.asarray(eta0, dtype=float).copy()
    out: list[LoopStep] = []
    call = solve or (lambda m, e, tm: m.solve(e, tm))
    for k in range(steps):
        t = t0_s + k * cfg.dt_s
        psi_q = agv(t).yaw_rad - eta[3]
        tm = horizon_motion(t, psi_q, cfg.horizon, cfg.dt_s, agv)
        res = call(mpc, eta, tm)
        out.append(LoopStep(t, eta.copy(), res))
        v_a, vdot_a, psidot_a = tm.stage(0)
        nxt = np.asarray(euler_step(eta, res.u0, v_a, vdot_a, psidot_a,
                                    cfg.desired_depth_m, cfg.dt_s))
        d = rng.normal(size=7)
        d *= rho * rng.uniform() ** (1.0 / 7.0) / np.linalg.norm(d)
        eta = nxt + d
    return out
