"""The RMPC of spec section 6: solutions are checked constraint by constraint, not trusted.

The compiled solver is built once per session (the first run ever compiles for ~25 s and
caches the libraries under ``rmpc.cache_dir``; later runs and processes load them).
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from companion.config import Config, load_config
from companion.core.design import design_terminal
from companion.core.dynamics import input_error
from companion.core.errors import CoreError
from companion.core.rmpc import (
    Rmpc,
    RmpcParameterError,
    RmpcResult,
    TargetMotion,
    check_solution,
    terminal_law,
    visibility_margin,
)
from companion.core.rmpc_scenario import closed_loop, horizon_motion, initial_error, paper_agv
from companion.core.terminal import TerminalDesign

ROOT = Path(__file__).resolve().parents[2]
PAPER_POSE = ((-0.2, 0.4, -3.2), np.pi / 8)
YAW_OFFSET_POSE = ((-0.2, 0.4, -3.2), -np.pi / 8)
EDGE_POSE = ((-1.0, 0.0, -3.2), np.pi / 4)
ETA0_PAPER = np.array([0.0159, -0.2230, 0.6, 0.3927, -0.1307, -0.0541, 0.0])
RHO = 1e-4
HARD = ("dynamics", "input", "state")


# The paper's problem (spec 6): centroid rows, the yaw error in the tube, the nominal target
# motion. The whole-target variants are tested in tests/core/test_visibility_corners.py.
PAPER_RMPC = ('rmpc.visibility="centroid"', 'rmpc.heading="tube"',
              'rmpc.target_motion="nominal"', 'rmpc.solver="nlp"')


@pytest.fixture(scope="module")
def cfg() -> Config:
    return load_config(overrides=PAPER_RMPC)


@pytest.fixture(scope="module")
def design(cfg: Config) -> TerminalDesign:
    return design_terminal(cfg.rmpc, cfg.camera)


@pytest.fixture(scope="module")
def mpc(cfg: Config, design: TerminalDesign) -> Rmpc:
    return Rmpc(cfg.rmpc, cfg.camera, design, clock=time.perf_counter)


@pytest.fixture()
def fresh(mpc: Rmpc) -> Rmpc:
    mpc.reset()
    return mpc


def _norm_p(eta: np.ndarray, design: TerminalDesign) -> float:
    return float(np.sqrt(eta @ design.p @ eta))


def _cost(res: RmpcResult, cfg: Config, design: TerminalDesign) -> float:
    q, r = np.diag(cfg.rmpc.q_diag), np.diag(cfg.rmpc.r_diag)
    total = 0.0
    for n in range(cfg.rmpc.horizon):
        v_a, vdot_a, psidot_a = res.target.stage(n)
        ue = input_error(res.u_pred[n], v_a, vdot_a, psidot_a)
        total += res.eta_pred[n] @ q @ res.eta_pred[n] + ue @ r @ ue
    return float(total + res.eta_pred[-1] @ design.p @ res.eta_pred[-1])


# ---------------------------------------------------------------------------------------------
def test_scenario_initial_states_match_the_spec() -> None:
    """The pose -> eta_e(0) helper reproduces the paper's initial error (spec 8)."""
    eta0 = initial_error(*PAPER_POSE)
    assert np.allclose(eta0, ETA0_PAPER, atol=1e-4)
    tm = horizon_motion(0.0, PAPER_POSE[1], 16, 0.05)
    assert np.allclose(tm.v_a_m_s[0], [0.1307, 0.0541], atol=1e-4)
    yaw = initial_error(*YAW_OFFSET_POSE)
    assert yaw[3] == pytest.approx(np.pi / 4 + np.pi / 8)  # 1.178 rad
    assert np.allclose(yaw[4:6], [-0.0541, -0.1307], atol=1e-4)


def test_paper_initial_state_is_optimal_and_every_constraint_holds(
    fresh: Rmpc, cfg: Config, design: TerminalDesign
) -> None:
    tm = horizon_motion(0.0, PAPER_POSE[1], cfg.rmpc.horizon, cfg.rmpc.dt_s)
    res = fresh.solve(ETA0_PAPER, tm)
    assert res.success and res.mode == "optimal", res.status
    assert res.active_groups == ("tube", "visibility", "terminal")
    assert check_solution(res, cfg.rmpc, cfg.camera, design) == []
    assert np.array_equal(res.eta_pred[0], ETA0_PAPER)
    assert np.all(np.abs(res.u0) <= np.asarray(cfg.rmpc.u_max) + 1e-9)
    # the reported cost is the objective of the returned trajectory (independent re-evaluation)
    assert res.cost == pytest.approx(_cost(res, cfg, design), rel=1e-9)
    assert res.iterations > 0 and res.solve_time_s > 0
    # optimality oracle: no worse than the terminal law rolled out, whenever that is feasible
    law = fresh._rollout(ETA0_PAPER, tm)
    alt = dataclasses.replace(res, eta_pred=law[0], u_pred=law[1], u0=law[1][0])
    if check_solution(alt, cfg.rmpc, cfg.camera, design) == []:
        assert res.cost <= _cost(alt, cfg, design) + 1e-9


def test_unconstrained_mpc_near_the_origin_is_the_lqr(cfg: Config, design: TerminalDesign) -> None:
    """Oracle: with the terminal cost the DARE's P, the unconstrained MPC of the linearised
    model IS the LQR: u_e(0) = K eta, cost = eta' P eta (to second order near the origin)."""
    rc = dataclasses.replace(cfg.rmpc, enable_tube=False, enable_visibility=False,
                             enable_terminal=False, jit=False)
    m = Rmpc(rc, cfg.camera, design)
    tm = TargetMotion.constant([0.0, 0.0], [0.0, 0.0], 0.0, rc.horizon)
    rng = np.random.default_rng(3)
    for scale in (1e-3, 1e-4):
        eta = rng.normal(size=7) * scale
        res = m.solve(eta, tm)
        assert res.mode == "optimal"
        ue0 = input_error(res.u0, *tm.stage(0))
        assert np.allclose(ue0, design.k @ eta, atol=1e-3 * scale)
        assert res.cost == pytest.approx(float(eta @ design.p @ eta), rel=1e-2)
        m.reset()


def test_closed_loop_paper_every_constraint_holds_and_enters_omega(
    fresh: Rmpc, cfg: Config, design: TerminalDesign
) -> None:
    steps = 300
    loop = closed_loop(fresh, ETA0_PAPER, steps, RHO, seed=7)
    modes = [s.result.mode for s in loop]
    assert modes == ["optimal"] * steps
    for s in loop:
        assert check_solution(s.result, cfg.rmpc, cfg.camera, design) == [], s.t_s
    norms = np.array([_norm_p(s.eta, design) for s in loop])
    entered = int(np.argmax(norms <= cfg.rmpc.eps))
    assert norms[entered] <= cfg.rmpc.eps and entered < 100
    assert np.all(norms[entered:] <= cfg.rmpc.eps)
    assert norms[-1] < 0.1 * cfg.rmpc.eps  # and keeps converging
    # on the paper path the visibility constraint never binds (spec 8's reference loop)
    margins = [visibility_margin(s.result, cfg.rmpc, cfg.camera, design).min() for s in loop]
    assert min(margins) > 0.2


def test_forced_solver_failure_falls_back_to_the_clipped_terminal_law(
    cfg: Config, design: TerminalDesign
) -> None:
    rc = dataclasses.replace(cfg.rmpc, max_iter=1, hard_max_iter=1)
    m = Rmpc(rc, cfg.camera, design)
    assert all(c is not None and not c.compiled_now for c in m.compiled)  # same code: cache hit
    tm = horizon_motion(0.0, PAPER_POSE[1], rc.horizon, rc.dt_s)
    res = m.solve(ETA0_PAPER, tm)
    assert res.mode == "fallback" and not res.success
    expected = terminal_law(ETA0_PAPER, *tm.stage(0), design.k, rc.u_max)
    assert np.array_equal(res.u0, expected)
    assert np.all(np.isfinite(res.u0)) and np.all(np.abs(res.u0) <= np.asarray(rc.u_max))
    assert np.all(np.isfinite(res.eta_pred)) and np.all(np.isfinite(res.u_pred))
    # the law really is the clip of K eta + Gamma: unclipped entries give u_e = K eta
    raw_ue = input_error(res.u0, *tm.stage(0))
    unclipped = np.abs(res.u0) < np.asarray(rc.u_max)
    if unclipped[3]:
        assert np.allclose(raw_ue[unclipped], (design.k @ ETA0_PAPER)[unclipped])


def test_yaw_offset_start_recovers_then_solves_the_hard_problem(
    fresh: Rmpc, cfg: Config, design: TerminalDesign
) -> None:
    eta0 = initial_error(*YAW_OFFSET_POSE)
    assert eta0[3] == pytest.approx(1.178, abs=1e-3)
    loop = closed_loop(fresh, eta0, 200, RHO, seed=11)
    modes = [s.result.mode for s in loop]
    assert "fallback" not in modes
    assert modes[0] == "recovery" and loop[0].result.max_soft_violation > 0
    # the first steps carry a proof of infeasibility (yaw error out of reach); check the proof
    # against the hard solver itself, and against the soft copy (zero slack would contradict it)
    assert loop[0].result.hard_status.startswith("infeasible: yaw error")
    hard, tm0 = fresh._hard, loop[0].result.target
    w0 = fresh._pack(hard.layout, *fresh._rollout(eta0, tm0))
    ok, status, *_ = hard.solve(w0, np.append(tm0.packed(), eta0[3]), *hard.bounds(eta0, tm0))
    assert not status.startswith("exception"), status  # a real solve, not a bad call
    assert not ok, status
    for s in loop:
        if s.result.hard_status.startswith("infeasible"):
            assert s.result.mode == "recovery" and s.result.max_soft_violation > 1e-6
    first_opt = modes.index("optimal")
    assert modes[first_opt:] == ["optimal"] * (len(modes) - first_opt)
    for s in loop:
        bad = check_solution(s.result, cfg.rmpc, cfg.camera, design)
        if s.result.mode == "recovery":
            # dynamics, inputs and the state box stay hard in the soft copy
            assert [v for v in bad if v.constraint in HARD] == []
        else:
            assert bad == []
    norms = np.array([_norm_p(s.eta, design) for s in loop])
    assert np.all(norms[-50:] <= cfg.rmpc.eps) and norms[-1] < 0.2 * norms[0]


def test_buffer_calls_match_the_dm_call_exactly(fresh: Rmpc) -> None:
    """The zero-copy solver call (FunctionBuffer) gives bit for bit what ``Function.call`` with
    DM arguments gives, on the hard problem and on the soft copy (an infeasible start: the
    recovery path), including the per-solve status and iteration count."""
    import casadi as ca

    seen: dict[str, int] = {"hard": 0, "soft": 0}
    originals = {}

    def checked(sv: Any) -> Any:
        orig = sv.solve

        def solve(w0: np.ndarray, par: np.ndarray, lbx: np.ndarray, ubx: np.ndarray,
                  backend: Any = None) -> Any:
            out = orig(w0, par, lbx, ubx, backend)
            _, _, st, w, cost, it, _ = out
            ref = sv.solver.call([ca.DM(w0), ca.DM(par), ca.DM(lbx), ca.DM(ubx),
                                  ca.DM(sv.lbg), ca.DM(sv.ubg), ca.DM(), ca.DM()])
            rst = sv.solver.stats()
            assert np.array_equal(w, ref[0].full().ravel())
            assert cost == float(ref[1])
            assert (st.get("success"), st.get("return_status"), it) == (
                rst.get("success"), rst.get("return_status"), rst.get("iter_count"))
            seen[sv.kind] += 1
            return out
        return solve

    for sv in (fresh._hard, fresh._soft):
        assert sv is not None
        originals[sv.kind] = sv
        sv.solve = checked(sv)
    try:
        loop = closed_loop(fresh, initial_error(*YAW_OFFSET_POSE), 40, RHO, seed=11)
    finally:
        for sv in originals.values():
            del sv.solve
    modes = {s.result.mode for s in loop}
    assert modes == {"recovery", "optimal"}
    assert seen["soft"] > 0 and seen["hard"] > 0


def test_edge_start_makes_the_visibility_constraint_bind(
    fresh: Rmpc, cfg: Config, design: TerminalDesign
) -> None:
    """UAV at (-1, 0, -3.2) m, psi0 = pi/4 (spec 8 'edge'): the circle constraint is active."""
    eta0 = initial_error(*EDGE_POSE)
    assert np.allclose(eta0, [0.5 / np.sqrt(2), -0.5 / np.sqrt(2), 0.6, 0.0,
                              -0.1 * np.sqrt(2), 0.0, 0.0], atol=1e-9)
    loop = closed_loop(fresh, eta0, 120, RHO, seed=5)
    modes = [s.result.mode for s in loop]
    assert "fallback" not in modes and modes[-1] == "optimal"
    binding = [
        s for s in loop
        if s.result.mode == "optimal"
        and visibility_margin(s.result, cfg.rmpc, cfg.camera, design).min() < 1e-6
    ]
    assert binding, "visibility never binds on the edge start"
    for s in loop:
        bad = check_solution(s.result, cfg.rmpc, cfg.camera, design)
        assert bad == [] if s.result.mode == "optimal" else all(v.constraint not in HARD
                                                                for v in bad)
    # without the constraint the optimum leaves the circle at the same state
    rc = dataclasses.replace(cfg.rmpc, enable_visibility=False, jit=False)
    free = Rmpc(rc, cfg.camera, design)
    s0 = binding[0]
    psi_q = paper_agv(s0.t_s).yaw_rad - s0.eta[3]
    res = free.solve(s0.eta, horizon_motion(s0.t_s, psi_q, rc.horizon, rc.dt_s))
    assert res.mode in ("optimal", "recovery")
    assert visibility_margin(res, cfg.rmpc, cfg.camera, design).min() < -1e-3


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_parameters_raise_before_the_solver(fresh: Rmpc, bad: float) -> None:
    tm = TargetMotion.constant([0.1, 0.0], [0.0, 0.0], 0.0, fresh.horizon)
    assert fresh.solve(ETA0_PAPER, tm).mode == "optimal"
    eta = ETA0_PAPER.copy()
    eta[2] = bad
    calls = fresh._hard.calls
    with pytest.raises(RmpcParameterError, match="eta0") as exc:
        fresh.solve(eta, tm)
    assert isinstance(exc.value, CoreError)
    with pytest.raises(RmpcParameterError, match="v_a_m_s"):
        TargetMotion.constant([bad, 0.0], [0.0, 0.0], 0.0, fresh.horizon)
    with pytest.raises(RmpcParameterError, match="psidot_a"):
        TargetMotion.constant([0.1, 0.0], [0.0, 0.0], bad, fresh.horizon)
    with pytest.raises(RmpcParameterError):
        fresh.solve(ETA0_PAPER, TargetMotion.constant([0.1, 0.0], [0.0, 0.0], 0.0, 3))
    assert fresh._hard.calls == calls


def test_check_solution_catches_tampered_trajectories(
    fresh: Rmpc, cfg: Config, design: TerminalDesign
) -> None:
    tm = horizon_motion(0.0, PAPER_POSE[1], cfg.rmpc.horizon, cfg.rmpc.dt_s)
    res = fresh.solve(ETA0_PAPER, tm)
    assert check_solution(res, cfg.rmpc, cfg.camera, design) == []
    u = res.u_pred.copy()
    u[3, 0] = 1.6  # outside |r1| <= 1.5, and breaks the dynamics from stage 3 on
    bad = check_solution(dataclasses.replace(res, u_pred=u), cfg.rmpc, cfg.camera, design)
    kinds = {(v.constraint, v.stage) for v in bad}
    assert ("input", 3) in kinds and ("dynamics", 3) in kinds
    assert next(v.amount for v in bad if v.constraint == "input") == pytest.approx(0.1)
    eta = res.eta_pred.copy()
    eta[-1] = eta[-1] * 0 + np.array([0.3, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    names = {v.constraint for v in check_solution(dataclasses.replace(res, eta_pred=eta),
                                                  cfg.rmpc, cfg.camera, design)}
    assert {"terminal_visibility", "terminal_set", "dynamics"} <= names


@settings(
    max_examples=25, deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    eta=st.lists(st.floats(-0.08, 0.08), min_size=7, max_size=7),
    v=st.lists(st.floats(-0.3, 0.3), min_size=2, max_size=2),
    psidot=st.floats(-0.05, 0.05),
)
def test_any_small_error_gives_a_checked_finite_answer(
    fresh: Rmpc, cfg: Config, design: TerminalDesign, eta: list[float], v: list[float],
    psidot: float,
) -> None:
    fresh.reset()
    tm = TargetMotion.constant(v, [0.0, 0.0], psidot, cfg.rmpc.horizon)
    res = fresh.solve(np.array(eta), tm)
    assert np.all(np.isfinite(res.u0)) and np.all(np.abs(res.u0) <= np.asarray(cfg.rmpc.u_max))
    assert res.mode == "optimal", res.status  # inside the tube: the hard problem is feasible
    assert check_solution(res, cfg.rmpc, cfg.camera, design) == []


@pytest.mark.slow
def test_a_second_process_loads_the_compiled_code_from_the_cache(mpc: Rmpc) -> None:
    hard, soft = mpc.compiled
    assert hard is not None and soft is not None and hard.library.exists()
    code = (
        "import json; from companion.config import load_config;"
        "from companion.core.design import design_terminal;"
        f"from companion.core.rmpc import Rmpc; c = load_config(overrides={PAPER_RMPC!r});"
        "m = Rmpc(c.rmpc, c.camera, design_terminal(c.rmpc, c.camera));"
        "print(json.dumps([[str(x.library), x.compiled_now] for x in m.compiled]))"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, timeout=120, check=True)
    libs = json.loads(out.stdout.strip().splitlines()[-1])
    assert libs == [[str(hard.library), False], [str(soft.library), False]]
    # the whole-target rows are another problem: another cache entry (the key hashes the
    # generated source), never the centroid library
    corners = Rmpc(dataclasses.replace(mpc.cfg, visibility="corners"), mpc.camera, mpc.terminal)
    k_hard, k_soft = corners.compiled
    assert k_hard is not None and k_soft is not None
    assert k_hard.key != hard.key and k_soft.key != soft.key


@pytest.mark.parametrize(
    ("tube", "vis", "term"),
    [(True, True, True), (True, False, False), (False, True, False), (False, False, True),
     (False, False, False)],
)
def test_constraint_groups_switch_exactly_their_rows(
    cfg: Config, design: TerminalDesign, tube: bool, vis: bool, term: bool
) -> None:
    from companion.core.rmpc_problem import build_nlp, visibility_pairs

    rc = dataclasses.replace(cfg.rmpc, enable_tube=tube, enable_visibility=vis,
                             enable_terminal=term)
    big_n = rc.horizon
    # both pairings: N-1 rows, at stages 1..N-1 ("spec") or 0..N-2 ("causal")
    stages = [st for st, _, _ in visibility_pairs(rc)]
    assert len(stages) == big_n - 1
    assert stages == (list(range(big_n - 1)) if rc.visibility_pairing == "causal"
                      else list(range(1, big_n)))
    for soft in (False, True):
        nlp, lay = build_nlp(rc, cfg.camera, design, soft=soft)
        kinds = sorted((r.kind, r.stage) for r in lay.rows)
        expected = sorted(
            [("tube", n) for n in range(big_n) if tube]
            + [("visibility", st) for st, _, _ in visibility_pairs(rc) if vis]
            + ([("terminal_set", big_n)] if tube or term else [])
            + ([("terminal_visibility", big_n)] if term else [])
        )
        assert kinds == expected
        assert lay.n_g == 7 * big_n + len(expected) == nlp["g"].shape[0]
        assert len(lay.slack_index) == (len(expected) if soft else 0)
        assert lay.n_w == 11 * big_n + 7 + len(lay.slack_index) == nlp["x"].shape[0]
        # OCP order: x_n, u_n (slacks), x_{n+1}; the gap rows of stage n precede its path rows
        assert np.all(np.diff(lay.x_index[:, 0]) > 0) and np.all(lay.u_index[:, 0] ==
                                                                 lay.x_index[:-1, 0] + 7)
        assert all(lay.equality[i] for i in lay.gap_index.ravel())
        assert sum(lay.equality) == 7 * big_n


def test_disturbance_moves_the_visible_area_centre_in_the_solved_problem(
    fresh: Rmpc, cfg: Config, design: TerminalDesign
) -> None:
    """With a disturbance estimate d the attitude realising the acceleration u is that of
    u - d (docs/reference/estimator.md): the solver's visibility rows are those of M(u - d), so the
    solution is checked clean against d, and the same trajectory checked with M(u) differs."""
    from companion.core.rmpc_problem import centre

    base = TargetMotion.constant([0.1, 0.0], [0.0, 0.0], 0.0, fresh.horizon)
    d = np.tile([0.4, -0.3, 0.1], (fresh.horizon, 1))
    tm = TargetMotion(base.v_a_m_s, base.vdot_a_m_s2, base.psidot_a_rad_s, d)
    res = fresh.solve(ETA0_PAPER, tm)
    assert res.mode == "optimal"
    assert check_solution(res, cfg.rmpc, cfg.camera, design) == []
    u = res.u_pred[0]
    assert np.allclose(centre(u, cfg.rmpc, cfg.camera, d[0]),
                       centre(u - np.r_[d[0], 0.0], cfg.rmpc, cfg.camera), atol=1e-12)
    without = dataclasses.replace(res, target=base)
    m_with = visibility_margin(res, cfg.rmpc, cfg.camera, design)
    m_without = visibility_margin(without, cfg.rmpc, cfg.camera, design)
    assert np.max(np.abs(m_with - m_without)) > 1e-3
    with pytest.raises(RmpcParameterError):
        TargetMotion(base.v_a_m_s, base.vdot_a_m_s2, base.psidot_a_rad_s, d * np.nan)


def test_nlp_visibility_rows_use_the_disturbance(cfg: Config, design: TerminalDesign) -> None:
    """The NLP's visibility rows (centroid or corner) evaluated at a random point equal numpy's
    |p - M(u - d)|^2, with the planned-yaw target motion of ``stage_motion``."""
    import casadi as ca

    from companion.core.dynamics import euler_step
    from companion.core.rmpc_problem import build_nlp, stage_motion
    from companion.core.rmpc_recovery import _row_value

    nlp, lay = build_nlp(cfg.rmpc, cfg.camera, design, soft=False)
    g = ca.Function("g", [nlp["x"], nlp["p"]], [nlp["g"]])
    rng = np.random.default_rng(3)
    w = rng.normal(0.0, 0.1, lay.n_w)
    base = TargetMotion.constant([0.1, 0.0], [0.0, 0.0], 0.0, lay.horizon)
    d = rng.normal(0.0, 0.5, (lay.horizon, 3))
    tm = TargetMotion(base.v_a_m_s, base.vdot_a_m_s2, base.psidot_a_rad_s, d)
    x = w[lay.x_index]
    u = w[lay.u_index]
    s4_ref = float(x[0][3])
    got = g(w, np.append(tm.packed(), s4_ref)).full().ravel()
    got0 = g(w, np.append(base.packed(), s4_ref)).full().ravel()
    rows = [r for r in lay.rows if r.kind in ("visibility", "corner")]
    assert rows
    for r in rows:
        n = r.stage
        # causal rows: the image after the step, p(F(x_n, u_n)) (rmpc_problem)
        v_a, vdot_a, psidot_a = base.stage(n)
        motion = stage_motion(cfg.rmpc, x[n], u[n], v_a, vdot_a, psidot_a, s4_ref)
        img = x[n] if cfg.rmpc.visibility_pairing == "spec" else euler_step(
            x[n], u[n], *motion, cfg.rmpc.desired_depth_m, cfg.rmpc.dt_s)
        want = _row_value(r.kind, img, u[n], design.p, cfg.rmpc, cfg.camera, d[n],
                          corner=r.corner)
        assert got[r.g_index] == pytest.approx(want, rel=1e-9, abs=1e-12)
        assert abs(got[r.g_index] - got0[r.g_index]) > 1e-6


def test_a_known_problem_loads_its_library_without_generating_code(
    mpc: Rmpc, cfg: Config, design: TerminalDesign, monkeypatch: pytest.MonkeyPatch
) -> None:
    import companion.core.rmpc_cache as rc

    def generate(*_: object) -> None:
        raise AssertionError("the source was generated although the alias names the library")

    monkeypatch.setattr(rc, "_generate_and_compile", generate)
    again = Rmpc(cfg.rmpc, cfg.camera, design)
    assert [(c.library, c.key, c.compiled_now) for c in again.compiled if c] == [
        (c.library, c.key, False) for c in mpc.compiled if c]


def test_a_dangling_or_foreign_alias_falls_back_to_generating(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import casadi as ca

    import companion.core.rmpc_cache as rc

    x, p = ca.SX.sym("x", 2), ca.SX.sym("p", 1)
    nlp = {"x": x, "p": p, "f": ca.sumsqr(x - p), "g": x[0] + x[1]}
    calls: list[str] = []

    def generate(solver: object, directory: Path, tag: str) -> rc.CompiledNlp:
        calls.append(tag)
        lib = directory / f"rmpc_{tag}_{'a' * 24}.so"
        lib.write_bytes(b"")
        return rc.CompiledNlp(library=lib, key="a" * 24, compiled_now=True)

    monkeypatch.setattr(rc, "_generate_and_compile", generate)
    alias = tmp_path / f"rmpc_t_{rc.problem_key(nlp, 't', 'o')}.alias"
    for content in ("rmpc_t_missing.so\n", "../elsewhere/rmpc_t_x.so\n", "garbage"):
        alias.write_text(content)
        got = rc.compiled_nlp(lambda: "symbolic", str(tmp_path), "t", nlp=nlp, options="o")
        assert got.compiled_now and alias.read_text().strip() == got.library.name
    assert len(calls) == 3
    hit = rc.compiled_nlp(lambda: "symbolic", str(tmp_path), "t", nlp=nlp, options="o")
    assert not hit.compiled_now and hit.library == got.library and len(calls) == 3
    # another problem (or other options) has another alias
    assert rc.problem_key(nlp, "t", "o2") != rc.problem_key(nlp, "t", "o")
    assert rc.problem_key({**nlp, "f": ca.sumsqr(x)}, "t", "o") != rc.problem_key(nlp, "t", "o")
