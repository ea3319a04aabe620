"""The measured error state eta_e and the target-motion parameters (spec section 4)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from companion.config import load_config
from companion.core.geometry import (
    PinholeCamera,
    camera_to_body_rotation,
    project_points,
    rectangle_corners_m,
    rot_z,
    rotation_zyx,
    world_to_camera,
)
from companion.core.moments import DegenerateTargetError, a_star
from companion.core.state import (
    MeasurementError,
    build_error_state,
    ned_to_virtual,
    target_motion_in_virtual,
)

PAPER_ETA0 = [0.0159, -0.2230, 0.6, 0.3927, -0.1307, -0.0541, 0.0]


def _agv_paper_velocity(t: float) -> tuple[np.ndarray, np.ndarray, float]:
    """x_a = 0.1 t, y_a = 4 sin(0.025 t): velocity, acceleration (NED) and heading rate."""
    xd, yd = 0.1, 4 * 0.025 * math.cos(0.025 * t)
    xdd, ydd = 0.0, -4 * 0.025**2 * math.sin(0.025 * t)
    psidot = (xd * ydd - yd * xdd) / (xd * xd + yd * yd)
    return np.array([xd, yd, 0.0]), np.array([xdd, ydd, 0.0]), psidot


def _corners_world(centre: np.ndarray, yaw: float, length: float, width: float) -> np.ndarray:
    xy = rectangle_corners_m(length, width) @ rot_z(yaw)[:2, :2].T + centre[:2]
    return np.column_stack([xy, np.full(4, centre[2])])


@pytest.mark.parametrize(
    "overrides",
    [[], ["camera.width_px=2000", "camera.height_px=2000", "camera.pixel_size_m=2.52e-6"]],
    ids=["1000px_5.04um", "2000px_2.52um"],
)
@pytest.mark.parametrize("tilt", [(0.0, 0.0), (0.12, -0.2)], ids=["level", "tilted"])
def test_paper_initial_state(overrides: list[str], tilt: tuple[float, float]) -> None:
    cfg = load_config(overrides=overrides)
    cam = PinholeCamera.from_config(cfg.camera)
    lam = cfg.camera.focal_length_m
    pos = np.array([-0.2, 0.4, -3.2])
    phi, theta, psi = tilt[0], tilt[1], math.pi / 8
    corners = _corners_world(np.zeros(3), math.pi / 4, cfg.target.length_m, cfg.target.width_m)
    # The detector's view: OpenCV pixels of the four corners, then back to metric.
    px = cam.project_to_opencv(world_to_camera(corners, pos, rotation_zyx(phi, theta, psi)))
    assert np.all((px > 0) & (px < cfg.camera.width_px))
    v_a, a_a, psidot_a = _agv_paper_velocity(0.0)
    st_ = build_error_state(
        cam.opencv_to_metric(px),
        roll_rad=phi, pitch_rad=theta, yaw_rad=psi, yaw_rate_rad_s=0.0,
        v_q_ned_m_s=np.zeros(3), v_a_ned_m_s=v_a, a_a_ned_m_s2=a_a, psidot_a_rad_s=psidot_a,
        a_star=a_star(rectangle_corners_m(0.5, 0.4), cfg.rmpc.desired_depth_m, lam), lam=lam,
    )
    np.testing.assert_allclose(st_.eta_e, PAPER_ETA0, atol=1e-4)
    np.testing.assert_allclose(st_.s_e, st_.s - [0, 0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(st_.v_e_m_s, st_.v_q_v_m_s - st_.v_a_v_m_s, atol=1e-15)
    assert st_.v_a_v_m_s[2] == 0.0
    with pytest.raises(ValueError):
        st_.eta_e[0] = 0.0


angle = st.floats(-math.pi, math.pi)
vec = st.tuples(st.floats(-3, 3), st.floats(-3, 3), st.floats(-1, 1))


@given(psi0=angle, psidot=st.floats(-1.5, 1.5), v0=vec, a0=vec, psidot_a=st.floats(-1, 1))
def test_vdot_a_is_the_rotating_frame_derivative(
    psi0: float, psidot: float, v0: tuple[float, float, float], a0: tuple[float, float, float],
    psidot_a: float,
) -> None:
    """d/dt [Rz(psi)^T v_a]_xy by central differences equals TargetMotion.vdot_a."""
    v0a, a0a = np.asarray(v0), np.asarray(a0)

    def v_in_v(t: float) -> np.ndarray:
        return (rot_z(psi0 + psidot * t).T @ (v0a + a0a * t))[:2]

    h = 1e-5
    fd = (v_in_v(h) - v_in_v(-h)) / (2 * h)
    m = target_motion_in_virtual(v0a, a0a, psidot_a, psi0, psidot)
    np.testing.assert_allclose(m.vdot_a_m_s2, fd, atol=1e-8)
    np.testing.assert_allclose(m.v_a_m_s, v_in_v(0.0), atol=1e-15)
    np.testing.assert_allclose(m.accel_a_v_m_s2, (rot_z(psi0).T @ a0a)[:2], atol=1e-15)
    assert m.psidot_a_rad_s == psidot_a
    # The opposite sign of the rotation term is detectably wrong whenever it matters.
    assume(abs(psidot) * math.hypot(v0[0], v0[1]) > 1e-3)
    wrong = m.accel_a_v_m_s2 - psidot * np.array([m.v_a_m_s[1], -m.v_a_m_s[0]])
    assert np.max(np.abs(wrong - fd)) > 1e-3


def test_ned_to_virtual_known_value() -> None:
    # Yaw 90 deg: north is the camera's left (-y), east its forward (+x).
    np.testing.assert_allclose(ned_to_virtual([1, 0, 0], math.pi / 2), [0, -1, 0], atol=1e-15)
    np.testing.assert_allclose(ned_to_virtual([0, 1, 0.5], math.pi / 2), [1, 0, 0.5], atol=1e-15)


@given(
    mount=st.tuples(st.floats(-0.2, 0.2), st.floats(-0.2, 0.2), st.floats(-math.pi, math.pi)),
    att=st.tuples(st.floats(-0.3, 0.3), st.floats(-0.3, 0.3), angle),
)
def test_mounted_camera_gives_the_same_state(
    mount: tuple[float, float, float], att: tuple[float, float, float]
) -> None:
    lam = 2.8e-3
    pos = np.array([0.3, -0.1, -2.5])
    corners = _corners_world(np.zeros(3), 0.3, 0.5, 0.4)
    r_nb = rotation_zyx(*att)
    r_bc = camera_to_body_rotation(mount)
    common = dict(
        roll_rad=att[0], pitch_rad=att[1], yaw_rad=att[2], yaw_rate_rad_s=0.2,
        v_q_ned_m_s=[0.1, 0.2, -0.1], v_a_ned_m_s=[0.3, 0.0, 0.0], a_a_ned_m_s2=[0, 0.1, 0],
        psidot_a_rad_s=0.05, a_star=8.036e-7, lam=lam,
    )
    plain = build_error_state(project_points(world_to_camera(corners, pos, r_nb), lam), **common)
    mounted_pts = project_points(world_to_camera(corners, pos, r_nb @ r_bc), lam)
    mounted = build_error_state(mounted_pts, cam_to_body=r_bc, **common)
    np.testing.assert_allclose(mounted.eta_e, plain.eta_e, rtol=1e-9, atol=1e-12)


GOOD_PTS = np.array([[1e-4, 1e-4], [3e-4, 1e-4], [3e-4, 2.5e-4], [1e-4, 2.5e-4]])
BASE = dict(
    roll_rad=0.0, pitch_rad=0.0, yaw_rad=0.0, yaw_rate_rad_s=0.0, v_q_ned_m_s=[0, 0, 0],
    v_a_ned_m_s=[0, 0, 0], a_a_ned_m_s2=[0, 0, 0], psidot_a_rad_s=0.0, a_star=8.036e-7,
    lam=2.8e-3,
)


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("roll_rad", math.nan), ("yaw_rad", math.inf), ("yaw_rate_rad_s", math.nan),
        ("v_q_ned_m_s", [0, math.nan, 0]), ("v_a_ned_m_s", [math.inf, 0, 0]),
        ("a_a_ned_m_s2", [0, 0, math.nan]), ("psidot_a_rad_s", math.nan),
        ("v_q_ned_m_s", [0, 0]),
    ],
)
def test_bad_measurements_are_refused(key: str, value: object) -> None:
    assert build_error_state(GOOD_PTS, **BASE).eta_e.shape == (7,)
    with pytest.raises(MeasurementError):
        build_error_state(GOOD_PTS, **{**BASE, key: value})


def test_bad_points_are_refused() -> None:
    with pytest.raises(DegenerateTargetError):
        build_error_state(GOOD_PTS[:2], **BASE)
    with pytest.raises(DegenerateTargetError):
        build_error_state(np.where(np.eye(4, 2) > 0, math.nan, GOOD_PTS), **BASE)
