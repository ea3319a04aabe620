"""Image moments of spec section 3 against the geometry they stand for (spec 9, section 3)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from companion.core.errors import CoreError
from companion.core.geometry import (
    project_points,
    real_points_to_virtual,
    rectangle_corners_m,
    rot_z,
    rotation_zyx,
    world_to_camera,
    wrap_pi,
)
from companion.core.moments import (
    COLLINEAR_REL_TOL,
    DegenerateTargetError,
    ImageMoments,
    a_star,
    image_moments,
    orientation_raw,
    unwrap_s4,
)

LAM = 2.8e-3
Z_STAR = 2.0
AGV = rectangle_corners_m(0.5, 0.4)
A_STAR = a_star(AGV, Z_STAR, LAM)


def test_a_star_is_the_papers_value() -> None:
    assert f"{A_STAR:.4g}" == "8.036e-07"
    # Analytic: lam^2 / z*^2 * sum |p - p_bar|^2 = 1.96e-6 * (0.25 + 0.16).
    assert pytest.approx(LAM**2 / Z_STAR**2 * 0.41, rel=1e-14) == A_STAR


def _world_target(centre: np.ndarray, yaw: float, pts2: np.ndarray) -> np.ndarray:
    xy = pts2 @ rot_z(yaw)[:2, :2].T + centre[:2]
    return np.column_stack([xy, np.full(len(xy), centre[2])])


def _virtual_points(world: np.ndarray, pos: np.ndarray, phi: float, theta: float,
                    psi: float) -> np.ndarray:
    real = project_points(world_to_camera(world, pos, rotation_zyx(phi, theta, psi)), LAM)
    return real_points_to_virtual(real, phi, theta, LAM)


small = st.floats(-0.35, 0.35)


@st.composite
def scene(draw: st.DrawFn) -> tuple[np.ndarray, float, float, float, np.ndarray, float]:
    pos = np.array([draw(st.floats(-3, 3)), draw(st.floats(-3, 3)), draw(st.floats(-6, -1.5))])
    phi, theta, psi = draw(small), draw(small), draw(st.floats(-math.pi, math.pi))
    # Target centre on the plane z = 0, within +-0.6 of the height horizontally.
    h = -pos[2]
    centre = pos + np.array([draw(st.floats(-0.6, 0.6)) * h, draw(st.floats(-0.6, 0.6)) * h, h])
    return pos, phi, theta, psi, centre, draw(st.floats(-math.pi, math.pi))


@given(scene())
def test_features_are_the_centroid_in_v_over_z_star(
    case: tuple[np.ndarray, float, float, float, np.ndarray, float],
) -> None:
    pos, phi, theta, psi, centre, yaw_a = case
    world = _world_target(centre, yaw_a, AGV)
    m = image_moments(_virtual_points(world, pos, phi, theta, psi), A_STAR, LAM)
    x_v, y_v, z = rot_z(psi).T @ (centre - pos)
    np.testing.assert_allclose(m.s[:3], [x_v / Z_STAR, y_v / Z_STAR, z / Z_STAR], rtol=1e-9,
                               atol=1e-12)
    # s4 is the target's yaw relative to the camera's, modulo the rectangle's symmetry (pi).
    assert math.remainder(m.s[3] - (yaw_a - psi), math.pi) == pytest.approx(0, abs=1e-9)
    assert -math.pi / 2 < m.s[3] <= math.pi / 2


@given(
    case=scene(),
    pts=st.lists(st.tuples(st.floats(-0.5, 0.5), st.floats(-0.5, 0.5)), min_size=3, max_size=8),
)
def test_s1_s2_s3_for_any_planar_point_set(
    case: tuple[np.ndarray, float, float, float, np.ndarray, float],
    pts: list[tuple[float, float]],
) -> None:
    pos, phi, theta, psi, centre, yaw_a = case
    p2 = np.asarray(pts)
    p2 = p2 - p2.mean(axis=0)  # centre = the points' centroid
    try:
        a_s = a_star(p2, Z_STAR, LAM)
    except DegenerateTargetError:
        assume(False)  # a collinear random draw: degenerate targets are tested below
        raise
    world = _world_target(centre, yaw_a, p2)
    m = image_moments(_virtual_points(world, pos, phi, theta, psi), a_s, LAM)
    x_v, y_v, z = rot_z(psi).T @ (centre - pos)
    np.testing.assert_allclose(m.s[:3], [x_v / Z_STAR, y_v / Z_STAR, z / Z_STAR], rtol=1e-8,
                               atol=1e-10)


def test_moments_at_the_desired_pose() -> None:
    # Level, 2 m above the AGV top, aligned: s = s_r = [0, 0, 1, 0].
    world = _world_target(np.array([0.0, 0.0, 2.0]), 0.0, AGV)
    m = image_moments(_virtual_points(world, np.zeros(3), 0.0, 0.0, 0.0), A_STAR, LAM)
    np.testing.assert_allclose(m.s, [0, 0, 1, 0], atol=1e-15)
    assert m.mu20 > m.mu02 and m.mu11 == pytest.approx(0, abs=1e-25)
    assert m.anisotropy == pytest.approx(0.09 / 0.41, rel=1e-12)
    assert m.n_points == 4
    with pytest.raises(ValueError):
        m.s[0] = 1.0  # read-only


@given(perm=st.permutations(range(4)), psi=st.floats(-3, 3))
def test_moments_do_not_depend_on_point_order(perm: list[int], psi: float) -> None:
    world = _world_target(np.array([0.3, -0.2, 2.5]), 0.4, AGV)
    pts = _virtual_points(world, np.zeros(3), 0.1, -0.05, psi)
    a = image_moments(pts, A_STAR, LAM)
    b = image_moments(pts[perm], A_STAR, LAM)
    np.testing.assert_allclose(a.s, b.s, rtol=1e-12, atol=1e-15)


# ---------------------------------------------------------------------------------------------
# s4 unwrapping


def test_s4_unwrapped_over_a_full_rotation() -> None:
    rel = np.arange(0.0, 2 * math.pi + 0.5, 0.05)  # the target turns once under the camera
    prev: float | None = None
    raw: list[float] = []
    for r in rel:
        world = _world_target(np.array([0.1, 0.05, 2.0]), float(r), AGV)
        pts = _virtual_points(world, np.zeros(3), 0.05, -0.08, 0.0)
        m = image_moments(pts, A_STAR, LAM, s4_prev_rad=prev)
        raw.append(image_moments(pts, A_STAR, LAM).s[3])
        assert m.s[3] == pytest.approx(r, abs=1e-9)
        prev = float(m.s[3])
    # Without unwrapping s4 jumps by pi (the test above would fail).
    assert np.max(np.abs(np.diff(raw))) > 3.0


@given(raw=st.floats(-math.pi / 2, math.pi / 2), prev=st.floats(-50, 50))
def test_unwrap_s4_picks_the_nearest_branch(raw: float, prev: float) -> None:
    out = unwrap_s4(raw, prev)
    assert math.remainder(out - raw, math.pi) == pytest.approx(0, abs=1e-9)
    assert abs(out - prev) <= math.pi / 2 + 1e-9
    assert unwrap_s4(raw, None) == raw


def test_orientation_raw_range() -> None:
    assert orientation_raw(1.0, 0.5, 0.0) == 0.0
    assert orientation_raw(0.5, 1.0, 0.0) == pytest.approx(math.pi / 2)
    assert orientation_raw(1.0, 1.0, 0.3) == pytest.approx(math.pi / 4)
    assert wrap_pi(orientation_raw(1.0, 1.0, -0.3)) == pytest.approx(-math.pi / 4)


# ---------------------------------------------------------------------------------------------
# Degenerate targets


GOOD = np.array([[1e-4, 1e-4], [3e-4, 1e-4], [3e-4, 2.5e-4], [1e-4, 2.5e-4]])


@pytest.mark.parametrize(
    "pts",
    [
        GOOD[:2],  # two points
        np.zeros((0, 2)),
        GOOD[:, :1],  # wrong shape
        np.array([[1e-4, 1e-4], [math.nan, 1e-4], [3e-4, 2e-4]]),
        np.array([[1e-4, 1e-4], [math.inf, 1e-4], [3e-4, 2e-4]]),
        np.array([[1e-4, 1e-4]] * 4),  # coincident
        np.array([[1e-4, 1e-4], [2e-4, 2e-4], [3e-4, 3e-4], [5e-4, 5e-4]]),  # collinear
        np.array([[0, 0], [1e-4, 0], [2e-4, 1e-13], [3e-4, 0]]),  # nearly collinear
    ],
)
def test_degenerate_targets_raise(pts: np.ndarray) -> None:
    with pytest.raises(DegenerateTargetError) as exc:
        image_moments(pts, A_STAR, LAM)
    assert isinstance(exc.value, CoreError)


def test_collinear_tolerance_is_relative() -> None:
    # The same thin triangle at any scale: degenerate below the tolerance, fine above it.
    for scale in (1e-6, 1e-4, 1e-2):
        thin = np.array([[0, 0], [1, 0], [0.5, 0.5 * COLLINEAR_REL_TOL]]) * scale + 1e-4
        with pytest.raises(DegenerateTargetError):
            image_moments(thin, A_STAR, LAM)
        ok = np.array([[0, 0], [1, 0], [0.5, 1e3 * COLLINEAR_REL_TOL]]) * scale + 1e-4
        assert isinstance(image_moments(ok, A_STAR, LAM), ImageMoments)


def test_bad_parameters_raise() -> None:
    for a_s, lam in ((0.0, LAM), (math.nan, LAM), (A_STAR, 0.0), (A_STAR, math.inf)):
        with pytest.raises(DegenerateTargetError):
            image_moments(GOOD, a_s, lam)
    with pytest.raises(DegenerateTargetError):
        a_star(AGV[:2], Z_STAR, LAM)
    with pytest.raises(DegenerateTargetError):
        a_star(AGV, 0.0, LAM)
    with pytest.raises(DegenerateTargetError):
        a_star(np.array([[0.0, math.nan], [1, 0], [0, 1]]), Z_STAR, LAM)
    with pytest.raises(DegenerateTargetError):
        unwrap_s4(0.1, math.nan)
