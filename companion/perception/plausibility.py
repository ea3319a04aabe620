"""Geometric plausibility of a detected quadrilateral (pure numpy).

Pixel convention: ``(col, row)``, row down. In these coordinates a positive shoelace area means
the polygon runs *clockwise on screen* (top-left, top-right, bottom-right, bottom-left).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
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


# These run a few times per frame on 4-corner arrays, where numpy's per-call overhead is most
# of the cost: the corners are read into Python floats and the arithmetic done on scalars (the
# same IEEE operations in the same order as the array versions these replace).


def _pts(corners: npt.ArrayLike) -> list[tuple[float, float]]:
    c = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    return [(x, y) for x, y in c.tolist()]


def _rot(a: FloatArray, k: int) -> FloatArray:
    """``np.roll(a, -k, axis=0)`` without its overhead (these run on 4-corner arrays)."""
    k %= a.shape[0]
    return np.concatenate((a[k:], a[:k]))


def _signed_area(p: list[tuple[float, float]]) -> float:
    acc = 0.0
    for (x0, y0), (x1, y1) in zip(p, p[1:] + p[:1], strict=True):
        acc += x0 * y1 - x1 * y0
    return 0.5 * acc


def signed_area(corners: npt.ArrayLike) -> float:
    """Shoelace area of a polygon (N, 2) ``(col, row)``: > 0 clockwise on screen (px^2)."""
    return _signed_area(_pts(corners))


def _is_convex(p: list[tuple[float, float]]) -> bool:
    e = [(x1 - x0, y1 - y0) for (x0, y0), (x1, y1) in zip(p, p[1:] + p[:1], strict=True)]
    nxt = e[1:] + e[:1]
    cross = [ax * by - ay * bx for (ax, ay), (bx, by) in zip(e, nxt, strict=True)]
    if any(abs(c) < 1e-12 for c in cross):
        return False
    if not (all(c > 0 for c in cross) or all(c < 0 for c in cross)):
        return False
    # turning number 1 (a pentagram has all-positive cross products but turns twice)
    ang = [math.atan2(ey, ex) for ex, ey in e]
    turn = 0.0
    for a0, a1 in zip(ang, ang[1:] + ang[:1], strict=True):
        d = a1 - a0
        turn += math.atan2(math.sin(d), math.cos(d))  # the turn wrapped to (-pi, pi]
    return abs(abs(turn) - 2 * math.pi) < 1e-6


def is_convex(corners: npt.ArrayLike) -> bool:
    """True for a strictly convex, non-self-intersecting polygon (N >= 3)."""
    return _is_convex(_pts(corners))


def _interior_angles(p: list[tuple[float, float]]) -> list[float]:
    out = []
    for (px, py), (cx, cy), (nx, ny) in zip(p[-1:] + p[:-1], p, p[1:] + p[:1], strict=True):
        ax, ay, bx, by = px - cx, py - cy, nx - cx, ny - cy
        cosang = (ax * bx + ay * by) / (math.sqrt(ax * ax + ay * ay) * math.sqrt(bx * bx + by * by))
        out.append(math.acos(min(max(cosang, -1.0), 1.0)))
    return out


def interior_angles(corners: npt.ArrayLike) -> FloatArray:
    """Interior angle at each vertex of a convex polygon (rad)."""
    return np.array(_interior_angles(_pts(corners)), dtype=np.float64)


def _edge_lengths(p: list[tuple[float, float]]) -> list[float]:
    return [math.sqrt((x1 - x0) * (x1 - x0) + (y1 - y0) * (y1 - y0))
            for (x0, y0), (x1, y1) in zip(p, p[1:] + p[:1], strict=True)]


def edge_lengths(corners: npt.ArrayLike) -> FloatArray:
    """Length of edge i (corner i -> corner i+1), px."""
    return np.array(_edge_lengths(_pts(corners)), dtype=np.float64)


def _aspect_ratio(p: list[tuple[float, float]]) -> float:
    e = _edge_lengths(p)
    a, b = e[0] + e[2], e[1] + e[3]
    return max(a, b) / max(min(a, b), 1e-12)


def aspect_ratio(corners: npt.ArrayLike) -> float:
    """Ratio of the longer to the shorter pair of opposite edges' summed lengths (>= 1)."""
    return _aspect_ratio(_pts(corners))


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
    e = _edge_lengths(_pts(c))
    pair02_short = (e[0] + e[2]) <= (e[1] + e[3])
    start = 0 if pair02_short == first_edge_short else 1
    options = [_rot(c, start), _rot(c, start + 2)]
    if hint is not None:
        h = _pts(hint)
        cost = [sum(math.sqrt((x - hx) * (x - hx) + (y - hy) * (y - hy))
                          for (x, y), (hx, hy) in zip(_pts(o), h, strict=True))
                for o in options]
        return options[0 if cost[0] <= cost[1] else 1]
    rows = [float(o[0, 1] + o[1, 1]) for o in options]
    return options[0 if rows[0] <= rows[1] else 1]


def _touches(p: list[tuple[float, float]] | list[list[float]], width: int, height: int,
             margin_px: float) -> bool:
    """:func:`touches_border` on a few points as plain floats."""
    hx, hy = width - 1 - margin_px, height - 1 - margin_px
    return any(x <= margin_px or y <= margin_px or x >= hx or y >= hy for x, y in p)


def touches_border(points: npt.ArrayLike, width: int, height: int, margin_px: float) -> bool:
    """True if any point lies within ``margin_px`` of the image border (pixel centres)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    lo = margin_px
    if p.shape[0] <= 8:  # a quad: scalar comparisons (numpy's per-call cost dominates)
        return _touches(p.tolist(), width, height, lo)
    return bool(
        np.any(p[:, 0] <= lo)
        or np.any(p[:, 1] <= lo)
        or np.any(p[:, 0] >= width - 1 - lo)
        or np.any(p[:, 1] >= height - 1 - lo)
    )


def box_touches_border(box: Sequence[int], width: int, height: int,
                        margin_px: float) -> bool:
    """:func:`touches_border` of a contour from its bounding
    box ``(x, y, w, h)`` (``cv2.boundingRect``: integer points, so its extremes are the
    points' own minima and maxima)."""
    x, y, bw, bh = box
    lo = margin_px
    return (x <= lo or y <= lo or x + bw - 1 >= width - 1 - lo
            or y + bh - 1 >= height - 1 - lo)


def approx_quad(contour: npt.NDArray[np.int32]) -> FloatArray | None:
    """Four vertices approximating a blob's convex hull, or ``None``."""
    hull = cv2.convexHull(contour)
    peri = cv2.arcLength(hull, True)
    # the smallest tolerance that yields 4 vertices keeps them closest to the true corners
    for frac in (0.005, 0.01, 0.015, 0.02, 0.03, 0.04, 0.05, 0.07):
        poly = cv2.approxPolyDP(hull, frac * peri, True)
        if len(poly) == 4:
            return poly.reshape(4, 2).astype(np.float64)
    return None


def check_quad(corners: npt.ArrayLike, width: int, height: int, limits: QuadLimits) -> str | None:
    """First failed plausibility check as a reason string, or ``None`` if plausible."""
    c = np.asarray(corners, dtype=np.float64)
    if c.shape != (4, 2):
        return "corners not finite (4, 2)"
    p = _pts(c)  # plain floats from here on (numpy's per-call cost dominates on 4 corners)
    if not all(math.isfinite(x) and math.isfinite(y) for x, y in p):
        return "corners not finite (4, 2)"
    if not _is_convex(p):
        return "not a convex quadrilateral"
    area = abs(_signed_area(p))
    if area < limits.min_area_px:
        return f"too small: area {area:.0f} px^2 < {limits.min_area_px:.0f}"
    if area > limits.max_area_fraction * width * height:
        return f"too large: area {area:.0f} px^2 > {limits.max_area_fraction:g} of the image"
    min_ang = min(_interior_angles(p))
    if min_ang < limits.min_corner_angle_rad:
        return f"implausible perspective: corner angle {min_ang:.2f} rad"
    ratio = _aspect_ratio(p)
    lo = max(1.0, limits.expected_aspect / limits.max_aspect_distortion)
    hi = limits.expected_aspect * limits.max_aspect_distortion
    if not lo <= ratio <= hi:
        return f"aspect ratio {ratio:.2f} outside [{lo:.2f}, {hi:.2f}]"
    if _touches(p, width, height, limits.border_margin_px):
        return "touches image border: partially visible"
    return None
