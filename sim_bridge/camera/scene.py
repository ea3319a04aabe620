"""The scene around the target: the textured ground (and sky) warped into the canvas, and the
anti-aliased polygon coverage the target is drawn with.

The ground plane (a periodic procedural texture, intensities ~40..150, precomputed once) is
warped into the image by its homography (``cv2.warpPerspective``'s pixels, INTER_LINEAR,
BORDER_WRAP, through the compiled kernel of ``warp`` when it is available, at half resolution,
then upsampled). Polygons are drawn with analytic anti-aliasing (coverage
``clip(0.5 + signed distance to the edge, 0, 1)`` per pixel), so an edge's 50 % level lies exactly
on the projected edge and detected corners land where the projection puts them.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import math
import os
from pathlib import Path

import cv2
import numpy as np

from sim_bridge.camera.lens import Lens
from sim_bridge.camera.upsample import upsample2x
from sim_bridge.camera.warp import warp_perspective

# Intensities (mono8).
GROUND_MIN, GROUND_MAX = 40, 150
SKY_LEVEL = 150

_GROUND_TEXEL_M = 0.01  # ground texture resolution
_GROUND_TEX_PX = 1024  # period of the ground texture: 10.24 m
_GROUND_PAD_PX = 512  # the stored texture repeats the period by this much on every side
_SKY_DZ = 0.08  # rays whose world-down component (|ray| ~ 1..1.6) is below this show sky


def cache_dir() -> Path:
    """Where the emulator keeps what it computes the same way every start (``$XDG_CACHE_HOME``
    or ``~/.cache``, then ``sim_bridge``)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "sim_bridge"


def _texture_file(seed: int, directory: Path) -> Path:
    """The cache file of ``seed``'s texture, keyed by this module's source and the numpy and
    OpenCV versions that computed it (a change to any of them computes it afresh)."""
    key = hashlib.sha256(Path(__file__).read_bytes())
    key.update(f"{np.__version__} {cv2.__version__} {seed}".encode())
    return directory / f"ground-{key.hexdigest()[:24]}.npy"


@functools.lru_cache(maxsize=4)
def ground_texture(seed: int, directory: Path | None = None) -> np.ndarray:
    """:func:`make_ground_texture` of ``seed``, read from the cache (``directory``, default
    :func:`cache_dir`) when an earlier start computed it: ~0.13 s of CPU per emulator start
    against ~2 ms (the period is stored, 1 MB, and padded on reading). A cache that cannot be
    read or written only costs the computation."""
    path = _texture_file(seed, cache_dir() if directory is None else directory)
    period = None
    with contextlib.suppress(OSError, ValueError):
        period = np.load(path, allow_pickle=False)
    if period is None or period.shape != (_GROUND_TEX_PX,) * 2 or period.dtype != np.uint8:
        period = make_ground_texture(seed)
        with contextlib.suppress(OSError):
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".{os.getpid()}.tmp")
            with open(tmp, "wb") as f:
                np.save(f, period, allow_pickle=False)
            os.replace(tmp, path)  # atomic: a concurrent start reads all or nothing
    out = np.ascontiguousarray(np.pad(period, _GROUND_PAD_PX, mode="wrap"))
    out.setflags(write=False)  # shared between cameras with the same seed
    return out


def make_ground_texture(seed: int) -> np.ndarray:
    """One period of the procedural ground (``_GROUND_TEX_PX`` square, seamless), uint8 in
    [40, 150]: 1/f noise plus 1 m tiles."""
    n = _GROUND_TEX_PX
    rng = np.random.default_rng(seed)
    fy = np.fft.fftfreq(n)[:, None]
    fx = np.fft.rfftfreq(n)[None, :]
    f = np.hypot(fx, fy)
    f[0, 0] = 1.0
    # Amplitude ~ 1/f, cut off above ~5 cm wavelength so the texture is smooth at the image's
    # scale (a few mm per pixel) and does not bias corner refinement.
    amp = np.where(f > 0.2, 0.0, 1.0 / f)
    amp[0, 0] = 0.0
    spec = amp * (rng.normal(size=f.shape) + 1j * rng.normal(size=f.shape))
    noise = np.fft.irfft2(spec, s=(n, n))
    noise = (noise - noise.mean()) / noise.std()
    # Tiles of 1 m with a shade each and faint joints: straight edges a detector must reject.
    tile_px = round(1.0 / _GROUND_TEXEL_M)
    n_tiles = -(-n // tile_px)
    shades = rng.uniform(-12.0, 12.0, size=(n_tiles, n_tiles))
    idx = np.arange(n) // tile_px
    tiles = shades[idx[:, None], idx[None, :]]
    joints = (np.arange(n) % tile_px) < 2
    joint = (joints[:, None] | joints[None, :]) * -15.0
    img = 95.0 + 14.0 * noise + tiles + joint
    pad = 8  # blur with wrap-around (cv2's filters do not support BORDER_WRAP)
    img = cv2.GaussianBlur(np.pad(img.astype(np.float32), pad, mode="wrap"), (0, 0), 1.0)
    img = img[pad:-pad, pad:-pad]
    return np.clip(np.rint(img), GROUND_MIN, GROUND_MAX).astype(np.uint8)


def clip_polygon_halfplane(poly: np.ndarray, a: np.ndarray, c: float) -> np.ndarray:
    """Keep the part of a convex polygon (n, d) where ``a . p + c >= 0`` (Sutherland-Hodgman)."""
    out: list[np.ndarray] = []
    n = len(poly)
    for i in range(n):
        p, q = poly[i], poly[(i + 1) % n]
        dp, dq = float(a @ p + c), float(a @ q + c)
        if dp >= 0:
            out.append(p)
        if (dp >= 0) != (dq >= 0):
            out.append(p + (q - p) * (dp / (dp - dq)))
    return np.array(out).reshape(-1, poly.shape[1])


def render_ground(tex: np.ndarray, lens: Lens, r: np.ndarray, c_w: np.ndarray, ground_z: float,
                  half: bool = False) -> np.ndarray:
        """The ground (and sky) on the canvas, or with ``half`` at half its resolution (the
        resolution it is warped at)."""
        w, h = lens.rw, lens.rh
        # Ray of pixel p = (col, row, 1) in NED: d = A p with A = R^T K^-1.
        a = r.T @ lens.rk_inv
        depth = ground_z - float(c_w[2])  # camera height above the ground (> 0 when above)
        wh, hh = (w + 1) // 2, (h + 1) // 2
        if depth <= 1e-6:
            return np.full((hh, wh) if half else (h, w), SKY_LEVEL, np.uint8)
        period_m = _GROUND_TEX_PX * _GROUND_TEXEL_M
        pad_m = _GROUND_PAD_PX * _GROUND_TEXEL_M
        # Offsets, whole periods, that put the camera within the first period of the padded
        # texture: views up to pad_m wide around it stay on cv2's fast (inside) path.
        ox = math.floor(c_w[0] / period_m) * period_m - pad_m
        oy = math.floor(c_w[1] / period_m) * period_m - pad_m
        # Ground point of the ray: c + depth * d / d_z; homogeneous [x, y, 1] ~ [depth d_xy +
        # c_xy d_z, d_z]. Texture: col = (y - oy) / texel, row = (x - ox) / texel.
        g = np.empty((3, 3))
        g[0] = (depth * a[1] + (c_w[1] - oy) * a[2]) / _GROUND_TEXEL_M
        g[1] = (depth * a[0] + (c_w[0] - ox) * a[2]) / _GROUND_TEXEL_M
        g[2] = a[2]
        # The ground is smooth at the image's scale: warp it at half resolution and upsample
        # (2.5x cheaper than a full-size warp). Half-size pixel xs sits at full-size
        # x = (xs + 0.5) / sx - 0.5 (cv2.resize's pixel-centre convention).
        sx, sy = wh / w, hh / h
        to_half = np.array(
            [[1.0 / sx, 0.0, 0.5 / sx - 0.5], [0.0, 1.0 / sy, 0.5 / sy - 0.5], [0.0, 0.0, 1.0]]
        )
        # cv2.warpPerspective(INTER_LINEAR | WARP_INVERSE_MAP, BORDER_WRAP)'s pixels
        small = warp_perspective(tex, g @ to_half, (wh, hh))
        if half:
            image = small
        elif (w, h) == (2 * wh, 2 * hh):  # cv2.resize's pixels, a third of its CPU
            image = upsample2x(small)
        else:
            image = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
        corners = np.array([[0, 0, 1], [w - 1, 0, 1], [w - 1, h - 1, 1], [0, h - 1, 1]], float)
        dz = corners @ a[2]
        if (dz > _SKY_DZ).all():
            return image
        # Part of the view is at or above the horizon: paint it as sky.
        rect = corners[:, :2] + 0.5 * np.sign(corners[:, :2] - [lens.rcx, lens.rcy])
        sky = clip_polygon_halfplane(rect, -a[2, :2], _SKY_DZ - float(a[2, 2]))
        if len(sky) >= 3:
            if half:
                sky = (sky + 0.5) * np.array([sx, sy]) - 0.5
            cv2.fillPoly(image, [np.round(sky * 16).astype(np.int32)], SKY_LEVEL, cv2.LINE_8, 4)
        return image


def roi(poly: np.ndarray, w: int, h: int) -> tuple[int, int, int, int] | None:
    """Integer pixel box [x0, x1) x [y0, y1) covering a polygon's anti-aliased footprint."""
    x0 = max(math.floor(poly[:, 0].min()) - 1, 0)
    y0 = max(math.floor(poly[:, 1].min()) - 1, 0)
    x1 = min(math.ceil(poly[:, 0].max()) + 2, w)
    y1 = min(math.ceil(poly[:, 1].max()) + 2, h)
    if x1 <= x0 or y1 <= y0:
        return None
    return x0, y0, x1, y1


def _area2(pts: list[list[float]]) -> float:
    """Twice the signed area of a polygon (shoelace), as ``np.sum(x * roll(y, -1) - roll(x, -1)
    * y)`` computes it for fewer than 8 vertices (numpy sums so few terms in order): the same
    float, without the ~0.2 ms a frame of numpy's ``roll``."""
    total = 0.0
    n = len(pts)
    for i in range(n):
        (x0, y0), (x1, y1) = pts[i], pts[(i + 1) % n]
        total += x0 * y1 - x1 * y0
    return total


EdgeLine = tuple[float, float, float]  # (nx, ny, c0): 0.5 + signed distance = nx col + ny row + c0


def edge_lines(poly: np.ndarray) -> list[EdgeLine]:
    """Each non-degenerate edge of a convex polygon as its inward unit normal ``(nx, ny)`` and
    offset ``c0 = 0.5 - n . a`` (``a`` the edge's first vertex), Python floats: two polygons
    that share an edge in the same direction give it the same three floats."""
    p = np.asarray(poly, dtype=float)
    pts = p.tolist()  # the per-edge arithmetic on Python floats: the same float64 operations
    if len(p) < 8:
        area2 = _area2(pts)
    else:  # numpy sums 8 or more terms pairwise
        area2 = float(np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1]))
    sign = 1.0 if area2 > 0 else -1.0
    lines: list[EdgeLine] = []
    n = len(pts)
    for i in range(n):
        (ax, ay), (bx, by) = pts[i], pts[(i + 1) % n]
        ex, ey = bx - ax, by - ay
        length = math.hypot(ex, ey)
        if length < 1e-9:
            continue
        # Inward unit normal (left of the edge for a counter-clockwise polygon in (col, row)).
        nx, ny = -sign * ey / length, sign * ex / length
        lines.append((nx, ny, 0.5 - (nx * ax + ny * ay)))
    return lines


def edge_min(lines: list[EdgeLine], roi: tuple[int, int, int, int],
             start: np.ndarray | None = None) -> np.ndarray | None:
    """``min_i (nx_i col + ny_i row + c0_i)`` over the ROI's pixels, float32 (h, w), unclipped
    (``start``, if given, is the running minimum to continue, updated in place); ``None``
    without lines and ``start``. The minimum is exact (no rounding), so its order does not
    matter and a line already in ``start`` changes nothing."""
    x0, y0, x1, y1 = roi
    cols = np.arange(x0, x1, dtype=np.float32)[None, :]
    rows = np.arange(y0, y1, dtype=np.float32)[:, None]
    # The ROI-sized arrays are written in place (out=): the same operations in the same order,
    # without allocating (and page-faulting) two fresh ROI arrays per edge.
    cov = start
    d = np.empty((y1 - y0, x1 - x0), np.float32)
    for nx, ny, c0 in lines:
        np.add(np.float32(nx) * cols, np.float32(ny) * rows, out=d)
        np.add(d, np.float32(c0), out=d)
        if cov is None:
            cov, d = d, np.empty_like(d)
        else:
            np.minimum(cov, d, out=cov)
    return cov


def coverage(poly: np.ndarray, roi: tuple[int, int, int, int]) -> np.ndarray:
    """Approximate pixel coverage (float32 (h, w) in [0, 1]) of a convex polygon in the ROI:
    ``clip(0.5 + min_i signed_distance_i, 0, 1)`` over its edges (pixel centres at integers)."""
    cov = edge_min(edge_lines(poly), roi)
    if cov is None:
        x0, y0, x1, y1 = roi
        return np.zeros((y1 - y0, x1 - x0), np.float32)
    return np.asarray(np.clip(cov, 0.0, 1.0, out=cov), dtype=np.float32)
