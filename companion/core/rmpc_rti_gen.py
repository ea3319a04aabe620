"""The compiled functions of the real-time iteration (:mod:`companion.core.rmpc_rti`), derived
from the hard NLP (:func:`companion.core.rmpc_problem.build_nlp`).

A module of its own so that the compiled library's cache key hashes only the code that builds
the functions: editing the RTI's Python step does not recompile them (minutes of gcc).

- ``rti_lin(U, eta0, p) -> (H, g, c, J_c')``: single shooting over the N x 4 inputs ``U``;
  ``c`` is the shooting states of stages 1..N (7 N) followed by the NLP's own path rows (its
  ``g`` function evaluated on the rollout: they cannot drift from the full solve's), ``J_c'``
  their Jacobian transposed and dense (column-major storage, so numpy reads it as ``J_c``
  row-major without a copy: the layout DAQP takes). The cost is ``|r(U)|^2`` with ``r =
  [sqrt(Q) eta(n), sqrt(R) u_e(n), L' eta(N)]`` (``P = L L'``); ``H = 2 J_r' J_r`` (the
  Gauss-Newton Hessian, positive definite) and ``g = 2 J_r' r``.
- ``rti_val(U, eta0, p, lo, hi) -> (c, f, excess, total)``: the rows, the NLP's cost and the
  largest excess of a hard row (the nonlinear check, :func:`_val`).

Two libraries (``rmpc_rti_lin_*``, ``rmpc_rti_val_*``): each is found by its generated
source's hash, so a change to one does not recompile the other.

The scalar code is generated with common subexpressions eliminated; the Gauss-Newton product
is CasADi's sparse matrix product (index loops), not scalar code: measured, a product written
out as scalar code (one triangle, mirrored) is ~40 % faster with warm caches, but it is ~70 k
more instructions (~1 MB more machine code) and in flight, where each step finds its code
evicted from the caches, it was no faster (docs/reference/solver.md, "Measured"): the code's
size is what a step costs there.
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

from companion.core.dynamics import euler_step, input_error
from companion.core.params import CameraParams, RmpcParams
from companion.core.rmpc_problem import NP_STAGE, NU, NX, Layout, build_nlp, stage_motion
from companion.core.terminal import TerminalDesign


def lin_function(rmpc: RmpcParams, camera: CameraParams, terminal: TerminalDesign) -> ca.Function:
    """``rti_lin`` (module docstring)."""
    return _functions(rmpc, camera, terminal)[0]


def val_function(rmpc: RmpcParams, camera: CameraParams, terminal: TerminalDesign) -> ca.Function:
    """``rti_val`` (module docstring)."""
    return _functions(rmpc, camera, terminal)[1]


def _functions(rmpc: RmpcParams, camera: CameraParams,
               terminal: TerminalDesign) -> tuple[ca.Function, ca.Function]:
    """``(rti_lin, rti_val)`` (module docstring)."""
    big_n = rmpc.horizon
    nlp, lay = build_nlp(rmpc, camera, terminal, soft=False)
    oracle = ca.Function("nlp_fg", [nlp["x"], nlp["p"]], [nlp["f"], nlp["g"]])
    u_all = ca.SX.sym("U", NU * big_n)
    eta0 = ca.SX.sym("eta0", NX)
    par = ca.SX.sym("p", NP_STAGE * big_n + 1)
    s4_ref = par[NP_STAGE * big_n]
    sq_q = np.sqrt(np.asarray(rmpc.q_diag, dtype=float))
    sq_r = np.sqrt(np.asarray(rmpc.r_diag, dtype=float))
    chol_p = np.linalg.cholesky(np.asarray(terminal.p, dtype=float))  # P = L L'
    xs: list[ca.SX] = [eta0]
    res: list[ca.SX] = []
    for n in range(big_n):
        x, u = xs[n], u_all[NU * n: NU * (n + 1)]
        pn_ = par[NP_STAGE * n: NP_STAGE * (n + 1)]
        v_a, vdot_a, psidot_a = stage_motion(rmpc, x, u, pn_[0:2], pn_[2:4], pn_[4], s4_ref)
        res += [sq_q * x, sq_r * input_error(u, v_a, vdot_a, psidot_a)]
        xs.append(euler_step(x, u, v_a, vdot_a, psidot_a, rmpc.desired_depth_m, rmpc.dt_s))
    res.append(ca.mtimes(chol_p.T, xs[big_n]))
    w: list[Any] = [None] * lay.n_w
    for n in range(big_n + 1):
        for i in range(NX):
            w[int(lay.x_index[n, i])] = xs[n][i]
    for n in range(big_n):
        for i in range(NU):
            w[int(lay.u_index[n, i])] = u_all[NU * n + i]
    f, g = oracle(ca.vertcat(*w), par)
    path = ca.vertcat(*[g[row.g_index] for row in lay.rows])
    c = ca.vertcat(*xs[1:], path)
    r = ca.vertcat(*res)
    # the scalar part (common subexpressions eliminated: ~23 % fewer instructions); the
    # Gauss-Newton product as CasADi's sparse product loops (small code, see the docstring)
    core = ca.Function("rti_core", [u_all, eta0, par],
                       [r, ca.jacobian(r, u_all), c, ca.jacobian(c, u_all)], {"cse": True})
    um, em, pm = ca.MX.sym("U", u_all.shape[0]), ca.MX.sym("eta0", NX), ca.MX.sym("p", par.shape[0])
    r_m, jr_m, c_m, jc_m = core(um, em, pm)
    lin = ca.Function("rti_lin", [um, em, pm],
                      [ca.densify(2.0 * ca.mtimes(jr_m.T, jr_m)), 2.0 * ca.mtimes(jr_m.T, r_m),
                       c_m, ca.densify(jc_m.T)])
    return lin, _val(rmpc, lay, u_all, eta0, par, c, f)


def _val(rmpc: RmpcParams, lay: Layout, u_all: ca.SX, eta0: ca.SX, par: ca.SX, c: ca.SX,
         f: ca.SX) -> ca.Function:
    """``rti_val(U, eta0, p, lo, hi) -> (c, f, excess, total)``: ``excess`` the largest
    amount by which a hard row exceeds its bound (natural units: the path rows' square roots
    against their radii; the state box ``lo``, ``hi`` (N*7) in state units; the input box),
    the numbers of :meth:`companion.core.rmpc_rti.RtiSolver.violation`; ``total`` the sum of
    every row and the cost, which is finite only if all of them are (``fmax`` drops a NaN:
    the step's finiteness test reads this instead)."""
    n_s = NX * rmpc.horizon
    lo, hi = ca.SX.sym("lo", n_s), ca.SX.sym("hi", n_s)
    upper = np.array([row.upper for row in lay.rows], dtype=float)
    u_max = np.tile(np.asarray(rmpc.u_max, dtype=float), rmpc.horizon)
    states, path = c[:n_s], c[n_s:]
    terms = [ca.sqrt(ca.fmax(path, 0.0)) - np.sqrt(upper), states - hi, lo - states,
             ca.fabs(u_all) - u_max]
    excess = ca.mmax(ca.vertcat(*terms))
    return ca.Function("rti_val", [u_all, eta0, par, lo, hi],
                       [c, f, excess, ca.sum1(c) + f])
