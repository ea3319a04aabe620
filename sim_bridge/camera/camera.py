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
the ground (``scene``), then the target's box and top (``target``), through the lens
(``lens``), then motion blur, optical blur and the fixed-pattern noise bank here; the sensor's
own photometric chain and timing are ``sensor``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from sim_bridge import ConfigError
from sim_bridge.camera.lens import Lens
from sim_bridge.camera.scene import ground_texture, render_ground
from sim_bridge.camera.scene import roi as roi_of
from sim_bridge.camera.sensor import line_kernel
from sim_bridge.camera.target import NEAR_M, TargetPainter
from sim_bridge.physics.agv import AgvState

_NOISE_BANK = 4
_MAX_FULL_KERNEL_PX = 11  # cv2.filter2D switches to a (16x slower) DFT above this

# Our camera axes (x fwd, y right, z down) -> OpenCV's (x right, y down, z fwd = optical axis).
_CV_FROM_CAM = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def _within(points: list[list[float]], col_max: float, row_max: float) -> bool:
    """Every ``(col, row)`` in ``[-0.5, col_max] x [-0.5, row_max]``."""
    return all(-0.5 <= c <= col_max and -0.5 <= r <= row_max for c, r in points)


def quat_to_matrix(q_wxyz: Sequence[float] | np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of a quaternion (w, x, y, z), normalised first: bit for bit
    scipy's ``Rotation.from_quat([x, y, z, w]).as_matrix()`` (same operations in the same
    order, tests/sim/test_render_fast.py), at a tenth of its cost per frame."""
    w, x, y, z = (float(v) for v in q_wxyz)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    return np.array([[x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw)],
                     [2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw)],
                     [2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2]])


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



def _check_args(focal_length_m: float, pixel_size_m: float, width_px: int, height_px: int,
                mount_rpy_rad: Sequence[float], mount_offset_m: Sequence[float],
                target_lwh_m: tuple[float, float, float], pattern: str, aruco_size_m: float,
                noise_std: float, blur_px: float) -> None:
    """Refuse what :class:`Camera` cannot render, naming the config key."""
    target_length_m, target_width_m, target_height_m = target_lwh_m
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
        _check_args(focal_length_m, pixel_size_m, width_px, height_px, mount_rpy_rad,
                    mount_offset_m, (target_length_m, target_width_m, target_height_m), pattern,
                    aruco_size_m, noise_std, blur_px)
        self.width_px = width_px
        self.height_px = height_px
        self.focal_length_m = float(focal_length_m)
        self.pixel_size_m = float(pixel_size_m)
        self.lens = Lens(self.focal_length_m / self.pixel_size_m, width_px, height_px,
                         camera_matrix, dist_coeffs)
        r, p, y = (float(v) for v in mount_rpy_rad)
        # Camera axes -> body axes (ZYX: Rz(yaw) Ry(pitch) Rx(roll)). scipy only for a
        # rotated mount: importing scipy.spatial costs the emulator ~0.5 s of start-up.
        self.r_body_cam = np.eye(3)
        if r or p or y:
            from scipy.spatial.transform import Rotation

            self.r_body_cam = Rotation.from_euler("ZYX", [y, p, r]).as_matrix()
        self.mount_offset_m = np.array(mount_offset_m, dtype=float)
        self.target = TargetPainter(target_length_m, target_width_m, target_height_m, pattern,
                                    aruco_dictionary, aruco_id, aruco_size_m)
        self.height_m = self.target.height_m
        self.pattern = pattern
        self.noise_std = float(noise_std)
        self.blur_px = float(blur_px)
        self._rng = np.random.default_rng(seed)
        self._ground_tex = ground_texture(seed)
        self._noise_bank: list[np.ndarray] = []
        if self.noise_std > 0:
            pad = 64
            for _ in range(_NOISE_BANK):
                noise = self._rng.normal(0.0, self.noise_std, (height_px + pad, width_px + pad))
                self._noise_bank.append(np.rint(noise).astype(np.int16))

    # ------------------------------------------------------------------------------ lens
    @property
    def camera_matrix(self) -> np.ndarray:
        return self.lens.camera_matrix

    @property
    def f_px(self) -> float:
        return self.lens.f_px

    @property
    def cx(self) -> float:
        return self.lens.cx

    @property
    def cy(self) -> float:
        return self.lens.cy

    @property
    def distorted(self) -> bool:
        return self.lens.distorted

    def ideal_px(self, points_px: np.ndarray) -> np.ndarray:
        """Ideal pinhole pixels (same ``camera_matrix``, no distortion) of image pixels (n, 2)."""
        return self.lens.ideal_px(points_px)

    # ------------------------------------------------------------------------------ geometry
    def pose(
        self, uav_pos_ned_m: np.ndarray, uav_q_wxyz: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """World -> OpenCV-camera rotation ``R`` (3, 3) and translation ``t`` (3,):
        ``X_cv = R X_world + t``. ``uav_q_wxyz`` rotates body vectors into NED (PX4 attitude)."""
        r_wb = quat_to_matrix(uav_q_wxyz)
        r_wc = r_wb @ self.r_body_cam
        c_w = np.asarray(uav_pos_ned_m, dtype=float) + r_wb @ self.mount_offset_m
        r_cv_w = _CV_FROM_CAM @ r_wc.T
        return r_cv_w, -r_cv_w @ c_w

    def project(
        self, points_ned_m: np.ndarray, uav_pos_ned_m: np.ndarray, uav_q_wxyz: np.ndarray
    ) -> np.ndarray:
        """Pixel ``(col, row)`` (n, 2) of world points (n, 3) with ``cv2.projectPoints``."""
        r, t = self.pose(uav_pos_ned_m, uav_q_wxyz)
        return self.lens.project(np.asarray(points_ned_m, dtype=float).reshape(-1, 3), r, t)

        return self.lens.project(np.asarray(points_ned_m, dtype=float).reshape(-1, 3), r, t)

    def agv_points(self, agv: AgvState) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World NED (4, 3) top corners, bottom corners and marker corners (FL, FR, RR, RL)."""
        return self.target.agv_points(agv)

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
        px = self.lens.project(pts, r, t)  # image pixels (through the lens)
        ideal = self.lens.project_ideal(pts, r, t) if self.distorted else px  # canvas pixels
        z_cv = pts @ r[2] + t[2]
        top_px, marker_px = px[0:4], px[8:12]

        ground_z = float(agv.pos_ned_m[2]) + self.height_m
        top_faces_camera = c_w[2] < agv.pos_ned_m[2]
        motion = None
        if exposure_s > 0 and uav_vel_ned_m_s is not None and uav_rates_frd_rad_s is not None:
            motion = self.image_motion_px(uav_pos_ned_m, uav_q_wxyz, uav_vel_ned_m_s,
                                          uav_rates_frd_rad_s, agv, exposure_s)
        if self.lens.remap is not None:
            image = self._render_through_lens(r, t, c_w, ground_z, ideal[:8], z_cv[:8],
                                              pts[:8], top_faces_camera, agv, occluded, motion)
        else:
            image = render_ground(self._ground_tex, self.lens, r, c_w, ground_z)
            hull_roi: tuple[int, int, int, int] | None = None
            if not occluded:
                hull_roi = self.target.draw_box(self.lens, image, ideal[:8], z_cv[:8], pts[:8],
                                                r, t, top_faces_camera, agv)
            if motion is not None:
                image = self._motion_blur(image, motion, hull_roi)

        target_px = marker_px if self.pattern == "aruco" else top_px
        target_ideal = ideal[8:12] if self.pattern == "aruco" else ideal[0:4]
        target_z = z_cv[8:12] if self.pattern == "aruco" else z_cv[0:4]
        w, h = self.width_px, self.height_px
        # a distortion polynomial can fold far-off points back into the image: the canvas
        # pixels too (plain floats: nine numpy reductions cost ~0.2 ms a frame)
        inside = (all(z > NEAR_M for z in target_z.tolist())
                  and _within(target_px.tolist(), w - 0.5, h - 0.5)
                  and _within(target_ideal.tolist(), self.lens.rw - 0.5, self.lens.rh - 0.5))
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
        assert self.lens.remap is not None and self.lens.remap_half is not None
        w, h = self.width_px, self.height_px
        small = render_ground(self._ground_tex, self.lens, r, c_w, ground_z, half=True)
        half = cv2.remap(small, self.lens.remap_half[0], self.lens.remap_half[1],
                         cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        k_full = None if motion is None else line_kernel(float(motion[0]), float(motion[1]))
        if motion is not None:
            k_half = line_kernel(float(motion[0]) / 2, float(motion[1]) / 2)
            if k_half is not None:
                half = cv2.filter2D(half, -1, k_half, borderType=cv2.BORDER_REFLECT)
        out = cv2.resize(half, (w, h), interpolation=cv2.INTER_LINEAR)
        if occluded or not (box_z > NEAR_M).all():
            if not occluded and not (box_z <= NEAR_M).all():  # rare: the camera at the box
                canvas = render_ground(self._ground_tex, self.lens, r, c_w, ground_z)
                self.target.draw_box(self.lens, canvas, box_px, box_z, box_pts, r, t,
                                     top_faces_camera, agv)
                return cv2.remap(canvas, self.lens.remap[0], self.lens.remap[1], cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_REPLICATE)
            return out
        hull = box_px[cv2.convexHull(box_px.astype(np.float32), returnPoints=False).ravel()]
        roi = roi_of(hull, self.lens.rw, self.lens.rh)
        if roi is None:
            return out
        spread = 0 if k_full is None else k_full.shape[0] // 2
        c0, r0, c1, r1 = self.lens.image_window(roi, spread)
        if c1 <= c0 or r1 <= r0:
            return out
        # the canvas pixels those output pixels sample, plus the kernel's reach: upsample the
        # ground there exactly as cv2.resize would, draw the box, blur
        mx, my = self.lens.map_f[0][r0:r1, c0:c1], self.lens.map_f[1][r0:r1, c0:c1]
        pad = spread + 2
        px0 = max(math.floor(float(mx.min())) - pad, 0)
        py0 = max(math.floor(float(my.min())) - pad, 0)
        px1 = min(math.ceil(float(mx.max())) + pad + 1, self.lens.rw)
        py1 = min(math.ceil(float(my.max())) + pad + 1, self.lens.rh)
        sx, sy = small.shape[1] / self.lens.rw, small.shape[0] / self.lens.rh
        up = np.array([[sx, 0.0, (px0 + 0.5) * sx - 0.5], [0.0, sy, (py0 + 0.5) * sy - 0.5]])
        patch = cv2.warpAffine(small, up, (px1 - px0, py1 - py0),
                               flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_REPLICATE)
        canvas = np.empty((self.lens.rh, self.lens.rw), np.uint8)  # only the patch is ever read
        canvas[py0:py1, px0:px1] = patch
        self.target.draw_box(self.lens, canvas, box_px, box_z, box_pts, r, t, top_faces_camera,
                             agv)
        if k_full is not None:
            canvas[py0:py1, px0:px1] = cv2.filter2D(canvas[py0:py1, px0:px1], -1, k_full,
                                                    borderType=cv2.BORDER_REFLECT)
        out[r0:r1, c0:c1] = cv2.remap(canvas[py0:py1, px0:px1], mx - px0, my - py0,
                                      cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return out

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
        from scipy.spatial.transform import Rotation  # the camera model's motion blur only

        half = 0.5 * exposure_s
        q = np.asarray(uav_q_wxyz, dtype=float)
        rot = Rotation.from_quat([q[1], q[2], q[3], q[0]])
        w = np.asarray(uav_rates_frd_rad_s, dtype=float)
        v = np.asarray(uav_vel_ned_m_s, dtype=float)
        p0 = np.asarray(uav_pos_ned_m, dtype=float)
        r_mid, t_mid = self.pose(p0, q)
        point = agv.pos_ned_m + np.array([0.0, 0.0, 0.0])
        if float(point @ r_mid[2] + t_mid[2]) <= NEAR_M:
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
            if float(pt @ r_s[2] + t_s[2]) <= NEAR_M:
                return None
            ends.append(self.lens.project_ideal(pt[None, :], r_s, t_s)[0])
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
        hw, hh = (self.lens.rw + 1) // 2, (self.lens.rh + 1) // 2
        small = cv2.resize(image, (hw, hh), interpolation=cv2.INTER_AREA)
        k2 = line_kernel(float(motion_px[0]) / 2, float(motion_px[1]) / 2)
        if k2 is not None:
            small = cv2.filter2D(small, -1, k2, borderType=cv2.BORDER_REFLECT)
        out = cv2.resize(small, (self.lens.rw, self.lens.rh), interpolation=cv2.INTER_LINEAR)
        if roi is not None:
            m = k.shape[0] // 2
            x0, y0 = max(roi[0] - 2 * m, 0), max(roi[1] - 2 * m, 0)
            x1, y1 = min(roi[2] + 2 * m, self.lens.rw), min(roi[3] + 2 * m, self.lens.rh)
            sharp = cv2.filter2D(image[y0:y1, x0:x1], -1, k, borderType=cv2.BORDER_REFLECT)
            out[y0 + m:y1 - m, x0 + m:x1 - m] = sharp[m:sharp.shape[0] - m, m:sharp.shape[1] - m]
        return out
