"""Real-time iteration (RTI) of the RMPC's hard problem (``rmpc.solver = "rti"``).

One step solves one (at most ``rmpc.rti_max_qp``) dense QP built from the same NLP as the
full solve (:func:`companion.core.rmpc_problem.build_nlp`: the same cost, tube, visibility and
terminal rows, the same state box), linearised at the previous plan shifted by one stage:

- single shooting: the decision is the N x 4 inputs ``U``; the states are the nonlinear
  rollout of the NLP's own dynamics from ``eta0`` (so the plan's dynamics are exact);
- the Gauss-Newton Hessian of the quadratic cost, the NLP's rows on the rollout (built by the
  code that builds the NLP's) and their Jacobian come from one compiled function, condensed
  from stage Jacobians (:mod:`companion.core.rmpc_rti_gen`; ``rmpc.rti_linearisation =
  "loops"``: the condensing as C loops, :mod:`companion.core.rmpc_rti_loops`, the same
  numbers bit for bit; ``"recursion"``: those loops with H and g by a backward recursion,
  :mod:`companion.core.rmpc_rti_recursion`, the same numbers to round-off; cached like the
  NLPs);
  a second one gives the rows by the NLP's own ``g``, the cost and their largest excess (the
  check);
- DAQP (a dual active-set solver for small dense QPs) solves the QP in-process with a bounded
  number of iterations. The state box's rows (7 N, far from binding in flight) are left out
  of the first attempt and the QP is solved again with them only when its solution breaks one
  of them (linearised): the QP is strictly convex, so a solution of the smaller QP that keeps
  the left-out rows is the solution of the whole one (:meth:`RtiSolver._qp`).

With a compiled ``"loops"`` or ``"recursion"`` library, a QP's linearisation, bounds, DAQP,
state-box test, update and check are one foreign call (:mod:`companion.core.rmpc_rti_cstep`,
the same numbers bit for bit).

Every plan is then rolled out through the nonlinear model and every hard row evaluated
(:meth:`RtiSolver.step`): a row exceeded by more than ``rmpc.rti_tol`` (natural units),
or a QP that failed, re-linearises at the QP's solution (up to ``rmpc.rti_max_qp`` QPs, and
only while the excess keeps shrinking) and then gives up: :class:`companion.core.rmpc.Rmpc`
solves the full NLP for that step. docs/reference/solver.md has the design, the guarantees and
the figures.
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

from companion.core import (
    rmpc_daqp,
    rmpc_rti_cstep,
    rmpc_rti_gen,
    rmpc_rti_loops,
    rmpc_rti_recursion,
)
from companion.core.frozen import make
from companion.core.params import CameraParams, RmpcParams
from companion.core.rmpc_cache import (
    CompiledNlp,
    RmpcBuildError,
    compiled_functions,
    problem_key,
)
from companion.core.rmpc_problem import NU, NX, build_nlp
from companion.core.terminal import TerminalDesign

log = logging.getLogger(__name__)

QP_ITER_LIMIT = 500
"""DAQP's active-set iterations per QP (measured: 2-40 on the paper, edge and figure-eight
flights); a QP that needs more is a failure and the step goes to the full NLP."""
DAQP_INF = 1e30
"""DAQP's 'no bound'."""
DAQP_OPTIMAL = (1, 2)
"""DAQP exit flags of a solved QP (1 optimal, 2 optimal with soft constraints)."""
DAQP_INFEASIBLE = -1
"""DAQP's exit flag of a QP whose rows cannot all hold."""


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


class _Buffered:
    """A CasADi function called through its zero-copy buffer (numpy arrays in and out; see
    :class:`companion.core.rmpc_nlp.NlpSolver`), dense outputs."""

    def __init__(self, fn: ca.Function) -> None:
        pair: Any = fn.buffer()
        buf, caller = pair
        self._buf = buf
        # CasADi's own fast caller of the buffer (buf._eval through a C partial: ~1 us less
        # a call than the SWIG method; the same evaluation)
        self._eval: Callable[[], None] = caller
        self.args = [np.zeros(fn.nnz_in(i)) for i in range(fn.n_in())]
        self.res = [np.zeros(fn.nnz_out(i)) for i in range(fn.n_out())]
        for i, a in enumerate(self.args):
            buf.set_arg(i, a.data)
        for i, a in enumerate(self.res):
            buf.set_res(i, a.data)
        self.fn = fn

    def share(self, other: _Buffered, indices: tuple[int, ...]) -> None:
        """Read the arguments ``indices`` from ``other``'s buffers (the same arrays: what one
        function's caller writes there, the other reads without a copy)."""
        for i in indices:
            if self.args[i].size != other.args[i].size:
                raise ValueError(f"{self.fn.name()}: argument {i} is not {other.fn.name()}'s")
            self.args[i] = other.args[i]
            self._buf.set_arg(i, self.args[i].data)

    def __call__(self, *args: np.ndarray) -> list[np.ndarray]:
        """Copy ``args`` (all of them, or none: the buffers as they are) in, evaluate."""
        if args:
            for dst, src in zip(self.args, args, strict=True):
                dst[:] = src
        self._eval()
        if self._buf.ret() != 0:
            raise RuntimeError(f"{self.fn.name()}: evaluation failed")
        return self.res


def _lin_library(rmpc: RmpcParams, camera: CameraParams, terminal: TerminalDesign,
                 key: str) -> CompiledNlp:
    """The compiled ``rti_lin`` of ``rmpc.rti_linearisation`` (``"loops"``: CasADi's stage
    functions and the C condensing around them, :mod:`companion.core.rmpc_rti_loops`, with
    its own gcc flags)."""
    if rmpc.rti_linearisation in ("loops", "recursion"):
        driver = rmpc_rti_recursion.DRIVER if rmpc.rti_linearisation == "recursion" \
            else rmpc_rti_loops.DRIVER
        return compiled_functions(
            lambda: rmpc_rti_loops.lin_source(rmpc, camera, terminal, driver),
            rmpc.cache_dir, "rti_lin", alias_key=key, flags=rmpc_rti_loops.FLAGS)
    return compiled_functions(lambda: [rmpc_rti_gen.lin_function(rmpc, camera, terminal)],
                              rmpc.cache_dir, "rti_lin", alias_key=key)


class RtiSolver:
    """The compiled RTI of one hard problem (module docstring). Deterministic: the same
    ``(eta0, parameters, guess, bounds)`` give the same plan bit for bit. Not thread-safe
    (it keeps its QP's arrays between calls)."""

    def __init__(self, rmpc: RmpcParams, camera: CameraParams, terminal: TerminalDesign,
                 clock: Callable[[], float] | None = None) -> None:
        self.cfg = rmpc
        self._clock = clock
        nlp, lay = build_nlp(rmpc, camera, terminal, soft=False)
        upper = np.array([row.upper for row in lay.rows], dtype=float)
        self._rows = lay.rows
        self.compiled: tuple[CompiledNlp, CompiledNlp] | None = None
        if rmpc.jit:
            # the functions are derived from the hard NLP by rmpc_rti_gen's code (and
            # rmpc_rti_loops'): a library built before is found by those alone, without
            # deriving them again
            code = hashlib.sha256(Path(rmpc_rti_gen.__file__).read_bytes()).hexdigest()
            if rmpc.rti_linearisation != "graph":  # (the same NLP: the form is in the key)
                code += f":{rmpc.rti_linearisation}"
            if rmpc.rti_linearisation in ("loops", "recursion"):
                code += hashlib.sha256(Path(rmpc_rti_loops.__file__).read_bytes()).hexdigest()
            if rmpc.rti_linearisation == "recursion":
                code += hashlib.sha256(
                    Path(rmpc_rti_recursion.__file__).read_bytes()).hexdigest()
            key = problem_key(nlp, "rti", code)
            self.compiled = (_lin_library(rmpc, camera, terminal, key),
                             compiled_functions(
                                 lambda: [rmpc_rti_gen.val_function(rmpc, camera, terminal)],
                                 rmpc.cache_dir, "rti_val", alias_key=key))
            try:
                lin = ca.external("rti_lin", str(self.compiled[0].library))
                val = ca.external("rti_val", str(self.compiled[1].library))
            except RuntimeError as exc:
                raise RmpcBuildError(f"loading the RTI's functions: {exc}") from exc
        else:  # ("loops", "recursion" are C: without jit, the graph's function)
            lin = rmpc_rti_gen.lin_function(rmpc, camera, terminal)
            val = rmpc_rti_gen.val_function(rmpc, camera, terminal)
        self._lin = _Buffered(lin)
        self._val = _Buffered(val)
        # (U, eta0, p): one set of arrays for both functions, written once per step
        self._val.share(self._lin, (0, 1, 2))
        self._u, self._eta0, self._par = self._lin.args[:3]
        self._lo_x, self._hi_x = self._val.args[3:5]
        self.horizon = rmpc.horizon
        self.n_u = n_u = NU * rmpc.horizon
        self.n_state = n_s = NX * rmpc.horizon
        self.n_c = n_s + upper.size
        self.path_upper = upper
        self.path_root = np.sqrt(upper)
        self.u_max = np.tile(np.asarray(rmpc.u_max, dtype=float), rmpc.horizon)
        self._u_min = -self.u_max  # (the same negation the step did each time, made once)
        # views of the compiled functions' outputs (filled by each call, never copied)
        self._hess = self._lin.res[0].reshape(n_u, n_u)
        self._grad = self._lin.res[1]
        self._c_x, self._c_p = self._lin.res[2][:n_s], self._lin.res[2][n_s:]
        self._u_plan = self._u.reshape(rmpc.horizon, NU)  # (views made once, not per step)
        self._j_c = self._lin.res[3].reshape(self.n_c, n_u)  # J_c' column-major: J_c rows
        self._j_state, self._j_path = self._j_c[:n_s], self._j_c[n_s:]
        self._rows_c, self._f, self._excess, self._total = self._val.res
        self._rows_x_flat = self._rows_c[:n_s]  # (the states of stages 1..N, a view)
        # the QP's bounds, filled in place: [input box (DAQP's simple bounds), path rows]
        n_p = upper.size
        self._up, self._lo = np.zeros(n_u + n_p), np.full(n_u + n_p, -DAQP_INF)
        self._sense = np.zeros(n_u + n_p, dtype=np.int32)
        self._up_u, self._lo_u, self._up_p = self._up[:n_u], self._lo[:n_u], self._up[n_u:]
        # the QP without the state box through DAQP's C entry on these arrays (None: the
        # installed DAQP is not the one its structs are laid out for; daqp.solve then)
        found = rmpc_daqp.direct(QP_ITER_LIMIT)
        self._direct = None if found is None else rmpc_daqp.DirectQp(
            *found, self._hess, self._grad, self._j_path, self._up, self._lo, self._sense)
        self._cstep = self._c_step(val)
        self._no_box = np.zeros(n_s)
        self._x_lin = np.zeros(n_s)
        self._in_hi, self._in_lo = np.zeros(n_s, dtype=bool), np.zeros(n_s, dtype=bool)
        self.calls = 0  # QPs solved (tests)
        self.full_qps = 0  # QPs solved again with the state box's rows (tests, bench)

    def _c_step(self, val: ca.Function) -> rmpc_rti_cstep.CStep | None:
        """One QP as one foreign call (:mod:`companion.core.rmpc_rti_cstep`: the same
        arithmetic, without Python between the parts); None: the graph form, no compiler,
        or no DAQP C entry (the step's Python then)."""
        if self.compiled is None or self._direct is None \
                or self.cfg.rti_linearisation not in ("loops", "recursion"):
            return None
        try:
            return rmpc_rti_cstep.CStep(
                self.compiled[0].library, self.compiled[1].library, self._direct,
                self._lin.args, self._lin.res, val, self._val.args, self._val.res,
                (self.u_max, self._u_min, self.path_upper, self._up, self._lo))
        except (OSError, AttributeError) as exc:  # (no rti_qp: the Python step's numbers
            log.warning("the RTI's C step not used (%s): the Python step", exc)  # are equal)
            return None

    def rows(self, u: np.ndarray, eta0: np.ndarray, par: np.ndarray) -> tuple[np.ndarray,
                                                                               np.ndarray, float]:
        """The nonlinear rollout of ``u`` (N*4) from ``eta0``: states (N+1, 7), the NLP's path
        rows (squared form, hard layout order) and the NLP's cost."""
        n_s = self.n_state
        self._val(u, eta0, par, self._no_box, self._no_box)  # (its excess is not read here)
        return self._states(), self._rows_c[n_s:].copy(), float(self._f[0])

    def _states(self) -> np.ndarray:
        """The last evaluated rollout (N+1, 7): ``eta0`` as the functions read it (written to
        their argument array by each caller) and the states of stages 1..N."""
        # (one allocation and copy: ~0.6 us less than filling an empty array in two parts)
        return np.concatenate((self._eta0, self._rows_x_flat)).reshape(self.horizon + 1, NX)

    def violation(self, eta: np.ndarray, path: np.ndarray, u: np.ndarray,
                  state_lo: np.ndarray, state_hi: np.ndarray) -> float:
        """The largest excess of a hard row of the nonlinear problem over its bound (natural
        units: the path rows' square roots against their radii; the state box in state
        units; the input box), in numpy: 0 or less, every row holds; NaN if a row is NaN.
        :meth:`step` reads the same number from the compiled check (``rti_val``)."""
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
        as the NLP's variable bounds). A QP after the second is solved only if the previous
        one brought the excess down (a full Gauss-Newton step far from the solution can
        oscillate; the step then goes to the full NLP, whose result does not depend on how
        many QPs were tried). See the module docstring."""
        u_max, u_min = self.u_max, self._u_min
        # the plan u, eta0 and par in the compiled functions' own argument arrays (shared by
        # both: no copy per call); the outcome gets a copy of u
        u = self._u
        cstep = self._cstep
        if cstep is None:
            np.minimum(np.maximum(u_guess.ravel(), u_min, out=u), u_max, out=u)
        else:
            u[:] = u_guess.ravel()  # (rti_qp clips it on the first QP)
        self._eta0[:] = eta0
        self._par[:] = par
        self._lo_x[:] = state_lo  # (rti_val's box; rows() writes no box there: again below)
        self._hi_x[:] = state_hi
        iters, qps = 0, 0
        status, viol = "rti: no QP", math.inf
        for _ in range(self.cfg.rti_max_qp):
            if cstep is not None:  # (u, eta0, par in the functions' arrays: written above)
                self.calls += 1
                code = cstep.run(qps == 0)
                flag, it = cstep.result.exitflag, cstep.result.iter
                if code:  # (DAQP failed, or the state box is for numpy to decide)
                    du, flag, it = self._c_rest(code, flag, it, state_lo, state_hi)
            else:
                code = 1
                du, flag, it = self._qp(u, self._eta0, self._par, state_lo, state_hi)
            qps += 1
            iters += it
            if flag not in DAQP_OPTIMAL:
                eta = np.tile(eta0, (self.horizon + 1, 1))
                return RtiOutcome(False, f"rti: QP {qps} failed (daqp exit flag {flag})",
                                  eta, self._u_plan.copy(), math.nan, iters,
                                  qps, math.inf)
            if code:  # (else rti_qp added du, clipped and checked)
                u += du
                np.minimum(np.maximum(u, u_min, out=u), u_max, out=u)
                self._val()
            previous, viol = viol, float(self._excess[0])
            if math.isfinite(float(self._total[0])) and viol <= self.cfg.rti_tol:
                return make(RtiOutcome, ok=True,
                            status=f"rti: {qps} QP, {iters} QP iterations",
                            eta=self._states(), u=self._u_plan.copy(), cost=float(self._f[0]),
                            qp_iterations=iters, qps=qps, violation=viol)
            worst = self._worst_row(u.copy(), eta0, par, state_lo, state_hi)
            self._lo_x[:] = state_lo
            self._hi_x[:] = state_hi
            status = (f"rti: rejected after {qps} QP ({worst} exceeded by {viol:.3g} > "
                      f"rmpc.rti_tol = {self.cfg.rti_tol:g})")
            if qps >= 2 and not viol < previous:
                break
        return RtiOutcome(False, status, self._states(),
                          self._u_plan.copy(), float(self._f[0]), iters, qps,
                          viol)

    def _c_rest(self, code: int, flag: int, iters: int, state_lo: np.ndarray,
                state_hi: np.ndarray) -> tuple[np.ndarray, int, int]:
        """After ``rti_qp`` returned ``code`` (not 0): raise on a failed evaluation, else the
        rest of :meth:`_qp` on the C entry's QP solution (a copy, as ``DirectQp.solve``)."""
        if code < 0:
            raise RuntimeError(f"rti_qp: {'rti_lin' if code == -1 else 'rti_val'}: "
                               "evaluation failed")
        assert self._direct is not None
        return self._qp_box(self._direct.x.copy(), flag, iters, state_lo, state_hi)

    def _worst_row(self, u: np.ndarray, eta0: np.ndarray, par: np.ndarray,
                   state_lo: np.ndarray, state_hi: np.ndarray) -> str:
        """Which hard row of the plan ``u`` is exceeded most (for the rejection's status: a
        rejected step's cost, not the accepted ones')."""
        eta, path, _ = self.rows(u, eta0, par)
        states = eta[1:].ravel()
        parts = [np.sqrt(np.maximum(path, 0.0)) - self.path_root, states - state_hi,
                 state_lo - states, np.abs(u) - self.u_max]
        which = int(np.argmax([np.max(p) for p in parts]))
        i = int(np.argmax(parts[which]))
        if which == 0:
            row = self._rows[i]
            corner = f", corner {row.corner}" if row.corner >= 0 else ""
            return f"the {row.kind} row of stage {row.stage}{corner}"
        if which in (1, 2):
            side = "upper" if which == 1 else "lower"
            return f"the state box's {side} bound on eta[{i % NX}] at stage {i // NX + 1}"
        return f"the input box on u[{i % NU}] at stage {i // NU}"

    def _qp(self, u: np.ndarray, eta0: np.ndarray, par: np.ndarray, state_lo: np.ndarray,
            state_hi: np.ndarray) -> tuple[np.ndarray, int, int]:
        """One Gauss-Newton QP in the input step ``du`` at ``u``: (du, exit flag, iterations).

        First without the state box's rows (7 N, far from binding in flight); if its
        solution breaks one of them (linearised: ``lo <= c_x + J_x du <= hi``, checked
        exactly, no tolerance), again with them. Without that break the first solution is the
        whole QP's: the QP is strictly convex, and a minimiser of its cost over a larger set
        that lies in the smaller one is the smaller one's minimiser."""
        self.calls += 1
        if u is not self._u or eta0 is not self._eta0 or par is not self._par:
            self._lin(u, eta0, par)  # (copied into the function's own argument buffers)
        else:
            self._lin()  # (step() wrote them there)
        up, lo = self._up, self._lo
        np.subtract(self.u_max, u, out=self._up_u)
        np.subtract(self._u_min, u, out=self._lo_u)
        np.subtract(self.path_upper, self._c_p, out=self._up_p)
        du, flag, iters = self._daqp(self._j_path, up, lo)
        return self._qp_box(du, flag, iters, state_lo, state_hi)

    def _qp_box(self, du: np.ndarray, flag: int, iters: int, state_lo: np.ndarray,
                state_hi: np.ndarray) -> tuple[np.ndarray, int, int]:
        """The rest of :meth:`_qp` after the QP without the state box's rows (its solution
        ``du``, exit flag, iterations): that solution if it keeps the state box, else the
        whole QP's."""
        up, lo = self._up, self._lo
        if flag == DAQP_INFEASIBLE:
            return du, flag, iters  # more rows cannot make an infeasible QP feasible
        if flag in DAQP_OPTIMAL:
            # (ndarray.dot: the same BLAS gemv as np.matmul, bit for bit, ~1 us less)
            x_lin = self._j_state.dot(du, out=self._x_lin)
            x_lin += self._c_x
            # both sides in one reduction (count_nonzero: ~2 us less than two .all())
            inside = np.logical_and(np.less_equal(x_lin, state_hi, out=self._in_hi),
                                    np.greater_equal(x_lin, state_lo, out=self._in_lo),
                                    out=self._in_hi)
            if np.count_nonzero(inside) == inside.size:
                return du, flag, iters
        # a state row binds (or the smaller QP failed): the whole QP
        self.full_qps += 1
        rows = np.vstack([self._j_path, self._j_state])
        du, flag, it = self._daqp(rows, np.concatenate([up, state_hi - self._c_x]),
                                  np.concatenate([lo, state_lo - self._c_x]))
        return du, flag, iters + it

    def _daqp(self, rows: np.ndarray, up: np.ndarray,
              lo: np.ndarray) -> tuple[np.ndarray, int, int]:
        """DAQP on this step's H and g with ``rows`` (the bounds' first ``n_u``: the input
        box, DAQP's simple bounds), from a cold start. DAQP writes none of its arguments."""
        if self._direct is not None and rows is self._j_path and up is self._up \
                and lo is self._lo:
            return self._direct.solve()  # (the same arrays, refilled in place)
        sense = self._sense if up.size == self._sense.size else np.zeros(up.size, np.int32)
        du, _, flag, info = daqp.solve(self._hess, self._grad, rows, up, lo, sense,
                                       iter_limit=QP_ITER_LIMIT)
        return np.asarray(du, dtype=float), int(flag), int(info.get("iterations", 0))
