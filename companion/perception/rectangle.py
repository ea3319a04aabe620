"""Detector for the emulator's pattern: a bright rectangle (the AGV's top) on a darker scene.

Scene model (what the emulator renders, docs/reference/wire.md): the AGV top is the brightest region
(235 at the nominal exposure), the ground is textured (about 40..150) and the box's sides are
dark (<= 60); a camera's exposure scales all of them (and saturates at 255).

Pipeline: per-frame grey threshold (adaptive: between the frame's ground level and its
brightest region, see :func:`grey_levels`; or a fixed level) -> external contours -> convex
hull -> polygon approximation to 4 vertices (coarse corners, about 1 px) -> plausibility of
the coarse quad -> sub-pixel refinement by fitting lines to the four edges
(``edges = "lean2"``: :mod:`companion.perception.edges_lean2`, the default; ``"lean"``:
:mod:`companion.perception.edges_lean`; ``"profiles"``: :mod:`companion.perception.edges`,
the detector of the logs recorded before 2026-11-28) -> plausibility of the refined quad.
With ``"lean"``/``"lean2"`` and the previous frame's corners (``hint``) the corners are
refined from those and the blob search is skipped (``_track``; the search runs when that
fails); ``"lean2"`` also starts from the previous frame's blur and motion. Measured on rendered
scenes (tests/companion/test_perception.py, bench/perception.py): worst corner error 0.28 px
over 458 random poses (1.5-5 m, tilt <= 0.3 rad), median 0.07 px; about 1.4 ms per
1000 x 1000 frame (2026-11-23, fixed threshold). The adaptive threshold holds the target
over exposure gains 0.5..1.5 (tests/companion/test_perception_exposure.py).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from companion.core.geometry import rectangle_corners_m
from companion.perception._types import (
    Detection,
    DetectionReport,
    FloatArray,
    PerceptionError,
    QuadDetectorBase,
    Rejection,
    to_gray,
)
from companion.perception.edges import EdgeFit, EdgeSettings, refine_quad
from companion.perception.edges_kernel import lean2_refiner
from companion.perception.edges_lean import LeanSettings, refine_quad_lean
from companion.perception.edges_lean2 import read_box_px
from companion.perception.plausibility import (
    QuadLimits,
    approx_quad,
    box_touches_border,
    check_quad,
    order_target_corners,
    signed_area,
    touches_border,
)

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RectangleSettings:
    """Tuning of :class:`RectangleDetector` (pixels unless named otherwise).

    ``threshold``: a fixed grey level separating the top from everything else, or ``None``
    (the default) for a level chosen per frame: ``G + level_fraction * (T - G)`` with ``G`` the
    frame's median (the ground: the top covers well under half of the searched image) and ``T``
    the bright region's level (the median of the pixels above a first threshold placed the same
    way with the level that ``bright_count_px`` pixels reach, so sensor noise on the top does
    not raise it). A frame whose bright region does not stand out is "no bright region":
    ``T - G`` must reach ``min_separation * G`` (the top at least 1.5 x the ground's median: at
    the emulator's nominal exposure it is 2.5 x; from gain ~1.8 on the ground saturates with
    the top) and ``min_level_contrast`` grey levels, and the valley around the
    threshold must be empty enough (pixels within ``valley_band`` of ``T - G`` of the
    threshold, at most ``max_valley_ratio`` times the pixels above it): a textured ground
    alone has a continuous histogram there, a bright top on it a gap. The edges' contrast
    bound then scales with the frame: ``min_contrast * (T - G) / 140`` (140: the top above
    the ground at the emulator's nominal exposure), at least ``min_level_contrast / 2``.
    ``presmooth_px``: Gaussian sigma applied before thresholding (coarse stage only).
    ``profile_half_px``: half length of the profile sampled across each edge; must cover the
    edge blur plus the coarse corners' error. ``min_contrast``: inside minus outside level for
    an edge sample to count. ``compiled``: "lean2" by :mod:`~companion.perception.edges_kernel`
    (the same numbers; numpy's without a compiler). ``noise_floor_px``: blobs smaller than
    this are ignored silently (sensor noise); larger ones that fail a check are rejections.
    ``max_candidates``: bright blobs examined per image, largest first.
    """

    threshold: int | None = None
    level_fraction: float = 0.7
    bright_count_px: float = 40.0
    min_separation: float = 0.5
    min_level_contrast: float = 20.0
    valley_band: float = 0.05
    max_valley_ratio: float = 0.5
    presmooth_px: float = 0.8
    profile_half_px: float = 4.0
    profile_step_px: float = 0.25
    min_contrast: float = 40.0
    max_samples_per_edge: int = 48  # 120 x 2 passes: same accuracy vs truth, twice the time
    refine_passes: int = 1
    noise_floor_px: float = 12.0
    max_candidates: int = 5
    min_fill: float = 0.85
    max_corner_shift_px: float = 4.0
    edges: str = "lean2"
    lean_samples_per_edge: int = 48
    compiled: bool = True

    def __post_init__(self) -> None:
        if self.threshold is not None and not 0 < self.threshold < 255:
            raise PerceptionError("threshold: must be in (0, 255), or None for adaptive")
        if not 0.3 <= self.level_fraction <= 0.9:
            raise PerceptionError("level_fraction: must be in [0.3, 0.9]")
        if not self.bright_count_px >= 1:
            raise PerceptionError("bright_count_px: must be >= 1")
        if not (self.min_separation >= 0 and self.min_level_contrast > 0):
            raise PerceptionError("min_separation, min_level_contrast: must be >= 0, > 0")
        if not (0 < self.valley_band < 0.5 and self.max_valley_ratio > 0):
            raise PerceptionError("valley_band: must be in (0, 0.5); max_valley_ratio > 0")
        if not self.profile_half_px >= 2:
            raise PerceptionError("profile_half_px: must be >= 2")
        if not 0 < self.profile_step_px <= 0.5:
            raise PerceptionError("profile_step_px: must be in (0, 0.5]")
        if self.refine_passes < 1:
            raise PerceptionError("refine_passes: must be >= 1")
        if self.edges not in EDGE_METHODS:
            raise PerceptionError(f"edges: {self.edges!r} is not one of {EDGE_METHODS}")


#: The sub-pixel edge methods (``RectangleSettings.edges``, ``[perception] rectangle_edges``):
#: "profiles" (:mod:`companion.perception.edges`, the detector of every log recorded before
#: 2026-11-28), "lean" (:mod:`companion.perception.edges_lean`, with a histogram of fewer
#: samples while tracking; about a third less CPU, the same accuracy) and "lean2"
#: (:mod:`companion.perception.edges_lean2`: fewer numpy calls and, tracking, about one pass
#: a frame instead of three; docs/reference/perception.md).
EDGE_METHODS = ("profiles", "lean", "lean2")
_TRACKING_METHODS = ("lean", "lean2")  # the methods that refine from the previous corners


class RectangleDetector(QuadDetectorBase):
    """Finds the target rectangle's four corners with sub-pixel accuracy.

    ``length_m``, ``width_m``: the target's sides (length along its heading). Corner order:
    clockwise on screen and edge 0 is the image of a width edge, i.e. front-left, front-right,
    rear-right, rear-left of the target up to the half-turn ambiguity of a plain rectangle
    (see :func:`~companion.perception.plausibility.order_target_corners`; pass ``hint`` to
    :meth:`analyse` to keep the order continuous between frames).

    ``quality`` = (fraction of usable edge samples) * exp(-(RMS line-fit residual in px)).
    """

    def __init__(
        self,
        length_m: float,
        width_m: float,
        *,
        settings: RectangleSettings | None = None,
        limits: QuadLimits | None = None,
    ) -> None:
        if not (length_m > 0 and width_m > 0):
            raise PerceptionError("length_m, width_m: must be > 0")
        self.length_m = float(length_m)
        self.width_m = float(width_m)
        self.settings = settings or RectangleSettings()
        s = self.settings
        self._edge_settings: EdgeSettings | LeanSettings = (
            EdgeSettings(s.profile_half_px, s.profile_step_px, s.min_contrast,
                         s.max_samples_per_edge) if s.edges == "profiles" else
            LeanSettings(s.profile_half_px, s.profile_step_px, s.min_contrast,
                         s.lean_samples_per_edge))
        aspect = max(length_m, width_m) / min(length_m, width_m)
        self.limits = limits or QuadLimits(expected_aspect=aspect)
        pts = rectangle_corners_m(length_m, width_m)  # FL, FR, RR, RL
        pts.setflags(write=False)
        self._target_points_m = pts
        self._edge_by_contrast: dict[float, EdgeSettings | LeanSettings] = {}
        # "lean2": the blur scales of the last detection this detector returned (its next
        # tracked refinement starts from them) and of the last refinement
        self._blur_scale: list[float] | None = None
        self._refined_scale: list[float] | None = None
        # "lean2": how the corners moved in the last tracked detection returned (a tracked
        # start is the hint moved as much again: a constant-velocity guess) and in the last
        # tracking attempt
        self._motion: FloatArray | None = None
        self._tracked_motion: FloatArray | None = None
        # the last adaptive grey levels computed and for how many frames they were reused
        self._held_levels: tuple[int, float] | None = None
        self._held_age = 0
        # (x0, y0, x1, y1) px, end exclusive: every pixel the last analyse read (a tracked
        # "lean2" frame on held levels: its edge profiles' box); None: the whole image
        self.last_read_box: tuple[int, int, int, int] | None = None
        self._reads = [0.0] * 4
        self._lean2 = lean2_refiner(s.compiled and s.edges == "lean2")  # compiled or numpy's

    def analyse(
        self, image: npt.NDArray[np.uint8], hint: npt.ArrayLike | None = None
    ) -> DetectionReport:
        gray = to_gray(image)
        h, w = gray.shape
        s = self.settings
        tracking = hint is not None and s.edges in _TRACKING_METHODS
        # "lean2" tracking reuses the grey levels of up to _HOLD_LEVELS_FRAMES frames before
        # (the histogram was a fifth of a tracked frame's CPU); a blob search has its own
        hold = (tracking and s.edges == "lean2" and self._held_levels is not None
                and self._held_age < _HOLD_LEVELS_FRAMES)
        levels = self._levels(gray, tracking, hold)
        self.last_read_box = None
        if isinstance(levels, str):
            return DetectionReport(
                None, (), f"no bright region (nothing stands out of the ground: {levels})", 0)
        threshold, edge_settings = levels
        if hint is not None and tracking:
            tracked = self._track(gray, hint, w, h, edge_settings)
            if tracked is not None:
                self._blur_scale, self._motion = self._refined_scale, self._tracked_motion
                if hold or s.threshold is not None:  # no histogram read the image
                    self.last_read_box = read_box_px(self._reads, w, h)
                return DetectionReport(tracked, (), "", 1)
            if hold:  # the blob search with this frame's own levels
                levels = self._levels(gray, tracking, False)
                if isinstance(levels, str):
                    return DetectionReport(None, (), "no bright region (nothing stands out of"
                                           f" the ground: {levels})", 0)
                threshold, edge_settings = levels
        blobs = self._blobs(gray, threshold)
        if not blobs:
            return DetectionReport(None, (), "no bright region (target not in view)", 0)
        blobs.sort(key=lambda b: -b[0])
        rejections: list[Rejection] = []
        accepted: list[tuple[Detection, list[float] | None]] = []
        for area, contour in blobs[: s.max_candidates]:
            result = self._candidate(gray, contour, area, w, h, hint, edge_settings)
            if isinstance(result, Rejection):
                rejections.append(result)
            else:
                accepted.append((result, self._refined_scale))
        if len(blobs) > s.max_candidates:
            rejections.append(Rejection(f"{len(blobs) - s.max_candidates} smaller blobs ignored"))
        if not accepted:
            reason = "; ".join(r.reason for r in rejections)
            return DetectionReport(None, tuple(rejections), reason, len(blobs))
        best, self._blur_scale = max(accepted, key=lambda d: (d[0].quality > 0.5, d[0].area_px))
        self._motion = None
        return DetectionReport(best, tuple(rejections), "", len(blobs))

    # ------------------------------------------------------------------------------------------

    def _levels(self, gray: npt.NDArray[np.uint8], tracking: bool, hold: bool
                ) -> tuple[int, EdgeSettings | LeanSettings] | str:
        """The grey threshold and the edge settings of this frame (the fixed threshold, or the
        adaptive levels: this frame's, or with ``hold`` the last ones computed), or why the
        frame has no bright region (a message)."""
        s = self.settings
        if s.threshold is not None:
            return s.threshold, self._edge_settings
        if hold and self._held_levels is not None:
            self._held_age += 1
            threshold, contrast = self._held_levels
        else:
            # tracking, the searched image is the region around the target (a ninth of it or
            # more): a quarter of the samples still hold its level; a whole frame keeps them
            # all (a small far target covers a few hundred of its pixels)
            levels = grey_levels(gray, s, _HIST_SAMPLES_TRACK if tracking else _HIST_SAMPLES)
            if isinstance(levels, str):
                self._held_levels = None
                return levels
            self._held_levels, self._held_age = levels, 0
            threshold, contrast = levels
        # one settings object per level contrast (an integer number of grey levels: a few
        # hundred at most), not a dataclasses.replace with its validation every frame
        cached = self._edge_by_contrast.get(contrast)
        if cached is None:
            cached = dataclasses.replace(
                self._edge_settings,
                min_contrast=max(s.min_contrast * contrast / _NOMINAL_CONTRAST,
                                 0.5 * s.min_level_contrast))
            self._edge_by_contrast[contrast] = cached
        return threshold, cached

    def _blobs(self, gray: npt.NDArray[np.uint8], threshold: int
               ) -> list[tuple[float, npt.NDArray[np.int32]]]:
        """The bright blobs (area px^2, contour) of at least ``noise_floor_px``, unsorted."""
        s = self.settings
        coarse = gray
        off = (0, 0)
        if s.presmooth_px > 0:
            # Work avoidance: blur and threshold only the window around the raw pixels above
            # the threshold (the top is a small part of the region of interest). The result is
            # the same as for the whole image: see _bright_window.
            win = _bright_window(gray, threshold, _blur_radius_px(s.presmooth_px))
            if win is None:
                return []
            x0, y0, x1, y1 = win
            coarse = gray[y0:y1, x0:x1]
            off = (x0, y0)
        if s.presmooth_px > 0:
            coarse = np.asarray(cv2.GaussianBlur(coarse, (0, 0), s.presmooth_px), dtype=np.uint8)
        _, binary = cv2.threshold(coarse, threshold, 255, cv2.THRESH_BINARY)
        contours, _ = cv2.findContours(binary, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE,
                                       offset=off)
        blobs = [(float(cv2.contourArea(c)), np.asarray(c, dtype=np.int32)) for c in contours]
        return [b for b in blobs if b[0] >= s.noise_floor_px]

    def _track(self, gray: npt.NDArray[np.uint8], hint: npt.ArrayLike, w: int, h: int,
               edge_settings: EdgeSettings | LeanSettings) -> Detection | None:
        """``edges = "lean"``/``"lean2"`` while tracking: the previous frame's corners
        (``hint``) are the coarse corners, so the bright-blob search (window, blur, contours,
        polygon) is skipped ("lean2": moved as they moved in the last tracked detection, a
        constant-velocity guess, and refined from that detection's blur scales).
        The target moves about a pixel a frame (p99 1.7 px on a paper flight); a start off by
        more than ``_TRACK_SHIFT_PX`` measures worse than the blob's coarse corners under
        heavy noise or blur (tests/companion/test_perception_edges.py). ``None`` (search the
        blobs instead) when the hint is not a clockwise quad away from the border, an edge is
        not measured, a corner
        moved more than ``_TRACK_SHIFT_PX``, or the result fails a check or has quality
        <= 0.5 (the blob search's preference)."""
        self._tracked_motion = None
        previous = np.asarray(hint, dtype=np.float64)
        if previous.shape != (4, 2) or not isinstance(edge_settings, LeanSettings):
            return None
        start = previous if self._motion is None else previous + self._motion
        # the hint passed every check in its own frame: here only its place in this image
        # (plain floats on 4 corners: numpy's per-call cost dominates)
        pts = start.tolist()
        m = self.limits.border_margin_px
        if (signed_area(start) <= 0.0
                or not all(m < x < w - 1 - m and m < y < h - 1 - m for x, y in pts)):
            return None
        self._reads[:] = (math.inf, math.inf, -math.inf, -math.inf)
        refined = self._refine(gray, start, edge_settings, self._blur_scale, self._reads)
        if refined is None:
            return None
        corners, fits = refined
        shift = max(math.sqrt(dx * dx + dy * dy) for dx, dy in (corners - start).tolist())
        if shift > _TRACK_SHIFT_PX:
            return None
        # the hint's order is the target's unless the perspective swapped which pair of
        # opposite edges looks shorter (then the blob search's rule orders them again)
        (x0, y0), (x1, y1), (x2, y2), (x3, y3) = corners.tolist()
        e02 = math.hypot(x1 - x0, y1 - y0) + math.hypot(x3 - x2, y3 - y2)
        e13 = math.hypot(x2 - x1, y2 - y1) + math.hypot(x0 - x3, y0 - y3)
        if (e02 <= e13) != (self.width_m <= self.length_m):
            corners = order_target_corners(corners, self.width_m <= self.length_m, start)
        elif self.settings.edges == "lean2":
            self._tracked_motion = corners - previous
        result = self._detection(corners, fits, w, h)
        if isinstance(result, Rejection) or result.quality <= 0.5:
            return None
        return result

    def _candidate(
        self,
        gray: npt.NDArray[np.uint8],
        contour: npt.NDArray[np.int32],
        area: float,
        w: int,
        h: int,
        hint: npt.ArrayLike | None,
        edge_settings: EdgeSettings | LeanSettings,
    ) -> Detection | Rejection:
        s = self.settings
        lim = self.limits
        if area < lim.min_area_px:
            return Rejection(f"too small: blob area {area:.0f} px^2 < {lim.min_area_px:.0f}")
        if box_touches_border(cv2.boundingRect(contour), w, h, lim.border_margin_px):
            return Rejection("touches image border: partially visible")
        quad = approx_quad(contour)
        if quad is None:
            return Rejection("not a quadrilateral")
        quad_area = abs(signed_area(quad))
        fill = area / max(quad_area, 1e-9)
        if not s.min_fill <= fill <= 1.0 / s.min_fill:
            return Rejection(f"not quadrilateral-shaped: fill {fill:.2f}", quad)
        reason = check_quad(quad, w, h, lim)
        if reason is not None:  # cheap and clearer before the refinement
            return Rejection(reason, quad)
        ordered = order_target_corners(quad, self.width_m <= self.length_m, hint)
        corners = ordered
        fits: list[EdgeFit] = []
        for _ in range(s.refine_passes):
            refined = self._refine(gray, corners, edge_settings)
            if refined is None:
                return Rejection("edges not measurable (low contrast or too short)", ordered)
            corners, fits = refined
        # plain floats on 4 corners (numpy's per-call cost dominates; the same values)
        shift = max(math.sqrt(dx * dx + dy * dy) for dx, dy in (corners - ordered).tolist())
        limit = s.max_corner_shift_px + 0.05 * math.sqrt(quad_area)
        if shift > limit:
            return Rejection(f"refinement moved a corner by {shift:.1f} px", ordered)
        return self._detection(corners, fits, w, h)

    def _refine(self, gray: npt.NDArray[np.uint8], corners: FloatArray,
                edge_settings: EdgeSettings | LeanSettings, scale: list[float] | None = None,
                reads: list[float] | None = None) -> tuple[FloatArray, list[EdgeFit]] | None:
        """The settings' edge method on coarse ``corners`` ("lean2": from the blur ``scale``
        when given, and the measured one kept in ``_refined_scale``)."""
        self._refined_scale = None
        if not isinstance(edge_settings, LeanSettings):
            return refine_quad(gray, corners, edge_settings)
        if self.settings.edges != "lean2":
            return refine_quad_lean(gray, corners, edge_settings)
        refined = self._lean2(gray, corners, edge_settings, scale, reads)
        if refined is None:
            return None
        self._refined_scale = refined[2]
        return refined[0], refined[1]

    def _detection(self, corners: FloatArray, fits: list[EdgeFit], w: int, h: int
                   ) -> Detection | Rejection:
        """The refined quad's last check, quality and flags."""
        lim = self.limits
        reason = check_quad(corners, w, h, lim)
        if reason is not None:
            return Rejection(reason, corners)
        valid = sum(f.valid_fraction for f in fits) / len(fits)
        rms = math.sqrt(sum(f.rms_px**2 for f in fits) / len(fits))
        quality = min(max(valid * math.exp(-rms), 0.0), 1.0)
        flags: tuple[str, ...] = ()
        if touches_border(corners, w, h, lim.border_margin_px + self.settings.profile_half_px):
            flags = ("near border",)
        return Detection(corners, quality, abs(signed_area(corners)), None, flags)


_HOLD_LEVELS_FRAMES = 7  # "lean2" tracking: grey levels reused at most this many frames
_TRACK_SHIFT_PX = 1.5  # a tracked corner moving farther: search the blobs instead
_NOMINAL_CONTRAST = 140.0  # the top above the ground's median at the nominal exposure
_HIST_SAMPLES = 65_536  # the histogram samples every n-th row and column beyond this many px
_HIST_SAMPLES_TRACK = 16_384  # the same while tracking with edges = "lean"


def grey_levels(gray: npt.NDArray[np.uint8], s: RectangleSettings,
                samples: int = _HIST_SAMPLES) -> tuple[int, float] | str:
    """The adaptive threshold of one frame: ``(threshold, T - G)``, or why the frame has no
    bright region standing out (a message). ``G``: the median grey level; ``T``: the median of
    the pixels above a first threshold, placed with the level that ``s.bright_count_px`` pixels
    reach (a few noisy pixels do not set it). Images of 4 x ``samples`` px or more are sampled on
    every n-th row and column (n = isqrt(size / samples): 3 on 1000 x 1000 with the default
    65 536; while tracking 16 384, 2 on a 400 x 400 region of interest; counts scaled to match):
    the levels agree with the whole image's to about a grey level."""
    step = max(math.isqrt(gray.size // samples), 1)
    sample = gray[::step, ::step] if step > 1 else gray
    # calcHist reads a strided view (a crop of the frame, rows apart) as is: no copy needed
    hist = cv2.calcHist([sample], [0], None, [256], [0, 256]).ravel()
    total = float(hist.sum())
    csum = np.cumsum(hist)
    g = int(np.searchsorted(csum, 0.5 * total))
    need = max(s.bright_count_px / (step * step), 1.0)
    from_top = np.cumsum(hist[::-1])
    t_max = 255 - int(np.searchsorted(from_top, need))
    if t_max - g < max(s.min_level_contrast, s.min_separation * g):
        return f"bright level {t_max} vs ground {g}"
    # the bright region's own level: the median of the pixels above a first threshold (noise
    # spreads the top's pixels; its brightest few would set the level too high)
    first = round(g + s.level_fraction * (t_max - g))
    n_first = float(total - csum[first])
    t = int(np.searchsorted(csum, csum[first] + 0.5 * n_first))
    contrast = float(t - g)
    if contrast < max(s.min_level_contrast, s.min_separation * g):
        return f"bright level {t} vs ground {g}"
    threshold = round(g + s.level_fraction * contrast)
    half = s.valley_band * contrast
    lo, hi = max(math.floor(threshold - half), 0), min(math.ceil(threshold + half), 255)
    band = float(csum[hi] - (csum[lo - 1] if lo > 0 else 0.0))
    above = float(total - csum[threshold])
    if band > s.max_valley_ratio * above:
        return f"no gap below the bright level {t} (ground {g})"
    return min(max(threshold, 1), 254), contrast


def _blur_radius_px(sigma: float) -> int:
    """An upper bound on the radius of the kernel ``cv2.GaussianBlur(..., (0, 0), sigma)`` uses
    on uint8 images (its size is ``round(6 sigma + 1) | 1``, so the radius is <= 3 sigma + 1)."""
    return math.ceil(3.0 * sigma) + 1


def _bright_window(gray: npt.NDArray[np.uint8], threshold: int, radius: int
                   ) -> tuple[int, int, int, int] | None:
    """``(x0, y0, x1, y1)`` (end exclusive): the bounding box of the raw pixels above
    ``threshold`` grown by ``2 * radius`` on every side and clipped to the image; ``None`` if no
    pixel is above it.

    Why blurring and thresholding only this window gives the same binary image as the whole:
    the blur averages a (2 radius + 1)^2 neighbourhood with non-negative weights summing to one,
    so a blurred pixel can exceed the threshold only within ``radius`` of a raw pixel that does;
    every pixel outside the window is at least ``2 radius`` away from one, so it stays below in
    the whole image's blur. Inside the window, a pixel whose neighbourhood the window's border
    cuts (only where the window ends inside the image) lies within ``radius`` of that border,
    and its neighbourhood and border reflection stay within ``2 radius`` of it, so all of its
    inputs are below the threshold in both blurs: it stays below in both. Every other pixel sees
    the same neighbourhood in both (OpenCV's uint8 Gaussian is bit-exact fixed point)."""
    _, raw = cv2.threshold(gray, threshold, 255, cv2.THRESH_BINARY)
    x, y, w, h = cv2.boundingRect(raw)
    if w == 0 or h == 0:
        return None
    pad = 2 * radius
    rows, cols = gray.shape[:2]
    return max(x - pad, 0), max(y - pad, 0), min(x + w + pad, cols), min(y + h + pad, rows)


__all__ = ["RectangleDetector", "RectangleSettings", "grey_levels"]
