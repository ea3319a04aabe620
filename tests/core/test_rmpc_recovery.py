"""The recovery (soft) copy when the measured state is already outside the state box
(docs/records/2026-11-visibility.md section 5): campaign flights on fast paths
measured the vehicle at 1.1-2.1 m/s against the 1 m/s box; the soft copy with a hard box was
then infeasible at stage 1 and the controller fell back to the terminal law, which ignores the
target. These tests fail on that behaviour."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from companion.config import Config
from companion.core.prediction import predict_target_motion
from companion.core.rmpc import (
    Rmpc,
    TargetMotion,
    check_solution,
    state_lower,
    velocity_box_return,
)
from companion.core.rmpc_problem import tube_matrix
from companion.core.terminal import TerminalDesign


@pytest.fixture(scope="module")
def mpc(cfg: Config, design: TerminalDesign) -> Rmpc:
    # the full NLP's hard-then-soft path (the RTI in front of it: tests/core/test_rmpc_rti.py)
    return Rmpc(dataclasses.replace(cfg.rmpc, solver="nlp"), cfg.camera, design)


def _box(cfg: Config) -> tuple[np.ndarray, np.ndarray]:
    n = cfg.rmpc.horizon
    return (np.tile(state_lower(cfg.rmpc), (n, 1)),
            np.tile(np.asarray(cfg.rmpc.eta_max, dtype=float), (n, 1)))


def test_a_velocity_inside_the_box_leaves_the_box_exactly_as_it_is(cfg: Config) -> None:
    lo, hi = _box(cfg)
    x0 = np.array([0.3, -0.2, 1.2, 0.1, 0.99, -0.99, 0.5])
    lo2, hi2 = velocity_box_return(x0, lo, hi, np.asarray(cfg.rmpc.u_max), cfg.rmpc.dt_s)
    assert np.array_equal(lo2, lo) and np.array_equal(hi2, hi)


def test_an_exceeded_velocity_bound_returns_at_the_admissible_rate(cfg: Config) -> None:
    lo, hi = _box(cfg)
    u_max, dt = np.asarray(cfg.rmpc.u_max), cfg.rmpc.dt_s
    x0 = np.array([0.3, -0.2, 1.2, 0.1, 1.4, -1.2, 0.0])
    lo2, hi2 = velocity_box_return(x0, lo, hi, u_max, dt)
    a_ret = u_max[0] - u_max[3] * 1.4
    n = np.arange(1, cfg.rmpc.horizon + 1)
    assert np.allclose(hi2[:, 4], np.maximum(1.0, 1.4 - n * dt * a_ret))
    assert np.allclose(lo2[:, 5], np.minimum(-1.0, -1.2 + n * dt * (u_max[1] - u_max[3] * 1.4)))
    assert hi2[-1, 4] == 1.0  # back inside the box within the horizon (0.4 m/s at 1.08 m/s^2)
    # everything else untouched: only the exceeded sides move
    assert np.array_equal(lo2[:, 4], lo[:, 4]) and np.array_equal(hi2[:, 5], hi[:, 5])
    assert np.array_equal(lo2[:, :4], lo[:, :4]) and np.array_equal(hi2[:, 6], hi[:, 6])


def test_without_braking_authority_the_bound_moves_out_instead_of_being_infeasible(
    cfg: Config,
) -> None:
    """A target drift larger than the braking authority: the excess may grow at that rate."""
    lo, hi = _box(cfg)
    u_max, dt = np.asarray(cfg.rmpc.u_max), cfg.rmpc.dt_s
    x0 = np.array([0.0, 0.0, 1.0, 0.0, 1.5, 0.0, 0.0])
    _, hi2 = velocity_box_return(x0, lo, hi, u_max, dt, target_drift_m_s2=2.0)
    a_ret = u_max[0] - u_max[3] * 1.5 - 2.0
    assert a_ret < 0
    n = np.arange(1, cfg.rmpc.horizon + 1)
    assert np.allclose(hi2[:, 4], 1.5 - n * dt * a_ret) and np.all(np.diff(hi2[:, 4]) > 0)


def test_recovery_from_above_the_velocity_box_plans_back_into_it_instead_of_falling_back(
    mpc: Rmpc, cfg: Config, design: TerminalDesign
) -> None:
    """A vehicle at 1.3 m/s behind a target at 1.2 m/s (a fast path, the target off-centre):
    the hard problem is infeasible (the box at stage 1 is out of reach); the soft copy must
    still plan, brake at least at the admissible rate and keep every predicted corner row
    (with its slack) instead of returning the terminal law."""
    n_h = cfg.rmpc.horizon
    v_a = np.array([1.2, 0.0])
    target = TargetMotion.constant(v_a, [0.0, 0.0], 0.0, n_h)
    eta0 = np.array([0.25, 0.05, 0.3, 0.0, 0.1, 0.0, 0.0])  # v_q = 1.3 m/s forward
    mpc.reset()
    res = mpc.solve(eta0, target)
    assert res.mode == "recovery", (res.mode, res.status, res.hard_status)
    v_q = res.eta_pred[:, 4] + v_a[0]
    # full braking against the yaw coupling and the planned-yaw drift of v_a (1.2 m/s x 0.3)
    a_ret = cfg.rmpc.u_max[0] - cfg.rmpc.u_max[3] * 1.3 - 1.2 * cfg.rmpc.u_max[3]
    bound = np.maximum(1.0, 1.3 - np.arange(n_h + 1) * cfg.rmpc.dt_s * a_ret)
    assert np.all(v_q[1:] <= bound[1:] + 1e-6)
    assert v_q[-1] <= 1.0 + 1e-6  # back inside the box by the end of the horizon (0.3 / 0.75)
    bad = check_solution(res, cfg.rmpc, cfg.camera, design)
    hard = [v for v in bad if v.constraint in ("dynamics", "input")]
    assert hard == []
    # the box is violated only where the return law allows it
    assert {v.stage for v in bad if v.constraint == "state"} <= set(
        int(k) for k in np.nonzero(bound > 1.0)[0])


def _p_norms(res_eta: np.ndarray, cfg: Config, design: TerminalDesign) -> np.ndarray:
    p = tube_matrix(cfg.rmpc, np.asarray(design.p, dtype=float))
    return np.sqrt(np.einsum("ni,ij,nj->n", res_eta, p, res_eta))


def test_recovery_closes_on_a_target_at_the_edge_of_the_view(
    cfg: Config, design: TerminalDesign
) -> None:
    """A logged state of a campaign flight (circle-2x seed 1, 1.4 s after OFFBOARD): the target
    1.4 m ahead and 1 m to the side at the edge of the visible area, moving at 0.6 m/s on a
    circle, the vehicle matching its velocity 1.6 m too high. The hard problem is infeasible
    (Omega is out of reach in N delta). With the configured recovery weights (tube/terminal
    above visibility) the soft copy must plan to close on the target: accelerate towards it
    and shrink the tube norm over the horizon. With equal weights it did not (the plan's
    |eta(N)|_P grew, the vehicle sat at the edge of the view for ~2.5 s while the target ran
    away, and the corners left the view anyway: docs/records/2026-11-visibility.md section 5)."""
    eta0 = np.array([0.709, -0.512, 0.783, -0.024, -0.013, 0.043, -0.569])
    target = predict_target_motion(np.array([0.527, 0.288, 0.0]), np.array([-0.058, 0.105, 0.0]),
                                   0.2, 0.521, cfg.rmpc.horizon, cfg.rmpc.dt_s)
    mpc = Rmpc(dataclasses.replace(cfg.rmpc, jit=False), cfg.camera, design)
    res = mpc.solve(eta0, target)
    assert res.mode == "recovery", (res.mode, res.status, res.hard_status)
    norms = _p_norms(res.eta_pred, cfg, design)
    assert norms[-1] < 0.75 * norms[0], norms
    assert res.u0[0] > 0.5  # towards the target (se1 > 0: it is ahead)
    bad = check_solution(res, cfg.rmpc, cfg.camera, design)
    assert [v for v in bad if v.constraint in ("dynamics", "input")] == []
    # the same state with equal weights: the plan does not close (why the weights differ)
    equal = Rmpc(dataclasses.replace(cfg.rmpc, jit=False,
                                     recovery_tube_penalty=cfg.rmpc.recovery_penalty),
                 cfg.camera, design)
    res_eq = equal.solve(eta0, target)
    assert res_eq.mode == "recovery"
    assert _p_norms(res_eq.eta_pred, cfg, design)[-1] > 0.95 * norms[0]


def test_a_target_accelerating_to_the_velocity_bound_keeps_the_hard_problem_feasible(
    cfg: Config, design: TerminalDesign
) -> None:
    """A logged state of a campaign flight (stop-and-go-2x seed 1, 6 s after OFFBOARD): the
    vehicle tracks well (|eta0| small) while the AGV accelerates at 0.7 m/s^2 from 0.73 m/s
    to its 1.0 m/s cruise speed. Extrapolated linearly over 0.8 s the target reaches 1.27 m/s,
    beyond the 1 m/s velocity box, so the terminal set is out of reach and the hard problem is
    infeasible although nothing is wrong with the state; with the extrapolation held at the
    bound ("box") it is feasible."""
    eta0 = np.array([0.053, 0.024, 0.061, 0.084, -0.073, 0.023, 0.057])
    args = (np.array([0.727, 0.129, 0.0]), np.array([0.7, 0.115, 0.0]), -0.013, 0.092,
            cfg.rmpc.horizon, cfg.rmpc.dt_s)
    mpc = Rmpc(dataclasses.replace(cfg.rmpc, jit=False), cfg.camera, design)
    linear = predict_target_motion(*args)
    assert np.hypot(*linear.v_a_m_s[-1]) > 1.2
    assert mpc.solve(eta0, linear).mode == "recovery"
    mpc.reset()
    boxed = predict_target_motion(*args, speed_cap_m_s=cfg.rmpc.eta_max[4])
    assert np.hypot(*boxed.v_a_m_s[-1]) == pytest.approx(1.0, abs=1e-9)
    res = mpc.solve(eta0, boxed)
    assert res.mode == "optimal", (res.status, res.hard_status)


def test_the_recovery_input_rate_term_pulls_the_first_input_towards_the_previous_one(
    cfg: Config, design: TerminalDesign
) -> None:
    """rmpc.recovery_input_rate_weight (off by default): the soft copy's first input is drawn
    towards the input the previous step applied, and only when the weight is on. The same
    logged edge state as above is solved right after a state that asked for the opposite
    horizontal input (the target mirrored to the other side)."""
    eta0 = np.array([0.709, -0.512, 0.783, -0.024, -0.013, 0.043, -0.569])
    mirrored = eta0 * np.array([-1, -1, 1, 1, -1, -1, 1])
    target = predict_target_motion(np.array([0.527, 0.288, 0.0]), np.array([-0.058, 0.105, 0.0]),
                                   0.2, 0.521, cfg.rmpc.horizon, cfg.rmpc.dt_s)
    u0 = {}
    prev = {}
    for w in (0.0, 100.0):
        mpc = Rmpc(dataclasses.replace(cfg.rmpc, jit=False, recovery_input_rate_weight=w),
                   cfg.camera, design)
        first = mpc.solve(mirrored, target)
        prev[w] = first.u0
        res = mpc.solve(eta0, target)
        assert res.mode == "recovery", (res.mode, res.status, res.hard_status)
        assert [v for v in check_solution(res, cfg.rmpc, cfg.camera, design)
                if v.constraint in ("dynamics", "input")] == []
        u0[w] = res.u0
        # without a previous input (a fresh controller) the term has nothing to act on
        fresh = Rmpc(dataclasses.replace(cfg.rmpc, jit=False, recovery_input_rate_weight=w),
                     cfg.camera, design).solve(eta0, target)
        if w == 0.0:
            assert np.allclose(fresh.u0, res.u0, atol=1e-4)  # off: the previous step is ignored
    assert np.allclose(prev[0.0], prev[100.0], atol=1e-4)  # the first solve is the same
    assert prev[0.0][0] < 0.0 < u0[0.0][0]  # the two states ask for opposite r1
    scale = np.asarray(cfg.rmpc.u_max)
    dist = {w: float(np.linalg.norm((u0[w] - prev[w]) / scale)) for w in u0}
    assert dist[100.0] < 0.8 * dist[0.0], dist


def test_the_soft_copy_can_have_its_own_weights_and_terminal_level(
    cfg: Config, design: TerminalDesign
) -> None:
    """rmpc.recovery_q_diag / recovery_eps (config/realistic.toml): the soft copy is built from
    its own weights, with P designed from them, while the hard problem keeps the stiff ones.
    Unset, the soft copy is the hard problem's (the same objects)."""
    from companion.core.design import design_terminal
    from companion.core.rmpc import recovery_design

    rmpc, terminal = recovery_design(cfg.rmpc, cfg.camera, design)
    assert rmpc is cfg.rmpc and terminal is design
    stiff = dataclasses.replace(cfg.rmpc, q_diag=(0.15, 0.15, 0.01, 1e-3, 0.05, 0.05, 3e-3),
                                eps=0.4, recovery_q_diag=cfg.rmpc.q_diag, recovery_eps=0.15)
    soft_rmpc, soft_terminal = recovery_design(stiff, cfg.camera,
                                               design_terminal(stiff, cfg.camera))
    assert soft_rmpc.q_diag == cfg.rmpc.q_diag and soft_rmpc.eps == 0.15
    assert np.allclose(soft_terminal.p, design.p) and np.allclose(soft_terminal.k, design.k)
    # the stiff P really is another metric (the reason for the option)
    assert not np.allclose(design_terminal(stiff, cfg.camera).p, design.p, rtol=0.5)
    # flown: the same edge state is a recovery step whose first input follows the soft
    # copy's weights: the paper-weighted soft copy of the stiff controller gives the paper
    # controller's own recovery input
    eta0 = np.array([0.709, -0.512, 0.783, -0.024, -0.013, 0.043, -0.569])
    target = predict_target_motion(np.array([0.527, 0.288, 0.0]), np.array([-0.058, 0.105, 0.0]),
                                   0.2, 0.521, cfg.rmpc.horizon, cfg.rmpc.dt_s)
    paper = Rmpc(dataclasses.replace(cfg.rmpc, jit=False), cfg.camera, design).solve(eta0, target)
    stiff_jit = dataclasses.replace(stiff, jit=False)
    mixed = Rmpc(stiff_jit, cfg.camera, design_terminal(stiff_jit, cfg.camera)).solve(eta0, target)
    assert paper.mode == mixed.mode == "recovery", (paper.mode, mixed.mode)
    assert np.allclose(mixed.u0, paper.u0, atol=1e-3), (mixed.u0, paper.u0)
    alone = dataclasses.replace(stiff_jit, recovery_q_diag=None, recovery_eps=None)
    own = Rmpc(alone, cfg.camera, design_terminal(alone, cfg.camera)).solve(eta0, target)
    assert own.mode == "recovery" and not np.allclose(own.u0, paper.u0, atol=1e-2), own.u0


def test_the_soft_copy_can_relax_the_hard_problems_rows(
    cfg: Config, design: TerminalDesign
) -> None:
    """rmpc.recovery_rows = "hard": the soft copy keeps its own cost (recovery_q_diag,
    recovery_eps) but relaxes the hard problem's tube, visibility and terminal rows, so its
    slacks measure the distance to the set whose reach ends recovery. "own" (the default, and
    what a config without the key reads) keeps its own design's rows. On a logged engagement
    state (circle at 1.5 m/s, 0.5 rad/s, the realistic world's limits) the plan with the hard
    rows ends nearer the hard problem's terminal set."""
    from companion.core.design import design_terminal
    from companion.core.rmpc_nlp import NlpSolver
    from companion.core.rmpc_problem import tube_bound

    stiff = dataclasses.replace(cfg.rmpc, q_diag=(0.15, 0.15, 0.01, 1e-3, 0.05, 0.05, 3e-3),
                                eps=0.4, recovery_q_diag=cfg.rmpc.q_diag, recovery_eps=0.15,
                                u_max=(2.4, 2.4, 2.4, 0.838), jit=False)
    hard_design = design_terminal(stiff, cfg.camera)
    upper = {}
    for rows in ("own", "hard"):
        p = dataclasses.replace(stiff, recovery_rows=rows)
        lay = NlpSolver(p, cfg.camera, hard_design, soft=True, solver="ipopt").layout
        upper[rows] = {(r.kind, r.stage): r.upper for r in lay.rows if r.kind == "tube"}
    assert upper["own"][("tube", 0)] == pytest.approx(tube_bound(
        dataclasses.replace(stiff, eps=0.15), 0) ** 2)
    assert upper["hard"][("tube", 0)] == pytest.approx(tube_bound(stiff, 0) ** 2)
    # the hard problem's own layout has the same bounds as the "hard" soft rows
    lay_h = NlpSolver(stiff, cfg.camera, hard_design, soft=False, solver="ipopt").layout
    assert {(r.kind, r.stage): r.upper for r in lay_h.rows if r.kind == "tube"} == upper["hard"]

    p_hard = tube_matrix(stiff, np.asarray(hard_design.p))
    end = _recovery_end_distances(cfg, stiff, hard_design, p_hard, ("own", "hard"))
    assert end["hard"] < 0.95 * end["own"], end  # measured 1.33 against 1.45


def test_the_soft_copy_can_add_the_hard_terminal_set_to_its_own_rows(
    cfg: Config, design: TerminalDesign
) -> None:
    """rmpc.recovery_rows = "own+terminal": the soft copy keeps its own design's rows and adds
    one, the hard problem's terminal set at the soft terminal level, ``eta(N)' P_h eta(N)
    (eps_s / eps_h)^2 <= eps_s^2`` (its slack in the soft terminal row's units). On a logged
    engagement state (circle at 1.5 m/s, 0.5 rad/s, the realistic world's limits) the plan
    ends nearer the hard problem's terminal set than with "own" alone."""
    import casadi as ca

    from companion.core.design import design_terminal
    from companion.core.rmpc_nlp import NlpSolver
    from companion.core.rmpc_problem import build_nlp
    from companion.core.rmpc_recovery import hard_terminal_row, recovery_design

    stiff = dataclasses.replace(cfg.rmpc, q_diag=(0.15, 0.15, 0.01, 1e-3, 0.05, 0.05, 3e-3),
                                eps=0.4, recovery_q_diag=cfg.rmpc.q_diag, recovery_eps=0.15,
                                u_max=(2.4, 2.4, 2.4, 0.838), jit=False)
    hard_design = design_terminal(stiff, cfg.camera)
    p_hard = tube_matrix(stiff, np.asarray(hard_design.p))
    lays = {rows: NlpSolver(dataclasses.replace(stiff, recovery_rows=rows), cfg.camera,
                            hard_design, soft=True, solver="ipopt").layout
            for rows in ("own", "own+terminal")}
    kinds = {rows: [(r.kind, r.stage, r.upper) for r in lay.rows] for rows, lay in lays.items()}
    # the same rows as "own", plus the goal row at stage N (with its slack)
    goal = [k for k in kinds["own+terminal"] if k[0] == "goal_set"]
    assert goal == [("goal_set", stiff.horizon, pytest.approx(0.15**2))]
    assert [k for k in kinds["own+terminal"] if k[0] != "goal_set"] == kinds["own"]
    assert len(lays["own+terminal"].slack_index) == len(lays["own"].slack_index) + 1
    # its value is the hard problem's terminal-set row (P_h, not the soft design's P), scaled
    soft_p, soft_t = recovery_design(stiff, cfg.camera, hard_design)
    assert not np.allclose(np.asarray(soft_t.p), np.asarray(hard_design.p))
    nlp, lay = build_nlp(soft_p, cfg.camera, soft_t, True, None,
                         hard_terminal_row(stiff, hard_design, soft_p))
    row = next(r for r in lay.rows if r.kind == "goal_set")
    w = np.random.default_rng(3).normal(size=lay.n_w) * 0.3
    w[lay.slack_index] = 0.0
    g = ca.Function("g", [nlp["x"], nlp["p"]], [nlp["g"]])(w, np.zeros(nlp["p"].shape[0]))
    e_n = w[lay.x_index[-1]]
    assert float(g[row.g_index]) == pytest.approx(float(e_n @ p_hard @ e_n) * (0.15 / 0.4) ** 2)
    # without a soft design of its own the row is the hard terminal set itself
    same = dataclasses.replace(stiff, recovery_q_diag=None, recovery_eps=None)
    g_same, b_same = hard_terminal_row(same, hard_design, same)
    assert np.allclose(g_same, p_hard) and b_same == pytest.approx(0.4**2)

    end = _recovery_end_distances(cfg, stiff, hard_design, p_hard, ("own", "own+terminal"))
    assert end["own+terminal"] < 0.99 * end["own"], end  # measured 1.432 against 1.454


def _recovery_end_distances(cfg: Any, stiff: Any, hard_design: Any, p_hard: np.ndarray,
                            rows_settings: tuple[str, ...]) -> dict[str, float]:
    """For each ``recovery_rows`` setting, the hard tube norm of the last predicted state of
    the recovery plan from one start that escapes the view behind a 1.5 m/s target."""
    eta0 = np.array([0.44, -0.48, 0.62, -0.31, -0.62, -0.35, -0.66])
    v_a = 1.5 * np.array([np.cos(eta0[3]), np.sin(eta0[3])])
    target = TargetMotion.constant(v_a, [0.0, 0.0], 0.5, cfg.rmpc.horizon)
    end = {}
    for rows in rows_settings:
        p = dataclasses.replace(stiff, recovery_rows=rows, solver="nlp")
        res = Rmpc(p, cfg.camera, hard_design).solve(eta0, target)
        assert res.mode == "recovery", (rows, res.mode, res.status)
        e_n = np.asarray(res.eta_pred)[-1]
        end[rows] = float(np.sqrt(e_n @ p_hard @ e_n))
    return end
