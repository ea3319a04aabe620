"""Target motion over the RMPC horizon, in the virtual frame (parameters of spec 6).

The AGV is predicted as a constant-speed, constant-turn-rate (unicycle) vehicle from its
current NED velocity and yaw rate; the vehicle's yaw is assumed to turn with the target
(``psi_q(n) = psi_q + n dt psidot_a``), which is what the controller steers towards. Each
stage's ``v_a`` and ``vdot_a`` are then expressed in that stage's virtual frame (spec 4:
``vdot_a`` is the derivative of the components as seen in the rotating frame).
"""

from __future__ import annotations

import math

import numpy as np

from companion.core.prediction_kernel import MotionKernel, Values, motion_kernel
from companion.core.rmpc import TargetMotion


def advance_target(v_ned_m_s: np.ndarray, a_ned_m_s2: np.ndarray, psidot_a_rad_s: float,
                   dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The target's NED velocity and acceleration ``dt_s`` later (earlier if negative) under
    the model of :func:`predict_target_motion`: constant turn rate, constant along-track
    acceleration (the speed not below 0). A FOLLOW_TARGET sample is up to a period (0.1 s at
    10 Hz) older or newer than the frame it is used with, and the horizon starts later still
    (latency compensation): on a curve its velocity then points off by ``psidot dt``."""
    v = np.array(v_ned_m_s, dtype=float).reshape(3)
    a = np.array(a_ned_m_s2, dtype=float).reshape(3)
    speed = float(np.hypot(v[0], v[1]))
    if speed <= 1e-6 or dt_s == 0.0:
        v[:2] = v[:2] + a[:2] * dt_s
        return v, a
    tangent = v[:2] / speed
    a_along = float(a[:2] @ tangent)
    sp = max(0.0, speed + a_along * dt_s)
    th = float(psidot_a_rad_s) * dt_s
    c, s = np.cos(th), np.sin(th)
    rot = np.array([[c, -s], [s, c]])
    v[:2] = rot @ tangent * sp
    a[:2] = rot @ a[:2]
    return v, a


def predict_target_motion(
    v_a_ned_m_s: np.ndarray,
    a_a_ned_m_s2: np.ndarray,
    psidot_a_rad_s: float,
    yaw_q_rad: float,
    horizon: int,
    dt_s: float,
    d_ned_m_s2: np.ndarray | tuple[float, float, float] | None = None,
    speed_cap_m_s: float | None = None,
) -> TargetMotion:
    """Predict the target's motion parameters for stages ``n = 0 .. horizon-1``.

    ``v_a_ned_m_s``, ``a_a_ned_m_s2`` (3,): the target's velocity/acceleration now (NED);
    ``psidot_a_rad_s``: its yaw rate; ``yaw_q_rad``: the vehicle's (= virtual frame's) yaw now.
    The along-track acceleration (projection of ``a`` on ``v``) is kept constant; the
    cross-track part is carried by the turn rate. ``d_ned_m_s2`` (3,): the estimated
    disturbance acceleration (NED, held constant), expressed in each stage's virtual frame.
    ``speed_cap_m_s``: a positive along-track acceleration is held only until the predicted
    speed reaches ``max(speed now, speed_cap_m_s)``, then the speed is held (``None``: held for
    the whole horizon). With the vehicle's velocity bound as the cap, a target accelerating
    towards a cruise speed at that bound is not predicted to outrun it (which would make the
    terminal set, ``v_q = v_a`` inside the box, unreachable whatever the state); a target
    already faster than the bound keeps its measured speed.
    """
    v0x, v0y = _first_two(v_a_ned_m_s)
    a0x, a0y = _first_two(a_a_ned_m_s2)
    speed = float(np.hypot(v0x, v0y))  # numpy's hypot: math's differs in the last bit
    values = (v0x, v0y, a0x, a0y, speed, float(psidot_a_rad_s), float(yaw_q_rad), float(dt_s),
              None if speed_cap_m_s is None else float(speed_cap_m_s))
    d = None if d_ned_m_s2 is None else _three(d_ned_m_s2)
    kernel = load_kernel()
    if kernel is None:
        return TargetMotion.built(*python_loop(values, horizon, d))
    arrays, finite = kernel(values, horizon, d)
    # (not finite: built's checks raise the error naming the array)
    return TargetMotion.finite(*arrays) if finite else TargetMotion.built(*arrays)


_KERNEL: list[MotionKernel | None] = []


def load_kernel() -> MotionKernel | None:
    """The compiled stage loop (:mod:`companion.core.prediction_kernel`), loaded and checked
    once per process (a pipeline calls it when it is built, so that its first step does not
    pay the check, ~30 ms, or a first-ever compile); None: the Python loop."""
    if not _KERNEL:
        _KERNEL.append(motion_kernel(python_loop))
    return _KERNEL[0]


def python_loop(values: Values, horizon: int, d: list[float] | None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """The stage loop of :func:`predict_target_motion` in Python (the reference the compiled
    one is checked against). ``values``: (v0x, v0y, a0x, a0y, speed, psidot, yaw_q, dt, the
    speed cap or None); ``d``: the disturbance (NED, 3) or None."""
    v0x, v0y, a0x, a0y, speed, w, yaw_q_rad, dt_s, speed_cap_m_s = values
    # stage by stage on plain floats (numpy's formulas row by row; ~16 stages of 2-vectors
    # cost more in numpy's per-call overhead than in arithmetic), into flat lists that
    # become the TargetMotion's arrays in one call each
    moving = speed > 1e-6
    cos, sin = math.cos, math.sin
    heading = math.atan2(v0y, v0x) if moving else 0.0
    a_along = a0x * cos(heading) + a0y * sin(heading) if moving else 0.0
    top = math.inf
    if moving and speed_cap_m_s is not None and a_along > 0.0:
        top = max(speed, speed_cap_m_s)
    d0, d1, d2 = (0.0, 0.0, 0.0) if d is None else d
    v_v: list[float] = []
    vdot: list[float] = []
    d_out: list[float] = []
    for n in range(horizon):
        t = n * dt_s
        wt = w * t  # (once: the two headings' w * t, the same product)
        if moving:
            # max(0.0, x) and min(x, top) spelt out (the builtins' results, bit for bit:
            # max keeps 0.0 unless x > 0.0, also for x = -0.0 or NaN; min keeps x unless
            # top < x), without two builtin calls a stage
            sp = speed + a_along * t
            if not sp > 0.0:
                sp = 0.0
            acc = a_along
            if sp >= top:
                acc = 0.0
                if top < sp:
                    sp = top
            hd = heading + wt
            ch, sh = cos(hd), sin(hd)
            vx, vy = sp * ch, sp * sh
            spw = sp * w  # (sp * w * x is (sp * w) * x)
            ax, ay = acc * ch - spw * sh, acc * sh + spw * ch
        else:
            vx, vy, ax, ay = v0x + a0x * t, v0y + a0y * t, a0x, a0y
        psi_q = yaw_q_rad + wt
        c, s = cos(psi_q), sin(psi_q)
        # Rz(psi_q(n))^T [x, y] = [c x + s y, -s x + c y]; d/dt (Rz^T v) = Rz^T a + psidot_q
        # [v_y, -v_x] with psidot_q = w (the vehicle turns along)
        vvx, vvy = c * vx + s * vy, -s * vx + c * vy
        v_v += (vvx, vvy)
        vdot += (c * ax + s * ay + w * vvy, -s * ax + c * ay + w * -vvx)
        if d is not None:
            d_out += (c * d0 + s * d1, -s * d0 + c * d1, d2)
    return (np.array(v_v).reshape(horizon, 2), np.array(vdot).reshape(horizon, 2),
            np.array([w] * horizon), None if d is None else np.array(d_out).reshape(horizon, 3))


def _first_two(x: np.ndarray | tuple[float, ...]) -> tuple[float, float]:
    """The first two values as floats (a tuple without numpy)."""
    if type(x) is tuple and len(x) >= 2:
        return float(x[0]), float(x[1])
    a, b = np.asarray(x, dtype=float)[:2].tolist()
    return a, b


def _three(x: np.ndarray | tuple[float, ...]) -> list[float]:
    """Three values as floats (numpy's ``reshape(3)`` check; a tuple without numpy)."""
    if type(x) is tuple and len(x) == 3:
        return [float(v) for v in x]
    out: list[float] = np.asarray(x, dtype=float).reshape(3).tolist()
    return out
