"""Image moments of the target in the virtual image (docs/reference/math.md, section 3).

Points are metric virtual-image coordinates ``[u_v, n_v]`` (m on the image plane, spec 2).
With ``N_p`` points::

    u_v_bar, n_v_bar = mean of the points
    mu_ij = sum_t (u_v_t - u_v_bar)^i (n_v_t - n_v_bar)^j          (m^(i+j))
    a     = mu_20 + mu_02
    s3    = sqrt(a_star / a),  s1 = s3 u_v_bar / lambda,  s2 = s3 n_v_bar / lambda
    s4    = 0.5 atan2(2 mu_11, mu_20 - mu_02)       (rad, unwrapped across frames)

For a horizontal planar target whose centroid is ``(x_v, y_v, z)`` in the virtual frame:
``s1 = x_v/z*``, ``s2 = y_v/z*``, ``s3 = z/z*`` and ``s4`` = the target's principal axis
relative to the camera's yaw.

``s4`` needs an anisotropic target: for a square (e.g. an ArUco marker) ``mu_20 = mu_02`` and
``mu_11 = 0`` at every rotation, so ``s4`` carries no information (see
:attr:`ImageMoments.anisotropy`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from companion.core.frozen import make
from companion.core.geometry import GeometryError, project_points

# Points whose rms spread about their centroid is below this fraction of the image scale
# (max(lambda, largest |point|)) are treated as coincident.
COINCIDENT_REL_TOL = 1e-9
# sqrt(det(mu)) / a is 0 for collinear points and 0.5 for an isotropic cloud (a square gives
# 0.5, the 0.5 x 0.4 m AGV top 0.49). Below this the points are treated as collinear: the
# thinner axis is < 2e-6 of the longer one, far below any real detection.
COLLINEAR_REL_TOL = 1e-6


class DegenerateTargetError(GeometryError):
    """The target points cannot give image moments (too few, non-finite, coincident or
    collinear points). The frame must be treated as "target not measured"."""


@dataclass(frozen=True, eq=False)  # holds arrays: no element-wise ==
class ImageMoments:
    """Image-moment features of one frame (spec 3).

    ``s``: (4,) ``[s1, s2, s3, s4]`` (s1..s3 dimensionless, s4 rad) -- read-only array;
    ``u_v_bar_m, n_v_bar_m``: centroid in the virtual image (m); ``a`` (m^2) and the central
    moments ``mu20, mu02, mu11`` (m^2) of the virtual-image points.
    """

    s: np.ndarray
    u_v_bar_m: float
    n_v_bar_m: float
    a: float
    mu20: float
    mu02: float
    mu11: float
    n_points: int = field(default=0)

    def __post_init__(self) -> None:
        s = self.s
        if not (isinstance(s, np.ndarray) and s.dtype == np.float64 and s.shape == (4,)
                and s.base is None and not s.flags.writeable):
            s = np.array(s, dtype=float).reshape(4)
            s.setflags(write=False)
        object.__setattr__(self, "s", s)

    @property
    def anisotropy(self) -> float:
        """``sqrt((mu20 - mu02)^2 + 4 mu11^2) / a`` in [0, 1]: 0 = isotropic (s4 undefined),
        1 = a line. The 0.5 x 0.4 m AGV top gives 0.22 (level view)."""
        return math.hypot(self.mu20 - self.mu02, 2.0 * self.mu11) / self.a


def central_moments(points_v_m: ArrayLike) -> tuple[float, float, float, float, float]:
    """``(u_bar, n_bar, mu20, mu02, mu11)`` of (N, 2) points (m, m^2), N >= 3.

    Raises :class:`DegenerateTargetError` for fewer than 3 points, non-finite values, coincident
    points (:data:`COINCIDENT_REL_TOL`) or collinear points (:data:`COLLINEAR_REL_TOL`).
    """
    p = np.asarray(points_v_m, dtype=float)
    if p.ndim != 2 or p.shape[1] != 2:
        raise DegenerateTargetError(f"target points: expected shape (N, 2), got {p.shape}")
    if p.shape[0] < 3:
        raise DegenerateTargetError(f"target points: need >= 3, got {p.shape[0]}")
    us, ns = p[:, 0].tolist(), p[:, 1].tolist()
    if not all(map(math.isfinite, us + ns)):
        raise DegenerateTargetError("target points: non-finite value")
    if len(us) >= 8:  # numpy sums eight or more pairwise: keep its values there
        ub, nb = float(np.mean(p[:, 0])), float(np.mean(p[:, 1]))
        du, dn = p[:, 0] - ub, p[:, 1] - nb
        return ub, nb, float(np.sum(du * du)), float(np.sum(dn * dn)), float(np.sum(du * dn))
    return _small_central_moments(us, ns)


def _small_central_moments(us: list[float],
                           ns: list[float]) -> tuple[float, float, float, float, float]:
    """:func:`central_moments` of fewer than eight finite points (two lists of floats)."""
    # a handful of points (the target's corners): plain floats, summed in order as numpy sums
    # fewer than eight (the same values, without its per-call overhead)
    ub, nb = _ordered_sum(us) / len(us), _ordered_sum(ns) / len(ns)
    dus = [u - ub for u in us]
    dns = [n - nb for n in ns]
    mu20 = _ordered_sum([a * a for a in dus])
    mu02 = _ordered_sum([b * b for b in dns])
    mu11 = _ordered_sum([a * b for a, b in zip(dus, dns, strict=True)])
    return ub, nb, mu20, mu02, mu11


def _ordered_sum(values: list[float]) -> float:
    """Left-to-right sum (Python's ``sum`` of floats is compensated from 3.12 on)."""
    total = 0.0
    for v in values:
        total += v
    return total


def _check_spread(
    mu20: float, mu02: float, mu11: float, n_points: int, scale: float
) -> None:
    a = mu20 + mu02
    if not a > 0 or math.sqrt(a / n_points) <= COINCIDENT_REL_TOL * scale:
        raise DegenerateTargetError(f"target points coincide (a = {a:.3e} m^2)")
    det = max(mu20 * mu02 - mu11 * mu11, 0.0)
    if math.sqrt(det) / a < COLLINEAR_REL_TOL:
        raise DegenerateTargetError(
            f"target points are collinear (sqrt(det mu)/a = {math.sqrt(det) / a:.3e})"
        )


def orientation_raw(mu20: float, mu02: float, mu11: float) -> float:
    """``0.5 atan2(2 mu11, mu20 - mu02)`` in (-pi/2, pi/2] (rad), before unwrapping."""
    return 0.5 * math.atan2(2.0 * mu11, mu20 - mu02)


def unwrap_s4(s4_raw_rad: float, s4_prev_rad: float | None) -> float:
    """Continue ``s4`` across frames: ``s4_raw + k pi`` closest to the previous value.

    The rectangle is symmetric under 180 deg, so ``0.5 atan2`` is defined modulo pi and jumps
    by pi when the principal axis passes +-90 deg. ``s4_prev_rad=None`` (first frame, or after
    the target was lost) returns the raw value in (-pi/2, pi/2].
    """
    if s4_prev_rad is None:
        return float(s4_raw_rad)
    if not math.isfinite(s4_prev_rad):
        raise DegenerateTargetError("unwrap_s4: previous s4 is not finite")
    k = round((s4_prev_rad - s4_raw_rad) / math.pi)
    return float(s4_raw_rad + k * math.pi)


def heading_from_ordered_corners(points_v_m: ArrayLike) -> float:
    """Heading (rad, (-pi, pi]) of an ordered target (front-left, front-right, rear-right,
    rear-left) in the virtual image: the angle of its rear-to-front direction from the image's
    ``u`` axis towards ``n``. A level camera at yaw ``psi_q`` sees a world heading ``psi_a`` at
    ``psi_a - psi_q``: the same quantity the moment orientation gives for an elongated target,
    but unique over a full turn and defined for a square (an ArUco marker, whose moments
    ``mu20 = mu02, mu11 = 0`` carry no orientation)."""
    p = np.asarray(points_v_m, dtype=float)
    if p.shape != (4, 2) or not np.all(np.isfinite(p)):
        raise DegenerateTargetError(f"heading needs 4 finite ordered corners, got {p.shape}")
    d = 0.5 * (p[0] + p[1]) - 0.5 * (p[2] + p[3])
    if not np.hypot(d[0], d[1]) > 0:
        raise DegenerateTargetError("heading: front and rear edges coincide")
    return math.atan2(float(d[1]), float(d[0]))


def _heading_xy(us: list[float], ns: list[float]) -> float:
    """:func:`heading_from_ordered_corners` of four finite corners given as float lists."""
    if len(us) != 4:
        raise DegenerateTargetError(f"heading needs 4 finite ordered corners, got {len(us)}")
    du = 0.5 * (us[0] + us[1]) - 0.5 * (us[2] + us[3])
    dn = 0.5 * (ns[0] + ns[1]) - 0.5 * (ns[2] + ns[3])
    if not math.hypot(du, dn) > 0:
        raise DegenerateTargetError("heading: front and rear edges coincide")
    return math.atan2(dn, du)


def unwrap_angle(raw_rad: float, prev_rad: float | None, period_rad: float) -> float:
    """``raw_rad`` shifted by a multiple of ``period_rad`` to lie nearest ``prev_rad``."""
    if prev_rad is None or not math.isfinite(prev_rad):
        return float(raw_rad)
    return float(raw_rad + round((prev_rad - raw_rad) / period_rad) * period_rad)


S4_FOLD_HYSTERESIS_RAD = 0.25


def fold_s4(s4_rad: float | None, period_rad: float,
            hysteresis_rad: float = S4_FOLD_HYSTERESIS_RAD) -> float | None:
    """``s4`` shifted by one ``period_rad`` towards 0 once it is more than half a period plus
    ``hysteresis_rad`` away from it (None stays None).

    The unwrapped ``s4`` is continuous but unbounded: a target that keeps turning faster than
    the yaw-rate bound winds it up (and the state box ``|s4| <= eta_max[3]`` then makes every
    problem infeasible). The target is symmetric under ``period_rad`` (pi for the rectangle's
    moments, 2 pi for ordered corners), so the shifted value is the same heading, the nearer
    way round; the hysteresis keeps it from flipping back and forth at the fold."""
    if s4_rad is None or not math.isfinite(s4_rad):
        return s4_rad
    half = 0.5 * period_rad + hysteresis_rad
    while s4_rad > half:
        s4_rad -= period_rad
    while s4_rad < -half:
        s4_rad += period_rad
    return s4_rad


def image_moments(
    points_v_m: ArrayLike, a_star: float, lam: float, s4_prev_rad: float | None = None,
    *, heading_from_corners: bool = False,
) -> ImageMoments:
    """Features ``s`` of spec 3 from N >= 3 virtual-image points (N, 2) (m).

    ``a_star`` (m^2): ``a`` at the desired pose (:func:`a_star`); ``lam``: focal length (m);
    ``s4_prev_rad``: the previous frame's ``s4`` for unwrapping (:func:`unwrap_s4`).
    ``heading_from_corners``: take ``s4`` from the ordered corners
    (:func:`heading_from_ordered_corners`, unwrapped over 2 pi) instead of the moments' 0.5 atan2
    (needed for square targets such as ArUco markers).
    Raises :class:`DegenerateTargetError` (see :func:`central_moments`).
    """
    p = np.asarray(points_v_m, dtype=float)
    if p.ndim != 2 or p.shape[1] != 2:
        raise DegenerateTargetError(f"target points: expected shape (N, 2), got {p.shape}")
    if p.shape[0] >= 8:  # numpy's pairwise sums (central_moments): keep its values there
        _check_scalars(a_star, lam)
        mom = central_moments(p)
        return _moments_of(mom, p[:, 0].tolist(), p[:, 1].tolist(), a_star, lam,
                           s4_prev_rad, heading_from_corners)
    return image_moments_xy(p[:, 0].tolist(), p[:, 1].tolist(), a_star, lam, s4_prev_rad,
                            heading_from_corners=heading_from_corners)


def image_moments_xy(
    us: list[float], ns: list[float], a_star: float, lam: float,
    s4_prev_rad: float | None = None, *, heading_from_corners: bool = False,
) -> ImageMoments:
    """:func:`image_moments` of a few points given as two lists of floats (``u_v``, ``n_v``,
    m): the control step's path, without arrays (the same values as the array form)."""
    _check_scalars(a_star, lam)
    if len(us) < 3:
        raise DegenerateTargetError(f"target points: need >= 3, got {len(us)}")
    if not all(map(math.isfinite, us + ns)):
        raise DegenerateTargetError("target points: non-finite value")
    if len(us) >= 8:
        return image_moments(np.column_stack([us, ns]), a_star, lam, s4_prev_rad,
                             heading_from_corners=heading_from_corners)
    return _moments_of(_small_central_moments(us, ns), us, ns, a_star, lam, s4_prev_rad,
                       heading_from_corners)


def _check_scalars(a_star: float, lam: float) -> None:
    if not (math.isfinite(a_star) and a_star > 0):
        raise DegenerateTargetError(f"a_star must be finite and > 0 (got {a_star})")
    if not (math.isfinite(lam) and lam > 0):
        raise DegenerateTargetError(f"lam must be finite and > 0 (got {lam})")


def _moments_of(mom: tuple[float, float, float, float, float], us: list[float],
                ns: list[float], a_star: float, lam: float, s4_prev_rad: float | None,
                heading_from_corners: bool) -> ImageMoments:
    ub, nb, mu20, mu02, mu11 = mom
    scale = max(lam, max(map(abs, us)), max(map(abs, ns)))  # (map: no generator frame)
    _check_spread(mu20, mu02, mu11, len(us), scale)
    a = mu20 + mu02
    s3 = math.sqrt(a_star / a)
    if heading_from_corners:
        s4 = unwrap_angle(_heading_xy(us, ns), s4_prev_rad, 2.0 * math.pi)
    else:
        s4 = unwrap_s4(orientation_raw(mu20, mu02, mu11), s4_prev_rad)
    s = np.array([s3 * ub / lam, s3 * nb / lam, s3, s4])
    s.setflags(write=False)  # owned and read-only, as ImageMoments keeps it: no __post_init__
    return make(ImageMoments, s=s, u_v_bar_m=ub, n_v_bar_m=nb, a=a, mu20=mu20, mu02=mu02,
                mu11=mu11, n_points=len(us))


def a_star(target_points_m: ArrayLike, z_star_m: float, lam: float) -> float:
    """``a*`` (m^2): ``a`` of the target seen level from the desired depth (spec 3).

    ``target_points_m`` (N, 2): the target points in the target's own plane (m), e.g.
    :func:`companion.core.geometry.rectangle_corners_m`. They are placed at depth ``z_star_m``
    in front of a level camera and projected with focal length ``lam``; ``a`` does not depend
    on where in the plane or how rotated the target is. The 0.5 x 0.4 m AGV top at 2 m with
    ``lam = 2.8e-3`` gives 8.036e-7 (the paper's value).
    """
    p = np.asarray(target_points_m, dtype=float)
    if p.ndim != 2 or p.shape[1] != 2:
        raise DegenerateTargetError(f"a_star: expected (N, 2) target points, got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise DegenerateTargetError("a_star: non-finite target point")
    if not (math.isfinite(z_star_m) and z_star_m > 0):
        raise DegenerateTargetError(f"a_star: z_star_m must be finite and > 0 (got {z_star_m})")
    pts3 = np.column_stack([p, np.full(p.shape[0], float(z_star_m))])
    img = project_points(pts3, lam)
    _, _, mu20, mu02, mu11 = central_moments(img)
    _check_spread(mu20, mu02, mu11, p.shape[0], max(lam, float(np.max(np.abs(img)))))
    return mu20 + mu02
