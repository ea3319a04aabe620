"""The certificate (Assumption 2, Theorems 1, 2) and the LMI design, against independent
recomputation: every condition is re-derived here with its own short formulas, the max of |p|
over Omega is checked against dense sampling and a slice-wise generalized-eigenvalue method."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.config import load_config
from companion.core.certificate import (
    PAPER_ETA0,
    certify,
    inputs_from_design,
    max_visibility_on_omega,
    paper_path_feedforward_bound,
    remainder_ratio_max,
    terminal_reach,
    visibility_of,
)
from companion.core.design import design_terminal
from companion.core.dynamics import euler_step, terminal_feedforward
from companion.core.lmi import (
    PAPER_TERMINAL_STATE,
    lmi_certified_design,
    lmi_fit_design,
    lmi_terminal,
)
from companion.core.terminal import dare_terminal, linearised_model

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "config" / "paper.toml"
CERTIFIED = ROOT / "config" / "certified.toml"


# ---------------------------------------------------------------------------------------------
# Independent oracles (short formulas, none of the module's functions)


def _slice_max_p(p: np.ndarray, eps: float, n_t: int = 20001, n_th: int = 721) -> float:
    """max |p| over Omega by slices: for each se3 = t the (se1, se2) shadow of the slice is an
    ellipse (centre c(t), shape M, radius rho(t)); maximise |c + y| on it, then over t."""
    w3 = np.linalg.inv(p)[:3, :3]
    w33 = w3[2, 2]
    b = eps * math.sqrt(w33)
    if b >= 1.0:
        return math.inf
    m = w3[:2, :2] - np.outer(w3[:2, 2], w3[:2, 2]) / w33
    ev, evec = np.linalg.eigh(m)
    mh = evec @ np.diag(np.sqrt(np.maximum(ev, 0))) @ evec.T
    th = np.linspace(0, 2 * np.pi, n_th)
    circle = np.stack([np.cos(th), np.sin(th)])
    best = 0.0
    for t in np.linspace(-b, b, n_t)[1:-1]:
        rho = math.sqrt(max(eps**2 - t * t / w33, 0.0))
        c = t * w3[:2, 2] / w33
        if np.allclose(c, 0.0):
            val = rho * math.sqrt(max(ev[-1], 0.0))  # generalized eigenvalue of the slice
        else:
            val = float(np.max(np.linalg.norm(c[:, None] + rho * mh @ circle, axis=0)))
        best = max(best, val / (1.0 + t))
    return best


def _sample_omega_boundary(p: np.ndarray, eps: float, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((n, 7))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    lc = np.linalg.cholesky(p)  # P = L L'
    return eps * np.linalg.solve(lc.T, x.T).T  # eta' P eta = eps^2


def _recompute(p, k, kappa, eps, q, r, a, b, n_h, h, rho, big_l, dt, gamma, u_max, gff):
    """Every condition, from scratch: {name: (lhs, rhs)}."""
    out = {}
    ak = a + b @ k
    qs = q + k.T @ r @ k
    out["kappa_in_01"] = 0 < kappa < 1
    out["decay_eig"] = np.linalg.eigvalsh(ak.T @ p @ ak - (1 - kappa) * p + qs).max()
    pinv = np.linalg.inv(p)
    for i in range(4):
        out[f"input{i + 1}"] = (eps * math.sqrt(k[i] @ pinv @ k[i]) + gff[i], u_max[i])
    sq = math.sqrt(np.linalg.eigvalsh(p).max())  # lambda_max(sqrt(P))

    def lam(n):
        return sq * rho * math.exp(big_l * n * dt)

    ratio = np.linalg.eigvalsh(qs).min() / np.linalg.eigvalsh(p).max()
    out["cond1"] = (lam(n_h - 1), (h - 1) / n_h * eps)
    out["cond2"] = (lam(n_h), (1 - math.sqrt(1 - ratio)) * eps)
    out["cond3"] = (_slice_max_p(p, eps), gamma)
    lqp = np.linalg.eigvalsh(q).max() / np.linalg.eigvalsh(p).min()

    def x_tube(n):
        return ((n_h - n) * h + n) / n_h * eps

    s = sum(lam(n - 1) ** 2 + 2 * lam(n - 1) * x_tube(n) for n in range(1, n_h + 1))
    out["theorem2"] = (lqp * s + lam(n_h) ** 2 + 2 * math.sqrt(1 - ratio) * lam(n_h) * eps,
                       lqp * eps**2)
    return out


def _design_and_inputs(path: Path):
    cfg = load_config(path)
    d = design_terminal(cfg.rmpc, cfg.camera)
    ci = inputs_from_design(cfg.rmpc, d)
    return cfg, d, ci


def _check_against_recompute(ci, cert) -> None:
    rec = _recompute(ci.p, ci.k, ci.kappa, ci.eps, ci.q, ci.r, ci.a, ci.b, ci.horizon,
                     ci.tube_h, ci.rho, ci.lipschitz_l, ci.dt_s, ci.gamma, ci.u_max,
                     ci.gamma_ff_bound)
    got = {c.name: c for c in cert.conditions}
    assert got["kappa"].ok == rec["kappa_in_01"]
    # decay: kappa <= margin  <=>  the matrix inequality holds (up to round-off)
    assert got["decay"].ok == (rec["decay_eig"] <= 1e-12 * np.abs(ci.p).max())
    for name in ("input1", "input2", "input3", "input4", "cond1", "cond2", "cond3",
                 "theorem2"):
        lhs, rhs = rec[name]
        assert got[name].ok == (lhs <= rhs), name
        assert got[name].lhs == pytest.approx(lhs, rel=1e-5), name
        assert got[name].rhs == pytest.approx(rhs, rel=1e-9), name


# ---------------------------------------------------------------------------------------------
# The two configs


def test_certified_config_all_conditions_hold_and_recompute() -> None:
    _, d, ci = _design_and_inputs(CERTIFIED)
    cert = certify(ci)
    assert cert.holds, [(c.name, c.lhs, c.rhs) for c in cert.failed]
    _check_against_recompute(ci, cert)
    rec = _recompute(ci.p, ci.k, ci.kappa, ci.eps, ci.q, ci.r, ci.a, ci.b, ci.horizon,
                     ci.tube_h, ci.rho, ci.lipschitz_l, ci.dt_s, ci.gamma, ci.u_max,
                     ci.gamma_ff_bound)
    assert 0 < d.kappa < 1
    assert rec["decay_eig"] <= 0.0
    for name in ("input1", "input2", "input3", "input4", "cond1", "cond2", "cond3",
                 "theorem2"):
        assert rec[name][0] <= rec[name][1], name


def test_certified_remainder_on_true_nonlinear_steps() -> None:
    """Assumption 2 (3) with the real Euler step and the terminal law u = K eta + Gamma:
    r = eta+ - A_K eta, for random target motion within the paper path's bounds."""
    _, d, ci = _design_and_inputs(CERTIFIED)
    ak = ci.a + ci.b @ ci.k
    a_max, _, _, psidot_max = paper_path_feedforward_bound()
    rng = np.random.default_rng(7)
    etas = _sample_omega_boundary(ci.p, ci.eps, 3000, seed=3)
    etas *= rng.uniform(0.2, 1.0, size=(len(etas), 1))
    worst = -np.inf
    for eta in etas:
        v_a = rng.uniform(-0.15, 0.15, 2)
        psidot_a = rng.uniform(-psidot_max, psidot_max)
        psidot_q = float(ci.k[3] @ eta + psidot_a)
        # vdot_a as seen in the rotating frame: R^T a + psidot_q [v_ay, -v_ax], |a| <= a_max
        acc = rng.uniform(-a_max, a_max, 2) / math.sqrt(2)
        vdot_a = acc + psidot_q * np.array([v_a[1], -v_a[0]])
        gam = terminal_feedforward(v_a, vdot_a, psidot_a, psidot_q)
        assert np.all(np.abs(gam) <= np.array(ci.gamma_ff_bound) + 1e-12)
        u = ci.k @ eta + gam
        nxt = euler_step(eta, u, v_a, vdot_a, psidot_a, 2.0, ci.dt_s)
        r = nxt - ak @ eta
        worst = max(worst, (r @ ci.p @ r + 2 * eta @ ak.T @ ci.p @ r) / (eta @ ci.p @ eta))
    assert worst <= d.kappa
    sampled, _ = remainder_ratio_max(ci.a, ci.b, ci.k, ci.p, ci.eps, ci.dt_s, psidot_max)
    assert worst <= sampled * (1 + 1e-9)  # the module's ray-exact max dominates random samples


def test_paper_config_verdicts_match_recompute_and_name_the_failures() -> None:
    _, d, ci = _design_and_inputs(PAPER)
    cert = certify(ci)
    _check_against_recompute(ci, cert)
    failed = {c.name for c in cert.failed}
    assert failed == {"kappa", "remainder", "cond3"}
    assert d.kappa == 0.0
    # the brief's own figure (0.32) is |(se1, se2)| alone; with p = se/s3 it is larger
    assert cert.visibility.se12_max == pytest.approx(0.318, abs=2e-3)
    assert cert.visibility.value > 0.4


def test_dare_scaled_eps_011_cond3_fails_with_s3() -> None:
    """P = 1.03 P_DARE, eps = 0.11: |(se1, se2)| <= gamma holds, but |p| = |se|/s3 does not."""
    cfg = load_config(PAPER, overrides=["rmpc.eps=0.11", "rmpc.terminal.p_scale=1.03"])
    d = design_terminal(cfg.rmpc, cfg.camera)
    cert = certify(inputs_from_design(cfg.rmpc, d))
    assert d.kappa == pytest.approx(6.4e-4, rel=0.05)
    assert cert.visibility.se12_max < d.gamma < cert.visibility.value
    assert {c.name for c in cert.failed} == {"cond3"}


# ---------------------------------------------------------------------------------------------
# max |p| over Omega


def test_max_visibility_matches_dense_sampling_and_slices() -> None:
    cfg = load_config(PAPER)
    a, b = linearised_model(cfg.rmpc.dt_s, cfg.rmpc.desired_depth_m)
    p = dare_terminal(a, b, np.diag(cfg.rmpc.q_diag), np.diag(cfg.rmpc.r_diag)).p
    eps = 0.15
    vm = max_visibility_on_omega(p, eps)
    samples = _sample_omega_boundary(p, eps, 400_000, seed=1)
    sampled = float(np.max(visibility_of(samples)))
    assert sampled <= vm.value * (1 + 1e-9)
    assert sampled >= vm.value * (1 - 2e-2)
    assert vm.value == pytest.approx(_slice_max_p(p, eps), rel=1e-5)
    # the reported maximiser is on Omega's boundary and attains the value
    assert vm.eta @ p @ vm.eta == pytest.approx(eps**2, rel=1e-9)
    assert float(visibility_of(vm.eta)) == pytest.approx(vm.value, rel=1e-7)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), eps=st.floats(0.05, 0.4))
def test_max_visibility_general_ellipsoids(seed: int, eps: float) -> None:
    """Coupled (se1, se2, se3) shapes, where the slice centres are off the origin."""
    rng = np.random.default_rng(seed)
    m = rng.standard_normal((7, 7))
    p = m @ m.T + 0.5 * np.eye(7)
    vm = max_visibility_on_omega(p, eps)
    slice_val = _slice_max_p(p, eps, n_t=4001, n_th=721)
    if math.isinf(slice_val):
        assert math.isinf(vm.value)
        return
    assert vm.value == pytest.approx(slice_val, rel=2e-4)
    samples = _sample_omega_boundary(p, eps, 20000, seed=seed % 1000)
    assert float(np.max(visibility_of(samples))) <= vm.value * (1 + 1e-9)


def test_max_visibility_infinite_when_s3_reaches_zero() -> None:
    p = np.eye(7)
    assert math.isinf(max_visibility_on_omega(p, 1.0).value)
    # diagonal oracle: semi-axes a (se1, se2), b (se3): max_z a sqrt(1 - z^2/b^2)/(1 - z)
    p = np.diag([4.0, 4.0, 16.0, 1, 1, 1, 1])
    eps = 0.5
    a_ax, b_ax = eps / 2, eps / 4
    z = np.linspace(0, b_ax, 200001)[:-1]
    oracle = float(np.max(a_ax * np.sqrt(1 - (z / b_ax) ** 2) / (1 - z)))
    assert max_visibility_on_omega(p, eps).value == pytest.approx(oracle, rel=1e-8)


# ---------------------------------------------------------------------------------------------
# LMI design


def test_lmi_result_satisfies_the_matrix_inequality() -> None:
    cfg = load_config(PAPER)
    rm = cfg.rmpc
    a, b = linearised_model(rm.dt_s, rm.desired_depth_m)
    q, r = np.diag(rm.q_diag), np.diag(rm.r_diag)
    gff = paper_path_feedforward_bound()
    kappa = 1e-3
    des = lmi_terminal(a, b, q, r, eps=0.15, kappa=kappa, u_max=rm.u_max, gamma_ff_bound=gff)
    p, k = des.p, des.k
    assert np.linalg.eigvalsh(p).min() > 0
    ak = a + b @ k
    lhs = ak.T @ p @ ak - (1 - kappa) * p + q + k.T @ r @ k
    assert np.linalg.eigvalsh(lhs).max() <= 1e-7 * np.abs(p).max()
    pinv = np.linalg.inv(p)
    for i in range(4):
        assert 0.15 * math.sqrt(k[i] @ pinv @ k[i]) + gff[i] <= rm.u_max[i] * (1 + 1e-6)
    # P dominates the DARE solution (it is the smallest cost-to-go of any K)
    p_dare = dare_terminal(a, b, q, r).p
    assert np.linalg.eigvalsh(p - p_dare).min() >= -1e-6


def test_lmi_certified_design_and_method_lmi() -> None:
    cfg = load_config(PAPER, overrides=["rmpc.eps=0.11", "rmpc.terminal.method='lmi'"])
    d = design_terminal(cfg.rmpc, cfg.camera)
    assert d.method == "lmi"
    assert 0 < d.kappa <= 4e-4
    cert = certify(inputs_from_design(cfg.rmpc, d))
    assert cert.holds, [(c.name, c.lhs, c.rhs) for c in cert.failed]
    # deterministic: the same design twice
    rm = cfg.rmpc
    a, b = linearised_model(rm.dt_s, rm.desired_depth_m)
    again = lmi_certified_design(a, b, np.diag(rm.q_diag), np.diag(rm.r_diag), eps=rm.eps,
                                 u_max=rm.u_max, gamma_ff_bound=paper_path_feedforward_bound(),
                                 gamma=d.gamma)
    np.testing.assert_allclose(again.p, d.p, rtol=1e-9, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# Small pieces


def test_paper_path_feedforward_bound() -> None:
    a1, a2, a3, a4 = paper_path_feedforward_bound()
    assert (a1, a2, a3) == pytest.approx((0.0025, 0.0025, 0.0), abs=1e-9)
    # psidot_a = -0.025 sin / (1 + cos^2): largest where cos = 0
    assert a4 == pytest.approx(0.025, rel=1e-6)


def test_terminal_reach_depth_bound_is_attained_by_full_descent() -> None:
    _, _, ci = _design_and_inputs(CERTIFIED)
    se3, se4 = terminal_reach(PAPER_ETA0, ci.p, ci.eps, ci.dt_s, 2.0, ci.horizon, ci.u_max, 0.0)
    eta = np.array(PAPER_ETA0)
    for _ in range(ci.horizon):  # full descent acceleration and full yaw rate towards 0
        eta = euler_step(eta, np.array([0.0, 0.0, 1.5, 0.3]), [0.0, 0.0], [0.0, 0.0], 0.0, 2.0,
                         ci.dt_s)
    assert se3.lo == pytest.approx(eta[2], abs=1e-12) == pytest.approx(0.375, abs=1e-12)
    assert se4.lo == pytest.approx(eta[3], abs=1e-12)
    assert not se3.ok  # the certified Omega ends at |se3| ~ 0.19
    assert se4.ok


def test_fit_design_feasible_at_paper_start_fails_only_the_papers_cond2() -> None:
    """Omega shaped for the paper's start (eps = 0.13): every condition but the paper's
    Theorem 1 (2) holds, its sharper form holds, and the RMPC stays on its hard problem for
    10 s of closed loop from eta_e(0) (the real RMPC, nominal model + rho-bounded noise)."""
    import dataclasses

    from companion.core.rmpc import Rmpc
    from companion.core.rmpc_scenario import closed_loop

    cfg = load_config(PAPER, overrides=["rmpc.eps=0.13"])
    rm = cfg.rmpc
    a, b = linearised_model(rm.dt_s, rm.desired_depth_m)
    d0 = design_terminal(rm, cfg.camera)
    des = lmi_fit_design(a, b, np.diag(rm.q_diag), np.diag(rm.r_diag), eps=0.13,
                         fit_state=PAPER_TERMINAL_STATE, fit_level=0.97, u_max=rm.u_max,
                         gamma_ff_bound=paper_path_feedforward_bound(), gamma=d0.gamma)
    d = dataclasses.replace(d0, p=des.p, k=des.k, kappa=des.kappa, method="given")
    ci = inputs_from_design(rm, d)
    cert = certify(ci)
    assert {c.name for c in cert.failed} == {"cond2"}
    assert cert.cond2_sharp.ok
    assert cert.cond2_sharp.rhs >= cert.theorem1[1].rhs  # never more demanding
    # the sharper contraction, checked on true nonlinear terminal-law steps from Omega
    c_sharp = 1.0 - cert.cond2_sharp.rhs / ci.eps
    for eta in _sample_omega_boundary(ci.p, ci.eps, 2000, seed=5):
        psidot_q = float(ci.k[3] @ eta)
        u = ci.k @ eta + terminal_feedforward(np.zeros(2), np.zeros(2), 0.0, psidot_q)
        nxt = euler_step(eta, u, [0.0, 0.0], [0.0, 0.0], 0.0, 2.0, ci.dt_s)
        assert math.sqrt(nxt @ ci.p @ nxt) <= c_sharp * ci.eps * (1 + 1e-9)
    mpc = Rmpc(dataclasses.replace(rm, jit=False), cfg.camera, d)
    steps = closed_loop(mpc, np.array(PAPER_ETA0), 200, rm.rho, seed=1)
    assert all(s.result.mode == "optimal" for s in steps)
    end = steps[-1].eta
    assert math.sqrt(end @ ci.p @ end) <= ci.eps  # converged into Omega (Theorem 2)
