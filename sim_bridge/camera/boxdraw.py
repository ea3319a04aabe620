"""The rectangle-topped box composited over the ground through a small compiled kernel
(``box_rect.c``): the same float32 operations as ``target.py``'s numpy passes (each edge's
distance, the running minima, the clips, the two blends and the rounding) in one loop over the
box's ROI instead of ~35 array passes with their allocations (docs/reference/emulator.md,
section 5.4).

Built once with the system's C compiler into the emulator's cache directory
(``upsample.build_library``), loaded with ctypes and, before its first use in a process,
checked against the numpy passes on random boxes (random silhouettes and tops, shared and own
edges, ROIs clipped at the canvas, every background level); any difference, no compiler or
another machine leaves the numpy passes in charge (logged once). Lines that are not finite and
degenerate polygons also go to numpy: the same pixels either way.
"""

from __future__ import annotations

import ctypes as ct
import functools
import logging
import math
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from sim_bridge.camera.scene import EdgeLine
from sim_bridge.camera.upsample import build_library, load_checked

log = logging.getLogger(__name__)

SOURCE_PATH = Path(__file__).with_name("box_rect.c")
# -O3: the per-row loops vectorised (element-wise float32: the same operations per pixel)
FLAGS = ("-O3", "-fPIC", "-shared", "-ffp-contract=off")
_Kernel = Callable[..., int]


def _build(directory: Path) -> Path | None:
    return build_library(SOURCE_PATH, FLAGS, directory)


def _load(lib: Path) -> _Kernel:
    fn = ct.CDLL(str(lib)).box_rect_u8
    fn.argtypes = [ct.c_void_p, ct.c_long, ct.c_int, ct.c_int, ct.c_int, ct.c_int, ct.c_void_p,
                   ct.c_int, ct.c_void_p, ct.c_int, ct.c_int, ct.c_float, ct.c_float]
    fn.restype = ct.c_int
    return fn


def _lines(lines: Sequence[EdgeLine]) -> np.ndarray:
    return np.array(lines, np.float32).reshape(-1, 3)


def run(fn: _Kernel, image: np.ndarray, roi: tuple[int, int, int, int],
        hull_lines: list[EdgeLine], top_lines: list[EdgeLine] | None, side: float,
        dtop: float) -> bool:
    """Composite in place through ``fn``; False (``image`` untouched) for what it leaves to
    numpy: no silhouette line, a degenerate top, a line that is not finite, an image it cannot
    write."""
    if (not hull_lines or (top_lines is not None and not top_lines)
            or image.dtype != np.uint8 or image.ndim != 2 or image.strides[1] != 1
            or not image.flags.writeable):
        return False
    shared = set(hull_lines)
    own = [] if top_lines is None else [e for e in top_lines if e not in shared]
    if not all(math.isfinite(v) for e in (*hull_lines, *own) for v in e):
        return False
    hl, tl = _lines(hull_lines), _lines(own)
    x0, y0, x1, y1 = roi
    return fn(image.ctypes.data, image.strides[0], x0, y0, x1, y1, hl.ctypes.data, len(hl),
              tl.ctypes.data, len(tl), top_lines is not None, side, dtop) == 0


def _random_case(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """A canvas, a convex silhouette (hull of 8 random points) and a top (4 of them, or None)."""
    canvas = rng.integers(0, 256, (int(rng.integers(20, 90)), int(rng.integers(20, 90))),
                          dtype=np.uint8)
    h, w = canvas.shape
    pts = rng.uniform([-8, -8], [w + 8, h + 8], (8, 2))
    kind = rng.integers(4)
    if kind == 3:  # integer corners: pixel centres on the edges, coverages of exactly 0.5
        x0, y0 = rng.integers(-3, [w // 2, h // 2])
        x1, y1 = x0 + rng.integers(3, w), y0 + rng.integers(3, h)
        rect = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], float)
        return canvas, rect, (None if rng.integers(3) == 0 else rect + np.array([1.0, 1.0]))
    if kind == 0:  # a small box: the anti-aliased edges dominate
        pts = rng.uniform(0, 6, (8, 2)) + rng.uniform(0, [w, h])
    elif kind == 1:  # slivers 0.3-3 px wide across the canvas: every pixel on an edge's ramp
        a, b = rng.uniform([-5, -5], [w + 5, h + 5], (2, 2))
        n = np.array([b[1] - a[1], a[0] - b[0]]) / max(float(np.hypot(*(b - a))), 1e-9)
        off = n * rng.uniform(0.3, 3.0)
        pts = np.array([a, b, b + off, a + off, a + off / 2, b + off / 2, a, b])
        pts = pts + rng.normal(0, 0.2, pts.shape)
    import cv2

    hull = pts[cv2.convexHull(pts.astype(np.float32), returnPoints=False).ravel()]
    top = None if rng.integers(4) == 0 else pts[:4]
    return canvas, hull, top


def _matches(fn: _Kernel) -> bool:
    """The kernel's pixels equal the numpy passes' (``target.composite``) on random boxes."""
    from sim_bridge.camera.scene import edge_lines
    from sim_bridge.camera.scene import roi as roi_of
    from sim_bridge.camera.target import BOX_SIDE_LEVEL, TOP_LEVEL, composite

    rng = np.random.default_rng(7)
    for _ in range(60):
        canvas, hull, top = _random_case(rng)
        roi = roi_of(hull, canvas.shape[1], canvas.shape[0])
        if roi is None:
            continue
        ref = canvas.copy()
        composite(ref, roi, hull, top, float(TOP_LEVEL))
        out = canvas.copy()
        top_lines = None if top is None else edge_lines(top)
        done = run(fn, out, roi, edge_lines(hull), top_lines, float(BOX_SIDE_LEVEL),
                   float(TOP_LEVEL - BOX_SIDE_LEVEL))
        if done and not np.array_equal(out, ref):
            return False
    return True


@functools.lru_cache(maxsize=1)
def kernel(directory: Path | None = None) -> _Kernel | None:
    """The checked kernel of this process, or None (the numpy passes then)."""
    return load_checked("box", _build, _load, _matches, "the numpy passes", directory)
