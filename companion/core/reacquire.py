"""Reacquisition law: follow the target's predicted position while it is out of sight.

Used by the safety supervisor's ``REACQUIRE`` level when the camera has lost the target but the
AGV's own FOLLOW_TARGET state is fresh (published IBVS stacks simply stop; users ask for this).
A PD law on the horizontal position error (in the virtual frame), a climb at a bounded rate to
widen the view (up to a height limit above the target) and a yaw rate towards the target's
heading; every component clipped to the RMPC's input box. Returns ``u = (r1, r2, r3,
psidot_q)`` in the same units and frame as the RMPC's input, so the same setpoint mapping
(spec 5) turns it into an attitude and thrust.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.core.geometry import rot_z, wrap_pi


@dataclass(frozen=True)
class ReacquireGains:
    kp_per_s2: float = 0.5
    kd_per_s: float = 1.2
    kz_per_s: float = 1.5
    kyaw_per_s: float = 0.8


def reacquire_input(
    rel_pos_ned_m: np.ndarray,
    v_q_ned_m_s: np.ndarray,
    v_a_ned_m_s: np.ndarray,
    a_a_ned_m_s2: np.ndarray,
    yaw_q_rad: float,
    yaw_a_rad: float,
    height_above_target_m: float,
    climb_rate_m_s: float,
    max_height_m: float,
    u_max: tuple[float, float, float, float],
    gains: ReacquireGains = ReacquireGains(),
) -> np.ndarray:
    """``u`` (4,) steering the vehicle over the target (``rel_pos = target - vehicle``, NED)."""
    vals = [rel_pos_ned_m, v_q_ned_m_s, v_a_ned_m_s, a_a_ned_m_s2,
            [yaw_q_rad, yaw_a_rad, height_above_target_m]]
    if not all(np.all(np.isfinite(np.asarray(v, dtype=float))) for v in vals):
        raise ValueError("reacquire_input: non-finite input")
    rzt = rot_z(yaw_q_rad).T
    e_xy = (rzt @ np.asarray(rel_pos_ned_m, dtype=float))[:2]
    ev_xy = (rzt @ (np.asarray(v_a_ned_m_s, float) - np.asarray(v_q_ned_m_s, float)))[:2]
    ff_xy = (rzt @ np.asarray(a_a_ned_m_s2, dtype=float))[:2]
    r12 = gains.kp_per_s2 * e_xy + gains.kd_per_s * ev_xy + ff_xy
    vz_des = -climb_rate_m_s if height_above_target_m < max_height_m else 0.0
    r3 = gains.kz_per_s * (vz_des - float(v_q_ned_m_s[2]))
    psidot = gains.kyaw_per_s * wrap_pi(yaw_a_rad - yaw_q_rad)
    u = np.array([r12[0], r12[1], r3, psidot])
    lim = np.asarray(u_max, dtype=float)
    out: np.ndarray = np.clip(u, -lim, lim)
    return out
