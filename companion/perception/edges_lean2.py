"""Sub-pixel corners of a bright convex quadrilateral, the rectangle detector's
``edges = "lean2"`` (the default since 2026-11-28): the measure of ``"lean"``
(:mod:`companion.perception.edges_lean`: per profile the crossing of the midpoint between the
inside plateau and the darkest sample just outside, a total-least-squares line per edge with
one outlier pass, adjacent lines intersected; from a blob's coarse corners three passes, the
later ones centred on the previous lines and stretched by the edge's blur), with fewer numpy
calls and, while tracking, fewer passes:

- the profiles are the *columns* of a (4 edges, k samples, N profiles) array, so every
  per-profile reduction (plateau mean, outside minimum) runs along a middle axis, which numpy
  vectorises across the N profiles (along the last axis, ``"lean"``'s rows of 33 samples, it
  loops per row); the crossing's two samples are one gather, its presence the crossing test
  on them; the per-edge bookkeeping (medians, counts, refits) is on plain floats;
- tracking (``scale`` given: the previous frame's corners as the start, its blur scales): the
  first pass is already stretched by the previous frame's blur and fitted with the outlier
  pass, and it is the last one when it moved no line end farther than ``_ACCEPT_PX`` from
  where it was centred (the plateau windows were then where a centred pass puts them: the
  same crossings to sampling noise). Otherwise passes follow, each centred on the previous
  lines, until one moves no line end farther than ``_CONVERGED_PX`` (the next would read
  the same samples) or ``passes`` ran. The detector starts a tracked frame from the previous
  corners moved as they moved the frame before (``RectangleDetector._track``): on a paper
  flight's frames 1.08 passes a frame instead of 3.

The corners differ from ``"lean"``'s by hundredths of a pixel at most, hence a method of its
own: a log flown with ``"lean"`` replays with it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from companion.perception._types import FloatArray
from companion.perception.edges import EdgeFit
from companion.perception.edges_lean import (
    LeanSettings,
    _edge_fit,
    _fit,
    _Frame,
    _intersections,
    _Line,
    _on_line,
    edge_frames,
)

_F32 = npt.NDArray[np.float32]
_CONVERGED_PX = 0.02  # a pass moving no line end farther ends the passes (see above)
_ACCEPT_PX = 0.1  # a tracked first pass moving no line end farther is the last (see above)


@dataclass(frozen=True)
class _Grid2:
    """Layout of a batch of profiles (depends only on the settings): ``k`` samples at
    offsets ``ks`` (px at scale 1), the plateau windows' rows, a per-row priority that
    prefers the crossing nearest the centre, and each profile's flat index of its first
    sample (``base``)."""

    k: int
    k0: float
    step: float
    in_rows: slice
    out_rows: slice
    prio: _F32  # (1, k - 1, 1)
    in_norm: np.float32
    base: npt.NDArray[np.intp]  # (4, N): edge * k * N + profile
    base1: npt.NDArray[np.intp]  # the same in (4, k - 1, N) arrays
    j: FloatArray  # profile index along an edge, 0..N-1
    near: npt.NDArray[np.intp]  # (3, 1, 1) row offsets read for the slope


_GRIDS: dict[tuple[float, float, int], _Grid2] = {}


def _grid(s: LeanSettings) -> _Grid2:
    key = (s.profile_half_px, s.profile_step_px, s.samples_per_edge)
    g = _GRIDS.get(key)
    if g is None:
        h, r, n = s.profile_step_px, s.profile_half_px, s.samples_per_edge
        m = round(r / h)
        ks = np.arange(-m, m + 1) * h
        k = len(ks)
        # "lean"'s windows: inside [-2.4, -1.4], the outside's darkest sample in [0.5, 2.4]
        in_rows = slice(int(ks.searchsorted(-2.4, "left")), int(ks.searchsorted(-1.4, "right")))
        out_rows = slice(int(ks.searchsorted(0.5, "left")), int(ks.searchsorted(2.4, "right")))
        mid = 0.5 * (ks[:-1] + ks[1:])
        prio = (2.0 * r - np.abs(mid)).astype(np.float32).reshape(1, k - 1, 1)
        edge = np.arange(4)[:, None]
        cols = np.arange(n)[None, :]
        g = _Grid2(k, float(ks[0]), h, in_rows, out_rows, prio,
                   np.float32(1.0 / (in_rows.stop - in_rows.start)),
                   edge * k * n + cols, edge * (k - 1) * n + cols,
                   np.arange(n, dtype=np.float64), np.array([-2, 0, 2]).reshape(3, 1, 1) * n)
        _GRIDS[key] = g
    return g


def refine_quad_lean2(gray: npt.NDArray[np.uint8], corners: FloatArray, s: LeanSettings,
                      scale: list[float] | None = None, reads: list[float] | None = None
                      ) -> tuple[FloatArray, list[EdgeFit], list[float]] | None:
    """Sub-pixel corners (4, 2) of the bright convex quadrilateral whose coarse corners
    (clockwise on screen, within ~2 px) are ``corners``, the four edges' fits and their blur
    scales (the profile stretch each edge's blur asks for, for the next frame); ``None`` when
    an edge is too short or has too few measured profiles (under ``max(4, 30 %)``). The same
    contract and edge frames as :func:`~companion.perception.edges_lean.refine_quad_lean`.

    ``scale``: the previous frame's blur scales when ``corners`` are its refined corners
    (tracking): the first pass is then already stretched and centred on lines measured at
    that stretch, and ends the passes when it moves no line end farther than
    ``_ACCEPT_PX``.

    ``reads``: ``[x_min, y_min, x_max, y_max]`` (px), widened to hold every sample position
    the passes read (:func:`_widen_reads`): the caller learns which pixels the result depends
    on (what the flight log must keep for an exact replay)."""
    g = _grid(s)
    frames = edge_frames(corners, s)
    if frames is None:
        return None
    u = g.j[None, :] * np.array([f[4] for f in frames])[:, None]  # (4, N) along each edge
    tracked = scale is not None
    if reads is not None:
        _widen_reads(reads, frames, scale if scale is not None else _ONES, g, s)
    e, ok, width = _pass(gray, frames, scale if scale is not None else _ONES, g, s, True)
    lines = _fit_final(u, e, ok) if tracked else _fit(u, e, ok, False)
    if lines is None:
        return None
    # the edges' blur sets how far apart the next passes read the plateaus
    scale = [min(max((0.5 + 0.9 * max(w, 1.0)) / 1.4, 1.0), 3.0) for w in width]
    if not (tracked and _converged(lines, u, _ACCEPT_PX)):
        for it in range(1, s.passes):
            frames = [_on_line(f, ln) for f, ln in zip(frames, lines, strict=True)]
            if reads is not None:
                _widen_reads(reads, frames, scale, g, s)
            e, ok, _ = _pass(gray, frames, scale, g, s, False)
            # tracked, every later pass's lines get the outlier pass (the next pass is centred
            # on the lines its outliers did not pull) and converged passes end early; from a
            # blob's coarse corners "lean"'s passes (the outlier pass on the last one only)
            last = it == s.passes - 1
            fitted = _fit_final(u, e, ok) if tracked or last else _fit(u, e, ok, False)
            if fitted is None:
                return None
            lines = fitted
            if tracked and _converged(lines, u, _CONVERGED_PX):
                break
    fits = [_edge_fit(f, ln) for f, ln in zip(frames, lines, strict=True)]
    out = _intersections(fits)
    return None if out is None else (out, fits, scale)


def _widen_reads(reads: list[float], frames: list[_Frame], scale: list[float], g: _Grid2,
                 s: LeanSettings) -> None:
    """Widen ``reads`` (``[x_min, y_min, x_max, y_max]``) to the sample positions of one
    :func:`_pass`: each edge's samples are an affine grid ``p0 + a t + b n`` (``a`` from 0 to
    the last profile, ``b`` across the profile's offsets ``k0 .. -k0``, symmetric), so per axis
    its extremes are ``p0 +- |along| +- |across|`` at the grid's corners. The bilinear
    interpolation reads the pixels around a position (:func:`read_box_px` adds that margin)."""
    last, half = s.samples_per_edge - 1, -g.k0
    lo_x, lo_y, hi_x, hi_y = [reads[0]], [reads[1]], [reads[2]], [reads[3]]
    for (x0, y0, tx, ty, sp), sc in zip(frames, scale, strict=True):
        a, b = 0.5 * sp * last, half * sc  # the normal is (ty, -tx) * sc
        cx, cy = x0 + a * tx, y0 + a * ty  # the grid's centre
        rx, ry = abs(a * tx) + abs(b * ty), abs(a * ty) + abs(b * tx)
        lo_x.append(cx - rx)
        hi_x.append(cx + rx)
        lo_y.append(cy - ry)
        hi_y.append(cy + ry)
    reads[:] = (min(lo_x), min(lo_y), max(hi_x), max(hi_y))


def read_box_px(reads: list[float], w: int, h: int) -> tuple[int, int, int, int] | None:
    """The pixels ``(x0, y0, x1, y1)`` (end exclusive, within a ``w`` x ``h`` image) that
    sample positions within ``reads`` (:func:`refine_quad_lean2`) can read; None when no
    position was recorded. ``cv2.warpAffine``'s bilinear interpolation reads the pixel at and
    after each position, rounded to 1/32 px: a pixel of margin each side is added for that
    rounding; positions off the image read its border pixels (``BORDER_REPLICATE``), which
    the clipped box holds."""
    x_min, y_min, x_max, y_max = reads
    if not (x_min <= x_max and y_min <= y_max):
        return None
    x0, y0 = max(math.floor(x_min) - 2, 0), max(math.floor(y_min) - 2, 0)
    x1, y1 = min(math.floor(x_max) + 4, w), min(math.floor(y_max) + 4, h)
    if x0 >= x1 or y0 >= y1:  # wholly off the image: it read a border pixel
        return None
    return x0, y0, x1, y1


def _converged(new_lines: list[_Line], u: FloatArray, eps_px: float) -> bool:
    """Whether every edge's new line lies within ``eps_px`` of the line its pass was
    centred on (the ``v = 0`` axis of the pass's frames) at the edge's first and last profile:
    the next pass, centred on the new line, would then read where this one did."""
    ends = u[:, -1].tolist()
    for (cu, cv, cos, sin, *_), end in zip(new_lines, ends, strict=True):
        if abs(cos) < 0.5:
            return False
        slope = sin / cos
        if abs(cv - cu * slope) > eps_px or abs(cv + (end - cu) * slope) > eps_px:
            return False
    return True


def _fit_final(u: FloatArray, v: FloatArray, ok: npt.NDArray[np.bool_]) -> list[_Line] | None:
    """``_fit(u, v, ok, True)`` of :mod:`~companion.perception.edges_lean` (the lines with
    one outlier pass, their RMS distance and the fraction of profiles kept; ``None`` when an
    edge has fewer than max(4, 30 %) measured points) with the per-edge bookkeeping (counts,
    medians, which edges to refit) on plain floats: four rows, numpy's per-call cost."""
    n = v.shape[1]
    cnt = ok.sum(axis=1).tolist()
    if min(cnt) < max(4, 0.3 * n):
        return None
    w = ok.astype(np.float64)
    line = _tls2(u, v, w)
    res = _line_distances(u, v, line)
    # the outlier bound per edge from the median distance of its measured points
    srt = np.sort(np.where(ok, res, np.inf), axis=1).tolist()
    bound = [max(3.0 * (_median(row, c) * 1.4826 + 0.05), 0.3) for row, c in zip(srt, cnt,
                                                                               strict=True)]
    keep = ok & (res <= np.array(bound)[:, None])
    n_keep = keep.sum(axis=1).tolist()
    refit = [4 <= k < c for k, c in zip(n_keep, cnt, strict=True)]
    if any(refit):
        keep = np.where(np.array(refit)[:, None], keep, ok)
        w = keep.astype(np.float64)
        line = _tls2(u, v, w)
        res = _line_distances(u, v, line)
    used = [k if r else c for k, c, r in zip(n_keep, cnt, refit, strict=True)]
    sq = (w * res * res).sum(axis=1).tolist()
    return [(*line[i], math.sqrt(sq[i] / used[i]), n_keep[i] / n) for i in range(4)]


def _tls2(u: FloatArray, v: FloatArray, w: FloatArray
          ) -> list[tuple[float, float, float, float]]:
    """:func:`~companion.perception.edges_lean._tls` (weighted total-least-squares lines
    through (u, v) (4, N): per edge the centroid and unit direction) with its six weighted
    moments summed by one matrix-vector product."""
    wu, wv = w * u, w * v
    mom = (np.concatenate((w, wu, wv, wu * u, wu * v, wv * v)) @ _ones(u.shape[1]))
    line = []
    for sw, su, sv, suu, suv, svv in zip(*mom.reshape(6, 4).tolist(), strict=True):
        cu, cv = su / sw, sv / sw
        sxx, sxy, syy = suu - su * cu, suv - su * cv, svv - sv * cv
        half = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
        line.append((cu, cv, math.cos(half), math.sin(half)))
    return line


_ONES_N: dict[int, FloatArray] = {}


def _ones(n: int) -> FloatArray:
    o = _ONES_N.get(n)
    if o is None:
        o = _ONES_N[n] = np.ones(n)
    return o


def _median(row: list[float], count: int) -> float:
    """The median of a sorted row's first ``count`` entries (1.0 without any)."""
    if count <= 0:
        return 1.0
    h = count // 2
    return row[h] if count % 2 == 1 else 0.5 * (row[h - 1] + row[h])


def _line_distances(u: FloatArray, v: FloatArray, line: list[tuple[float, float, float, float]]
                    ) -> FloatArray:
    """Every point's distance (4, N) from its edge's line."""
    cs = np.array([(cos, -sin, cu * sin - cv * cos) for cu, cv, cos, sin in line])
    res: FloatArray = np.abs(v * cs[:, 0:1] + u * cs[:, 1:2] + cs[:, 2:3])
    return res


_ONES = [1.0, 1.0, 1.0, 1.0]


def _pass(gray: npt.NDArray[np.uint8], frames: list[_Frame], scale: list[float], g: _Grid2,
          s: LeanSettings, want_width: bool
          ) -> tuple[FloatArray, npt.NDArray[np.bool_], list[float]]:
    """One set of profiles, edge ``i`` sampled every ``step * scale[i]`` px (one
    ``cv2.warpAffine`` per edge into a (k, N) slab: profile ``j`` is column ``j``). Per
    profile: the crossing's offset ``e`` (px along the normal) and whether it was measured;
    per edge (``want_width``): the median transition width (px; 1.0 without any)."""
    n, k, h, k0 = s.samples_per_edge, g.k, g.step, g.k0
    raw = np.empty((4, k, n), dtype=np.uint8)
    for i, ((x0, y0, tx, ty, sp), sc) in enumerate(zip(frames, scale, strict=True)):
        nx, ny = ty * sc, -tx * sc  # outward normal, scaled
        m = np.array(((sp * tx, h * nx, x0 + k0 * nx), (sp * ty, h * ny, y0 + k0 * ny)))
        cv2.warpAffine(gray, m, (n, k), dst=raw[i],
                       flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                       borderMode=cv2.BORDER_REPLICATE)
    prof = raw.astype(np.float32)
    inside = np.add.reduce(prof[:, g.in_rows], axis=1) * g.in_norm  # (4, N)
    outside = np.minimum.reduce(prof[:, g.out_rows], axis=1)
    level = 0.5 * (inside + outside)
    # a falling crossing between rows r and r + 1; the one nearest the centre
    above = prof >= level[:, None, :]
    idx = ((above[:, :-1] > above[:, 1:]) * g.prio).argmax(axis=1)  # (4, N)
    at = idx * n + g.base
    flat = prof.reshape(-1)
    v0, v1 = flat[at], flat[at + n]
    frac = (v0 - level) / np.maximum(v0 - v1, np.float32(1e-6))
    contrast = inside - outside
    # a crossing at idx (argmax's 0 without any is none: the test on its two samples)
    ok = (v0 >= level) & (v1 < level) & (contrast >= s.min_contrast)
    spacing = np.array(scale)[:, None] * h  # (4, 1) px between samples
    e: FloatArray = (idx + (frac + k0 / h)) * spacing
    if not want_width:
        return e, ok, []
    # transition width (px): contrast over the steepest slope at the crossing's rows
    diffs = (prof[:, :-1] - prof[:, 1:]).reshape(-1)
    near = np.minimum(np.maximum(idx * n + g.near, 0), (k - 2) * n) + g.base1  # (3, 4, N)
    drop = np.maximum(np.maximum.reduce(diffs[near], axis=0), 1e-6)  # grey per sample
    width = np.sort(np.where(ok, contrast * spacing / drop, np.inf), axis=1).tolist()
    cnt = ok.sum(axis=1).tolist()
    return e, ok, [_median(row, c) for row, c in zip(width, cnt, strict=True)]


__all__ = ["read_box_px", "refine_quad_lean2"]
