"""Geometry of spec sections 1-2: rotations, quaternions, projection, pixel mapping, mount."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from companion.config import load_config
from companion.core.errors import CoreError
from companion.core.geometry import (
    GeometryError,
    PinholeCamera,
    camera_points_to_body_image,
    camera_position_ned,
    camera_to_body_rotation,
    euler_zyx_from_quat,
    euler_zyx_from_rotation,
    metric_to_normalised,
    metric_to_opencv,
    metric_to_pixel,
    normalised_to_metric,
    opencv_to_metric,
    opencv_to_spec_pixel,
    pixel_to_metric,
    principal_point_px,
    project_points,
    quat_from_euler_zyx,
    quat_from_rotation,
    real_points_to_virtual,
    real_to_virtual,
    rot_x,
    rot_y,
    rot_z,
    rotation_from_quat,
    rotation_zyx,
    spec_pixel_to_opencv,
    visible_area_centre,
    world_to_camera,
    wrap_pi,
)

LAM = 2.8e-3
angle = st.floats(-math.pi, math.pi, allow_nan=False)
tilt = st.floats(-0.6, 0.6, allow_nan=False)
pitch_ok = st.floats(-1.55, 1.55, allow_nan=False)


def _scipy_zyx(phi: float, theta: float, psi: float) -> Rotation:
    # Intrinsic Z-Y-X (capital letters) = Rz(psi) Ry(theta) Rx(phi).
    return Rotation.from_euler("ZYX", [psi, theta, phi])


# ---------------------------------------------------------------------------------------------
# Rotations and quaternions


@given(phi=angle, theta=pitch_ok, psi=angle)
def test_rotation_zyx_matches_scipy_and_is_proper(phi: float, theta: float, psi: float) -> None:
    r = rotation_zyx(phi, theta, psi)
    np.testing.assert_allclose(r, _scipy_zyx(phi, theta, psi).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(r, rot_z(psi) @ rot_y(theta) @ rot_x(phi), atol=0)


def test_rotation_known_values_frd_ned() -> None:
    # Yaw 90 deg: the nose (body x) points east.
    np.testing.assert_allclose(rotation_zyx(0, 0, math.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    # Roll 90 deg right: the right wing (body y) points down.
    np.testing.assert_allclose(rotation_zyx(math.pi / 2, 0, 0) @ [0, 1, 0], [0, 0, 1], atol=1e-15)
    # Pitch +10 deg is nose up: body x gets a negative (upward) NED z component.
    th = math.radians(10)
    np.testing.assert_allclose(
        rotation_zyx(0, th, 0) @ [1, 0, 0], [math.cos(th), 0, -math.sin(th)], atol=1e-15
    )


@given(phi=angle, theta=pitch_ok, psi=angle)
def test_quaternion_matches_scipy_and_rotation(phi: float, theta: float, psi: float) -> None:
    q = quat_from_euler_zyx(phi, theta, psi)
    assert q[0] >= 0 and np.linalg.norm(q) == pytest.approx(1.0, abs=1e-14)
    x, y, z, w = _scipy_zyx(phi, theta, psi).as_quat()
    ref = np.array([w, x, y, z])
    ref = -ref if ref[0] < 0 else ref
    np.testing.assert_allclose(q, ref, atol=1e-12)
    np.testing.assert_allclose(rotation_from_quat(q), rotation_zyx(phi, theta, psi), atol=1e-12)


@given(phi=angle, theta=st.floats(-1.5, 1.5), psi=angle)
def test_euler_quaternion_round_trip(phi: float, theta: float, psi: float) -> None:
    q = quat_from_euler_zyx(phi, theta, psi)
    p2, t2, y2 = euler_zyx_from_quat(q)
    assert wrap_pi(p2 - phi) == pytest.approx(0, abs=1e-9)
    assert t2 == pytest.approx(theta, abs=1e-9)
    assert wrap_pi(y2 - psi) == pytest.approx(0, abs=1e-9)
    p3, t3, y3 = euler_zyx_from_rotation(rotation_zyx(phi, theta, psi))
    assert (wrap_pi(p3 - phi), t3 - theta, wrap_pi(y3 - psi)) == pytest.approx((0, 0, 0), abs=1e-9)
    np.testing.assert_allclose(quat_from_rotation(rotation_from_quat(q)), q, atol=1e-12)


@given(q=st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(
    lambda v: np.linalg.norm(v) > 1e-3))
def test_quat_from_rotation_all_branches(q: list[float]) -> None:
    qn = np.asarray(q) / np.linalg.norm(q)
    qn = -qn if qn[0] < 0 else qn
    out = quat_from_rotation(rotation_from_quat(qn))
    # q and -q are the same rotation; when w == 0 either sign is canonical.
    assert min(np.linalg.norm(out - qn), np.linalg.norm(out + qn)) < 1e-9


def test_quaternion_known_values() -> None:
    s = math.sqrt(0.5)
    np.testing.assert_allclose(quat_from_euler_zyx(0, 0, math.pi / 2), [s, 0, 0, s], atol=1e-15)
    np.testing.assert_allclose(quat_from_euler_zyx(math.pi / 2, 0, 0), [s, s, 0, 0], atol=1e-15)
    np.testing.assert_allclose(quat_from_euler_zyx(0, math.pi / 2, 0), [s, 0, s, 0], atol=1e-15)
    np.testing.assert_allclose(quat_from_euler_zyx(0, 0, 0), [1, 0, 0, 0], atol=0)


def test_quaternion_refuses_bad_values() -> None:
    with pytest.raises(GeometryError):
        rotation_from_quat([0, 0, 0, 0])
    with pytest.raises(GeometryError):
        rotation_from_quat([1, math.nan, 0, 0])
    with pytest.raises(CoreError):
        quat_from_euler_zyx(0, math.inf, 0)


@given(a=st.floats(-100, 100))
def test_wrap_pi(a: float) -> None:
    w = wrap_pi(a)
    assert -math.pi < w <= math.pi
    assert math.remainder(w - a, 2 * math.pi) == pytest.approx(0, abs=1e-9)


# ---------------------------------------------------------------------------------------------
# Spec 9, section 2: real image -> virtual image equals a level camera at the same yaw


@st.composite
def pose_and_point(draw: st.DrawFn) -> tuple[np.ndarray, float, float, float, np.ndarray]:
    pos = np.array([draw(st.floats(-5, 5)), draw(st.floats(-5, 5)), draw(st.floats(-8, -1))])
    phi, theta, psi = draw(tilt), draw(tilt), draw(angle)
    # A point on the ground plane (z = 0) within 40 deg of the camera's optical axis.
    r = rotation_zyx(phi, theta, psi)
    ax = r @ np.array([0.0, 0.0, 1.0])
    off = np.array([draw(st.floats(-0.8, 0.8)), draw(st.floats(-0.8, 0.8)), 1.0])
    ray = r @ off
    # Tilt and offset together can aim the ray at or above the horizon: such a ray meets no
    # ground point in front of the camera (the generator's domain, not the mapping's).
    assume(ray[2] / np.linalg.norm(ray) > 0.25)
    t = -pos[2] / ray[2]
    point = pos + t * ray
    assert ax[2] > 0
    return pos, phi, theta, psi, point


@given(pose_and_point())
def test_real_to_virtual_equals_level_camera(
    case: tuple[np.ndarray, float, float, float, np.ndarray],
) -> None:
    pos, phi, theta, psi, point = case
    real = project_points(world_to_camera(point, pos, rotation_zyx(phi, theta, psi)), LAM)
    virt = real_points_to_virtual(real, phi, theta, LAM)
    level = project_points(world_to_camera(point, pos, rot_z(psi)), LAM)
    np.testing.assert_allclose(virt, level, rtol=1e-9, atol=1e-9 * LAM)
    # The scalar function agrees with the array wrapper.
    uv, nv = real_to_virtual(real[0, 0], real[0, 1], phi, theta, LAM)
    np.testing.assert_allclose([uv, nv], virt[0], rtol=1e-15, atol=0)


def test_real_to_virtual_refuses_rays_above_horizon() -> None:
    # Pitched 60 deg nose up, a ray towards the image's top edge points above the horizon.
    with pytest.raises(GeometryError):
        real_points_to_virtual([[3 * LAM, 0.0]], 0.0, math.radians(60), LAM)
    with pytest.raises(GeometryError):
        project_points([[0.0, 0.0, -1.0]], LAM)
    with pytest.raises(GeometryError):
        real_points_to_virtual([[math.nan, 0.0]], 0.0, 0.0, LAM)


def test_visible_area_centre_is_origin_at_hover() -> None:
    mu, mn = visible_area_centre(0.0, 0.0, 1.26e-3, 1.26e-3, LAM)
    assert (mu, mn) == (0.0, 0.0)


# ---------------------------------------------------------------------------------------------
# Image coordinates


def test_spec_pixel_mapping_orientation() -> None:
    cx, cy = principal_point_px(1000, 1000)
    assert (cx, cy) == (499.5, 499.5)
    # Forward (u > 0) is up in the image (smaller row); right (n > 0) is a larger column.
    col, row = spec_pixel_to_opencv(10.0, 0.0, cx, cy)
    assert (col, row) == (cx, cy - 10.0)
    col, row = spec_pixel_to_opencv(0.0, 7.0, cx, cy)
    assert (col, row) == (cx + 7.0, cy)


pix = st.floats(-3000, 3000, allow_nan=False)


@given(u=pix, n=pix, cx=st.floats(0, 2000), cy=st.floats(0, 2000))
def test_pixel_round_trips(u: float, n: float, cx: float, cy: float) -> None:
    ps = 5.04e-6
    col, row = spec_pixel_to_opencv(u, n, cx, cy)
    u2, n2 = opencv_to_spec_pixel(col, row, cx, cy)
    assert (u2, n2) == pytest.approx((u, n), abs=1e-9)
    um, nm = pixel_to_metric(u, n, ps)
    assert metric_to_pixel(um, nm, ps) == pytest.approx((u, n), abs=1e-9)
    c2, r2 = metric_to_opencv(um, nm, ps, cx, cy)
    assert (c2, r2) == pytest.approx((col, row), abs=1e-9)
    assert opencv_to_metric(c2, r2, ps, cx, cy) == pytest.approx((um, nm), abs=1e-15)
    un, nn = metric_to_normalised(um, nm, LAM)
    assert normalised_to_metric(un, nn, LAM) == pytest.approx((um, nm), abs=1e-15)


def test_pinhole_camera_from_config_round_trip() -> None:
    cfg = load_config()
    cam = PinholeCamera.from_config(cfg.camera)
    assert cam.focal_length_m == 2.8e-3 and (cam.cx_px, cam.cy_px) == (499.5, 499.5)
    pts_cam = np.array([[0.2, -0.1, 2.0], [0.0, 0.0, 3.0], [-0.3, 0.4, 2.5]])
    cr = cam.project_to_opencv(pts_cam)
    # The optical axis hits the principal point.
    np.testing.assert_allclose(cr[1], [499.5, 499.5], atol=1e-12)
    np.testing.assert_allclose(cam.opencv_to_metric(cr), project_points(pts_cam, LAM), atol=1e-15)
    # 0.2 m forward at 2 m: u = 2.8e-4 m = 55.56 px up from the centre.
    assert cr[0, 1] == pytest.approx(499.5 - 0.2 / 2.0 * 2.8e-3 / 5.04e-6, abs=1e-9)
    with pytest.raises(GeometryError):
        PinholeCamera(0.0, 5e-6, 0, 0)


# ---------------------------------------------------------------------------------------------
# Camera mount


def test_default_mount_is_identity() -> None:
    cfg = load_config()
    np.testing.assert_array_equal(camera_to_body_rotation(cfg.camera.mount_rpy_rad), np.eye(3))
    pts = np.array([[1e-4, -2e-4], [3e-4, 5e-4], [0.0, 0.0]])
    np.testing.assert_allclose(camera_points_to_body_image(pts, np.eye(3), LAM), pts, atol=1e-18)


@given(
    case=pose_and_point(),
    mount=st.tuples(st.floats(-0.3, 0.3), st.floats(-0.3, 0.3), st.floats(-math.pi, math.pi)),
)
def test_mounted_camera_reprojects_to_body_and_virtual(
    case: tuple[np.ndarray, float, float, float, np.ndarray],
    mount: tuple[float, float, float],
) -> None:
    pos, phi, theta, psi, point = case
    r_nb = rotation_zyx(phi, theta, psi)
    r_bc = camera_to_body_rotation(mount)
    offset = np.zeros(3)
    cam_pos = camera_position_ned(pos, r_nb, offset)
    p_cam = world_to_camera(point, cam_pos, r_nb @ r_bc)
    assume(p_cam[0, 2] > 0.05)  # in front of the mounted camera
    seen = project_points(p_cam, LAM)
    body_img = camera_points_to_body_image(seen, r_bc, LAM)
    np.testing.assert_allclose(
        body_img, project_points(world_to_camera(point, pos, r_nb), LAM), rtol=1e-9, atol=1e-14
    )
    virt = real_points_to_virtual(body_img, phi, theta, LAM)
    level = project_points(world_to_camera(point, pos, rot_z(psi)), LAM)
    np.testing.assert_allclose(virt, level, rtol=1e-9, atol=1e-14)


@settings(max_examples=20)
@given(off=st.tuples(st.floats(-0.2, 0.2), st.floats(-0.2, 0.2), st.floats(-0.2, 0.2)),
       psi=angle)
def test_camera_position_offset(off: tuple[float, float, float], psi: float) -> None:
    p = camera_position_ned([1.0, 2.0, -3.0], rot_z(psi), off)
    np.testing.assert_allclose(p, np.array([1.0, 2.0, -3.0]) + rot_z(psi) @ np.asarray(off))
