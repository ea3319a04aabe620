"""Sub-pixel corners of a bright convex quadrilateral in three sampled passes (the rectangle
detector's ``edges = "lean"``, the default since 2026-11-28).

The measure per profile is the one of :mod:`companion.perception.edges`: the edge lies where
the intensity crosses the midpoint between the inside plateau (the mean of a 1 px window
inside the transition) and the outside level (the darkest sample just beyond it, so a box side
showing as a thin dark band sets it); a total-least-squares line with one outlier pass is
fitted to each edge's crossings and adjacent lines are intersected. What differs is how the
profiles are placed, which is where the time went (numpy's per-call cost, not the arithmetic:
the old per-row plateau windows took ~65 calls a pass, three passes, and a second batch for a
blurred edge):

1. each edge's ``samples_per_edge`` profiles (``profile_half_px`` long, every
   ``profile_step_px``) are one ``cv2.warpAffine`` (a rotated grid); every row is centred on
   the coarse edge, so the plateau windows are the same columns for every row and a pass is
   ~20 whole-array calls; lines are fitted to the four edges at once (weighted moments);
2. the profiles are sampled again, each row centred on its edge's fitted line and stretched by
   the edge's measured blur (a transition ``w`` px wide is sampled ``(0.5 + 0.9 w) / 1.4``
   times coarser, at most 3x), so the same columns again hold the plateaus at the distance
   the blur needs (the old detector's second, longer profiles, without a second layout);
3. once more, centred on pass 2's lines; the final lines (with the outlier pass) are fitted to
   these crossings. Two passes were as accurate from a blob's coarse corners but not from a
   tracked start 2-3 px off under noise 20: a second pass centred on a biased first line can
   keep the bias, and a tracker feeds it back (measured: a corner drifting 7 px over 12
   frames; with the third pass, 0.40 px at most).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from companion.perception._types import FloatArray, PerceptionError
from companion.perception.edges import EdgeFit

_F32 = npt.NDArray[np.float32]


@dataclass(frozen=True)
class LeanSettings:
    """``profile_half_px``: half length of a profile across a sharp edge (also the unit
    profile the blurred edges' profiles are stretched from); must cover the coarse corners'
    error. ``profile_step_px``: sample spacing along it. ``min_contrast``: inside minus outside
    (grey levels) for a profile to count. ``samples_per_edge``: profiles per edge (spread
    evenly between the corners, ``1.5 * profile_half_px + 1`` px away from them)."""

    profile_half_px: float = 4.0
    profile_step_px: float = 0.25
    min_contrast: float = 40.0
    samples_per_edge: int = 48
    passes: int = 3

    def __post_init__(self) -> None:
        if not self.profile_half_px >= 3:
            raise PerceptionError("profile_half_px: must be >= 3")
        if not 0 < self.profile_step_px <= 0.5:
            raise PerceptionError("profile_step_px: must be in (0, 0.5]")
        if self.samples_per_edge < 8:
            raise PerceptionError("samples_per_edge: must be >= 8")


@dataclass(frozen=True)
class _Grid:
    """Column layout of a batch of profiles (depends only on the settings): offsets ``ks``
    along the profile (px at scale 1), the plateau windows' columns, and a priority that
    prefers the crossing nearest the centre."""

    ks: FloatArray
    ks32: _F32
    in_cols: slice
    out_cols: slice
    prio: _F32
    in_norm: np.float32  # 1 / the inside window's samples
    step: np.float32
    inv_step: np.float32
    j: FloatArray  # profile index along an edge, 0..N-1
    row_k: npt.NDArray[np.intp]  # row offsets in the flattened profiles (k columns)
    row_k1: npt.NDArray[np.intp]  # and in arrays of k - 1 columns


_GRIDS: dict[tuple[float, float, int], _Grid] = {}


def _grid(s: LeanSettings) -> _Grid:
    key = (s.profile_half_px, s.profile_step_px, s.samples_per_edge)
    g = _GRIDS.get(key)
    if g is None:
        h, r = s.profile_step_px, s.profile_half_px
        n = round(r / h)
        ks = np.arange(-n, n + 1) * h
        # the old detector's windows for an edge at 0 of width 1: inside [-2.4, -1.4], the
        # outside's darkest sample in [0.5, 2.4] (columns by the same searchsorted rule)
        in_cols = slice(int(ks.searchsorted(-2.4, "left")), int(ks.searchsorted(-1.4, "right")))
        out_cols = slice(int(ks.searchsorted(0.5, "left")), int(ks.searchsorted(2.4, "right")))
        mid = 0.5 * (ks[:-1] + ks[1:])
        prio = (2.0 * r - np.abs(mid)).astype(np.float32)  # > 0: nearer the centre wins
        rows = np.arange(4 * s.samples_per_edge)
        g = _Grid(np.asarray(ks, dtype=np.float64), ks.astype(np.float32), in_cols, out_cols, prio,
                  np.float32(1.0 / (in_cols.stop - in_cols.start)), np.float32(h),
                  np.float32(1.0 / h), np.arange(s.samples_per_edge, dtype=np.float64),
                  rows * len(ks), rows * (len(ks) - 1))
        _GRIDS[key] = g
    return g


def refine_quad_lean(gray: npt.NDArray[np.uint8], corners: FloatArray, s: LeanSettings
                     ) -> tuple[FloatArray, list[EdgeFit]] | None:
    """Sub-pixel corners (4, 2) of the bright convex quadrilateral whose coarse corners
    (clockwise on screen, within ~2 px) are ``corners``, and the four edges' fits; ``None``
    when an edge is too short or has too few measured profiles (under ``max(4, 30 %)``).

    Each edge works in its own frame: an origin ``p0``, the unit direction ``t`` along it and
    the outward normal ``nrm``; profile ``j`` is centred on ``p0 + j sp t``, its crossing at
    ``e`` px along ``nrm``. Lines are fitted to ``(j sp, e)`` in that frame (a rotation: the
    same total-least-squares line as in the image) and mapped back."""
    g = _grid(s)
    frames = edge_frames(corners, s)
    if frames is None:
        return None
    u = g.j[None, :] * np.array([f[4] for f in frames])[:, None]  # (4, N) along each edge
    e, ok, width = _pass(gray, frames, _ONES, g, s, True)
    lines = _fit(u, e, ok, False)
    if lines is None:
        return None
    # the edges' blur sets how far apart the next passes read the plateaus
    scale = [min(max((0.5 + 0.9 * max(w, 1.0)) / 1.4, 1.0), 3.0) for w in width]
    passes = s.passes
    for it in range(1, passes):
        frames = [_on_line(f, ln) for f, ln in zip(frames, lines, strict=True)]
        e, ok, _ = _pass(gray, frames, scale, g, s, False)
        lines = _fit(u, e, ok, it == passes - 1)
        if lines is None:
            return None
    fits = [_edge_fit(f, ln) for f, ln in zip(frames, lines, strict=True)]
    out = _intersections(fits)
    return None if out is None else (out, fits)


_Frame = tuple[float, float, float, float, float]  # p0 x, y; t x, y; profile spacing sp
_Line = tuple[float, float, float, float, float, float]  # u, v of a point; cos, sin; rms, kept
_ONES = [1.0, 1.0, 1.0, 1.0]



def edge_frames(corners: FloatArray, s: LeanSettings) -> list[_Frame] | None:
    """Each edge's frame (origin, unit direction, profile spacing) from the quad's corners,
    the profiles kept ``1.5 profile_half_px + 1`` px from the corners; None when an edge is
    too short for that."""
    c = np.asarray(corners, dtype=np.float64).tolist()
    margin = 1.5 * s.profile_half_px + 1.0
    frames = []
    for i in range(4):
        (ax, ay), (bx, by) = c[i], c[(i + 1) % 4]
        dx, dy = bx - ax, by - ay
        length = math.sqrt(dx * dx + dy * dy)
        if length < 2.0 * margin + 4.0:
            return None
        tx, ty = dx / length, dy / length
        frames.append((ax + margin * tx, ay + margin * ty, tx, ty,
                       (length - 2.0 * margin) / (s.samples_per_edge - 1)))
    return frames

def _pass(gray: npt.NDArray[np.uint8], frames: list[_Frame], scale: list[float], g: _Grid,
          s: LeanSettings, want_width: bool
          ) -> tuple[FloatArray, npt.NDArray[np.bool_], list[float]]:
    """One set of profiles, edge ``i`` sampled every ``step * scale[i]`` px (one
    ``cv2.warpAffine`` per edge: the profiles of an edge are a rotated, scaled grid). Per
    profile: the crossing's offset ``e`` (px along the normal) and whether it was measured;
    per edge (``want_width``): the median transition width (px; 1.0 without any)."""
    n, k = s.samples_per_edge, g.ks.shape[0]
    raw = np.empty((4 * n, k), dtype=np.uint8)
    h, k0 = float(g.step), float(g.ks[0])
    for i, ((x0, y0, tx, ty, sp), sc) in enumerate(zip(frames, scale, strict=True)):
        nx, ny = ty * sc, -tx * sc  # outward normal, scaled
        m = np.array([[h * nx, sp * tx, x0 + k0 * nx], [h * ny, sp * ty, y0 + k0 * ny]])
        cv2.warpAffine(gray, m, (k, n), dst=raw[i * n:(i + 1) * n],
                       flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                       borderMode=cv2.BORDER_REPLICATE)
    prof = raw.astype(np.float32)
    inside = np.add.reduce(prof[:, g.in_cols], axis=1) * g.in_norm
    outside = np.minimum.reduce(prof[:, g.out_cols], axis=1)
    level = 0.5 * (inside + outside)
    # a falling crossing between columns j and j + 1; the one nearest the centre
    above = prof >= level[:, None]
    score = (above[:, :-1] > above[:, 1:]) * g.prio
    idx = score.argmax(axis=1)
    found = np.maximum.reduce(score, axis=1) > 0.0
    v01 = prof.ravel()[(g.row_k + idx)[:, None] + _PAIR]
    v0 = v01[:, 0]
    frac = (v0 - level) / np.maximum(v0 - v01[:, 1], np.float32(1e-6))
    contrast = inside - outside
    ok = (found & (contrast >= s.min_contrast)).reshape(4, n)
    e_unit = ((idx + frac) * g.step + np.float32(k0)).reshape(4, n)
    if scale is not _ONES:
        e_unit = e_unit * np.array(scale, dtype=np.float32)[:, None]
    e: FloatArray = e_unit.astype(np.float64)
    if not want_width:
        return e, ok, []
    # transition width (px): contrast over the steepest slope at the crossing's columns
    diffs = (prof[:, :-1] - prof[:, 1:]).ravel()
    near = np.minimum(np.maximum(idx[:, None] + _NEAR, 0), k - 2) + g.row_k1[:, None]
    slope = np.maximum.reduce(diffs[near], axis=1) * g.inv_step
    width = np.where(ok.ravel(), contrast / np.maximum(slope, 1e-6), np.inf).reshape(4, n)
    return e, ok, _medians(width, ok.sum(axis=1)).tolist()


def _fit(u: FloatArray, v: FloatArray, ok: npt.NDArray[np.bool_], final: bool
         ) -> list[_Line] | None:
    """Each edge's line through its measured points ``(u, v)`` (4, N), or ``None`` when an
    edge has fewer than max(4, 30 %) measured points. ``final``: with one outlier pass (the
    old detector's rule: drop points farther than max(3 (1.4826 MAD + 0.05), 0.3) px from the
    line, refit if at least 4 remain), the RMS distance (px) and the fraction of profiles
    kept (else 0, 0: the lines of the first passes only place the next profiles)."""
    n = v.shape[1]
    cnt = ok.sum(axis=1)
    if int(cnt.min()) < max(4, 0.3 * n):
        return None
    w = ok.astype(np.float64)
    line = _tls(u, v, w)
    if not final:
        return [(*ln, 0.0, 0.0) for ln in line]
    res = _distances(u, v, line)
    bound = np.maximum(3.0 * (_medians(np.where(ok, res, np.inf), cnt) * 1.4826 + 0.05), 0.3)
    keep = ok & (res <= bound[:, None])
    n_keep = keep.sum(axis=1)
    refit = (n_keep >= 4) & (n_keep < cnt)
    if refit.any():
        keep = np.where(refit[:, None], keep, ok)
        w = keep.astype(np.float64)
        line = _tls(u, v, w)
        res = _distances(u, v, line)
    rms = np.sqrt((w * res * res).sum(axis=1) / w.sum(axis=1)).tolist()
    frac = (n_keep / n).tolist()
    return [(*line[i], rms[i], frac[i]) for i in range(4)]


def _tls(u: FloatArray, v: FloatArray, w: FloatArray) -> list[tuple[float, float, float, float]]:
    """Weighted total-least-squares lines through (u, v) (4, N), weights 0 or 1: per edge the
    centroid and unit direction ``(cu, cv, cos, sin)``. The five weighted moments come from
    one sum over a stacked array; the 2 x 2 scatter and its principal axis per edge in plain
    floats (numpy's per-call cost dominates on 4 lines)."""
    wu, wv = w * u, w * v
    mom = np.stack((w, wu, wv, wu * u, wu * v, wv * v)).sum(axis=2).tolist()
    line = []
    for sw, su, sv, suu, suv, svv in zip(*mom, strict=True):
        cu, cv = su / sw, sv / sw
        sxx, sxy, syy = suu - su * cu, suv - su * cv, svv - sv * cv
        half = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
        line.append((cu, cv, math.cos(half), math.sin(half)))
    return line


def _distances(u: FloatArray, v: FloatArray, line: list[tuple[float, float, float, float]]
               ) -> FloatArray:
    """Every point's distance (4, N) from its edge's line."""
    cs = np.array([(cos, sin, cv * cos - cu * sin) for cu, cv, cos, sin in line])
    res: FloatArray = np.abs(v * cs[:, 0:1] - u * cs[:, 1:2] - cs[:, 2:3])
    return res


def _on_line(f: _Frame, ln: _Line) -> _Frame:
    """The frame of an edge's fitted line: origin the foot of ``f``'s origin on it, direction
    along it (the sense of ``f``'s), the same profile spacing."""
    x0, y0, tx, ty, sp = f
    cu, cv, cos, sin = ln[:4]
    if cos < 0.0:  # the line's sense along the edge's
        cos, sin = -cos, -sin
    dx, dy = cos * tx + sin * ty, cos * ty - sin * tx  # cos t + sin nrm, nrm = (ty, -tx)
    px, py = x0 + cu * tx + cv * ty, y0 + cu * ty - cv * tx
    a = (x0 - px) * dx + (y0 - py) * dy
    return (px + a * dx, py + a * dy, dx, dy, sp)


def _edge_fit(f: _Frame, ln: _Line) -> EdgeFit:
    x0, y0, tx, ty, _ = f
    cu, cv, cos, sin, rms, kept = ln
    point = np.array([x0 + cu * tx + cv * ty, y0 + cu * ty - cv * tx])
    direction = np.array([cos * tx + sin * ty, cos * ty - sin * tx])
    return EdgeFit(point, direction, rms, kept)


def _intersections(fits: list[EdgeFit]) -> FloatArray | None:
    """Corner ``i``: lines ``i - 1`` and ``i`` intersected (Cramer's rule), ``None`` if two
    adjacent lines are (nearly) parallel."""
    out = np.empty((4, 2))
    pts = [f.point.tolist() for f in fits]
    dirs = [f.direction.tolist() for f in fits]
    for i in range(4):
        (p1x, p1y), (d1x, d1y) = pts[i - 1], dirs[i - 1]
        (p2x, p2y), (d2x, d2y) = pts[i], dirs[i]
        det = d2x * d1y - d1x * d2y
        if abs(det) < 1e-6:
            return None
        rx, ry = p2x - p1x, p2y - p1y
        t1 = (d2x * ry - rx * d2y) / det
        out[i] = (p1x + t1 * d1x, p1y + t1 * d1y)
    return out


def _medians(x: FloatArray, cnt: npt.NDArray[np.intp]) -> FloatArray:
    """Per row of ``x`` (4, N): the median of its first ``cnt`` entries once sorted (the
    others are +inf), 1.0 for a row without any."""
    xs = np.sort(x, axis=1)
    h = cnt // 2
    hi = xs[_ROWS4, np.minimum(h, x.shape[1] - 1)]
    lo = xs[_ROWS4, np.maximum(h - 1, 0)]
    med = np.where(cnt % 2 == 1, hi, 0.5 * (lo + hi))
    return np.where(cnt > 0, med, 1.0)


_ROWS4 = np.arange(4)
_NEAR = np.array([-2, 0, 2])
_PAIR = np.array([0, 1])


__all__ = ["LeanSettings", "refine_quad_lean"]
