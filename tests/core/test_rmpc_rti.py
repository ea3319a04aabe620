"""The real-time iteration (``rmpc.solver = "rti"``, companion/core/rmpc_rti.py) against the
full NLP: same commands on the paper's closed loop within a stated tolerance, every accepted
plan feasible for the nonlinear problem, a violated plan caught, deterministic replay, the old
spelling of ``rmpc.solver`` read as the full NLP."""

from __future__ import annotations

import dataclasses

import daqp
import numpy as np
import pytest

from companion.config import ConfigError, config_from_dict, load_config, read_document
from companion.core.design import design_terminal
from companion.core.rmpc import Rmpc, RmpcResult, check_solution
from companion.core.rmpc_scenario import closed_loop, initial_error
from tests.core.rti_forms import halfway_state_bounds

PAPER_POSE = ((-0.2, 0.4, -3.2), np.pi / 8)
EDGE_POSE = ((-1.0, 0.0, -3.2), np.pi / 4)
STEPS = 200  # 10 s of the paper's loop: engagement and tracking
RHO = 1e-4


@pytest.fixture(scope="module")
def cfg():  # type: ignore[no-untyped-def]
    return load_config()


@pytest.fixture(scope="module")
def design(cfg):  # type: ignore[no-untyped-def]
    return design_terminal(cfg.rmpc, cfg.camera)


@pytest.fixture(scope="module")
def rti(cfg, design):  # type: ignore[no-untyped-def]
    return Rmpc(dataclasses.replace(cfg.rmpc, solver="rti"), cfg.camera, design)


@pytest.fixture(scope="module")
def nlp(cfg, design):  # type: ignore[no-untyped-def]
    return Rmpc(dataclasses.replace(cfg.rmpc, solver="nlp"), cfg.camera, design)


def _u0(mpc: Rmpc, pose: tuple, steps: int = STEPS) -> tuple[np.ndarray, list[RmpcResult]]:
    mpc.reset()
    loop = closed_loop(mpc, initial_error(*pose), steps, RHO, 1)
    return np.array([s.result.u0 for s in loop]), [s.result for s in loop]


def test_rti_and_nlp_agree_on_the_paper_loop(cfg, rti, nlp) -> None:  # type: ignore[no-untyped-def]
    """Tolerance: an input difference du changes the next state by at most dt |du| (the
    velocity rows, and s4 for the yaw rate), so |du| <= rho / dt keeps the two controllers'
    one-step difference inside the disturbance bound rho the tube is tightened for:
    1e-4 / 0.05 = 2e-3 (m/s^2, rad/s). Measured: 4.7e-4."""
    u_rti, res = _u0(rti, PAPER_POSE)
    u_nlp, _ = _u0(nlp, PAPER_POSE)
    tol = cfg.rmpc.rho / cfg.rmpc.dt_s
    diff = np.max(np.abs(u_rti - u_nlp))
    assert diff <= tol, diff
    # most steps flew the RTI's plan (not the NLP behind it)
    assert sum(r.status.startswith("rti: 1 QP") or r.status.startswith("rti: 2 QP")
               for r in res) >= 0.9 * STEPS


def test_every_accepted_rti_plan_passes_the_independent_check(cfg, design, rti) -> None:  # type: ignore[no-untyped-def]
    """check_solution (numpy, independent of the compiled rows) finds every plan the RTI flew
    feasible for the nonlinear problem: dynamics, boxes, tube, corners, terminal set."""
    for pose in (PAPER_POSE, EDGE_POSE):
        _, res = _u0(rti, pose, 120)
        flown = [r for r in res if r.status.startswith("rti:") and "nlp" not in r.status]
        assert flown
        for r in flown:
            assert check_solution(r, rti.cfg, cfg.camera, design,
                                  tol=cfg.rmpc.rti_tol + 1e-9) == [], r.status


def test_the_check_catches_a_violated_plan(cfg, design, rti) -> None:  # type: ignore[no-untyped-def]
    """A plan pushed off the solution (every input at the box's corner) is rejected by the
    RTI's own nonlinear check and by check_solution: it would steer the corners out."""
    _, res = _u0(rti, PAPER_POSE, 40)
    good = res[-1]
    solver = rti._rti
    assert solver is not None
    eta0 = good.eta_pred[0]
    par = np.append(good.target.packed(), eta0[3])
    lay = rti._hard.layout
    lbx, ubx = rti._hard.bounds(eta0, good.target)
    lo, hi = lbx[lay.x_index[1:]].ravel(), ubx[lay.x_index[1:]].ravel()
    eta, path, _ = solver.rows(good.u_pred.ravel(), eta0, par)
    assert solver.violation(eta, path, good.u_pred, lo, hi) <= cfg.rmpc.rti_tol
    bad_u = np.tile(np.asarray(cfg.rmpc.u_max), (cfg.rmpc.horizon, 1))
    eta_b, path_b, _ = solver.rows(bad_u.ravel(), eta0, par)
    assert solver.violation(eta_b, path_b, bad_u, lo, hi) > 0.1
    bad = dataclasses.replace(good, u0=bad_u[0], u_pred=bad_u, eta_pred=eta_b)
    kinds = {v.constraint for v in check_solution(bad, rti.cfg, cfg.camera, design)}
    assert "visibility" in kinds or "tube" in kinds, kinds


def test_a_rejected_rti_step_solves_the_full_nlp(cfg, design) -> None:  # type: ignore[no-untyped-def]
    """With one QP a step and no tolerance to speak of, the engagement's first plan (far
    from the optimum: the linearisation's error is large) is rejected: the step is the full
    NLP's (said in the status, counted) and its plan passes the check."""
    p = dataclasses.replace(cfg.rmpc, solver="rti", rti_max_qp=1, rti_tol=1e-12)
    mpc = Rmpc(p, cfg.camera, design)
    _, res = _u0(mpc, EDGE_POSE, 3)
    first = res[0]
    assert first.status.startswith("rti: ") and "nlp: " in first.status, first.status
    assert mpc.rti_rejected >= 1
    if first.mode == "optimal":
        assert check_solution(first, p, cfg.camera, design) == []


def test_rti_is_deterministic_and_reset_restores_it(rti) -> None:  # type: ignore[no-untyped-def]
    """Replay is exact: the same inputs give the same commands bit for bit, and reset()
    forgets the warm start completely."""
    a, _ = _u0(rti, EDGE_POSE, 60)
    b, _ = _u0(rti, EDGE_POSE, 60)
    assert np.array_equal(a, b)


def test_rti_cost_is_the_nlp_cost(cfg, rti) -> None:  # type: ignore[no-untyped-def]
    """The Gauss-Newton residuals square to the NLP's own objective (same cost)."""
    _, res = _u0(rti, PAPER_POSE, 20)
    for r in res[5:]:
        assert r.cost == pytest.approx(rti._objective(r.eta_pred, r.u_pred, r.target),
                                       rel=1e-9, abs=1e-12)


@pytest.mark.parametrize("old", ["fatrop", "ipopt"])
def test_an_old_config_reads_as_the_full_nlp(old: str) -> None:
    """A log recorded before rmpc.solver = "nlp" | "rti" says solver = "fatrop": it replays
    with the full NLP by that solver, as it was flown."""
    doc = read_document("config/paper.toml")
    rm = {k: v for k, v in doc["rmpc"].items() if k not in ("nlp_solver",)}
    rm["solver"] = old
    cfg = config_from_dict({**doc, "rmpc": rm})
    assert cfg.rmpc.solver == "nlp" and cfg.rmpc.nlp_solver == old
    with pytest.raises(ConfigError, match="nlp_solver"):
        config_from_dict({**doc, "rmpc": {**rm, "nlp_solver": "ipopt" if old == "fatrop"
                                          else "fatrop"}})
    with pytest.raises(ConfigError, match=r"rmpc\.solver"):
        config_from_dict({**doc, "rmpc": {**rm, "solver": "qpoases"}})


def _paper_step(rti: Rmpc, steps: int = 40):  # type: ignore[no-untyped-def]
    """The RTI's inputs at the last step of a short paper loop, linearised half-way between
    hover and the flown plan (a QP with a real step): (solver, eta0, par, u, lo, hi)."""
    _, res = _u0(rti, PAPER_POSE, steps)
    good = res[-1]
    eta0 = good.eta_pred[0]
    par = np.append(good.target.packed(), eta0[3])
    lo, hi = rti._state_box(good.target)
    assert rti._rti is not None
    return rti._rti, eta0, par, 0.5 * good.u_pred.ravel(), lo, hi


def test_the_state_box_is_the_nlp_bounds(rti) -> None:  # type: ignore[no-untyped-def]
    """Rmpc._state_box gives the hard NLP's state bounds of stages 1..N bit for bit."""
    _, res = _u0(rti, EDGE_POSE, 5)
    for r in res:
        lay = rti._hard.layout
        lbx, ubx = rti._hard.bounds(r.eta_pred[0], r.target)
        lo, hi = rti._state_box(r.target)
        assert np.array_equal(lo, lbx[lay.x_index[1:]].ravel())
        assert np.array_equal(hi, ubx[lay.x_index[1:]].ravel())


def _whole_qp(solver, u, eta0, par, lo, hi):  # type: ignore[no-untyped-def]
    """The QP with every row (input box, state box, path rows), as DAQP solves it."""
    hess, grad, c, jct = (a.copy() for a in solver._lin(u, eta0, par))
    n_u, n_s = solver.n_u, solver.n_state
    up = np.concatenate([solver.u_max - u, hi - c[:n_s], solver.path_upper - c[n_s:]])
    low = np.concatenate([-solver.u_max - u, lo - c[:n_s], np.full(c.size - n_s, -1e30)])
    du, _, flag, _ = daqp.solve(hess.reshape(n_u, n_u), grad, jct.reshape(c.size, n_u), up, low,
                                np.zeros(up.size, dtype=np.int32), iter_limit=500)
    assert flag == 1
    return np.asarray(du)


def test_the_qp_without_the_state_box_is_the_whole_qp(rti) -> None:  # type: ignore[no-untyped-def]
    """The QP is solved without the state box's rows first (they do not bind in flight): its
    step is the whole QP's (strictly convex: a solution that keeps the rows left out is the
    whole QP's minimiser). A state box the step would leave is caught and the whole QP
    solved, its step kept inside."""
    solver, eta0, par, u, lo, hi = _paper_step(rti)
    full0 = solver.full_qps
    for at in (2.0 * u, u):  # the flown plan (nothing binds), half-way (corner rows bind)
        du, flag, _ = solver._qp(at, eta0, par, lo, hi)
        assert flag == 1 and solver.full_qps == full0
        np.testing.assert_allclose(du, _whole_qp(solver, at, eta0, par, lo, hi), rtol=0,
                                   atol=1e-10)
    # a box the step leaves: the state that moves most may only move half as far
    solver._lin(u, eta0, par)
    lo2, hi2 = halfway_state_bounds(solver, du, lo, hi)
    du2, flag2, _ = solver._qp(u, eta0, par, lo2, hi2)
    assert flag2 == 1 and solver.full_qps == full0 + 1
    x2 = solver._c_x + solver._j_state @ du2
    assert np.all(x2 <= hi2 + 1e-9) and np.all(x2 >= lo2 - 1e-9)
    np.testing.assert_allclose(du2, _whole_qp(solver, u, eta0, par, lo2, hi2), rtol=0,
                               atol=1e-10)


def test_the_compiled_check_is_the_numpy_check(rti) -> None:  # type: ignore[no-untyped-def]
    """The step reads the largest excess from the compiled check (rti_val): the same number
    as RtiSolver.violation's numpy, bit for bit, on a good plan, a violated one and one with
    a single row broken; a NaN anywhere makes its 'total' non-finite (fmax would drop it)."""
    solver, eta0, par, u, lo, hi = _paper_step(rti)
    bad = np.tile(np.asarray(rti.cfg.u_max), rti.cfg.horizon)
    for plan in (2.0 * u, u, bad):
        eta, path, _ = solver.rows(plan, eta0, par)
        hi2 = hi.copy()
        hi2[5] = eta[1 + 5 // 7, 5 % 7] - 1e-3  # one state row exceeded by 1e-3
        for box_hi in (hi, hi2):
            _, _, excess, total = solver._val(plan, eta0, par, lo, box_hi)
            assert float(excess[0]) == solver.violation(eta, path, plan, lo, box_hi)
            assert np.isfinite(total[0])
        assert solver.violation(eta, path, plan, lo, hi2) >= 0.999e-3
    nan_plan = u.copy()
    nan_plan[7] = np.nan
    assert not np.isfinite(solver._val(nan_plan, eta0, par, lo, hi)[3][0])


def test_a_diverging_step_stops_early(cfg, design) -> None:  # type: ignore[no-untyped-def]
    """Far from the solution (the engagement's first step) the full Gauss-Newton steps do
    not bring the excess down: the step goes to the full NLP before rti_max_qp QPs."""
    p = dataclasses.replace(cfg.rmpc, solver="rti", rti_max_qp=8)
    mpc = Rmpc(p, cfg.camera, design)
    _, res = _u0(mpc, PAPER_POSE, 1)
    assert "nlp: " in res[0].status and mpc.rti_qps < 8, (res[0].status, mpc.rti_qps)
    assert res[0].mode == "optimal" and check_solution(res[0], p, cfg.camera, design) == []


def test_the_condensed_linearisation_is_the_rollouts(rti) -> None:  # type: ignore[no-untyped-def]
    """rti_lin (condensed from stage Jacobians) gives the rows rti_val computes with the NLP's
    own g on the rollout, and their Jacobian is the rollout's (central differences); the
    Gauss-Newton Hessian is 2 J_r' J_r (symmetric, positive definite)."""
    solver, eta0, par, u, lo, hi = _paper_step(rti)
    hess, _, c, jct = (a.copy() for a in solver._lin(u, eta0, par))
    c_val = solver._val(u, eta0, par, lo, hi)[0].copy()
    np.testing.assert_allclose(c, c_val, rtol=0, atol=1e-12)
    j_c = jct.reshape(c.size, solver.n_u)
    step = 1e-6
    for k in range(0, solver.n_u, 5):
        du = np.zeros(solver.n_u)
        du[k] = step
        plus = solver._val(u + du, eta0, par, lo, hi)[0].copy()  # (the output buffer)
        fd = (plus - solver._val(u - du, eta0, par, lo, hi)[0]) / (2 * step)
        np.testing.assert_allclose(j_c[:, k], fd, rtol=0, atol=1e-6)
    h = hess.reshape(solver.n_u, solver.n_u)
    np.testing.assert_allclose(h, h.T, rtol=0, atol=1e-15)
    assert np.min(np.linalg.eigvalsh(h)) > 0


@pytest.mark.parametrize("form", ["recursion", "loops", "graph", "scalar"])
def test_the_condensed_hessian_is_the_rollouts_gauss_newton(cfg, design, rti, form) -> None:  # type: ignore[no-untyped-def]
    """rti_lin's H and g (rmpc.rti_linearisation "recursion", the default: a backward
    recursion over the stages in C; "loops": the condensed J_r's
    product as C loops; "graph": the same as CasADi's sparse product; "scalar": a backward
    recursion over stage blocks, as scalar code) are 2 J_r' J_r and
    2 J_r' r of the residuals of the whole rollout differentiated as one expression (no
    condensing), and g is the gradient of the NLP's cost (central differences of rti_val's
    cost)."""
    import casadi as ca

    from companion.core.rmpc_problem import NP_STAGE, NU
    from companion.core.rmpc_rti_gen import _StageFunctions

    assert rti.cfg.rti_linearisation == "recursion"  # (the default config's, compiled)
    if form == "loops":  # (compiled: C)
        rti = Rmpc(dataclasses.replace(cfg.rmpc, solver="rti", rti_linearisation=form),
                   cfg.camera, design)
    elif form != "recursion":  # (not compiled here: the same function, evaluated by CasADi)
        rti = Rmpc(dataclasses.replace(cfg.rmpc, solver="rti", rti_linearisation=form,
                                       jit=False), cfg.camera, design)
    solver, eta0, par, u, lo, hi = _paper_step(rti)
    hess, grad = (a.copy() for a in solver._lin(u, eta0, par)[:2])
    big_n = cfg.rmpc.horizon
    stage = _StageFunctions(cfg.rmpc, cfg.camera, design)
    u_s, x = ca.SX.sym("U", NU * big_n), ca.SX(eta0)
    res = []
    for n in range(big_n):
        out = stage.function(n)(x, u_s[NU * n: NU * (n + 1)],
                                par[NP_STAGE * n: NP_STAGE * (n + 1)], par[-1])
        res.append(out[1])
        x = out[0]
    res.append(ca.mtimes(np.linalg.cholesky(np.asarray(design.p, dtype=float)).T, x))
    r_all = ca.vertcat(*res)
    j_r = ca.Function("j", [u_s], [ca.jacobian(r_all, u_s), r_all])
    jr, r = (np.asarray(v, dtype=float) for v in j_r(u))
    np.testing.assert_allclose(hess.reshape(solver.n_u, solver.n_u), 2 * jr.T @ jr,
                               rtol=1e-10, atol=1e-10 * np.max(np.abs(hess)))
    np.testing.assert_allclose(grad, 2 * jr.T @ r.ravel(), rtol=1e-10,
                               atol=1e-10 * np.max(np.abs(grad)))
    step = 1e-6
    for k in range(0, solver.n_u, 7):
        du = np.zeros(solver.n_u)
        du[k] = step
        f_plus = float(solver._val(u + du, eta0, par, lo, hi)[1][0])
        f_minus = float(solver._val(u - du, eta0, par, lo, hi)[1][0])
        assert abs((f_plus - f_minus) / (2 * step) - grad[k]) <= 1e-6 * max(1.0, abs(grad[k]))


@pytest.mark.parametrize("motion", ["planned_yaw", "nominal"])
def test_the_warm_starts_law_and_parameters_are_the_generic_ones(cfg, design, motion) -> None:  # type: ignore[no-untyped-def]
    """The RTI step's own copies of the terminal law (Rmpc._law_numbers) and of the parameter
    vector (Rmpc._parameters) give the generic functions' numbers bit for bit, so the warm
    start and the commands do not move."""
    from companion.core.rmpc import TargetMotion

    mpc = Rmpc(dataclasses.replace(cfg.rmpc, solver="nlp", target_motion=motion, jit=False),
               cfg.camera, design)  # (not compiled: only the numpy side is used)
    rng = np.random.default_rng(7)
    big_n = cfg.rmpc.horizon
    for _ in range(200):
        target = TargetMotion(rng.normal(size=(big_n, 2)), rng.normal(size=(big_n, 2)),
                              rng.normal(size=big_n) * 0.3, rng.normal(size=(big_n, 3)) * 0.1)
        eta = rng.normal(size=7) * [0.3, 0.3, 0.2, 0.5, 1.0, 1.0, 0.5]
        mpc._s4_ref = float(rng.normal())
        n = int(rng.integers(big_n))
        assert np.array_equal(mpc._law_numbers(eta, target, n), mpc._law(eta, target, n))
        assert np.array_equal(mpc._parameters(eta, target),
                              np.append(target.packed(), eta[3]))
