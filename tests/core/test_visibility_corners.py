"""Whole-target visibility (docs/reference/visibility.md): the corner rows, the heading-in-cost
tube and the planned-yaw target motion, each against an independent oracle or a case that must
fail."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.config import Config, load_config
from companion.core.geometry import (
    project_points,
    rectangle_corners_m,
    rotation_zyx,
    world_to_camera,
)
from companion.core.moments import fold_s4
from companion.core.params import RmpcParams
from companion.core.prediction import predict_target_motion
from companion.core.rmpc import Rmpc, RmpcResult, TargetMotion, check_solution, planned_motion
from companion.core.rmpc_problem import corner_gain, corner_points, stage_motion, tube_matrix
from companion.core.terminal import TerminalDesign


def _params(cfg: Config, **kw: object) -> RmpcParams:
    return dataclasses.replace(cfg.rmpc, **kw)  # type: ignore[arg-type]


@settings(max_examples=60, deadline=None)
@given(
    x=st.floats(-1.0, 1.0), y=st.floats(-1.0, 1.0), depth=st.floats(1.0, 4.0),
    yaw_q=st.floats(-np.pi, np.pi), yaw_a=st.floats(-np.pi, np.pi),
)
def test_corner_points_equal_the_level_camera_projection(
    cfg: Config, x: float, y: float, depth: float, yaw_q: float, yaw_a: float
) -> None:
    """p_i from (s_e, s3, s4) equals projecting the target's world corners into a level camera
    at the vehicle's yaw (the virtual camera), normalised: exact, for any pose."""
    z_star = cfg.rmpc.desired_depth_m
    cam = np.array([0.0, 0.0, -depth])
    centre = np.array([x, y, 0.0])
    c = rectangle_corners_m(cfg.target.length_m, cfg.target.width_m)
    rz = rotation_zyx(0.0, 0.0, yaw_a)[:2, :2]
    world = np.array([[*(centre[:2] + rz @ ci), 0.0] for ci in c])
    img = project_points(world_to_camera(world, cam, rotation_zyx(0.0, 0.0, yaw_q)), 1.0)
    d = rotation_zyx(0.0, 0.0, yaw_q).T @ (centre - cam)
    eta = np.array([d[0] / z_star, d[1] / z_star, depth / z_star - 1.0, yaw_a - yaw_q,
                    0.0, 0.0, 0.0])
    got = np.array(corner_points(eta, cfg.rmpc), dtype=float)
    assert np.allclose(got, img, atol=1e-12)


def _hover_result(eta: np.ndarray, cfg: Config) -> RmpcResult:
    """A 'prediction' resting at ``eta`` with level inputs (so M(u) = 0)."""
    n = cfg.rmpc.horizon
    tm = TargetMotion.constant([0.0, 0.0], [0.0, 0.0], 0.0, n)
    eta_p = np.tile(eta, (n + 1, 1))
    u = np.zeros((n, 4))
    return RmpcResult(True, "optimal", "", "", 0.0, 0, 0.0, u[0], eta_p, u, 0.0,
                      ("visibility",), tm)


def test_a_corner_outside_violates_the_corner_rows_not_the_centroid_row(
    cfg: Config, design: TerminalDesign
) -> None:
    """Centroid 0.40 from the centre (inside r_v = 0.45), at the desired depth: the corners
    reach 0.40 + 0.16 > 0.45, so the corner rows are violated and the centroid row is not."""
    eta = np.array([0.40 * 2.0 / 2.0, 0.0, 0.0, np.pi / 4, 0.0, 0.0, 0.0])
    res = _hover_result(eta, cfg)
    corners = _params(cfg, visibility="corners")
    centroid = _params(cfg, visibility="centroid")
    bad = check_solution(res, corners, cfg.camera, design, groups=("visibility",))
    assert bad and {v.constraint for v in bad} == {"visibility"}
    worst = max(np.hypot(*p) for p in corner_points(eta, corners))
    # the violation is the overshoot plus the tightening (k_c times the paper's margin, < 0.01)
    assert worst - design.r_v <= max(v.amount for v in bad) <= worst - design.r_v + 0.01
    assert check_solution(res, centroid, cfg.camera, design, groups=("visibility",)) == []
    # and well inside, both admit it
    inside = _hover_result(np.array([0.1, 0.0, 0.0, 0.3, 0.0, 0.0, 0.0]), cfg)
    assert check_solution(inside, corners, cfg.camera, design, groups=("visibility",)) == []


def test_corner_gain_is_the_derivation(cfg: Config) -> None:
    """k_c = sqrt(1 + (c_max/z*)^2 + p_max^2) / s3_min >= 1/s3_min, recomputed by hand."""
    k = corner_gain(cfg.rmpc, cfg.camera)
    c_max = np.hypot(0.25, 0.2)
    s3_min = cfg.rmpc.min_depth_m / cfg.rmpc.desired_depth_m
    assert k > np.sqrt(1 + (c_max / 2.0) ** 2 + cfg.camera.r_v**2) / s3_min
    assert k < np.sqrt(1 + (c_max / 2.0) ** 2 + (2 * cfg.camera.r_v) ** 2) / s3_min
    # a corner point moves at most k_c |d eta| (sampled): the tightening covers the disturbance
    rng = np.random.default_rng(3)
    for _ in range(200):
        eta = np.array([*rng.uniform(-0.2, 0.2, 2), rng.uniform(-0.3, 0.5),
                        rng.uniform(-np.pi, np.pi), 0.0, 0.0, 0.0])
        d = rng.normal(size=7)
        d[4:] = 0.0
        d *= 1e-4 / np.linalg.norm(d)
        a = np.array(corner_points(eta, cfg.rmpc))
        b = np.array(corner_points(eta + d, cfg.rmpc))
        assert np.max(np.hypot(*(b - a).T)) <= k * 1e-4 * (1 + 1e-6)


def test_heading_in_cost_removes_s4_from_the_tube(cfg: Config, design: TerminalDesign) -> None:
    """P_r is P minimised over s4 (Schur complement): checked against a 1-D minimisation."""
    p = np.asarray(design.p)
    pr = tube_matrix(_params(cfg, heading="cost"), p)
    assert np.array_equal(tube_matrix(_params(cfg, heading="tube"), p), p)
    rng = np.random.default_rng(1)
    for _ in range(20):
        eta = rng.normal(size=7)
        grid = np.linspace(-20, 20, 40001)
        vals = [(e := eta.copy(), e.__setitem__(3, s4), e @ p @ e)[2] for s4 in grid[::400]]
        s4_opt = -(p[3, :] @ eta - p[3, 3] * eta[3]) / p[3, 3]
        e = eta.copy()
        e[3] = s4_opt
        assert eta @ pr @ eta == pytest.approx(e @ p @ e, rel=1e-9)
        assert eta @ pr @ eta <= min(vals) + 1e-12
        e[3] = 123.0  # s4 does not matter
        assert e @ pr @ e == pytest.approx(eta @ pr @ eta, rel=1e-9)


def test_planned_yaw_motion_matches_the_prediction_for_any_planned_yaw() -> None:
    """stage_motion('planned_yaw') at a planned yaw offset theta equals predicting the target
    from a vehicle whose yaw is theta off the nominal, with vdot_a at the planned yaw rate."""
    v_ned, a_ned, w, yaw_q = np.array([0.6, -0.4, 0.0]), np.array([0.05, 0.1, 0.0]), 0.4, 0.7
    cfg = load_config()
    rp = _params(cfg, target_motion="planned_yaw")
    nominal = predict_target_motion(v_ned, a_ned, w, yaw_q, 4, 0.05)
    # the acceleration the unicycle model carries: along-track kept, cross-track from w
    t_hat = v_ned[:2] / np.linalg.norm(v_ned[:2])
    a_model = (a_ned[:2] @ t_hat) * t_hat + np.linalg.norm(v_ned[:2]) * w * np.array(
        [-t_hat[1], t_hat[0]])
    s4_ref = 0.3
    for theta, psidot_q in ((0.0, w), (0.35, 0.1), (-1.2, -0.3)):
        x = np.array([0.0, 0.0, 0.0, s4_ref - theta, 0.0, 0.0, 0.0])
        u = np.array([0.0, 0.0, 0.0, psidot_q])
        v_a, vdot_a, _ = stage_motion(rp, x, u, *nominal.stage(0), s4_ref)
        c, s = np.cos(yaw_q + theta), np.sin(yaw_q + theta)
        rzt = np.array([[c, s], [-s, c]])
        v_true = rzt @ v_ned[:2]
        vdot_true = rzt @ a_model + psidot_q * np.array([v_true[1], -v_true[0]])
        assert np.allclose(v_a, v_true, atol=1e-12)
        assert np.allclose(vdot_a, vdot_true, atol=1e-12)
    # nominal ignores the plan
    rn = _params(cfg, target_motion="nominal")
    x = np.array([0.0, 0.0, 0.0, s4_ref - 0.35, 0.0, 0.0, 0.0])
    v_a, _, _ = planned_motion(rn, x, np.zeros(4), nominal, 0, s4_ref)
    assert np.allclose(v_a, nominal.v_a_m_s[0])


def test_fold_s4_keeps_the_yaw_error_bounded_with_hysteresis() -> None:
    assert fold_s4(None, np.pi) is None
    assert fold_s4(1.7, np.pi) == 1.7  # inside pi/2 + 0.25: untouched
    assert fold_s4(1.9, np.pi) == pytest.approx(1.9 - np.pi)
    assert fold_s4(-7.0, 2 * np.pi) == pytest.approx(-7.0 + 2 * np.pi)
    assert fold_s4(10.0, np.pi) == pytest.approx(10.0 - 3 * np.pi)


def test_corner_rmpc_keeps_every_predicted_corner_where_the_centroid_rmpc_does_not(
    cfg: Config, design: TerminalDesign
) -> None:
    """From a start near the edge of the visible area (centroid 0.22 ahead, every corner inside
    at 0.38 < r_v = 0.45, at the desired depth, the target moving away at 0.35 m/s): the
    centroid RMPC's optimal plan accelerates after it and, tilting, puts corners outside their
    disc; the corner RMPC's plan meets every corner row."""
    eta0 = np.array([0.22, 0.0, 0.0, 0.0, -0.35, 0.0, 0.0])
    tm = TargetMotion.constant([0.35, 0.0], [0.0, 0.0], 0.0, cfg.rmpc.horizon)
    corners = _params(cfg, visibility="corners")
    centroid = _params(cfg, visibility="centroid")
    res_c = Rmpc(centroid, cfg.camera, design).solve(eta0, tm)
    res_k = Rmpc(corners, cfg.camera, design).solve(eta0, tm)
    assert res_k.mode == "optimal" and res_c.mode == "optimal"
    assert check_solution(res_k, corners, cfg.camera, design) == []
    assert check_solution(res_c, centroid, cfg.camera, design) == []
    bad = check_solution(res_c, corners, cfg.camera, design, groups=("visibility",))
    assert bad, "the centroid plan keeps every corner inside: the case is too easy"
