"""Real-time iteration of the RMPC's soft (recovery) copy (``rmpc.recovery_solver = "rti"``).

When the hard problem fails, :class:`companion.core.rmpc.Rmpc` solves the soft copy (the same
rows with an L1-penalised slack each, :func:`companion.core.rmpc_problem.build_nlp` with
``soft=True``). With a warm start, this module solves it first the way
:mod:`companion.core.rmpc_rti` solves the hard problem: Gauss-Newton QPs (at most
``rmpc.rti_max_qp``) linearised at the guess (the previous plan shifted by one stage), solved
by DAQP, each step checked on the nonlinear rollout; a step that finds no plan passing the
check goes to the soft NLP (counted and logged by :func:`recovery_step`).

- **The linearisation is the hard RTI's own**, compiled for the soft design
  (:func:`companion.core.rmpc_recovery.recovery_design`: its ``q_diag``, ``eps``, ``P``): an
  :class:`~companion.core.rmpc_rti.RtiSolver` of that design gives, in single shooting over the
  inputs ``U``, the Gauss-Newton ``H``, ``g`` of the quadratic cost, the states of stages 1..N,
  the path rows (the soft NLP's rows, in its order, before the slacks) and their Jacobian. The
  soft copy's input-rate term (``rmpc.recovery_input_rate_weight``) is quadratic in ``U``:
  added exactly (:func:`rate_matrices`). Hence ``rmpc.recovery_rows = "own"`` only.
- **The QP** in ``z = (dU, s)``, ``s`` the slacks of the rows the linearisation point exceeds
  (the others stay hard in the QP)::

      min 0.5 dU' (H + mu_p I) dU + g' dU + w' s + 0.5 mu_s |s|^2
      s.t. c_p + J_p dU - s <= upper,  s >= 0,  |u + dU| <= u_max,  lo <= c_x + J_x dU <= hi

  ``w`` the soft NLP's slack weights (``recovery_penalty``, ``recovery_tube_penalty``); the
  state box ``lo``, ``hi`` is the soft NLP's own (its velocity box moved out by
  :func:`~companion.core.rmpc_recovery.velocity_box_return`). ``mu_s = SLACK_CURVATURE w``:
  DAQP needs a positive definite Hessian (a slack's marginal price ``w + mu_s s`` instead of
  ``w``). ``mu_p``: a Levenberg-Marquardt weight (:data:`PROX_WEIGHT`, adapted between QPs).
- **The line search and the check** (:meth:`SoftRti.refusal`): ``u + a dU``, ``a = 1, 1/2,
  ...``, rolled out through the nonlinear model (the compiled ``rti_val``); the dynamics are
  exact by construction, the input box by clipping; the state box must hold within
  ``rmpc.rti_tol`` and every row and the cost be finite. The slacks are the rows' exact
  excesses on the rollout (``max(row - upper, 0)``: every soft row holds exactly, the tube's
  included), and the plan's soft cost (the NLP's objective there) must be no higher than the
  plan it started from (the merit an L1-penalty SQP accepts a step on).

docs/reference/solver.md ("The soft copy's RTI") has the design, what the check covers and
the figures.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import daqp
import numpy as np

from companion.core.errors import ParamError
from companion.core.params import CameraParams, RmpcParams
from companion.core.rmpc_problem import NP_STAGE, NU, NX, Layout
from companion.core.rmpc_recovery import recovery_design
from companion.core.rmpc_rti import (
    DAQP_INF,
    DAQP_OPTIMAL,
    QP_ITER_LIMIT,
    RtiSolver,
)
from companion.core.terminal import TerminalDesign

log = logging.getLogger(__name__)

LINE_SEARCH_STEPS = 8
"""Tries of the step along a QP's solution (1, 1/2, ..., 1/128) before giving up."""
PROX_WEIGHT = 1.0e3
"""The proximal (Levenberg-Marquardt) weight on the first QP's input step (cost per
(m/s^2)^2; later QPs: :data:`PROX_FACTOR`). Measured on the edge loop's recovery steps (4
fixed-weight QPs) against 0, 10, 100: the commands nearest the soft NLP's and the fewest
DAQP iterations."""
PROX_FACTOR = 10.0
"""How the proximal weight moves between a step's QPs (Levenberg-Marquardt)."""
PROX_MIN = 1.0
"""Its floor."""
MERIT_TOL = 1e-4
"""A QP after the first only while the one before it brought the soft cost down by more than
this (relative)."""

SLACK_CURVATURE = 1e-6
"""``mu / w``: the slacks' quadratic term relative to their L1 weight (DAQP needs a positive
definite Hessian; module docstring)."""


_Found = tuple[np.ndarray, np.ndarray, np.ndarray, float, float]
"""A line search's point: (u, eta, slack, soft cost, step length)."""


@dataclass(frozen=True)
class SoftRtiOutcome:
    """One soft RTI step. ``ok``: the plan passed the check; ``status``: ``rti-soft: ...``;
    ``eta`` (N+1, 7), ``u`` (N, 4): the plan; ``slack``: its slacks (the rows' exact excesses,
    soft layout order); ``cost``: its soft cost; ``qp_iterations``, ``qps``: DAQP's."""

    ok: bool
    status: str
    eta: np.ndarray
    u: np.ndarray
    slack: np.ndarray
    cost: float
    qp_iterations: int
    qps: int


def rate_matrices(rmpc: RmpcParams) -> tuple[np.ndarray, np.ndarray]:
    """The soft copy's input-rate term as ``w_du |D U - E u_prev|^2`` (``U``: N*4 stacked
    inputs): ``D`` ((N*4) x (N*4)) and ``E`` ((N*4) x 4), rows scaled by ``1/u_max``
    (:func:`companion.core.rmpc_problem._input_rate`: u(0) against u_prev, then stage to
    stage)."""
    big_n = rmpc.horizon
    inv = 1.0 / np.asarray(rmpc.u_max, dtype=float)
    d = np.zeros((NU * big_n, NU * big_n))
    e = np.zeros((NU * big_n, NU))
    d[:NU, :NU] = np.diag(inv)
    e[:NU, :NU] = np.diag(inv)
    for n in range(1, big_n):
        d[NU * n: NU * (n + 1), NU * n: NU * (n + 1)] = np.diag(inv)
        d[NU * n: NU * (n + 1), NU * (n - 1): NU * n] = -np.diag(inv)
    return d, e


class SoftRti:
    """The compiled RTI of the soft copy built from ``rmpc`` (the soft design: what
    :func:`companion.core.rmpc_recovery.recovery_design` returns) and ``layout`` (the soft
    NLP's: its rows and their order). Only ``rmpc.recovery_rows = "own"`` (the shipped
    configs'): the other values build rows from another design or add one, which the shared
    linearisation does not (a clear error). Deterministic; not thread-safe."""

    def __init__(self, rmpc: RmpcParams, camera: CameraParams, terminal: TerminalDesign,
                 layout: Layout, max_qp: int, tol: float) -> None:
        if rmpc.recovery_rows != "own":
            raise ParamError(f"rmpc.recovery_solver = 'rti' needs rmpc.recovery_rows = 'own' "
                             f"(got {rmpc.recovery_rows!r})")
        self.rti = RtiSolver(rmpc, camera, terminal)
        if len(layout.rows) != self.rti.path_upper.size:  # pragma: no cover (a layout bug)
            raise ValueError("SoftRti: the soft layout's rows are not the linearisation's")
        self.max_qp, self.tol = max_qp, tol
        self.horizon = big_n = rmpc.horizon
        n_u, n_p, n_s = NU * big_n, len(layout.rows), NX * big_n
        self.n_u, self.n_p, self.n_s = n_u, n_p, n_s
        self.weight = np.array([rmpc.recovery_penalty if row.group == "visibility"
                                else rmpc.recovery_tube_penalty for row in layout.rows])
        self.upper = self.rti.path_upper
        self.u_max = np.tile(np.asarray(rmpc.u_max, dtype=float), big_n)
        self._rate_d, self._rate_e = rate_matrices(rmpc)
        self._rate_h = self._rate_d.T @ self._rate_d
        # the hard RTI's compiled linearisation, for this design (its check function is
        # read through RtiSolver.rows)
        self._lin = self.rti._lin
        self.calls = 0  # QPs solved (tests)
        self.accepted = 0  # steps whose plan flew (recovery_step)
        self.rejected = 0  # steps handed to the soft NLP
        self.last_time_s = math.nan  # the last recovery_step's time (its clock)

    # ------------------------------------------------------------------------------------
    def evaluate(self, u: np.ndarray, eta0: np.ndarray, par: np.ndarray, w_du: float,
                 u_prev: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """The nonlinear rollout of ``u`` (N*4): states (N+1, 7), the least slacks (the path
        rows' excesses) and the soft NLP's objective there (``par``: the hard parameters)."""
        eta, path, f = self.rti.rows(u, eta0, par)
        slack = np.maximum(path - self.upper, 0.0)
        rate = self._rate_d @ u - self._rate_e @ u_prev
        return eta, slack, f + float(self.weight @ slack) + w_du * float(rate @ rate)

    def step(self, eta0: np.ndarray, spar: np.ndarray, u_guess: np.ndarray,
             state_lo: np.ndarray, state_hi: np.ndarray) -> SoftRtiOutcome:
        """Up to ``max_qp`` QPs from ``u_guess`` (N, 4), each step ``dU`` shortened until the
        soft cost decreases (:meth:`_line_search`); ``spar``: the soft NLP's parameters (the
        hard ones, ``u_prev``, ``w_du``); ``state_lo``, ``state_hi`` (N*7): the soft NLP's
        state box of stages 1..N (error coordinates). Module docstring."""
        n_par = NP_STAGE * self.horizon + 1
        par, u_prev, w_du = spar[:n_par], spar[n_par:n_par + NU], float(spar[n_par + NU])
        u = np.clip(np.ravel(u_guess), -self.u_max, self.u_max)
        plan = self.evaluate(u, eta0, par, w_du, u_prev)
        iters, qps, moved, status = 0, 0, False, ""
        prox = PROX_WEIGHT
        for _ in range(self.max_qp):
            du, flag, it = self._qp(u, eta0, par, (w_du, u_prev, prox), state_lo, state_hi)
            qps += 1
            iters += it
            if flag not in DAQP_OPTIMAL:
                status = f"QP {qps} failed (daqp exit flag {flag})"
                break
            found, why = self._line_search(u, du, plan[2], (eta0, par, w_du, u_prev),
                                           (state_lo, state_hi))
            if found is None:  # (a shorter step next: a stiffer proximal term)
                status, prox = f"QP {qps}: {why}", prox * PROX_FACTOR
                continue
            previous = plan[2]
            u, plan, moved = found[0], found[1:4], True
            # Levenberg-Marquardt: a full step accepted, the model trusted more; cut, less
            prox = max(prox / PROX_FACTOR, PROX_MIN) if found[4] == 1.0 else prox * PROX_FACTOR
            if plan[2] >= previous - MERIT_TOL * abs(previous):
                break  # (no more progress to speak of)
        eta, slack, merit = plan
        if moved:
            return SoftRtiOutcome(True, f"rti-soft: {qps} QP, {iters} QP iterations", eta,
                                  u.reshape(self.horizon, NU), slack, merit, iters, qps)
        return SoftRtiOutcome(False, f"rti-soft: rejected ({status})", eta,
                              u.reshape(self.horizon, NU), slack, merit, iters, qps)

    def _line_search(self, u: np.ndarray, du: np.ndarray, merit: float,
                     problem: tuple[np.ndarray, np.ndarray, float, np.ndarray],
                     box: tuple[np.ndarray, np.ndarray],
                     ) -> tuple[_Found | None, str]:
        """``u + a du`` for ``a = 1, 1/2, ...`` (:data:`LINE_SEARCH_STEPS` tries): the first
        whose rollout keeps the state box (within ``tol``), is finite and has a soft cost no
        higher than ``merit``: (u, eta, slack, cost, a), or None and why not. Far from the soft
        optimum the full Gauss-Newton step overshoots: the L1 rows' curvature (their
        multipliers are the penalty weights, 1e3-1e4) is not in ``H``."""
        why = "no step"
        alpha = 1.0
        for _ in range(LINE_SEARCH_STEPS):
            cand = np.clip(u + alpha * du, -self.u_max, self.u_max)
            eta, slack, cost = self.evaluate(cand, *problem)
            why = self.refusal(eta, cost, merit, box)
            if not why:
                return (cand, eta, slack, cost, alpha), ""
            alpha *= 0.5
        return None, f"{why} after {LINE_SEARCH_STEPS} halvings"

    def refusal(self, eta: np.ndarray, cost: float, bound: float,
                box: tuple[np.ndarray, np.ndarray]) -> str:
        """Why a rolled-out plan (``eta`` (N+1, 7) from :meth:`evaluate`, its soft ``cost``)
        may not fly, or ``""``: a row or the cost not finite, the state box ``box`` (lo, hi;
        N*7) exceeded by more than ``tol``, or the cost above ``bound`` (the guess's). The
        dynamics hold by construction (the rollout), the input box by clipping and the soft
        rows by the slacks :meth:`evaluate` computes (each the row's exact excess)."""
        lo, hi = box
        states = eta[1:].ravel()
        if not (math.isfinite(cost) and np.isfinite(states).all()):
            return "a row or the cost not finite"
        excess = float(max(np.max(states - hi), np.max(lo - states)))
        if not excess <= self.tol:
            return f"the state box exceeded by {excess:.3g} > rmpc.rti_tol = {self.tol:g}"
        if not cost <= bound:
            return f"soft cost {cost:.6g} > {bound:.6g}"
        return ""

    def _qp(self, u: np.ndarray, eta0: np.ndarray, par: np.ndarray,
            terms: tuple[float, np.ndarray, float], state_lo: np.ndarray,
            state_hi: np.ndarray) -> tuple[np.ndarray, int, int]:
        """One Gauss-Newton QP at ``u`` (module docstring): (dU, exit flag, iterations). Only
        the rows exceeded at ``u`` get a slack (the others stay hard in the QP: the step may
        not newly break them; each slack costs DAQP at least one active-set iteration, ~78
        of them made it ~400 iterations a QP); the state box's rows are always in (they
        bind in most recovery steps: measured)."""
        self.calls += 1
        w_du, u_prev, prox = terms
        n_u, n_s = self.n_u, self.n_s
        hess, grad, c, j_c = self._lin(u, eta0, par)
        c_x, c_p = c[:n_s], c[n_s:]
        j = j_c.reshape(n_s + self.n_p, n_u)
        out = np.flatnonzero(c_p > self.upper)  # the rows that get a slack
        n_z = n_u + out.size
        h = np.zeros((n_z, n_z))
        h[:n_u, :n_u] = hess.reshape(n_u, n_u)
        # a proximal term (vanishes at a fixed point, du = 0): without it the QP, whose only
        # curvature is the small tracking cost's while the slacks' weights are 1e3-1e4, is
        # nearly an LP whose steps the line search cut to 1/64 (measured; module docstring)
        h[:n_u, :n_u] += prox * np.eye(n_u)
        f = np.concatenate([grad, self.weight[out]])
        if w_du:
            rate = self._rate_d @ u - self._rate_e @ u_prev
            h[:n_u, :n_u] += 2.0 * w_du * self._rate_h
            f[:n_u] += 2.0 * w_du * (self._rate_d.T @ rate)
        rows = np.zeros((self.n_p + n_s, n_z))
        rows[:self.n_p, :n_u] = j[n_s:]
        rows[out, n_u + np.arange(out.size)] = -1.0
        rows[self.n_p:, :n_u] = j[:n_s]
        up = np.concatenate([self.u_max - u, np.full(out.size, DAQP_INF), self.upper - c_p,
                             state_hi - c_x])
        lo = np.concatenate([-self.u_max - u, np.zeros(out.size), np.full(self.n_p, -DAQP_INF),
                             state_lo - c_x])
        z, _, flag, info = daqp.solve(h, f, rows, up, lo, np.zeros(up.size, np.int32),
                                      iter_limit=QP_ITER_LIMIT)
        return np.asarray(z, dtype=float)[:n_u], int(flag), int(info.get("iterations", 0))


def build(rmpc: RmpcParams, camera: CameraParams, terminal: TerminalDesign,
          layout: Layout | None) -> SoftRti | None:
    """The soft copy's RTI of a controller configured with ``rmpc`` (the hard problem's
    parameters) if ``rmpc.recovery_solver = "rti"`` and it has a soft copy (``layout``: the
    soft NLP's), else None."""
    if rmpc.recovery_solver != "rti" or layout is None:
        return None
    soft_rmpc, soft_terminal = recovery_design(rmpc, camera, terminal)
    return SoftRti(soft_rmpc, camera, soft_terminal, layout, rmpc.rti_max_qp, rmpc.rti_tol)


def recovery_step(solver: SoftRti, e0: np.ndarray, spar: np.ndarray, u_g: np.ndarray,
                  bounds: tuple[np.ndarray, np.ndarray], layout: Layout,
                  clock: Callable[[], float] | None) -> SoftRtiOutcome:
    """One soft RTI step for :meth:`companion.core.rmpc.Rmpc._recover`: the state box from the
    soft NLP's own variable bounds ``bounds`` (lbx, ubx), timed by ``clock``, counted
    (``solver.accepted``, ``solver.rejected``) and a rejection logged."""
    lbx, ubx = bounds
    t0 = clock() if clock is not None else math.nan
    out = solver.step(e0, spar, u_g, lbx[layout.x_index[1:]].ravel(),
                      ubx[layout.x_index[1:]].ravel())
    solver.last_time_s = clock() - t0 if clock is not None else math.nan
    if out.ok:
        solver.accepted += 1
    else:
        solver.rejected += 1
        log.info("RMPC %s: solving the soft NLP", out.status)
    return out


INFEASIBLE_QP = "(daqp exit flag -1)"
"""How the hard RTI's status names a QP DAQP found infeasible."""


def skip_hard_nlp(rmpc: RmpcParams, note: str) -> bool:
    """Whether the full hard NLP is not tried after the hard RTI's attempt ``note`` (its
    status): with ``rmpc.rti_infeasible_qp = "soft"`` a step whose hard QP was infeasible goes
    to the soft copy directly (a linearisation's infeasibility is no proof: an option, off by
    default; docs/reference/solver.md)."""
    return rmpc.rti_infeasible_qp == "soft" and INFEASIBLE_QP in note
