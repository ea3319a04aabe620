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
from companion.core.frozen import make
from companion.core.geometry import quat_from_euler_zyx, wrap_pi
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
        q = self.q_wxyz
        if not (isinstance(q, np.ndarray) and q.dtype == np.float64 and q.shape == (4,)
                and q.base is None and not q.flags.writeable):
            q = np.array(q, dtype=float).reshape(4)
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
    if isinstance(u, list | tuple) and len(u) == 4:
        vals = [float(x) for x in u]  # the control step's path: no array
    else:
        uu = np.asarray(u, dtype=float).reshape(-1)
        if uu.shape != (4,):
            raise SetpointError(f"u: expected 4 components, got shape {uu.shape}")
        vals = uu.tolist()
    if not all(map(math.isfinite, vals)):
        raise SetpointError(f"u: non-finite value {vals}")
    for name, v in (("yaw_rad", yaw_rad), ("dt_s", dt_s), ("hover_thrust", hover_thrust),
                    ("thrust_min", thrust_min), ("thrust_max", thrust_max),
                    ("g_m_s2", g_m_s2)):
        if not math.isfinite(float(v)):
            raise SetpointError(f"{name}: non-finite value")
    if not (0.0 <= thrust_min < hover_thrust < thrust_max <= 1.0):
        raise SetpointError("need 0 <= thrust_min < hover_thrust < thrust_max <= 1")
    if not (g_m_s2 > 0 and dt_s >= 0):
        raise SetpointError("need g_m_s2 > 0 and dt_s >= 0")
    r1, r2, r3, psidot = vals
    if r3 - g_m_s2 >= 0.0:
        raise SetpointError(f"r3 = {r3} m/s^2 >= g: the thrust would not point up")
    # attitude_from_accel's formulas on plain floats (math's functions give numpy's values)
    f_norm = math.sqrt(r1 * r1 + r2 * r2 + (r3 - g_m_s2) * (r3 - g_m_s2))
    phi_d = math.asin(r2 / f_norm)
    theta_d = math.atan(r1 / (r3 - g_m_s2))
    psi_d = wrap_pi(float(yaw_rad) + psidot * float(dt_s))
    thrust_raw = hover_thrust * f_norm / g_m_s2
    thrust = min(max(thrust_raw, thrust_min), thrust_max)
    # (quat_from_euler_zyx's array is owned and read-only, as __post_init__ makes it)
    return make(
        AttitudeSetpoint, q_wxyz=quat_from_euler_zyx(phi_d, theta_d, psi_d),
        thrust_norm=thrust,
        roll_rad=phi_d,
        pitch_rad=theta_d,
        yaw_rad=psi_d,
        yaw_rate_rad_s=psidot,
        specific_force_m_s2=f_norm,
        thrust_clamped=thrust != thrust_raw,
    )


def input_in_reference_frame(u: ArrayLike, yaw_frame_rad: float, yaw_ref_rad: float) -> np.ndarray:
    """``u`` (4,), whose ``r1, r2`` are expressed in the frame of yaw ``yaw_frame_rad`` (the
    measured yaw the controller's virtual frame was built on), re-expressed in the frame of
    the yaw reference ``yaw_ref_rad`` that :func:`attitude_setpoint` builds the attitude on.

    The tilt the setpoint asks for is ``Rz(psi_d) R(phi, theta)``: its roll and pitch are
    relative to the setpoint's own yaw. When that yaw is the integrated previous setpoint (it
    leads the measured yaw by the attitude loop's lag, ~0.2-0.3 rad behind PX4's yaw loop at
    0.5-0.8 rad/s) the horizontal acceleration flown would be the one asked, turned by that
    lead: on a curve, a rotating error the disturbance estimate (constant in NED) cannot
    absorb. Rotating ``r1, r2`` by ``-(yaw_ref - yaw_frame)`` keeps the NED acceleration the
    controller asked for; ``r3`` and the yaw rate are unchanged."""
    uu = np.array(u, dtype=float).reshape(-1)
    if uu.shape != (4,):
        raise SetpointError(f"u: expected 4 components, got shape {uu.shape}")
    d = wrap_pi(float(yaw_ref_rad) - float(yaw_frame_rad))
    if not math.isfinite(d):
        raise SetpointError("yaw: non-finite value")
    c, s = math.cos(d), math.sin(d)
    r1, r2 = float(uu[0]), float(uu[1])
    uu[0], uu[1] = c * r1 + s * r2, -s * r1 + c * r2
    return uu


def yaw_reference(prev_sp_rad: float | None, measured_rad: float, max_lead_rad: float) -> float:
    """The yaw the next setpoint builds on (``psi_d = this + psidot dt``): the previous yaw
    setpoint, held within ``max_lead_rad`` of the measured yaw (the measured yaw when there is
    no previous setpoint or either is not finite).

    Spec 5 writes ``psi_d = psi_q + psidot dt`` with the measured ``psi_q``. Behind a real
    attitude loop (first order, time constant tau) that commands a yaw step of only
    ``psidot dt`` per step and the achieved rate settles near ``psidot dt / tau``; integrating
    the setpoint makes the achieved yaw rate equal the commanded one once the setpoint leads
    by the loop's lag ``psidot tau``. The lead is *clamped*, not reset: a reset to the measured
    yaw whenever the lead passes the bound throws the lag away and the achieved rate collapses
    to ~``bound / tau``, lower the faster the command (the yaw then runs away from a turning
    target while the controller asks for ever more rate). The clamp still bounds the wind-up
    when the vehicle does not follow (before OFFBOARD PX4 holds its own yaw)."""
    if prev_sp_rad is None or not (math.isfinite(prev_sp_rad) and math.isfinite(measured_rad)):
        return measured_rad
    d = wrap_pi(prev_sp_rad - measured_rad)
    if abs(d) <= max_lead_rad:
        return prev_sp_rad
    return wrap_pi(measured_rad + math.copysign(max_lead_rad, d))


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
