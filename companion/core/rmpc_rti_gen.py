"""The compiled functions of the real-time iteration (:mod:`companion.core.rmpc_rti`), derived
from the hard NLP's own pieces (:mod:`companion.core.rmpc_problem`).

A module of its own so that the compiled libraries' cache key hashes only the code that
builds the functions: editing the RTI's Python step does not recompile them.

- ``rti_lin(U, eta0, p) -> (H, g, c, J_c')``: single shooting over the N x 4 inputs ``U``;
  ``c`` is the shooting states of stages 1..N (7 N) followed by the path rows (hard layout
  order), ``J_c'`` their Jacobian transposed and dense (column-major storage, so numpy reads
  it as ``J_c`` row-major without a copy: the layout DAQP takes). The cost is ``|r(U)|^2``
  with ``r = [sqrt(Q) eta(n), sqrt(R) u_e(n), L' eta(N)]`` (``P = L L'``); ``H = 2 J_r' J_r``
  (the Gauss-Newton Hessian, positive definite) and ``g = 2 J_r' r``.
- ``rti_val(U, eta0, p, lo, hi) -> (c, f, excess, total)``: the rows evaluated by the NLP's
  own ``g`` function on the rollout, the NLP's cost, and the largest excess of a hard row
  (the nonlinear check, :func:`_val`).

``rti_lin`` is **condensed from stage Jacobians** (:func:`lin_function`): one small
function per kind of stage (the dynamics, the residuals and the stage's path rows of
:func:`companion.core.rmpc_problem._path_items`, the code ``build_nlp`` builds its rows
with, and their Jacobians in ``(x, u)``), called once per stage, and the products
``dx(n)/du(k) = A(n-1) ... A(k+1) B(k)`` of 7 x 7 and 7 x 4 blocks. Its C code is ~0.3 MB
instead of the ~3 MB of the whole rollout differentiated as one expression: measured, the
in-flight cost of the linearisation is its code's size (each step finds it evicted from the
caches), not its operation count (docs/reference/solver.md, "Measured").

``rmpc.rti_linearisation = "scalar"`` (:func:`_scalar_lin_function`): the same numbers to
~1e-15, ``H`` and ``g`` by a backward recursion over the stages (:func:`_gauss_newton`,
O(N^2) 4 x 4 blocks, ``J_r`` never formed) and the whole function expanded into scalar code
(~66 k operations, a ~1.1 MB library, ~73 s of CPU to compile): 3x faster with warm caches,
within the run-to-run spread of the default in flight (cold caches); docs/reference/solver.md,
"Measured". ``rti_val`` evaluates the rows the other way (the NLP's ``g``), so the two cannot
drift apart unseen (tests/core/test_rmpc_rti.py compares them, and ``H``, ``g`` of both forms
with those of the whole rollout differentiated as one expression).

``rmpc.rti_linearisation = "loops"`` (:mod:`companion.core.rmpc_rti_loops`): this module's
stage functions, with the condensing of :func:`lin_function` as fixed C loops around them:
the same numbers bit for bit, ~1/8 of the code.

Two libraries (``rmpc_rti_lin_*``, ``rmpc_rti_val_*``): each is found by its generated
source's hash, so a change to one does not recompile the other.
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

from companion.core.dynamics import euler_step, input_error
from companion.core.params import CameraParams, RmpcParams
from companion.core.rmpc_problem import (
    NP_STAGE,
    NU,
    NX,
    Layout,
    _path_items,
    build_nlp,
    stage_motion,
    visibility_pairs,
)
from companion.core.terminal import TerminalDesign


def lin_function(rmpc: RmpcParams, camera: CameraParams, terminal: TerminalDesign) -> ca.Function:
    """``rti_lin``, condensed from stage Jacobians (module docstring); its scalar form with
    ``rmpc.rti_linearisation = "scalar"``."""
    if rmpc.rti_linearisation == "scalar":
        return _scalar_lin_function(rmpc, camera, terminal)
    big_n = rmpc.horizon
    stage = _StageFunctions(rmpc, camera, terminal)
    u_all, eta0 = ca.MX.sym("U", NU * big_n), ca.MX.sym("eta0", NX)
    par = ca.MX.sym("p", NP_STAGE * big_n + 1)
    x = eta0
    sens: list[ca.MX] = []  # dx(n)/du(k), k < n
    rv: list[ca.MX] = []
    jr: list[ca.MX] = []
    gv: list[ca.MX] = []
    jg: list[ca.MX] = []
    xv: list[ca.MX] = []
    jx: list[ca.MX] = []

    def blocks(j_x: ca.MX, j_u: ca.MX | None, n: int, rows: int) -> ca.MX:
        """A row block of the condensed Jacobian: ``J_x dx(n)/du(k)`` for k < n, ``J_u``
        at k = n, zeros after."""
        out = [ca.mtimes(j_x, s_k) for s_k in sens] + ([j_u] if j_u is not None else [])
        return ca.horzcat(*out, *[ca.MX(rows, NU)] * (big_n - len(out)))

    for n in range(big_n):
        x_next, r, g, a, b, r_x, r_u, g_x, g_u = stage.function(n)(
            x, u_all[NU * n: NU * (n + 1)], par[NP_STAGE * n: NP_STAGE * (n + 1)],
            par[NP_STAGE * big_n])
        rv.append(r)
        jr.append(blocks(r_x, r_u, n, r.shape[0]))
        if g.shape[0]:
            gv.append(g)
            jg.append(blocks(g_x, g_u, n, g.shape[0]))
        sens = [ca.mtimes(a, s_k) for s_k in sens] + [b]
        x = x_next
        xv.append(x)
        jx.append(ca.horzcat(*sens, *[ca.MX(NX, NU)] * (big_n - len(sens))))
    r_n, g_n, r_nx, g_nx = stage.terminal(x)
    rv.append(r_n)
    jr.append(blocks(r_nx, None, big_n, r_n.shape[0]))
    gv.append(g_n)
    jg.append(blocks(g_nx, None, big_n, g_n.shape[0]))
    j_r, r_all = ca.vertcat(*jr), ca.vertcat(*rv)
    j_c = ca.vertcat(*jx, *jg)
    return ca.Function("rti_lin", [u_all, eta0, par],
                       [ca.densify(2.0 * ca.mtimes(j_r.T, j_r)), 2.0 * ca.mtimes(j_r.T, r_all),
                        ca.vertcat(*xv, *gv), ca.densify(j_c.T)])


def _scalar_lin_function(rmpc: RmpcParams, camera: CameraParams,
                         terminal: TerminalDesign) -> ca.Function:
    """``rti_lin`` with ``rmpc.rti_linearisation = "scalar"`` (module docstring):
    ``S(n) = dx(n)/d(u(0), ..., u(n-1))`` (7 x 4 n) is one matrix, ``S(n+1) = [A(n) S(n),
    B(n)]``; H and g by :func:`_gauss_newton`; the graph then expanded into scalar code."""
    big_n = rmpc.horizon
    stage = _StageFunctions(rmpc, camera, terminal)
    u_all, eta0 = ca.MX.sym("U", NU * big_n), ca.MX.sym("eta0", NX)
    par = ca.MX.sym("p", NP_STAGE * big_n + 1)
    x = eta0
    sens = ca.MX(NX, 0)  # S(n)
    stages: list[list[ca.MX]] = []  # (r, A, B, R_x, R_u, S(n)) of each stage
    gv: list[ca.MX] = []
    jg: list[ca.MX] = []
    xv: list[ca.MX] = []
    jx: list[ca.MX] = []

    def blocks(j_x: ca.MX, j_u: ca.MX | None, n: int, rows: int) -> ca.MX:
        """A row block of the condensed Jacobian: ``J_x S(n)``, ``J_u`` at stage n, zeros
        after."""
        out = ([ca.mtimes(j_x, sens)] if n else []) + ([j_u] if j_u is not None else [])
        done = n + (j_u is not None)
        return ca.horzcat(*out, ca.MX(rows, NU * (big_n - done)))

    for n in range(big_n):
        x_next, r, g, a, b, r_x, r_u, g_x, g_u = stage.function(n)(
            x, u_all[NU * n: NU * (n + 1)], par[NP_STAGE * n: NP_STAGE * (n + 1)],
            par[NP_STAGE * big_n])
        stages.append([r, a, b, r_x, r_u, sens])
        if g.shape[0]:
            gv.append(g)
            jg.append(blocks(g_x, g_u, n, g.shape[0]))
        sens = ca.horzcat(ca.mtimes(a, sens), b) if n else b
        x = x_next
        xv.append(x)
        jx.append(ca.horzcat(sens, ca.MX(NX, NU * (big_n - n - 1))))
    r_n, g_n, r_nx, g_nx = stage.terminal(x)
    gv.append(g_n)
    jg.append(blocks(g_nx, None, big_n, g_n.shape[0]))
    hess, grad = _gauss_newton(stages, r_n, r_nx)
    j_c = ca.vertcat(*jx, *jg)
    graph = ca.Function("rti_lin", [u_all, eta0, par],
                        [ca.densify(hess), grad, ca.vertcat(*xv, *gv), ca.densify(j_c.T)])
    # as scalar code: the graph's ~1000 sparse matrix products cost ~150 us as library
    # calls, the ~66 k scalar operations they expand to ~30-60 us (~1.1 MB of machine code)
    scalar = graph.expand()
    return ca.Function("rti_lin", scalar.sx_in(), scalar.call(scalar.sx_in()), {"cse": True})


def _gauss_newton(stages: list[list[ca.MX]], r_n: ca.MX, r_nx: ca.MX) -> tuple[ca.MX, ca.MX]:
    """``H = 2 J_r' J_r`` and ``g = 2 J_r' r`` of the condensed residuals without forming
    ``J_r`` (O(N^2) small blocks instead of the (11 N + 7) x 4 N product): with ``P(N) =
    R_N' R_N``, ``P(k) = R_x(k)' R_x(k) + A(k)' P(k+1) A(k)`` (the cost-to-go's curvature in
    ``x(k)``) and ``l(N) = R_N' r_N``, ``l(k) = R_x(k)' r(k) + A(k)' l(k+1)``, stage k's blocks
    are ``H(k,k) = R_u' R_u + B' P(k+1) B``, ``H(0..k-1, k) = S(k)' (R_x' R_u + A' P(k+1) B)``
    (mirrored below the diagonal) and ``g(k) = R_u' r(k) + B' l(k+1)`` (stage k's matrices)."""
    big_n = len(stages)
    p_next = ca.mtimes(r_nx.T, r_nx)
    l_next = ca.mtimes(r_nx.T, r_n)
    diag: list[ca.MX] = [ca.MX()] * big_n
    upper: list[ca.MX] = [ca.MX()] * big_n  # column k of the strictly upper triangle
    g: list[ca.MX] = [ca.MX()] * big_n
    for k in range(big_n - 1, -1, -1):
        r, a, b, r_x, r_u, s_k = stages[k]
        pb = ca.mtimes(p_next, b)
        diag[k] = ca.mtimes(r_u.T, r_u) + ca.mtimes(b.T, pb)
        g[k] = ca.mtimes(r_u.T, r) + ca.mtimes(b.T, l_next)
        column = [ca.MX(NU * (big_n - k), NU)]
        if k:
            w = ca.mtimes(r_x.T, r_u) + ca.mtimes(a.T, pb)
            column.insert(0, ca.mtimes(s_k.T, w))
            p_next = ca.mtimes(r_x.T, r_x) + ca.mtimes(a.T, ca.mtimes(p_next, a))
            l_next = ca.mtimes(r_x.T, r) + ca.mtimes(a.T, l_next)
        upper[k] = ca.vertcat(*column)
    strict = ca.horzcat(*upper)
    return 2.0 * (strict + strict.T + ca.diagcat(*diag)), 2.0 * ca.vertcat(*g)


class _StageFunctions:
    """The per-stage functions of :func:`lin_function`: ``(x, u, p_n, s4_ref) -> (x_next,
    r, g, A, B, R_x, R_u, G_x, G_u)`` (one per set of path rows: stages with the same rows
    share the function, so its code once) and the terminal ``x_N -> (r_N, g_N, R_N, G_N)``."""

    def __init__(self, rmpc: RmpcParams, camera: CameraParams, terminal: TerminalDesign) -> None:
        self.rmpc, self.camera, self.design = rmpc, camera, terminal
        self.vis_stage = {st: img for st, img, _ in visibility_pairs(rmpc)}
        self.x, self.u = ca.SX.sym("x", NX), ca.SX.sym("u", NU)
        self.pn, self.s4_ref = ca.SX.sym("p_n", NP_STAGE), ca.SX.sym("s4_ref")
        pn = self.pn
        v_a, vdot_a, psidot_a = stage_motion(rmpc, self.x, self.u, pn[0:2], pn[2:4], pn[4],
                                             self.s4_ref)
        self.x_next = euler_step(self.x, self.u, v_a, vdot_a, psidot_a, rmpc.desired_depth_m,
                                 rmpc.dt_s)
        self.r = ca.vertcat(np.sqrt(np.asarray(rmpc.q_diag, dtype=float)) * self.x,
                            np.sqrt(np.asarray(rmpc.r_diag, dtype=float))
                            * input_error(self.u, v_a, vdot_a, psidot_a))
        self._made: dict[tuple[tuple[str, int], ...], ca.Function] = {}

    def function(self, n: int) -> ca.Function:
        """Stage ``n``'s function (its path rows as ``build_nlp`` lays them out)."""
        items = _path_items(self.rmpc, self.camera, self.design, n, self.x, self.u,
                            self.x_next, self.pn[5:8], self.vis_stage)
        key = tuple((kind, corner) for _, kind, _, _, corner in items)
        if key not in self._made:
            g = ca.vertcat(*[item[2] for item in items])
            x, u, x_next, r = self.x, self.u, self.x_next, self.r
            self._made[key] = ca.Function(
                f"rti_stage{len(self._made)}", [x, u, self.pn, self.s4_ref],
                [x_next, r, g, ca.jacobian(x_next, x), ca.jacobian(x_next, u),
                 ca.jacobian(r, x), ca.jacobian(r, u), ca.jacobian(g, x), ca.jacobian(g, u)],
                {"cse": True})
        return self._made[key]

    def terminal_function(self) -> ca.Function:
        """``x_N -> (r_N, g_N, dr_N/dx_N, dg_N/dx_N)``."""
        xt = ca.SX.sym("x_N", NX)
        items = _path_items(self.rmpc, self.camera, self.design, self.rmpc.horizon, xt,
                            None, None, None, self.vis_stage)
        g = ca.vertcat(*[item[2] for item in items])
        chol_p = np.linalg.cholesky(np.asarray(self.design.p, dtype=float))  # P = L L'
        r = ca.mtimes(chol_p.T, xt)
        return ca.Function("rti_terminal", [xt], [r, g, ca.jacobian(r, xt), ca.jacobian(g, xt)],
                           {"cse": True})

    def terminal(self, x_n: ca.MX) -> list[ca.MX]:
        """``(r_N, g_N, dr_N/dx_N, dg_N/dx_N)`` at ``x_n``."""
        out: list[ca.MX] = self.terminal_function().call([x_n])
        return out


def val_function(rmpc: RmpcParams, camera: CameraParams, terminal: TerminalDesign) -> ca.Function:
    """``rti_val``: the rollout (no derivatives), its rows by the NLP's own ``g`` (module
    docstring)."""
    big_n = rmpc.horizon
    nlp, lay = build_nlp(rmpc, camera, terminal, soft=False)
    oracle = ca.Function("nlp_fg", [nlp["x"], nlp["p"]], [nlp["f"], nlp["g"]])
    u_all = ca.SX.sym("U", NU * big_n)
    eta0 = ca.SX.sym("eta0", NX)
    par = ca.SX.sym("p", NP_STAGE * big_n + 1)
    s4_ref = par[NP_STAGE * big_n]
    xs: list[ca.SX] = [eta0]
    for n in range(big_n):
        x, u = xs[n], u_all[NU * n: NU * (n + 1)]
        pn_ = par[NP_STAGE * n: NP_STAGE * (n + 1)]
        v_a, vdot_a, psidot_a = stage_motion(rmpc, x, u, pn_[0:2], pn_[2:4], pn_[4], s4_ref)
        xs.append(euler_step(x, u, v_a, vdot_a, psidot_a, rmpc.desired_depth_m, rmpc.dt_s))
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
    return _val(rmpc, lay, u_all, eta0, par, c, f)


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
