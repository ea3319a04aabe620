"""Camera calibration files and point undistortion.

File format: what ``cv2.FileStorage`` writes (YAML, XML or JSON), as produced by OpenCV's
calibration sample (``samples/cpp/calibration.cpp``): ``camera_matrix`` (3x3) and
``distortion_coefficients`` (4, 5, 8, 12 or 14 values: k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4
[tx ty]]]]), optional ``image_width`` / ``image_height``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from companion.perception._types import CalibrationError, FloatArray

_DIST_LENGTHS = (4, 5, 8, 12, 14)
# undistortPoints is an iterative inverse of the distortion model; OpenCV's default (5
# iterations) leaves ~0.1 px at a wide-angle image's corners. Iterate to convergence.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


@dataclass(frozen=True)
class Calibration:
    """Pinhole intrinsics plus OpenCV distortion.

    ``camera_matrix``: (3, 3) ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels (pixel
    centres at integer coordinates). ``dist_coeffs``: (n,) OpenCV order.
    ``image_size_px``: ``(width, height)`` the calibration was made at, or ``None``.
    """

    camera_matrix: FloatArray
    dist_coeffs: FloatArray
    image_size_px: tuple[int, int] | None = None
    source: str = ""

    def __post_init__(self) -> None:
        k = np.array(self.camera_matrix, dtype=np.float64)
        d = np.array(self.dist_coeffs, dtype=np.float64).reshape(-1)
        where = self.source or "calibration"
        if k.shape != (3, 3) or not np.all(np.isfinite(k)):
            raise CalibrationError(f"{where}: camera_matrix must be a finite 3x3 matrix")
        if not (k[0, 0] > 0 and k[1, 1] > 0):
            raise CalibrationError(f"{where}: camera_matrix: fx and fy must be > 0")
        if not np.allclose(k[2], [0.0, 0.0, 1.0]) or k[1, 0] != 0.0:
            raise CalibrationError(f"{where}: camera_matrix: last row must be [0, 0, 1]")
        if d.size not in (0, *_DIST_LENGTHS) or not np.all(np.isfinite(d)):
            raise CalibrationError(
                f"{where}: distortion_coefficients must have 0, 4, 5, 8, 12 or 14 finite values"
                f" (got {d.size})"
            )
        if self.image_size_px is not None and min(self.image_size_px) <= 0:
            raise CalibrationError(f"{where}: image_width/image_height must be > 0")
        k.setflags(write=False)
        d.setflags(write=False)
        object.__setattr__(self, "camera_matrix", k)
        object.__setattr__(self, "dist_coeffs", d)

    @property
    def fx(self) -> float:
        return float(self.camera_matrix[0, 0])

    @property
    def fy(self) -> float:
        return float(self.camera_matrix[1, 1])

    @property
    def principal_point_px(self) -> tuple[float, float]:
        """``(cx, cy)`` = (col, row) of the optical axis."""
        return float(self.camera_matrix[0, 2]), float(self.camera_matrix[1, 2])

    def undistort_px(self, points_px: npt.ArrayLike) -> FloatArray:
        """Ideal pinhole pixel positions of observed (distorted) ``(col, row)`` points.

        ``cv2.undistortPoints`` with ``P = camera_matrix`` so the result stays in pixels of
        the same camera. (N, 2) in, (N, 2) out.
        """
        pts = np.asarray(points_px, dtype=np.float64).reshape(-1, 1, 2)
        if self.dist_coeffs.size == 0 or not np.any(self.dist_coeffs):
            return pts.reshape(-1, 2).copy()
        out = cv2.undistortPoints(
            pts,
            self.camera_matrix,
            self.dist_coeffs,
            R=None,
            P=self.camera_matrix,
            criteria=_UNDISTORT_CRITERIA,
        )
        return np.asarray(out, dtype=np.float64).reshape(-1, 2)


def load_calibration(path: str | Path) -> Calibration:
    """Read a ``cv2.FileStorage`` calibration (YAML/XML/JSON). Raises :class:`CalibrationError`
    naming the file and the missing or bad entry."""
    p = Path(path).expanduser()
    if not p.is_file():
        raise CalibrationError(f"{p}: calibration file not found")
    try:
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # cv2 wraps its parse errors in SystemError
        raise CalibrationError(f"{p}: not a readable OpenCV FileStorage file: {exc}") from None
    if not fs.isOpened():
        raise CalibrationError(f"{p}: not a readable OpenCV FileStorage file")
    try:
        k = _read_matrix(fs, p, "camera_matrix", required=True)
        d = _read_matrix(fs, p, "distortion_coefficients", required=False)
        if d is None:
            d = _read_matrix(fs, p, "dist_coeffs", required=False)
        if d is None:
            raise CalibrationError(f"{p}: missing distortion_coefficients")
        size = None
        wn, hn = fs.getNode("image_width"), fs.getNode("image_height")
        if not wn.empty() and not hn.empty():
            size = (int(wn.real()), int(hn.real()))
    finally:
        fs.release()
    assert k is not None
    return Calibration(k, d.reshape(-1), size, str(p))


def _read_matrix(fs: cv2.FileStorage, path: Path, key: str, *, required: bool) -> FloatArray | None:
    node = fs.getNode(key)
    if node.empty():
        if required:
            raise CalibrationError(f"{path}: missing {key}")
        return None
    if node.isSeq():  # a plain list (hand-written JSON/YAML) instead of an opencv-matrix
        vals = [node.at(i).real() for i in range(node.size())]
        arr = np.array(vals, dtype=np.float64)
        return arr.reshape(3, 3) if key == "camera_matrix" and arr.size == 9 else arr
    mat = node.mat()
    if mat is None:
        raise CalibrationError(f"{path}: {key} is not a matrix")
    return np.asarray(mat, dtype=np.float64)


def save_calibration(path: str | Path, calibration: Calibration) -> None:
    """Write ``calibration`` in the format :func:`load_calibration` reads (by extension:
    .yaml/.yml, .xml or .json)."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        if calibration.image_size_px is not None:
            fs.write("image_width", int(calibration.image_size_px[0]))
            fs.write("image_height", int(calibration.image_size_px[1]))
        fs.write("camera_matrix", np.asarray(calibration.camera_matrix))
        fs.write("distortion_coefficients", np.asarray(calibration.dist_coeffs).reshape(-1, 1))
    finally:
        fs.release()


__all__ = ["Calibration", "load_calibration", "save_calibration"]
