"""The checks that hold the compiled ``"lean2"`` kernel (:mod:`companion.perception.edges_kernel`)
to the numpy path bit for bit: run once before a process uses the kernel (a failure: the
numpy path) and, with more probes, by the tests.

- :func:`warp_matches`: the kernel's sampling against ``cv2.warpAffine`` on random images,
  sizes (the detector's 33 x 48 and others, which read OpenCV's scalar tail), matrices and
  positions (off the image: the replicated border), and on *adversarial* images
  (:func:`adversarial_probe`): pixels planted around sample positions so that an
  interpolation rounded differently (e.g. without OpenCV's fused multiply-adds) gives another
  byte there, which random images show about once in a million samples;
- :func:`refine_mismatch`: whole refinements, kernel against numpy, on rendered quads
  (:func:`check_frames`), from coarse corners and tracked.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import cv2
import numpy as np
import numpy.typing as npt

from companion.perception._types import FloatArray
from companion.perception.edges import EdgeFit
from companion.perception.edges_lean import LeanSettings
from companion.perception.edges_lean2 import refine_quad_lean2

Refined = tuple[FloatArray, list[EdgeFit], list[float]]
Refiner = Callable[[npt.NDArray[np.uint8], FloatArray, LeanSettings, "list[float] | None",
                    "list[float] | None"], "Refined | None"]
Probe = tuple[npt.NDArray[np.uint8], FloatArray, int, int]  # image, matrix, rows k, columns n
_F32, _F64 = np.float32, np.float64
_FLAGS = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP


def random_probe(rng: np.random.Generator, t: int) -> Probe:
    """A random image (every third blurred), matrix (a rotated, scaled profile grid placed
    anywhere within 20 px of the image) and size (odd ``t``: the detector's 33 x 48)."""
    rows, cols = int(rng.integers(8, 120)), int(rng.integers(8, 120))
    img = rng.integers(0, 256, (rows, cols), dtype=np.uint8)
    if t % 3 == 0:
        img = np.asarray(cv2.GaussianBlur(img, (0, 0), 1.5), dtype=np.uint8)
    k, n = (33, 48) if t % 2 else (int(rng.integers(3, 40)), int(rng.integers(2, 90)))
    ang, sc, sp = rng.uniform(0.0, 2.0 * math.pi), rng.uniform(0.1, 3.0), rng.uniform(0.1, 3.0)
    tx, ty = math.cos(ang), math.sin(ang)
    x0, y0 = rng.uniform(-20, cols + 20), rng.uniform(-20, rows + 20)
    m = np.array([[sp * tx, 0.25 * ty * sc, x0 - 4.0 * ty * sc],
                  [sp * ty, -0.25 * tx * sc, y0 + 4.0 * tx * sc]])
    return img, m, k, n


def adversarial_probe(rng: np.random.Generator, size: int = 64, tries: int = 512) -> Probe:
    """A 33 x 48 grid over a ``size`` x ``size`` image whose pixels around many sample
    positions (disjoint 2 x 2 neighbourhoods; ``tries`` random values a position) are chosen
    so that OpenCV's interpolation
    (``fma(b, f1 - f0, f0)`` of ``f0 = fma(a, p01 - p00, p00)``, ...) and the same rounded
    after each product give different bytes. The positions come from OpenCV's float
    arithmetic as emulated in numpy; where that were wrong the probe is merely random."""
    k, n = 33, 48
    img = rng.integers(0, 256, (size, size), dtype=np.uint8)
    ang, sc, sp = rng.uniform(0, 2 * math.pi), rng.uniform(0.1, 3.0), rng.uniform(0.1, 1.0)
    tx, ty = math.cos(ang), math.sin(ang)
    x0, y0 = size / 2 - 24 * sp * tx, size / 2 - 24 * sp * ty
    m = np.array([[sp * tx, 0.25 * ty * sc, x0 - 4 * ty * sc],
                  [sp * ty, -0.25 * tx * sc, y0 + 4 * tx * sc]])
    y = np.arange(k, dtype=_F32)[:, None]
    x = np.arange(n, dtype=_F64)[None, :]
    mx, my = _F32(m[0, 1]) * y + _F32(m[0, 2]), _F32(m[1, 1]) * y + _F32(m[1, 2])
    sx = (_F64(_F32(m[0, 0])) * x + mx.astype(_F64)).astype(_F32)
    sy = (_F64(_F32(m[1, 0])) * x + my.astype(_F64)).astype(_F32)
    fx, fy = np.floor(sx), np.floor(sy)
    ix, iy = fx.astype(np.intp), fy.astype(np.intp)
    a, b = (sx - fx).astype(_F32), (sy - fy).astype(_F32)
    rs, cs = np.nonzero((ix >= 0) & (ix < size - 1) & (iy >= 0) & (iy < size - 1))
    aa, bb = a[rs, cs][:, None], b[rs, cs][:, None]
    q = rng.integers(0, 256, (4, rs.size, tries)).astype(_F32)

    def fused(u: npt.NDArray[np.float32], v: npt.NDArray[np.float32],
              w: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        return (u.astype(_F64) * v.astype(_F64) + w.astype(_F64)).astype(_F32)

    f0, f1 = fused(aa, q[1] - q[0], q[0]), fused(aa, q[3] - q[2], q[2])
    g0, g1 = q[0] + aa * (q[1] - q[0]), q[2] + aa * (q[3] - q[2])
    differ = np.rint(fused(bb, f1 - f0, f0)) != np.rint(g0 + bb * (g1 - g0))
    used = np.zeros((size, size), dtype=bool)
    for s in np.flatnonzero(differ.any(axis=1)):  # about one sample in 2000 (tries 512)
        i, j = int(ix[rs[s], cs[s]]), int(iy[rs[s], cs[s]])
        if not used[j:j + 2, i:i + 2].any():
            used[j:j + 2, i:i + 2] = True
            p = q[:, s, np.flatnonzero(differ[s])[0]].astype(np.uint8)
            img[j, i], img[j, i + 1], img[j + 1, i], img[j + 1, i + 1] = p
    return img, m, k, n


def warp_matches(warp_fn: Callable[..., int], block: int, probes: int = 60, adversarial: int = 0,
                 seed: int = 7) -> bool:
    """Whether the kernel's warp (``lean2_warp``) with OpenCV's vector block ``block`` gives
    ``cv2.warpAffine``'s bytes on ``probes`` random and ``adversarial`` adversarial probes."""
    rng = np.random.default_rng(seed)
    cases = [random_probe(rng, t) for t in range(probes)]
    cases += [adversarial_probe(rng) for _ in range(adversarial)]
    for img, m, k, n in cases:
        ref = cv2.warpAffine(img, m, (n, k), flags=_FLAGS, borderMode=cv2.BORDER_REPLICATE)
        out = np.empty((k, n), dtype=np.uint8)
        rows, cols = img.shape
        if warp_fn(img.ctypes.data, img.strides[0], rows, cols, m.ctypes.data, k, n, block,
                   out.ctypes.data) != 0 or not np.array_equal(out, ref):
            return False
    return True


def check_frames(seed: int, count: int) -> list[tuple[npt.NDArray[np.uint8], FloatArray]]:
    """``count`` frames of a bright quad on a textured ground (random pose, top level 120-255,
    blur 0.5-2 px on two frames in three, noise up to 15; every fourth near the image's left
    border; one in eight clean, a top 40 grey levels above a flat ground) and the quad's
    corners moved by up to 1.5 px: a refinement's inputs."""
    rng = np.random.default_rng(seed)
    out = []
    for t in range(count):
        rows, cols = 160, 200
        ground = rng.integers(40, 150, (rows, cols)).astype(np.float64)
        cx = rng.uniform(30, cols - 30) if t % 4 else rng.uniform(22, 40)
        cy = rng.uniform(30, rows - 30)
        half_l, half_w, ang = rng.uniform(18, 40), rng.uniform(12, 25), rng.uniform(0, math.pi)
        c, s = math.cos(ang), math.sin(ang)
        quad = np.array([[cx + u * c - v * s, cy + u * s + v * c]
                         for u, v in ((-half_l, -half_w), (half_l, -half_w), (half_l, half_w),
                                      (-half_l, half_w))])
        mask = np.zeros((rows, cols), dtype=np.uint8)
        cv2.fillConvexPoly(mask, np.round(quad * 16).astype(np.int32), 255, cv2.LINE_AA, 4)
        img: FloatArray = ground + (rng.uniform(120, 255) - ground) * (mask / 255.0)
        if t % 8 == 5:  # clean: ground 100, top 140 (contrast 40 exactly), hard edges
            img = np.asarray(np.where(mask > 127, 140.0, 100.0), dtype=np.float64)
        elif t % 3:
            img = np.asarray(cv2.GaussianBlur(img, (0, 0), rng.uniform(0.5, 2.0)), np.float64)
        if t % 8 != 5:
            img = img + rng.normal(0, rng.uniform(0, 15), img.shape)
        gray = np.clip(np.round(img), 0, 255).astype(np.uint8)
        x, y = quad[:, 0], quad[:, 1]
        if float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y)) <= 0:
            quad = quad[::-1].copy()  # clockwise on screen, as the detector passes them
        out.append((gray, quad + rng.uniform(-1.5, 1.5, quad.shape)))
    return out


def refine_mismatch(refiner: Refiner, frames: int = 24, seed: int = 11) -> str:
    """'' when ``refiner`` gives the numpy path's corners, fits, blur scales and read box on
    ``frames`` rendered frames (each with a default-like and a low contrast bound, refined from
    coarse corners and tracked with given blur scales), else which frame differed first."""
    for i, (gray, start) in enumerate(check_frames(seed, frames)):
        # 40 + 1e-9: a bound that is not a float32 (numpy compares in float32: 40.0), which
        # the clean frames' contrast of exactly 40 meets; 12: low-contrast profiles count
        for contrast in (40.000000001, 12.0):
            s = LeanSettings(min_contrast=contrast)
            for scale in (None, [1.0, 1.3, 2.2, 3.0]):
                r_np = [math.inf, math.inf, -math.inf, -math.inf]
                r_c = list(r_np)
                want = refine_quad_lean2(gray, start, s, scale, r_np)
                got = refiner(gray, start, s, scale, r_c)
                if not same_refinement(want, got) or r_np != r_c:
                    return f"frame {i} (min_contrast {contrast}, scale {scale})"
    return ""


def same_refinement(a: Refined | None, b: Refined | None) -> bool:
    """Bit for bit: ``==`` on every float (corners, line points and directions, RMS, kept
    fraction, blur scales)."""
    if a is None or b is None:
        return a is None and b is None
    (ca, fa, sa), (cb, fb, sb) = a, b
    return (ca.tolist() == cb.tolist() and sa == sb and all(
        x.point.tolist() == y.point.tolist() and x.direction.tolist() == y.direction.tolist()
        and x.rms_px == y.rms_px and x.valid_fraction == y.valid_fraction
        for x, y in zip(fa, fb, strict=True)))


__all__ = ["adversarial_probe", "check_frames", "random_probe", "refine_mismatch",
           "same_refinement", "warp_matches"]
