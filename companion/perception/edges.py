"""Sub-pixel edges and corners of a convex quadrilateral by fitting lines to its edges.

Each edge is sampled across its normal; on every profile the edge lies where the intensity
crosses the midpoint between the inside and outside plateaus (for an area-sampled step this
is the edge itself, for any symmetric blur too); a line is fitted to those points (total least
squares, one outlier pass) and adjacent lines are intersected. Fitting whole edges averages
pixel quantisation, noise and texture; the corners' own pixels are never used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from companion.perception._types import FloatArray, PerceptionError


@dataclass(frozen=True)
class EdgeSettings:
    """``profile_half_px``: half length of the profile across an edge for sharp edges (grown
    automatically for blurred ones); must cover the coarse corners' error. ``min_contrast``:
    inside minus outside level (grey levels) for a profile to count. ``outside_level``:
    ``"min"`` reads the outside as the darkest value just beyond the edge, so a box side
    showing as a 1-2 px dark band next to the top sets the level (the band is what the edge
    pixel mixes with); ``"mean"`` averages a 1 px window beyond the transition (unbiased on a
    plain background, biased by thin bands: worst corner error 0.44 px vs 0.28 px with
    "min" over 200 rendered poses)."""

    profile_half_px: float = 4.0
    profile_step_px: float = 0.25
    min_contrast: float = 40.0
    max_samples_per_edge: int = 120
    outside_level: str = "min"

    def __post_init__(self) -> None:
        if not self.profile_half_px >= 2:
            raise PerceptionError("profile_half_px: must be >= 2")
        if not 0 < self.profile_step_px <= 0.5:
            raise PerceptionError("profile_step_px: must be in (0, 0.5]")
        if self.outside_level not in ("min", "mean"):
            raise PerceptionError("outside_level: must be 'min' or 'mean'")
        if self.max_samples_per_edge < 4:
            raise PerceptionError("max_samples_per_edge: must be >= 4")


@dataclass(frozen=True)
class EdgeFit:
    """A fitted edge line: a point on it, its unit direction (col, row), the RMS residual of
    the edge points (px) and the fraction of profiles that gave a usable edge point."""

    point: FloatArray
    direction: FloatArray
    rms_px: float
    valid_fraction: float


def refine_quad(
    gray: npt.NDArray[np.uint8],
    corners: FloatArray,
    settings: EdgeSettings,
    *,
    bright_inside: bool = True,
) -> tuple[FloatArray, list[EdgeFit]] | None:
    """Sub-pixel corners of a convex quadrilateral from its four fitted edges.

    ``corners``: (4, 2) coarse corners (within ~2 px), clockwise on screen. Each edge is
    fitted independently (as :func:`fit_edge` does) and adjacent lines are intersected. ``None``
    if an edge cannot be measured. ``bright_inside``: the polygon is brighter than its
    surroundings (else darker, e.g. a marker's black border on white).
    """
    if not bright_inside:
        gray = np.asarray(cv2.bitwise_not(gray), dtype=np.uint8)
    fits = _fit_edges(gray, [(corners[i], corners[(i + 1) % 4]) for i in range(4)], settings)
    if fits is None:
        return None
    out = np.empty((4, 2))
    for i in range(4):
        p = _intersect(fits[(i - 1) % 4], fits[i])
        if p is None:
            return None
        out[i] = p
    return out, fits


def fit_edge(
    gray: npt.NDArray[np.uint8], a: FloatArray, b: FloatArray, settings: EdgeSettings
) -> EdgeFit | None:
    """Sub-pixel line through the edge from ``a`` to ``b`` (clockwise polygon).

    Sharp edges are measured with a short profile; if the edge turns out blurred (median
    transition wider than 1.6 px) it is measured again with a profile long enough to
    reach the plateaus on both sides.
    """
    fits = _fit_edges(gray, [(a, b)], settings)
    return None if fits is None else fits[0]


def _fit_edges(
    gray: npt.NDArray[np.uint8], segs: list[tuple[FloatArray, FloatArray]], settings: EdgeSettings
) -> list[EdgeFit] | None:
    """Fitted lines of the edges ``segs`` (``None`` if any cannot be measured). All edges'
    profiles are taken in one pass, the blurred ones re-measured in a second (rows are
    independent: the same result as one edge at a time, without numpy's per-call overhead
    once per edge)."""
    r = settings.profile_half_px
    got = _edge_points_batch(gray, segs, [r] * len(segs), settings)
    blurred = [(i, g[1]) for i, g in enumerate(got) if g is not None and g[1] > _BLURRED_PX]
    if blurred:
        again = _edge_points_batch(gray, [segs[i] for i, _ in blurred],
                                   [_blur_half_px(r, w, settings) for _, w in blurred], settings)
        for (i, _), g in zip(blurred, again, strict=True):
            got[i] = g
    if any(g is None for g in got):
        return None
    return [_fit_points(*g) for g in got if g is not None]


_BLURRED_PX = 1.6  # median transition width beyond which an edge is re-measured


def _blur_half_px(r: float, width: float, settings: EdgeSettings) -> float:
    """Profile half length for a blurred edge: long enough to reach both plateaus, a whole
    number of profile steps (so its samples are a subset of a longer profile's)."""
    step = settings.profile_step_px
    return math.ceil(min(max(r, 1.0 + 1.8 * width), 3.0 * r) / step - 1e-9) * step


def _fit_points(pts: FloatArray, width: float, n_samples: int) -> EdgeFit:
    """Total-least-squares line through the edge points, with one outlier pass (texture or a
    side face can fool a few profiles)."""
    c, d, cos, sin = _tls(pts)
    res = np.abs(d @ np.array([-sin, cos]))  # distances from the line (the centred points')
    mad = _median(res) * 1.4826 + 0.05
    keep = res <= max(3.0 * mad, 0.3)
    n_keep = int(np.count_nonzero(keep))
    if n_keep >= 4 and n_keep < keep.shape[0]:
        c, d, cos, sin = _tls(pts[keep])
        res = np.abs(d @ np.array([-sin, cos]))
    rms = math.sqrt(float(np.dot(res, res)) / res.shape[0])
    return EdgeFit(c, np.array([cos, sin]), rms, n_keep / n_samples)


def _edge_points_batch(
    gray: npt.NDArray[np.uint8], segs: list[tuple[FloatArray, FloatArray]], rs: list[float],
    settings: EdgeSettings,
) -> list[tuple[FloatArray, float, int] | None]:
    """Edge crossings on profiles across each edge a -> b, edge ``i`` with profile half length
    ``rs[i]`` (a whole number of profile steps). Per edge: (points (M, 2), median transition
    width px, samples tried), or ``None``.

    On each profile the edge is where the intensity crosses the midpoint between the inside
    and outside plateaus; the plateaus are read just beyond the transition, relative to the
    current crossing, and the crossing is iterated (3 times), so a coarse start 1-2 px off
    does not bias the levels. The edges' profiles are stacked as rows of one array sampled
    over the longest half length; every operation is row-wise and confined to the row's own
    profile, and the rows are split again at the end."""
    rows = _profile_rows(segs, rs, settings)
    if rows is None:
        return [None] * len(segs)
    lay = rows.lay
    # the samples land in float64 rows padded by one column (+inf) so that every range end
    # below is a valid index of the flattened array: no separate float copy of the profiles
    padded = np.empty((lay.n_rows, lay.n_k + 1))
    padded[:, lay.n_k] = np.inf
    padded[:, :lay.n_k] = cv2.remap(gray, rows.map_x, rows.map_y, cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_REPLICATE)
    e, width, ok = _crossings(padded, lay, settings)
    return _edge_points(rows, e, width, ok, len(segs))


@dataclass(frozen=True)
class _Rows:
    """The profiles of one batch: which edges (``used``, in row order) with how many profiles
    each, the row layout, each row's base point on its edge, the edges' unit directions and the
    sampling maps (float32, as ``cv2.remap`` takes them)."""

    used: list[int]
    counts: list[int]
    lay: _Layout
    base: FloatArray
    t_all: FloatArray
    map_x: npt.NDArray[np.float32]
    map_y: npt.NDArray[np.float32]


def _profile_rows(segs: list[tuple[FloatArray, FloatArray]], rs: list[float],
                  s: EdgeSettings) -> _Rows | None:
    """Where the profiles of the edges ``segs`` (half lengths ``rs``) are sampled, or ``None``
    if no edge is long enough. Per-edge scalars in plain Python; the rows of all edges are then
    built by whole-array operations (the same arithmetic per element as one edge at a time:
    bit-identical)."""
    n_segs = len(segs)
    a_all = np.array([a for a, _ in segs], dtype=np.float64).reshape(n_segs, 2)
    d_all = np.array([b for _, b in segs], dtype=np.float64).reshape(n_segs, 2) - a_all
    lengths = np.hypot(d_all[:, 0], d_all[:, 1]).tolist()
    used: list[int] = []
    counts: list[int] = []
    spacings: list[float] = []
    for i, r in enumerate(rs):
        margin = 1.5 * r + 1.0
        length = lengths[i]
        if length < 2 * margin + 4:
            continue
        n_samples = int(min(s.max_samples_per_edge, max(4, math.floor(length - 2 * margin))))
        used.append(i)
        counts.append(n_samples)
        spacings.append((length - 2 * margin) / (n_samples - 1))
    if not used:
        return None
    lay = _layout(tuple(used), tuple(counts), tuple(rs), s.profile_step_px)
    along = lay.in_row * np.array(spacings)[lay.pos_of_row] + lay.margin_row
    t_all = d_all / np.array(lengths)[:, None]
    t_rows = t_all[lay.seg_of_row]
    base = a_all[lay.seg_of_row] + along[:, None] * t_rows
    # outward normal (t_y, -t_x) for a clockwise-on-screen polygon; the maps are computed in
    # float64 and rounded once to float32 on the way out (as astype would)
    map_x = np.empty((lay.n_rows, lay.n_k), dtype=np.float32)
    map_y = np.empty((lay.n_rows, lay.n_k), dtype=np.float32)
    np.add(base[:, :1], lay.ks[None, :] * t_rows[:, 1:], out=map_x)
    np.add(base[:, 1:], lay.ks[None, :] * -t_rows[:, :1], out=map_y)
    return _Rows(used, counts, lay, base, t_all, map_x, map_y)


def _crossings(padded: FloatArray, lay: _Layout, s: EdgeSettings
               ) -> tuple[FloatArray, FloatArray, npt.NDArray[np.bool_]]:
    """Per row: the edge's offset along the profile, its transition width (px) and whether it
    was measured. ``padded``: the profiles (one per row, ``lay.n_k`` samples) and a +inf
    column."""
    step = s.profile_step_px
    ks, n_rows, n_k = lay.ks, lay.n_rows, lay.n_k
    mid, first, last_1, not_own = lay.mid, lay.first, lay.last_1, lay.not_own_seg
    row_start, dist_start = lay.row_start, lay.dist_start
    in_lo_bound, out_hi_bound, width_hi = lay.in_lo_bound, lay.out_hi_bound, lay.width_hi
    prof = padded[:, :n_k]
    flat = padded.ravel()
    # Row-wise look-ups below index the flattened arrays (one 1-D take instead of a 2-D fancy
    # index). csum: running sums, one leading zero per row.
    csum = np.zeros((n_rows, n_k + 1))
    np.cumsum(prof, axis=1, out=csum[:, 1:])
    csum_f = csum.ravel()
    bounds = np.empty(2 * n_rows, dtype=np.intp)
    e = np.zeros(n_rows)
    width = np.ones(n_rows)
    ok = np.zeros(n_rows, dtype=bool)
    dist = np.empty((n_rows, n_k - 1))
    mode = s.outside_level
    for it in range(3):
        # plateau windows (index ranges of the uniform k grid) just beyond the transition; the
        # first pass starts every row at e = 0, width 1: its windows are the layout's
        i0, i1, j0, j1 = (lay.start_windows[mode] if it == 0 else
                          _windows(ks, in_lo_bound, out_hi_bound, e, width, mode))
        # window means as differences of running sums
        inside = (csum_f[row_start + i1] - csum_f[row_start + i0]) / np.maximum(i1 - i0, 1)
        if mode == "min":
            # darkest sample in [e + 0.5, out_lo + 1]: a range minimum per row (0 if empty)
            bounds[0::2] = row_start + j0
            bounds[1::2] = row_start + j1
            outside = np.minimum.reduceat(flat, bounds)[0::2]
            outside = np.where(j1 > j0, outside, 0.0)
        else:  # the mean of [out_lo, out_lo + 1]
            outside = (csum_f[row_start + j1] - csum_f[row_start + j0]) / np.maximum(j1 - j0, 1)
        contrast = inside - outside
        level = 0.5 * (inside + outside)
        above = prof >= level[:, None]
        # no crossing where a sample is not above and the next is, or is, or outside the row's
        # own profile (bools: ~(a & ~b) is a <= b); such places are at +inf distance
        no_cross = above[:, :-1] <= above[:, 1:]
        if not_own is not None:
            no_cross |= not_own
        np.subtract(mid[None, :], e[:, None], out=dist)
        np.abs(dist, out=dist)
        np.copyto(dist, np.inf, where=no_cross)
        idx = dist.argmin(axis=1)
        ok = np.isfinite(dist.ravel()[dist_start + idx]) & (contrast >= s.min_contrast)
        at = row_start + idx
        v0, v1 = flat[at], flat[at + 1]
        dv = np.where(v0 != v1, v0 - v1, 1.0)
        frac = np.minimum(np.maximum((v0 - level) / dv, 0.0), 1.0)
        e = np.where(ok, ks[idx] + frac * step, e)
        # transition width (px): contrast / steepest slope near the crossing
        lo = row_start + np.minimum(np.maximum(idx - 2, first), last_1)
        hi = row_start + np.minimum(np.maximum(idx + 2, first), last_1)
        slopes = np.maximum(np.maximum(flat[lo] - flat[lo + 1], v0 - v1), flat[hi] - flat[hi + 1])
        slope = np.maximum(slopes / step, 1e-6)
        width = np.where(ok, np.minimum(np.maximum(contrast / slope, 0.5), width_hi), width)
    return e, width, ok


_Windows = tuple[npt.NDArray[np.intp], npt.NDArray[np.intp], npt.NDArray[np.intp],
                 npt.NDArray[np.intp]]


def _windows(ks: FloatArray, in_lo_bound: FloatArray, out_hi_bound: FloatArray, e: FloatArray,
             width: FloatArray, mode: str) -> _Windows:
    """Index ranges ``[i0, i1)`` of the inside plateau and ``[j0, j1)`` of the outside one on
    the k grid, per row, for edges at ``e`` of transition width ``width``: the inside window
    ``[in_hi - 1, in_hi]``, the outside one ``[e + 0.5, out_lo + 1]`` (``"min"``) or
    ``[out_lo, out_lo + 1]`` (``"mean"``), kept inside the row's profile.

    np.clip(x, lo, hi) is written np.minimum(np.maximum(x, lo), hi) (the same values; without
    its Python-level wrapper, which cost more than the arithmetic on these arrays)."""
    near = 0.5 + 0.9 * np.maximum(width, 1.0)
    in_hi = np.minimum(np.maximum(e - near, in_lo_bound), 0.0)
    out_lo = np.minimum(np.maximum(e + near, 0.0), out_hi_bound)
    i0 = ks.searchsorted(in_hi - 1.0, side="left")
    i1 = ks.searchsorted(in_hi, side="right")
    if mode == "min":
        j0 = ks.searchsorted(e + 0.5, side="left")
    else:
        j0 = ks.searchsorted(out_lo, side="left")
    j1 = ks.searchsorted(out_lo + 1.0, side="right")
    return i0, i1, j0, j1


def _edge_points(rows: _Rows, e: FloatArray, width: FloatArray, ok: npt.NDArray[np.bool_],
                 n_segs: int) -> list[tuple[FloatArray, float, int] | None]:
    """The batch's rows split back into edges: per edge its points, median width and profiles
    tried, or ``None`` when fewer than ``max(4, 30 %)`` of its profiles measured the edge."""
    out: list[tuple[FloatArray, float, int] | None] = [None] * n_segs
    row0 = 0
    for i, n_samples in zip(rows.used, rows.counts, strict=True):
        sl = slice(row0, row0 + n_samples)
        row0 += n_samples
        ok_e = ok[sl]
        if ok_e.sum() < max(4, 0.3 * n_samples):
            continue
        normal_out = np.array([rows.t_all[i, 1], -rows.t_all[i, 0]])
        pts = rows.base[sl][ok_e] + e[sl][ok_e, None] * normal_out[None, :]
        out[i] = (pts, _median(width[sl][ok_e]), n_samples)
    return out


@dataclass(frozen=True)
class _Layout:
    """The rows of a batch of profiles that depend only on which edges are measured, how many
    profiles each and their half lengths (not on the image or the edges' positions): the same
    for nearly every frame, so built once (read-only arrays; the same values as built anew)."""

    ks: FloatArray  # profile offsets over the longest half length
    n_k: int
    seg_of_row: npt.NDArray[np.intp]
    n_rows: int
    in_row: npt.NDArray[np.intp]  # the row's index among its edge's rows
    pos_of_row: npt.NDArray[np.intp]  # the row's edge's position in ``used``
    margin_row: FloatArray  # the row's edge's end margin (px): 1.5 r + 1
    rr: FloatArray  # the row's half length
    mid: FloatArray
    first: npt.NDArray[np.intp]  # index of k = -r
    last_1: npt.NDArray[np.intp]  # index of k = +r, minus one
    not_own_seg: npt.NDArray[np.bool_] | None  # a segment not in the row's own profile
    # (an end beyond its half length); None when every row spans the whole array
    row_start: npt.NDArray[np.intp]  # row offsets in the flat arrays (n_k + 1 wide)
    dist_start: npt.NDArray[np.intp]
    in_lo_bound: FloatArray
    out_hi_bound: FloatArray
    width_hi: FloatArray
    start_windows: dict[str, _Windows]  # the first pass's windows, per outside_level


_LAYOUTS: dict[tuple[tuple[int, ...], tuple[int, ...], tuple[float, ...], float], _Layout] = {}


def _layout(used: tuple[int, ...], counts: tuple[int, ...], rs: tuple[float, ...],
            step: float) -> _Layout:
    key = (used, counts, rs, step)
    lay = _LAYOUTS.get(key)
    if lay is not None:
        return lay
    r_max = max(rs)
    ks = np.arange(-r_max, r_max + 1e-9, step)
    n_k = len(ks)
    seg_of_row = np.repeat(np.array(used), counts)
    first_row = np.repeat(np.cumsum([0, *counts[:-1]]), counts)
    n_rows = seg_of_row.shape[0]
    rows = np.arange(n_rows)
    rr = np.array(rs)[seg_of_row]
    pos_of_row = np.repeat(np.arange(len(used)), counts)
    margin_row = np.repeat([1.5 * rs[i] + 1.0 for i in used], counts)
    mid = (ks[:-1] + ks[1:]) / 2
    # a row's own profile: |k| <= r (the same samples as a profile of half length r)
    first = np.rint((r_max - rr) / step).astype(np.intp)
    not_own = ~(np.abs(mid)[None, :] < rr[:, None])
    in_lo_bound, out_hi_bound = 1.0 - rr, rr - 1.0
    e0, width0 = np.zeros(n_rows), np.ones(n_rows)
    start = {mode: _windows(ks, in_lo_bound, out_hi_bound, e0, width0, mode)
             for mode in ("min", "mean")}
    lay = _Layout(
        ks=ks, n_k=n_k, seg_of_row=seg_of_row, n_rows=n_rows, in_row=rows - first_row,
        pos_of_row=pos_of_row, margin_row=margin_row, rr=rr,
        mid=mid, first=first, last_1=n_k - 2 - first,
        not_own_seg=not_own if not_own.any() else None,
        row_start=rows * (n_k + 1), dist_start=rows * (n_k - 1),
        in_lo_bound=in_lo_bound, out_hi_bound=out_hi_bound, width_hi=2.0 * rr,
        start_windows=start,
    )
    for a in [*vars(lay).values(), *(w for ws in start.values() for w in ws)]:
        if isinstance(a, np.ndarray):
            a.setflags(write=False)
    if len(_LAYOUTS) >= 256:  # edges shorter than the sample cap vary: keep the cache small
        _LAYOUTS.clear()
    _LAYOUTS[key] = lay
    return lay


def _median(x: FloatArray) -> float:
    """``np.median`` of a small 1-D array, without its overhead (same value)."""
    xs = np.sort(x)
    n = xs.shape[0]
    h = n // 2
    return float(xs[h]) if n % 2 else float(0.5 * (xs[h - 1] + xs[h]))


def _tls(points: FloatArray) -> tuple[FloatArray, FloatArray, float, float]:
    """Total-least-squares line: (centroid, the centred points, the unit direction's cos and
    sin).

    The direction is the principal axis of the points' 2 x 2 scatter matrix, in closed form
    (the angle ``atan2(2 sxy, sxx - syy) / 2``): the same line as the first right singular vector
    of the centred points (an SVD per edge cost more than the rest of the fit; the two differ by
    rounding, ~1e-13 px at the corners, and the direction's sign, which nothing uses)."""
    c = points.sum(axis=0) / points.shape[0]  # np.mean's arithmetic, without its wrapper
    d = points - c
    (sxx, sxy), (_, syy) = (d.T @ d).tolist()
    half = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
    return c, d, math.cos(half), math.sin(half)


def _intersect(e1: EdgeFit, e2: EdgeFit) -> FloatArray | None:
    """Intersection of two fitted lines (Cramer's rule on the 2 x 2 system
    ``p1 + t1 d1 = p2 + t2 d2``), ``None`` if they are (nearly) parallel."""
    d1x, d1y = e1.direction.tolist()
    d2x, d2y = e2.direction.tolist()
    det = d2x * d1y - d1x * d2y
    if abs(det) < 1e-6:
        return None
    rx, ry = (e2.point - e1.point).tolist()
    t1 = (d2x * ry - rx * d2y) / det
    p1x, p1y = e1.point.tolist()
    return np.array([p1x + t1 * d1x, p1y + t1 * d1y])


__all__ = ["EdgeFit", "EdgeSettings", "fit_edge", "refine_quad"]
