"""Value types shared by the detectors and the perception pipeline.

Pixel convention everywhere in this package: ``(col, row)`` in the OpenCV sense, pixel centres
at integer coordinates (the convention of ``cv2.projectPoints`` and ``cv2.cornerSubPix``), row 0
at the top of the image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np
import numpy.typing as npt

from companion import CompanionError

FloatArray = npt.NDArray[np.float64]


class PerceptionError(CompanionError):
    """Root of the perception package's errors (bad image, bad calibration, bad settings)."""


class CalibrationError(PerceptionError):
    """A calibration file is missing, unreadable or inconsistent; the message names it."""


def _as_corners(value: npt.ArrayLike, name: str) -> FloatArray:
    arr = np.array(value, dtype=np.float64)
    if arr.shape != (4, 2):
        raise PerceptionError(f"{name}: expected shape (4, 2), got {arr.shape}")
    # plain floats on 8 values: np.all(np.isfinite(...)) cost ~10 us a call in numpy's
    # Python-level reduction wrapper, twice a frame
    if not all(map(math.isfinite, arr.ravel().tolist())):
        raise PerceptionError(f"{name}: contains non-finite values")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True)
class Detection:
    """One accepted target detection.

    ``corners_px``: (4, 2) sub-pixel ``(col, row)`` in the *raw* (distorted) image, in the
    detector's documented order (see :attr:`Detector.target_points_m`, same order).
    ``quality``: 0..1, higher is better (detector specific, documented there).
    ``area_px``: area of the quadrilateral (px^2). ``marker_id``: ArUco id, ``None`` otherwise.
    ``flags``: soft remarks that did not reject the detection (e.g. ``"near border"``).
    """

    corners_px: FloatArray
    quality: float
    area_px: float
    marker_id: int | None = None
    flags: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "corners_px", _as_corners(self.corners_px, "corners_px"))
        if not 0.0 <= self.quality <= 1.0:
            raise PerceptionError(f"quality: must be in [0, 1] (got {self.quality})")


@dataclass(frozen=True)
class Rejection:
    """A candidate that failed a plausibility check: where it was (if known) and why."""

    reason: str
    corners_px: FloatArray | None = None

    def __post_init__(self) -> None:
        if self.corners_px is not None:
            object.__setattr__(self, "corners_px", _as_corners(self.corners_px, "corners_px"))


@dataclass(frozen=True)
class DetectionReport:
    """Everything one detector call found: the accepted detection (or ``None``), every
    rejected candidate with its reason, and ``reason``: why nothing was accepted ("" if one
    was)."""

    detection: Detection | None
    rejections: tuple[Rejection, ...] = ()
    reason: str = ""
    candidates: int = 0

    @property
    def reasons(self) -> tuple[str, ...]:
        return tuple(r.reason for r in self.rejections)


class QuadDetectorBase:
    """Shared by the concrete detectors: the target's corner layout and ``detect``."""

    _target_points_m: FloatArray

    @property
    def target_points_m(self) -> FloatArray:
        """(4, 2) ``(x forward, y right)`` metres: FL, FR, RR, RL (the detection's order)."""
        return self._target_points_m

    def analyse(
        self, image: npt.NDArray[np.uint8], hint: npt.ArrayLike | None = None
    ) -> DetectionReport:
        raise NotImplementedError

    def detect(self, image: npt.NDArray[np.uint8]) -> Detection | None:
        return self.analyse(image).detection


class Detector(Protocol):
    """What every detector offers. ``detect`` is ``analyse(image).detection``."""

    @property
    def target_points_m(self) -> FloatArray:
        """(4, 2) target-frame corner positions ``(x forward, y right)`` in metres, in the
        same order as ``Detection.corners_px``."""
        ...

    def analyse(
        self, image: npt.NDArray[np.uint8], hint: npt.ArrayLike | None = None
    ) -> DetectionReport:
        """Everything found in ``image``; ``hint``: the previous frame's corners (same
        order), used by detectors whose corner order is ambiguous to stay continuous."""
        ...

    def detect(self, image: npt.NDArray[np.uint8]) -> Detection | None: ...


def to_gray(image: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    """(H, W) uint8 as is, (H, W, 3) BGR converted; anything else raises PerceptionError."""
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
        raise PerceptionError("image: expected a uint8 numpy array")
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 3:
        return np.asarray(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), dtype=np.uint8)
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    raise PerceptionError(f"image: expected (H, W) or (H, W, 3) BGR, got shape {image.shape}")


__all__ = [
    "CalibrationError",
    "Detection",
    "DetectionReport",
    "Detector",
    "FloatArray",
    "PerceptionError",
    "Rejection",
    "to_gray",
]
