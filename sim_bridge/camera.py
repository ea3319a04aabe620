"""The synthetic downward camera: renders the AGV on a textured ground into mono8 frames.

Conventions (docs/reference/math.md, section 1; docs/reference/wire.md): world NED, body FRD, camera
axes = body axes rotated by the mount (x forward, y right, z down = optical axis). Ideal
pinhole: ``fx = fy = focal_length_m / pixel_size_m``, principal point at the image centre
``cx = (width_px - 1) / 2``, ``cy = (height_px - 1) / 2`` (pixel centres at integer
``(col, row)``, OpenCV's convention). With "forward = up" in the image:
``col = cx + n_px``, ``row = cy - u_px``, ``u = lambda x_c / z_c``, ``n = lambda y_c / z_c``.

OpenCV's camera frame is x right, y down, z forward; ours maps to it as
``x_cv = y_c``, ``y_cv = -x_c``, ``z_cv = z_c`` (a rotation, det +1), so ``cv2.projectPoints``
with ``K = [[f, 0, cx], [0, f, cy], [0, 0, 1]]`` gives exactly the mapping above.

This is an independent implementation of the geometry (it never imports the companion), so a
geometry bug on either side shows up as a failed flight instead of cancelling out.

Rendering, per frame (about 1.3 ms at 1000 x 1000 on the dev machine, see bench/sim_step.py):
the ground plane (a periodic procedural texture, intensities ~40..150, precomputed once) is
warped into the image by its homography (``cv2.warpPerspective``, INTER_LINEAR, BORDER_WRAP,
at half resolution, then upsampled);
then the box's silhouette (dark, 30) and its top (rectangle: 235; aruco: white with the marker)
are drawn with analytic anti-aliasing (coverage ``clip(0.5 + signed distance to the edge, 0, 1)``
per pixel), so an edge's 50 % level lies exactly on the projected edge and detected corners
land where the projection puts them.
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from sim_bridge import ConfigError
from sim_bridge.camera_model import line_kernel
from sim_bridge.physics.agv import AgvState

__all__ = ["Camera", "RenderedFrame", "read_calibration"]

log = logging.getLogger(__name__)

# Intensities (mono8).
GROUND_MIN, GROUND_MAX = 40, 150
SKY_LEVEL = 150
BOX_SIDE_LEVEL = 30
TOP_LEVEL = 235
ARUCO_WHITE, ARUCO_BLACK = 245, 10

_NEAR_M = 0.05  # points closer than this along the optical axis are not drawn
_GROUND_TEXEL_M = 0.01  # ground texture resolution
_GROUND_TEX_PX = 1024  # period of the ground texture: 10.24 m
_GROUND_PAD_PX = 512  # the stored texture repeats the period by this much on every side
_SKY_DZ = 0.08  # rays whose world-down component (|ray| ~ 1..1.6) is below this show sky
_TOP_TEXEL_M = 5.0e-4  # finest texel of the ArUco top texture (mip level 0)
_MIP_LEVELS = 7  # 0.5 mm .. 32 mm texels
_NOISE_BANK = 4
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
_MAX_FULL_KERNEL_PX = 11  # cv2.filter2D switches to a (16x slower) DFT above this

# Our camera axes (x fwd, y right, z down) -> OpenCV's (x right, y down, z fwd = optical axis).
_CV_FROM_CAM = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


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
        bases.append(Path(__file__).resolve().parent.parent)
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


@dataclass(frozen=True, eq=False)
class RenderedFrame:
    """One rendered frame and the truth about it.

    ``image``: (H, W) uint8 mono8, row 0 at the top. ``corners_px``: (4, 2) true projection
    ``(col, row)`` of the target points before noise, whether or not they are in the image:
    rectangle: the AGV top's corners, aruco: the marker's corners in cv2.aruco's order; both in
    the AGV frame order front-left, front-right, rear-right, rear-left. ``target_in_image``: all
    target points in front of the camera and inside the image, the top facing the camera and not
    occluded. ``top_corners_px``: (4, 2) the AGV top's corners (same order) for either pattern.
    """

    image: np.ndarray
    corners_px: np.ndarray
    target_in_image: bool
    top_corners_px: np.ndarray


@functools.lru_cache(maxsize=4)
def _ground_texture(seed: int) -> np.ndarray:
    """A periodic (seamless) procedural ground, uint8 in [40, 150]: 1/f noise plus 1 m tiles."""
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
    tex = np.clip(np.rint(img), GROUND_MIN, GROUND_MAX).astype(np.uint8)
    out = np.ascontiguousarray(np.pad(tex, _GROUND_PAD_PX, mode="wrap"))
    out.setflags(write=False)  # shared between cameras with the same seed
    return out


def _clip_polygon_halfplane(poly: np.ndarray, a: np.ndarray, c: float) -> np.ndarray:
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


class Camera:
    """Renders what the UAV's camera sees of the AGV (see the module docstring).

    Constructor arguments are plain values (metres, radians, pixels); see ``config/paper.toml``
    ``[camera]``, ``[target]``, ``[sim.camera]``. ``render`` is the only per-frame call.
    """

    def __init__(
        self,
        focal_length_m: float,
        pixel_size_m: float,
        width_px: int,
        height_px: int,
        mount_rpy_rad: Sequence[float] = (0.0, 0.0, 0.0),
        mount_offset_m: Sequence[float] = (0.0, 0.0, 0.0),
        target_length_m: float = 0.5,
        target_width_m: float = 0.4,
        target_height_m: float = 0.3,
        pattern: str = "rectangle",
        aruco_dictionary: str = "DICT_4X4_50",
        aruco_id: int = 7,
        aruco_size_m: float = 0.4,
        noise_std: float = 0.0,
        blur_px: float = 0.0,
        seed: int = 0,
        camera_matrix: np.ndarray | None = None,
        dist_coeffs: Sequence[float] | np.ndarray | None = None,
    ) -> None:
        for name, v in (
            ("camera.focal_length_m", focal_length_m),
            ("camera.pixel_size_m", pixel_size_m),
            ("target.length_m", target_length_m),
            ("target.width_m", target_width_m),
            ("target.height_m", target_height_m),
            ("target.aruco_size_m", aruco_size_m),
        ):
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"{name}: must be a finite number > 0, got {v}")
        for name, iv in (("camera.width_px", width_px), ("camera.height_px", height_px)):
            if not (isinstance(iv, int) and 2 <= iv <= 65535):
                raise ConfigError(f"{name}: must be an integer in 2..65535, got {iv!r}")
        if pattern not in ("rectangle", "aruco"):
            raise ConfigError(f"target.pattern: must be 'rectangle' or 'aruco', got {pattern!r}")
        if not (math.isfinite(noise_std) and noise_std >= 0):
            raise ConfigError(f"sim.camera.noise_std: must be >= 0, got {noise_std}")
        if not (math.isfinite(blur_px) and blur_px >= 0):
            raise ConfigError(f"sim.camera.blur_px: must be >= 0, got {blur_px}")
        if len(mount_rpy_rad) != 3 or len(mount_offset_m) != 3:
            raise ConfigError("camera.mount_rpy_rad / camera.mount_offset_m: need 3 values each")
        if pattern == "aruco" and aruco_size_m > min(target_length_m, target_width_m) + 1e-12:
            raise ConfigError(
                f"target.aruco_size_m: {aruco_size_m} m does not fit on the "
                f"{target_length_m} x {target_width_m} m top"
            )

        self.width_px = width_px
        self.height_px = height_px
        self.focal_length_m = float(focal_length_m)
        self.pixel_size_m = float(pixel_size_m)
        self.f_px = self.focal_length_m / self.pixel_size_m
        self.cx = (width_px - 1) / 2.0
        self.cy = (height_px - 1) / 2.0
        self.camera_matrix = np.array(
            [[self.f_px, 0.0, self.cx], [0.0, self.f_px, self.cy], [0.0, 0.0, 1.0]]
        )
        self._dist = np.zeros(5)
        if camera_matrix is not None:
            self._set_lens(np.asarray(camera_matrix, dtype=float),
                           np.zeros(5) if dist_coeffs is None else dist_coeffs)
        else:
            self._set_render_canvas(self.camera_matrix, width_px, height_px)
        r, p, y = (float(v) for v in mount_rpy_rad)
        # Camera axes -> body axes (ZYX: Rz(yaw) Ry(pitch) Rx(roll)).
        self.r_body_cam = Rotation.from_euler("ZYX", [y, p, r]).as_matrix()
        self.mount_offset_m = np.array(mount_offset_m, dtype=float)
        self.length_m = float(target_length_m)
        self.width_m = float(target_width_m)
        self.height_m = float(target_height_m)
        self.pattern = pattern
        self.aruco_size_m = float(aruco_size_m)
        self.noise_std = float(noise_std)
        self.blur_px = float(blur_px)
        self._rng = np.random.default_rng(seed)

        half_l, half_w = self.length_m / 2.0, self.width_m / 2.0
        # AGV-frame (x fwd, y right, z down) top corners: FL, FR, RR, RL.
        self._top_local = np.array(
            [
                [half_l, -half_w, 0.0],
                [half_l, half_w, 0.0],
                [-half_l, half_w, 0.0],
                [-half_l, -half_w, 0.0],
            ]
        )
        self._bottom_local = self._top_local + np.array([0.0, 0.0, self.height_m])
        hs = self.aruco_size_m / 2.0
        # Marker mounted centred on the top, its image "up" towards the AGV front: cv2.aruco's
        # corner order (TL, TR, BR, BL of the marker image) = FL, FR, RR, RL.
        self._marker_local = np.array(
            [[hs, -hs, 0.0], [hs, hs, 0.0], [-hs, hs, 0.0], [-hs, -hs, 0.0]]
        )
        self._ground_tex = _ground_texture(seed)
        self._top_mips: list[np.ndarray] = []
        self._top_texel_m: list[float] = []
        if pattern == "aruco":
            self._build_aruco_top(aruco_dictionary, aruco_id)
        self._noise_bank: list[np.ndarray] = []
        if self.noise_std > 0:
            pad = 64
            for _ in range(_NOISE_BANK):
                noise = self._rng.normal(0.0, self.noise_std, (height_px + pad, width_px + pad))
                self._noise_bank.append(np.rint(noise).astype(np.int16))

    # ------------------------------------------------------------------------------ lens
    @property
    def distorted(self) -> bool:
        return self._remap is not None

    def _set_render_canvas(self, k: np.ndarray, w: int, h: int) -> None:
        """The ideal pinhole image everything is drawn in: the output image itself for an
        ideal lens, else a larger canvas that covers the distorted image's field of view."""
        self._rk = k
        self._rk_inv = np.linalg.inv(k)
        self._rw, self._rh = w, h
        self._rcx, self._rcy = float(k[0, 2]), float(k[1, 2])
        self._remap: tuple[np.ndarray, np.ndarray] | None = None
        self._remap_half: tuple[np.ndarray, np.ndarray] | None = None

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
        self._dist = d.copy()
        self.f_px = float(k[0, 0])
        self.cx, self.cy = float(k[0, 2]), float(k[1, 2])
        w, h = self.width_px, self.height_px
        if not np.any(d):
            self._set_render_canvas(self.camera_matrix, w, h)
            return
        inverse = _InverseLensMap(k, d, w, h)
        ideal = inverse.at(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        if not np.all(np.isfinite(ideal)):
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
        self._canvas_offset = (ox, oy)
        mx = (ideal[..., 0] + ox).astype(np.float32)
        my = (ideal[..., 1] + oy).astype(np.float32)
        self._remap = cv2.convertMaps(mx, my, cv2.CV_16SC2)
        self._map_f = (mx, my)
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
        self._remap_half = cv2.convertMaps(
            ((ideal_h[..., 0] + ox + 0.5) * (shw / cw) - 0.5).astype(np.float32),
            ((ideal_h[..., 1] + oy + 0.5) * (shh / ch) - 0.5).astype(np.float32),
            cv2.CV_16SC2)

    def ideal_px(self, points_px: np.ndarray) -> np.ndarray:
        """Ideal pinhole pixels (same ``camera_matrix``, no distortion) of image pixels (n, 2)."""
        pts = np.asarray(points_px, dtype=float).reshape(-1, 1, 2)
        if not self.distorted:
            return pts.reshape(-1, 2).copy()
        out = cv2.undistortPoints(pts, self.camera_matrix, self._dist, R=None,
                                  P=self.camera_matrix, criteria=_UNDISTORT_CRITERIA)
        return np.asarray(out, dtype=float).reshape(-1, 2)

    # ------------------------------------------------------------------------------ geometry
    def _build_aruco_top(self, dictionary: str, marker_id: int) -> None:
        try:
            dict_id = getattr(cv2.aruco, dictionary)
        except AttributeError as e:
            raise ConfigError(f"target.aruco_dictionary: unknown {dictionary!r}") from e
        aruco_dict = cv2.aruco.getPredefinedDictionary(dict_id)
        n_markers = aruco_dict.bytesList.shape[0]
        if not (isinstance(marker_id, int) and 0 <= marker_id < n_markers):
            raise ConfigError(f"target.aruco_id: must be in 0..{n_markers - 1}, got {marker_id!r}")
        cells = aruco_dict.markerSize + 2  # one black border cell each side
        step = 2 ** (_MIP_LEVELS - 1)
        # Texels per cell: a multiple of `step`, so every cell edge (the marker's outline
        # included) falls on a texel boundary at every mip level.
        k = step * max(1, round(self.aruco_size_m / cells / _TOP_TEXEL_M / step))
        side = cells * k  # marker side in texels
        texel = self.aruco_size_m / side
        marker = cv2.aruco.generateImageMarker(aruco_dict, marker_id, side, borderBits=1)

        # Texture centred on the marker, covering the whole top plus a margin; its sides are
        # multiples of 2**(levels-1) texels so every mip level halves exactly and keeps the
        # marker centre at the texture centre.
        def _span(m: float) -> int:
            margin = math.ceil((m / texel - side) / 2.0) + 2
            return int(side + 2 * (-(-margin // step) * step))

        rows, cols = _span(self.length_m), _span(self.width_m)
        tex: np.ndarray = np.full((rows, cols), ARUCO_WHITE, np.uint8)
        r0, c0 = (rows - side) // 2, (cols - side) // 2
        tex[r0 : r0 + side, c0 : c0 + side] = np.where(marker > 127, ARUCO_WHITE, ARUCO_BLACK)
        for level in range(_MIP_LEVELS):
            self._top_mips.append(tex)
            self._top_texel_m.append(texel * 2**level)
            tex = cv2.resize(
                tex, (tex.shape[1] // 2, tex.shape[0] // 2), interpolation=cv2.INTER_AREA
            )

    def pose(
        self, uav_pos_ned_m: np.ndarray, uav_q_wxyz: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """World -> OpenCV-camera rotation ``R`` (3, 3) and translation ``t`` (3,):
        ``X_cv = R X_world + t``. ``uav_q_wxyz`` rotates body vectors into NED (PX4 attitude)."""
        q = np.asarray(uav_q_wxyz, dtype=float)
        r_wb = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()  # scipy: x, y, z, w
        r_wc = r_wb @ self.r_body_cam
        c_w = np.asarray(uav_pos_ned_m, dtype=float) + r_wb @ self.mount_offset_m
        r_cv_w = _CV_FROM_CAM @ r_wc.T
        return r_cv_w, -r_cv_w @ c_w

    def project(
        self, points_ned_m: np.ndarray, uav_pos_ned_m: np.ndarray, uav_q_wxyz: np.ndarray
    ) -> np.ndarray:
        """Pixel ``(col, row)`` (n, 2) of world points (n, 3) with ``cv2.projectPoints``."""
        r, t = self.pose(uav_pos_ned_m, uav_q_wxyz)
        return self._project(np.asarray(points_ned_m, dtype=float).reshape(-1, 3), r, t)

    def _project(self, pts: np.ndarray, r: np.ndarray, t: np.ndarray) -> np.ndarray:
        rvec, _ = cv2.Rodrigues(r)
        img, _ = cv2.projectPoints(pts, rvec, t, self.camera_matrix, self._dist)
        return np.asarray(img, dtype=float).reshape(-1, 2)

    def agv_points(self, agv: AgvState) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World NED (4, 3) top corners, bottom corners and marker corners (FL, FR, RR, RL)."""
        c, s = math.cos(agv.yaw_rad), math.sin(agv.yaw_rad)
        rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        p = agv.pos_ned_m
        return (
            self._top_local @ rz.T + p,
            self._bottom_local @ rz.T + p,
            self._marker_local @ rz.T + p,
        )

    # ------------------------------------------------------------------------------ rendering
    def render(
        self,
        uav_pos_ned_m: np.ndarray,
        uav_q_wxyz: np.ndarray,
        agv: AgvState,
        occluded: bool = False,
        *,
        uav_vel_ned_m_s: np.ndarray | None = None,
        uav_rates_frd_rad_s: np.ndarray | None = None,
        exposure_s: float = 0.0,
    ) -> RenderedFrame:
        """Render the frame seen from the UAV pose (NED m, quaternion w,x,y,z body -> NED) at the
        exposure middle. With ``exposure_s > 0`` and the UAV's velocity (NED) and body rates
        (FRD), the frame is blurred along the target's image motion over the exposure."""
        r, t = self.pose(uav_pos_ned_m, uav_q_wxyz)
        c_w = -r.T @ t  # camera centre, NED
        top, bottom, marker = self.agv_points(agv)
        pts = np.vstack([top, bottom, marker])
        px = self._project(pts, r, t)  # image pixels (through the lens)
        ideal = self._project_ideal(pts, r, t) if self.distorted else px  # canvas pixels
        z_cv = pts @ r[2] + t[2]
        top_px, marker_px = px[0:4], px[8:12]

        ground_z = float(agv.pos_ned_m[2]) + self.height_m
        top_faces_camera = c_w[2] < agv.pos_ned_m[2]
        motion = None
        if exposure_s > 0 and uav_vel_ned_m_s is not None and uav_rates_frd_rad_s is not None:
            motion = self.image_motion_px(uav_pos_ned_m, uav_q_wxyz, uav_vel_ned_m_s,
                                          uav_rates_frd_rad_s, agv, exposure_s)
        if self._remap is not None:
            image = self._render_through_lens(r, t, c_w, ground_z, ideal[:8], z_cv[:8],
                                              pts[:8], top_faces_camera, agv, occluded, motion)
        else:
            image = self._render_ground(r, c_w, ground_z)
            hull_roi: tuple[int, int, int, int] | None = None
            if not occluded:
                hull_roi = self._draw_box(image, ideal[:8], z_cv[:8], pts[:8], r, t,
                                          top_faces_camera, agv)
            if motion is not None:
                image = self._motion_blur(image, motion, hull_roi)

        target_px = marker_px if self.pattern == "aruco" else top_px
        target_ideal = ideal[8:12] if self.pattern == "aruco" else ideal[0:4]
        target_z = z_cv[8:12] if self.pattern == "aruco" else z_cv[0:4]
        w, h = self.width_px, self.height_px
        inside = bool(
            np.all(target_z > _NEAR_M)
            and np.all(target_px[:, 0] >= -0.5)
            and np.all(target_px[:, 0] <= w - 0.5)
            and np.all(target_px[:, 1] >= -0.5)
            and np.all(target_px[:, 1] <= h - 0.5)
            # a distortion polynomial can fold far-off points back into the image
            and np.all(target_ideal[:, 0] >= -0.5)
            and np.all(target_ideal[:, 0] <= self._rw - 0.5)
            and np.all(target_ideal[:, 1] >= -0.5)
            and np.all(target_ideal[:, 1] <= self._rh - 0.5)
        )
        in_image = inside and bool(top_faces_camera) and not occluded

        if self.blur_px > 0:
            image = cv2.GaussianBlur(image, (0, 0), self.blur_px)
        if self._noise_bank:
            bank = self._noise_bank[int(self._rng.integers(len(self._noise_bank)))]
            dy, dx = (int(v) for v in self._rng.integers(0, 64, size=2))
            image = cv2.add(image, bank[dy : dy + h, dx : dx + w], dtype=cv2.CV_8U)
        image.setflags(write=False)
        return RenderedFrame(
            image=image,
            corners_px=target_px.copy(),
            target_in_image=in_image,
            top_corners_px=top_px.copy(),
        )

    def _render_through_lens(
        self,
        r: np.ndarray,
        t: np.ndarray,
        c_w: np.ndarray,
        ground_z: float,
        box_px: np.ndarray,
        box_z: np.ndarray,
        box_pts: np.ndarray,
        top_faces_camera: bool,
        agv: AgvState,
        occluded: bool,
        motion: np.ndarray | None,
    ) -> np.ndarray:
        """The scene through the lens without a full-resolution canvas: the ground (smooth at
        the image's scale, warped at half resolution anyway) is distorted at half the output
        resolution and upsampled; only the box's region is drawn on the ideal canvas at full
        resolution (``box_px``: its corners in canvas pixels) and remapped at full resolution.
        Motion blur: the line kernel on the box's canvas region, half of it on the ground."""
        assert self._remap is not None and self._remap_half is not None
        w, h = self.width_px, self.height_px
        small = self._render_ground(r, c_w, ground_z, half=True)
        half = cv2.remap(small, self._remap_half[0], self._remap_half[1], cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)
        k_full = None if motion is None else line_kernel(float(motion[0]), float(motion[1]))
        if motion is not None:
            k_half = line_kernel(float(motion[0]) / 2, float(motion[1]) / 2)
            if k_half is not None:
                half = cv2.filter2D(half, -1, k_half, borderType=cv2.BORDER_REFLECT)
        out = cv2.resize(half, (w, h), interpolation=cv2.INTER_LINEAR)
        if occluded or not np.all(box_z > _NEAR_M):
            if not occluded and not np.all(box_z <= _NEAR_M):  # rare: the camera at the box
                canvas = self._render_ground(r, c_w, ground_z)
                self._draw_box(canvas, box_px, box_z, box_pts, r, t, top_faces_camera, agv)
                return cv2.remap(canvas, self._remap[0], self._remap[1], cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_REPLICATE)
            return out
        hull = box_px[cv2.convexHull(box_px.astype(np.float32), returnPoints=False).ravel()]
        roi = _roi(hull, self._rw, self._rh)
        if roi is None:
            return out
        spread = 0 if k_full is None else k_full.shape[0] // 2
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
        img_px = self._canvas_to_image(border)
        c0 = max(math.floor(img_px[:, 0].min()) - 2, 0)
        r0 = max(math.floor(img_px[:, 1].min()) - 2, 0)
        c1 = min(math.ceil(img_px[:, 0].max()) + 3, w)
        r1 = min(math.ceil(img_px[:, 1].max()) + 3, h)
        if c1 <= c0 or r1 <= r0:
            return out
        # the canvas pixels those output pixels sample, plus the kernel's reach: upsample the
        # ground there exactly as cv2.resize would, draw the box, blur
        mx, my = self._map_f[0][r0:r1, c0:c1], self._map_f[1][r0:r1, c0:c1]
        pad = spread + 2
        px0 = max(math.floor(float(mx.min())) - pad, 0)
        py0 = max(math.floor(float(my.min())) - pad, 0)
        px1 = min(math.ceil(float(mx.max())) + pad + 1, self._rw)
        py1 = min(math.ceil(float(my.max())) + pad + 1, self._rh)
        sx, sy = small.shape[1] / self._rw, small.shape[0] / self._rh
        up = np.array([[sx, 0.0, (px0 + 0.5) * sx - 0.5], [0.0, sy, (py0 + 0.5) * sy - 0.5]])
        patch = cv2.warpAffine(small, up, (px1 - px0, py1 - py0),
                               flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_REPLICATE)
        canvas = np.empty((self._rh, self._rw), np.uint8)  # only the patch is ever read
        canvas[py0:py1, px0:px1] = patch
        self._draw_box(canvas, box_px, box_z, box_pts, r, t, top_faces_camera, agv)
        if k_full is not None:
            canvas[py0:py1, px0:px1] = cv2.filter2D(canvas[py0:py1, px0:px1], -1, k_full,
                                                    borderType=cv2.BORDER_REFLECT)
        out[r0:r1, c0:c1] = cv2.remap(canvas[py0:py1, px0:px1], mx - px0, my - py0,
                                      cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return out

    def _canvas_to_image(self, pts: np.ndarray) -> np.ndarray:
        """Image pixels (through the lens) of canvas pixels (n, 2)."""
        xn = (pts[:, 0] - self._rk[0, 2]) / self._rk[0, 0]
        yn = (pts[:, 1] - self._rk[1, 2]) / self._rk[1, 1]
        obj = np.column_stack([xn, yn, np.ones(len(pts))])
        img, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), self.camera_matrix,
                                   self._dist)
        return np.asarray(img, dtype=float).reshape(-1, 2)

    def _project_ideal(self, pts: np.ndarray, r: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Canvas pixels (ideal pinhole ``_rk``) of world points (n, 3)."""
        cam = pts @ r.T + t
        z = cam[:, 2:3]
        z = np.where(np.abs(z) < 1e-9, 1e-9, z)
        uv = (cam / z) @ self._rk.T
        return np.asarray(uv[:, :2], dtype=float)

    def image_motion_px(
        self,
        uav_pos_ned_m: np.ndarray,
        uav_q_wxyz: np.ndarray,
        uav_vel_ned_m_s: np.ndarray,
        uav_rates_frd_rad_s: np.ndarray,
        agv: AgvState,
        exposure_s: float,
    ) -> np.ndarray | None:
        """Canvas-pixel motion ``(dcol, drow)`` of the target's centre (or, when it is behind
        the camera, of the ground point on the optical axis) from the start to the end of the
        exposure, the UAV and the AGV moving at constant velocity and body rates around the
        exposure middle. ``None`` when neither point is in front of the camera."""
        half = 0.5 * exposure_s
        q = np.asarray(uav_q_wxyz, dtype=float)
        rot = Rotation.from_quat([q[1], q[2], q[3], q[0]])
        w = np.asarray(uav_rates_frd_rad_s, dtype=float)
        v = np.asarray(uav_vel_ned_m_s, dtype=float)
        p0 = np.asarray(uav_pos_ned_m, dtype=float)
        r_mid, t_mid = self.pose(p0, q)
        point = agv.pos_ned_m + np.array([0.0, 0.0, 0.0])
        if float(point @ r_mid[2] + t_mid[2]) <= _NEAR_M:
            axis = r_mid[2]  # optical axis in NED
            c_w = -r_mid.T @ t_mid
            depth = float(agv.pos_ned_m[2]) + self.height_m - float(c_w[2])
            if axis[2] <= 1e-3 or depth <= 0:
                return None
            point = c_w + axis * depth / axis[2]
        ends = []
        for sign in (-1.0, 1.0):
            rq = (rot * Rotation.from_rotvec(sign * half * w)).as_quat()  # body rates: right
            qs = np.array([rq[3], rq[0], rq[1], rq[2]])
            r_s, t_s = self.pose(p0 + sign * half * v, qs)
            pt = point + sign * half * agv.vel_ned_m_s
            if float(pt @ r_s[2] + t_s[2]) <= _NEAR_M:
                return None
            ends.append(self._project_ideal(pt[None, :], r_s, t_s)[0])
        return np.asarray(ends[1] - ends[0], dtype=float)

    def _motion_blur(self, image: np.ndarray, motion_px: np.ndarray,
                     roi: tuple[int, int, int, int] | None) -> np.ndarray:
        """Blur by the straight motion ``motion_px`` (a line kernel, ``camera_model``). Kernels
        above 11 px (where cv2.filter2D turns to a slow DFT) blur the frame at half resolution
        and the target's box region (``roi``) at full resolution."""
        k = line_kernel(float(motion_px[0]), float(motion_px[1]))
        if k is None:
            return image
        if k.shape[0] <= _MAX_FULL_KERNEL_PX:
            return cv2.filter2D(image, -1, k, borderType=cv2.BORDER_REFLECT)
        hw, hh = (self._rw + 1) // 2, (self._rh + 1) // 2
        small = cv2.resize(image, (hw, hh), interpolation=cv2.INTER_AREA)
        k2 = line_kernel(float(motion_px[0]) / 2, float(motion_px[1]) / 2)
        if k2 is not None:
            small = cv2.filter2D(small, -1, k2, borderType=cv2.BORDER_REFLECT)
        out = cv2.resize(small, (self._rw, self._rh), interpolation=cv2.INTER_LINEAR)
        if roi is not None:
            m = k.shape[0] // 2
            x0, y0 = max(roi[0] - 2 * m, 0), max(roi[1] - 2 * m, 0)
            x1, y1 = min(roi[2] + 2 * m, self._rw), min(roi[3] + 2 * m, self._rh)
            sharp = cv2.filter2D(image[y0:y1, x0:x1], -1, k, borderType=cv2.BORDER_REFLECT)
            out[y0 + m:y1 - m, x0 + m:x1 - m] = sharp[m:sharp.shape[0] - m, m:sharp.shape[1] - m]
        return out

    def _render_ground(self, r: np.ndarray, c_w: np.ndarray, ground_z: float,
                       half: bool = False) -> np.ndarray:
        """The ground (and sky) on the canvas, or with ``half`` at half its resolution (the
        resolution it is warped at)."""
        w, h = self._rw, self._rh
        # Ray of pixel p = (col, row, 1) in NED: d = A p with A = R^T K^-1.
        a = r.T @ self._rk_inv
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
        small = cv2.warpPerspective(
            self._ground_tex,
            g @ to_half,
            (wh, hh),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_WRAP,
        )
        image = small if half else cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
        corners = np.array([[0, 0, 1], [w - 1, 0, 1], [w - 1, h - 1, 1], [0, h - 1, 1]], float)
        dz = corners @ a[2]
        if np.all(dz > _SKY_DZ):
            return image
        # Part of the view is at or above the horizon: paint it as sky.
        rect = corners[:, :2] + 0.5 * np.sign(corners[:, :2] - [self._rcx, self._rcy])
        sky = _clip_polygon_halfplane(rect, -a[2, :2], _SKY_DZ - float(a[2, 2]))
        if len(sky) >= 3:
            if half:
                sky = (sky + 0.5) * np.array([sx, sy]) - 0.5
            cv2.fillPoly(image, [np.round(sky * 16).astype(np.int32)], SKY_LEVEL, cv2.LINE_8, 4)
        return image

    def _draw_box(
        self,
        image: np.ndarray,
        px: np.ndarray,
        z_cv: np.ndarray,
        pts: np.ndarray,
        r: np.ndarray,
        t: np.ndarray,
        top_faces_camera: bool,
        agv: AgvState,
    ) -> tuple[int, int, int, int] | None:
        """Draw the box (``px``: its 8 corners in canvas pixels); returns the drawn ROI."""
        if np.all(z_cv > _NEAR_M):
            # The box's silhouette (convex hull of its 8 corners) is dark; the top is drawn in
            # the same pass with coverages that partition each pixel: ground (1 - h), sides
            # (h - t), top t. Compositing the top over a separately anti-aliased silhouette
            # would leak ground into the shared edges and bias them by ~0.1 px.
            idx = cv2.convexHull(px.astype(np.float32), returnPoints=False).ravel()
            hull = px[idx]
            roi = _roi(hull, self._rw, self._rh)
            if roi is None:
                return None
            h_cov = _coverage(hull, roi)
            x0, y0, x1, y1 = roi
            bg = image[y0:y1, x0:x1].astype(np.float32)
            out = bg + (np.float32(BOX_SIDE_LEVEL) - bg) * h_cov
            if top_faces_camera:
                t_cov = np.minimum(_coverage(px[:4], roi), h_cov)
                if self.pattern == "rectangle":
                    fg: float | np.ndarray = float(TOP_LEVEL)
                else:
                    fg = self._aruco_top(roi, r, t, agv, float(np.mean(z_cv[:4])))
                out += (fg - np.float32(BOX_SIDE_LEVEL)) * t_cov
            image[y0:y1, x0:x1] = (out + 0.5).astype(np.uint8)
            return roi
        if np.all(z_cv <= _NEAR_M):
            return None
        # The box crosses the near plane (the camera is at/inside it): clip each visible face in
        # the camera frame and fill it plainly. Rare; no sub-pixel care needed.
        cam = pts @ r.T + t
        faces = [[4, 5, 6, 7]] + [[i, (i + 1) % 4, (i + 1) % 4 + 4, i + 4] for i in range(4)]
        if top_faces_camera:
            faces.append([0, 1, 2, 3])
        for k, face in enumerate(faces):
            poly = _clip_polygon_halfplane(cam[face], np.array([0.0, 0.0, 1.0]), -_NEAR_M)
            if len(poly) < 3:
                continue
            proj = (self._rk @ poly.T).T
            uv = proj[:, :2] / proj[:, 2:3]
            level = TOP_LEVEL if (top_faces_camera and k == len(faces) - 1) else BOX_SIDE_LEVEL
            uv = np.clip(uv, -1e5, 1e5)
            cv2.fillPoly(image, [np.round(uv * 16).astype(np.int32)], level, cv2.LINE_8, 4)
        return None

    def _aruco_top(
        self,
        roi: tuple[int, int, int, int],
        r: np.ndarray,
        t: np.ndarray,
        agv: AgvState,
        depth_m: float,
    ) -> np.ndarray:
        """The top's texture (white with the marker) warped onto the ROI, float32 (h, w)."""
        x0, y0, x1, y1 = roi
        # Mip level whose texel is the smallest at or above the pixel's footprint on the top:
        # bilinear sampling then spreads each edge over 1..2 pixels, like a camera's pixel
        # (box) integration, so interpolating between pixels finds the edge where it is.
        # (Sharper, minified texels give a sub-pixel ramp that biases edges by up to ~0.2 px.)
        footprint_m = depth_m / float(self._rk[0, 0])
        ratio = max(footprint_m / self._top_texel_m[0], 1.0)
        level = min(math.ceil(math.log2(ratio) - 1e-9), _MIP_LEVELS - 1)
        tex = self._top_mips[level]
        texel = self._top_texel_m[level]
        rows, cols = tex.shape
        # Texel (tc, tr) centre -> top-local (a fwd, b right): a = (rows/2 - tr - 0.5) texel,
        # b = (tc + 0.5 - cols/2) texel. Top-local (a, b, 1) -> image: the plane homography
        # K [R rz e_x, R rz e_y, R p + t].
        c, s = math.cos(agv.yaw_rad), math.sin(agv.yaw_rad)
        gmat = self._rk @ np.column_stack(
            [r @ np.array([c, s, 0.0]), r @ np.array([-s, c, 0.0]), r @ agv.pos_ned_m + t]
        )
        s_map = np.array(
            [
                [0.0, -texel, (rows / 2 - 0.5) * texel],
                [texel, 0.0, (0.5 - cols / 2) * texel],
                [0.0, 0.0, 1.0],
            ]
        )
        shift = np.array([[1.0, 0.0, x0], [0.0, 1.0, y0], [0.0, 0.0, 1.0]])
        m_inv = np.linalg.inv(gmat @ s_map) @ shift  # ROI pixel -> texel
        fg = cv2.warpPerspective(
            tex,
            m_inv,
            (x1 - x0, y1 - y0),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_REPLICATE,
        )
        return fg.astype(np.float32)


class _InverseLensMap:
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
        ideal = cv2.undistortPoints(grid, k, d, R=None, P=k, criteria=_UNDISTORT_CRITERIA)
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


def _roi(poly: np.ndarray, w: int, h: int) -> tuple[int, int, int, int] | None:
    """Integer pixel box [x0, x1) x [y0, y1) covering a polygon's anti-aliased footprint."""
    x0 = max(math.floor(poly[:, 0].min()) - 1, 0)
    y0 = max(math.floor(poly[:, 1].min()) - 1, 0)
    x1 = min(math.ceil(poly[:, 0].max()) + 2, w)
    y1 = min(math.ceil(poly[:, 1].max()) + 2, h)
    if x1 <= x0 or y1 <= y0:
        return None
    return x0, y0, x1, y1


def _coverage(poly: np.ndarray, roi: tuple[int, int, int, int]) -> np.ndarray:
    """Approximate pixel coverage (float32 (h, w) in [0, 1]) of a convex polygon in the ROI:
    ``clip(0.5 + min_i signed_distance_i, 0, 1)`` over its edges (pixel centres at integers)."""
    x0, y0, x1, y1 = roi
    p = np.asarray(poly, dtype=float)
    area2 = float(np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1]))
    sign = 1.0 if area2 > 0 else -1.0
    cols = np.arange(x0, x1, dtype=np.float32)[None, :]
    rows = np.arange(y0, y1, dtype=np.float32)[:, None]
    # The ROI-sized arrays are written in place (out=): the same operations in the same order,
    # without allocating (and page-faulting) two fresh ROI arrays per edge.
    cov: np.ndarray | None = None
    d = np.empty((y1 - y0, x1 - x0), np.float32)
    n = len(p)
    for i in range(n):
        a, b = p[i], p[(i + 1) % n]
        e = b - a
        length = math.hypot(e[0], e[1])
        if length < 1e-9:
            continue
        # Inward unit normal (left of the edge for a counter-clockwise polygon in (col, row)).
        nx, ny = -sign * e[1] / length, sign * e[0] / length
        c0 = 0.5 - (nx * a[0] + ny * a[1])
        np.add(np.float32(nx) * cols, np.float32(ny) * rows, out=d)
        np.add(d, np.float32(c0), out=d)
        if cov is None:
            cov, d = d, np.empty_like(d)
        else:
            np.minimum(cov, d, out=cov)
    if cov is None:
        return np.zeros((y1 - y0, x1 - x0), np.float32)
    return np.asarray(np.clip(cov, 0.0, 1.0, out=cov), dtype=np.float32)
