"""The ground's perspective warp (``cv2.warpPerspective``, INTER_LINEAR, WARP_INVERSE_MAP, of
the padded ground texture into the half-resolution view) through a small compiled kernel
(``warp_persp.c``, AVX2 and FMA) that gives OpenCV's pixels with less CPU: OpenCV 5 gathers
each pixel's four neighbours byte by byte through a buffer (docs/reference/emulator.md,
section 5.4).

The kernel reproduces OpenCV 5's float kernel (matrix in float32, one division per
coordinate, fused multiply-adds where OpenCV's AVX2 build has them, its scalar loop for the
last columns of a row). It is built once with the system's C compiler into the emulator's
cache directory (``upsample.build_library``), loaded with ctypes and, before its first use in a
process, checked against ``cv2.warpPerspective`` on random and adversarial probes (exact
halves for the rounding, every column of the vector loop and of its scalar tail, random
homographies); any difference, no compiler, no AVX2/FMA or another machine leaves OpenCV in
charge (logged once). A view that samples outside the texture's fast range (the border
mode then matters) also goes to OpenCV for that frame: the same pixels either way.
"""

from __future__ import annotations

import ctypes as ct
import functools
import logging
from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np

from sim_bridge.camera.upsample import build_library, load_checked

log = logging.getLogger(__name__)

SOURCE_PATH = Path(__file__).with_name("warp_persp.c")
FLAGS = ("-O2", "-fPIC", "-shared", "-ffp-contract=off")
_FLAGS_CV = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
_Kernel = Callable[..., int]


def _build(directory: Path) -> Path | None:
    return build_library(SOURCE_PATH, FLAGS, directory)


def _load(lib: Path) -> _Kernel:
    fn = ct.CDLL(str(lib)).warp_persp_u8
    fn.argtypes = [ct.c_void_p, ct.c_int, ct.c_int, ct.c_long, ct.c_void_p, ct.c_int, ct.c_int,
                   ct.c_long, ct.c_void_p]
    fn.restype = ct.c_int
    return fn


def _run(fn: _Kernel, src: np.ndarray, m: np.ndarray, size: tuple[int, int]) -> np.ndarray | None:
    """The kernel's warp of ``src`` into ``size`` (w, h), or None when it declines the view."""
    w, h = size
    out = np.empty((h, w), np.uint8)
    md = np.ascontiguousarray(m, dtype=np.float64)
    rc = fn(src.ctypes.data, src.shape[0], src.shape[1], src.strides[0], out.ctypes.data, h, w,
            out.strides[0], md.ctypes.data)
    return out if rc == 0 else None


def _homography(rng: np.random.Generator, src_hw: tuple[int, int],
                dst_wh: tuple[int, int]) -> np.ndarray:
    """A random homography taking the destination's corners to four random points (a convex
    quadrilateral, so every pixel maps inside) of the source's fast range."""
    sh, sw = src_hw
    w, h = dst_wh
    lo, hi = np.array([0.5, 0.5]), np.array([sw - 4.5, sh - 2.5])
    while True:
        c = rng.uniform(lo, hi, (4, 2))
        # keep the corners in order around their centre: a convex (or at least simple) quad
        ang = np.arctan2(c[:, 1] - c[:, 1].mean(), c[:, 0] - c[:, 0].mean())
        quad = c[np.argsort(ang)].astype(np.float32)
        if cv2.isContourConvex(quad):
            break
    corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], np.float32)
    # a random start among the four rotations and either orientation: mirrored views too
    quad = np.roll(quad, int(rng.integers(4)), axis=0)
    if rng.integers(2):
        quad = quad[::-1].copy()
    return np.asarray(cv2.getPerspectiveTransform(corners, quad), np.float64)


def probes(seed: int = 2024) -> Iterator[tuple[np.ndarray, np.ndarray, tuple[int, int]]]:
    """(source, matrix, (w, h)) cases for the check: exact half-pixel shifts (the rounding's
    ties), tiny and large destinations (the vector loop, its 16-column turns and the scalar
    tail), random homographies over random and ground-like sources, narrow ones whose every
    pixel is the scalar tail's, and the ground's size."""
    rng = np.random.default_rng(seed)
    src = rng.integers(0, 256, (40, 52), dtype=np.uint8)
    for tx, ty in ((0.5, 0.5), (0.25, 0.75), (0.0, 0.5), (1.5, 2.0), (0.0, 0.0)):
        yield src, np.array([[1.0, 0, tx], [0, 1.0, ty], [0, 0, 1.0]]), (35, 30)
    yield src, np.array([[0.5, 0, 0.25], [0, 0.5, 0.75], [0, 0, 1.0]]), (63, 31)
    # the scalar tail's interpolation contracted: 195.49998 fused, 195.5 (so 196) unfused
    tie = np.array([[174, 148, 0, 0], [211, 205, 0, 0]], np.uint8)
    yield tie, np.array([[1.0, 0, 0.961883544921875], [0, 1.0, 0.8270072937011719],
                         [0, 0, 1.0]]), (1, 1)
    for w, h in ((2, 2), (15, 3), (16, 2), (17, 5), (31, 4), (33, 7), (47, 9), (100, 6)):
        for lo, hi in ((0, 256), (40, 151), (0, 2), (254, 256)):
            s = rng.integers(lo, hi, (int(rng.integers(6, 60)), int(rng.integers(8, 70))),
                             dtype=np.uint8)
            yield s, _homography(rng, s.shape, (w, h)), (w, h)
    for _ in range(6):  # tall and narrow: the scalar tail's arithmetic on ~50 000 pixels
        s = rng.integers(0, 256, (int(rng.integers(20, 200)), int(rng.integers(20, 200))),
                         dtype=np.uint8)
        yield s, _homography(rng, s.shape, (15, 600)), (15, 600)
    big = rng.integers(40, 151, (300, 420), dtype=np.uint8)
    yield big, _homography(rng, big.shape, (500, 500)), (500, 500)


def _matches(fn: _Kernel) -> bool:
    """The kernel gives ``cv2.warpPerspective``'s pixels on every probe (and takes them all)."""
    for src, m, size in probes():
        out = _run(fn, src, m, size)
        ref = cv2.warpPerspective(src, m, size, flags=_FLAGS_CV, borderMode=cv2.BORDER_WRAP)
        if out is None or not np.array_equal(out, ref):
            return False
    return True


@functools.lru_cache(maxsize=1)
def kernel(directory: Path | None = None) -> _Kernel | None:
    """The checked kernel of this process, or None (``cv2.warpPerspective`` then)."""
    return load_checked("warp", _build, _load, _matches, "cv2.warpPerspective", directory)


def warp_perspective(src: np.ndarray, m: np.ndarray, size: tuple[int, int],
                     border: int = cv2.BORDER_WRAP) -> np.ndarray:
    """``cv2.warpPerspective(src, m, size, flags=INTER_LINEAR | WARP_INVERSE_MAP,
    borderMode=border)`` of a uint8 (h, w) image: through the kernel when it is available and
    the view samples only inside ``src`` (the same pixels), else OpenCV."""
    fn = kernel()
    if fn is not None and src.dtype == np.uint8 and src.ndim == 2 and src.strides[1] == 1:
        out = _run(fn, src, m, size)
        if out is not None:
            return out
    return cv2.warpPerspective(src, m, size, flags=_FLAGS_CV, borderMode=border)
