"""The target as the camera draws it: the AGV's box (dark sides) and its top (a bright rectangle,
or white with an ArUco marker, textured through a mip chain), in the AGV's frame and in the
image."""

from __future__ import annotations

import math

import cv2
import numpy as np

from sim_bridge import ConfigError
from sim_bridge.camera import boxdraw
from sim_bridge.camera.lens import Lens
from sim_bridge.camera.scene import clip_polygon_halfplane, edge_lines, edge_min
from sim_bridge.camera.scene import roi as roi_of
from sim_bridge.physics.agv import AgvState

BOX_SIDE_LEVEL = 30
TOP_LEVEL = 235
ARUCO_WHITE, ARUCO_BLACK = 245, 10

NEAR_M = 0.05  # points closer than this along the optical axis are not drawn
_TOP_TEXEL_M = 5.0e-4  # finest texel of the ArUco top texture (mip level 0)
_MIP_LEVELS = 7  # 0.5 mm .. 32 mm texels


def _coverages(hull: np.ndarray, top: np.ndarray | None, roi: tuple[int, int, int, int]
               ) -> tuple[np.ndarray, np.ndarray | None]:
    """The silhouette's coverage ``h`` and, with ``top``, the top's ``t = min(coverage(top),
    h)`` (float32 ROI arrays), as ``scene.coverage`` computes each: ``t`` is ``clip(min(...))``
    over the top's edges and the silhouette's (clip is monotone, the minimum exact), so it
    continues the silhouette's running minimum, and a top edge that is also a silhouette edge
    in the same direction (the same three floats: the same float32 array) is not computed
    again: seen from above, most of the top's edges are silhouette edges."""
    x0, y0, x1, y1 = roi
    hull_lines = edge_lines(hull)
    h_min = edge_min(hull_lines, roi)
    t_cov = None
    if top is not None:
        top_lines = edge_lines(top)
        if h_min is None or not top_lines:  # a degenerate polygon covers nothing
            t_cov = np.zeros((y1 - y0, x1 - x0), np.float32)
        else:
            shared = set(hull_lines)
            t_min = edge_min([e for e in top_lines if e not in shared], roi, h_min.copy())
            assert t_min is not None
            t_cov = np.clip(t_min, 0.0, 1.0, out=t_min)
    if h_min is None:
        return np.zeros((y1 - y0, x1 - x0), np.float32), t_cov
    return np.clip(h_min, 0.0, 1.0, out=h_min), t_cov


def composite(image: np.ndarray, roi: tuple[int, int, int, int], hull: np.ndarray,
              top: np.ndarray | None, fg: float | np.ndarray) -> None:
    """The box over ``image``'s ROI in numpy passes: ground (1 - h), sides (h - t) at
    ``BOX_SIDE_LEVEL``, top t at ``fg`` (a level or the top's texture)."""
    h_cov, t_cov = _coverages(hull, top, roi)
    x0, y0, x1, y1 = roi
    bg = image[y0:y1, x0:x1].astype(np.float32)
    out = bg + (np.float32(BOX_SIDE_LEVEL) - bg) * h_cov
    if t_cov is not None:
        out += (fg - np.float32(BOX_SIDE_LEVEL)) * t_cov
    image[y0:y1, x0:x1] = (out + 0.5).astype(np.uint8)


class TargetPainter:
    """The AGV box of ``length_m x width_m x height_m`` with its top ``pattern``
    (``"rectangle"`` or ``"aruco"``: the marker ``aruco_id`` of ``aruco_dictionary``,
    ``aruco_size_m`` wide, centred on the top, its image "up" towards the AGV's front)."""

    def __init__(self, length_m: float, width_m: float, height_m: float, pattern: str,
                 aruco_dictionary: str, aruco_id: int, aruco_size_m: float) -> None:
        self.length_m = float(length_m)
        self.width_m = float(width_m)
        self.height_m = float(height_m)
        self.pattern = pattern
        self.aruco_size_m = float(aruco_size_m)
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
        self._top_mips: list[np.ndarray] = []
        self._top_texel_m: list[float] = []
        if pattern == "aruco":
            self._build_aruco_top(aruco_dictionary, aruco_id)

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


    def draw_box(
        self,
        lens: Lens,
        image: np.ndarray,
        px: np.ndarray,
        z_cv: np.ndarray,
        pts: np.ndarray,
        r: np.ndarray,
        t: np.ndarray,
        top_faces_camera: bool,
        agv: AgvState,
    ) -> tuple[int, int, int, int] | None:
        """Draw the box on ``lens``'s canvas (``px``: its 8 corners in canvas pixels); returns
        the drawn ROI."""
        if (z_cv > NEAR_M).all():
            # The box's silhouette (convex hull of its 8 corners) is dark; the top is drawn in
            # the same pass with coverages that partition each pixel: ground (1 - h), sides
            # (h - t), top t. Compositing the top over a separately anti-aliased silhouette
            # would leak ground into the shared edges and bias them by ~0.1 px.
            idx = cv2.convexHull(px.astype(np.float32), returnPoints=False).ravel()
            hull = px[idx]
            roi = roi_of(hull, lens.rw, lens.rh)
            if roi is None:
                return None
            top = px[:4] if top_faces_camera else None
            fg: float | np.ndarray = float(TOP_LEVEL)
            if self.pattern == "rectangle":
                fn = boxdraw.kernel()  # the same pixels in one compiled loop
                if fn is not None and boxdraw.run(
                        fn, image, roi, edge_lines(hull), None if top is None else edge_lines(top),
                        float(BOX_SIDE_LEVEL), float(TOP_LEVEL - BOX_SIDE_LEVEL)):
                    return roi
            elif top is not None:
                fg = self._aruco_top(lens, roi, r, t, agv, float(np.mean(z_cv[:4])))
            composite(image, roi, hull, top, fg)
            return roi
        if (z_cv <= NEAR_M).all():
            return None
        # The box crosses the near plane (the camera is at/inside it): clip each visible face in
        # the camera frame and fill it plainly. Rare; no sub-pixel care needed.
        cam = pts @ r.T + t
        faces = [[4, 5, 6, 7]] + [[i, (i + 1) % 4, (i + 1) % 4 + 4, i + 4] for i in range(4)]
        if top_faces_camera:
            faces.append([0, 1, 2, 3])
        for k, face in enumerate(faces):
            poly = clip_polygon_halfplane(cam[face], np.array([0.0, 0.0, 1.0]), -NEAR_M)
            if len(poly) < 3:
                continue
            proj = (lens.rk @ poly.T).T
            uv = proj[:, :2] / proj[:, 2:3]
            level = TOP_LEVEL if (top_faces_camera and k == len(faces) - 1) else BOX_SIDE_LEVEL
            uv = np.clip(uv, -1e5, 1e5)
            cv2.fillPoly(image, [np.round(uv * 16).astype(np.int32)], level, cv2.LINE_8, 4)
        return None

    def _aruco_top(
        self,
        lens: Lens,
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
        footprint_m = depth_m / float(lens.rk[0, 0])
        ratio = max(footprint_m / self._top_texel_m[0], 1.0)
        level = min(math.ceil(math.log2(ratio) - 1e-9), _MIP_LEVELS - 1)
        tex = self._top_mips[level]
        texel = self._top_texel_m[level]
        rows, cols = tex.shape
        # Texel (tc, tr) centre -> top-local (a fwd, b right): a = (rows/2 - tr - 0.5) texel,
        # b = (tc + 0.5 - cols/2) texel. Top-local (a, b, 1) -> image: the plane homography
        # K [R rz e_x, R rz e_y, R p + t].
        c, s = math.cos(agv.yaw_rad), math.sin(agv.yaw_rad)
        gmat = lens.rk @ np.column_stack(
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

