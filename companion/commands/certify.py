"""``companion certify``: evaluate the paper's certificate for a config (spec section 7).

Prints each condition of Assumption 2 and Theorems 1, 2 (left side, right side, holds?) and
whether the first RMPC problem is feasible from a given initial error (default: the paper's
``eta_e(0)``), so users see where the guarantee applies. Exit status 0 when every condition
holds, 1 when any fails (feasibility at ``eta0`` is reported, it does not change the status).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
from typing import Any

import numpy as np

from companion.config import Config, load_config
from companion.core.certificate import (
    PAPER_ETA0,
    PAPER_V_A,
    Certificate,
    CertificateInputs,
    Condition,
    FeasibilityReport,
    certify,
    feasibility_report,
    inputs_from_design,
)
from companion.core.design import design_terminal
from companion.core.terminal import TerminalDesign

log = logging.getLogger(__name__)


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "certify",
        help="evaluate the paper's stability/feasibility certificate for a config",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--config", default=None, help="config file (default config/paper.toml)")
    p.add_argument("--json", action="store_true", help="print JSON instead of the table")
    p.add_argument("--eta0", type=float, nargs=7, default=list(PAPER_ETA0),
                   metavar="X", help="initial error eta_e (7 numbers; default: the paper's)")
    p.add_argument("--v-a", type=float, nargs=2, default=list(PAPER_V_A), metavar="V",
                   help="target velocity in the virtual frame at eta0 (m/s; default the paper's)")
    p.add_argument("--no-rmpc", action="store_true",
                   help="skip the RMPC solve (only the exact necessary reach check)")
    p.set_defaults(func=run)


def _why(c: Condition, cert: Certificate, ci: CertificateInputs) -> str:
    """A short reason for a failed condition, from the numbers that decided it."""
    if c.name == "kappa":
        return (f"kappa = {c.lhs:.3g}: P allows no decay margin in (0, 1) (the DARE P meets "
                "the decay inequality with equality)" if c.lhs <= 0 else "kappa must be < 1")
    if c.name == "decay":
        return f"P, K allow kappa <= {c.rhs:.4g} only"
    if c.name == "remainder":
        return (f"the sampled nonlinear remainder ratio {c.lhs:.3g} exceeds kappa {c.rhs:.3g}")
    if c.name.startswith("input"):
        return "u_f = K eta + Gamma leaves U on Omega: reduce eps or the gain"
    if c.name == "cond2":
        qs = ci.q + ci.k.T @ ci.r @ ci.k
        return (f"lambda_max(P) = {np.linalg.eigvalsh(ci.p).max():.4g} is too large for "
                f"lambda_min(Q*) = {np.linalg.eigvalsh(qs).min():.3g} at eps = {ci.eps:.4g}")
    if c.name == "cond3":
        e = cert.visibility.eta
        return (f"Omega reaches |p| = {c.lhs:.4g} > gamma at se1 = {e[0]:.3f}, se2 = {e[1]:.3f}, "
                f"se3 = {e[2]:.3f} (|(se1, se2)| alone reaches {cert.visibility.se12_max:.4g})")
    return c.note


def _cond_dict(c: Condition) -> dict[str, Any]:
    return {"lhs": c.lhs, "rhs": c.rhs, "ok": c.ok}


def _report_dict(cfg: Config, d: TerminalDesign, ci: CertificateInputs, cert: Certificate,
                 feas: FeasibilityReport) -> dict[str, Any]:
    t1 = {c.name: _cond_dict(c) for c in cert.theorem1}
    return {
        "config": cfg.source,
        "method": d.method,
        "P": np.asarray(d.p).tolist(),
        "K": np.asarray(d.k).tolist(),
        "eps": d.eps,
        "kappa": d.kappa,
        "gamma": d.gamma,
        "r_v": d.r_v,
        "L": d.lipschitz_l,
        "holds": cert.holds,
        "assumption2": {c.name: _cond_dict(c) for c in cert.assumption2},
        "theorem1": t1,
        "theorem2": _cond_dict(cert.theorem2),
        "failed": {c.name: _why(c, cert, ci) for c in cert.failed},
        "not_in_verdict": {"cond2_sharp": _cond_dict(cert.cond2_sharp)},
        "notes": {c.name: c.note for c in cert.conditions},
        "gamma_ff_bound": list(ci.gamma_ff_bound),
        "visibility": {
            "max_p": cert.visibility.value,
            "se12_max": cert.visibility.se12_max,
            "argmax_eta": [float(x) for x in cert.visibility.eta],
        },
        "feasibility": {
            "eta0": list(feas.eta0),
            "v_a": list(feas.v_a_m_s),
            "feasible": feas.feasible,
            "solver_mode": feas.solver_mode,
            "solver_status": feas.solver_status,
            "reach": {
                r.name: {"lo": r.lo, "hi": r.hi, "omega_extent": r.omega, "ok": r.ok}
                for r in feas.reach
            },
        },
    }


def _rmpc_solver(cfg: Config, d: TerminalDesign, v_a: list[float]) -> Any:
    """``eta0 -> (mode, hard_status)`` with the project's RMPC (one solve, no JIT needed)."""
    from companion.core.rmpc import Rmpc, TargetMotion

    mpc = Rmpc(dataclasses.replace(cfg.rmpc, jit=False), cfg.camera, d)
    target = TargetMotion.constant(v_a, [0.0, 0.0], 0.0, cfg.rmpc.horizon)

    def solve(eta0: np.ndarray) -> tuple[str, str]:
        res = mpc.solve(eta0, target)
        return res.mode, res.hard_status

    return solve


def _fmt(x: float) -> str:
    return "inf" if math.isinf(x) else f"{x:.5g}"


def _print_table(cfg: Config, d: TerminalDesign, ci: CertificateInputs, cert: Certificate,
                 feas: FeasibilityReport) -> None:
    print(f"certificate for {cfg.source}: method {d.method}, eps {d.eps:.4g}, "
          f"kappa {d.kappa:.4g}, gamma {d.gamma:.4f}, r_v {d.r_v:.4f}, L {d.lipschitz_l:.4g}")
    print(f"  |Gamma| bound (paper AGV path): {', '.join(f'{g:.4g}' for g in ci.gamma_ff_bound)}")
    rows = [("Assumption 2", cert.assumption2), ("Theorem 1", cert.theorem1),
            ("Theorem 2", (cert.theorem2,))]
    print(f"  {'condition':<12} {'left side':>12} {'right side':>12}  holds  meaning")
    for title, conds in rows:
        print(f" {title}")
        for c in conds:
            print(f"  {c.name:<12} {_fmt(c.lhs):>12} {_fmt(c.rhs):>12}  "
                  f"{'yes' if c.ok else 'NO':<5}  {c.note}")
    s = cert.cond2_sharp
    print(f"  {'(cond2_sharp':<12} {_fmt(s.lhs):>12} {_fmt(s.rhs):>12}  "
          f"{'yes' if s.ok else 'NO':<5}  not in the verdict: {s.note})")
    print(f"  (max |p| on Omega at eta = {np.round(cert.visibility.eta, 4).tolist()}; "
          f"|(se1, se2)| alone: {cert.visibility.se12_max:.4g}; remainder check is sampled)")
    if cert.holds:
        print("VERDICT: every condition holds")
    else:
        print(f"VERDICT: {len(cert.failed)} condition(s) fail:")
        for c in cert.failed:
            print(f"  - {c.name}: {_why(c, cert, ci)}")
    print(f"first RMPC problem from eta0 = {list(feas.eta0)}, v_a = {list(feas.v_a_m_s)}:")
    for r in feas.reach:
        print(f"  {r.name}(N) reachable in [{r.lo:.4f}, {r.hi:.4f}], Omega extent +-{r.omega:.4f}"
              f": {'ok' if r.ok else 'MISSES Omega (infeasible)'}")
    if feas.solver_mode:
        print(f"  RMPC hard problem: {feas.solver_mode} ({feas.solver_status})")
    verdict = {True: "feasible", False: "INFEASIBLE", None: "not solved (--no-rmpc)"}
    print(f"  -> {verdict[feas.feasible]}")


def run(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    d = design_terminal(cfg.rmpc, cfg.camera)
    ci = inputs_from_design(cfg.rmpc, d)
    cert = certify(ci)
    solve = None if args.no_rmpc else _rmpc_solver(cfg, d, list(args.v_a))
    feas = feasibility_report(args.eta0, args.v_a, ci, cfg.rmpc.desired_depth_m, solve)
    if args.json:
        print(json.dumps(_report_dict(cfg, d, ci, cert, feas), indent=2))
    else:
        _print_table(cfg, d, ci, cert, feas)
    return 0 if cert.holds else 1
