"""Real-time iteration (RTI) of the RMPC's hard problem (``rmpc.solver = "rti"``).

One step solves one (at most ``rmpc.rti_max_qp``) dense QP built from the same NLP as the
full solve (:func:`companion.core.rmpc_problem.build_nlp`: the same cost, tube, visibility and
terminal rows, the same state box), linearised at the previous plan shifted by one stage:

- single shooting: the decision is the N x 4 inputs ``U``; the states are the nonlinear
  rollout of the NLP's own dynamics from ``eta0`` (so the plan's dynamics are exact);
- the cost is quadratic in ``(eta, u_e)``, ``f = |r(U)|^2`` with ``r = [sqrt(Q) eta(n),
  sqrt(R) u_e(n), L' eta(N)]`` (``P = L L'``), so the Gauss-Newton Hessian ``2 J_r' J_r`` is
  positive definite without any second derivative;
- the path rows are the NLP's rows evaluated on the rollout (the NLP's own ``g`` function
  called on the shooting states: they cannot drift from the full solve's), linearised;
- one compiled CasADi function (cached like the NLPs, :func:`compiled_functions`) returns
  ``r``, ``J_r``, the rows and their Jacobian; a second one only the rows and the cost (the
  check). DAQP (a dual active-set solver for small dense QPs) solves the QP in-process with a
  bounded number of iterations.

Every plan is then rolled out through the nonlinear model and every hard row evaluated
(:meth:`RtiSolver.step`): a row exceeded by more than ``rmpc.rti_tol`` (natural units),
or a QP that failed, re-linearises at the QP's solution (up to ``rmpc.rti_max_qp`` QPs) and
then gives up: :class:`companion.core.rmpc.Rmpc` solves the full NLP for that step.
docs/reference/solver.md has the design, the guarantees and the figures.
"""

from __future__ import annotations

import hashlib
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import casadi as ca
import daqp
import numpy as np

from companion.core.dynamics import euler_step, input_error
from companion.core.params import CameraParams, RmpcParams
from companion.core.rmpc_cache import (
    CompiledNlp,
    RmpcBuildError,
    compiled_functions,
    problem_key,
)
from companion.core.rmpc_problem import NP_STAGE, NU, NX, build_nlp, stage_motion
from companion.core.terminal import TerminalDesign

log = logging.getLogger(__name__)

QP_ITER_LIMIT = 500
"""DAQP's active-set iterations per QP (measured: 2-40 on the paper, edge and figure-eight
flights); a QP that needs more is a failure and the step goes to the full NLP."""
DAQP_INF = 1e30
"""DAQP's 'no bound'."""
DAQP_OPTIMAL = (1, 2)
"""DAQP exit flags of a solved QP (1 optimal, 2 optimal with soft constraints)."""


@dataclass(frozen=True)
class RtiOutcome:
    """One RTI step. ``ok``: the plan passed the nonlinear check; ``status``: ``rti: ...``
    (what was solved, or why it was rejected); ``eta`` (N+1, 7) and ``u`` (N, 4): the last
    plan (the rollout of its inputs); ``cost``: its NLP cost; ``qp_iterations``: DAQP's
    iterations summed over the step's QPs; ``qps``: QPs solved; ``violation``: the largest
    excess of a hard row of the last plan (natural units; inf after a QP failure)."""

    ok: bool
    status: str
    eta: np.ndarray
    u: np.ndarray
    cost: float
    qp_iterations: int
    qps: int
    violation: float


def _stage_functions(rmpc: RmpcParams, camera: CameraParams,
                     terminal: TerminalDesign) -> tuple[ca.Function, ca.Function]:
    """``lin(U, eta0, p) -> (H, g, c, J_c')`` (the Gauss-Newton Hessian ``2 J_r' J_r``, the
    gradient ``2 J_r' r``, the rows and their Jacobian, transposed: row-major) and
    ``val(U, eta0, p) -> (c, f)``, with ``c`` the shooting states of stages 1..N (7 N)
    followed by the NLP's path rows (hard layout order); and the path rows' upper bounds
    (the NLP's, squared form)."""
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
    core = ca.Function("rti_core", [u_all, eta0, par],
                       [r, ca.jacobian(r, u_all), c, ca.jacobian(c, u_all)])
    # the Gauss-Newton products in the generated C (sparse loops), not in numpy: a BLAS call
    # on a busy machine cost ~2 ms of CPU for this 183 x 64 product (thread hand-offs)
    um, em, pm = ca.MX.sym("U", u_all.shape[0]), ca.MX.sym("eta0", NX), ca.MX.sym("p", par.shape[0])
    r_m, jr_m, c_m, jc_m = core(um, em, pm)
    lin = ca.Function("rti_lin", [um, em, pm],
                      [ca.densify(2.0 * ca.mtimes(jr_m.T, jr_m)), 2.0 * ca.mtimes(jr_m.T, r_m),
                       c_m, ca.densify(jc_m.T)])
    val = ca.Function("rti_val", [u_all, eta0, par], [c, f])
    return lin, val


class _Buffered:
    """A CasADi function called through its zero-copy buffer (numpy arrays in and out; see
    :class:`companion.core.rmpc_nlp.NlpSolver`), dense outputs."""

    def __init__(self, fn: ca.Function) -> None:
        buf: Any = fn.buffer()[0]
        self._buf = buf
        self.args = [np.zeros(fn.nnz_in(i)) for i in range(fn.n_in())]
        self.res = [np.zeros(fn.nnz_out(i)) for i in range(fn.n_out())]
        for i, a in enumerate(self.args):
            buf.set_arg(i, a.data)
        for i, a in enumerate(self.res):
            buf.set_res(i, a.data)
        self.fn = fn

    def __call__(self, *args: np.ndarray) -> list[np.ndarray]:
        for dst, src in zip(self.args, args, strict=True):
            dst[:] = src
        self._buf._eval()
        if int(self._buf.ret()) != 0:
            raise RuntimeError(f"{self.fn.name()}: evaluation failed")
        return self.res


class RtiSolver:
    """The compiled RTI of one hard problem (module docstring). Deterministic: the same
    ``(eta0, parameters, guess, bounds)`` give the same plan bit for bit."""

    def __init__(self, rmpc: RmpcParams, camera: CameraParams, terminal: TerminalDesign,
                 clock: Callable[[], float] | None = None) -> None:
        self.cfg = rmpc
        self._clock = clock
        nlp, lay = build_nlp(rmpc, camera, terminal, soft=False)
        upper = np.array([row.upper for row in lay.rows], dtype=float)
        self.compiled: CompiledNlp | None = None
        if rmpc.jit:
            # the functions are derived from the hard NLP by this module's code: a library
            # built before is found by those two alone, without deriving them again
            code = hashlib.sha256(Path(__file__).read_bytes()).hexdigest()
            self.compiled = compiled_functions(
                lambda: list(_stage_functions(rmpc, camera, terminal)), rmpc.cache_dir, "rti",
                alias_key=problem_key(nlp, "rti", code))
            try:
                lin = ca.external("rti_lin", str(self.compiled.library))
                val = ca.external("rti_val", str(self.compiled.library))
            except RuntimeError as exc:
                raise RmpcBuildError(f"loading {self.compiled.library}: {exc}") from exc
        else:
            lin, val = _stage_functions(rmpc, camera, terminal)
        self._lin = _Buffered(lin)
        self._val = _Buffered(val)
        self.horizon = rmpc.horizon
        self.n_u = NU * rmpc.horizon
        self.n_state = NX * rmpc.horizon
        self.n_c = self.n_state + upper.size
        self.path_upper = upper
        self.path_root = np.sqrt(upper)
        self.u_max = np.tile(np.asarray(rmpc.u_max, dtype=float), rmpc.horizon)
        self.calls = 0  # QPs solved (tests)

    def rows(self, u: np.ndarray, eta0: np.ndarray, par: np.ndarray) -> tuple[np.ndarray,
                                                                               np.ndarray, float]:
        """The nonlinear rollout of ``u`` (N*4) from ``eta0``: states (N+1, 7), the NLP's path
        rows (squared form, hard layout order) and the NLP's cost."""
        c, f = self._val(u, eta0, par)
        eta = np.vstack([eta0, c[: self.n_state].reshape(self.horizon, NX)])
        return eta, c[self.n_state:].copy(), float(f[0])

    def violation(self, eta: np.ndarray, path: np.ndarray, u: np.ndarray,
                  state_lo: np.ndarray, state_hi: np.ndarray) -> float:
        """The largest excess of a hard row of the nonlinear problem over its bound (natural
        units: the path rows' square roots against their radii; the state box in state
        units; the input box). 0 or less: every row holds."""
        states = eta[1:].ravel()
        return max(
            float(np.max(np.sqrt(np.maximum(path, 0.0)) - self.path_root, initial=-np.inf)),
            float(np.max(states - state_hi)), float(np.max(state_lo - states)),
            float(np.max(np.abs(np.ravel(u)) - self.u_max)),
        )

    def step(self, eta0: np.ndarray, par: np.ndarray, u_guess: np.ndarray,
             state_lo: np.ndarray, state_hi: np.ndarray) -> RtiOutcome:
        """Up to ``rmpc.rti_max_qp`` QPs from the guess ``u_guess`` (N, 4); ``state_lo``,
        ``state_hi`` (N*7): the box of the shooting states of stages 1..N (error coordinates,
        as the NLP's variable bounds). See the module docstring."""
        u = np.clip(u_guess.ravel(), -self.u_max, self.u_max)
        iters, qps = 0, 0
        status, viol = "rti: no QP", math.inf
        eta, cost = np.tile(eta0, (self.horizon + 1, 1)), math.nan
        for _ in range(self.cfg.rti_max_qp):
            du, flag, it = self._qp(u, eta0, par, state_lo, state_hi)
            qps += 1
            iters += it
            if flag not in DAQP_OPTIMAL:
                return RtiOutcome(False, f"rti: QP {qps} failed (daqp exit flag {flag})",
                                  eta, u.reshape(self.horizon, NU), cost, iters, qps, math.inf)
            u = np.clip(u + du, -self.u_max, self.u_max)
            eta, path, cost = self.rows(u, eta0, par)
            viol = self.violation(eta, path, u, state_lo, state_hi)
            finite = bool(np.all(np.isfinite(eta)) and math.isfinite(cost))
            if finite and viol <= self.cfg.rti_tol:
                status = f"rti: {qps} QP, {iters} QP iterations"
                return RtiOutcome(True, status, eta, u.reshape(self.horizon, NU), cost,
                                  iters, qps, viol)
            status = (f"rti: rejected after {qps} QP (a hard row exceeded by {viol:.3g} > "
                      f"rmpc.rti_tol = {self.cfg.rti_tol:g})")
        return RtiOutcome(False, status, eta, u.reshape(self.horizon, NU), cost, iters, qps,
                          viol)

    def _qp(self, u: np.ndarray, eta0: np.ndarray, par: np.ndarray, state_lo: np.ndarray,
            state_hi: np.ndarray) -> tuple[np.ndarray, int, int]:
        """One Gauss-Newton QP in the input step ``du`` at ``u``: (du, exit flag, iterations)."""
        self.calls += 1
        h, grad, c, jct = self._lin(u, eta0, par)
        hess = h.reshape(self.n_u, self.n_u)  # symmetric: the storage order does not matter
        j_c = jct.reshape(self.n_c, self.n_u)  # J_c' column-major is J_c row-major
        upper = np.concatenate([self.u_max - u, state_hi - c[: self.n_state],
                                self.path_upper - c[self.n_state:]])
        lower = np.concatenate([-self.u_max - u, state_lo - c[: self.n_state],
                                np.full(self.path_upper.size, -DAQP_INF)])
        sense = np.zeros(upper.size, dtype=np.int32)
        du, _, flag, info = daqp.solve(hess, grad, j_c, upper, lower, sense,
                                       iter_limit=QP_ITER_LIMIT)
        return np.asarray(du, dtype=float), int(flag), int(info.get("iterations", 0))
