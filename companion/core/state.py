"""The RMPC's measured state ``eta_e`` and target-motion parameters (spec section 4).

Inputs are measurements: the target points detected in the real image (metric), the attitude
of the camera (roll, pitch, yaw; the virtual frame ``v`` has the camera's yaw), the vehicle's
velocity in NED and yaw rate, and the target's NED velocity, acceleration and yaw rate.

In ``v`` a world vector ``d`` reads ``Rz(psi)^T d``. The target-motion parameters::

    v_a      = [Rz(psi)^T v_a_ned]_xy                      (v_az = 0 by the spec)
    vdot_a   = d/dt [Rz(psi)^T v_a_ned]_xy                 (as seen in the rotating frame v)
             = [Rz(psi)^T a_a_ned]_xy + psidot_q [v_ay, -v_ax]
    psidot_a = the target's yaw rate

(``d/dt Rz^T = psidot J Rz^T`` with ``J = [[0, 1], [-1, 0]]``; a test checks it by finite
differences). Note: with this ``vdot_a``, ``u_e1 = r1 + psidot_q v_ay - vdot_ax`` equals
``r1 - [Rz^T a_a]_x`` exactly when the ``psidot_q`` in ``u`` is the one used here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from companion.core.dynamics import S_REF
from companion.core.errors import CoreError
from companion.core.frozen import make
from companion.core.geometry import (
    camera_points_to_body_image,
    real_lists_to_virtual,
    real_points_to_virtual,
)
from companion.core.moments import (
    DegenerateTargetError,
    ImageMoments,
    image_moments,
    image_moments_xy,
)


class MeasurementError(CoreError, ValueError):
    """A measurement is non-finite or has the wrong shape: no state is built from it."""


def _vec(x: ArrayLike, n: int, name: str) -> np.ndarray:
    v = np.asarray(x, dtype=float).reshape(-1)
    if v.shape != (n,):
        raise MeasurementError(f"{name}: expected {n} components, got shape {v.shape}")
    if not np.isfinite(v).all():
        raise MeasurementError(f"{name}: non-finite value")
    return v


def _scalar(x: float, name: str) -> float:
    v = float(x)
    if not math.isfinite(v):
        raise MeasurementError(f"{name}: non-finite value")
    return v


def _ro(a: np.ndarray) -> np.ndarray:
    if (isinstance(a, np.ndarray) and a.dtype == np.float64 and a.base is None
            and not a.flags.writeable):
        return a  # already a read-only array owning its data (built here): no copy needed
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


def _frozen(values: list[float]) -> np.ndarray:
    a = np.array(values)
    a.setflags(write=False)
    return a


def _xyz(x: ArrayLike, name: str) -> tuple[float, float, float]:
    """A finite 3-vector as floats (:func:`_vec`'s checks; tuples without numpy)."""
    if (isinstance(x, tuple) and len(x) == 3) or (isinstance(x, np.ndarray)
                                                  and x.shape == (3,)):
        a, b, c = x.tolist() if isinstance(x, np.ndarray) else x
        a, b, c = float(a), float(b), float(c)  # (unpacked: no generator)
        if not (math.isfinite(a) and math.isfinite(b) and math.isfinite(c)):
            raise MeasurementError(f"{name}: non-finite value")
        return a, b, c
    a, b, c = _vec(x, 3, name).tolist()
    return a, b, c


def _to_virtual(x: tuple[float, float, float], c: float, s: float) -> list[float]:
    """``Rz(yaw)^T x`` with ``c, s = cos, sin(yaw)``: the matrix product's terms in its
    order (the same bits as ``rot_z(yaw).T @ x``)."""
    x0, x1, x2 = x
    return [c * x0 + s * x1 + 0.0 * x2, -s * x0 + c * x1 + 0.0 * x2,
            0.0 * x0 + 0.0 * x1 + 1.0 * x2]


def ned_to_virtual(vec_ned: ArrayLike, yaw_rad: float) -> np.ndarray:
    """A world (NED) vector (3,) in the virtual frame's axes: ``Rz(yaw)^T vec`` (3,)."""
    v = _xyz(vec_ned, "vec_ned")
    yaw = _scalar(yaw_rad, "yaw_rad")
    return np.array(_to_virtual(v, math.cos(yaw), math.sin(yaw)))


@dataclass(frozen=True, eq=False)  # holds arrays: no element-wise ==
class TargetMotion:
    """Target-motion parameters of the RMPC, in the virtual frame ``v`` (spec 4).

    ``v_a_m_s`` (2,): ``[v_ax, v_ay]``; ``vdot_a_m_s2`` (2,): their derivative as seen in the
    rotating frame ``v`` (computed with the vehicle yaw rate ``yaw_rate_rad_s``);
    ``psidot_a_rad_s``: target yaw rate; ``accel_a_v_m_s2`` (2,): the target's inertial
    acceleration expressed in ``v`` axes, ``[Rz^T a_a_ned]_xy`` (independent of the yaw rate).
    """

    v_a_m_s: np.ndarray
    vdot_a_m_s2: np.ndarray
    psidot_a_rad_s: float
    accel_a_v_m_s2: np.ndarray
    yaw_rate_rad_s: float

    def __post_init__(self) -> None:
        for name in ("v_a_m_s", "vdot_a_m_s2", "accel_a_v_m_s2"):
            object.__setattr__(self, name, _ro(getattr(self, name)))


def target_motion_in_virtual(
    v_a_ned_m_s: ArrayLike,
    a_a_ned_m_s2: ArrayLike,
    psidot_a_rad_s: float,
    yaw_rad: float,
    yaw_rate_rad_s: float,
) -> TargetMotion:
    """:class:`TargetMotion` from the target's NED velocity (3,) / acceleration (3,) and yaw
    rate, at the virtual frame's yaw ``yaw_rad`` turning at ``yaw_rate_rad_s`` (the vehicle's
    yaw rate ``psidot_q``). Vertical components are dropped (spec: ``v_az = 0``)."""
    psidot_q = _scalar(yaw_rate_rad_s, "yaw_rate_rad_s")
    yaw = _scalar(yaw_rad, "yaw_rad")
    return _motion(_xyz(v_a_ned_m_s, "v_a_ned_m_s"), _xyz(a_a_ned_m_s2, "a_a_ned_m_s2"),
                   _scalar(psidot_a_rad_s, "psidot_a_rad_s"), math.cos(yaw), math.sin(yaw),
                   psidot_q)


def _motion(v_ned: tuple[float, float, float], a_ned: tuple[float, float, float],
            psidot_a: float, c: float, s: float, psidot_q: float) -> TargetMotion:
    v = _to_virtual(v_ned, c, s)[:2]
    acc = _to_virtual(a_ned, c, s)[:2]
    vdot = [acc[0] + psidot_q * v[1], acc[1] + psidot_q * -v[0]]
    # (arrays owned and read-only, as __post_init__ makes them: built without it)
    return make(TargetMotion, v_a_m_s=_frozen(v), vdot_a_m_s2=_frozen(vdot),
                psidot_a_rad_s=psidot_a, accel_a_v_m_s2=_frozen(acc), yaw_rate_rad_s=psidot_q)


def virtual_image_points(
    points_real_m: ArrayLike,
    roll_rad: float,
    pitch_rad: float,
    lam: float,
    cam_to_body: ArrayLike | None = None,
) -> np.ndarray:
    """Real-image target points (N, 2) (m) -> virtual image (N, 2) (m).

    Without ``cam_to_body`` (the spec's default mount) ``roll_rad, pitch_rad`` are the
    camera's = body's. With a mount rotation ``R_bc`` (3, 3, from
    :func:`companion.core.geometry.camera_to_body_rotation`) the points are first re-projected
    into body axes and ``roll_rad, pitch_rad`` must be the BODY's; ``v`` then has the body's yaw.
    Raises :class:`DegenerateTargetError` for fewer than 3 or non-finite points and
    :class:`companion.core.geometry.GeometryError` (its parent) for a ray above the horizon.
    """
    pts = np.asarray(points_real_m, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] < 3:
        raise DegenerateTargetError(f"target points: need (N >= 3, 2), got shape {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise DegenerateTargetError("target points: non-finite value")
    if cam_to_body is not None:
        pts = camera_points_to_body_image(pts, cam_to_body, lam)
    return real_points_to_virtual(pts, roll_rad, pitch_rad, lam)


@dataclass(frozen=True, eq=False)  # holds arrays: no element-wise ==
class ErrorState:
    """The measured error state of spec 4 and what it was built from.

    ``eta_e`` (7,): ``[s1, s2, s3 - 1, s4, v_ex, v_ey, v_ez]`` (``v_e`` in m/s, v frame, z down);
    ``s`` (4,) the features; ``v_q_v_m_s`` (3,) vehicle velocity in ``v``; ``v_a_v_m_s`` (3,)
    ``[v_ax, v_ay, 0]``; ``moments`` the image moments; ``motion`` the RMPC's target
    parameters; ``roll_rad, pitch_rad, yaw_rad`` the attitude used (v has ``yaw_rad``).
    All arrays are read-only.
    """

    eta_e: np.ndarray
    s: np.ndarray
    v_q_v_m_s: np.ndarray
    v_a_v_m_s: np.ndarray
    moments: ImageMoments
    motion: TargetMotion
    roll_rad: float
    pitch_rad: float
    yaw_rad: float

    def __post_init__(self) -> None:
        for name in ("eta_e", "s", "v_q_v_m_s", "v_a_v_m_s"):
            object.__setattr__(self, name, _ro(getattr(self, name)))

    @property
    def s_e(self) -> np.ndarray:
        """``s - s_r`` (4,)."""
        return self.eta_e[:4]

    @property
    def v_e_m_s(self) -> np.ndarray:
        """``v_q - v_a`` in ``v`` (3,) (m/s)."""
        return self.eta_e[4:]


def build_error_state(
    points_real_m: ArrayLike,
    *,
    roll_rad: float,
    pitch_rad: float,
    yaw_rad: float,
    yaw_rate_rad_s: float,
    v_q_ned_m_s: ArrayLike,
    v_a_ned_m_s: ArrayLike,
    a_a_ned_m_s2: ArrayLike,
    psidot_a_rad_s: float,
    a_star: float,
    lam: float,
    s4_prev_rad: float | None = None,
    cam_to_body: ArrayLike | None = None,
    heading_from_corners: bool = False,
) -> ErrorState:
    """``eta_e`` of spec 4 and the target-motion parameters from one frame's measurements.

    ``points_real_m`` (N >= 3, 2): detected target points, metric real-image ``[u, n]`` (m).
    ``roll_rad, pitch_rad, yaw_rad``: camera attitude (ZYX, rad; body attitude when
    ``cam_to_body`` is given, see :func:`virtual_image_points`); ``yaw_rate_rad_s``: the
    vehicle's yaw rate ``psidot_q``; ``v_q_ned_m_s`` (3,) own velocity; ``v_a_ned_m_s``,
    ``a_a_ned_m_s2`` (3,) the target's velocity and acceleration (NED); ``psidot_a_rad_s`` its
    yaw rate; ``a_star`` (m^2) and ``lam`` (m) as in :func:`companion.core.moments.image_moments`;
    ``s4_prev_rad`` the previous ``s4`` for unwrapping (None on the first frame);
    ``heading_from_corners``: ``s4`` from the ordered points (square targets: ArUco).

    Raises :class:`MeasurementError` on non-finite measurements,
    :class:`companion.core.moments.DegenerateTargetError` on unusable target points and
    :class:`companion.core.geometry.GeometryError` (the latter's parent) when a point's ray is
    above the virtual horizon. Catch ``GeometryError`` for "no target measurement this frame".
    """
    roll = _scalar(roll_rad, "roll_rad")
    pitch = _scalar(pitch_rad, "pitch_rad")
    yaw = _scalar(yaw_rad, "yaw_rad")
    pts = np.asarray(points_real_m, dtype=float)
    if cam_to_body is None and pts.ndim == 2 and pts.shape[1] == 2 and 3 <= pts.shape[0] < 8:
        # the corners of one frame (every control step): plain floats, the same formulas
        us, ns = pts[:, 0].tolist(), pts[:, 1].tolist()
        if not all(map(math.isfinite, us + ns)):
            raise DegenerateTargetError("target points: non-finite value")
        uv, nv = real_lists_to_virtual(us, ns, roll, pitch, lam)
        mom = image_moments_xy(uv, nv, a_star, lam, s4_prev_rad,
                               heading_from_corners=heading_from_corners)
    else:
        pts_v = virtual_image_points(pts, roll, pitch, lam, cam_to_body)
        mom = image_moments(pts_v, a_star, lam, s4_prev_rad,
                            heading_from_corners=heading_from_corners)
    c, s = math.cos(yaw), math.sin(yaw)
    motion = _motion(_xyz(v_a_ned_m_s, "v_a_ned_m_s"), _xyz(a_a_ned_m_s2, "a_a_ned_m_s2"),
                     _scalar(psidot_a_rad_s, "psidot_a_rad_s"), c, s,
                     _scalar(yaw_rate_rad_s, "yaw_rate_rad_s"))
    v_q = _to_virtual(_xyz(v_q_ned_m_s, "v_q_ned_m_s"), c, s)
    va0, va1 = motion.v_a_m_s.tolist()
    s_list = mom.s.tolist()
    eta = [s_list[i] - S_REF[i] for i in range(4)] + [v_q[0] - va0, v_q[1] - va1, v_q[2] - 0.0]
    # (arrays owned and read-only, as __post_init__ makes them: built without it)
    return make(
        ErrorState, eta_e=_frozen(eta), s=_ro(mom.s), v_q_v_m_s=_frozen(v_q),
        v_a_v_m_s=_frozen([va0, va1, 0.0]), moments=mom, motion=motion,
        roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw,
    )
