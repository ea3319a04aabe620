"""Camera geometry of spec sections 1, 2, 5 and 6 (the virtual camera and the visible area).

Conventions (docs/reference/math.md, section 1): world NED, body FRD, ZYX Euler
``R = Rz(psi) Ry(theta) Rx(phi)``. Camera axes = body axes (x forward, y right, z down = optical
axis). Metric image coordinates ``u = lambda x/z`` (along camera x), ``n = lambda y/z``.
The virtual camera ``v`` has the camera's origin and yaw, roll = pitch = 0:
``p_v = Ry(theta) Rx(phi) p_c``.

``real_to_virtual``, ``attitude_from_accel``, ``visible_area_centre`` and the coordinate
conversions accept numpy arrays (vectorised) or CasADi symbols (for the RMPC); the rotation,
quaternion and projection helpers are numpy only.

Quaternions are ``[w, x, y, z]``: the attitude of body FRD relative to NED, as MAVLink
ATTITUDE_QUATERNION and SET_ATTITUDE_TARGET carry it (scipy's order is x, y, z, w).
Image coordinates: metric ``(u, n)`` (m on the image plane), spec pixels
``(u_px, n_px) = (u, n)/pixel_size`` from the principal point, OpenCV ``(col, row)`` with
``col = cx + n_px``, ``row = cy - u_px`` (:func:`spec_pixel_to_opencv`, the only place that
mapping is written), normalised ``(u, n)/lambda``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from companion.core._backend import asin, atan, xp
from companion.core.errors import CoreError
from companion.core.params import CameraParams


def real_to_virtual(u: Any, n: Any, phi: Any, theta: Any, lam: float) -> tuple[Any, Any]:
    """Map real-image metric coordinates to the virtual image (spec section 2).

    The real-image point ``(u, n)`` is the ray ``[u, n, lam]`` in the camera frame; in the
    virtual frame it is ``Ry(theta) Rx(phi) [u, n, lam]``, re-projected with focal length
    ``lam``. ``u, n`` in metres on the image plane (any shape); ``phi, theta`` roll and pitch
    (rad); returns ``(u_v, n_v)`` in metres. Valid while the ray stays below the horizon
    (``D > 0``).
    """
    m = xp(u, n, phi, theta)
    sp, cp = m.sin(phi), m.cos(phi)
    st, ct = m.sin(theta), m.cos(theta)
    d = sp * ct * n + lam * cp * ct - u * st
    u_v = lam * (sp * st * n + lam * cp * st + u * ct) / d
    n_v = lam * (n * cp - lam * sp) / d
    return u_v, n_v


def attitude_from_accel(r1: Any, r2: Any, r3: Any, g: float) -> tuple[Any, Any, Any]:
    """Desired roll, pitch and specific-force norm from the commanded acceleration (spec 5).

    ``r = [r1, r2, r3]`` is the commanded acceleration in the virtual frame (z down, m/s^2).
    The specific force is ``f = [r1, r2, r3 - g]``. Returns ``(phi_d, theta_d, |f|)`` with
    ``phi_d = asin(r2/|f|)`` and ``theta_d = atan(r1/(r3 - g))`` (rad, rad, m/s^2).
    Note the sign: for r1 > 0 (accelerate forward) ``theta_d < 0`` (nose down, FRD pitch).
    """
    m = xp(r1, r2, r3)
    f_norm = m.sqrt(r1 * r1 + r2 * r2 + (r3 - g) * (r3 - g))
    phi_d = asin(m, r2 / f_norm)
    theta_d = atan(m, r1 / (r3 - g))
    return phi_d, theta_d, f_norm


def visible_area_centre(
    phi: Any, theta: Any, u_b: float, n_b: float, lam: float
) -> tuple[Any, Any]:
    """Centre ``M`` of the visible area mapped to the virtual image, normalised (spec 6).

    Maps the four corners ``(+-u_b, +-n_b)`` (metres, real image) through
    :func:`real_to_virtual` at roll ``phi`` and pitch ``theta``, takes their mean and divides
    by ``lam``. Returns ``(M_u, M_n)`` (dimensionless, the units of ``p = s_e[:2]/s3``).
    """
    mu = 0.0
    mn = 0.0
    for su in (1.0, -1.0):
        for sn in (1.0, -1.0):
            uv, nv = real_to_virtual(su * u_b, sn * n_b, phi, theta, lam)
            mu = mu + uv
            mn = mn + nv
    return mu / (4.0 * lam), mn / (4.0 * lam)


# ----------------------------------------------------------------------------------------------
# Errors


class GeometryError(CoreError, ValueError):
    """Geometry cannot be evaluated on these inputs (non-finite, behind the camera, ...)."""


def _finite(name: str, *arrays: ArrayLike) -> None:
    for a in arrays:
        # scalars (most calls, once per control step) without numpy's per-call overhead
        ok = (math.isfinite(a) if isinstance(a, float | int)
              else bool(np.isfinite(np.asarray(a, dtype=float)).all()))
        if not ok:
            raise GeometryError(f"{name}: non-finite input")


# ----------------------------------------------------------------------------------------------
# Rotations (spec 1): ZYX Euler, R = Rz(psi) Ry(theta) Rx(phi) maps body (FRD) to world (NED).


def rot_x(phi: float) -> np.ndarray:
    """Elementary rotation about x by ``phi`` (rad), shape (3, 3): ``Rx @ v`` rotates ``v``."""
    c, s = math.cos(phi), math.sin(phi)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(theta: float) -> np.ndarray:
    """Elementary rotation about y by ``theta`` (rad), shape (3, 3)."""
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(psi: float) -> np.ndarray:
    """Elementary rotation about z by ``psi`` (rad), shape (3, 3)."""
    c, s = math.cos(psi), math.sin(psi)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_zyx(phi: float, theta: float, psi: float) -> np.ndarray:
    """``R = Rz(psi) Ry(theta) Rx(phi)`` (3, 3): body FRD -> world NED (``p_ned = R p_body``)."""
    r: np.ndarray = rot_z(psi) @ rot_y(theta) @ rot_x(phi)
    return r


def euler_zyx_from_rotation(r: ArrayLike) -> tuple[float, float, float]:
    """Inverse of :func:`rotation_zyx`: ``(phi, theta, psi)`` in rad.

    ``phi, psi`` in (-pi, pi], ``theta`` in [-pi/2, pi/2]; at ``|theta| = pi/2`` (gimbal lock)
    roll and yaw are not separable and the split returned is arbitrary but consistent.
    """
    m = np.asarray(r, dtype=float)
    _finite("euler_zyx_from_rotation", m)
    theta = -math.asin(max(-1.0, min(1.0, float(m[2, 0]))))
    phi = math.atan2(float(m[2, 1]), float(m[2, 2]))
    psi = math.atan2(float(m[1, 0]), float(m[0, 0]))
    return phi, theta, psi


def quat_from_euler_zyx(phi: float, theta: float, psi: float) -> np.ndarray:
    """Unit quaternion ``[w, x, y, z]`` of ZYX Euler angles (rad), with ``w >= 0``.

    The attitude of body FRD relative to NED (MAVLink ATTITUDE_QUATERNION / SET_ATTITUDE_TARGET
    ``q``): :func:`rotation_from_quat` of it equals :func:`rotation_zyx`.
    """
    _finite("quat_from_euler_zyx", phi, theta, psi)
    cr, sr = math.cos(0.5 * phi), math.sin(0.5 * phi)
    cp, sp = math.cos(0.5 * theta), math.sin(0.5 * theta)
    cy, sy = math.cos(0.5 * psi), math.sin(0.5 * psi)
    w = cr * cp * cy + sr * sp * sy
    x = sr * cp * cy - cr * sp * sy
    y = cr * sp * cy + sr * cp * sy
    z = cr * cp * sy - sr * sp * cy
    # _canonical on plain floats (the same values); read-only: a setpoint keeps it as is
    n = math.sqrt(w * w + x * x + y * y + z * z)
    k = -1.0 if w / n < 0 else 1.0
    q = np.array([k * (w / n), k * (x / n), k * (y / n), k * (z / n)])
    q.setflags(write=False)
    return q


def _canonical(q: np.ndarray) -> np.ndarray:
    q = q / np.linalg.norm(q)
    return -q if q[0] < 0 else q


def rotation_from_quat(q_wxyz: ArrayLike) -> np.ndarray:
    """Rotation matrix (3, 3, body -> NED) of a quaternion ``[w, x, y, z]`` (normalised here).

    Raises :class:`GeometryError` for a non-finite or (near-)zero quaternion.
    """
    q = np.asarray(q_wxyz, dtype=float).reshape(4)
    _finite("rotation_from_quat", q)
    nrm = float(np.linalg.norm(q))
    if nrm < 1e-9:
        raise GeometryError("rotation_from_quat: zero quaternion")
    w, x, y, z = (q / nrm).tolist()  # plain floats: the same IEEE arithmetic, less overhead
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _unit_quat(q_wxyz: Sequence[float]) -> tuple[float, float, float, float]:
    """``q / |q|`` on plain floats (rotation_from_quat's normalisation, the same values);
    :class:`GeometryError` for a non-finite or zero quaternion, as there."""
    w, x, y, z = (float(v) for v in q_wxyz)
    nrm = math.sqrt(w * w + x * x + y * y + z * z)
    if not math.isfinite(nrm):
        raise GeometryError("rotation_from_quat: non-finite input")
    if nrm < 1e-9:
        raise GeometryError("rotation_from_quat: zero quaternion")
    return w / nrm, x / nrm, y / nrm, z / nrm


def body_z_from_quat(q_wxyz: tuple[float, float, float, float]) -> tuple[float, float, float]:
    """The body z axis in NED, ``rotation_from_quat(q)[:, 2]`` (the same values, on plain
    floats); :class:`GeometryError` as there."""
    w, x, y, z = _unit_quat(q_wxyz)
    return 2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)


def quat_from_rotation(r: ArrayLike) -> np.ndarray:
    """Quaternion ``[w, x, y, z]`` (``w >= 0``) of a rotation matrix (Shepperd's method)."""
    m = np.asarray(r, dtype=float)
    _finite("quat_from_rotation", m)
    tr = float(m[0, 0] + m[1, 1] + m[2, 2])
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    return _canonical(np.array(q, dtype=float))


def euler_zyx_from_quat(q_wxyz: ArrayLike) -> tuple[float, float, float]:
    """``(phi, theta, psi)`` (rad) of a quaternion ``[w, x, y, z]`` (body FRD rel. to NED)."""
    if isinstance(q_wxyz, tuple | list) and len(q_wxyz) == 4:
        # a telemetry sample's tuple or list (every step): the same formulas as the
        # matrix path below, on plain floats
        w, x, y, z = _unit_quat(q_wxyz)
        theta = -math.asin(max(-1.0, min(1.0, 2 * (x * z - w * y))))
        phi = math.atan2(2 * (y * z + w * x), 1 - 2 * (x * x + y * y))
        psi = math.atan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z))
        return phi, theta, psi
    return euler_zyx_from_rotation(rotation_from_quat(q_wxyz))


def wrap_pi(angle: float) -> float:
    """Angle wrapped to (-pi, pi] (rad)."""
    a = math.remainder(float(angle), 2.0 * math.pi)  # in [-pi, pi]
    return math.pi if a == -math.pi else a


# ----------------------------------------------------------------------------------------------
# Camera mount (config camera.mount_rpy_rad, camera.mount_offset_m)


def camera_to_body_rotation(mount_rpy_rad: ArrayLike = (0.0, 0.0, 0.0)) -> np.ndarray:
    """``R_bc`` (3, 3): camera axes -> body FRD axes (``p_body = R_bc p_cam + offset``).

    The config says "camera axes = body axes rotated by mount_rpy_rad (ZYX)", so
    ``R_bc = rotation_zyx(*mount_rpy_rad)``; the default (zeros) is the identity (spec 1).
    """
    rpy = np.asarray(mount_rpy_rad, dtype=float).reshape(3)
    _finite("camera_to_body_rotation", rpy)
    return rotation_zyx(float(rpy[0]), float(rpy[1]), float(rpy[2]))


def camera_position_ned(
    body_pos_ned_m: ArrayLike, r_body_to_ned: ArrayLike, mount_offset_m: ArrayLike
) -> np.ndarray:
    """Camera optical centre in NED (m): ``p_body + R_nb offset`` (offset in body FRD, m)."""
    r = np.asarray(r_body_to_ned, dtype=float)
    out: np.ndarray = np.asarray(body_pos_ned_m, float) + r @ np.asarray(mount_offset_m, float)
    return out


def camera_points_to_body_image(points_m: ArrayLike, r_bc: ArrayLike, lam: float) -> np.ndarray:
    """Re-project real-image points of a mounted camera into a camera with body axes.

    ``points_m`` (N, 2) metric ``(u, n)`` of the mounted camera; each is the ray
    ``[u, n, lam]`` in camera axes, ``R_bc`` of it in body axes, re-projected with focal length
    ``lam``. The result (N, 2) is what a camera with the body's axes at the same optical centre
    sees, ready for :func:`real_points_to_virtual` with the BODY roll/pitch. Identity ``R_bc``
    returns the points unchanged. Raises :class:`GeometryError` for a ray that does not point
    below the body's x-y plane.
    """
    p = _points2(points_m, "camera_points_to_body_image")
    rays = np.column_stack([p[:, 0], p[:, 1], np.full(len(p), float(lam))])
    rb = rays @ np.asarray(r_bc, dtype=float).T
    if np.any(rb[:, 2] <= 0.0):
        raise GeometryError("camera_points_to_body_image: ray not in front of the body image plane")
    return np.column_stack([lam * rb[:, 0] / rb[:, 2], lam * rb[:, 1] / rb[:, 2]])


# ----------------------------------------------------------------------------------------------
# Pinhole projection and image coordinates (spec 1)


def _points2(points: ArrayLike, name: str) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    if p.ndim == 1 and p.shape[0] == 2:
        p = p.reshape(1, 2)
    if p.ndim != 2 or p.shape[1] != 2:
        raise GeometryError(f"{name}: expected points of shape (N, 2), got {p.shape}")
    _finite(name, p)
    return p


def project_points(points_cam_m: ArrayLike, lam: float) -> np.ndarray:
    """Pinhole projection of camera-frame points (N, 3) (m) to metric image coords (N, 2).

    ``u = lam x/z``, ``n = lam y/z`` (z = optical axis, down for the level camera). Raises
    :class:`GeometryError` for a point not in front of the camera (``z <= 0``).
    """
    p = np.asarray(points_cam_m, dtype=float)
    if p.ndim == 1:
        p = p.reshape(1, 3)
    if p.ndim != 2 or p.shape[1] != 3:
        raise GeometryError(f"project_points: expected shape (N, 3), got {p.shape}")
    _finite("project_points", p)
    if np.any(p[:, 2] <= 0.0):
        raise GeometryError("project_points: point not in front of the camera (z <= 0)")
    return np.column_stack([lam * p[:, 0] / p[:, 2], lam * p[:, 1] / p[:, 2]])


def world_to_camera(
    points_ned_m: ArrayLike, cam_pos_ned_m: ArrayLike, r_cam_to_ned: ArrayLike
) -> np.ndarray:
    """World NED points (N, 3) in camera axes (N, 3): ``R_nc^T (p - p_cam)``."""
    p = np.atleast_2d(np.asarray(points_ned_m, dtype=float))
    d = p - np.asarray(cam_pos_ned_m, dtype=float).reshape(1, 3)
    out: np.ndarray = d @ np.asarray(r_cam_to_ned, dtype=float)  # row-wise R^T d
    return out


def real_points_to_virtual(points_m: ArrayLike, phi: float, theta: float, lam: float) -> np.ndarray:
    """Map real-image points (N, 2) (metric ``u, n``) to the virtual image (spec 2), (N, 2).

    Uses :func:`real_to_virtual` at camera roll ``phi``, pitch ``theta`` (rad). Raises
    :class:`GeometryError` when a ray is at or above the virtual camera's horizon (``D <= 0``),
    where the virtual image of the point does not exist.
    """
    p = _points2(points_m, "real_points_to_virtual")
    _finite("real_points_to_virtual", phi, theta, lam)
    u, n = p[:, 0], p[:, 1]
    d = math.sin(phi) * math.cos(theta) * n + lam * math.cos(phi) * math.cos(theta)
    d = d - u * math.sin(theta)
    if np.any(d <= 0.0):
        raise GeometryError("real_points_to_virtual: ray at or above the horizon (D <= 0)")
    u_v, n_v = real_to_virtual(u, n, phi, theta, lam)
    return np.column_stack([u_v, n_v])


def real_lists_to_virtual(us: list[float], ns: list[float], phi: float, theta: float,
                          lam: float) -> tuple[list[float], list[float]]:
    """:func:`real_points_to_virtual` of points given as two lists of floats (``u``, ``n``,
    m), returned the same way: the control step's path, without arrays (the same formulas
    on plain floats)."""
    _finite("real_points_to_virtual", phi, theta, lam)
    sp, cp = math.sin(phi), math.cos(phi)
    st, ct = math.sin(theta), math.cos(theta)
    uv: list[float] = []
    nv: list[float] = []
    for u, n in zip(us, ns, strict=True):
        d = sp * ct * n + lam * cp * ct - u * st
        if not d > 0.0:
            raise GeometryError("real_points_to_virtual: ray at or above the horizon (D <= 0)")
        uv.append(lam * (sp * st * n + lam * cp * st + u * ct) / d)
        nv.append(lam * (n * cp - lam * sp) / d)
    return uv, nv


def metric_to_normalised(u_m: Any, n_m: Any, lam: float) -> tuple[Any, Any]:
    """Normalised image coordinates ``(u/lam, n/lam)`` (dimensionless)."""
    return u_m / lam, n_m / lam


def normalised_to_metric(u_norm: Any, n_norm: Any, lam: float) -> tuple[Any, Any]:
    """Metric image coordinates ``(lam u_norm, lam n_norm)`` (m)."""
    return u_norm * lam, n_norm * lam


def metric_to_pixel(u_m: Any, n_m: Any, pixel_size_m: float) -> tuple[Any, Any]:
    """Spec pixels ``(u_px, n_px) = (u, n) / pixel_size``, measured from the principal point."""
    return u_m / pixel_size_m, n_m / pixel_size_m


def pixel_to_metric(u_px: Any, n_px: Any, pixel_size_m: float) -> tuple[Any, Any]:
    """Inverse of :func:`metric_to_pixel` (m)."""
    return u_px * pixel_size_m, n_px * pixel_size_m


def principal_point_px(width_px: int, height_px: int) -> tuple[float, float]:
    """Ideal principal point ``(cx, cy)`` in OpenCV pixels: the sensor's geometric centre.

    OpenCV puts pixel centres on integers, so the centre of a W x H sensor is
    ``((W - 1)/2, (H - 1)/2)`` (499.5 for 1000 px). With a calibration file use its ``cx, cy``.
    """
    return 0.5 * (width_px - 1), 0.5 * (height_px - 1)


def spec_pixel_to_opencv(u_px: Any, n_px: Any, cx_px: float, cy_px: float) -> tuple[Any, Any]:
    """THE mapping spec pixels -> OpenCV ``(col, row)`` (spec 1, docs/reference/wire.md).

    Camera looking down, "forward = up" in the image: ``col = cx + n_px``, ``row = cy - u_px``.
    Every other conversion goes through this function and :func:`opencv_to_spec_pixel`.
    """
    return cx_px + n_px, cy_px - u_px


def opencv_to_spec_pixel(col: Any, row: Any, cx_px: float, cy_px: float) -> tuple[Any, Any]:
    """Inverse of :func:`spec_pixel_to_opencv`: ``u_px = cy - row``, ``n_px = col - cx``."""
    return cy_px - row, col - cx_px


def metric_to_opencv(
    u_m: Any, n_m: Any, pixel_size_m: float, cx_px: float, cy_px: float
) -> tuple[Any, Any]:
    """Metric image coords -> OpenCV ``(col, row)`` (pixels)."""
    u_px, n_px = metric_to_pixel(u_m, n_m, pixel_size_m)
    return spec_pixel_to_opencv(u_px, n_px, cx_px, cy_px)


def opencv_to_metric(
    col: Any, row: Any, pixel_size_m: float, cx_px: float, cy_px: float
) -> tuple[Any, Any]:
    """OpenCV ``(col, row)`` (pixels) -> metric image coords ``(u, n)`` (m)."""
    u_px, n_px = opencv_to_spec_pixel(col, row, cx_px, cy_px)
    return pixel_to_metric(u_px, n_px, pixel_size_m)


@dataclass(frozen=True)
class PinholeCamera:
    """An ideal pinhole camera: focal length, pixel pitch and principal point.

    ``focal_length_m`` is the spec's ``lambda``; ``cx_px, cy_px`` the principal point in OpenCV
    pixels. Point arrays are (N, 2): metric ``[u, n]`` or OpenCV ``[col, row]``.
    """

    focal_length_m: float
    pixel_size_m: float
    cx_px: float
    cy_px: float

    def __post_init__(self) -> None:
        for name in ("focal_length_m", "pixel_size_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise GeometryError(f"PinholeCamera.{name}: must be finite and > 0")
        if not (math.isfinite(self.cx_px) and math.isfinite(self.cy_px)):
            raise GeometryError("PinholeCamera: principal point must be finite")

    @classmethod
    def from_config(cls, cam: CameraParams) -> PinholeCamera:
        """Ideal camera of a :class:`~companion.core.params.CameraParams` (principal point
        centred)."""
        cx, cy = principal_point_px(cam.width_px, cam.height_px)
        return cls(cam.focal_length_m, cam.pixel_size_m, cx, cy)

    def opencv_to_metric(self, points_cr: ArrayLike) -> np.ndarray:
        """OpenCV ``[col, row]`` (N, 2) -> metric ``[u, n]`` (N, 2)."""
        p = _points2(points_cr, "PinholeCamera.opencv_to_metric")
        u, n = opencv_to_metric(p[:, 0], p[:, 1], self.pixel_size_m, self.cx_px, self.cy_px)
        return np.column_stack([u, n])

    def metric_to_opencv(self, points_m: ArrayLike) -> np.ndarray:
        """Metric ``[u, n]`` (N, 2) -> OpenCV ``[col, row]`` (N, 2)."""
        p = _points2(points_m, "PinholeCamera.metric_to_opencv")
        col, row = metric_to_opencv(p[:, 0], p[:, 1], self.pixel_size_m, self.cx_px, self.cy_px)
        return np.column_stack([col, row])

    def project_to_opencv(self, points_cam_m: ArrayLike) -> np.ndarray:
        """Camera-frame points (N, 3) -> OpenCV ``[col, row]`` (N, 2)."""
        return self.metric_to_opencv(project_points(points_cam_m, self.focal_length_m))


def rectangle_corners_m(length_m: float, width_m: float) -> np.ndarray:
    """Corners (4, 2) of a ``length x width`` rectangle in its own frame (x forward, y right).

    Order as docs/reference/wire.md ``corners_px``: front-left, front-right, rear-right, rear-left.
    """
    hl, hw = 0.5 * length_m, 0.5 * width_m
    return np.array([[hl, -hw], [hl, hw], [-hl, hw], [-hl, -hw]])
