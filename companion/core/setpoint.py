"""From the RMPC input ``u`` to an attitude/thrust setpoint for PX4 (spec section 5).

``u = [r1, r2, r3, psidot_q]``: commanded acceleration in the virtual frame ``v`` (m/s^2,
z down) and yaw rate (rad/s). Specific force ``f = [r1, r2, r3 - g]`` in ``v``; the thrust acts
along body -z, so the attitude must satisfy ``R(q_d) [0, 0, -|f|] = Rz(psi_d) f`` in NED::

    phi_d   = asin(r2 / |f|)
    theta_d = atan(r1 / (r3 - g))
    psi_d   = psi_q + psidot_q dt
    thrust  = hover_thrust |f| / g         (PX4: hover thrust gives 1 g), clamped

``q_d``: ZYX ``(phi_d, theta_d, psi_d)`` as ``[w, x, y, z]``, the attitude of body FRD relative
to NED -- what SET_ATTITUDE_TARGET carries (docs/reference/px4-offboard.md, section 1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from companion.core.errors import CoreError
from companion.core.geometry import attitude_from_accel, quat_from_euler_zyx, wrap_pi
from companion.core.params import ControlParams, RmpcParams


class SetpointError(CoreError, ValueError):
    """No setpoint can be built from these inputs (non-finite, or no upward thrust)."""


@dataclass(frozen=True, eq=False)  # holds arrays: no element-wise ==
class AttitudeSetpoint:
    """One attitude/thrust command.

    ``q_wxyz`` (4,): desired attitude, body FRD relative to NED, ``w >= 0`` (read-only);
    ``thrust_norm``: normalised collective thrust in ``[thrust_min, thrust_max]``;
    ``roll_rad, pitch_rad, yaw_rad``: the ZYX angles of ``q_wxyz`` (yaw wrapped to (-pi, pi]);
    ``yaw_rate_rad_s``: ``psidot_q`` (an Earth-frame yaw-rate feed-forward if sent);
    ``specific_force_m_s2``: ``|f|`` before clamping; ``thrust_clamped``: the clamp was active.
    """

    q_wxyz: np.ndarray
    thrust_norm: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    yaw_rate_rad_s: float
    specific_force_m_s2: float
    thrust_clamped: bool

    def __post_init__(self) -> None:
        q = np.array(self.q_wxyz, dtype=float).reshape(4)
        q.setflags(write=False)
        object.__setattr__(self, "q_wxyz", q)


def attitude_setpoint(
    u: ArrayLike,
    yaw_rad: float,
    dt_s: float,
    *,
    hover_thrust: float,
    thrust_min: float,
    thrust_max: float,
    g_m_s2: float = 9.81,
) -> AttitudeSetpoint:
    """Spec 5: the setpoint for input ``u`` (4,) at current yaw ``yaw_rad`` (psi_q, rad).

    ``dt_s`` is the control interval (``psi_d = psi_q + psidot_q dt_s``). Raises
    :class:`SetpointError` for non-finite inputs, bad thrust limits, or ``r3 >= g`` (the
    commanded specific force would not point up: no attitude realises it).
    """
    uu = np.asarray(u, dtype=float).reshape(-1)
    if uu.shape != (4,):
        raise SetpointError(f"u: expected 4 components, got shape {uu.shape}")
    scalars = {
        "yaw_rad": yaw_rad, "dt_s": dt_s, "hover_thrust": hover_thrust,
        "thrust_min": thrust_min, "thrust_max": thrust_max, "g_m_s2": g_m_s2,
    }
    if not np.all(np.isfinite(uu)):
        raise SetpointError(f"u: non-finite value {uu.tolist()}")
    for name, v in scalars.items():
        if not math.isfinite(float(v)):
            raise SetpointError(f"{name}: non-finite value")
    if not (0.0 <= thrust_min < hover_thrust < thrust_max <= 1.0):
        raise SetpointError("need 0 <= thrust_min < hover_thrust < thrust_max <= 1")
    if not (g_m_s2 > 0 and dt_s >= 0):
        raise SetpointError("need g_m_s2 > 0 and dt_s >= 0")
    r1, r2, r3, psidot = (float(x) for x in uu)
    if r3 - g_m_s2 >= 0.0:
        raise SetpointError(f"r3 = {r3} m/s^2 >= g: the thrust would not point up")
    phi_d, theta_d, f_norm = attitude_from_accel(r1, r2, r3, g_m_s2)
    phi_d, theta_d, f_norm = float(phi_d), float(theta_d), float(f_norm)
    psi_d = wrap_pi(float(yaw_rad) + psidot * float(dt_s))
    thrust_raw = hover_thrust * f_norm / g_m_s2
    thrust = min(max(thrust_raw, thrust_min), thrust_max)
    return AttitudeSetpoint(
        q_wxyz=quat_from_euler_zyx(phi_d, theta_d, psi_d),
        thrust_norm=thrust,
        roll_rad=phi_d,
        pitch_rad=theta_d,
        yaw_rad=psi_d,
        yaw_rate_rad_s=psidot,
        specific_force_m_s2=f_norm,
        thrust_clamped=thrust != thrust_raw,
    )


def attitude_setpoint_from_config(
    u: ArrayLike, yaw_rad: float, control: ControlParams, rmpc: RmpcParams
) -> AttitudeSetpoint:
    """:func:`attitude_setpoint` with ``dt_s``, ``g`` and the thrust limits from the config."""
    return attitude_setpoint(
        u, yaw_rad, rmpc.dt_s,
        hover_thrust=control.hover_thrust, thrust_min=control.thrust_min,
        thrust_max=control.thrust_max, g_m_s2=rmpc.g_m_s2,
    )


def hover_setpoint(
    yaw_rad: float, *, hover_thrust: float, thrust_min: float, thrust_max: float
) -> AttitudeSetpoint:
    """Level hover at ``yaw_rad``: ``u = 0`` (thrust = hover thrust, zero yaw rate)."""
    return attitude_setpoint(
        np.zeros(4), yaw_rad, 0.0, hover_thrust=hover_thrust, thrust_min=thrust_min,
        thrust_max=thrust_max,
    )
