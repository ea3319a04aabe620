"""Terminal ingredients and the visible-area geometry of spec 6 (and the spec 9 check)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.config import load_config
from companion.core.design import design_terminal
from companion.core.geometry import real_to_virtual, visible_area_centre
from companion.core.terminal import (
    dare_terminal,
    linearised_model,
    terminal_visibility_radius,
    tilt_limits,
)

CFG = load_config()
LAM = CFG.camera.focal_length_m
HALF = CFG.camera.visible_half_m
PHI_MAX, THETA_MAX = tilt_limits(CFG.rmpc.u_max, CFG.rmpc.g_m_s2)


def _quad(phi: float, theta: float) -> np.ndarray:
    """The visible area's corners mapped to the virtual image, normalised (4, 2), in order."""
    c = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]], dtype=float) * HALF
    uv, nv = real_to_virtual(c[:, 0], c[:, 1], phi, theta, LAM)
    return np.column_stack([uv, nv]) / LAM


def _edge_distance(p: np.ndarray, quad: np.ndarray) -> float:
    """Smallest distance from p to the quadrangle's edges (p inside)."""
    best = math.inf
    for i in range(4):
        a, b = quad[i], quad[(i + 1) % 4]
        t = np.clip((p - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
        best = min(best, float(np.linalg.norm(a + t * (b - a) - p)))
    return best


def test_paper_camera_numbers() -> None:
    assert CFG.camera.r_v == pytest.approx(0.45, abs=1e-12)
    assert math.degrees(THETA_MAX) == pytest.approx(10.2, abs=0.05)  # pitch
    assert math.degrees(PHI_MAX) == pytest.approx(10.1, abs=0.05)  # roll
    gamma = design_terminal(CFG.rmpc, CFG.camera).gamma
    assert gamma == pytest.approx(0.242, abs=1e-3)


def test_gamma_against_dense_boundary_sampling() -> None:
    """gamma = distance from the origin to the intersection of the four extreme mapped areas:
    recomputed by sampling their edges densely (an independent route)."""
    gamma = terminal_visibility_radius(PHI_MAX, THETA_MAX, HALF, LAM)
    best = math.inf
    s = np.linspace(0.0, 1.0, 4001)[:, None]
    for phi in (-PHI_MAX, PHI_MAX):
        for theta in (-THETA_MAX, THETA_MAX):
            q = _quad(phi, theta)
            for i in range(4):
                pts = q[i] + s * (q[(i + 1) % 4] - q[i])
                best = min(best, float(np.min(np.linalg.norm(pts, axis=1))))
    assert gamma == pytest.approx(best, abs=1e-6)


def test_circle_about_the_centre_at_hover_touches_the_edges() -> None:
    m = np.array(visible_area_centre(0.0, 0.0, HALF, HALF, LAM))
    assert np.allclose(m, 0.0)
    assert _edge_distance(m, _quad(0.0, 0.0)) == pytest.approx(CFG.camera.r_v, rel=1e-12)


@settings(max_examples=200, deadline=None)
@given(phi=st.floats(-1.0, 1.0), theta=st.floats(-1.0, 1.0))
def test_spec9_circle_about_m_stays_inside_the_mapped_area(phi: float, theta: float) -> None:
    """Spec 9 (section 6): within the tilt limits the r_v circle about M(u) lies inside the
    mapped visible quadrangle; its smallest edge distance is r_v at hover."""
    phi, theta = phi * PHI_MAX, theta * THETA_MAX
    m = np.array(visible_area_centre(phi, theta, HALF, HALF, LAM))
    assert _edge_distance(m, _quad(phi, theta)) >= CFG.camera.r_v - 1e-9


def test_dare_terminal_solves_the_riccati_equation_and_stabilises() -> None:
    a, b = linearised_model(CFG.rmpc.dt_s, CFG.rmpc.desired_depth_m)
    q, r = np.diag(CFG.rmpc.q_diag), np.diag(CFG.rmpc.r_diag)
    t = dare_terminal(a, b, q, r)
    p, k = t.p, t.k
    resid = a.T @ p @ a - p - a.T @ p @ b @ np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a) + q
    assert np.max(np.abs(resid)) < 1e-10 * np.max(np.abs(p))
    assert np.max(np.abs(np.linalg.eigvals(a + b @ k))) < 1.0
    assert np.all(np.linalg.eigvalsh(p) > 0)
