"""Camera geometry of spec sections 1, 2, 5 and 6 (the virtual camera and the visible area).

Conventions (shared/spec/rmpc-ibvs.md section 1): world NED, body FRD, ZYX Euler
``R = Rz(psi) Ry(theta) Rx(phi)``. Camera axes = body axes (x forward, y right, z down = optical
axis). Metric image coordinates ``u = lambda x/z`` (along camera x), ``n = lambda y/z``.
The virtual camera ``v`` has the camera's origin and yaw, roll = pitch = 0:
``p_v = Ry(theta) Rx(phi) p_c``.

Functions here accept numpy arrays (vectorised) or CasADi symbols (for the RMPC).
"""

from __future__ import annotations

from typing import Any

from companion.core._backend import asin, atan, xp


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
