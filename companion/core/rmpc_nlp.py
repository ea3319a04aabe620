"""One compiled NLP of the RMPC (the hard problem or its soft copy) and its solve: the
nlpsol built from :func:`companion.core.rmpc_problem.build_nlp`, loaded from the compiled-code
cache (:mod:`companion.core.rmpc_cache`), with its bounds template, zero-copy evaluation and
the residual check of what the solver returns.

Split out of :mod:`companion.core.rmpc`; the solver child process
(:mod:`companion.control.solve_guard`) builds the same :class:`NlpSolver`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

import casadi as ca
import numpy as np

from companion.core.dynamics import S_REF
from companion.core.nlp_buffer import NlpBuffer
from companion.core.params import CameraParams, RmpcParams
from companion.core.rmpc_cache import CompiledNlp, RmpcBuildError, compiled_nlp
from companion.core.rmpc_problem import NX, Layout, build_nlp
from companion.core.rmpc_recovery import (
    hard_terminal_row,
    recovery_design,
    velocity_box_return,
)
from companion.core.rmpc_types import (
    Evaluation,
    SolveBackend,
    TargetMotion,
    state_lower,
)
from companion.core.terminal import TerminalDesign

log = logging.getLogger(__name__)

FATROP_OPTIONS: dict[str, Any] = {"print_level": 0, "mu_init": 1e-4, "tol": 1e-6}
"""mu_init 1e-4: the warm start is close to the solution, a large initial barrier undoes it."""
IPOPT_OPTIONS: dict[str, Any] = {"print_level": 0, "sb": "yes"}
RECOVERY_SOLVER = "ipopt"
"""The soft copy is solved with ipopt whatever ``rmpc.solver`` says: with active L1 penalties
the costates grow ~penalty-fold, the bilinear dynamics make fatrop's stage-wise Riccati
indefinite and fatrop crawls under heavy regularisation (measured: 'edge' start, >300
iterations, dual infeasibility stuck at ~1e-3) where ipopt converges in ~18 iterations."""
ACCEPT_TOL = 1e-6
"""Largest constraint residual (g rows and bounds, solver units) a 'success' may carry."""



class NlpSolver:
    """One compiled NLP (hard or soft) with its bounds template."""

    def __init__(
        self, rmpc: RmpcParams, camera: CameraParams, terminal: TerminalDesign, soft: bool,
        solver: str, clock: Callable[[], float] | None = None,
    ) -> None:
        self._clock = clock
        row_design = None
        goal: tuple[np.ndarray, float] | None = None
        if soft:
            # recovery_rows = "hard": the soft copy relaxes the hard problem's rows (only its
            # cost is its own design's), so its slacks measure the distance to the hard set
            row_design = (rmpc, terminal) if rmpc.recovery_rows == "hard" else None
            hard_rmpc, hard_terminal = rmpc, terminal
            rmpc, terminal = recovery_design(rmpc, camera, terminal)
            # "own+terminal": its own rows and the hard problem's terminal set as one more row
            goal = (hard_terminal_row(hard_rmpc, hard_terminal, rmpc)
                    if rmpc.recovery_rows == "own+terminal" else None)
        nlp, layout = build_nlp(rmpc, camera, terminal, soft, row_design, goal)
        self.layout: Layout = layout
        self.kind = "soft" if soft else "hard"
        self.solver_name = solver
        opts: dict[str, Any] = {"print_time": False, "record_time": True}
        max_iter = (rmpc.max_iter if soft or rmpc.hard_max_iter is None
                    else rmpc.hard_max_iter)
        if solver == "fatrop":
            opts |= {
                "structure_detection": "auto",
                "equality": list(layout.equality),
                "fatrop": FATROP_OPTIONS | {"max_iter": max_iter},
            }
        else:
            opts |= {"ipopt": IPOPT_OPTIONS | {"max_iter": max_iter}}
        name = f"rmpc_{self.kind}"
        self.options = opts  # a solver process loads the same library with these (solve_guard)
        self.compiled: CompiledNlp | None = None
        if rmpc.jit:
            # the symbolic solver is built only if the source must be generated (cache miss)
            # (the expressions too: a problem built before knows its layout and digest,
            # companion/core/rmpc_memo.py)
            self.compiled = compiled_nlp(
                lambda: ca.nlpsol(name, solver, nlp.expressions(), opts), rmpc.cache_dir,
                f"{solver}_{self.kind}", nlp=nlp, options=repr(sorted(opts.items())))
            try:
                self.solver = ca.nlpsol(name, solver, str(self.compiled.library), opts)
            except RuntimeError as exc:
                raise RmpcBuildError(f"loading {self.compiled.library}: {exc}") from exc
        else:
            self.solver = ca.nlpsol(name, solver, nlp.expressions(), opts)
        # bounds templates (the parts that never change)
        nw, ng = layout.n_w, layout.n_g
        self.lbx = np.full(nw, -np.inf)
        self.ubx = np.full(nw, np.inf)
        umax = np.asarray(rmpc.u_max, dtype=float)
        self.lbx[layout.u_index] = -umax
        self.ubx[layout.u_index] = umax
        self.lbx[layout.slack_index] = 0.0
        self.lbg = np.zeros(ng)
        self.ubg = np.zeros(ng)
        for row in layout.rows:
            self.lbg[row.g_index] = -np.inf
            self.ubg[row.g_index] = row.upper
        # zero-copy calls (companion/core/nlp_buffer.py); results bit-identical to
        # ``self.solver.call`` (tests/core/test_rmpc.py)
        self._buffer = NlpBuffer(self.solver, self.lbg, self.ubg)
        self.calls = 0  # evaluations of the solver (tests: nothing bad reaches it)
        self.eta_max = np.asarray(rmpc.eta_max, dtype=float)
        self.state_lo = state_lower(rmpc)
        self.u_max = np.asarray(rmpc.u_max, dtype=float)
        self.dt_s = rmpc.dt_s
        self.planned_yaw = rmpc.target_motion == "planned_yaw"
        self.eq_rows = layout.gap_index.ravel()
        self.ineq_rows = np.array([row.g_index for row in layout.rows], dtype=int)

    def bounds(self, eta0: np.ndarray, target: TargetMotion) -> tuple[np.ndarray, np.ndarray]:
        lay = self.layout
        lbx = self.lbx.copy()
        ubx = self.ubx.copy()
        big_n = lay.horizon
        v = np.vstack([target.v_a_m_s, target.v_a_m_s[-1:]])  # (N+1, 2), stage N holds N-1
        off = np.zeros((big_n + 1, NX))
        off[:, :4] = S_REF
        off[:, 4:6] = v
        lo = np.tile(self.state_lo, (big_n, 1))
        hi = np.tile(self.eta_max, (big_n, 1))
        if self.kind == "soft":
            drift = 0.0
            if self.planned_yaw:
                drift = float(np.max(np.hypot(*target.v_a_m_s.T))) * (
                    self.u_max[3] + float(np.max(np.abs(target.psidot_a_rad_s))))
            lo, hi = velocity_box_return(eta0 + off[0], lo, hi, self.u_max, self.dt_s, drift)
        lbx[lay.x_index[1:]] = lo - off[1:]
        ubx[lay.x_index[1:]] = hi - off[1:]
        lbx[lay.x_index[0]] = eta0
        ubx[lay.x_index[0]] = eta0
        return lbx, ubx

    def evaluate(self, w0: np.ndarray, par: np.ndarray, lbx: np.ndarray,
                 ubx: np.ndarray) -> Evaluation:
        """One evaluation of the compiled solver in this thread (CasADi's ``RuntimeError``
        passes through). What a solver process runs for :class:`SolveBackend`."""
        return self._buffer.evaluate(w0, par, lbx, ubx)

    def solve(
        self, w0: np.ndarray, par: np.ndarray, lbx: np.ndarray, ubx: np.ndarray,
        backend: SolveBackend | None = None,
    ) -> tuple[bool, str, dict[str, Any], np.ndarray, float, int, float]:
        """Solve (here, or on ``backend``); return (accepted, status, stats, w, cost,
        iterations, t_wall_s). :class:`SolveAborted` from the backend passes through."""
        self.calls += 1
        t0 = self._clock() if self._clock is not None else math.nan
        try:
            if backend is None:
                flag, st, w, cost, g = self.evaluate(w0, par, lbx, ubx)
            else:
                flag, st, w, cost, g = backend.evaluate(self.kind, w0, par, lbx, ubx)
        except RuntimeError as exc:  # CasADi raises on internal errors (e.g. evaluation)
            log.warning("RMPC %s solve raised: %s", self.kind, exc)
            return False, f"exception: {exc}", {}, w0, float("nan"), 0, float("nan")
        t = self._clock() - t0 if self._clock is not None else math.nan
        if flag != 0:  # what ``Function.call`` raises as "Evaluation failed"
            log.warning("RMPC %s solve: evaluation failed (flag %d)", self.kind, flag)
            return False, f"exception: evaluation failed (flag {flag})", {}, w0, float("nan"), \
                0, float("nan")
        status = _status_string(st)
        it = int(st.get("iter_count", 0))
        ok = bool(st.get("success", False))
        if ok and not (np.all(np.isfinite(w)) and np.all(np.isfinite(g)) and np.isfinite(cost)):
            ok, status = False, f"{status} (non-finite iterate)"
        if ok:
            resid = max(
                float(np.max(np.abs(g[self.eq_rows]), initial=0.0)),
                float(np.max(g[self.ineq_rows] - self.ubg[self.ineq_rows], initial=0.0)),
                float(np.max(lbx - w, initial=0.0)),
                float(np.max(w - ubx, initial=0.0)),
            )
            if resid > ACCEPT_TOL:
                ok, status = False, f"{status} (residual {resid:.3g} > {ACCEPT_TOL:g})"
        return ok, status, st, w, cost, it, t


def _status_string(st: dict[str, Any]) -> str:
    rs = st.get("return_status", "unknown")
    if isinstance(rs, str):
        return rs
    # fatrop reports an integer flag; CasADi's unified status names it
    return f"{st.get('unified_return_status', 'SOLVER_RET_UNKNOWN')} (flag {rs})"

