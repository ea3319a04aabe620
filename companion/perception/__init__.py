"""Perception from pixels: detectors, calibration/undistortion, plausibility, metric points.

``Perception(camera_cfg, target_cfg).process(image)`` -> :class:`PerceptionResult` with the
target's four corners in raw pixels and in metric image coordinates ``(u, n)`` (spec section 1).
Pixel convention: ``(col, row)``, pixel centres at integer coordinates, row 0 at the top.
"""

from __future__ import annotations

from companion.perception._types import (
    CalibrationError,
    Detection,
    DetectionReport,
    Detector,
    PerceptionError,
    Rejection,
    to_gray,
)
from companion.perception.aruco import ArucoDetector, aruco_dictionary
from companion.perception.calibration import Calibration, load_calibration, save_calibration
from companion.perception.pipeline import (
    CameraModel,
    Perception,
    PerceptionResult,
    camera_model,
    make_detector,
    pixels_to_metric,
)
from companion.perception.plausibility import QuadLimits, check_quad
from companion.perception.rectangle import RectangleDetector, RectangleSettings

__all__ = [
    "ArucoDetector",
    "Calibration",
    "CalibrationError",
    "CameraModel",
    "Detection",
    "DetectionReport",
    "Detector",
    "Perception",
    "PerceptionError",
    "PerceptionResult",
    "QuadLimits",
    "RectangleDetector",
    "RectangleSettings",
    "Rejection",
    "aruco_dictionary",
    "camera_model",
    "check_quad",
    "load_calibration",
    "make_detector",
    "pixels_to_metric",
    "save_calibration",
    "to_gray",
]
