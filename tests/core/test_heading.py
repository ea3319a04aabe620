"""s4 for a square target (ArUco): from the ordered corners, since its moments carry none."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

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
    DegenerateTargetError,
    heading_from_ordered_corners,
    image_moments,
    unwrap_angle,
)

LAM = 2.8e-3
A_STAR = 1.0e-7


def _marker_virtual(psi_a: float, pos_q: np.ndarray, phi: float, theta: float,
                    psi_q: float, size: float = 0.3) -> np.ndarray:
    """A square marker (FL, FR, RR, RL, heading psi_a) on the ground, seen by a tilted camera,
    mapped to the virtual image: exactly what perception + spec 2 deliver."""
    local = rectangle_corners_m(size, size)
    world = np.column_stack([(rot_z(psi_a)[:2, :2] @ local.T).T, np.zeros(4)])
    real = project_points(world_to_camera(world, pos_q, rotation_zyx(phi, theta, psi_q)), LAM)
    return real_points_to_virtual(real, phi, theta, LAM)


@settings(max_examples=150, deadline=None)
@given(psi_a=st.floats(-math.pi, math.pi), psi_q=st.floats(-math.pi, math.pi),
       phi=st.floats(-0.2, 0.2), theta=st.floats(-0.2, 0.2),
       x=st.floats(-0.5, 0.5), y=st.floats(-0.5, 0.5), h=st.floats(1.5, 4.0))
def test_heading_from_corners_is_the_relative_yaw(psi_a: float, psi_q: float, phi: float,
                                                  theta: float, x: float, y: float,
                                                  h: float) -> None:
    pts = _marker_virtual(psi_a, np.array([x, y, -h]), phi, theta, psi_q)
    got = heading_from_ordered_corners(pts)
    assert wrap_pi(got - (psi_a - psi_q)) == pytest.approx(0.0, abs=1e-9)
    s = image_moments(pts, A_STAR, LAM, None, heading_from_corners=True).s
    assert wrap_pi(s[3] - (psi_a - psi_q)) == pytest.approx(0.0, abs=1e-9)


def test_moments_alone_cannot_orient_a_square() -> None:
    """Why the corner heading exists: the square's moment orientation does not follow its yaw."""
    for a in (0.0, 0.3, 0.6):
        m = image_moments(_marker_virtual(a, np.array([0.0, 0.0, -2.0]), 0.0, 0.0, 0.0),
                          A_STAR, LAM)
        assert m.anisotropy < 1e-9  # mu20 = mu02, mu11 = 0 whatever the yaw
    head = [image_moments(_marker_virtual(a, np.array([0.0, 0.0, -2.0]), 0.0, 0.0, 0.0),
                          A_STAR, LAM, heading_from_corners=True).s[3] for a in (0.0, 0.3, 0.6)]
    assert np.allclose(head, [0.0, 0.3, 0.6], atol=1e-9)


def test_heading_unwraps_over_a_full_turn() -> None:
    prev = None
    out = []
    for a in np.linspace(0.0, 4.0 * math.pi, 200):
        pts = _marker_virtual(float(a), np.array([0.1, -0.1, -2.5]), 0.05, -0.05, 0.0)
        prev = image_moments(pts, A_STAR, LAM, prev, heading_from_corners=True).s[3]
        out.append(prev)
    assert np.allclose(out, np.linspace(0.0, 4.0 * math.pi, 200), atol=1e-9)
    assert unwrap_angle(-3.1, 3.1, 2 * math.pi) == pytest.approx(-3.1 + 2 * math.pi)


def test_heading_refuses_bad_points() -> None:
    with pytest.raises(DegenerateTargetError):
        heading_from_ordered_corners(np.zeros((3, 2)))
    with pytest.raises(DegenerateTargetError):
        heading_from_ordered_corners(np.array([[0, 0], [0, 0], [0, 0], [0, 0.0]]))
