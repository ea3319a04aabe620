"""Perception on real pixels rendered here with known geometry.

Scenes follow the emulator's pattern (docs/reference/wire.md, config [target]): a procedural
textured ground (40..150), the AGV box's sides dark (35) and its top bright (225). Polygons are
filled
with ``cv2.fillPoly`` at sub-pixel precision (``shift``) on a 16x supersampled crop and
area-averaged down (``INTER_AREA``): each pixel holds its true area coverage to 1/32 px, so
the projected corners are an exact oracle.
"""

from __future__ import annotations

import functools
import itertools
import math
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from companion.config import load_config
from companion.perception import (
    ArucoDetector,
    Calibration,
    CalibrationError,
    Perception,
    PerceptionError,
    RectangleDetector,
    load_calibration,
    pixels_to_metric,
)

CFG = load_config()
CAM = CFG.camera
W, H = CAM.width_px, CAM.height_px
LAM = CAM.focal_length_m
F_PX = CAM.focal_length_m / CAM.pixel_size_m
CX, CY = (W - 1) / 2.0, (H - 1) / 2.0
K = np.array([[F_PX, 0.0, CX], [0.0, F_PX, CY], [0.0, 0.0, 1.0]])
L_M, W_M, H_M = 0.5, 0.4, 0.3
SS = 16  # supersampling factor

# ---------------------------------------------------------------------------------------------
# Rendering (test oracle)


@functools.lru_cache(maxsize=1)
def _texture_bank() -> np.ndarray:
    rng = np.random.default_rng(1234)
    n = 1400
    lo = rng.uniform(0, 1, (n // 25 + 2, n // 25 + 2)).astype(np.float32)
    big = cv2.resize(lo, (n, n), interpolation=cv2.INTER_CUBIC)
    fine = rng.uniform(0, 1, (n, n)).astype(np.float32)
    return np.clip(40 + 110 * np.clip(0.7 * big + 0.3 * fine, 0, 1), 40, 150).astype(np.uint8)


def ground(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    r0, c0 = rng.integers(0, 400, 2)
    return _texture_bank()[r0 : r0 + H, c0 : c0 + W].copy()


def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def to_camera(p_level: np.ndarray, phi: float, theta: float) -> np.ndarray:
    """Level frame (camera origin, x fwd, y right, z down) -> camera frame of a camera with
    roll ``phi``, pitch ``theta`` (spec section 1: p_v = Ry(theta) Rx(phi) p_c)."""
    return p_level @ (rot_y(theta) @ rot_x(phi))


def project(p_cam: np.ndarray, dist: np.ndarray | None = None) -> np.ndarray:
    """Camera-frame points (x fwd, y right, z down) -> (col, row), spec section 1."""
    p_cv = np.column_stack([p_cam[:, 1], -p_cam[:, 0], p_cam[:, 2]])  # OpenCV x right, y down
    d = np.zeros(5) if dist is None else dist
    px, _ = cv2.projectPoints(p_cv.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, d)
    return px.reshape(-1, 2)


def box_level(
    depth: float, ox: float, oy: float, yaw: float, length: float = L_M, width: float = W_M
) -> tuple[np.ndarray, np.ndarray]:
    """Top (FL, FR, RR, RL) and bottom corners of the AGV box in the level frame."""
    loc = np.array(
        [
            [length / 2, -width / 2],
            [length / 2, width / 2],
            [-length / 2, width / 2],
            [-length / 2, -width / 2],
        ]
    )
    c, s = math.cos(yaw), math.sin(yaw)
    xy = loc @ np.array([[c, s], [-s, c]]) + [ox, oy]
    top = np.column_stack([xy, np.full(4, depth)])
    return top, top + np.array([0.0, 0.0, H_M])


def _inset(poly: np.ndarray, delta: float) -> np.ndarray:
    """Move the edges of a convex polygon inwards by ``delta`` px (fillPoly also fills the
    pixels its outline touches: half a supersampled pixel)."""
    p = np.asarray(poly, float)
    area2 = np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1])
    sgn = 1.0 if area2 > 0 else -1.0
    lines = []
    for i in range(len(p)):
        a, b = p[i], p[(i + 1) % len(p)]
        t = (b - a) / np.linalg.norm(b - a)
        lines.append((a - delta * sgn * np.array([t[1], -t[0]]), t))
    out = []
    for i in range(len(p)):
        (p1, t1), (p2, t2) = lines[i - 1], lines[i]
        s_ = np.linalg.solve(np.column_stack([t1, -t2]), p2 - p1)
        out.append(p1 + s_[0] * t1)
    return np.array(out)


def fill_supersampled(img: np.ndarray, polys: list[tuple[np.ndarray, int]], pad: int = 4) -> None:
    """Fill convex polygons ((N, 2) (col, row), grey level) with exact-ish area coverage."""
    allp = np.vstack([p for p, _ in polys])
    h, w = img.shape
    c0 = max(math.floor(allp[:, 0].min()) - pad, 0)
    r0 = max(math.floor(allp[:, 1].min()) - pad, 0)
    c1 = min(math.ceil(allp[:, 0].max()) + pad, w - 1)
    r1 = min(math.ceil(allp[:, 1].max()) + pad, h - 1)
    crop = img[r0 : r1 + 1, c0 : c1 + 1]
    hi = cv2.resize(crop, None, fx=SS, fy=SS, interpolation=cv2.INTER_NEAREST)
    for p, value in polys:
        q = (_inset(p, 0.5 / SS) - [c0, r0] + 0.5) * SS - 0.5
        cv2.fillPoly(hi, [np.round(q * 16).astype(np.int32)], int(value), cv2.LINE_8, shift=4)
    img[r0 : r1 + 1, c0 : c1 + 1] = cv2.resize(
        hi, (crop.shape[1], crop.shape[0]), interpolation=cv2.INTER_AREA
    )


def render_box(
    seed: int,
    top_level: np.ndarray,
    bottom_level: np.ndarray,
    phi: float,
    theta: float,
    dist: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Image and true top corners (col, row) of the box seen by a tilted camera."""
    pt = project(to_camera(top_level, phi, theta), dist)
    pb = project(to_camera(bottom_level, phi, theta), dist)
    hull = cv2.convexHull(np.vstack([pt, pb]).astype(np.float32)).reshape(-1, 2)
    img = ground(seed)
    fill_supersampled(img, [(hull.astype(np.float64), 35), (pt, 225)])
    return img, pt


def degrade(img: np.ndarray, noise_std: float, blur_sigma_px: float, seed: int) -> np.ndarray:
    out = img.astype(np.float64)
    if blur_sigma_px > 0:
        out = cv2.GaussianBlur(out, (0, 0), blur_sigma_px)
    if noise_std > 0:
        out = out + np.random.default_rng(seed).normal(0.0, noise_std, out.shape)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def set_error_px(found: np.ndarray, true: np.ndarray) -> float:
    """Largest corner error after the best one-to-one matching (corners as sets)."""
    best = math.inf
    for perm in itertools.permutations(range(4)):
        best = min(best, float(np.max(np.linalg.norm(found[list(perm)] - true, axis=1))))
    return best


def pose_ok(top: np.ndarray, bottom: np.ndarray, phi: float, theta: float, margin: float) -> bool:
    pts = np.vstack([project(to_camera(top, phi, theta)), project(to_camera(bottom, phi, theta))])
    return bool(
        pts.min() >= margin
        and pts[:, 0].max() <= W - 1 - margin
        and pts[:, 1].max() <= H - 1 - margin
    )


poses = st.tuples(
    st.floats(1.5, 5.0),  # depth of the top below the camera (m)
    st.floats(-0.5, 0.5),  # lateral offsets as a fraction of the depth
    st.floats(-0.5, 0.5),
    st.floats(-math.pi, math.pi),  # AGV yaw
    st.floats(-0.3, 0.3),  # camera roll
    st.floats(-0.3, 0.3),  # camera pitch
    st.integers(0, 10_000),  # background
)


def _scene(pose: tuple[float, float, float, float, float, float, int]):
    depth, fx, fy, yaw, phi, theta, seed = pose
    top, bottom = box_level(depth, fx * depth, fy * depth, yaw)
    return top, bottom, phi, theta, seed


# ---------------------------------------------------------------------------------------------
# Rectangle detector


def side_band_px(top_px: np.ndarray, bottom_px: np.ndarray) -> np.ndarray:
    """(4, 2) outward thickness (px) of the box's side face below top edge i (corner i ->
    i+1), at both ends of the edge; <= 0 where the face is hidden behind the top."""
    area2 = np.sum(
        top_px[:, 0] * np.roll(top_px[:, 1], -1) - np.roll(top_px[:, 0], -1) * top_px[:, 1]
    )
    sgn = 1.0 if area2 > 0 else -1.0
    out = np.zeros((4, 2))
    for i in range(4):
        a, b = top_px[i], top_px[(i + 1) % 4]
        t = (b - a) / np.linalg.norm(b - a)
        n_out = sgn * np.array([t[1], -t[0]])
        out[i] = [(bottom_px[i] - a) @ n_out, (bottom_px[(i + 1) % 4] - a) @ n_out]
    return out


def corner_tolerance_px(top_px: np.ndarray, bottom_px: np.ndarray) -> np.ndarray:
    """Per-corner bound: 0.5 px, or 0.75 px next to a side face imaged thinner than 1.5 px.

    Such a sliver is ambiguous at the pixel level: the edge pixel mixes top, dark side and
    ground, and no edge-profile measure can tell a thin sliver from an edge further in.
    Measured over 1500 random poses (yaw 0 and pi/2 over-represented): 5258 corners away
    from slivers, worst 0.25 px; 394 corners next to one, worst 0.56 px (p99 0.35).
    """
    band = side_band_px(top_px, bottom_px)
    thin = np.any((band > 0) & (band < 1.5), axis=1)  # per edge
    near = thin | np.roll(thin, 1)  # corner k touches edges k - 1 and k
    return np.where(near, 0.75, 0.5)


@settings(max_examples=40, deadline=None)
@given(poses)
@example(pose=(4.75, 0.0703125, 0.5, 0.0, 0.09375, 0.25, 1))  # a 0.6 px sliver: 0.50 px
def test_rectangle_corners_within_half_a_pixel(pose) -> None:
    top, bottom, phi, theta, seed = _scene(pose)
    assume(pose_ok(top, bottom, phi, theta, margin=8))
    img, true = render_box(seed, top, bottom, phi, theta)
    det = RectangleDetector(L_M, W_M).detect(img)
    assert det is not None
    # order: the true FL, FR, RR, RL up to the rectangle's half-turn symmetry
    errs = [np.linalg.norm(np.roll(det.corners_px, -k, 0) - true, axis=1) for k in (0, 2)]
    err = min(errs, key=lambda e: float(e.max()))
    bottom_px = project(to_camera(bottom, phi, theta))
    assert np.all(err < corner_tolerance_px(true, bottom_px)), err
    assert 0.5 < det.quality <= 1.0


FIXED_POSES = [
    (1.6, 0.1, -0.2, 0.3, 0.1, -0.2, 1),
    (2.0, 0.0, 0.0, 0.785, 0.0, 0.0, 2),
    (2.5, -0.3, 0.25, -1.2, -0.25, 0.15, 3),
    (3.0, 0.35, 0.3, 2.9, 0.2, 0.3, 4),
    (3.5, -0.2, -0.35, 1.7, -0.3, -0.3, 5),
    (4.0, 0.3, -0.1, -2.5, 0.05, 0.25, 6),
    (4.5, -0.1, 0.4, 0.1, 0.3, -0.1, 7),
    (5.0, 0.2, 0.2, -0.6, -0.15, 0.0, 8),
]


@pytest.mark.parametrize(
    ("noise_std", "blur_sigma_px", "bound_px"),
    # Measured worst corner error (px) on these 8 poses / on 100 random poses (seeded):
    # clean 0.16 / 0.28; noise 10: 0.16 / 0.28; noise 20: 0.24 / 0.43; blur 1.0: 0.18 / 0.64;
    # blur 1.5: 0.30 / 0.94; noise 10 + blur 1.5: 0.36 / 0.80; blur 2.0: 0.57 / 1.23.
    # Blur hurts most where a box side shows as a thin dark band next to the top: blurred,
    # it no longer has a plateau to read the outside level from.
    [
        (0.0, 0.0, 0.5),
        (5.0, 0.0, 0.5),
        (10.0, 0.0, 0.5),
        (20.0, 0.0, 0.5),
        (0.0, 1.0, 0.5),
        (0.0, 1.5, 0.75),
        (10.0, 1.5, 0.75),
        (0.0, 2.0, 1.0),
    ],
)
def test_noise_and_blur_degrade_gracefully(
    noise_std: float, blur_sigma_px: float, bound_px: float
) -> None:
    detector = RectangleDetector(L_M, W_M)
    errors = []
    for i, pose in enumerate(FIXED_POSES):
        top, bottom, phi, theta, seed = _scene(pose)
        assert pose_ok(top, bottom, phi, theta, margin=8)
        img, true = render_box(seed, top, bottom, phi, theta)
        det = detector.detect(degrade(img, noise_std, blur_sigma_px, seed=i))
        assert det is not None, f"pose {i} lost"
        errors.append(set_error_px(det.corners_px, true))
    assert max(errors) < bound_px, errors


def test_bgr_input_gives_the_mono_result() -> None:
    top, bottom, phi, theta, seed = _scene(FIXED_POSES[2])
    img, _ = render_box(seed, top, bottom, phi, theta)
    det = RectangleDetector(L_M, W_M)
    a = det.detect(img)
    b = det.detect(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    assert a is not None and b is not None
    np.testing.assert_allclose(a.corners_px, b.corners_px, atol=1e-9)


def test_empty_image_is_lost_with_a_reason() -> None:
    det = RectangleDetector(L_M, W_M)
    report = det.analyse(ground(3))
    assert report.detection is None and "no bright region" in report.reason
    res = Perception(CAM, CFG.target).process(ground(3), t_us=42)
    assert (res.status, res.t_us, res.points_m) == ("lost", 42, None)


def test_partial_target_at_the_border_is_rejected() -> None:
    # the box straddles the left image border
    top, bottom = box_level(2.0, 0.0, -1.82, 0.4)
    img, true = render_box(5, top, bottom, 0.0, 0.0)
    assert true[:, 0].min() < 0 < true[:, 0].max()
    report = RectangleDetector(L_M, W_M).analyse(img)
    assert report.detection is None
    assert any("border" in r for r in report.reasons), report.reasons
    res = Perception(CAM, CFG.target).process(img)
    assert res.status == "rejected" and "border" in res.reason


def _bright(img: np.ndarray, poly: np.ndarray) -> np.ndarray:
    fill_supersampled(img, [(poly, 225)])
    return img


def test_tiny_blob_is_rejected_as_too_small() -> None:
    img = _bright(
        ground(4), np.array([[500.2, 500.1], [509.3, 500.4], [509.1, 507.9], [500.0, 508.2]])
    )
    report = RectangleDetector(L_M, W_M).analyse(img)
    assert report.detection is None and "too small" in report.reason


def test_round_blob_is_not_a_quadrilateral() -> None:
    img = ground(5)
    cv2.circle(img, (400, 600), 40, 225, -1, cv2.LINE_AA)
    report = RectangleDetector(L_M, W_M).analyse(img)
    assert report.detection is None
    assert "quadrilateral" in report.reason, report.reason


def test_wrong_aspect_ratio_is_rejected() -> None:
    img = _bright(
        ground(6), np.array([[300.0, 300.0], [600.0, 320.0], [597.0, 360.0], [297.0, 340.0]])
    )
    report = RectangleDetector(L_M, W_M).analyse(img)
    assert report.detection is None and "aspect ratio" in report.reason, report.reason


def test_the_target_is_found_among_distractors() -> None:
    top, bottom, phi, theta, seed = _scene(FIXED_POSES[1])
    img, true = render_box(seed, top, bottom, phi, theta)
    cv2.circle(img, (150, 150), 30, 230, -1, cv2.LINE_AA)
    fill_supersampled(
        img, [(np.array([[800.0, 800.0], [806.0, 800.0], [806.0, 806.0], [800.0, 806.0]]), 230)]
    )
    report = RectangleDetector(L_M, W_M).analyse(img)
    assert report.detection is not None
    assert set_error_px(report.detection.corners_px, true) < 0.5
    assert len(report.rejections) == 2


def test_corner_order_is_held_through_a_full_turn() -> None:
    """With the previous frame's corners as hint the order follows the AGV: FL stays FL."""
    perception = Perception(CAM, CFG.target)
    for k, yaw in enumerate(np.arange(0.0, 2 * math.pi + 0.01, 0.15)):
        if k % 5 == 4:  # a lost frame now and then must not reset the order
            assert perception.process(ground(k)).status == "lost"
            continue
        top, bottom = box_level(2.5, 0.2, -0.1, float(yaw))
        img, true = render_box(k, top, bottom, 0.05, -0.05)
        res = perception.process(img)
        assert res.status == "ok", res.reason
        assert res.corners_px is not None
        assert float(np.max(np.linalg.norm(res.corners_px - true, axis=1))) < 0.5, yaw


# ---------------------------------------------------------------------------------------------
# Metric coordinates (spec section 1) end to end


@settings(max_examples=15, deadline=None)
@given(poses)
def test_points_m_are_the_spec_image_coordinates(pose) -> None:
    top, bottom, phi, theta, seed = _scene(pose)
    assume(pose_ok(top, bottom, phi, theta, margin=8))
    img, _ = render_box(seed, top, bottom, phi, theta)
    res = Perception(CAM, CFG.target).process(img, t_us=7)
    assert res.status == "ok" and res.points_m is not None and res.corners_px is not None
    p_c = to_camera(top, phi, theta)
    expected = np.column_stack([LAM * p_c[:, 0] / p_c[:, 2], LAM * p_c[:, 1] / p_c[:, 2]])
    # the pixel bounds on the image plane (1 px = pixel_size), corners in the detector's order
    err = min(
        (np.linalg.norm(np.roll(res.points_m, -k, 0) - expected, axis=1) for k in (0, 2)),
        key=lambda e: float(e.max()),
    )
    tol = corner_tolerance_px(project(p_c), project(to_camera(bottom, phi, theta)))
    assert np.all(err < tol * CAM.pixel_size_m), err / CAM.pixel_size_m
    np.testing.assert_allclose(res.corners_undistorted_px, res.corners_px)


def test_desired_pose_gives_the_papers_a_star() -> None:
    """Spec section 3: the 0.5 x 0.4 m top seen from 2 m gives a = mu20 + mu02 = 8.036e-7."""
    for yaw in (0.0, 0.7, 2.0):
        top, bottom = box_level(2.0, 0.0, 0.0, yaw)
        img, _ = render_box(9, top, bottom, 0.0, 0.0)
        res = Perception(CAM, CFG.target).process(img)
        assert res.points_m is not None
        d = res.points_m - res.points_m.mean(axis=0)
        a = float(np.sum(d**2))
        assert a == pytest.approx(8.036e-7, rel=2e-3)


def test_pixels_to_metric_convention() -> None:
    from companion.perception import camera_model

    model = camera_model(CAM)
    pts = np.array([[CX, CY], [CX + 100.0, CY], [CX, CY - 100.0]])  # centre, right, up
    um = pixels_to_metric(pts, model)
    np.testing.assert_allclose(um[0], [0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(um[1], [0.0, 100 * CAM.pixel_size_m])  # right = +n
    np.testing.assert_allclose(um[2], [100 * CAM.pixel_size_m, 0.0])  # up = +u (forward)
    # the same numbers as the core's camera, for any pixel
    from companion.core.geometry import PinholeCamera

    rand = np.random.default_rng(0).uniform(0, W - 1, (50, 2))
    core = PinholeCamera.from_config(CAM).opencv_to_metric(rand)
    np.testing.assert_allclose(pixels_to_metric(rand, model), core, rtol=1e-12, atol=1e-18)


def test_pixels_to_metric_few_points_bit_identical() -> None:
    """A detection's corners take the plain-float path; its values are the array path's bit
    for bit (a replay of a log flown before must reproduce every command)."""
    from companion.core.geometry import opencv_to_spec_pixel
    from companion.perception import camera_model

    model = camera_model(CAM)
    rng = np.random.default_rng(3)
    for n in (1, 4, 8, 9):
        p = rng.uniform(0, W - 1, (n, 2))
        u_px, n_px = opencv_to_spec_pixel(p[:, 0], p[:, 1], model.cx_px, model.cy_px)
        ref = np.column_stack([model.focal_length_m * u_px / model.fy_px,
                               model.focal_length_m * n_px / model.fx_px])
        got = pixels_to_metric(p, model)
        assert got.shape == ref.shape and got.dtype == np.float64
        assert got.tobytes() == ref.tobytes()


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_detection_rejects_non_finite_corners(bad: float) -> None:
    from companion.perception import Detection

    c = np.array([[10.0, 10.0], [50.0, 10.0], [50.0, 40.0], [10.0, 40.0]])
    d = Detection(c, 0.9, 1200.0)
    assert d.corners_px.tobytes() == c.tobytes() and not d.corners_px.flags.writeable
    c[2, 1] = bad
    with pytest.raises(PerceptionError, match="non-finite"):
        Detection(c, 0.9, 1200.0)


def test_wrong_image_size_is_rejected() -> None:
    res = Perception(CAM, CFG.target).process(np.zeros((480, 640), np.uint8))
    assert res.status == "rejected" and "640x480" in res.reason


# ---------------------------------------------------------------------------------------------
# ArUco


def _marker_image(
    dict_name: str, marker_id: int, cell_px: int = 60, quiet_cells: int = 2
) -> tuple[np.ndarray, int]:
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dict_name))
    side = (d.markerSize + 2) * cell_px
    marker = cv2.aruco.generateImageMarker(d, marker_id, side, borderBits=1)
    pad = quiet_cells * cell_px  # white quiet zone
    return cv2.copyMakeBorder(marker, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255), pad


def render_marker(
    img: np.ndarray, corners_px: np.ndarray, dict_name: str, marker_id: int, quiet_cells: int = 2
) -> None:
    """Warp a generated marker (outer border corners TL, TR, BR, BL -> ``corners_px``) into
    ``img`` by a homography, supersampled 8x and area-averaged."""
    tex, pad = _marker_image(dict_name, marker_id, quiet_cells=quiet_cells)
    side = tex.shape[0] - 2 * pad
    src = np.array(
        [
            [pad - 0.5, pad - 0.5],
            [pad + side - 0.5, pad - 0.5],
            [pad + side - 0.5, pad + side - 0.5],
            [pad - 0.5, pad + side - 0.5],
        ]
    )
    s = 8
    c0 = max(math.floor(corners_px[:, 0].min()) - 40, 0)
    r0 = max(math.floor(corners_px[:, 1].min()) - 40, 0)
    c1 = min(math.ceil(corners_px[:, 0].max()) + 40, img.shape[1] - 1)
    r1 = min(math.ceil(corners_px[:, 1].max()) + 40, img.shape[0] - 1)
    crop = img[r0 : r1 + 1, c0 : c1 + 1]
    hi = cv2.resize(crop, None, fx=s, fy=s, interpolation=cv2.INTER_NEAREST)
    dst = (corners_px - [c0, r0] + 0.5) * s - 0.5
    hmat = cv2.getPerspectiveTransform(src.astype(np.float32), dst.astype(np.float32))
    cv2.warpPerspective(
        tex,
        hmat,
        (hi.shape[1], hi.shape[0]),
        dst=hi,
        flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_TRANSPARENT,
    )
    img[r0 : r1 + 1, c0 : c1 + 1] = cv2.resize(
        hi, (crop.shape[1], crop.shape[0]), interpolation=cv2.INTER_AREA
    )


@settings(max_examples=15, deadline=None)
@given(
    st.floats(1.5, 3.0),
    st.floats(-0.3, 0.3),
    st.floats(-0.3, 0.3),
    st.floats(-math.pi, math.pi),
    st.floats(-0.3, 0.3),
    st.floats(-0.3, 0.3),
    st.integers(0, 10_000),
)
def test_aruco_id_and_corners(depth, fx, fy, yaw, phi, theta, seed) -> None:
    size = CFG.target.aruco_size_m
    top, _ = box_level(depth, fx * depth, fy * depth, yaw, size, size)
    true = project(to_camera(top, phi, theta))
    assume(true.min() > 60 and true.max() < W - 61)
    img = ground(seed)
    render_marker(img, true, CFG.target.aruco_dictionary, CFG.target.aruco_id)
    det = ArucoDetector(CFG.target.aruco_dictionary, CFG.target.aruco_id, size).detect(img)
    assert det is not None and det.marker_id == CFG.target.aruco_id
    # the marker's own corner order is FL, FR, RR, RL: no symmetry to match away
    assert float(np.max(np.linalg.norm(det.corners_px - true, axis=1))) < 0.5


def test_aruco_wrong_id_is_ignored() -> None:
    top, _ = box_level(2.0, 0.0, 0.0, 0.3, 0.4, 0.4)
    true = project(to_camera(top, 0.0, 0.0))
    img = ground(11)
    render_marker(img, true, "DICT_4X4_50", 3)
    report = ArucoDetector("DICT_4X4_50", 7, 0.4).analyse(img)
    assert report.detection is None and "marker id 3" in report.reason
    other = ArucoDetector("DICT_4X4_50", 3, 0.4).detect(img)
    assert other is not None and other.marker_id == 3
    aruco_cfg = replace(CFG.target, pattern="aruco")
    res = Perception(CAM, aruco_cfg).process(img)
    assert res.status == "rejected"
    res3 = Perception(CAM, replace(aruco_cfg, aruco_id=3)).process(img)
    assert res3.status == "ok" and res3.points_m is not None
    h = aruco_cfg.aruco_size_m / 2  # the marker's own corners, from the config
    np.testing.assert_allclose(
        Perception(CAM, aruco_cfg).target_points_m, [[h, -h], [h, h], [-h, h], [-h, -h]],
    )


def test_aruco_search_paths_agree() -> None:
    """The bright-region search, the whole-frame search and cv2's own sub-pixel corners
    (no edge refinement) find the same marker."""
    top, _ = box_level(2.2, 0.3, -0.4, 1.1, 0.4, 0.4)
    true = project(to_camera(top, 0.1, -0.2))
    img = ground(12)
    render_marker(img, true, "DICT_4X4_50", 7)
    fast = ArucoDetector("DICT_4X4_50", 7, 0.4).detect(img)
    full = ArucoDetector("DICT_4X4_50", 7, 0.4, roi_threshold=None).detect(img)
    cv2_only = ArucoDetector("DICT_4X4_50", 7, 0.4, refine_edges=False).detect(img)
    assert fast is not None and full is not None and cv2_only is not None
    np.testing.assert_allclose(fast.corners_px, full.corners_px, atol=1e-3)
    assert fast.flags == () and fast.quality == 1.0
    assert cv2_only.flags == ("subpix corners",) and cv2_only.quality == 0.8
    assert float(np.max(np.linalg.norm(cv2_only.corners_px - true, axis=1))) < 0.5
    assert float(np.max(np.linalg.norm(fast.corners_px - true, axis=1))) < 0.15


def test_aruco_without_quiet_zone_on_a_dark_side_is_rejected() -> None:
    """A 0.4 m marker on the 0.4 m wide AGV top: its black border touches the dark box side
    on two edges, and cv2's quad swallows the side (8 px errors measured on the emulator)."""
    top, bottom = box_level(2.5, -0.6, 0.0, 0.0, 0.4, 0.4)
    true = project(to_camera(top, 0.0, 0.0))
    pb = project(to_camera(bottom, 0.0, 0.0))
    img = ground(14)
    hull = cv2.convexHull(np.vstack([true, pb]).astype(np.float32)).reshape(-1, 2)
    fill_supersampled(img, [(hull.astype(np.float64), 35)])
    render_marker(img, true, "DICT_4X4_50", 7, quiet_cells=0)
    report = ArucoDetector("DICT_4X4_50", 7, 0.4).analyse(img)
    assert report.detection is None and "quiet zone" in report.reason, report
    # what accepting cv2's own corners would have meant
    raw = ArucoDetector("DICT_4X4_50", 7, 0.4, refine_edges=False).detect(img)
    assert raw is not None
    assert float(np.max(np.linalg.norm(raw.corners_px - true, axis=1))) > 2.0


def test_aruco_bad_config_is_a_clear_error() -> None:
    with pytest.raises(PerceptionError, match="DICT_NOPE"):
        ArucoDetector("DICT_NOPE", 1, 0.4)
    with pytest.raises(PerceptionError, match="aruco_id"):
        ArucoDetector("DICT_4X4_50", 50, 0.4)


# ---------------------------------------------------------------------------------------------
# Calibration


DIST = np.array([-0.28, 0.09, 0.0012, -0.0009, -0.012])


def _write_calibration(path: Path, k: np.ndarray, d: np.ndarray, size=(W, H)) -> None:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("calibration_time", "test")
    fs.write("image_width", size[0])
    fs.write("image_height", size[1])
    fs.write("camera_matrix", k)
    fs.write("distortion_coefficients", d.reshape(-1, 1))
    fs.write("avg_reprojection_error", 0.2)
    fs.release()


@pytest.mark.parametrize("suffix", [".yaml", ".json", ".xml"])
def test_undistortion_recovers_pinhole_positions(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"cam{suffix}"
    _write_calibration(path, K, DIST)
    cal = load_calibration(path)
    assert cal.image_size_px == (W, H)
    np.testing.assert_allclose(cal.camera_matrix, K)
    np.testing.assert_allclose(cal.dist_coeffs, DIST)
    rng = np.random.default_rng(0)
    # points over the whole field of view, out to the image corners (84 deg FoV)
    xy = rng.uniform(-0.85, 0.85, (400, 2))
    p_c = np.column_stack([xy, np.ones(len(xy))]) * rng.uniform(1.0, 5.0, (len(xy), 1))
    distorted = project(p_c, DIST)
    inside = (distorted.min(axis=1) >= 0) & (distorted[:, 0] <= W - 1) & (distorted[:, 1] <= H - 1)
    assert inside.sum() > 300
    ideal = project(p_c[inside])
    got = cal.undistort_px(distorted[inside])
    assert float(np.max(np.linalg.norm(got - ideal, axis=1))) < 0.05


def test_perception_with_a_calibrated_distorting_camera(tmp_path: Path) -> None:
    path = tmp_path / "cam.yaml"
    _write_calibration(path, K, DIST)
    cam = replace(CAM, calibration_file=str(path))
    top, bottom = box_level(2.5, 0.6, -0.5, 0.4)
    # the renderer draws straight edges between the distorted corners: the corners are exact
    img, distorted = render_box(13, top, bottom, 0.0, 0.0, dist=DIST)
    res = Perception(cam, CFG.target).process(img)
    assert res.status == "ok" and res.corners_undistorted_px is not None
    assert res.points_m is not None
    ideal = project(top)
    assert set_error_px(res.corners_px, distorted) < 0.5
    assert set_error_px(res.corners_undistorted_px, ideal) < 0.5
    expected = np.column_stack([LAM * top[:, 0] / top[:, 2], LAM * top[:, 1] / top[:, 2]])
    assert set_error_px(res.points_m / CAM.pixel_size_m, expected / CAM.pixel_size_m) < 0.5


def test_calibration_errors_name_the_problem(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="not found"):
        load_calibration(tmp_path / "missing.yaml")
    garbage = tmp_path / "garbage.yaml"
    garbage.write_text("this is { not [ opencv")
    with pytest.raises(CalibrationError, match=r"garbage\.yaml"):
        load_calibration(garbage)
    no_k = tmp_path / "no_k.yaml"
    fs = cv2.FileStorage(str(no_k), cv2.FILE_STORAGE_WRITE)
    fs.write("distortion_coefficients", DIST)
    fs.release()
    with pytest.raises(CalibrationError, match="missing camera_matrix"):
        load_calibration(no_k)
    no_d = tmp_path / "no_d.yaml"
    fs = cv2.FileStorage(str(no_d), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", K)
    fs.release()
    with pytest.raises(CalibrationError, match="distortion_coefficients"):
        load_calibration(no_d)
    bad_k = tmp_path / "bad_k.yaml"
    _write_calibration(bad_k, np.eye(2), DIST)
    with pytest.raises(CalibrationError, match="3x3"):
        load_calibration(bad_k)
    bad_d = tmp_path / "bad_d.yaml"
    _write_calibration(bad_d, K, np.zeros(3))
    with pytest.raises(CalibrationError, match="distortion_coefficients"):
        load_calibration(bad_d)
    other_size = tmp_path / "vga.yaml"
    _write_calibration(other_size, K, DIST, size=(640, 480))
    with pytest.raises(PerceptionError, match="640"):
        Perception(replace(CAM, calibration_file=str(other_size)), CFG.target)
    with pytest.raises(CalibrationError, match="fx"):
        Calibration(np.diag([0.0, 1.0, 1.0]), np.zeros(5))
