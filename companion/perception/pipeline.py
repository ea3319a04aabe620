"""Perception: pixels in, the target's four image points in metric image coordinates out.

``image -> detector (raw pixel corners) -> undistortion (if calibrated) -> metric (u, n)``.
The virtual-camera mapping and the image moments are the core's job
(``companion.core.geometry`` / ``moments``), not this module's.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
import numpy.typing as npt

from companion.config import PerceptionConfig, TargetConfig
from companion.core.geometry import opencv_to_spec_pixel, principal_point_px
from companion.core.params import CameraParams
from companion.perception._types import (
    Detection,
    DetectionReport,
    Detector,
    FloatArray,
    PerceptionError,
)
from companion.perception.aruco import ArucoDetector
from companion.perception.calibration import Calibration, load_calibration
from companion.perception.rectangle import RectangleDetector, RectangleSettings

_log = logging.getLogger(__name__)

Status = Literal["ok", "lost", "rejected"]


ROI_GROW = 1.0
_FEW_POINTS = 8  # pixels_to_metric on plain floats up to this many points
ROI_MIN_MARGIN_PX = 40.0


def limit_opencv_threads() -> None:
    """Run OpenCV's functions on the calling thread (``cv2.setNumThreads(1)``) unless
    ``OPENCV_FOR_THREADS_NUM`` says otherwise.

    Why: perception works on a small region of interest, where OpenCV's thread pool saves no
    time, but its idle workers spin-wait after every parallel call. Measured on 1198 flight
    frames (2 cores): 2.9 ms of CPU per frame with the pool against 1.6 ms without, the same
    wall time. In lockstep that spinning takes a core from the emulator (and from the
    controller process of a replay). Results are the same: OpenCV splits work by rows."""
    if "OPENCV_FOR_THREADS_NUM" not in os.environ:
        cv2.setNumThreads(1)


@dataclass(frozen=True)
class CameraModel:
    """What the pixel -> metric conversion needs: focal lengths and principal point in
    pixels, the focal length in metres (the spec's ``lambda``)."""

    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    focal_length_m: float


def camera_model(camera: CameraParams, calibration: Calibration | None = None) -> CameraModel:
    """Intrinsics from the calibration if given, else the ideal pinhole of the config:
    ``f_px = focal_length_m / pixel_size_m`` and the principal point at the image centre
    (``companion.core.geometry.principal_point_px``: ``((width - 1) / 2, (height - 1) / 2)``,
    pixel centres at integer coordinates)."""
    if calibration is not None:
        cx, cy = calibration.principal_point_px
        return CameraModel(calibration.fx, calibration.fy, cx, cy, camera.focal_length_m)
    f_px = camera.focal_length_m / camera.pixel_size_m
    cx, cy = principal_point_px(camera.width_px, camera.height_px)
    return CameraModel(f_px, f_px, cx, cy, camera.focal_length_m)


def pixels_to_metric(points_px: npt.ArrayLike, model: CameraModel) -> FloatArray:
    """Undistorted pixel ``(col, row)`` -> metric image coordinates ``(u, n)`` (metres).

    Spec section 1 via the core's single mapping
    (:func:`companion.core.geometry.opencv_to_spec_pixel`: ``u_px = cy - row``,
    ``n_px = col - cx``), then ``u = lambda * u_px / f_y``, ``n = lambda * n_px / f_x``
    (= ``pixel * pixel_size`` for the ideal camera; a calibration's own focal lengths
    otherwise). (N, 2) in, (N, 2) out.
    """
    p = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
    if p.shape[0] <= _FEW_POINTS:
        # a detection's 4 corners: plain floats, the same float64 operations in the same
        # order (numpy's per-call cost was ~30 us a frame here)
        f, fx, fy, cx, cy = (model.focal_length_m, model.fx_px, model.fy_px, model.cx_px,
                             model.cy_px)
        out = []
        for col, row in p.tolist():
            u_px, n_px = opencv_to_spec_pixel(col, row, cx, cy)
            out.append((f * u_px / fy, f * n_px / fx))
        return np.array(out, dtype=np.float64).reshape(-1, 2)
    u_px, n_px = opencv_to_spec_pixel(p[:, 0], p[:, 1], model.cx_px, model.cy_px)
    u = model.focal_length_m * np.asarray(u_px, dtype=np.float64) / model.fy_px
    n = model.focal_length_m * np.asarray(n_px, dtype=np.float64) / model.fx_px
    return np.column_stack([u, n])


@dataclass(frozen=True)
class PerceptionResult:
    """One frame's measurement of the target.

    ``status``: ``"ok"`` (target measured), ``"lost"`` (nothing target-like in view) or
    ``"rejected"`` (candidates seen, none plausible); ``reason`` says why when not ok.
    ``corners_px``: (4, 2) raw detected ``(col, row)``; ``corners_undistorted_px``: the same
    after undistortion (equal without calibration); ``points_m``: (4, 2) metric ``(u, n)`` on
    the real image plane, spec section 1 (``None`` unless ok). Order: the detector's
    (front-left, front-right, rear-right, rear-left), matching :attr:`target_points_m`.
    ``t_us``: the frame's capture time, passed through.
    """

    status: Status
    reason: str = ""
    corners_px: FloatArray | None = None
    corners_undistorted_px: FloatArray | None = None
    points_m: FloatArray | None = None
    quality: float = 0.0
    t_us: int | None = None
    detection: Detection | None = None
    report: DetectionReport | None = None

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def make_detector(target: TargetConfig, perception: PerceptionConfig | None = None
                  ) -> RectangleDetector | ArucoDetector:
    """The detector ``target.pattern`` names, tuned by ``perception`` (default: its
    defaults)."""
    if target.pattern == "rectangle":
        p = perception or PerceptionConfig()
        settings = RectangleSettings(
            threshold=p.rectangle_threshold or None,
            level_fraction=p.rectangle_level_fraction,
            edges=p.rectangle_edges,
            compiled=p.compiled_edges,
        )
        return RectangleDetector(target.length_m, target.width_m, settings=settings)
    if target.pattern == "aruco":
        return ArucoDetector(target.aruco_dictionary, target.aruco_id, target.aruco_size_m)
    raise PerceptionError(f"target.pattern: {target.pattern!r} has no detector")


class Perception:
    """Detector + undistortion + metric conversion for one camera and target.

    ``calibration``: explicit, else loaded from ``camera.calibration_file`` when set, else
    the ideal pinhole. A calibration made at another image size than the config's is an
    error (its pixels would not be ours). Keeps the last accepted corners to hold the
    rectangle's corner order across frames (``track_order=False`` to disable). ``perception``:
    the config's ``[perception]`` table (detector tuning; default: its defaults).
    """

    def __init__(
        self,
        camera: CameraParams,
        target: TargetConfig,
        *,
        calibration: Calibration | None = None,
        detector: Detector | None = None,
        track_order: bool = True,
        roi: bool = True,
        perception: PerceptionConfig | None = None,
    ) -> None:
        limit_opencv_threads()
        if calibration is None and camera.calibration_file:
            calibration = load_calibration(camera.calibration_file)
        if calibration is not None and calibration.image_size_px is not None:
            expected = (camera.width_px, camera.height_px)
            if tuple(calibration.image_size_px) != expected:
                raise PerceptionError(
                    f"camera.calibration_file: calibrated at {calibration.image_size_px} px,"
                    f" camera is {expected} px"
                )
        self.camera = camera
        self.calibration = calibration
        self.model = camera_model(camera, calibration)
        self.detector: Detector = (detector if detector is not None
                                   else make_detector(target, perception))
        self._track_order = track_order
        self._use_roi = roi
        self._last_corners: FloatArray | None = None
        self.roi_hits = 0
        self.full_searches = 0
        #: ``(x0, y0, x1, y1)`` (pixels, end exclusive) of the last image: every pixel the
        #: detector read lies inside it (the region of interest, the detector's own smaller
        #: box when it knows one, or the whole image when it searched everywhere). Logging
        #: this crop is enough to replay perception exactly.
        self.last_region: tuple[int, int, int, int] | None = None

    @property
    def target_points_m(self) -> FloatArray:
        return self.detector.target_points_m

    def _analyse(self, image: npt.NDArray[np.uint8], hint: FloatArray | None
                 ) -> DetectionReport:
        """Search a region of interest around the previous detection first (the target moves
        little between frames); the whole image when there is none or the region finds
        nothing acceptable. A candidate cut by the region's edge fails the border check and so
        sends the search to the whole image. Depends only on earlier results: replay-exact."""
        h, w = image.shape[:2]
        tried = False
        if self._use_roi and self._last_corners is not None:
            x0, y0, x1, y1 = roi_box(self._last_corners, w, h)
            if (x1 - x0) * (y1 - y0) < 0.5 * w * h:
                tried = True
                off = np.array([x0, y0], dtype=np.float64)
                sub = self.detector.analyse(image[y0:y1, x0:x1],
                                            None if hint is None else hint - off)
                if sub.detection is not None:
                    self.roi_hits += 1
                    self.last_region = self._read_region(x0, y0, x1, y1)
                    d = sub.detection
                    # the constructors, not dataclasses.replace (its generic field walk cost
                    # more than the rest of this function): the same values
                    moved = Detection(d.corners_px + off, d.quality, d.area_px, d.marker_id,
                                      d.flags)
                    return DetectionReport(moved, sub.rejections, sub.reason, sub.candidates)
        self.full_searches += 1
        report = self.detector.analyse(image, hint)
        # after a failed region of interest, what it read (and left in the detector's state)
        # counts too: the whole image
        self.last_region = (0, 0, w, h) if tried else self._read_region(0, 0, w, h)
        return report

    def _read_region(self, x0: int, y0: int, x1: int, y1: int) -> tuple[int, int, int, int]:
        """The pixels of the image that the detector's last analyse of its part ``(x0, y0,
        x1, y1)`` read: the detector's own box when it knows a smaller one (a tracked
        rectangle's edge profiles: about a sixth of the region of interest, so the logged
        crop and its PNG shrink as much), else the whole part."""
        box = getattr(self.detector, "last_read_box", None)
        if box is None:
            return x0, y0, x1, y1
        return x0 + box[0], y0 + box[1], x0 + box[2], y0 + box[3]

    def process(self, image: npt.NDArray[np.uint8], *, t_us: int | None = None) -> PerceptionResult:
        """Measure the target in ``image`` ((H, W) mono or (H, W, 3) BGR uint8)."""
        if not isinstance(image, np.ndarray) or image.ndim not in (2, 3):
            raise PerceptionError("image: expected an (H, W) or (H, W, 3) numpy array")
        if image.shape[:2] != (self.camera.height_px, self.camera.width_px):
            self.last_region = (0, 0, image.shape[1], image.shape[0])
            return PerceptionResult(
                "rejected",
                f"image is {image.shape[1]}x{image.shape[0]} px, camera is "
                f"{self.camera.width_px}x{self.camera.height_px}",
                t_us=t_us,
            )
        hint = self._last_corners if self._track_order else None
        report = self._analyse(image, hint)
        det = report.detection
        if det is None:
            # the order hint survives a loss: the nearer rotation is still the best guess
            status: Status = "rejected" if report.rejections else "lost"
            return PerceptionResult(status, report.reason, t_us=t_us, report=report)
        self._last_corners = det.corners_px
        return self.measured(det.corners_px, det.quality, t_us, det, report)

    def measured(self, corners_px: FloatArray, quality: float = 0.0, t_us: int | None = None,
                 detection: Detection | None = None, report: DetectionReport | None = None
                 ) -> PerceptionResult:
        """The ``"ok"`` result of detected raw pixel corners (4, 2) ``(col, row)``:
        undistorted and converted to metric image points. :meth:`process` ends here; a replay
        from logged detections starts here (same arithmetic, same result)."""
        undist = (
            self.calibration.undistort_px(corners_px)
            if self.calibration is not None
            else corners_px.copy()
        )
        points = pixels_to_metric(undist, self.model)
        for a in (undist, points):
            a.setflags(write=False)
        return PerceptionResult(
            "ok", "", corners_px, undist, points, quality, t_us, detection, report
        )


def roi_box(corners: FloatArray, width: int, height: int,
            grow: float = ROI_GROW, min_margin_px: float = ROI_MIN_MARGIN_PX
            ) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)`` (pixels, end exclusive): the corners' bounding box grown by
    ``grow`` times its size (at least ``min_margin_px``) on every side, clipped to the image."""
    # plain floats on 4 corners (numpy's per-call cost dominates): the same float64 arithmetic
    xs, ys = corners[:, 0].tolist(), corners[:, 1].tolist()
    lo_x, lo_y, hi_x, hi_y = min(xs), min(ys), max(xs), max(ys)
    m_x = max(grow * (hi_x - lo_x), min_margin_px)
    m_y = max(grow * (hi_y - lo_y), min_margin_px)
    x0, y0 = math.floor(lo_x - m_x), math.floor(lo_y - m_y)
    x1, y1 = math.ceil(hi_x + m_x) + 1, math.ceil(hi_y + m_y) + 1
    return max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)


__all__ = [
    "CameraModel",
    "Perception",
    "PerceptionResult",
    "camera_model",
    "make_detector",
    "pixels_to_metric",
]
