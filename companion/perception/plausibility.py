"""Geometric plausibility of a detected quadrilateral (pure numpy).

Pixel convention: ``(col, row)``, row down. In these coordinates a positive shoelace area means
the polygon runs *clockwise on screen* (top-left, top-right, bottom-right, bottom-left).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from companion.perception._types import FloatArray, PerceptionError


@dataclass(frozen=True)
class QuadLimits:
    """Bounds a target quadrilateral must meet to be accepted.

    ``min_area_px``: smaller blobs are noise or a target too far to measure (px^2).
    ``max_area_fraction``: of the image area; larger means we are too close or it is not the
    target. ``expected_aspect``: the target's long/short side ratio (>= 1).
    ``max_aspect_distortion``: how far perspective (camera tilt) may stretch that ratio, as a
    factor: accepted ratios are ``[expected / f, expected * f]`` (and >= 1). 1/cos(0.6 rad) is
    1.21 for a fronto-parallel plane tilted by the vehicle's maximum tilt; 1.6 leaves room for
    off-axis perspective. ``border_margin_px``: a candidate whose outline comes this close to
    the image border is partially visible and rejected. ``min_corner_angle_rad``: smallest
    interior angle (a rectangle under the allowed perspective stays far from 0 and pi).
    """

    min_area_px: float = 150.0
    max_area_fraction: float = 0.5
    expected_aspect: float = 1.25
    max_aspect_distortion: float = 1.6
    border_margin_px: float = 1.0
    min_corner_angle_rad: float = 0.6

    def __post_init__(self) -> None:
        if not self.min_area_px > 0:
            raise PerceptionError("min_area_px: must be > 0")
        if not 0 < self.max_area_fraction <= 1:
            raise PerceptionError("max_area_fraction: must be in (0, 1]")
        if not self.expected_aspect >= 1:
            raise PerceptionError("expected_aspect: must be >= 1 (long / short)")
        if not self.max_aspect_distortion >= 1:
            raise PerceptionError("max_aspect_distortion: must be >= 1")
        if not self.border_margin_px >= 0:
            raise PerceptionError("border_margin_px: must be >= 0")
        if not 0 < self.min_corner_angle_rad < math.pi / 2:
            raise PerceptionError("min_corner_angle_rad: must be in (0, pi/2)")


def _rot(a: FloatArray, k: int) -> FloatArray:
    """``np.roll(a, -k, axis=0)`` without its overhead (these run on 4-corner arrays)."""
    k %= a.shape[0]
    return np.concatenate((a[k:], a[:k]))


def _nxt(a: FloatArray) -> FloatArray:
    return _rot(a, 1)


def _prv(a: FloatArray) -> FloatArray:
    return _rot(a, -1)


def signed_area(corners: npt.ArrayLike) -> float:
    """Shoelace area of a polygon (N, 2) ``(col, row)``: > 0 clockwise on screen (px^2)."""
    c = np.asarray(corners, dtype=np.float64)
    x, y = c[:, 0], c[:, 1]
    return 0.5 * float(np.sum(x * _nxt(y) - _nxt(x) * y))


def is_convex(corners: npt.ArrayLike) -> bool:
    """True for a strictly convex, non-self-intersecting polygon (N >= 3)."""
    c = np.asarray(corners, dtype=np.float64)
    e = _nxt(c) - c
    cross = e[:, 0] * _nxt(e)[:, 1] - e[:, 1] * _nxt(e)[:, 0]
    if np.any(np.abs(cross) < 1e-12):
        return False
    if not (np.all(cross > 0) or np.all(cross < 0)):
        return False
    # turning number 1 (a pentagram has all-positive cross products but turns twice)
    ang = np.arctan2(e[:, 1], e[:, 0])
    turn = np.sum(np.angle(np.exp(1j * (_nxt(ang) - ang))))
    return bool(abs(abs(turn) - 2 * math.pi) < 1e-6)


def interior_angles(corners: npt.ArrayLike) -> FloatArray:
    """Interior angle at each vertex of a convex polygon (rad)."""
    c = np.asarray(corners, dtype=np.float64)
    a = _prv(c) - c
    b = _nxt(c) - c
    cosang = np.sum(a * b, axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return np.asarray(np.arccos(np.clip(cosang, -1.0, 1.0)), dtype=np.float64)


def edge_lengths(corners: npt.ArrayLike) -> FloatArray:
    """Length of edge i (corner i -> corner i+1), px."""
    c = np.asarray(corners, dtype=np.float64)
    return np.asarray(np.linalg.norm(_nxt(c) - c, axis=1), dtype=np.float64)


def aspect_ratio(corners: npt.ArrayLike) -> float:
    """Ratio of the longer to the shorter pair of opposite edges' summed lengths (>= 1)."""
    e = edge_lengths(corners)
    a, b = e[0] + e[2], e[1] + e[3]
    return float(max(a, b) / max(min(a, b), 1e-12))


def order_clockwise(corners: npt.ArrayLike) -> FloatArray:
    """Return the 4 corners clockwise on screen (positive :func:`signed_area`), same start."""
    c = np.array(corners, dtype=np.float64)
    if signed_area(c) < 0:
        c = c[[0, 3, 2, 1]]
    return c


def order_target_corners(
    corners: npt.ArrayLike, first_edge_short: bool, hint: npt.ArrayLike | None = None
) -> FloatArray:
    """Put a rectangle's image corners in the target order.

    Order: clockwise on screen, and edge 0 (corner 0 -> 1) is the image of the target's
    width edge (``first_edge_short`` says whether that edge is the shorter one). Two
    rotations satisfy this (a plain rectangle is symmetric under a half turn); ``hint``
    (previous corners, same order) picks the closer one, else the one whose edge 0 is
    higher in the image (smaller row = forward for a downward camera with forward up).
    """
    c = order_clockwise(corners)
    e = edge_lengths(c)
    pair02_short = (e[0] + e[2]) <= (e[1] + e[3])
    start = 0 if pair02_short == first_edge_short else 1
    options = [_rot(c, start), _rot(c, start + 2)]
    if hint is not None:
        h = np.asarray(hint, dtype=np.float64)
        cost = [float(np.sum(np.linalg.norm(o - h, axis=1))) for o in options]
        return options[int(np.argmin(cost))]
    rows = [float(o[0, 1] + o[1, 1]) for o in options]
    return options[int(np.argmin(rows))]


def touches_border(points: npt.ArrayLike, width: int, height: int, margin_px: float) -> bool:
    """True if any point lies within ``margin_px`` of the image border (pixel centres)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    lo = margin_px
    return bool(
        np.any(p[:, 0] <= lo)
        or np.any(p[:, 1] <= lo)
        or np.any(p[:, 0] >= width - 1 - lo)
        or np.any(p[:, 1] >= height - 1 - lo)
    )


def check_quad(corners: npt.ArrayLike, width: int, height: int, limits: QuadLimits) -> str | None:
    """First failed plausibility check as a reason string, or ``None`` if plausible."""
    c = np.asarray(corners, dtype=np.float64)
    if c.shape != (4, 2) or not np.all(np.isfinite(c)):
        return "corners not finite (4, 2)"
    if not is_convex(c):
        return "not a convex quadrilateral"
    area = abs(signed_area(c))
    if area < limits.min_area_px:
        return f"too small: area {area:.0f} px^2 < {limits.min_area_px:.0f}"
    if area > limits.max_area_fraction * width * height:
        return f"too large: area {area:.0f} px^2 > {limits.max_area_fraction:g} of the image"
    ang = interior_angles(c)
    if float(np.min(ang)) < limits.min_corner_angle_rad:
        return f"implausible perspective: corner angle {float(np.min(ang)):.2f} rad"
    ratio = aspect_ratio(c)
    lo = max(1.0, limits.expected_aspect / limits.max_aspect_distortion)
    hi = limits.expected_aspect * limits.max_aspect_distortion
    if not lo <= ratio <= hi:
        return f"aspect ratio {ratio:.2f} outside [{lo:.2f}, {hi:.2f}]"
    if touches_border(c, width, height, limits.border_margin_px):
        return "touches image border: partially visible"
    return None
