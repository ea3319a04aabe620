"""The robust MPC of spec section 6 (Yang & Li 2024, problem (2)), solved with CasADi.

Build once, then call :meth:`Rmpc.solve` every control step::

    mpc = Rmpc(cfg.rmpc, cfg.camera, design_terminal(cfg.rmpc, cfg.camera))
    res = mpc.solve(eta0, TargetMotion.constant(v_a, vdot_a, psidot_a, cfg.rmpc.horizon))
    res.u0   # (4,) [r1, r2, r3 (m/s^2, virtual frame, z down), psidot_q (rad/s)]

Each step sets the parameters, warm-starts from the previous solution shifted by one stage (the
last stage filled with the terminal law) and solves the hard problem. If that fails (infeasible
or not converged) a soft copy (L1 penalties on the tube, visibility and terminal rows) is solved
and its input is returned with ``mode='recovery'``; if that fails too, the terminal law clipped to
the input box is returned with ``mode='fallback'``. Every returned trajectory is finite and its
solver status was checked; :func:`check_solution` re-evaluates every constraint independently.

The solves run here, or on a :class:`SolveBackend` the shell provides (``rmpc.solve_isolation =
"process"``: a child process, each step's solves bounded by ``rmpc.max_solve_time_s``); a step
the backend abandons (:class:`SolveAborted`: timeout, solver restarting) is a ``'fallback'``
whose status says so (``timeout: ...``).

The parts: the problem layout in :mod:`companion.core.rmpc_problem`, one compiled NLP and its
solve in :mod:`companion.core.rmpc_nlp` (cache: :mod:`companion.core.rmpc_cache`), the soft
copy's design in :mod:`companion.core.rmpc_recovery`, the independent check in
:mod:`companion.core.rmpc_check`, the data types in :mod:`companion.core.rmpc_types`; this
module re-exports their public names.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike

from companion.core.dynamics import S_REF, euler_step, input_error
from companion.core.frozen import make
from companion.core.params import CameraParams, RmpcParams
from companion.core.rmpc_cache import CompiledNlp, RmpcBuildError
from companion.core.rmpc_check import check_solution, visibility_margin
from companion.core.rmpc_nlp import RECOVERY_SOLVER, NlpSolver
from companion.core.rmpc_problem import NP_STAGE, NU, NX, Layout, tube_bound, tube_matrix
from companion.core.rmpc_recovery import (
    recovery_design,
    slack_guess,
    velocity_box_return,
)
from companion.core.rmpc_rti import RtiSolver
from companion.core.rmpc_rti_soft import build as build_soft_rti
from companion.core.rmpc_rti_soft import recovery_step, skip_hard_nlp
from companion.core.rmpc_types import (
    ConstraintViolation,
    Evaluation,
    RmpcError,
    RmpcParameterError,
    RmpcResult,
    SolveAborted,
    SolveBackend,
    TargetMotion,
    _ro,
    planned_motion,
    state_lower,
    terminal_law,
)
from companion.core.terminal import TerminalDesign

__all__ = [
    "ConstraintViolation",
    "Evaluation",
    "Rmpc",
    "RmpcBuildError",
    "RmpcError",
    "RmpcParameterError",
    "RmpcResult",
    "SolveAborted",
    "SolveBackend",
    "TargetMotion",
    "check_solution",
    "planned_motion",
    "recovery_design",
    "state_lower",
    "terminal_law",
    "velocity_box_return",
    "visibility_margin",
]

log = logging.getLogger(__name__)


class Rmpc:
    """The RMPC of spec 6, built (and compiled, or loaded from the cache) once.

    ``rmpc.solver`` picks the full NLP (``rmpc.nlp_solver``: fatrop or ipopt) or the
    real-time iteration in front of it (:mod:`companion.core.rmpc_rti`); ``rmpc.jit``
    compiles the NLP functions (cached in ``rmpc.cache_dir``). ``solve`` is not thread-safe
    (it keeps the warm start). ``clock`` (seconds, e.g. ``time.perf_counter``, given by the
    shell: the core reads no clock) times each solve for ``RmpcResult.solve_time_s``; without
    it that is NaN. ``backend`` (built from this controller once its solvers are compiled)
    runs the NLP evaluations elsewhere (:class:`SolveBackend`); :meth:`close` stops it.
    """

    def __init__(self, rmpc: RmpcParams, camera: CameraParams, terminal: TerminalDesign,
                 clock: Callable[[], float] | None = None,
                 backend: Callable[[Rmpc], SolveBackend] | None = None) -> None:
        self.cfg = rmpc
        self.camera = camera
        self.terminal = terminal
        self.horizon = rmpc.horizon
        self.u_max = np.asarray(rmpc.u_max, dtype=float)
        self._u_max_list: list[float] = self.u_max.tolist()
        self.k = np.asarray(terminal.k, dtype=float)
        self.groups = tuple(
            name
            for name, on in (
                ("tube", rmpc.enable_tube),
                ("visibility", rmpc.enable_visibility),
                ("terminal", rmpc.enable_terminal),
            )
            if on
        )
        self._clock = clock
        self._hard = NlpSolver(rmpc, camera, terminal, soft=False, solver=rmpc.nlp_solver,
                               clock=clock)
        # rmpc.solver = "rti": the in-process real-time iteration, the full NLP behind it
        self._rti = RtiSolver(rmpc, camera, terminal) if rmpc.solver == "rti" else None
        self.rti_accepted = 0  # steps the RTI's plan flew
        self.rti_rejected = 0  # steps it handed to the full NLP (check or QP failed)
        self.rti_qps = 0  # QPs solved
        # the state box of stages 1..N (_state_box): absolute bounds minus [S_REF, v_a, 0]
        self._box_offset = np.zeros((self.horizon, NX))
        self._box_offset[:, :4] = S_REF
        self._box_lo = np.tile(state_lower(rmpc), (self.horizon, 1))
        self._box_hi = np.tile(np.asarray(rmpc.eta_max, dtype=float), (self.horizon, 1))
        # set by the shell for steps that must go to the full NLP whatever rmpc.solver says
        # (the runtime's solver-hang fault injection exercises the NLP's child process)
        self.force_nlp = False
        self._soft = (
            NlpSolver(rmpc, camera, terminal, soft=True, solver=RECOVERY_SOLVER, clock=clock)
            if self.groups
            else None
        )
        # rmpc.recovery_solver = "rti": the soft copy's RTI, the soft NLP behind it
        self.soft_rti = build_soft_rti(rmpc, camera, terminal,
                                       self._soft.layout if self._soft else None)
        self._prev: tuple[np.ndarray, np.ndarray] | None = None
        # sqrt((P^-1)_44): |eta|_P >= |se4| / this (see _infeasibility_certificate)
        self._se4_scale = float(np.sqrt(np.linalg.inv(np.asarray(terminal.p))[3, 3]))
        self._p_tube = tube_matrix(rmpc, np.asarray(terminal.p, dtype=float))
        self._tube0_sq = tube_bound(rmpc, 0) ** 2  # X(0)^2 (the certificate, every step)
        self._s4_ref = 0.0  # eta0[3] of the current step (stage_motion's reference yaw)
        # where the solves run: here (None), or a backend the shell builds for this controller
        # (a child process bounded by rmpc.max_solve_time_s, companion.control.solve_guard)
        self.backend: SolveBackend | None = backend(self) if backend is not None else None

    def solver_kinds(self) -> dict[str, tuple[bool, str]]:
        """The NLPs this controller solves: kind -> (soft, solver name)."""
        out = {self._hard.kind: (False, self._hard.solver_name)}
        if self._soft is not None:
            out[self._soft.kind] = (True, self._soft.solver_name)
        return out

    def nlps(self) -> list[NlpSolver]:
        """The NLP solvers this controller built (hard, and the soft copy when there is
        one): what a solver process loads (companion/control/solve_guard.py)."""
        return [self._hard] + ([self._soft] if self._soft is not None else [])

    def close(self) -> None:
        """Stop the solve backend (its child process), if any. Idempotent."""
        if self.backend is not None:
            self.backend.close()

    @property
    def compiled(self) -> tuple[CompiledNlp | None, CompiledNlp | None]:
        """The compiled libraries (hard, soft); ``compiled_now`` False means a cache hit."""
        return self._hard.compiled, self._soft.compiled if self._soft else None

    def reset(self) -> None:
        """Forget the warm start (e.g. after the target was lost)."""
        self._prev = None

    # ------------------------------------------------------------------------------------
    def solve(self, eta0: ArrayLike, target: TargetMotion) -> RmpcResult:
        """One RMPC step from the measured error ``eta0`` (7,) for ``target`` (N rows).

        Raises :class:`RmpcParameterError` if ``eta0`` or ``target`` is malformed or not
        finite (nothing reaches the solver). ``u0``, ``eta_pred``, ``u_pred`` and ``cost`` are
        always finite (``solve_time_s`` is NaN only if CasADi raised and gave no stats).
        """
        e0 = np.asarray(eta0, dtype=float).reshape(-1)
        if e0.shape != (NX,):
            raise RmpcParameterError(f"eta0: need 7 values, got shape {np.shape(eta0)}")
        # (one sum is finite iff every entry is, short of an overflow: the full test then)
        if not math.isfinite(float(e0.sum())) and not np.isfinite(e0).all():
            raise RmpcParameterError(f"eta0: not finite ({e0.tolist()})")
        if not isinstance(target, TargetMotion) or target.horizon != self.horizon:
            raise RmpcParameterError(f"target: need a TargetMotion with {self.horizon} rows")
        par = self._parameters(e0, target)
        self._s4_ref = float(e0[3])
        u_g, eta_g = self._guess_inputs(e0, target)
        certificate = self._infeasibility_certificate(e0, target)
        note, rti_iters, rti_time = "", 0, 0.0
        if self._rti is not None and certificate is None and not self.force_nlp:
            out = self._rti_step(e0, par, u_g, target)
            if isinstance(out, RmpcResult):
                return out
            note, rti_iters, rti_time = out
            if skip_hard_nlp(self.cfg, note):  # (rmpc.rti_infeasible_qp = "soft")
                note, certificate = f"{note}not tried (rmpc.rti_infeasible_qp = 'soft'); ", ""
        if eta_g is None:  # the RTI reads only the inputs: the states for the NLP's guess
            eta_g = self._guess_states(e0, target, u_g)
        if self.backend is not None:
            self.backend.start_step()
        lay = self._hard.layout
        if certificate is None:
            lbx, ubx = self._hard.bounds(e0, target)
            w0 = self._pack(lay, eta_g, u_g)
            try:
                ok, status, _, w, cost, iters, t_wall = self._hard.solve(w0, par, lbx, ubx,
                                                                         self.backend)
            except SolveAborted as exc:
                return self._aborted(e0, target, note + str(exc), note + str(exc), rti_iters,
                                     math.nan)
        else:  # provably infeasible (or skipped): do not spend the solver's iterations on it
            ok, status, w, cost, iters, t_wall = False, certificate, np.zeros(0), 0.0, 0, 0.0
        status, iters, t_wall = note + status, iters + rti_iters, t_wall + rti_time
        hard_status = status
        if ok:
            eta_p, u_p = self._unpack(lay, w)
            self._prev = (eta_p, u_p)
            return RmpcResult(True, "optimal", status, hard_status, cost, iters, t_wall,
                              _ro(u_p[0]), _ro(eta_p), _ro(u_p), 0.0, self.groups, target)
        return self._recover(e0, target, par, eta_g, u_g, (note, hard_status, iters, t_wall))

    def _parameters(self, e0: np.ndarray, target: TargetMotion) -> np.ndarray:
        """The NLP's parameters: ``target.packed()`` and ``eta0[3]`` (stage_motion's reference
        yaw), the same numbers copied into place (``np.column_stack`` costs ~10 us a step)."""
        par = np.empty(NP_STAGE * self.horizon + 1)
        rows = par[:-1].reshape(self.horizon, NP_STAGE)
        rows[:, 0:2] = target.v_a_m_s
        rows[:, 2:4] = target.vdot_a_m_s2
        rows[:, 4] = target.psidot_a_rad_s
        rows[:, 5:8] = target.disturbance_v_m_s2
        par[-1] = e0[3]
        return par

    def _rti_step(self, e0: np.ndarray, par: np.ndarray, u_g: np.ndarray,
                  target: TargetMotion) -> RmpcResult | tuple[str, int, float]:
        """The RTI of the hard problem (``rmpc.solver = "rti"``): its result if the nonlinear
        check passed, else what the full NLP's status is prefixed with, the QP iterations and
        the time spent (the step then solves the full NLP)."""
        assert self._rti is not None
        lo, hi = self._state_box(target)
        t0 = self._clock() if self._clock is not None else math.nan
        out = self._rti.step(e0, par, u_g, lo, hi)
        t_wall = self._clock() - t0 if self._clock is not None else math.nan
        self.rti_qps += out.qps
        if out.ok:
            self.rti_accepted += 1
            # the outcome's arrays are its own (fresh each step) and only read from here
            # on: made read-only and shared with the warm start, not copied
            eta, u = out.eta, out.u
            eta.setflags(write=False)
            u.setflags(write=False)
            u0 = u[0].copy()
            u0.setflags(write=False)
            self._prev = (eta, u)
            return make(RmpcResult, success=True, mode="optimal", status=out.status,
                        hard_status=out.status, cost=out.cost,
                        iterations=out.qp_iterations, solve_time_s=t_wall, u0=u0,
                        eta_pred=eta, u_pred=u, max_soft_violation=0.0,
                        active_groups=self.groups, target=target)
        self.rti_rejected += 1
        log.info("RMPC %s: solving the full NLP", out.status)
        return f"{out.status}; nlp: ", out.qp_iterations, t_wall

    def _state_box(self, target: TargetMotion) -> tuple[np.ndarray, np.ndarray]:
        """The hard NLP's bounds on the states of stages 1..N (N*7 each, error coordinates):
        ``NlpSolver.bounds``' numbers (the same subtractions), without building the whole
        bound vectors (~30 us of CPU a step)."""
        off = self._box_offset
        off[:-1, 4:6] = target.v_a_m_s[1:]
        off[-1, 4:6] = target.v_a_m_s[-1]  # stage N holds N-1's motion
        return (self._box_lo - off).ravel(), (self._box_hi - off).ravel()

    def _recover(self, e0: np.ndarray, target: TargetMotion, par: np.ndarray,
                 eta_g: np.ndarray, u_g: np.ndarray,
                 hard: tuple[str, str, int, float]) -> RmpcResult:
        """The hard problem failed: the soft copy, else the terminal-law fallback. ``hard``:
        (the RTI's note, the hard attempt's status, iterations and time so far)."""
        note, hard_status, iters, t_wall = hard
        status = hard_status
        log.info("RMPC hard problem failed (%s): trying the soft copy", status)
        if self._soft is not None:
            slay = self._soft.layout
            slbx, subx = self._soft.bounds(e0, target)
            # the soft copy's input-rate term: against the input the previous step applied (its
            # plan's first input; a failed hard solve leaves _prev alone); off at the start and
            # after a fallback or a reset (no previous input)
            if self._prev is None:
                spar = np.concatenate([par, np.zeros(NU), [0.0]])
            else:
                spar = np.concatenate([par, self._prev[1][0],
                                       [self.cfg.recovery_input_rate_weight]])
            if self.soft_rti is not None and self._prev is not None:  # (a warm start only)
                srti = recovery_step(self.soft_rti, e0, spar, u_g, (slbx, subx), slay,
                                     self._clock)
                iters, t_wall = iters + srti.qp_iterations, t_wall + self.soft_rti.last_time_s
                if srti.ok:
                    self._prev = (srti.eta, srti.u)
                    return RmpcResult(True, "recovery", note + srti.status, hard_status,
                                      srti.cost, iters, t_wall, _ro(srti.u[0]), _ro(srti.eta),
                                      _ro(srti.u), float(np.max(srti.slack, initial=0.0)),
                                      self.groups, target)
                note += f"{srti.status}; nlp: "
            sw0 = self._pack(slay, eta_g, u_g)
            sw0[slay.slack_index] = slack_guess(slay, eta_g, u_g, target, self._p_tube, self.cfg,
                                                 self.camera)
            try:
                sok, sstatus, _, sw, scost, sit, st_wall = self._soft.solve(
                    sw0, spar, slbx, subx, self.backend)
            except SolveAborted as exc:
                return self._aborted(e0, target, note + str(exc), hard_status, iters, math.nan)
            iters += sit
            t_wall += st_wall
            if sok:
                eta_p, u_p = self._unpack(slay, sw)
                self._prev = (eta_p, u_p)
                slack = float(np.max(sw[slay.slack_index], initial=0.0))
                return RmpcResult(True, "recovery", note + sstatus, hard_status, scost, iters,
                                  t_wall,
                                  _ro(u_p[0]), _ro(eta_p), _ro(u_p), max(slack, 0.0),
                                  self.groups, target)
            status = note + sstatus
            log.warning("RMPC soft copy failed too (%s): terminal-law fallback", sstatus)
        eta_f, u_f = self._rollout(e0, target)
        self._prev = None
        return RmpcResult(False, "fallback", status, hard_status,
                          self._objective(eta_f, u_f, target), iters, t_wall,
                          _ro(u_f[0]), _ro(eta_f), _ro(u_f), 0.0, self.groups, target)

    def _aborted(self, e0: np.ndarray, target: TargetMotion, status: str, hard_status: str,
                 iters: int, t_wall: float) -> RmpcResult:
        """The terminal-law fallback of a step whose solve the backend abandoned."""
        log.warning("RMPC step abandoned (%s): terminal-law fallback", status)
        eta_f, u_f = self._rollout(e0, target)
        self._prev = None
        return RmpcResult(False, "fallback", status, hard_status,
                          self._objective(eta_f, u_f, target), iters, t_wall,
                          _ro(u_f[0]), _ro(eta_f), _ro(u_f), 0.0, self.groups, target)

    def _objective(self, eta: np.ndarray, u: np.ndarray, target: TargetMotion) -> float:
        """The hard problem's cost of a trajectory (numpy)."""
        q, r = np.asarray(self.cfg.q_diag), np.asarray(self.cfg.r_diag)
        total = 0.0
        for n in range(self.horizon):
            motion = planned_motion(self.cfg, eta[n], u[n], target, n, float(eta[0][3]))
            ue = np.asarray(input_error(u[n], *motion))
            total += float(eta[n] @ (q * eta[n]) + ue @ (r * ue))
        return total + float(eta[-1] @ self.terminal.p @ eta[-1])

    def _infeasibility_certificate(self, eta0: np.ndarray, target: TargetMotion) -> str | None:
        """A proof that the hard problem is infeasible, or None (no proof: try the solver).

        Two exact arguments: (1) ``eta(0)`` is fixed, so ``|eta0|_P > X(0)`` violates the
        tube at n = 0. (2) The yaw error is decoupled and linear, ``se4(n+1) = se4(n) +
        (psidot_a(n) - psidot_q(n)) delta`` with ``|psidot_q| <= u_max[3]``, so ``se4(n)`` lies
        in a known interval; and ``min {eta' P eta : eta_4 = c} = c^2 / (P^-1)_44``, so the
        tube (n <= N-1) or terminal set (n = N) is out of reach once that interval stays
        farther than ``X(n) sqrt((P^-1)_44)`` from 0.
        """
        tube, term = "tube" in self.groups, "terminal" in self.groups
        if not (tube or term):
            return None
        if tube and float(eta0 @ self._p_tube @ eta0) > self._tube0_sq:
            return "infeasible: |eta0|_P > X(0)"
        if self.cfg.heading == "cost":  # s4 is in no hard row: no yaw argument
            return None
        dt = self.cfg.dt_s
        drift = eta0[3] + np.concatenate([[0.0], np.cumsum(target.psidot_a_rad_s) * dt])
        reach = np.arange(self.horizon + 1) * dt * self.u_max[3]
        gap = np.maximum(np.abs(drift) - reach, 0.0)  # smallest |se4(n)| reachable
        for n in range(1, self.horizon + 1):
            if n < self.horizon and not tube:
                continue
            if gap[n] > tube_bound(self.cfg, n) * self._se4_scale * (1.0 + 1e-9):
                return f"infeasible: yaw error cannot reach the tube at n = {n}"
        return None

    def check(self, result: RmpcResult, tol: float = 1e-6) -> list[ConstraintViolation]:
        """:func:`check_solution` with this controller's configuration."""
        return check_solution(result, self.cfg, self.camera, self.terminal, tol=tol)

    # ------------------------------------------------------------------------------------
    def _law(self, eta: np.ndarray, target: TargetMotion, n: int) -> np.ndarray:
        # the law's own yaw rate is not known before it is computed: the nominal one
        v_a, vdot_a, psidot_a = target.stage(n)
        u_nom = np.array([0.0, 0.0, 0.0, psidot_a])
        v_a, vdot_a, psidot_a = planned_motion(self.cfg, eta, u_nom, target, n, self._s4_ref)
        return terminal_law(eta, v_a, vdot_a, psidot_a, self.k, self.u_max)

    def _law_numbers(self, eta: np.ndarray, target: TargetMotion, n: int) -> np.ndarray:
        """:meth:`_law` bit for bit (the same operations in the same order, a test holds them
        to each other), without the two-backend functions' dispatch: the warm start's last
        input every RTI step, ~40 us of CPU less in flight."""
        # plain floats but for K eta (numpy's product: BLAS's order of the sums); math's
        # cos and sin are numpy's, the clipping np.maximum/np.minimum's (NaN kept)
        va0, va1 = target.v_a_m_s[n].tolist()
        vd0, vd1 = target.vdot_a_m_s2[n].tolist()
        psidot_a = float(target.psidot_a_rad_s[n])
        if self.cfg.target_motion != "nominal":  # stage_motion's "planned_yaw", u[3] = psidot_a
            th = self._s4_ref - float(eta[3])
            c, s = math.cos(th), math.sin(th)
            an0 = vd0 - psidot_a * va1
            an1 = vd1 + psidot_a * va0
            va0, va1 = c * va0 + s * va1, -s * va0 + c * va1
            vd0, vd1 = c * an0 + s * an1 + psidot_a * va1, -s * an0 + c * an1 - psidot_a * va0
        k0, k1, k2, k3 = (self.k @ eta).tolist()
        psidot_q = k3 + psidot_a
        out = []
        for v, hi in zip((k0 + (vd0 - psidot_q * va1), k1 + (psidot_q * va0 + vd1),
                          k2 + 0.0, k3 + psidot_a), self._u_max_list, strict=True):
            lo = -hi
            v = lo if v < lo else v  # (np.maximum then np.minimum: a NaN stays)
            out.append(hi if v > hi else v)
        return np.array(out)

    def _step(self, eta: np.ndarray, u: np.ndarray, target: TargetMotion, n: int) -> np.ndarray:
        v_a, vdot_a, psidot_a = planned_motion(self.cfg, eta, u, target, n, self._s4_ref)
        return np.asarray(
            euler_step(eta, u, v_a, vdot_a, psidot_a, self.cfg.desired_depth_m, self.cfg.dt_s)
        )

    def _rollout(self, eta0: np.ndarray, target: TargetMotion) -> tuple[np.ndarray, np.ndarray]:
        """The clipped terminal law rolled out on the nominal model (finite by construction
        for finite inputs; clipped to the state box's scale so it can never overflow)."""
        big_n = self.horizon
        eta = np.zeros((big_n + 1, NX))
        u = np.zeros((big_n, NU))
        eta[0] = eta0
        for n in range(big_n):
            u[n] = self._law(eta[n], target, n)
            eta[n + 1] = self._step(eta[n], u[n], target, n)
        if not (np.all(np.isfinite(eta)) and np.all(np.isfinite(u))):  # pragma: no cover
            eta = np.tile(eta0, (big_n + 1, 1))
            u = np.zeros((big_n, NU))
        return eta, u

    def _guess_inputs(self, eta0: np.ndarray, target: TargetMotion
                      ) -> tuple[np.ndarray, np.ndarray | None]:
        """The warm start's inputs: the previous plan's shifted by one stage (the last stage: the
        terminal law), else the terminal law's rollout's; and its states when they came with
        them (the rollout; None: :meth:`_guess_states` gives them, only a step that solves
        the NLP needs them)."""
        if self._prev is None:
            eta, u = self._rollout(eta0, target)
            return u, eta
        u_p = self._prev[1]
        big_n = self.horizon
        u = np.empty_like(u_p)
        u[: big_n - 1] = u_p[1:]
        u[big_n - 1] = self._law_numbers(self._prev[0][big_n], target, big_n - 1)
        return u, None

    def _guess_states(self, eta0: np.ndarray, target: TargetMotion,
                      u: np.ndarray) -> np.ndarray:
        """The warm start's states (the previous plan's, shifted; the last stage stepped
        with the terminal law's input ``u[N-1]``)."""
        assert self._prev is not None
        eta_p = self._prev[0]
        big_n = self.horizon
        eta = np.empty_like(eta_p)
        eta[0] = eta0
        eta[1:big_n] = eta_p[2:]
        eta[big_n] = self._step(eta_p[big_n], u[big_n - 1], target, big_n - 1)
        return eta

    @staticmethod
    def _pack(lay: Layout, eta: np.ndarray, u: np.ndarray) -> np.ndarray:
        w = np.zeros(lay.n_w)
        w[lay.x_index] = eta
        w[lay.u_index] = u
        return w

    @staticmethod
    def _unpack(lay: Layout, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return w[lay.x_index].copy(), w[lay.u_index].copy()
