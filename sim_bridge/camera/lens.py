"""The camera's lens: an ideal pinhole, or a calibrated OpenCV lens (``camera_matrix`` +
``distortion_coefficients``) rendered through an ideal pinhole canvas and an exact inverse map.

The scene is drawn on the canvas (:attr:`Lens.rk`, :attr:`Lens.rw` x :attr:`Lens.rh`): the output
image itself for an ideal lens, else a larger canvas that covers the distorted image's field of
view, warped into the image by ``cv2.remap`` (each output pixel's ray from
``cv2.undistortPoints``, iterated to convergence), so a straight edge's 50 % level lands where
``cv2.projectPoints`` with the distortion puts it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from sim_bridge import ConfigError

UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
_REPO_ROOT = Path(__file__).resolve().parents[2]


def read_calibration(path: str | Path, width_px: int, height_px: int,
                     relative_to: str | Path = "") -> tuple[np.ndarray, np.ndarray]:
    """``camera_matrix`` (3, 3) and ``distortion_coefficients`` (n,) of an OpenCV
    ``cv2.FileStorage`` calibration file (YAML/XML/JSON, the format of OpenCV's calibration
    sample and of the companion's ``camera.calibration_file``). A relative path is looked up
    in the working directory, then next to ``relative_to`` (the scenario file), then in the
    repository root. ``image_width``/``image_height``, when present, must match the camera."""
    p = Path(path).expanduser()
    if not p.is_absolute():
        bases = [Path.cwd()]
        if relative_to:
            bases.append(Path(relative_to).expanduser().resolve().parent)
        bases.append(_REPO_ROOT)
        p = next((b / p for b in bases if (b / p).is_file()), p)
    key = "camera.calibration_file"
    if not p.is_file():
        raise ConfigError(f"{key}: {path}: file not found")
    try:
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as e:
        raise ConfigError(f"{key}: {p}: not an OpenCV FileStorage file ({e})") from None
    try:
        if not fs.isOpened():
            raise ConfigError(f"{key}: {p}: not an OpenCV FileStorage file")

        def matrix(name: str) -> np.ndarray | None:
            node = fs.getNode(name)
            if node.empty():
                return None
            if node.isSeq():
                return np.array([node.at(i).real() for i in range(node.size())], float)
            m = node.mat()
            return None if m is None else np.asarray(m, dtype=float)

        k = matrix("camera_matrix")
        d = matrix("distortion_coefficients")
        if d is None:
            d = matrix("dist_coeffs")
        if k is None or k.size != 9:
            raise ConfigError(f"{key}: {p}: missing or bad camera_matrix")
        if d is None:
            raise ConfigError(f"{key}: {p}: missing distortion_coefficients")
        wn, hn = fs.getNode("image_width"), fs.getNode("image_height")
        if not wn.empty() and not hn.empty():
            size = (int(wn.real()), int(hn.real()))
            if size != (width_px, height_px):
                raise ConfigError(f"{key}: {p}: calibrated at {size[0]} x {size[1]} px, the "
                                  f"camera renders {width_px} x {height_px} px")
    finally:
        fs.release()
    return k.reshape(3, 3), d.reshape(-1)



class InverseLensMap:
    """Ideal pinhole pixel of every image pixel, ``cv2.undistortPoints`` (iterated to
    convergence) on a 4 px grid and bilinear in between: the map is smooth (for the bundled lens
    its second derivative is below 1e-3 px/px^2, so the interpolation error is below 0.01 px)
    and the grid costs 1/16 of the per-pixel inversion (~20 ms instead of ~0.3 s)."""

    STEP = 4

    def __init__(self, k: np.ndarray, d: np.ndarray, w: int, h: int) -> None:
        s = self.STEP
        self.gx = np.arange(-s, w + 2 * s, s, dtype=np.float64)
        self.gy = np.arange(-s, h + 2 * s, s, dtype=np.float64)
        grid = np.stack(np.meshgrid(self.gx, self.gy), axis=-1).reshape(-1, 1, 2)
        ideal = cv2.undistortPoints(grid, k, d, R=None, P=k, criteria=UNDISTORT_CRITERIA)
        self.coarse = np.asarray(ideal, dtype=np.float64).reshape(len(self.gy), len(self.gx), 2)

    @staticmethod
    def _cells(x: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Grid cell index and fraction of each position ``x`` on the regular grid ``g``."""
        f = (x - g[0]) / (g[1] - g[0])
        i = np.clip(np.floor(f).astype(int), 0, len(g) - 2)
        return i, f - i

    def at(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        """(len(ys), len(xs), 2) ideal (col, row) of the image pixels ``xs`` x ``ys``."""
        iy, ty = self._cells(ys, self.gy)
        ix, tx = self._cells(xs, self.gx)
        c = self.coarse
        rows = c[iy] * (1.0 - ty)[:, None, None] + c[iy + 1] * ty[:, None, None]
        return np.asarray(rows[:, ix] * (1.0 - tx)[None, :, None]
                          + rows[:, ix + 1] * tx[None, :, None])


class Lens:
    """Intrinsics of the rendered camera and its drawing canvas. ``camera_matrix`` ``None``:
    the ideal pinhole ``fx = fy = f_px``, principal point at the image centre."""

    def __init__(self, f_px: float, width_px: int, height_px: int,
                 camera_matrix: np.ndarray | None = None,
                 dist_coeffs: Sequence[float] | np.ndarray | None = None) -> None:
        self.width_px, self.height_px = width_px, height_px
        self.f_px = float(f_px)
        self.cx = (width_px - 1) / 2.0
        self.cy = (height_px - 1) / 2.0
        self.camera_matrix = np.array(
            [[self.f_px, 0.0, self.cx], [0.0, self.f_px, self.cy], [0.0, 0.0, 1.0]]
        )
        self.dist = np.zeros(5)
        self.map_f: tuple[np.ndarray, np.ndarray] = (np.zeros((0, 0), np.float32),) * 2
        if camera_matrix is not None:
            self._set_lens(np.asarray(camera_matrix, dtype=float),
                           np.zeros(5) if dist_coeffs is None else dist_coeffs)
        else:
            self._set_render_canvas(self.camera_matrix, width_px, height_px)

    @property
    def distorted(self) -> bool:
        return self.remap is not None

    def _set_render_canvas(self, k: np.ndarray, w: int, h: int) -> None:
        """The ideal pinhole image everything is drawn in: the output image itself for an
        ideal lens, else a larger canvas that covers the distorted image's field of view."""
        self.rk = k
        self.rk_inv = np.linalg.inv(k)
        self.rw, self.rh = w, h
        self.rcx, self.rcy = float(k[0, 2]), float(k[1, 2])
        self.remap: tuple[np.ndarray, np.ndarray] | None = None
        self.remap_half: tuple[np.ndarray, np.ndarray] | None = None

    def _set_lens(self, k: np.ndarray, dist: Sequence[float] | np.ndarray) -> None:
        """A calibrated lens (OpenCV ``camera_matrix`` + ``distortion_coefficients``): the scene
        is drawn on an ideal pinhole canvas with the same ``fx, fy`` and then warped by
        ``cv2.remap`` with the exact inverse map (each output pixel's ray from
        ``cv2.undistortPoints``, iterated to convergence), so a straight edge's 50 % level
        lands where ``cv2.projectPoints`` with the distortion puts it."""
        d = np.asarray(dist, dtype=float).reshape(-1)
        if k.shape != (3, 3) or not np.all(np.isfinite(k)) or not (k[0, 0] > 0 and k[1, 1] > 0):
            raise ConfigError("camera.calibration_file: camera_matrix must be a finite 3x3 "
                              "matrix with fx, fy > 0")
        if d.size not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(d)):
            raise ConfigError("camera.calibration_file: distortion_coefficients must have 4, 5, "
                              f"8, 12 or 14 finite values (got {d.size})")
        self.camera_matrix = k.copy()
        self.dist = d.copy()
        self.f_px = float(k[0, 0])
        self.cx, self.cy = float(k[0, 2]), float(k[1, 2])
        w, h = self.width_px, self.height_px
        if not np.any(d):
            self._set_render_canvas(self.camera_matrix, w, h)
            return
        inverse = InverseLensMap(k, d, w, h)
        ideal = inverse.at(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        if not np.isfinite(ideal).all():
            raise ConfigError("camera.calibration_file: the distortion does not invert over "
                              "the image")
        lo = np.floor(ideal.reshape(-1, 2).min(axis=0)) - 2
        hi = np.ceil(ideal.reshape(-1, 2).max(axis=0)) + 2
        ox, oy = max(0.0, -lo[0]), max(0.0, -lo[1])
        cw = int(max(hi[0], w - 1) + ox) + 1
        ch = int(max(hi[1], h - 1) + oy) + 1
        if cw * ch > 4 * w * h:
            raise ConfigError("camera.calibration_file: the distortion needs an ideal canvas "
                              f"of {cw} x {ch} px to cover a {w} x {h} image (too strong)")
        rk = k.copy()
        rk[0, 2] += ox
        rk[1, 2] += oy
        self._set_render_canvas(rk, cw, ch)
        self.canvas_offset = (ox, oy)
        mx = (ideal[..., 0] + ox).astype(np.float32)
        my = (ideal[..., 1] + oy).astype(np.float32)
        self.remap = cv2.convertMaps(mx, my, cv2.CV_16SC2)
        self.map_f = (mx, my)
        # The ground is smooth at the image's scale (it is warped at half resolution anyway):
        # distort it at half the output resolution and upsample; only the box's region is
        # remapped at full resolution. Half-size pixel (xs, ys) sits at full-size
        # ((xs + 0.5) / s - 0.5) (cv2.resize's convention): its source is interpolated.
        wh, hh = (w + 1) // 2, (h + 1) // 2
        xs = (np.arange(wh) + 0.5) * (w / wh) - 0.5
        ys = (np.arange(hh) + 0.5) * (h / hh) - 0.5
        ideal_h = inverse.at(xs, ys)
        # sampled from the half-resolution canvas (the ground as warped): canvas pixel x sits
        # at (x + 0.5) s - 0.5 there
        shw, shh = (cw + 1) // 2, (ch + 1) // 2
        self.remap_half = cv2.convertMaps(
            ((ideal_h[..., 0] + ox + 0.5) * (shw / cw) - 0.5).astype(np.float32),
            ((ideal_h[..., 1] + oy + 0.5) * (shh / ch) - 0.5).astype(np.float32),
            cv2.CV_16SC2)

    def ideal_px(self, points_px: np.ndarray) -> np.ndarray:
        """Ideal pinhole pixels (same ``camera_matrix``, no distortion) of image pixels (n, 2)."""
        pts = np.asarray(points_px, dtype=float).reshape(-1, 1, 2)
        if not self.distorted:
            return pts.reshape(-1, 2).copy()
        out = cv2.undistortPoints(pts, self.camera_matrix, self.dist, R=None,
                                  P=self.camera_matrix, criteria=UNDISTORT_CRITERIA)
        return np.asarray(out, dtype=float).reshape(-1, 2)


    def project(self, pts: np.ndarray, r: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Image pixels (through the lens, ``cv2.projectPoints``) of world points (n, 3) with
        the world -> OpenCV-camera pose ``r``, ``t``."""
        rvec, _ = cv2.Rodrigues(r)
        img, _ = cv2.projectPoints(pts, rvec, t, self.camera_matrix, self.dist)
        return np.asarray(img, dtype=float).reshape(-1, 2)

    def canvas_to_image(self, pts: np.ndarray) -> np.ndarray:
        """Image pixels (through the lens) of canvas pixels (n, 2)."""
        xn = (pts[:, 0] - self.rk[0, 2]) / self.rk[0, 0]
        yn = (pts[:, 1] - self.rk[1, 2]) / self.rk[1, 1]
        obj = np.column_stack([xn, yn, np.ones(len(pts))])
        img, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), self.camera_matrix,
                                   self.dist)
        return np.asarray(img, dtype=float).reshape(-1, 2)

    def project_ideal(self, pts: np.ndarray, r: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Canvas pixels (ideal pinhole ``_rk``) of world points (n, 3)."""
        cam = pts @ r.T + t
        z = cam[:, 2:3]
        z = np.where(np.abs(z) < 1e-9, 1e-9, z)
        uv = (cam / z) @ self.rk.T
        return np.asarray(uv[:, :2], dtype=float)

    def image_window(self, roi: tuple[int, int, int, int], spread: int
                     ) -> tuple[int, int, int, int]:
        """The output pixels ``[c0, c1) x [r0, r1)`` that see the canvas region ``roi`` grown by
        ``spread`` (a blur kernel's reach): its border through the lens, with a margin."""
        # output pixels that see the (blurred) box: its region's border through the lens
        x0, y0 = roi[0] - spread - 2, roi[1] - spread - 2
        x1, y1 = roi[2] + spread + 2, roi[3] + spread + 2
        n = 16
        ts = np.linspace(0.0, 1.0, n)
        border = np.concatenate([
            np.column_stack([x0 + ts * (x1 - x0), np.full(n, y0)]),
            np.column_stack([x0 + ts * (x1 - x0), np.full(n, y1)]),
            np.column_stack([np.full(n, x0), y0 + ts * (y1 - y0)]),
            np.column_stack([np.full(n, x1), y0 + ts * (y1 - y0)]),
        ])
        img_px = self.canvas_to_image(border)
        c0 = max(math.floor(img_px[:, 0].min()) - 2, 0)
        r0 = max(math.floor(img_px[:, 1].min()) - 2, 0)
        c1 = min(math.ceil(img_px[:, 0].max()) + 3, self.width_px)
        r1 = min(math.ceil(img_px[:, 1].max()) + 3, self.height_px)
        return c0, r0, c1, r1
